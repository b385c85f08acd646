//! RoI tracking: same pose as a full search on a moving sequence, periodic full
//! searches, and recovery after the marker leaves and re-enters the view.

mod common;

use common::*;
use markhold_camera::Frame;
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerTracker, Tracked};
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn small_calib() -> CameraCalibration {
    CameraCalibration {
        dist: vec![-0.1, 0.02, 0.0, 0.0, 0.0],
        model: markhold_vision::DistortionModel::PlumbBob,
        ..CameraCalibration::pinhole(800, 600, 600.0, 600.0, 399.5, 299.5)
    }
}

/// Frame `k` of a sweep: the marker slides left to right at 1.2 m, turning.
fn sweep(k: usize) -> Isometry3<f64> {
    let s = k as f64 / 40.0;
    pose(
        [-0.35 + 0.7 * s, 0.1 - 0.2 * s, 1.2 + 0.3 * s],
        15.0 + 25.0 * s,
        -10.0 + 5.0 * s,
    )
}

fn render(
    frame: &mut Frame,
    calib: &CameraCalibration,
    t: &Isometry3<f64>,
    k: usize,
    rng: &mut ChaCha8Rng,
) {
    let m = marker();
    render_marker(
        frame,
        calib,
        &bitmap(&m),
        m.size_m,
        t,
        &SceneParams::default(),
    );
    add_noise(frame, 2.0, rng);
    frame.meta.seq = k as u64;
    frame.meta.stamp_s = k as f64 / 30.0;
}

/// A tracker of the test marker with the default detector.
fn default_tracker(calib: &CameraCalibration) -> MarkerTracker {
    MarkerTracker::new(&marker(), &DetectorConfig::default(), calib.clone())
        .expect("the test marker and calibration make a tracker")
}

/// The default detector with `full_search_period_frames` set: 1 searches every frame
/// whole, 0 only when the marker is lost.
fn with_period(full_search_period_frames: u32) -> DetectorConfig {
    DetectorConfig {
        full_search_period_frames,
        ..Default::default()
    }
}

/// The largest distance (px) between the matching corners of two observations.
fn max_corner_gap(a: &markhold_camera::Corners, b: &markhold_camera::Corners) -> f32 {
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
        .fold(0.0f32, f32::max)
}

/// Area of the corners' bounding box, pixels.
fn roi_area_of(c: &markhold_camera::Corners) -> u64 {
    let xs = c.iter().map(|p| p[0]);
    let ys = c.iter().map(|p| p[1]);
    let w = xs.clone().fold(f32::MIN, f32::max) - xs.fold(f32::MAX, f32::min);
    let h = ys.clone().fold(f32::MIN, f32::max) - ys.fold(f32::MAX, f32::min);
    (w * h) as u64
}

/// Lateral marker positions (m): `n` frames sliding right from 0 in 2 cm steps, `away`
/// frames at 2 m (far outside the view at 1.2 m range), `n` frames back from 0.2 m.
fn out_and_back(n: usize, away: usize) -> Vec<f64> {
    (0..n)
        .map(|k| k as f64 * 0.02)
        .chain(std::iter::repeat_n(2.0, away))
        .chain((0..n).map(|k| 0.2 - k as f64 * 0.02))
        .collect()
}

#[test]
fn tracked_search_matches_full_search_on_a_moving_sequence() {
    let calib = small_calib();
    let m = marker();
    let tracked_cfg = with_period(15);
    let full_cfg = with_period(1);
    let mut tracker = MarkerTracker::new(&m, &tracked_cfg, calib.clone()).unwrap();
    let mut full = MarkerTracker::new(&m, &full_cfg, calib.clone()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut frame = Frame::default();
    let mut n_tracked = 0;
    let frames = 41;
    for k in 0..frames {
        let truth = sweep(k);
        render(&mut frame, &calib, &truth, k, &mut rng);
        let a = tracker
            .process(&frame)
            .unwrap()
            .expect("tracker sees the marker");
        let b = full
            .process(&frame)
            .unwrap()
            .expect("full search sees the marker");
        assert!(!b.tracked);
        if a.tracked {
            n_tracked += 1;
            // The window is a small part of the frame, and holds the marker.
            let roi = tracker
                .last_search_roi()
                .expect("tracked frames have a window");
            assert!(roi.area() * 4 < 800 * 600, "window {roi:?} is not small");
            for c in &a.corners {
                assert!(c[0] >= roi.x as f32 && c[0] <= (roi.x + roi.width) as f32);
                assert!(c[1] >= roi.y as f32 && c[1] <= (roi.y + roi.height) as f32);
            }
        }
        let range = truth.translation.vector.norm();
        let dp = position_error(&a.t_cam_marker, &b.t_cam_marker);
        let dr = rotation_error_deg(&a.t_cam_marker, &b.t_cam_marker);
        assert!(
            dp < 1e-3 * range,
            "frame {k}: tracked and full poses differ by {dp} m"
        );
        assert!(
            dr < 0.05,
            "frame {k}: tracked and full rotations differ by {dr} deg"
        );
        let max_corner = max_corner_gap(&a.corners, &b.corners);
        assert!(
            max_corner < 0.05,
            "frame {k}: corners differ by {max_corner} px"
        );
        assert!(position_error(&a.t_cam_marker, &truth) < 0.01 * range);
        // The exposure region holds the marker and little else.
        let er = a.exposure_roi(0.1, 800, 600).expect("marker in view");
        assert!(er.area() < 2 * roi_area_of(&a.corners), "{er:?}");
    }
    // Frames 0, 15 and 30 are full searches (first frame and the period); the rest
    // are tracked.
    let stats = tracker.stats();
    assert_eq!(stats.full_searches, 3, "{stats:?}");
    assert_eq!(n_tracked, frames - 3, "{stats:?}");
    assert_eq!(stats.tracked_hits as usize, n_tracked);
}

#[test]
fn recovers_after_the_marker_leaves_and_reenters() {
    let calib = small_calib();
    let mut tracker = default_tracker(&calib);
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let mut frame = Frame::default();
    // In view (x = 0), out to the right (x = 2 m at 1.2 m range is far outside the
    // 67 degree field of view), and back.
    let xs = out_and_back(10, 5);
    let mut seen = Vec::new();
    for (k, x) in xs.iter().enumerate() {
        let truth = pose([*x, 0.0, 1.2], 25.0, 0.0);
        render(&mut frame, &calib, &truth, k, &mut rng);
        let obs = tracker.process(&frame).unwrap();
        if let Some(o) = &obs {
            assert!(
                position_error(&o.t_cam_marker, &truth) < 0.01 * 1.2,
                "frame {k}"
            );
        }
        seen.push(obs.map(|o| o.tracked));
    }
    // Seen in the first part (tracked after the first frame), lost while away.
    assert_eq!(seen[0], Some(false));
    assert!(seen[1..10].iter().all(|s| *s == Some(true)), "{seen:?}");
    assert!(seen[10..15].iter().all(|s| s.is_none()), "{seen:?}");
    // Found by the full search on its first frame back, then tracked again.
    assert_eq!(seen[15], Some(false), "{seen:?}");
    assert!(seen[16..].iter().all(|s| *s == Some(true)), "{seen:?}");
}

/// The loop's split (`process_tracked`, then `process_full` only when asked, after the
/// command is out) sees exactly what `process` sees: same observations, same counters,
/// over a sequence that tracks, loses the marker, finds it again and tracks again.
#[test]
fn split_search_gives_what_process_gives() {
    let calib = small_calib();
    let m = marker();
    let cfg = with_period(7);
    let mut whole = MarkerTracker::new(&m, &cfg, calib.clone()).unwrap();
    let mut split = MarkerTracker::new(&m, &cfg, calib.clone()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let mut frame = Frame::default();
    let xs = out_and_back(12, 3);
    let (mut asked, mut done) = (0, 0);
    for (k, x) in xs.iter().enumerate() {
        render(
            &mut frame,
            &calib,
            &pose([*x, 0.0, 1.2], 25.0, 0.0),
            k,
            &mut rng,
        );
        let a = whole.process(&frame).unwrap();
        let b = match split.process_tracked(&frame).unwrap() {
            Tracked::Done(o) => {
                done += 1;
                o
            }
            Tracked::NeedsFullSearch => {
                asked += 1;
                split.process_full(&frame).unwrap()
            }
        };
        match (&a, &b) {
            (None, None) => {}
            (Some(a), Some(b)) => {
                assert_eq!(a.corners, b.corners, "frame {k}");
                assert_eq!(a.t_cam_marker, b.t_cam_marker, "frame {k}");
                assert_eq!(a.tracked, b.tracked, "frame {k}");
            }
            _ => panic!(
                "frame {k}: process {:?}, split {:?}",
                a.is_some(),
                b.is_some()
            ),
        }
        assert_eq!(whole.stats(), split.stats(), "frame {k}");
    }
    // Both paths ran: the first frame, the periodic searches and the frames away (and
    // the first one back) asked for a full search; the rest were tracked.
    assert!(asked >= 1 + 3 + 3, "{asked} full searches asked");
    assert!(done >= 15, "{done} tracked frames");
    assert_eq!(whole.stats().full_searches, asked);
}

#[test]
fn a_jump_beyond_the_window_falls_back_to_a_full_search_in_the_same_frame() {
    let calib = small_calib();
    let mut tracker = default_tracker(&calib);
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let mut frame = Frame::default();
    let a = pose([-0.3, 0.0, 1.2], 20.0, 0.0);
    render(&mut frame, &calib, &a, 0, &mut rng);
    assert!(tracker.process(&frame).unwrap().is_some());
    // Next frame: the marker is on the other side of the image.
    let b = pose([0.35, 0.1, 1.2], 20.0, 0.0);
    render(&mut frame, &calib, &b, 1, &mut rng);
    let o = tracker
        .process(&frame)
        .unwrap()
        .expect("found by the fallback search");
    assert!(!o.tracked);
    assert!(position_error(&o.t_cam_marker, &b) < 0.012);
    let s = tracker.stats();
    assert_eq!(
        (s.tracked_searches, s.tracked_hits, s.full_searches),
        (1, 0, 2),
        "{s:?}"
    );
}

#[test]
fn close_marker_is_tracked_in_a_downscaled_window_with_full_search_accuracy() {
    // At 0.45 m the marker side is about 270 px: the tracked window is searched at
    // 1/4 scale and the corners refined at full resolution.
    let calib = small_calib();
    let m = marker();
    let cfg = with_period(0);
    let full_cfg = DetectorConfig {
        full_search_downscale: 1,
        ..with_period(1)
    };
    let mut tracker = MarkerTracker::new(&m, &cfg, calib.clone()).unwrap();
    let mut full = MarkerTracker::new(&m, &full_cfg, calib.clone()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    let mut frame = Frame::default();
    for k in 0..8 {
        let truth = pose([-0.02 + 0.005 * k as f64, 0.01, 0.45], 30.0 - k as f64, 8.0);
        render(&mut frame, &calib, &truth, k, &mut rng);
        let a = tracker.process(&frame).unwrap().expect("tracked");
        let b = full.process(&frame).unwrap().expect("full");
        assert_eq!(a.tracked, k > 0);
        let max_corner = max_corner_gap(&a.corners, &b.corners);
        assert!(
            max_corner < 0.05,
            "frame {k}: corners differ by {max_corner} px"
        );
        assert!(position_error(&a.t_cam_marker, &truth) < 0.01 * 0.45);
    }
}

#[test]
fn continuity_resolves_the_ipe_ambiguity_of_a_distant_marker() {
    // A marker tilted 10 degrees, receding from 3 m to 10 m in front of a narrow
    // (37 degree) camera: far away both IPPE
    // solutions fit the noisy corners about equally well, and a tracker without a
    // previous pose picks the mirrored tilt about half the time. The tracker that
    // followed the marker out keeps the right one.
    let calib = CameraCalibration::pinhole(640, 480, 1000.0, 1000.0, 319.5, 239.5);
    let m = marker();
    let bm = bitmap(&m);
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    let mut frame = Frame::default();
    let mut tracker = default_tracker(&calib);
    let (mut flips_continuous, mut flips_fresh, mut far_frames) = (0, 0, 0);
    for k in 0..60 {
        let range = (3.0 + 7.0 * k as f64 / 35.0).min(10.0);
        let truth = pose([0.0, 0.0, range], 10.0, 0.0);
        render_noisy(&mut frame, &calib, &m, &bm, &truth, 3.0, &mut rng);
        frame.meta.stamp_s = k as f64 / 30.0;
        let a = tracker.process(&frame).unwrap().expect("tracker sees it");
        if range < 9.0 {
            continue;
        }
        far_frames += 1;
        if rotation_error_deg(&a.t_cam_marker, &truth) > 5.0 {
            flips_continuous += 1;
        }
        let mut fresh = default_tracker(&calib);
        if let Some(b) = fresh.process(&frame).unwrap() {
            if rotation_error_deg(&b.t_cam_marker, &truth) > 5.0 {
                flips_fresh += 1;
            }
        }
    }
    println!("{far_frames} frames beyond 9 m: {flips_fresh} flipped without history, {flips_continuous} with");
    assert!(
        flips_fresh >= 5,
        "the scene is not ambiguous enough to test: {flips_fresh} flips"
    );
    assert_eq!(flips_continuous, 0);
    assert!(tracker.stats().ambiguous > 0, "{:?}", tracker.stats());
}

/// With nothing tracked, after a search that found nothing, the bounded search (the
/// frame at a quarter of its resolution, then one part at half or full resolution in
/// turn) finds a close marker on its first frame in view, and a distant one within its
/// cycle: 6 frames for a marker the half-resolution parts find, 32 for the smallest.
#[test]
fn the_bounded_search_finds_near_and_far_markers_within_its_cycle() {
    let calib = calib();
    let mut rng = ChaCha8Rng::seed_from_u64(45);
    let mut frame = Frame::default();
    // 0.2 m at f = 1000 px: 133 px, 50 px and 29 px.
    for (range, within) in [(1.5, 1), (4.0, 6), (7.0, 32)] {
        let mut tracker = default_tracker(&calib);
        // Out of view: the first search (complete) finds nothing.
        render(
            &mut frame,
            &calib,
            &pose([50.0, 0.0, range], 10.0, 0.0),
            0,
            &mut rng,
        );
        assert!(tracker.process(&frame).unwrap().is_none());
        let truth = pose([0.1, -0.05, range], 10.0, 0.0);
        let mut found = None;
        for k in 1..=within {
            render(&mut frame, &calib, &truth, k, &mut rng);
            if let Some(o) = tracker.process(&frame).unwrap() {
                found = Some((k, o));
                break;
            }
        }
        let (k, o) = found.unwrap_or_else(|| panic!("{range} m: not found in {within} frames"));
        assert!(
            position_error(&o.t_cam_marker, &truth) < 0.01 * range,
            "{range} m, frame {k}"
        );
        println!("{range} m: found on frame {k} of at most {within}");
    }
}

#[test]
fn tracked_corners_hold_the_rendered_truth_at_every_window_scale() {
    // 1440x1080 with lens distortion, the marker drifting and turning at four ranges:
    // sides of about 80, 165, 250 and 330 px, tracked windows searched at 1/1 to 1/4.
    // Each tracked frame's corners against the rendered ones, and against a full
    // search's (a fresh search of the same frame) error on the same frames.
    let calib = calib_distorted();
    let m = marker();
    let bm = bitmap(&m);
    let cfg = with_period(0);
    let full_cfg = with_period(1);
    let mut rng = ChaCha8Rng::seed_from_u64(45);
    let mut frame = Frame::default();
    let frames = 12;
    for range in [2.5, 1.2, 0.8, 0.6] {
        let mut tracker = MarkerTracker::new(&m, &cfg, calib.clone()).unwrap();
        let mut full = MarkerTracker::new(&m, &full_cfg, calib.clone()).unwrap();
        let (mut sq_tracked, mut sq_full, mut worst) = (0.0f64, 0.0f64, 0.0f64);
        let mut n = 0;
        for k in 0..frames {
            let s = k as f64 / frames as f64;
            let truth = pose(
                [(-0.06 + 0.1 * s) * range, (0.04 - 0.06 * s) * range, range],
                20.0 - 30.0 * s,
                -15.0 + 10.0 * s,
            );
            let exact = render_marker(
                &mut frame,
                &calib,
                &bm,
                m.size_m,
                &truth,
                &SceneParams::default(),
            )
            .map(|p| p.expect("corner in front of the camera"));
            add_noise(&mut frame, 2.0, &mut rng);
            frame.meta.seq = k as u64;
            frame.meta.stamp_s = k as f64 / 30.0;
            let a = tracker.process(&frame).unwrap().expect("tracked");
            let b = full.process(&frame).unwrap().expect("full");
            assert_eq!(a.tracked, k > 0, "{range} m frame {k}");
            if !a.tracked {
                continue;
            }
            for ((p, q), e) in a.corners.iter().zip(&b.corners).zip(&exact) {
                let ea = (p[0] as f64 - e[0]).powi(2) + (p[1] as f64 - e[1]).powi(2);
                let eb = (q[0] as f64 - e[0]).powi(2) + (q[1] as f64 - e[1]).powi(2);
                sq_tracked += ea;
                sq_full += eb;
                worst = worst.max(ea.sqrt());
                n += 1;
            }
        }
        let rms_tracked = (sq_tracked / n as f64).sqrt();
        let rms_full = (sq_full / n as f64).sqrt();
        println!(
            "{range} m: tracked corner error RMS {rms_tracked:.4} px (max {worst:.4}), full search {rms_full:.4} px"
        );
        assert!(rms_tracked < 0.1, "{range} m: tracked RMS {rms_tracked} px");
        assert!(worst < 0.3, "{range} m: tracked corner off by {worst} px");
        assert!(
            rms_tracked < 1.05 * rms_full + 0.005,
            "{range} m: tracked RMS {rms_tracked} px against the full search's {rms_full} px"
        );
    }
}
