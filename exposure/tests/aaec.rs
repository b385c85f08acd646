//! AAEC on rendered scenes: convergence to the argmax of M, delay handling.
mod common;

use common::*;
use markhold_exposure::*;

fn aaec(cfg: AaecConfig, initial: f64) -> Aaec {
    let fallback = Box::new(MeanAe::new(MeanAeConfig::default(), limits(), initial).unwrap());
    Aaec::new(cfg, Response::linear(), limits(), initial, fallback).unwrap()
}

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
        assert!(
            matches!(at, Some(k) if k <= 8),
            "from {t0:.0} (best {best:.0}): settled at {at:?}: {:?}",
            short(&tr, best)
        );
    }
}
