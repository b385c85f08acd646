//! The one error type of this crate.

use std::path::PathBuf;

/// Errors of markhold-vision. Config errors name the site-file key and the value,
/// file errors name the file and the field.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    #[error(transparent)]
    Config(#[from] markhold_config::ConfigError),
    #[error("unknown marker family '{name}': expected one of {expected}")]
    UnknownFamily { name: String, expected: String },
    #[error("{path}: field '{field}': {reason}")]
    Calibration {
        path: PathBuf,
        field: String,
        reason: String,
    },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("frame is {width}x{height} but {what} expects {expected_width}x{expected_height}")]
    FrameSize {
        what: &'static str,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("OpenCV {op}: {source}")]
    OpenCv {
        op: &'static str,
        #[source]
        source: opencv::Error,
    },
    #[error("marker map: no frame shows two or more of the map's markers together ({frames} frames read)")]
    MapNoFrames { frames: usize },
    #[error("marker map: origin marker {origin} is not one of the site's markers ({ids})")]
    MapOrigin { origin: u32, ids: String },
    #[error("marker map: markers {ids} are not linked to origin marker {origin} through frames that show markers together: {detail}")]
    MapDisconnected {
        origin: u32,
        ids: String,
        detail: String,
    },
    #[error("AprilTag 3: {reason}")]
    AprilTag { reason: String },
    #[error("calibration refused: {reason}")]
    CalibrationRefused { reason: String },
    #[error(transparent)]
    Camera(#[from] markhold_camera::CameraError),
}

/// Attach the name of the OpenCV operation to its error.
pub(crate) trait CvContext<T> {
    fn cv(self, op: &'static str) -> Result<T, VisionError>;
}

impl<T> CvContext<T> for Result<T, opencv::Error> {
    fn cv(self, op: &'static str) -> Result<T, VisionError> {
        self.map_err(|source| VisionError::OpenCv { op, source })
    }
}
