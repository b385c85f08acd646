//! markhold-camera: frames and the cameras that fill them.
//!
//! - [`Frame`], [`ImageView`], [`Roi`], [`Corners`]: 8-bit grey images with what they were
//!   taken with, borrowed windows into them, pixel rectangles and marker corners.
//! - [`Camera`]: the seam every frame source implements (grab into a caller-owned frame,
//!   command the exposure within [`ExposureLimits`]); [`CameraError`] the errors.
//! - Backends, one module each, behind the feature that brings their system library:
//!   `frames` (recorded folders) and `v4l2` through OpenCV (feature `opencv`), `genicam`
//!   through Aravis (feature `genicam`).

mod frame;

#[cfg(feature = "opencv")]
mod cv;
#[cfg(feature = "opencv")]
pub mod frames;
#[cfg(feature = "genicam")]
pub mod genicam;
#[cfg(feature = "opencv")]
pub mod v4l2;

pub use frame::{Camera, CameraError, Corners, ExposureLimits, Frame, FrameMeta, ImageView, Roi};
#[cfg(feature = "opencv")]
pub use frames::{
    check_encoded_size, encoded_image_size, FrameRecorder, RecordedCamera, MAX_IMAGE_SIDE, SIDECAR,
};
#[cfg(feature = "opencv")]
pub use v4l2::V4l2Camera;
