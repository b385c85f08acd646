//! Per-frame observers a runner attaches to the loop: a CSV trace, PNG snapshots and a
//! progress bar. (The MCAP recorder and the Foxglove live view are `crate::record`.)

mod progress;
mod snapshot;
mod trace;

pub use progress::{bar_span, Progress};
pub use snapshot::Snapshots;
pub use trace::TraceWriter;
