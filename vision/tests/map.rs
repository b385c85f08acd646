//! A marker map: one pose from every marker in view, tighter than the origin marker's
//! alone; a moved marker and a wrong id left out and counted; markers entering the view
//! found where the map puts them, without a full-frame search; nothing allocated per
//! frame.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use common::*;
use markhold_camera::Frame;
use markhold_vision::synth::{render_markers, SceneParams};
use markhold_vision::{
    marker_bitmap, DetectorConfig, MapMarker, MarkerConfig, MarkerFamily, MarkerTracker,
};
use nalgebra::{Isometry3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

#[global_allocator]
static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;

const SIZE: f64 = 0.12;

fn entry(id: u32, position_m: [f64; 3], rpy_deg: [f64; 3]) -> MapMarker {
    MapMarker {
        id,
        size_m: SIZE,
        position_m,
        rpy_deg,
        plane: None,
    }
}

/// Origin id 7 and four markers around it on a panel, one of them turned 20 degrees
/// toward the centre.
fn map() -> MarkerConfig {
    MarkerConfig {
        map: vec![
            entry(3, [0.35, 0.0, 0.0], [0.0, 0.0, 0.0]),
            entry(11, [-0.35, 0.0, 0.0], [0.0, 0.0, 0.0]),
            entry(20, [0.0, 0.28, 0.0], [0.0, 0.0, 0.0]),
            entry(25, [0.0, -0.28, 0.03], [0.0, -20.0, 0.0]),
        ],
        ..MarkerConfig::single(MarkerFamily::AprilTag36h11, 7, SIZE)
    }
}

/// The world as printed: each marker's id and pose in the site frame.
fn world(m: &MarkerConfig) -> Vec<(u32, Isometry3<f64>)> {
    m.markers().map(|p| (p.id, p.t_site_marker)).collect()
}

/// Render the world's markers seen from `t_cam_site`, with 2 grey levels of noise.
fn render(
    frame: &mut Frame,
    world: &[(u32, Isometry3<f64>)],
    t_cam_site: &Isometry3<f64>,
    k: usize,
    rng: &mut ChaCha8Rng,
) {
    let bitmaps: Vec<_> = world
        .iter()
        .map(|(id, _)| marker_bitmap(MarkerFamily::AprilTag36h11, *id).unwrap())
        .collect();
    let placed: Vec<_> = world
        .iter()
        .zip(&bitmaps)
        .map(|((_, t), b)| (b, SIZE, t_cam_site * t))
        .collect();
    render_markers(frame, &calib(), &placed, &SceneParams::default());
    add_noise(frame, 2.0, rng);
    frame.meta.seq = k as u64;
    frame.meta.stamp_s = k as f64 / 30.0;
}

/// The site 1.6 m ahead, slightly off-axis and turned.
fn view(k: usize) -> Isometry3<f64> {
    let s = k as f64;
    pose([0.04 + 0.002 * s, -0.03, 1.6], 12.0 + 0.3 * s, -8.0)
}

fn tracker(m: &MarkerConfig) -> MarkerTracker {
    MarkerTracker::new(m, &DetectorConfig::default(), calib()).unwrap()
}

#[test]
fn every_marker_in_view_makes_one_tighter_pose() {
    let m = map();
    let w = world(&m);
    let mut joint = tracker(&m);
    let mut single = tracker(&m.origin_only());
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut frame = Frame::new(W, H);
    let (mut e_joint, mut e_single, n) = (0.0, 0.0, 8);
    for k in 0..n {
        let truth = view(k);
        render(&mut frame, &w, &truth, k, &mut rng);
        let j = joint.process(&frame).unwrap().expect("joint pose");
        let s = single.process(&frame).unwrap().expect("origin marker");
        assert_eq!((j.markers_used, j.outliers), (5, 0), "frame {k}");
        assert_eq!(j.id, 7, "the origin marker's corners are given");
        assert_eq!((s.markers_used, s.outliers), (1, 0));
        e_joint += position_error(&j.t_cam_marker, &truth).powi(2);
        e_single += position_error(&s.t_cam_marker, &truth).powi(2);
        // The covariance says the same: five markers pin the pose down better.
        let tr = |c: &nalgebra::Matrix6<f64>| c[(0, 0)] + c[(1, 1)] + c[(2, 2)];
        assert!(tr(&j.cov_cam) < 0.5 * tr(&s.cov_cam), "frame {k}");
        // And it is consistent with the error (3 sigma per axis).
        let err = j.t_cam_marker.translation.vector - truth.translation.vector;
        for a in 0..3 {
            assert!(
                err[a].abs() < 3.0 * j.cov_cam[(a, a)].sqrt() + 2e-4,
                "frame {k} axis {a}: {err} vs {}",
                j.cov_cam[(a, a)].sqrt()
            );
        }
    }
    let (rms_joint, rms_single) = ((e_joint / n as f64).sqrt(), (e_single / n as f64).sqrt());
    println!("position RMS: joint {rms_joint:.5} m, origin marker alone {rms_single:.5} m");
    assert!(rms_joint < 0.5 * rms_single, "{rms_joint} vs {rms_single}");
    let st = joint.stats();
    assert_eq!(
        (st.detections, st.markers_used, st.outliers),
        (n as u64, 5 * n as u64, 0)
    );
}

#[test]
fn a_moved_marker_and_a_wrong_id_are_left_out_and_counted() {
    let m = map();
    // Marker 3 moved 6 cm since the map was measured; where the map has 11, a marker
    // that decodes as 20 (a wrong id; 20's own place is empty).
    let mut w = world(&m);
    w[1].1.translation.vector += Vector3::new(0.06, 0.0, 0.0);
    w[2].0 = 20;
    w.remove(3);
    let mut t = tracker(&m);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut frame = Frame::new(W, H);
    for k in 0..4 {
        let truth = view(k);
        render(&mut frame, &w, &truth, k, &mut rng);
        let o = t.process(&frame).unwrap().expect("pose");
        assert_eq!((o.markers_used, o.outliers), (2, 2), "frame {k}");
        assert!(
            position_error(&o.t_cam_marker, &truth) < 0.002,
            "frame {k}: {}",
            position_error(&o.t_cam_marker, &truth)
        );
        assert!(
            rotation_error_deg(&o.t_cam_marker, &truth) < 0.3,
            "frame {k}"
        );
    }
    assert_eq!(t.stats().outliers, 8);
    // The same frames with the outlier test off (an infinite gate) give a pose pulled
    // off by centimetres: the test is what keeps them out.
    let open = DetectorConfig {
        map_outlier_rms_px: f64::MAX,
        ..DetectorConfig::default()
    };
    let mut t = MarkerTracker::new(&m, &open, calib()).unwrap();
    render(&mut frame, &w, &view(0), 0, &mut rng);
    let o = t.process(&frame).unwrap().expect("pose");
    assert_eq!(o.markers_used, 4);
    assert!(position_error(&o.t_cam_marker, &view(0)) > 0.005);
}

/// The vehicle turns so that the markers on the right come into view one by one: each
/// is found in the window where the map puts it (no full-frame search after the first);
/// while the markers on the far right stay out of view the pose is the one the markers
/// in view give.
#[test]
fn markers_entering_the_view_are_found_where_the_map_puts_them() {
    // A row of markers 0.5 m apart to the right of the origin.
    let m = MarkerConfig {
        map: (1..=4)
            .map(|i| entry(30 + i, [0.5 * i as f64, 0.0, 0.0], [0.0; 3]))
            .collect(),
        ..MarkerConfig::single(MarkerFamily::AprilTag36h11, 7, SIZE)
    };
    let w = world(&m);
    let cfg = DetectorConfig {
        full_search_period_frames: 0,
        ..DetectorConfig::default()
    };
    let mut t = MarkerTracker::new(&m, &cfg, calib()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut frame = Frame::new(W, H);
    let mut used = Vec::new();
    for k in 0..30 {
        // The camera slides right at 1.4 m: 2 cm a frame.
        let truth = pose([0.3 - 0.02 * k as f64, 0.0, 1.4], 0.0, 0.0);
        render(&mut frame, &w, &truth, k, &mut rng);
        let o = t.process(&frame).unwrap().expect("pose");
        assert!(position_error(&o.t_cam_marker, &truth) < 0.003, "frame {k}");
        used.push(o.markers_used);
    }
    let st = t.stats();
    assert_eq!(st.full_searches, 1, "{st:?}");
    assert!(used[0] < used[29], "{used:?}");
    assert_eq!(st.outliers, 0);
}

/// A map whose other markers are never in view gives what the origin marker alone
/// gives, frame for frame.
#[test]
fn markers_out_of_view_change_nothing() {
    let mut m = map();
    for e in &mut m.map {
        e.position_m[0] += 10.0;
    }
    let w = world(&m);
    let mut with_map = tracker(&m);
    let mut alone = tracker(&m.origin_only());
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut frame = Frame::new(W, H);
    for k in 0..6 {
        render(&mut frame, &w, &view(k), k, &mut rng);
        let a = with_map.process(&frame).unwrap();
        let b = alone.process(&frame).unwrap();
        assert_eq!(a, b, "frame {k}");
    }
    assert_eq!(with_map.stats(), alone.stats());
}

/// Tracking five markers allocates nothing on the Rust heap after the first frames.
#[test]
fn tracking_a_map_allocates_nothing_per_frame() {
    let m = map();
    let w = world(&m);
    let mut t = tracker(&m);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let frames: Vec<Frame> = (0..6)
        .map(|k| {
            let mut f = Frame::new(W, H);
            render(&mut f, &w, &view(k), k, &mut rng);
            f
        })
        .collect();
    for f in &frames[..2] {
        t.process(f).unwrap().expect("pose");
    }
    let before = markhold_testkit::thread_allocs();
    for f in &frames[2..] {
        let o = t.process(f).unwrap().expect("pose");
        assert_eq!(o.markers_used, 5);
    }
    assert_eq!(markhold_testkit::thread_allocs() - before, 0);
}
