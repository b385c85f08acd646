//! markhold's real-vehicle edge: the `run` runner ([`run`]), where its frames come from
//! ([`camera`]: the `--camera` URL, stream cameras over GStreamer with their control
//! channel, V4L2, GenICam and recorded frames) and the vehicle checklist ([`preflight`]).
//! It builds on `markhold-core` and imports no simulation code.

pub mod camera;
pub mod error;
pub mod preflight;
pub mod run;

pub use error::FieldError;
