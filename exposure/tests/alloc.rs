//! Per-frame paths allocate nothing after the first frame (one test in this binary, so
//! no other test allocates while it counts).
mod common;

use common::*;
use markhold_exposure::*;
use markhold_testkit::process_allocs;

#[global_allocator]
static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;

#[test]
fn controllers_do_not_allocate_per_frame() {
    let scene = Scene::marker(Response::linear(), 3.0, 0.15);
    let mut frames: Vec<Frame> = (0..6)
        .map(|k| {
            let mut f = Frame::new(W, H);
            scene.render(200.0 * (k + 1) as f64, k, &mut f);
            f
        })
        .collect();
    let mut cfg = ExposureConfig::default();
    let mut ctrls: Vec<Box<dyn ExposureController>> = ExposureMethod::ALL
        .iter()
        .map(|&m| build_controller(&cfg, m, limits(), 200.0).unwrap())
        .collect();
    cfg.aaec.fallback = AaecFallback::Aec;
    ctrls.push(build_controller(&cfg, ExposureMethod::Aaec, limits(), 200.0).unwrap());
    // Several markers in view, per-marker regions and their union.
    let beside = scene.corners.map(|[x, y]| [x - 30.0, y - 20.0]);
    let in_view = [scene.corners, beside];
    let mut multi: Vec<Box<dyn ExposureController>> = Vec::new();
    for regions in [
        MarkerRegions::LogSum,
        MarkerRegions::Sum,
        MarkerRegions::Union,
    ] {
        let mut cfg = ExposureConfig::default();
        cfg.aaec.regions = regions;
        let mut c = build_controller(&cfg, ExposureMethod::Aaec, limits(), 200.0).unwrap();
        c.reserve_markers(in_view.len());
        multi.push(c);
    }
    for c in multi.iter_mut() {
        for (k, f) in frames.iter_mut().enumerate() {
            f.meta.exposure_us = c.commanded_us();
            c.update_in_view(f, Some(&scene.corners), &in_view[..1 + k % 2]);
        }
        let before = process_allocs();
        for round in 0..3 {
            for (k, f) in frames.iter_mut().enumerate() {
                f.meta.exposure_us = c.commanded_us();
                let seen = round != 1 || k < 2;
                let view: &[Corners] = if seen { &in_view } else { &[] };
                c.update_in_view(f, seen.then_some(&scene.corners), view);
            }
        }
        let after = process_allocs();
        assert_eq!(after - before, 0, "aaec over two markers allocated");
    }
    for c in ctrls.iter_mut() {
        // First frames (with and without the marker, so AAEC's fallback runs too)
        // size the buffers.
        for (k, f) in frames.iter_mut().enumerate() {
            f.meta.exposure_us = c.commanded_us();
            let marker = (k % 3 != 2).then_some(&scene.corners);
            c.update(f, marker);
        }
        // A long loss too (AAEC: the fallback, a pass of the reacquisition sweep, the
        // fallback again), then found on whatever was commanded: its log lines register
        // with `tracing` the first time they run, which allocates once.
        let long_loss = |c: &mut Box<dyn ExposureController>, frames: &mut [Frame]| {
            for k in 0..96 {
                let f = &mut frames[k % 6];
                f.meta.exposure_us = c.commanded_us();
                c.update(f, (k >= 90).then_some(&scene.corners));
            }
        };
        long_loss(c, &mut frames);
        c.reset(300.0);
        for (k, f) in frames.iter_mut().enumerate().take(2) {
            f.meta.exposure_us = c.commanded_us();
            c.update(f, (k == 0).then_some(&scene.corners));
        }
        let before = process_allocs();
        for round in 0..3 {
            for (k, f) in frames.iter_mut().enumerate() {
                f.meta.exposure_us = c.commanded_us();
                // Marker seen, then lost long enough for the fallback, then back.
                let marker = (round != 1).then_some(&scene.corners);
                let s = c.update(f, marker);
                assert!(s.used_frame || k > 0);
            }
        }
        long_loss(c, &mut frames);
        let after = process_allocs();
        assert_eq!(
            after - before,
            0,
            "{} allocated {} times",
            c.method(),
            after - before
        );
    }
}
