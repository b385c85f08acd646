//! markhold-geometry: frames and poses (pure nalgebra).
//!
//! - [`frames`]: `skew`, the pose-error convention, pose inversion and covariance
//!   transport between frames.
//! - [`stats`]: normal, chi-square and Student-t quantiles.
//!
//! Frames and units: `docs/frames.md` of the workspace.

pub mod frames;
pub mod stats;

pub use frames::{cov_in_frame, cov_of_inverse, cov_through, inverse_with_cov, perturb, skew};
