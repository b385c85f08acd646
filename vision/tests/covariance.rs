//! Covariance consistency: the normalised estimation error squared (NEES) of the
//! pose over many noisy trials matches the 6-dof chi-square distribution.

mod common;

use common::*;
use markhold_camera::Frame;
use markhold_vision::pose::{isotropic_corner_cov, marker_object_points, refine_pose};
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerTracker};
use nalgebra::{Isometry3, Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Error of `est` against `truth` in the covariance's coordinates: translation
/// difference and the left rotation vector, both in the camera frame.
fn error(est: &Isometry3<f64>, truth: &Isometry3<f64>) -> Vector6<f64> {
    let dt = est.translation.vector - truth.translation.vector;
    let dr = (est.rotation * truth.rotation.inverse()).scaled_axis();
    Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z)
}

fn nees(e: &Vector6<f64>, cov: &Matrix6<f64>) -> f64 {
    (e.transpose() * cov.try_inverse().expect("invertible covariance") * e)[0]
}

/// Mean of `n` chi-square(6) draws: mean 6, variance 12 / n. Bounds at 4 standard
/// deviations (a false alarm about once in 30 000 runs; the seed is fixed anyway).
fn chi2_mean_bounds(n: usize) -> (f64, f64) {
    let sd = (12.0 / n as f64).sqrt();
    (6.0 - 4.0 * sd, 6.0 + 4.0 * sd)
}

#[test]
fn nees_matches_chi_square_for_corner_noise() {
    // Corners with exactly the modelled noise: the first-order covariance must be
    // consistent (this checks the Jacobian and the information matrix).
    let calib = calib_distorted();
    let obj = marker_object_points(0.2);
    let sigma = 0.15;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for (pos, yaw, pitch) in [
        ([0.1, -0.05, 1.0], 35.0, -10.0),
        ([-0.3, 0.2, 3.0], 55.0, 20.0),
    ] {
        let truth = pose(pos, yaw, pitch);
        let n = 2000;
        let mut sum = 0.0;
        for _ in 0..n {
            let img = obj.map(|p| {
                let uv = calib.project(&(truth * p)).unwrap();
                uv + Vector2::new(sigma * gauss(&mut rng), sigma * gauss(&mut rng))
            });
            // Start away from the truth, as IPPE would.
            let init = Isometry3::from_parts(
                (truth.translation.vector + Vector3::new(0.01, -0.01, 0.03)).into(),
                UnitQuaternion::from_scaled_axis(Vector3::new(0.02, 0.01, -0.02)) * truth.rotation,
            );
            let sol = refine_pose(&calib, &obj, &img, &init, &isotropic_corner_cov(sigma)).unwrap();
            sum += nees(
                &error(&sol.t_cam_marker, &truth),
                &sol.covariance().unwrap(),
            );
        }
        let mean = sum / n as f64;
        let (lo, hi) = chi2_mean_bounds(n);
        println!("corner noise, {pos:?}: mean NEES {mean:.3} (bounds {lo:.3}..{hi:.3})");
        assert!(
            mean > lo && mean < hi,
            "mean NEES {mean} outside {lo}..{hi}"
        );
    }
}

#[test]
fn nees_of_tracker_on_noisy_images_within_factor_two() {
    // Whole pipeline on rendered images with pixel noise: the covariance comes from
    // the edge-fit residuals plus the floor; it must be neither over- nor
    // under-confident by more than 2x (mean NEES within 3..12), and the mean must
    // sit inside the chi-square bounds widened by that factor.
    let calib = CameraCalibration::pinhole(640, 480, 500.0, 500.0, 319.5, 239.5);
    let m = marker();
    let bm = bitmap(&m);
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let mut clean = Frame::default();
    let mut frame = Frame::default();
    let mut all = Vec::new();
    for (pos, yaw, pitch) in [
        ([0.05, 0.02, 0.8], 20.0, -15.0),
        ([-0.1, 0.05, 1.5], 50.0, 10.0),
        ([0.1, -0.1, 2.0], -35.0, 30.0),
    ] {
        let truth = pose(pos, yaw, pitch);
        render_marker(
            &mut clean,
            &calib,
            &bm,
            m.size_m,
            &truth,
            &SceneParams::default(),
        );
        let mut sum = 0.0;
        let n = 60;
        for _ in 0..n {
            frame.clone_from(&clean);
            add_noise(&mut frame, 4.0, &mut rng);
            // Fresh tracker: no continuity, every frame a full search.
            let mut t = MarkerTracker::new(&m, &DetectorConfig::default(), calib.clone()).unwrap();
            let obs = t.process(&frame).unwrap().expect("detected");
            let e = nees(&error(&obs.t_cam_marker, &truth), &obs.cov_cam);
            sum += e;
            all.push(e);
        }
        println!("image noise, {pos:?}: mean NEES {:.3}", sum / n as f64);
    }
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    println!("image noise, all {} trials: mean NEES {mean:.3}", all.len());
    assert!(
        mean > 3.0 && mean < 12.0,
        "mean NEES {mean}: covariance off by more than 2x"
    );
    // The default floor (0.005 px) only adds, so the mean may sit below 6, not above
    // the chi-square bound.
    let (_, hi) = chi2_mean_bounds(all.len());
    assert!(
        mean < hi,
        "mean NEES {mean} above the chi-square bound {hi}: over-confident"
    );
}
