//! markhold-vision (being built).
