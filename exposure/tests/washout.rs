//! A marker washed out in a lamp's spot (the adversarial picture): the lit plate is one
//! clipped disc in a dark frame, so no detector finds the marker and AAEC has no RoI.
//! Its fallback must shorten the exposure until the marker can be seen, not meter the
//! dark surround and lengthen it.
mod common;

use common::*;
use markhold_exposure::*;

/// Marker 60 px on a lamp-lit plate of radius 55 px (16% of the frame), surround lit at
/// 1% of the lamp, glare 8% of the lamp on the plate.
fn scene() -> Scene {
    Scene::lamp_plate(Response::linear(), 60.0, 55.0, 1.0, 0.01, 0.08)
}

/// Contrast a detector needs (grey levels between white and black cells).
const FOUND: f64 = 40.0;

fn best_exposure(scene: &Scene, cfg: &AaecConfig) -> f64 {
    let roi = scene.roi();
    Scene::argmax(20.0, 30_000.0, |t| {
        scene.metric_at(t, roi, cfg.metric_params())
    })
}

fn contrast_at(scene: &Scene, t: f64) -> f64 {
    let mut f = Frame::new(W, H);
    scene.render(t, 0, &mut f);
    scene.cell_contrast(&f)
}

/// The scene is the failure case: at 10x the best exposure the marker is invisible and
/// the frame is dark on average (a whole-frame mean AE lengthens).
#[test]
fn ten_times_long_is_a_clipped_disc_in_a_dark_frame() {
    let scene = scene();
    let best = best_exposure(&scene, &AaecConfig::default());
    let mut f = Frame::new(W, H);
    scene.render(10.0 * best, 0, &mut f);
    let mean = MeanAe::mean_grey(&f, f.full_roi(), 1).unwrap();
    let clipped = f.data.iter().filter(|&&p| p == 255).count() as f64 / f.data.len() as f64;
    eprintln!(
        "best {best:.0} us; at 10x: contrast {:.1}, mean {mean:.1}, clipped {:.3}; at best: contrast {:.1}",
        scene.cell_contrast(&f),
        clipped,
        contrast_at(&scene, best)
    );
    assert!(scene.cell_contrast(&f) < 5.0);
    assert!(mean < 80.0, "mean {mean}");
    assert!(clipped > 0.1, "clipped {clipped}");
    assert!(contrast_at(&scene, best) > 150.0);
}

/// No marker at all (no RoI ever): from 10x too long the fallback brings the exposure
/// into the range where the marker can be seen, and keeps it there.
#[test]
fn without_a_marker_a_clipped_blob_shortens_the_exposure() {
    let scene = scene();
    // The guard alone: with no detector at all, the reacquisition sweep (tested in
    // `sweep.rs`) would start walking its ladder after 15 frames.
    let cfg = AaecConfig {
        sweep_after_frames: 0,
        ..AaecConfig::default()
    };
    let best = best_exposure(&scene, &cfg);
    let t0 = 10.0 * best;
    let mut c = aaec(cfg, t0);
    let tr = run(&scene, &mut c, t0, 60, 1, false);
    let rel: Vec<f64> = tr
        .iter()
        .map(|t| (t / best * 100.0).round() / 100.0)
        .collect();
    eprintln!("no marker, from {t0:.0} (best {best:.0}): {:?}", &rel[..16]);
    for (k, &t) in tr.iter().enumerate().skip(8) {
        let contrast = contrast_at(&scene, t);
        assert!(
            (0.4 * best..=1.05 * best).contains(&t) && contrast >= FOUND,
            "frame {k}: {t:.0} us = {:.2} x best, contrast {contrast:.0}: {rel:?}",
            t / best
        );
    }
}

/// With a detector that finds the marker once its cells have contrast: from 10x too
/// long AAEC ends within 5% of the argmax of M.
#[test]
fn from_a_washed_out_marker_aaec_reaches_the_best_exposure() {
    let scene = scene();
    let cfg = AaecConfig::default();
    let best = best_exposure(&scene, &cfg);
    let t0 = 10.0 * best;
    let mut c = aaec(cfg, t0);
    let (tr, seen) = run_detecting(&scene, &mut c, t0, 60, 1, FOUND);
    let at = settled_at(&tr, best, 0.05);
    let first_seen = seen.iter().position(|&s| s);
    let rel: Vec<f64> = tr
        .iter()
        .map(|t| (t / best * 100.0).round() / 100.0)
        .collect();
    eprintln!(
        "detector, from {t0:.0} (best {best:.0}): seen from {first_seen:?}, within 5% from {at:?}: {:?}",
        &rel[..20]
    );
    assert!(
        matches!(at, Some(k) if k <= 16),
        "settled at {at:?}: {rel:?}"
    );
    assert!(seen[at.unwrap_or(0)..].iter().all(|&s| s));
}
