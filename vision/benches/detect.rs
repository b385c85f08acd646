//! Detect + pose at 1440x1080: full-frame search and RoI-tracked, beside OpenCV's
//! default full-frame `detect_markers` (default parameters, no refinement, no pose); and
//! a marker map with 4 markers in view (one joint pose) beside the single marker.

#![allow(clippy::unwrap_used)] // A benchmark's setup fails loudly when broken, by design.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use markhold_camera::Frame;
use markhold_vision::synth::{render_marker, render_markers, SceneParams};
use markhold_vision::{
    marker_bitmap, CameraCalibration, DetectorConfig, MapMarker, MarkerConfig, MarkerFamily,
    MarkerTracker,
};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::{aruco, core};
use rand::{Rng, SeedableRng};

fn calib() -> CameraCalibration {
    CameraCalibration::pinhole(1440, 1080, 1000.0, 1000.0, 719.5, 539.5)
}

/// The site frame (the origin marker's) seen from `range_m`, facing the camera, turned.
fn site_pose(range_m: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.1 * range_m, -0.05 * range_m, range_m),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.4),
    )
}

/// Texture everywhere (a flat background is unrealistically cheap to threshold).
fn texture(frame: &mut Frame, seed: u64) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for p in frame.data.iter_mut() {
        *p = (*p as i32 + rng.random_range(-6..=6)).clamp(0, 255) as u8;
    }
}

fn scene(range_m: f64) -> (CameraCalibration, MarkerConfig, Frame) {
    let calib = calib();
    let marker = MarkerConfig::single(MarkerFamily::AprilTag36h11, 7, 0.2);
    let bm = marker_bitmap(marker.family, marker.id).unwrap();
    let mut frame = Frame::default();
    render_marker(
        &mut frame,
        &calib,
        &bm,
        marker.size_m,
        &site_pose(range_m),
        &SceneParams::default(),
    );
    texture(&mut frame, 1);
    (calib, marker, frame)
}

/// The marker of `scene(1.0)` with three more of the same size around it, all in view:
/// a map of four.
fn map_scene() -> (CameraCalibration, MarkerConfig, Frame) {
    let calib = calib();
    let at = |id: u32, x: f64, y: f64| MapMarker {
        id,
        size_m: 0.2,
        position_m: [x, y, 0.0],
        rpy_deg: [0.0; 3],
        plane: None,
    };
    let marker = MarkerConfig {
        map: vec![at(3, -0.3, 0.0), at(11, 0.0, 0.3), at(19, -0.3, 0.3)],
        ..MarkerConfig::single(MarkerFamily::AprilTag36h11, 7, 0.2)
    };
    let t_cam_site = site_pose(1.0);
    let placed: Vec<_> = marker
        .markers()
        .map(|m| {
            let bm = marker_bitmap(marker.family, m.id).unwrap();
            (bm, m.size_m, t_cam_site * m.t_site_marker)
        })
        .collect();
    let refs: Vec<_> = placed.iter().map(|(b, s, t)| (b, *s, *t)).collect();
    let mut frame = Frame::default();
    let corners = render_markers(&mut frame, &calib, &refs, &SceneParams::default());
    assert!(corners
        .iter()
        .flatten()
        .all(|c| c
            .is_some_and(|p| { (0.0..1440.0).contains(&p[0]) && (0.0..1080.0).contains(&p[1]) })));
    texture(&mut frame, 1);
    (calib, marker, frame)
}

fn bench(c: &mut Criterion) {
    let threads: i32 = std::env::var("MARKHOLD_CV_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let mut g = c.benchmark_group(format!("detect_pose_1440x1080_threads{threads}"));
    g.throughput(Throughput::Elements(1440 * 1080));
    for range in [1.0, 3.0] {
        let (calib, marker, mut frame) = scene(range);
        let id = format!("{range}m");

        // Baseline: OpenCV's default full-frame detection (no sub-pixel, no pose).
        core::set_num_threads(threads).unwrap();
        let dict = aruco::get_predefined_dictionary(
            aruco::PREDEFINED_DICTIONARY_NAME::DICT_APRILTAG_36h11,
        )
        .unwrap();
        let params = aruco::DetectorParameters::create().unwrap();
        let img = core::Mat::new_rows_cols_with_data::<u8>(1080, 1440, &frame.data).unwrap();
        let (mut corners, mut ids, mut rej) = (
            core::Vector::<core::Vector<core::Point2f>>::new(),
            core::Vector::<i32>::new(),
            core::Vector::<core::Vector<core::Point2f>>::new(),
        );
        g.bench_function(BenchmarkId::new("opencv_default_full", &id), |b| {
            b.iter(|| {
                aruco::detect_markers(&img, &dict, &mut corners, &mut ids, &params, &mut rej)
                    .unwrap();
                assert!(ids.iter().any(|i| i == 7));
            })
        });
        drop(img);

        for (name, downscale) in [("full_search_fullres", 1u32), ("full_search", 2)] {
            let cfg = DetectorConfig {
                full_search_period_frames: 1,
                full_search_downscale: downscale,
                opencv_threads: threads,
                ..Default::default()
            };
            let mut t = MarkerTracker::new(&marker, &cfg, calib.clone()).unwrap();
            g.bench_function(BenchmarkId::new(name, &id), |b| {
                b.iter(|| {
                    let o = t.process(&frame).unwrap().unwrap();
                    assert!(!o.tracked);
                })
            });
        }

        let cfg = DetectorConfig {
            full_search_period_frames: 0,
            opencv_threads: threads,
            ..Default::default()
        };
        let mut t = MarkerTracker::new(&marker, &cfg, calib.clone()).unwrap();
        let mut stamp = 0.0;
        t.process(&frame).unwrap().unwrap();
        g.bench_function(BenchmarkId::new("tracked", &id), |b| {
            b.iter(|| {
                stamp += 0.033;
                frame.meta.stamp_s = stamp;
                let o = t.process(&frame).unwrap().unwrap();
                assert!(o.tracked);
            })
        });
    }
    // A map of four, every marker in view: one joint pose over 16 corners, beside the
    // single marker at 1 m above.
    let (calib, marker, mut frame) = map_scene();
    let cfg = DetectorConfig {
        full_search_period_frames: 1,
        opencv_threads: threads,
        ..Default::default()
    };
    let mut t = MarkerTracker::new(&marker, &cfg, calib.clone()).unwrap();
    g.bench_function(BenchmarkId::new("map4_full_search", "1m"), |b| {
        b.iter(|| {
            let o = t.process(&frame).unwrap().unwrap();
            assert!(!o.tracked && o.markers_used == 4);
        })
    });
    let cfg = DetectorConfig {
        full_search_period_frames: 0,
        opencv_threads: threads,
        ..Default::default()
    };
    let mut t = MarkerTracker::new(&marker, &cfg, calib).unwrap();
    let mut stamp = 0.0;
    t.process(&frame).unwrap().unwrap();
    g.bench_function(BenchmarkId::new("map4_tracked", "1m"), |b| {
        b.iter(|| {
            stamp += 0.033;
            frame.meta.stamp_s = stamp;
            let o = t.process(&frame).unwrap().unwrap();
            assert!(o.tracked && o.markers_used == 4);
        })
    });

    // No marker in view: every frame is a full search (half resolution, then the
    // full-resolution fallback), the worst case of the loop.
    let (calib, marker, mut frame) = scene(1.0);
    let blank = frame.data[0];
    frame.data.iter_mut().for_each(|p| *p = blank);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    for p in frame.data.iter_mut() {
        *p = (*p as i32 + rng.random_range(-6..=6)).clamp(0, 255) as u8;
    }
    let cfg = DetectorConfig {
        opencv_threads: threads,
        ..Default::default()
    };
    let mut t = MarkerTracker::new(&marker, &cfg, calib).unwrap();
    g.bench_function(BenchmarkId::new("full_search", "absent"), |b| {
        b.iter(|| assert!(t.process(&frame).unwrap().is_none()))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
