//! A static scene must hold a still exposure once AAEC has converged (no probing
//! excursions), while a change of light is still followed quickly.
mod common;

use common::*;
use markhold_exposure::*;

/// Largest relative deviation of `tr` from its first value, and max / min.
fn spread(tr: &[f64]) -> (f64, f64) {
    let (lo, hi) = tr
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &t| (a.min(t), b.max(t)));
    let dev = tr
        .iter()
        .map(|t| (t / tr[0] - 1.0).abs())
        .fold(0.0, f64::max);
    (dev, hi / lo)
}

fn best_of(scene: &Scene, cfg: &AaecConfig) -> f64 {
    let roi = scene.roi();
    Scene::argmax(20.0, 30_000.0, |t| {
        scene.metric_at(t, roi, cfg.metric_params())
    })
}

/// Static marker scene with 2 grey levels of sensor noise, one frame of actuation delay:
/// after 60 frames to converge, 300 frames in which the exposure changes by less than 2%
/// (max / min), from both sides of the optimum.
#[test]
fn static_scene_exposure_holds_still_after_convergence() {
    let scenes = [
        (
            "spot r 400",
            Scene::marker_lit(Response::linear(), 3.0, 0.15, 400.0),
        ),
        (
            "spot r 90",
            Scene::marker_lit(Response::linear(), 2.0, 0.05, 90.0),
        ),
        (
            "even light",
            Scene::marker_lit(Response::linear(), 3.0, 0.15, 2000.0),
        ),
        (
            "lamp plate",
            Scene::lamp_plate(Response::linear(), 60.0, 55.0, 1.0, 0.01, 0.08),
        ),
    ];
    for (name, mut scene) in scenes {
        let cfg = AaecConfig::default();
        let best = best_of(&scene, &cfg);
        scene.noise_grey = 2.0;
        for t0 in [best / 10.0, best * 10.0] {
            let mut c = aaec(cfg.clone(), t0);
            let tr = run(&scene, &mut c, t0, 360, 1, true);
            let tail = &tr[60..];
            let (dev, ratio) = spread(tail);
            let moves = tail.windows(2).filter(|w| w[1] != w[0]).count();
            eprintln!(
                "{name}: from {t0:.0} (best {best:.0}): at frame 60 {:.3} x best; \
                 next 300 frames: max/min {ratio:.4}, max deviation {dev:.4}, {moves} changes",
                tr[60] / best
            );
            assert!(
                ratio < 1.02,
                "{name} from {t0:.0}: max/min {ratio:.4} over 300 frames: {:?}",
                tail.iter()
                    .map(|t| (t / best * 1000.0).round() / 1000.0)
                    .collect::<Vec<_>>()
            );
            assert!(
                (tail[0] / best - 1.0).abs() < 0.05,
                "not converged: {:.3}",
                tail[0] / best
            );
        }
    }
}

/// After converging, the light steps by 10x (up and down): AAEC is within 5% of the new
/// optimum at most 8 frames after the first frame that sees the new light (one frame
/// of actuation delay, so every other frame is skipped).
#[test]
fn a_tenfold_step_of_light_is_followed_within_8_frames() {
    let mut scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let cfg = AaecConfig::default();
    let best = best_of(&scene, &cfg);
    scene.noise_grey = 2.0;
    for factor in [10.0, 0.1] {
        let stepped = scene.scaled(factor);
        let new_best = best / factor;
        let mut c = aaec(cfg.clone(), best);
        let before = run(&scene, &mut c, best, 60, 1, true);
        let t = *before.last().unwrap();
        let tr = run(&stepped, &mut c, t, 60, 1, true);
        let at = settled_at(&tr, new_best, 0.05);
        eprintln!(
            "light x{factor}: within 5% of {new_best:.0} from frame {at:?}: {:?}",
            tr[..14]
                .iter()
                .map(|t| (t / new_best * 1000.0).round() / 1000.0)
                .collect::<Vec<_>>()
        );
        assert!(
            matches!(at, Some(k) if k <= 8),
            "light x{factor}: settled at {at:?}"
        );
    }
}
