//! Exposure in HIL: AAEC against an independent optimum, the paper's methods at its
//! camera's size, a lamp on one marker of a map, and `markhold response fit`.
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod exposure_optimum;
mod lamp_map;
mod paper_camera;
mod response_fit;
