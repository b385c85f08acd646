//! Vision: marker corners on real photographs, `markhold calibrate` and `markhold map`,
//! clipped edges, the pose covariance graded in HIL (NEES), and maps of markers.
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod apriltag3;
mod calibrate;
mod clipped_edges;
mod dock_map;
mod map;
mod real_images;
mod vision_nees;
