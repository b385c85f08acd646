//! markhold: keeps an ArduSub vehicle on station in front of a fiducial marker.
//!
//! The binary's own modules are the commands that stand beside the loop (`calibrate`,
//! `map`, `tag`, `response`, the generated docs). The loop and what every runner shares
//! are `markhold-core`, the real-vehicle edge `markhold-field`, the simulation commands
//! `markhold-sim` (feature `sim`, on by default); they are re-exported here under the
//! paths the commands and the tests use.

pub use markhold_core::{
    error, feasibility, observe, outln, params, pipeline, print_report, record, web, write_summary,
};

/// The real-vehicle edge (`markhold-field`), with the engagement and signal handling it
/// shares with the simulator (`markhold-core`).
pub mod field {
    pub use markhold_core::{engage, signal};
    pub use markhold_field::{camera, preflight, run, FieldError};
}

#[cfg(feature = "sim")]
pub use markhold_sim as sim;

pub mod calibrate;
pub mod cli_docs;
pub mod map;
pub mod response_fit;
pub mod tag;
