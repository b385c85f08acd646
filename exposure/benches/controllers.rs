//! AAEC on a 300x300 RoI, AEC and GEC on 1440x1080, each beside a naive reference
//! (full sort, f64, fresh buffers) in the same run.

#![allow(clippy::unwrap_used)] // A benchmark's setup fails loudly when broken, by design.

use criterion::measurement::WallTime;
use criterion::{
    criterion_group, criterion_main, BenchmarkGroup, BenchmarkId, Criterion, Throughput,
};
use markhold_exposure::*;
use std::hint::black_box;

/// A textured, slightly noisy frame with a bright marker-like block pattern in the
/// middle.
fn frame(w: u32, h: u32, marker_side: u32) -> (Frame, Corners) {
    let mut f = Frame::new(w, h);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let side = marker_side as f64;
    let (x0, y0) = (cx - side / 2.0, cy - side / 2.0);
    for y in 0..h as usize {
        for x in 0..w as usize {
            let u = (x as f64 - x0) / side;
            let v = (y as f64 - y0) / side;
            let inside = (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v);
            let cell = inside.then(|| ((u * 6.0) as u32 * 7 + (v * 6.0) as u32 * 3) % 2 == 1);
            f.data[y * w as usize + x] = markhold_testkit::synthetic_grey(x, y, cell);
        }
    }
    let c = [
        [x0 as f32, y0 as f32],
        [(x0 + side) as f32, y0 as f32],
        [(x0 + side) as f32, (y0 + side) as f32],
        [x0 as f32, (y0 + side) as f32],
    ];
    (f, c)
}

fn limits() -> ExposureLimits {
    ExposureLimits {
        min_us: 10.0,
        max_us: 30_000.0,
        fps: 30.0,
    }
}

/// `fast/{size}`: the controller's update on `f`, exposed as it last commanded.
fn bench_fast(
    g: &mut BenchmarkGroup<'_, WallTime>,
    size: &str,
    ctrl: &mut dyn ExposureController,
    f: &mut Frame,
    marker: Option<&Corners>,
) {
    g.bench_function(BenchmarkId::new("fast", size), |b| {
        b.iter(|| {
            f.meta.exposure_us = ctrl.commanded_us();
            black_box(ctrl.update(black_box(&*f), marker))
        })
    });
}

fn bench_aaec(c: &mut Criterion) {
    // Marker 250 px: the padded RoI is 300 x 300.
    let (mut f, corners) = frame(1440, 1080, 250);
    let roi = Roi::from_corners_padded(&corners, 0.1, f.width, f.height).unwrap();
    assert_eq!((roi.width, roi.height), (300, 300));
    let cfg = ExposureConfig::default();
    let mut ctrl = build_controller(&cfg, ExposureMethod::Aaec, limits(), 1000.0).unwrap();
    let params = cfg.aaec.metric_params();
    let response = Response::linear();
    let mut g = c.benchmark_group("aaec_update_roi");
    g.throughput(Throughput::Elements(roi.area()));
    bench_fast(&mut g, "300x300", ctrl.as_mut(), &mut f, Some(&corners));
    // The metric alone, dispatched (AVX2 where the CPU has it) and portable (SSE2): the
    // ratio of the two is what the runtime dispatch buys on this machine.
    let mut metric = GradientMetric::new(&response, params);
    g.bench_function(BenchmarkId::new("metric_dispatched", "300x300"), |b| {
        b.iter(|| black_box(metric.evaluate(black_box(f.view().crop(roi)))))
    });
    g.bench_function(BenchmarkId::new("metric_portable", "300x300"), |b| {
        b.iter(|| black_box(metric.evaluate_portable(black_box(f.view().crop(roi)))))
    });
    g.bench_function(BenchmarkId::new("reference_full_sort", "300x300"), |b| {
        b.iter(|| {
            black_box(reference::metric_full_sort(
                f.view().crop(roi),
                &response,
                &params,
            ))
        })
    });
    g.finish();
}

fn bench_aec(c: &mut Criterion) {
    let (mut f, _) = frame(1440, 1080, 400);
    let cfg = ExposureConfig::default();
    let mut ctrl = build_controller(&cfg, ExposureMethod::Aec, limits(), 1000.0).unwrap();
    let params = cfg.aec.metric_params();
    let response = Response::linear();
    let mut g = c.benchmark_group("aec_update");
    g.throughput(Throughput::Elements(1440 * 1080));
    bench_fast(&mut g, "1440x1080", ctrl.as_mut(), &mut f, None);
    g.bench_function(BenchmarkId::new("reference_full_sort", "1440x1080"), |b| {
        b.iter(|| black_box(reference::aec_metric(f.view(), 8, &response, &params)))
    });
    g.finish();
}

fn bench_gec(c: &mut Criterion) {
    let (mut f, _) = frame(1440, 1080, 400);
    let cfg = ExposureConfig::default();
    let mut ctrl = build_controller(&cfg, ExposureMethod::Gec, limits(), 1000.0).unwrap();
    let gcfg = cfg.gec.clone();
    let mut g = c.benchmark_group("gec_update");
    g.throughput(Throughput::Elements(1440 * 1080));
    bench_fast(&mut g, "1440x1080", ctrl.as_mut(), &mut f, None);
    g.bench_function(BenchmarkId::new("reference_naive", "1440x1080"), |b| {
        b.iter(|| {
            let (w, h, data) = reference::downsample(f.view(), gcfg.downsample as usize);
            let v = ImageView {
                width: w,
                height: h,
                stride: w,
                data: &data,
            };
            let s = reference::gec_scores(v, &gcfg).unwrap();
            let c = fit_quintic(&GEC_GAMMAS, &s).unwrap();
            black_box(gec_ratio(best_gamma(&c), gcfg.kp, gcfg.d))
        })
    });
    g.finish();
}

criterion_group!(benches, bench_aaec, bench_aec, bench_gec);
criterion_main!(benches);
