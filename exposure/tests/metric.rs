//! The metric against the math: analytic derivative vs finite differences, histogram
//! ranks vs a full sort.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use common::*;
use markhold_exposure::*;

/// Below this |dM/d(ln t)| (grey levels squared) 8-bit rounding dominates a finite
/// difference of M over a 10% exposure change.
const TINY: f64 = 5.0;

/// Analytic dM/d(ln t) vs the central difference of M rendered at t(1 +- eps), over a
/// sweep of exposures without clipping, for several percentiles. Returns the number of
/// exposures where |dM| was not tiny.
fn check_derivative(response: Response, t_start: f64, t_end: f64) -> usize {
    let scene = Scene::grating(response.clone());
    let roi = scene.roi();
    let eps = 0.05;
    let mut checked = 0;
    for p in [0.6, 0.7, 0.9] {
        let params = MetricParams {
            percentile: p,
            ..MetricParams::default()
        };
        let mut gm = GradientMetric::new(&response, params);
        let mut f = Frame::new(W, H);
        let mut at = |t: f64| {
            scene.render(t, 0, &mut f);
            gm.evaluate(f.view().crop(roi)).unwrap()
        };
        let mut t = t_start;
        while t < t_end {
            let hi = at(t * (1.0 + eps));
            assert_eq!(hi.saturated_frac, 0.0, "sweep reaches clipping at {t}");
            let lo = at(t * (1.0 - eps));
            let v = at(t);
            let fd = (hi.m - lo.m) / ((1.0 + eps).ln() - (1.0 - eps).ln());
            if fd.abs().max(v.dm_dlnt.abs()) >= TINY {
                let rel = (v.dm_dlnt - fd).abs() / fd.abs();
                assert!(
                    rel < 0.05,
                    "p {p} t {t:.0}: analytic {} vs fd {fd} ({:.1}%)",
                    v.dm_dlnt,
                    rel * 100.0
                );
                checked += 1;
            }
            t *= 1.2;
        }
    }
    checked
}

/// Linear camera: dM/d(ln t) = 2M exactly in theory; the finite differences agree.
#[test]
fn derivative_matches_finite_differences_linear() {
    assert!(check_derivative(Response::linear(), 100.0, 1000.0) >= 25);
}

/// The same through a gamma-2.2 response (g' = 2.2 / I).
#[test]
fn derivative_matches_finite_differences_gamma() {
    assert!(check_derivative(Response::gamma(2.2).unwrap(), 10.0, 350.0) >= 25);
}

/// A response read from a table file (here a gamma-1.8 curve written out).
#[test]
fn derivative_matches_finite_differences_table() {
    let g = Response::gamma(1.8).unwrap();
    let text: String = g.g_prime_table().iter().map(|v| format!("{v}\n")).collect();
    let table = Response::parse_table(std::path::Path::new("g18.txt"), &text).unwrap();
    assert!(check_derivative(table, 20.0, 500.0) >= 25);
}

/// Histogram ranks (O(S)) vs a full sort: same M and dM/d(ln t) within the bins'
/// resolution, on dim, good, and over-exposed frames of the scene and a noisy one.
#[test]
fn histogram_matches_full_sort() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let mut f = Frame::new(W, H);
    for (p, sat, pen) in [(0.7, 250u8, 3.0), (0.9, 255, 1.0), (0.5, 200, 2.0)] {
        let params = MetricParams {
            percentile: p,
            saturation_grey: sat,
            saturation_penalty: pen,
            ..MetricParams::default()
        };
        let mut gm = GradientMetric::new(&scene.response, params);
        for t in [100.0, 700.0, 1500.0, 5000.0] {
            scene.render(t, 0, &mut f);
            for roi in [
                scene.roi(),
                f.full_roi(),
                Roi {
                    x: 3,
                    y: 5,
                    width: 7,
                    height: 4,
                },
            ] {
                let view = f.view().crop(roi);
                let fast = gm.evaluate(view).unwrap();
                let slow = reference::metric_full_sort(view, &scene.response, &params).unwrap();
                let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 5e-3 * scale + 1e-9;
                assert!(
                    close(fast.m, slow.m, slow.m.abs()),
                    "M {} vs {}",
                    fast.m,
                    slow.m
                );
                assert!(
                    close(fast.dm_dlnt, slow.dm_dlnt, slow.dm_dlnt.abs().max(slow.m)),
                    "p {p} t {t} {roi:?}: dM {} vs {}",
                    fast.dm_dlnt,
                    slow.dm_dlnt
                );
                assert_eq!(fast.pixels, slow.pixels);
                assert!((fast.mean_grey - slow.mean_grey).abs() < 1e-9);
            }
        }
    }
}

/// With integer G below the first inexact bin, both paths must agree to rounding.
#[test]
fn histogram_is_exact_on_small_gradients() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let data: Vec<u8> = (0..40 * 30)
        .map(|_| 100 + rng.random_range(0..2u8))
        .collect();
    let view = ImageView::new(40, 30, &data).unwrap();
    let params = MetricParams::default();
    let r = Response::linear();
    let fast = GradientMetric::new(&r, params).evaluate(view).unwrap();
    let slow = reference::metric_full_sort(view, &r, &params).unwrap();
    assert!(
        (fast.m - slow.m).abs() < 1e-9 * slow.m,
        "{} {}",
        fast.m,
        slow.m
    );
    assert!((fast.dm_dlnt - slow.dm_dlnt).abs() < 1e-6 * slow.dm_dlnt.abs().max(1.0));
}

/// The fast GEC scorer (tables, reused rows) against the naive one.
#[test]
fn gec_scores_match_reference() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let mut f = Frame::new(W, H);
    let cfg = GecConfig::default();
    let mut sc = GecScorer::new(&cfg);
    for t in [50.0, 300.0, 1500.0] {
        scene.render(t, 0, &mut f);
        let fast = sc.scores(f.view()).unwrap();
        let slow = reference::gec_scores(f.view(), &cfg).unwrap();
        for (a, b) in fast.iter().zip(&slow) {
            assert!(
                (a - b).abs() <= 2e-3 * b.abs() + 1e-3,
                "t {t}: {fast:?} vs {slow:?}"
            );
        }
        // And the pyramid level.
        let mut d = pyramid::Downsampler::new();
        let (w, h, data) = reference::downsample(f.view(), 8);
        let v = d.run(f.view(), 8);
        assert_eq!((v.width, v.height), (w, h));
        assert_eq!(v.data, &data[..]);
    }
}

/// The CPU-dispatched metric (AVX2 where present) and the portable one give the same bits
/// on every response model, exposure and RoI, so a run does not depend on the machine.
#[test]
fn dispatched_metric_is_bit_identical_to_portable() {
    let mut g_prime = [0.0; 256];
    for (i, g) in g_prime.iter_mut().enumerate() {
        *g = 2.0 / (i as f64 + 4.0);
    }
    for response in [
        Response::linear(),
        Response::gamma(2.2).unwrap(),
        Response::from_g_prime(g_prime).unwrap(),
    ] {
        let scene = Scene::marker(response.clone(), 3.0, 0.15);
        let mut f = Frame::new(W, H);
        let mut a = GradientMetric::new(&scene.response, MetricParams::default());
        let mut b = GradientMetric::new(&scene.response, MetricParams::default());
        for (k, t) in [30.0, 400.0, 1500.0, 6000.0].into_iter().enumerate() {
            scene.render(t, k as u64, &mut f);
            for roi in [scene.roi(), f.full_roi()] {
                let x = a.evaluate(f.view().crop(roi)).unwrap();
                let y = b.evaluate_portable(f.view().crop(roi)).unwrap();
                assert_eq!(x.m.to_bits(), y.m.to_bits(), "t {t}: M {} vs {}", x.m, y.m);
                assert_eq!(x.dm_dlnt.to_bits(), y.dm_dlnt.to_bits(), "t {t}");
                assert_eq!(x.mean_grey.to_bits(), y.mean_grey.to_bits());
                assert_eq!(x.saturated_frac.to_bits(), y.saturated_frac.to_bits());
            }
        }
    }
}
