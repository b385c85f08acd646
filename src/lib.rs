//! markhold: keeps an ArduSub vehicle on station in front of a fiducial marker.
//!
//! This crate wires the member crates into one loop ([`pipeline`]) and runs it against
//! the simulated world ([`hil_run`]); `params` reads dive-site files.

pub mod compare;
pub mod external;
pub mod faults;
pub mod hil_run;
pub mod live;
pub mod params;
pub mod pipeline;
pub mod plots;
pub mod record;
pub mod replay;
pub mod signal;
pub mod snapshot;
pub mod summary;
pub mod trace;
