//! markhold-vision: frames in, marker poses the controller can trust out.
//!
//! - [`MarkerTracker`]: detection of the configured marker (OpenCV 4.6 aruco, SUBPIX
//!   corners), RoI tracking, IPPE_SQUARE pose with both solutions considered, LM
//!   refinement and a covariance from the reprojection Jacobian.
//! - [`CameraCalibration`]: intrinsics, read from OpenCV or ROS YAML files.
//! - [`marker_bitmap`]: the printed marker, module by module (the HIL camera renders it).
//! - [`mapping`]: a marker map (each marker's pose in the site frame) from frames that
//!   show several markers together, by bundle adjustment.
//! - [`synth`]: a reference renderer for tests and benchmarks.
//!
//! Conventions: `docs/frames.md` (aruco corner order, OpenCV camera frame, covariance
//! order (tx, ty, tz, rx, ry, rz)).

mod calib;
pub mod calibration;
mod config;
mod corners;
mod dict;
pub mod distortion;
mod error;
pub mod mapping;
pub mod pose;
pub mod synth;
mod tracker;
mod yaml;

pub use calib::{CalibrationNotes, CalibrationSource, CameraCalibration};
pub use config::{
    DetectorConfig, MapMarker, MarkerConfig, MarkerFamily, PlacedMarker, MAX_MAP_MARKERS,
};
pub use corners::CornerCov;
pub use dict::{marker_bitmap, MarkerBitmap};
pub use distortion::DistortionModel;
pub use error::VisionError;
pub use markhold_config::ConfigError;
pub use tracker::{MarkerObservation, MarkerTracker, Tracked, TrackerStats};
