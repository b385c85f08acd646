//! The one error enum of markhold-sim. The errors of the crates it builds on pass
//! through unchanged; its own variants name the file, the flag or the step that failed.

use std::path::PathBuf;

use markhold_core::params::ParamsError;
use markhold_core::CoreError;

/// Everything that can go wrong in markhold-sim.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A site file that cannot be read or used.
    #[error(transparent)]
    Params(#[from] ParamsError),
    #[error(transparent)]
    Config(#[from] markhold_config::ConfigError),
    /// The loop, its observers, recording and replay.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// The stream camera (`--camera-transport h264-rtp`).
    #[error(transparent)]
    Field(#[from] markhold_field::FieldError),
    /// The simulated world, its vehicle endpoint and SITL server.
    #[error(transparent)]
    Hil(#[from] markhold_hil::HilError),
    /// The vehicle link.
    #[error(transparent)]
    Autopilot(#[from] markhold_autopilot::AutopilotError),
    #[error(transparent)]
    Camera(#[from] markhold_exposure::CameraError),
    #[error(transparent)]
    Exposure(#[from] markhold_exposure::ExposureError),
    #[error(transparent)]
    Vision(#[from] markhold_vision::VisionError),
    #[error(transparent)]
    Record(#[from] markhold_core::record::RecordError),
    #[error(transparent)]
    Signal(#[from] markhold_core::signal::SignalError),
    #[error(transparent)]
    Fault(#[from] crate::faults::FaultError),
    #[error(transparent)]
    OpenCv(#[from] opencv::Error),
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The web page (`--web`).
    #[error(transparent)]
    Web(#[from] markhold_core::web::WebError),
    /// The simulated camera manager's exposure control.
    #[error(transparent)]
    Control(#[from] markhold_core::control::ControlError),
    /// The stream camera receiving the simulated H.264.
    #[error(transparent)]
    Stream(#[from] markhold_field::camera::stream::StreamError),
    /// A file or folder that could not be created, read or written: what was being
    /// done (naming the flag when one gave the path) and the path.
    #[error("{action} {path}")]
    File {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Command-line options that do not fit together or hold a value the command cannot
    /// use: the option, its value and what is expected.
    #[error("{reason}")]
    Usage { reason: String },
    /// A simulated or external vehicle, SITL or a run that did not do what the command
    /// needs: what happened.
    #[error("{reason}")]
    Run { reason: String },
    /// A step (named in `step`: the run, the case, the part being built) failed for
    /// the error beneath.
    #[error("{step}")]
    Step {
        step: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
}

impl SimError {
    /// The site-file error inside, if this is one (the binary exits with its own code
    /// for a bad site file).
    pub fn params(&self) -> Option<&ParamsError> {
        match self {
            Self::Params(e) => Some(e),
            Self::Core(e) => e.params(),
            Self::Field(e) => e.params(),
            _ => None,
        }
    }
}

/// `Err(err())` unless `ok`.
pub(crate) fn ensure(ok: bool, err: impl FnOnce() -> SimError) -> Result<(), SimError> {
    if ok {
        Ok(())
    } else {
        Err(err())
    }
}

/// Attach what was being done (`step`) to an error, keeping it as the source.
pub(crate) trait StepContext<T> {
    fn step(self, step: impl FnOnce() -> String) -> Result<T, SimError>;
}

impl<T, E: std::error::Error + Send + Sync + 'static> StepContext<T> for Result<T, E> {
    fn step(self, step: impl FnOnce() -> String) -> Result<T, SimError> {
        self.map_err(|e| SimError::Step {
            step: step(),
            source: Box::new(e),
        })
    }
}

/// Attach the file and what was being done with it to an I/O error.
pub(crate) trait FileContext<T> {
    fn file(self, action: &'static str, path: impl Into<PathBuf>) -> Result<T, SimError>;
}

impl<T> FileContext<T> for std::io::Result<T> {
    fn file(self, action: &'static str, path: impl Into<PathBuf>) -> Result<T, SimError> {
        self.map_err(|source| SimError::File {
            action,
            path: path.into(),
            source,
        })
    }
}

/// A value that must be there, or `SimError::Run` saying what is missing.
pub(crate) trait Required<T> {
    fn required(self, what: impl FnOnce() -> String) -> Result<T, SimError>;
}

impl<T> Required<T> for Option<T> {
    fn required(self, what: impl FnOnce() -> String) -> Result<T, SimError> {
        self.ok_or_else(|| SimError::Run { reason: what() })
    }
}
