//! Laws every controller keeps on any input: no NaN, no panic, exposure in limits.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use markhold_exposure::*;
use proptest::prelude::*;

#[derive(Debug, Clone)]
enum Fill {
    Black,
    White,
    Noise(Vec<u8>),
}

fn frame_strategy() -> impl Strategy<Value = (u32, u32, Fill)> {
    (0u32..24, 0u32..24).prop_flat_map(|(w, h)| {
        let n = (w * h) as usize;
        let fill = prop_oneof![
            Just(Fill::Black),
            Just(Fill::White),
            proptest::collection::vec(any::<u8>(), n).prop_map(Fill::Noise),
        ];
        (Just(w), Just(h), fill)
    })
}

fn coord() -> impl Strategy<Value = f32> {
    prop_oneof![
        -50.0f32..80.0,
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(-1e9f32),
        Just(1e9f32),
    ]
}

fn corners_strategy() -> impl Strategy<Value = Option<Corners>> {
    proptest::option::of(proptest::array::uniform4(
        proptest::array::uniform2(coord()),
    ))
}

fn limits_strategy() -> impl Strategy<Value = ExposureLimits> {
    (
        1.0f64..200.0,
        1.0f64..1000.0,
        prop_oneof![Just(0.0), 1.0f64..240.0],
    )
        .prop_map(|(min, span, fps)| ExposureLimits {
            min_us: min,
            max_us: min * span,
            fps,
        })
}

/// Every controller, and whether it learns only from frames exposed as commanded (the
/// paper's methods by default use every frame, as its code did).
fn all_controllers(limits: ExposureLimits, t0: f64) -> Vec<(Box<dyn ExposureController>, bool)> {
    let mut cfg = ExposureConfig::default();
    let mut v: Vec<_> = ExposureMethod::ALL
        .iter()
        .map(|&m| {
            let c = build_controller(&cfg, m, limits, t0).unwrap();
            (c, !ExposureMethod::PAPER_CODE.contains(&m))
        })
        .collect();
    cfg.aaec.fallback = AaecFallback::Aec;
    cfg.aaec.adaptive_step = false;
    v.push((
        build_controller(&cfg, ExposureMethod::Aaec, limits, t0).unwrap(),
        true,
    ));
    let mut cfg = ExposureConfig::default();
    cfg.aaec_paper.frames = PaperFrames::ExposedAsCommanded;
    cfg.aaec_paper.pre_detection = PreDetection::Hold;
    cfg.aec_paper.frames = PaperFrames::ExposedAsCommanded;
    cfg.gec_paper.frames = PaperFrames::ExposedAsCommanded;
    for m in ExposureMethod::PAPER_CODE {
        v.push((build_controller(&cfg, m, limits, t0).unwrap(), true));
    }
    v
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn controllers_stay_finite_and_in_limits(
        frames in proptest::collection::vec((frame_strategy(), corners_strategy(), any::<bool>()), 1..8),
        limits in limits_strategy(),
        t0 in prop_oneof![Just(f64::NAN), -10.0f64..1e6],
    ) {
        let lo = limits.min_us;
        let hi = limits.effective_max_us().max(lo);
        for (mut c, only_commanded) in all_controllers(limits, t0) {
            let mut frame = Frame::new(0, 0);
            for ((w, h, fill), corners, at_commanded) in &frames {
                frame.resize(*w, *h);
                match fill {
                    Fill::Black => frame.data.fill(0),
                    Fill::White => frame.data.fill(255),
                    Fill::Noise(d) => frame.data.copy_from_slice(d),
                }
                frame.meta.exposure_us = if *at_commanded { c.commanded_us() } else { c.commanded_us() * 0.3 };
                let step = c.update(&frame, corners.as_ref());
                let t = step.exposure_us;
                prop_assert!(t.is_finite() && t >= lo && t <= hi, "{}: {t} outside [{lo}, {hi}]", c.method());
                prop_assert_eq!(t, c.commanded_us());
                prop_assert!(step.metric.is_nan() || step.metric.is_finite());
                if let Some(r) = step.roi {
                    prop_assert!(r.x + r.width <= *w && r.y + r.height <= *h, "{r:?} outside {w}x{h}");
                }
                if !*at_commanded && only_commanded {
                    prop_assert!(!step.used_frame, "{} used a frame not at its command", c.method());
                }
            }
            // A frame whose buffer is shorter than its size is skipped, not a panic.
            let mut broken = Frame::new(16, 16);
            broken.data.truncate(10);
            broken.meta.exposure_us = c.commanded_us();
            let s = c.update(&broken, Some(&[[2.0, 2.0], [12.0, 2.0], [12.0, 12.0], [2.0, 12.0]]));
            prop_assert!(!s.used_frame);
            c.reset(f64::NAN);
            prop_assert!(c.commanded_us() >= lo && c.commanded_us() <= hi);
        }
    }

    #[test]
    fn metric_is_finite_on_any_view(
        (w, h, fill) in frame_strategy(),
        p in 0.01f64..0.99,
        k in prop_oneof![Just(1u32), Just(3), Just(5), Just(7), Just(9)],
        gamma in 0.2f64..5.0,
    ) {
        let mut f = Frame::new(w, h);
        match fill {
            Fill::Black => f.data.fill(0),
            Fill::White => f.data.fill(255),
            Fill::Noise(d) => f.data.copy_from_slice(&d),
        }
        let r = Response::gamma(gamma).unwrap();
        let params = MetricParams { percentile: p, weight_power: k, ..MetricParams::default() };
        let mut gm = GradientMetric::new(&r, params);
        match gm.evaluate(f.view()) {
            None => prop_assert!(w < 3 || h < 3),
            Some(v) => {
                prop_assert!(v.m.is_finite() && v.m >= 0.0);
                prop_assert!(v.dm_dlnt.is_finite());
                prop_assert_eq!(v.pixels, (w as usize - 2) * (h as usize - 2));
            }
        }
    }
}
