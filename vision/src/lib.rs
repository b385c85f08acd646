//! markhold-vision: frames in, marker poses the controller can trust out.
//!
//! - [`MarkerTracker`]: detection of the configured marker (OpenCV 4.6 aruco, SUBPIX
//!   corners), RoI tracking, IPPE_SQUARE pose with both solutions considered, LM
//!   refinement and a covariance from the reprojection Jacobian.
//! - [`apriltag3`] (cargo feature `apriltag3`): AprilTag 3's own detector, chosen per
//!   site (`[marker] detector`) in place of OpenCV's quad detection and decoding.
//! - [`CameraCalibration`]: intrinsics, read from OpenCV or ROS YAML files.
//! - [`marker_bitmap`]: the printed marker, module by module (the HIL camera renders it).
//! - [`mapping`]: a marker map (each marker's pose in the site frame) from frames that
//!   show several markers together, by bundle adjustment.
//! - [`synth`]: a reference renderer for tests and benchmarks.
//!
//! Conventions: `docs/frames.md` (aruco corner order, OpenCV camera frame, covariance
//! order (tx, ty, tz, rx, ry, rz)).

#[cfg(feature = "apriltag3")]
pub mod apriltag3;
#[cfg(not(feature = "apriltag3"))]
mod apriltag3 {
    //! Built without AprilTag 3: no detector can be made (the site check refuses
    //! `detector = "apriltag3"` first, naming the feature).
    use crate::{MarkerDetector, MarkerFamily, VisionError};

    /// Uninhabited: this build has no AprilTag 3 detector.
    pub enum AprilTag3 {}

    impl AprilTag3 {
        pub fn new(family: MarkerFamily) -> Result<Self, VisionError> {
            Err(MarkerDetector::AprilTag3.unavailable_for(family).into())
        }

        pub fn detect(
            &mut self,
            _: &impl opencv::core::MatTraitConst,
            _: impl FnMut(u32, markhold_camera::Corners),
        ) -> Result<(), VisionError> {
            match *self {}
        }

        pub(crate) fn detect_into(
            &mut self,
            _: &impl opencv::core::MatTraitConst,
            _: (f64, f64),
            _: (f64, f64),
            _: &[i16],
            _: &mut [Option<(f64, markhold_camera::Corners)>],
        ) -> Result<usize, VisionError> {
            match *self {}
        }
    }
}
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
    DetectorConfig, MapMarker, MarkerConfig, MarkerDetector, MarkerFamily, PlacedMarker,
    MAX_MAP_MARKERS,
};
pub use corners::CornerCov;
pub use dict::{marker_bitmap, MarkerBitmap};
pub use distortion::DistortionModel;
pub use error::VisionError;
pub use markhold_config::ConfigError;
pub use tracker::{MarkerObservation, MarkerTracker, Tracked, TrackerStats};
