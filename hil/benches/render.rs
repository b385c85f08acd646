//! One 1440x1080 frame of the HIL camera: the fast renderer beside the plain per-pixel
//! reference (f64, no precomputation), in the same run.

#![allow(clippy::unwrap_used)] // A benchmark's setup fails loudly when broken, by design.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use markhold_exposure::{ExposureLimits, Frame, ResponseModel};
use markhold_hil::camera::{CameraModel, RenderLoops, UnderwaterCamera};
use markhold_hil::scene::{LightingConfig, LightingScenario, MarkerSpec, Scene, WaterConfig};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

fn rot(cols: [[f64; 3]; 3]) -> UnitQuaternion<f64> {
    let m = Matrix3::from_columns(&cols.map(Vector3::from));
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
}

fn marker() -> MarkerSpec {
    let cells = 8;
    let white = (0..cells * cells)
        .map(|k| {
            let (i, j) = (k % cells, k / cells);
            i > 0 && j > 0 && i < cells - 1 && j < cells - 1 && (i * 5 + j * 3) % 4 < 2
        })
        .collect();
    MarkerSpec {
        cells,
        white,
        size_m: 0.15,
        plate_margin_m: 0.04,
    }
}

fn setup(scenario: LightingScenario) -> (Scene, UnderwaterCamera, Isometry3<f64>) {
    let depth = 4.0;
    let t_wm = Isometry3::from_parts(
        Translation3::new(0.0, 0.0, depth),
        rot([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),
    );
    let lighting = LightingConfig {
        scenario,
        ..LightingConfig::default()
    };
    let scene = Scene::new(&WaterConfig::default(), &lighting, marker(), t_wm, 1).unwrap();
    let mut model = CameraModel::blackfly_s(ResponseModel::Gamma { gamma: 2.2 });
    model.dist = [-0.2, 0.05, 0.0, 0.0, 0.0];
    model.limits = ExposureLimits {
        min_us: 20.0,
        max_us: 30_000.0,
        fps: 30.0,
    };
    let mut cam = UnderwaterCamera::new(model, 1).unwrap();
    cam.set_exposure_us(2000.0);
    let t_wc = Isometry3::from_parts(
        Translation3::new(-1.0, 0.05, depth - 0.05),
        rot([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
            * UnitQuaternion::from_euler_angles(0.05, 0.08, 0.02),
    );
    (scene, cam, t_wc)
}

/// How a bench renders its frames.
#[derive(Clone, Copy)]
enum Build {
    /// The fast renderer with the widest loops this CPU runs up to these.
    Fast(RenderLoops),
    /// The per-pixel f64 reference.
    Reference,
}

fn bench_render(c: &mut Criterion) {
    let mut g = c.benchmark_group("render_1440x1080");
    g.throughput(Throughput::Elements(1440 * 1080));
    let (all, some) = (
        &LightingScenario::ALL[..],
        &[LightingScenario::Normal, LightingScenario::Caustics][..],
    );
    let runs = [
        // The widest build this CPU runs, and AVX2 alone beside it.
        (Build::Fast(RenderLoops::Avx512), "fast", all),
        (Build::Fast(RenderLoops::Avx2), "fast-avx2", some),
        // What a CPU without AVX2 runs (same frames).
        (Build::Fast(RenderLoops::Portable), "portable", some),
        (
            Build::Reference,
            "reference",
            &[LightingScenario::Normal, LightingScenario::Adversarial][..],
        ),
    ];
    for (build, name, scenarios) in runs {
        if let Build::Reference = build {
            g.sample_size(10);
        }
        for &sc in scenarios {
            let (scene, mut cam, t_wc) = setup(sc);
            if let Build::Fast(loops) = build {
                let got = cam.set_render_loops(loops);
                if got != loops && name != "fast" {
                    continue; // this CPU lacks the named build: nothing to time
                }
            }
            let mut frame = Frame::default();
            let mut t = 0.0;
            g.bench_with_input(BenchmarkId::new(name, sc), &sc, |b, _| {
                b.iter(|| {
                    t += 1.0 / 30.0;
                    match build {
                        Build::Reference => {
                            cam.render_reference(&scene, &t_wc, &t_wc, t, &mut frame)
                        }
                        Build::Fast(_) => cam.render(&scene, &t_wc, &t_wc, t, &mut frame),
                    }
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench_render);
criterion_main!(benches);
