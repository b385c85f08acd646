//! Per-frame observers a runner attaches to the loop: a CSV trace, PNG snapshots, a
//! progress bar, and the status the web page shows. (The MCAP recorder and the Foxglove
//! live view are `crate::record`; the web page is `crate::web`.)

mod progress;
mod snapshot;
pub mod status;
mod trace;

pub use progress::{bar_span, Progress};
pub use snapshot::Snapshots;
pub use status::{Engagement, StatusBoard, StatusObserver};
pub use trace::TraceWriter;
