//! The paper's AAEC (`aaec-paper`) on the crate's rendered marker scene: it converges to
//! an independent optimum (the exposure maximizing the paper's `M`, found by a sweep of
//! the same scene) when the camera's response has the shoulder of a real camera, never
//! turns down on a linear one, and what caustics do to it.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use common::*;
use markhold_exposure::*;

/// The calibrated response of the paper's camera: its code's degree-14 polynomial
/// `g'(I)` (there highest order first; here lowest first).
fn paper_camera() -> Response {
    let mut c = vec![
        2.23648003e-28,
        -4.23843983e-25,
        3.61455838e-22,
        -1.83243015e-19,
        6.14568309e-17,
        -1.43597629e-14,
        2.39781444e-12,
        -2.88855261e-10,
        2.50378889e-08,
        -1.54014489e-06,
        6.54831886e-05,
        -1.84372346e-03,
        3.21098127e-02,
        -3.08446340e-01,
        1.30761122e+00,
    ];
    c.reverse();
    ResponseModel::Polynomial { coefficients: c }
        .load()
        .unwrap()
}

/// The marker scene seen by the paper's camera (its response puts mid grey near 0.4 %
/// of full well, so the light is scaled down to land the optimum near 1.2 ms).
fn paper_scene() -> Scene {
    Scene::marker(paper_camera(), 3.0, 0.15).scaled(0.01)
}

/// The exposure maximizing the paper's `M` on the scene's RoI: a 2 % sweep, then a
/// 0.25 % one around its best.
fn paper_argmax(scene: &Scene, cfg: &AaecPaperConfig) -> f64 {
    let roi = scene.roi();
    let mut f = Frame::new(W, H);
    let mut e = PaperMetricEval::new(&scene.response);
    let mut m = |t: f64| {
        scene.render(t, 0, &mut f);
        e.evaluate(f.view().crop(roi), t, cfg).unwrap().m
    };
    let sweep = |lo: f64, hi: f64, ratio: f64, m: &mut dyn FnMut(f64) -> f64| {
        let (mut best, mut best_m, mut t) = (lo, f64::MIN, lo);
        while t <= hi {
            let v = m(t);
            if v > best_m {
                (best, best_m) = (t, v);
            }
            t *= ratio;
        }
        best
    };
    let coarse = sweep(100.0, 10_000.0, 1.02, &mut m);
    sweep(coarse / 1.02, coarse * 1.02, 1.0025, &mut m)
}

fn run_paper(scene: &Scene, cfg: &AaecPaperConfig, t0: f64, frames: usize) -> Vec<f64> {
    let mut c = AaecPaper::new(cfg.clone(), &scene.response, limits(), t0).unwrap();
    run(scene, &mut c, t0, frames, 1, true)
}

/// Every exposure after the first `from` frames within `tol` of `target`?
fn stays_within(tr: &[f64], from: usize, target: f64, tol: f64) -> bool {
    tr[from..].iter().all(|t| (t / target - 1.0).abs() <= tol)
}

#[test]
fn converges_to_the_argmax_of_its_metric_on_the_papers_camera() {
    let scene = paper_scene();
    // The step that converges from both sides here (the code's 2e-13 stalls 3x above:
    // its momentum stays under the 1 us threshold and is then never updated).
    let cfg = AaecPaperConfig {
        learning_rate: 5e-12,
        ..Default::default()
    };
    let best = paper_argmax(&scene, &cfg);
    assert!((800.0..2000.0).contains(&best), "optimum {best}");
    for t0 in [best / 3.0, best * 3.0] {
        let tr = run_paper(&scene, &cfg, t0, 200);
        eprintln!(
            "from {t0:.0}: within 10% of {best:.0} from frame {:?}, ends at {:.3} of it",
            settled_at(&tr, best, 0.10),
            tr[199] / best
        );
        // 10 %: from above it stops where |v| falls under the 1 us threshold (8-9 %
        // below the optimum here, where M is flat).
        assert!(
            stays_within(&tr, 150, best, 0.10),
            "from {t0:.0}: not within 10% of {best:.0} after frame 150: {:?}",
            &tr[150..]
        );
        // A frozen controller would fail this check.
        assert!(!stays_within(&vec![t0; 200], 150, best, 0.10));
    }
    // The code's own step (2e-13) climbs from below.
    let slow = AaecPaperConfig::default();
    let tr = run_paper(&scene, &slow, best / 3.0, 200);
    assert!(stays_within(&tr, 150, best, 0.10), "{:?}", &tr[150..]);
}

#[test]
fn on_a_linear_camera_the_papers_derivative_never_turns_down() {
    // D = I / t at every pixel, clipped ones included, so dG/dt = 2 G / t and
    // dM/dt = 2 M / t > 0: the published law can only lengthen the exposure.
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let cfg = AaecPaperConfig::default();
    let mut e = PaperMetricEval::new(&scene.response);
    let mut f = Frame::new(W, H);
    for t in [300.0, 1000.0, 3000.0] {
        scene.render(t, 0, &mut f);
        let v = e.evaluate(f.view().crop(scene.roi()), t, &cfg).unwrap();
        assert!(v.m > 0.0, "t {t}: {v:?}");
        let want = 2.0 * v.m / (t * 1e-6);
        assert!((v.dm_dt / want - 1.0).abs() < 1e-9, "t {t}: {v:?}");
    }
}

/// The paper's open problem, re-tested on the published law: with caustics changing
/// every frame, a step that converges from both sides wanders; the code's smaller step
/// holds (the paper's remedy: a smaller step length).
#[test]
fn caustics_make_the_converging_step_wander() {
    let mut scene = paper_scene();
    let fast = AaecPaperConfig {
        learning_rate: 5e-12,
        ..Default::default()
    };
    let best = paper_argmax(&scene, &fast);
    scene.caustic_amp = 0.6;
    let stats = |cfg: &AaecPaperConfig| {
        let tr = run_paper(&scene, cfg, best, 200);
        let tail = &tr[40..];
        let max_step = tail
            .windows(2)
            .map(|w| (w[1] / w[0]).ln().abs())
            .fold(0.0, f64::max);
        let (lo, hi) = tail
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &t| (a.min(t), b.max(t)));
        (max_step, hi / lo)
    };
    let (fast_step, fast_range) = stats(&fast);
    let (slow_step, slow_range) = stats(&AaecPaperConfig::default());
    eprintln!(
        "caustics 0.6: eta 5e-12 max step {fast_step:.3} range {fast_range:.2}; \
         eta 2e-13 max step {slow_step:.3} range {slow_range:.2}"
    );
    assert!(
        fast_range > 1.3 && fast_step > 0.05,
        "{fast_range} {fast_step}"
    );
    assert!(
        slow_range < 1.25 && slow_step < 0.02,
        "{slow_range} {slow_step}"
    );
}
