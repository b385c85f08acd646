//! The scene: marker plate, background, water and light (being built by the camera engineer).
