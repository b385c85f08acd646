//! The one error enum of markhold-core. The errors of its parts (site files, the
//! recorder, the web page, the link, the camera, vision, exposure) pass through unchanged;
//! the variants of its own name the file and what was being done with it.

use std::path::PathBuf;

use crate::params::ParamsError;

/// Everything that can go wrong in markhold-core.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// A site file that cannot be read or used.
    #[error(transparent)]
    Params(#[from] ParamsError),
    /// A recorded site or calibration value out of range.
    #[error(transparent)]
    Config(#[from] markhold_config::ConfigError),
    /// The vehicle link (or the station keeper's configuration).
    #[error(transparent)]
    Autopilot(#[from] markhold_autopilot::AutopilotError),
    #[error(transparent)]
    Camera(#[from] markhold_exposure::CameraError),
    #[error(transparent)]
    Vision(#[from] markhold_vision::VisionError),
    #[error(transparent)]
    Exposure(#[from] markhold_exposure::ExposureError),
    #[error(transparent)]
    Record(#[from] crate::record::RecordError),
    #[error(transparent)]
    OpenCv(#[from] opencv::Error),
    /// A value that could not be written as JSON.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// A file or folder of a command (`--trace`, `--summary`, a recording) that could
    /// not be created, read or written; `action` says which and names the flag.
    #[error("{action} {path}")]
    File {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// `--snapshot DIR` could not be created.
    #[error("creating --snapshot {dir}")]
    SnapshotCreate {
        dir: PathBuf,
        #[source]
        source: markhold_exposure::CameraError,
    },
    /// A frame could not be saved into `--snapshot DIR` (`source` names the folder).
    #[error("saving snapshots")]
    SnapshotSave {
        #[source]
        source: SnapshotWrite,
    },
    /// A recording that is not a markhold recording or cannot be read as one: the file
    /// and why.
    #[error("{path}: {reason}")]
    Recording { path: PathBuf, reason: String },
    /// A recording that is not MCAP, or is damaged beyond its first chunk.
    #[error("{path}: not a readable MCAP file: {reason}")]
    NotMcap { path: PathBuf, reason: String },
    /// A part of a recording (its site, calibration, a frame or command message, an
    /// image) that could not be read: the file, the part and the error beneath.
    #[error("{path}: {part}")]
    RecordingPart {
        path: PathBuf,
        part: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    /// A key of a recording's run metadata with a value replay cannot use.
    #[error("{path}: {key} {value}: {reason}")]
    RecordedValue {
        path: PathBuf,
        key: &'static str,
        value: String,
        reason: String,
    },
    /// The recorded initial exposure lies outside the recorded site's camera limits.
    #[error("{path}: the recorded initial exposure {exposure_us} us is outside the recorded site's limits")]
    RecordedExposure { path: PathBuf, exposure_us: f64 },
    /// The recorded loop could not be built again.
    #[error("rebuilding the recorded loop")]
    Rebuild {
        #[source]
        source: Box<CoreError>,
    },
    /// A recorded image that is not what the recorded camera gives.
    #[error("{reason}")]
    Image { reason: String },
}

/// The folder a snapshot could not be written into, and why.
#[derive(Debug, thiserror::Error)]
#[error("in {dir}")]
pub struct SnapshotWrite {
    pub dir: PathBuf,
    #[source]
    pub source: markhold_exposure::CameraError,
}

impl CoreError {
    /// The site-file error inside, if this is one (the binary exits with its own code
    /// for a bad site file).
    pub fn params(&self) -> Option<&ParamsError> {
        match self {
            Self::Params(e) => Some(e),
            _ => None,
        }
    }

    /// The camera error inside, if this is one (the end of a recorded stream ends a run).
    pub fn camera(&self) -> Option<&markhold_exposure::CameraError> {
        match self {
            Self::Camera(e) => Some(e),
            _ => None,
        }
    }
}

/// An error and its sources on one line, `error: source: source`, as the binary prints
/// errors.
pub struct Chain<'a>(pub &'a (dyn std::error::Error + 'static));

impl std::fmt::Display for Chain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut next = self.0.source();
        while let Some(e) = next {
            write!(f, ": {e}")?;
            next = e.source();
        }
        Ok(())
    }
}
