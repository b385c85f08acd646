//! The one error enum of markhold-field: a start-up check that failed, an error of the
//! loop (markhold-core's, passed through unchanged), and the frame it happened on.

use markhold_core::params::ParamsError;
use markhold_core::CoreError;

pub use crate::run::StartupError;

/// Everything that can go wrong in markhold-field.
#[derive(Debug, thiserror::Error)]
pub enum FieldError {
    /// A start-up check that failed: the run did not start.
    #[error(transparent)]
    Startup(#[from] StartupError),
    #[error(transparent)]
    Core(#[from] CoreError),
    /// The vehicle link.
    #[error(transparent)]
    Autopilot(#[from] markhold_autopilot::AutopilotError),
    /// An environment variable with a value that cannot be used.
    #[error("{name}={value}: expected {expected}")]
    Env {
        name: &'static str,
        value: String,
        expected: &'static str,
    },
    /// The loop failed on frame `frame` (frames stepped before it).
    #[error("frame {frame}")]
    Frame {
        frame: u64,
        #[source]
        source: Box<CoreError>,
    },
}

impl FieldError {
    /// The site-file error inside, if this is one.
    pub fn params(&self) -> Option<&ParamsError> {
        match self {
            Self::Core(e) => e.params(),
            _ => None,
        }
    }
}
