//! The underwater camera (being built by the camera engineer).
