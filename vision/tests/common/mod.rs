//! Shared helpers of the integration tests: the test camera, marker poses and noisy
//! renders through the crate's reference renderer.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
#![allow(dead_code)]

use markhold_camera::Frame;
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{marker_bitmap, CameraCalibration, MarkerBitmap, MarkerConfig, MarkerFamily};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;

pub const W: u32 = 1440;
pub const H: u32 = 1080;

/// A 1440x1080 camera with about 71 degrees horizontal field of view.
pub fn calib() -> CameraCalibration {
    CameraCalibration::pinhole(W, H, 1000.0, 1000.0, 719.5, 539.5)
}

pub fn calib_distorted() -> CameraCalibration {
    CameraCalibration {
        dist: vec![-0.12, 0.03, 0.0005, -0.0003, 0.0],
        model: markhold_vision::DistortionModel::PlumbBob,
        ..calib()
    }
}

pub fn marker() -> MarkerConfig {
    MarkerConfig::single(MarkerFamily::AprilTag36h11, 7, 0.2)
}

pub fn bitmap(m: &MarkerConfig) -> MarkerBitmap {
    marker_bitmap(m.family, m.id).unwrap()
}

/// The marker at `pos` in the camera frame, facing the camera, then turned by
/// `yaw_deg` about its own y axis and `pitch_deg` about its own x axis (obliquity).
pub fn pose(pos: [f64; 3], yaw_deg: f64, pitch_deg: f64) -> Isometry3<f64> {
    let facing = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians())
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pitch_deg.to_radians());
    Isometry3::from_parts(Translation3::new(pos[0], pos[1], pos[2]), facing * turn)
}

/// Standard normal sample (Box-Muller).
pub fn gauss(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Render the marker at `t_cam_marker` with additive Gaussian pixel noise of
/// `noise_grey` grey levels; returns the exact corners.
pub fn render_noisy(
    frame: &mut Frame,
    calib: &CameraCalibration,
    m: &MarkerConfig,
    bm: &MarkerBitmap,
    t_cam_marker: &Isometry3<f64>,
    noise_grey: f64,
    rng: &mut impl Rng,
) -> [[f64; 2]; 4] {
    let c = render_marker(
        frame,
        calib,
        bm,
        m.size_m,
        t_cam_marker,
        &SceneParams::default(),
    );
    if noise_grey > 0.0 {
        for p in frame.data.iter_mut() {
            *p = (*p as f64 + noise_grey * gauss(rng))
                .round()
                .clamp(0.0, 255.0) as u8;
        }
    }
    c.map(|p| p.expect("corner in front of the camera"))
}

pub fn position_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

pub fn rotation_error_deg(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    a.rotation.angle_to(&b.rotation).to_degrees()
}

/// Additive Gaussian noise of `sigma` grey levels. Box-Muller per pixel costs more
/// than the render: draw from a fresh table of 4096 samples with random indices.
pub fn add_noise(frame: &mut Frame, sigma: f64, rng: &mut impl Rng) {
    if sigma <= 0.0 {
        return;
    }
    let table: Vec<f64> = (0..4096).map(|_| sigma * gauss(rng)).collect();
    for p in frame.data.iter_mut() {
        let n = table[(rng.next_u32() & 4095) as usize];
        *p = (*p as f64 + n).round().clamp(0.0, 255.0) as u8;
    }
}
