//! The real-vehicle edge: the `run` runner, its cameras, and signals. Nothing here
//! imports simulation code.

pub mod camera;
pub mod engage;
pub mod preflight;
pub mod run;
pub mod signal;
