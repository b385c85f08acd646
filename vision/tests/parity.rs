//! Parity with the AprilTag reference library: on the same rendered images, our
//! corners agree with apriltag 3 (PyPI apriltag-python) within 0.2 px.
//!
//! The fixture folder holds the rendered frames (PNG + frames.csv, replayed through
//! RecordedCamera), the renderer's exact corners (truth.csv) and the library's corners
//! (reference.csv). Refresh: `MARKHOLD_PARITY_REFRESH=1 cargo test --release -p
//! markhold-vision --test parity`, then `python3 vision/tests/parity/apriltag_reference.py`.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use common::*;
use markhold_camera::{Camera, Frame, FrameRecorder, RecordedCamera};
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerTracker};
use nalgebra::Isometry3;
use rand::SeedableRng;
use std::path::{Path, PathBuf};

fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/parity")
}

fn camera() -> CameraCalibration {
    CameraCalibration::pinhole(640, 480, 500.0, 500.0, 319.5, 239.5)
}

fn scenes() -> Vec<Isometry3<f64>> {
    vec![
        pose([0.0, 0.0, 0.6], 0.0, 0.0),
        pose([0.1, -0.05, 1.0], 30.0, -10.0),
        pose([-0.2, 0.1, 1.5], -50.0, 15.0),
        pose([0.3, 0.2, 2.0], 20.0, -30.0),
        pose([-0.05, 0.05, 0.8], 60.0, 0.0),
        pose([0.15, -0.1, 1.2], 0.0, 55.0),
    ]
}

fn refresh() {
    let d = dir();
    let _ = std::fs::remove_dir_all(&d);
    let mut rec = FrameRecorder::create(&d).unwrap();
    let m = marker();
    let calib = camera();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
    let mut frame = Frame::default();
    let mut truth = String::from("file,tl_x,tl_y,tr_x,tr_y,br_x,br_y,bl_x,bl_y\n");
    for (k, t) in scenes().iter().enumerate() {
        let c = render_marker(
            &mut frame,
            &calib,
            &bitmap(&m),
            m.size_m,
            t,
            &SceneParams::default(),
        );
        add_noise(&mut frame, 1.5, &mut rng);
        frame.meta.seq = k as u64;
        frame.meta.stamp_s = k as f64;
        frame.meta.exposure_us = 1000.0;
        rec.write(&frame).unwrap();
        let name = format!("frame_{k:06}");
        let mut pgm = format!("P5\n{} {}\n255\n", frame.width, frame.height).into_bytes();
        pgm.extend_from_slice(&frame.data);
        std::fs::write(d.join(format!("{name}.pgm")), pgm).unwrap();
        let xs: Vec<String> = c
            .iter()
            .flat_map(|p| p.unwrap())
            .map(|v| format!("{v:.6}"))
            .collect();
        truth.push_str(&format!("{name}.png,{}\n", xs.join(",")));
    }
    std::fs::write(d.join("truth.csv"), truth).unwrap();
    std::fs::write(d.join(".gitignore"), "*.pgm\n").unwrap();
}

/// Rows of a CSV after its header: file name and numbers.
fn read_csv(path: &Path) -> Vec<(String, Vec<f64>)> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let mut f = l.split(',');
            let name = f.next().unwrap().to_string();
            (name, f.map(|v| v.parse::<f64>().unwrap()).collect())
        })
        .collect()
}

#[test]
fn corners_agree_with_apriltag_reference_library() {
    if std::env::var_os("MARKHOLD_PARITY_REFRESH").is_some() {
        refresh();
        panic!(
            "fixture frames rewritten: now run python3 vision/tests/parity/apriltag_reference.py"
        );
    }
    let d = dir();
    let truth = read_csv(&d.join("truth.csv"));
    let reference = read_csv(&d.join("reference.csv"));
    let m = marker();
    let mut cam = RecordedCamera::open(&d).unwrap();
    let mut frame = Frame::default();
    let mut worst_ref = 0.0f64;
    let (mut ours_rms, mut ref_rms, mut n) = (0.0, 0.0, 0);
    for (k, (name, exact)) in truth.iter().enumerate() {
        cam.grab(&mut frame).unwrap();
        let mut tracker = MarkerTracker::new(&m, &DetectorConfig::default(), camera()).unwrap();
        let obs = tracker
            .process(&frame)
            .unwrap()
            .unwrap_or_else(|| panic!("{name}: not detected"));
        let r = reference
            .iter()
            .find(|(f, v)| f == name && v[0] as u32 == m.id)
            .unwrap_or_else(|| panic!("{name}: no reference detection of id {}", m.id));
        // AprilTag puts (0, 0) at the outer corner of the first pixel, OpenCV at its
        // centre: subtract half a pixel. Its corners go the other way round (lb, rb,
        // rt, lt in its own axes): rotate them into ours (tl, tr, br, bl) by matching
        // the first corner, then require the same cyclic order.
        let rc = |i: usize| [r.1[1 + 2 * i] - 0.5, r.1[2 + 2 * i] - 0.5];
        let lib = [rc(0), rc(1), rc(2), rc(3)];
        let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
        let ours0 = [obs.corners[0][0] as f64, obs.corners[0][1] as f64];
        let start = (0..4)
            .min_by(|&a, &b| dist(lib[a], ours0).total_cmp(&dist(lib[b], ours0)))
            .unwrap();
        // Reversed cyclic order (the library runs counter-clockwise in the image).
        let reference_corners = [0, 1, 2, 3].map(|i| lib[(start + 4 - i) % 4]);
        for i in 0..4 {
            let ours = [obs.corners[i][0] as f64, obs.corners[i][1] as f64];
            let exact = [exact[2 * i], exact[2 * i + 1]];
            let d_ref =
                (ours[0] - reference_corners[i][0]).hypot(ours[1] - reference_corners[i][1]);
            let e_ours = (ours[0] - exact[0]).hypot(ours[1] - exact[1]);
            let e_ref =
                (reference_corners[i][0] - exact[0]).hypot(reference_corners[i][1] - exact[1]);
            worst_ref = worst_ref.max(d_ref);
            ours_rms += e_ours * e_ours;
            ref_rms += e_ref * e_ref;
            n += 1;
            assert!(
                d_ref < 0.2,
                "frame {k} corner {i}: ours {ours:?}, apriltag {:?} ({d_ref:.3} px apart)",
                reference_corners[i]
            );
        }
    }
    println!(
        "{} frames: max |ours - apriltag| {worst_ref:.3} px; error vs exact corners: ours rms {:.3} px, apriltag rms {:.3} px",
        truth.len(),
        (ours_rms / n as f64).sqrt(),
        (ref_rms / n as f64).sqrt()
    );
}
