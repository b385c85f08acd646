//! AAEC's reacquisition sweep: when the whole-frame fallback cannot show the marker
//! again (it meters the frame, not the marker), the exposure walks a ladder around the
//! exposure the marker was last seen at, and AAEC restarts from the rung that shows it.
mod common;

use common::*;
use markhold_exposure::*;

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * b.abs()
}

/// Sweeps from the first lost frame on, every rung held one frame (`cfg` sets the rest),
/// after one frame that shows the marker at 1000 us: the controller, the frame buffer
/// and its command.
fn seen_at_1000(scene: &Scene, cfg: AaecConfig) -> (Aaec, Frame, f64) {
    let cfg = AaecConfig {
        lost_hold_frames: 0,
        sweep_after_frames: 1,
        sweep_dwell_frames: 1,
        ..cfg
    };
    let mut c = aaec(cfg, 1000.0);
    let mut f = Frame::new(W, H);
    scene.render(1000.0, 0, &mut f);
    let t = c.update(&f, Some(&scene.corners)).exposure_us;
    (c, f, t)
}

/// With every rung held one frame and no actuation delay, the commands are the ladder:
/// the last exposure the marker was seen at (c), then x2, c, /2, c, x4, ... out to the
/// span (64 here: /64 is 15.6 us), each side up to and including the camera's limit
/// (30 ms) once, then one frame of the fallback (`sweep_after_frames` = 1; NaN in the
/// expected list: its exposure is the mean AE's), then the next pass.
#[test]
fn the_sweep_walks_a_ladder_around_the_last_exposure_seen() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let cfg = AaecConfig {
        sweep_ratio: 2.0,
        sweep_span: 64.0,
        ..AaecConfig::default()
    };
    let (mut c, mut f, mut t) = seen_at_1000(&scene, cfg);
    // First lost frame: the fallback (not the sweep yet).
    scene.render(t, 1, &mut f);
    let s = c.update(&f, None);
    assert!(s.metric.is_finite(), "the fallback's step: {s:?}");
    t = s.exposure_us;
    let mut got = Vec::new();
    for k in 2..60 {
        scene.render(t, k, &mut f);
        let s = c.update(&f, None);
        assert!(s.roi.is_none());
        got.push(s.exposure_us);
        t = s.exposure_us;
    }
    let pass = [
        1000.0,
        2000.0,
        1000.0,
        500.0,
        1000.0,
        4000.0,
        1000.0,
        250.0,
        1000.0,
        8000.0,
        1000.0,
        125.0,
        1000.0,
        16_000.0,
        1000.0,
        62.5,
        1000.0,
        30_000.0,
        1000.0,
        31.25,
        1000.0,
        15.625,
        1000.0,
        f64::NAN,
    ];
    let want: Vec<f64> = pass.iter().cycle().take(got.len()).copied().collect();
    assert!(
        got.iter()
            .zip(&want)
            .all(|(g, w)| w.is_nan() || close(*g, *w)),
        "sweep {got:?}\nexpected {want:?}"
    );
}

/// Found on a rung while the command has moved on (the camera applies it later): AAEC
/// restarts from the exposure the frame was taken at, exactly as a fresh controller
/// there, instead of holding the frame as stale.
#[test]
fn a_marker_found_on_a_rung_restarts_the_ascent_from_that_rung() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let (mut c, mut f, mut t) = seen_at_1000(&scene, AaecConfig::default());
    for k in 1..5 {
        scene.render(t, k, &mut f);
        t = c.update(&f, None).exposure_us;
    }
    // The sweep has commanded 1000, 2000, 1000 by now; the camera delivers the frame at
    // 2000 (one step behind) and it shows the marker.
    assert!(close(t, 1000.0), "sweep at {t}");
    scene.render(2000.0, 5, &mut f);
    let s = c.update(&f, Some(&scene.corners));
    let mut fresh = aaec(c.config().clone(), 2000.0);
    let e = fresh.update(&f, Some(&scene.corners));
    assert!(s.used_frame && s.metric.is_finite(), "{s:?}");
    assert_eq!(s.exposure_us, e.exposure_us);
    assert_eq!(s.metric, e.metric);
}

/// The failure the sweep is for: a detector that decodes the marker only within 1.5x
/// of its best exposure, the marker hidden for 60 frames while the light drops to a
/// quarter, and a fallback (the mean AE) that settles far from that band. Without the
/// sweep the marker is never found again; with it, within a pass of the ladder, and
/// AAEC then holds it.
#[test]
fn the_sweep_finds_a_marker_the_fallback_cannot_show() {
    let bright = Scene::marker(Response::linear(), 3.0, 0.15);
    let dim = bright.scaled(0.25);
    let cfg = AaecConfig::default();
    let best = |s: &Scene| {
        Scene::argmax(20.0, 30_000.0, |t| {
            s.metric_at(t, s.roi(), cfg.metric_params())
        })
    };
    let (best_bright, best_dim) = (best(&bright), best(&dim));
    let band = |t: f64, b: f64| t > b / 1.5 && t < b * 1.5;
    // The mean AE's settling point on the dim scene must lie outside the band, or the
    // fallback alone would find the marker and the test would show nothing.
    let mut mean = MeanAe::new(MeanAeConfig::default(), limits(), best_dim).unwrap();
    let settled = *run(&dim, &mut mean, best_dim, 120, 1, false)
        .last()
        .unwrap();
    assert!(
        !band(settled, best_dim),
        "mean AE settles at {settled:.0} us, inside the band around {best_dim:.0} us"
    );

    let found_over = |sweep_after_frames: u32| {
        let mut c = aaec(
            AaecConfig {
                sweep_after_frames,
                ..cfg.clone()
            },
            best_bright,
        );
        let (frames, delay) = (400usize, 1usize);
        let mut applied = vec![best_bright; frames + delay + 2];
        let mut f = Frame::new(W, H);
        let mut seen = Vec::with_capacity(frames);
        for k in 0..frames {
            let (scene, hidden) = match k {
                0..30 => (&bright, false),
                30..90 => (&dim, true),
                _ => (&dim, false),
            };
            let b = if k < 30 { best_bright } else { best_dim };
            scene.render(applied[k], k as u64, &mut f);
            let found = !hidden && band(applied[k], b);
            seen.push(found);
            let s = c.update(&f, found.then_some(&scene.corners));
            for a in applied.iter_mut().skip(k + 1 + delay) {
                *a = s.exposure_us;
            }
        }
        assert!(seen[..30].iter().all(|&s| s), "not seen before the loss");
        (
            seen[90..].iter().position(|&s| s),
            seen[300..].iter().filter(|&&s| s).count(),
        )
    };
    let (first_off, _) = found_over(0);
    assert_eq!(first_off, None, "the fallback alone found it: no test");
    let (first_on, held) = found_over(AaecConfig::default().sweep_after_frames);
    // Within two passes and the fallback's 10 frames between them: a pass is 3 frames
    // a step, eight steps (c, x2, c, /2, c, x4, c, /4).
    assert!(
        matches!(first_on, Some(k) if k <= 90),
        "found {first_on:?} frames after the marker came back"
    );
    assert!(held >= 95, "seen in {held} of the last 100 frames");
}
