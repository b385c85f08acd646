//! Rendered markers at known poses are recovered: position within 1% of range,
//! rotation within 1 degree, with image noise.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use common::*;
use markhold_camera::Frame;
use markhold_vision::{DetectorConfig, MarkerTracker};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn check_grid(calib: markhold_vision::CameraCalibration, ranges: &[f64], seed: u64) {
    let m = marker();
    let bm = bitmap(&m);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut frame = Frame::default();
    let mut worst_pos = 0.0f64;
    let mut worst_rot = 0.0f64;
    let mut n = 0;
    for &range in ranges {
        for &(yaw, pitch) in &[
            (0.0, 0.0),
            (30.0, -10.0),
            (-45.0, 20.0),
            (60.0, 0.0),
            (0.0, -60.0),
        ] {
            // Off-centre so that the marker is not always on the optical axis.
            let pos = [0.12 * range, -0.08 * range, range];
            let truth = pose(pos, yaw, pitch);
            let exact = render_noisy(&mut frame, &calib, &m, &bm, &truth, 2.0, &mut rng);
            // A fresh tracker each time: no continuity to lean on.
            let mut tracker =
                MarkerTracker::new(&m, &DetectorConfig::default(), calib.clone()).unwrap();
            let obs = tracker
                .process(&frame)
                .unwrap()
                .unwrap_or_else(|| panic!("not detected at {range} m, yaw {yaw}, pitch {pitch}"));
            assert_eq!(obs.id, m.id);
            assert!(!obs.tracked);
            let range_true = truth.translation.vector.norm();
            let pe = position_error(&obs.t_cam_marker, &truth) / range_true;
            let re = rotation_error_deg(&obs.t_cam_marker, &truth);
            let sd_t = (obs.cov_cam[(0, 0)] + obs.cov_cam[(1, 1)] + obs.cov_cam[(2, 2)]).sqrt()
                / range_true;
            let sd_r = (obs.cov_cam[(3, 3)] + obs.cov_cam[(4, 4)] + obs.cov_cam[(5, 5)])
                .sqrt()
                .to_degrees();
            let cerr: f64 = obs
                .corners
                .iter()
                .zip(&exact)
                .map(|(a, b)| ((a[0] as f64 - b[0]).powi(2) + (a[1] as f64 - b[1]).powi(2)).sqrt())
                .fold(0.0, f64::max);
            println!("{range} {yaw} {pitch}: pos {:.3}% (sd {:.3}%) rot {re:.3} (sd {sd_r:.3}) rms {:.3} max corner err {cerr:.3}", pe * 100.0, sd_t * 100.0, obs.reproj_rms_px);
            assert!(
                pe < 0.01,
                "{range} m yaw {yaw} pitch {pitch}: position error {:.3}% of range",
                pe * 100.0
            );
            assert!(
                re < 1.0,
                "{range} m yaw {yaw} pitch {pitch}: rotation error {re:.3} deg"
            );
            assert!(obs.reproj_rms_px < 0.5, "rms {}", obs.reproj_rms_px);
            worst_pos = worst_pos.max(pe);
            worst_rot = worst_rot.max(re);
            n += 1;
        }
    }
    println!(
        "{n} poses: worst position error {:.3}% of range, worst rotation error {worst_rot:.3} deg",
        worst_pos * 100.0
    );
}

#[test]
fn recovers_known_poses_pinhole() {
    check_grid(calib(), &[0.5, 1.0, 2.0, 3.0], 1);
}

#[test]
fn recovers_known_poses_with_lens_distortion() {
    check_grid(calib_distorted(), &[0.5, 1.0, 2.0, 3.0], 2);
}

#[test]
fn other_ids_and_families_are_not_reported() {
    let m = marker();
    let calib = calib();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut frame = Frame::default();
    let truth = pose([0.0, 0.0, 1.0], 10.0, 0.0);
    // Id 8 is in view, the tracker looks for id 7.
    let other = markhold_vision::MarkerConfig { id: 8, ..m.clone() };
    render_noisy(
        &mut frame,
        &calib,
        &other,
        &bitmap(&other),
        &truth,
        2.0,
        &mut rng,
    );
    let mut tracker = MarkerTracker::new(&m, &DetectorConfig::default(), calib.clone()).unwrap();
    assert!(tracker.process(&frame).unwrap().is_none());
    // Id 7 is then found by the same tracker.
    render_noisy(&mut frame, &calib, &m, &bitmap(&m), &truth, 2.0, &mut rng);
    assert!(tracker.process(&frame).unwrap().is_some());
}

#[test]
fn wrong_frame_size_is_an_error() {
    let mut tracker = MarkerTracker::new(&marker(), &DetectorConfig::default(), calib()).unwrap();
    let e = tracker
        .process(&Frame::new(640, 480))
        .unwrap_err()
        .to_string();
    assert!(e.contains("640x480") && e.contains("1440x1080"), "{e}");
}
