//! AAEC on rendered scenes: convergence to the argmax of M, delay handling.
mod common;

use common::*;
use markhold_exposure::*;

fn short(tr: &[f64], best: f64) -> Vec<f64> {
    tr.iter()
        .map(|t| (t / best * 1000.0).round() / 1000.0)
        .collect()
}

/// From 10x too short and 10x too long, with one frame of actuation delay (a command
/// after frame k applies at frame k + 2, so every other frame is skipped), AAEC is
/// within 5% of the argmax of M by frame 8 and stays there.
#[test]
fn aaec_converges_to_argmax_of_m_within_8_frames() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let cfg = AaecConfig::default();
    let roi = scene.roi();
    let best = Scene::argmax(100.0, 30_000.0, |t| {
        scene.metric_at(t, roi, cfg.metric_params())
    });
    assert!(
        best > 200.0 && best < 3000.0,
        "scene out of the camera's range: {best}"
    );
    for t0 in [best / 10.0, best * 10.0] {
        let mut c = aaec(cfg.clone(), t0);
        let tr = run(&scene, &mut c, t0, 60, 1, true);
        let at = settled_at(&tr, best, 0.05);
        eprintln!(
            "aaec from {t0:.0}: within 5% of {best:.0} from frame {at:?}: {:?}",
            &short(&tr, best)[..12]
        );
        assert!(
            matches!(at, Some(k) if k <= 8),
            "from {t0:.0} (best {best:.0}): settled at {at:?}: {:?}",
            short(&tr, best)
        );
    }
}

fn scene_frame(scene: &Scene, t: f64) -> Frame {
    let mut f = Frame::new(W, H);
    scene.render(t, 0, &mut f);
    f
}

/// A frame not exposed at the last command teaches nothing.
#[test]
fn frames_at_a_stale_exposure_are_skipped() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let mut c = aaec(AaecConfig::default(), 200.0);
    let s = c.update(&scene_frame(&scene, 150.0), Some(&scene.corners));
    assert!(!s.used_frame && s.metric.is_nan());
    assert_eq!(s.exposure_us, 200.0);
    let s = c.update(&scene_frame(&scene, 200.0), Some(&scene.corners));
    assert!(s.used_frame && s.metric > 0.0);
    assert!(s.exposure_us > 200.0, "a dim frame must raise the exposure");
}

/// RoI = corner box padded by 10% of its size on each side, clamped to the image.
#[test]
fn roi_is_padded_box_clamped() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let mut c = aaec(AaecConfig::default(), 200.0);
    let f = scene_frame(&scene, 200.0);
    let s = c.update(&f, Some(&scene.corners));
    // Marker 100..220 x 60..180 (120 px): padded by 12 px.
    assert_eq!(
        s.roi,
        Some(Roi {
            x: 88,
            y: 48,
            width: 144,
            height: 144
        })
    );
    let edge: Corners = [
        [300.0, 200.0],
        [330.0, 200.0],
        [330.0, 250.0],
        [300.0, 250.0],
    ];
    let s = c.update(&f, Some(&edge));
    assert_eq!(
        s.roi,
        Some(Roi {
            x: 297,
            y: 195,
            width: 23,
            height: 45
        })
    );
}

/// Marker lost: the last RoI for `lost_hold_frames` frames, then the fallback (here
/// the mean AE, whose step we can predict), with the ascent state reset, so that on
/// re-acquisition AAEC steps exactly as a fresh controller would.
#[test]
fn marker_loss_holds_roi_then_falls_back_and_resets() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    // The highlight guard off, so the fallback's own step can be predicted (the guard
    // is tested in `washout.rs`).
    let cfg = AaecConfig {
        lost_hold_frames: 3,
        highlight_frac: 0.0,
        ..AaecConfig::default()
    };
    let mut c = aaec(cfg.clone(), 100.0);
    let mut f = Frame::new(W, H);
    let mut t = 100.0;
    let mut roi = None;
    for _ in 0..4 {
        scene.render(t, 0, &mut f);
        let s = c.update(&f, Some(&scene.corners));
        t = s.exposure_us;
        roi = s.roi;
    }
    for k in 0..3 {
        scene.render(t, 0, &mut f);
        let s = c.update(&f, None);
        assert_eq!(s.roi, roi, "lost frame {k} keeps the last RoI");
        assert!(s.used_frame && s.metric.is_finite());
        t = s.exposure_us;
    }
    // Fourth lost frame: the fallback runs on the whole image.
    scene.render(t, 0, &mut f);
    let s = c.update(&f, None);
    let mut mean = MeanAe::new(MeanAeConfig::default(), limits(), t).unwrap();
    let expect = mean.update(&f, None);
    assert_eq!(s.roi, None);
    assert_eq!(s.exposure_us, expect.exposure_us);
    assert_eq!(s.metric, expect.metric);
    t = s.exposure_us;
    // Marker back: the step is the one of a fresh AAEC at this exposure.
    scene.render(t, 0, &mut f);
    let s = c.update(&f, Some(&scene.corners));
    let mut fresh = aaec(cfg, t);
    let e = fresh.update(&f, Some(&scene.corners));
    assert_eq!(s.exposure_us, e.exposure_us);
    assert_eq!(s.metric, e.metric);
}

/// The same convergence through a gamma-2.2 camera (the controller told so through its
/// response): the slope is scale free, so the same learning rate works.
#[test]
fn aaec_converges_through_a_gamma_camera() {
    let response = Response::gamma(2.2).unwrap();
    let scene = Scene::marker(response.clone(), 3.0, 0.15);
    let cfg = AaecConfig::default();
    let roi = scene.roi();
    let best = Scene::argmax(20.0, 30_000.0, |t| {
        scene.metric_at(t, roi, cfg.metric_params())
    });
    for t0 in [best / 10.0, best * 10.0] {
        let fallback = Box::new(MeanAe::new(MeanAeConfig::default(), limits(), t0).unwrap());
        let mut c = Aaec::new(cfg.clone(), response.clone(), limits(), t0, fallback).unwrap();
        let tr = run(&scene, &mut c, t0, 60, 1, true);
        let at = settled_at(&tr, best, 0.05);
        eprintln!(
            "gamma 2.2, from {t0:.0}: within 5% of {best:.0} from frame {at:?}: {:?}",
            &short(&tr, best)[..14]
        );
        assert!(matches!(at, Some(k) if k <= 12), "settled at {at:?}");
    }
}
