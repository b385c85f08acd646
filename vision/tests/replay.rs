//! Frames written by FrameRecorder replay through RecordedCamera into the tracker
//! with the same poses as live.

mod common;

use common::*;
use markhold_camera::{Camera, Frame, FrameRecorder, RecordedCamera};
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerTracker};
use rand::SeedableRng;

#[test]
fn recorded_frames_replay_to_the_same_poses() {
    let calib = CameraCalibration::pinhole(640, 480, 500.0, 500.0, 319.5, 239.5);
    let m = marker();
    let dir = std::env::temp_dir().join(format!("markhold-vision-replay-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut rec = FrameRecorder::create(&dir).unwrap();
    let mut live = MarkerTracker::new(&m, &DetectorConfig::default(), calib.clone()).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(31);
    let mut frame = Frame::default();
    let mut live_poses = Vec::new();
    for k in 0..5 {
        let t = pose([0.02 * k as f64, 0.0, 1.0], 20.0, 5.0);
        render_marker(
            &mut frame,
            &calib,
            &bitmap(&m),
            m.size_m,
            &t,
            &SceneParams::default(),
        );
        add_noise(&mut frame, 2.0, &mut rng);
        frame.meta.seq = k;
        frame.meta.stamp_s = k as f64 * 0.05;
        frame.meta.exposure_us = 2000.0 + k as f64;
        rec.write(&frame).unwrap();
        live_poses.push(
            live.process(&frame)
                .unwrap()
                .expect("seen live")
                .t_cam_marker,
        );
    }
    drop(rec);
    let mut cam = RecordedCamera::open(&dir).unwrap();
    let mut replay = MarkerTracker::new(&m, &DetectorConfig::default(), calib).unwrap();
    for (k, want) in live_poses.iter().enumerate() {
        cam.grab(&mut frame).unwrap();
        assert_eq!(frame.meta.exposure_us, 2000.0 + k as f64);
        let got = replay
            .process(&frame)
            .unwrap()
            .expect("seen in replay")
            .t_cam_marker;
        // PNG is lossless: bit-identical input, identical pose.
        assert_eq!(got, *want, "frame {k}");
    }
    std::fs::remove_dir_all(&dir).ok();
}
