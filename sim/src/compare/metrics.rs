//! From a case's runs to its numbers: the paper's four experiments' metrics, the
//! scene optimum's reach, and the statistics over seeds of results.json.

use super::*;

use crate::error::{Required, SimError};
use markhold_hil::scene::LightingScenario;
use nalgebra::Vector3;

use crate::summary::{convergence_frames, cov_det, first_within_frames, rms};
use markhold_core::params::LoadedSite;

pub(super) fn v3(a: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(a[0], a[1], a[2])
}

pub(super) fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

pub(super) fn detection_rate(s: &[Sample]) -> f64 {
    s.iter().filter(|x| x.detected).count() as f64 / s.len().max(1) as f64
}

pub(super) fn measured(s: &[Sample]) -> Vec<Vector3<f64>> {
    s.iter()
        .filter_map(|x| x.measured_m.as_ref().map(v3))
        .collect()
}

/// Largest distance between two points (exact, O(n^2): a minute is 1800 points).
pub fn max_pairwise_distance(p: &[Vector3<f64>]) -> Option<f64> {
    if p.len() < 2 {
        return None;
    }
    let mut best = 0.0f64;
    for (i, a) in p.iter().enumerate() {
        for b in &p[i + 1..] {
            best = best.max((a - b).norm_squared());
        }
    }
    Some(best.sqrt())
}

/// Distance from a point to a polyline.
pub fn distance_to_polyline(p: &Vector3<f64>, line: &[Vector3<f64>]) -> f64 {
    match line {
        [] => f64::NAN,
        [only] => (p - only).norm(),
        _ => line
            .windows(2)
            .map(|w| {
                let d = w[1] - w[0];
                let len2 = d.norm_squared();
                let t = if len2 > 0.0 {
                    ((p - w[0]).dot(&d) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                (p - (w[0] + t * d)).norm()
            })
            .fold(f64::INFINITY, f64::min),
    }
}

/// Times the series goes from above the band around `last` to below it, or back.
pub fn band_crossings(series: &[f64], last: f64, tol: f64) -> u64 {
    let band = tol * last.abs();
    let mut side = 0i8;
    let mut n = 0;
    for v in series {
        let s = if *v > last + band {
            1
        } else if *v < last - band {
            -1
        } else {
            0
        };
        if s != 0 {
            if side != 0 && s != side {
                n += 1;
            }
            side = s;
        }
    }
    n
}

pub(super) fn static_result(s: &[Sample]) -> StaticResult {
    let m = measured(s);
    let bias = if m.is_empty() {
        None
    } else {
        let mut sum = Vector3::zeros();
        let mut n = 0.0;
        for x in s {
            if let Some(p) = &x.measured_m {
                sum += v3(p) - v3(&x.truth_m);
                n += 1.0;
            }
        }
        Some((sum / n).norm())
    };
    StaticResult {
        frames: s.len() as u64,
        detection_rate: detection_rate(s),
        position_cov_det_m6: finite(cov_det(&m)),
        max_distance_m: max_pairwise_distance(&m),
        mean_bias_m: bias,
        final_exposure_us: s.last().map_or(f64::NAN, |x| x.exposure_us),
    }
}

pub(super) fn motion_result(s: &[Sample], span_m: f64, speed_mps: f64) -> MotionResult {
    let truth: Vec<Vector3<f64>> = s.iter().map(|x| v3(&x.truth_m)).collect();
    let mut to_line = Vec::new();
    let mut same_time = Vec::new();
    for x in s {
        if let Some(p) = &x.measured_m {
            let p = v3(p);
            to_line.push(distance_to_polyline(&p, &truth));
            same_time.push((p - v3(&x.truth_m)).norm());
        }
    }
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    MotionResult {
        frames: s.len() as u64,
        speed_mps,
        span_m,
        detection_rate: detection_rate(s),
        mean_distance_to_trajectory_m: mean(&to_line),
        mean_error_m: mean(&same_time),
    }
}

/// Frames until `inside` holds for every remaining value of `series`; none when it does
/// not hold for the last.
pub fn frames_to_stay(series: &[f64], inside: impl Fn(f64) -> bool) -> Option<u64> {
    if !series.last().is_some_and(|&v| inside(v)) {
        return None;
    }
    Some(
        series
            .iter()
            .rposition(|&v| !inside(v))
            .map_or(0, |i| i as u64 + 1),
    )
}

/// `t` inside the swept band `[lo, hi]`, widened by half a sweep step each way.
pub(super) fn in_band(t: f64, band: [f64; 2]) -> bool {
    let half = OPTIMUM_SWEEP_RATIO.sqrt();
    t >= band[0] / half && t <= band[1] * half
}

pub(super) fn convergence_start(
    r: &RunSeries,
    fps: f64,
    reference_us: f64,
    opt: &SceneOptimum,
) -> ConvergenceStart {
    let e: Vec<f64> = r.samples.iter().map(|x| x.exposure_us).collect();
    let last = e.last().copied().unwrap_or(f64::NAN);
    let frames = convergence_frames(&e, CONVERGENCE_TOL);
    let first = first_within_frames(&e, CONVERGENCE_TOL);
    let crossings = band_crossings(&e, last, CONVERGENCE_TOL);
    let argmax = opt.m_argmax_us;
    ConvergenceStart {
        frames_to_m_argmax: frames_to_stay(&e, |t| (t / argmax - 1.0).abs() <= CONVERGENCE_TOL),
        frames_to_m_band: frames_to_stay(&e, |t| in_band(t, opt.m_band_us)),
        frames_to_detection_band: opt
            .detection_band_us
            .and_then(|b| frames_to_stay(&e, |t| in_band(t, b))),
        final_over_m_argmax: last / argmax,
        initial_exposure_us: r.initial_exposure_us,
        final_exposure_us: last,
        frames,
        seconds: frames as f64 / fps,
        first_within_frames: first,
        first_within_seconds: first as f64 / fps,
        settled: (e.len() as u64).saturating_sub(frames) as f64 >= fps,
        oscillates: crossings >= 2,
        band_crossings: crossings,
        final_over_reference: last / reference_us,
        detection_rate: detection_rate(&r.samples),
    }
}

pub(super) fn station_result(s: &[Sample]) -> StationResult {
    let half = &s[s.len() / 2..];
    let pos: Vec<Vector3<f64>> = half.iter().map(|x| v3(&x.vehicle_marker_m)).collect();
    let err: Vec<f64> = half.iter().map(|x| x.station_error_m).collect();
    StationResult {
        frames: s.len() as u64,
        detection_rate: detection_rate(s),
        position_cov_det_m6: finite(cov_det(&pos)),
        measured_position_cov_det_m6: finite(cov_det(&measured(half))),
        position_rms_m: rms(&err),
        final_position_error_m: s.last().map_or(f64::NAN, |x| x.station_error_m),
    }
}

/// Every metric of a case, keyed `experiment.metric` (the report's and the stats' keys).
pub fn metrics(c: &CaseResult) -> Vec<(&'static str, Option<f64>)> {
    let s = &c.static_precision;
    let m = &c.motion_tracking;
    let cv = &c.convergence;
    let st = &c.station_keeping;
    let b = |x: bool| Some(if x { 1.0 } else { 0.0 });
    let mut v = vec![
        ("static.detection_rate", Some(s.detection_rate)),
        ("static.position_cov_det_m6", s.position_cov_det_m6),
        ("static.max_distance_m", s.max_distance_m),
        ("static.mean_bias_m", s.mean_bias_m),
        ("static.final_exposure_us", finite(s.final_exposure_us)),
        ("motion.detection_rate", Some(m.detection_rate)),
        (
            "motion.mean_distance_to_trajectory_m",
            m.mean_distance_to_trajectory_m,
        ),
        ("motion.mean_error_m", m.mean_error_m),
        ("convergence.long.seconds", Some(cv.from_long.seconds)),
        ("convergence.long.frames", Some(cv.from_long.frames as f64)),
        (
            "convergence.long.first_within_seconds",
            Some(cv.from_long.first_within_seconds),
        ),
        ("convergence.long.settled", b(cv.from_long.settled)),
        ("convergence.long.oscillates", b(cv.from_long.oscillates)),
        (
            "convergence.long.final_over_reference",
            finite(cv.from_long.final_over_reference),
        ),
        ("convergence.short.seconds", Some(cv.from_short.seconds)),
        (
            "convergence.short.frames",
            Some(cv.from_short.frames as f64),
        ),
        (
            "convergence.short.first_within_seconds",
            Some(cv.from_short.first_within_seconds),
        ),
        ("convergence.short.settled", b(cv.from_short.settled)),
        ("convergence.short.oscillates", b(cv.from_short.oscillates)),
        (
            "convergence.short.final_over_reference",
            finite(cv.from_short.final_over_reference),
        ),
        (
            "convergence.optimum.m_argmax_us",
            finite(cv.optimum.m_argmax_us),
        ),
        (
            "convergence.optimum.detection_best",
            Some(cv.optimum.detection_best),
        ),
    ];
    for (start, keys) in [
        (&cv.from_long, OPTIMUM_REACH_KEYS[0]),
        (&cv.from_short, OPTIMUM_REACH_KEYS[1]),
    ] {
        v.extend(optimum_reach(start, keys));
    }
    v.extend([
        ("station.detection_rate", Some(st.detection_rate)),
        ("station.position_cov_det_m6", st.position_cov_det_m6),
        (
            "station.measured_position_cov_det_m6",
            st.measured_position_cov_det_m6,
        ),
        ("station.position_rms_m", finite(st.position_rms_m)),
        (
            "station.final_position_error_m",
            finite(st.final_position_error_m),
        ),
    ]);
    v
}

/// The keys of [`optimum_reach`], from the long start and from the short one.
pub(super) const OPTIMUM_REACH_KEYS: [[&str; 7]; 2] = [
    [
        "convergence.long.frames_to_m_argmax",
        "convergence.long.reaches_m_argmax",
        "convergence.long.frames_to_m_band",
        "convergence.long.reaches_m_band",
        "convergence.long.frames_to_detection_band",
        "convergence.long.reaches_detection_band",
        "convergence.long.final_over_m_argmax",
    ],
    [
        "convergence.short.frames_to_m_argmax",
        "convergence.short.reaches_m_argmax",
        "convergence.short.frames_to_m_band",
        "convergence.short.reaches_m_band",
        "convergence.short.frames_to_detection_band",
        "convergence.short.reaches_detection_band",
        "convergence.short.final_over_m_argmax",
    ],
];

/// How a start reached the scene's optimum: frames to each target and whether it did,
/// then its final exposure over the argmax of M.
pub(super) fn optimum_reach(
    c: &ConvergenceStart,
    keys: [&'static str; 7],
) -> [(&'static str, Option<f64>); 7] {
    let frames = |f: Option<u64>| f.map(|v| v as f64);
    let reached = |f: Option<u64>| Some(if f.is_some() { 1.0 } else { 0.0 });
    [
        (keys[0], frames(c.frames_to_m_argmax)),
        (keys[1], reached(c.frames_to_m_argmax)),
        (keys[2], frames(c.frames_to_m_band)),
        (keys[3], reached(c.frames_to_m_band)),
        (keys[4], frames(c.frames_to_detection_band)),
        (keys[5], reached(c.frames_to_detection_band)),
        (keys[6], finite(c.final_over_m_argmax)),
    ]
}

/// The results of each case from its five runs in `series`.
pub(super) fn case_results(
    site: &LoadedSite,
    opts: &CompareOptions,
    cases: &[CaseKey],
    series: &[RunSeries],
    optima: &[((LightingScenario, u64), SceneOptimum)],
) -> Result<Vec<CaseResult>, SimError> {
    let fps = site.site.camera.fps;
    let (span, speed) = motion_traverse(site, opts.seconds);
    let find = |c: &CaseKey, kind| {
        series
            .iter()
            .find(|s| {
                s.method == c.method
                    && s.lighting == c.lighting
                    && s.seed == c.seed
                    && s.kind == kind
            })
            .required(|| {
                format!(
                    "missing {kind:?} run for {} / {} / seed {}",
                    c.method, c.lighting, c.seed
                )
            })
    };
    let mut out = Vec::with_capacity(cases.len());
    for c in cases {
        let st = find(c, RunKind::Static)?;
        let long = find(c, RunKind::ConvergenceLong)?;
        let short = find(c, RunKind::ConvergenceShort)?;
        let static_precision = static_result(&st.samples);
        let reference = static_precision.final_exposure_us;
        let optimum = optima
            .iter()
            .find(|(k, _)| *k == (c.lighting, c.seed))
            .map(|(_, o)| o.clone())
            .required(|| format!("no optimum sweep for {} / seed {}", c.lighting, c.seed))?;
        out.push(CaseResult {
            method: c.method,
            lighting: c.lighting,
            seed: c.seed,
            convergence: ConvergenceResult {
                reference_exposure_us: reference,
                from_long: convergence_start(long, fps, reference, &optimum),
                from_short: convergence_start(short, fps, reference, &optimum),
                optimum,
            },
            static_precision,
            motion_tracking: motion_result(&find(c, RunKind::Motion)?.samples, span, speed),
            station_keeping: station_result(&find(c, RunKind::Station)?.samples),
            lockstep_timeouts: series
                .iter()
                .filter(|s| s.method == c.method && s.lighting == c.lighting && s.seed == c.seed)
                .map(|s| s.lockstep_timeouts)
                .sum(),
        });
    }
    Ok(out)
}

/// The optimum from a sweep: M and the detection rate at each exposure.
pub fn optimum_of(exposures: &[f64], m: &[f64], det: &[f64]) -> SceneOptimum {
    let best = (0..m.len())
        .max_by(|&a, &b| m[a].total_cmp(&m[b]))
        .unwrap_or(0);
    let m_max = m.get(best).copied().unwrap_or(f64::NAN);
    // A parabola through the best and its neighbours, in log exposure.
    let mut argmax = exposures.get(best).copied().unwrap_or(f64::NAN);
    if best > 0 && best + 1 < m.len() {
        let (a, b, c) = (m[best - 1], m[best], m[best + 1]);
        let den = a - 2.0 * b + c;
        if den < 0.0 {
            let step = OPTIMUM_SWEEP_RATIO.ln();
            let d = (0.5 * (a - c) / den).clamp(-1.0, 1.0);
            argmax *= (d * step).exp();
        }
    }
    let band = |ok: &dyn Fn(usize) -> bool| {
        let inside: Vec<f64> = (0..exposures.len())
            .filter(|&i| ok(i))
            .map(|i| exposures[i])
            .collect();
        Some([*inside.first()?, *inside.last()?])
    };
    let m_band = band(&|i| m[i] >= (1.0 - CONVERGENCE_TOL) * m_max).unwrap_or([argmax, argmax]);
    let det_best = det.iter().copied().fold(0.0, f64::max);
    SceneOptimum {
        m_argmax_us: argmax,
        m_max,
        m_band_us: m_band,
        detection_best: det_best,
        detection_band_us: if det_best > 0.0 {
            band(&|i| det[i] >= det_best - 0.05)
        } else {
            None
        },
    }
}

/// results.json from the cases of a sweep (in sweep order): the statistics over seeds and
/// the paired tests of the paper's claims. The one place both an unsharded run and a merge
/// of shards go through, so both give the same file.
pub fn assemble(h: CompareHeader, cases: Vec<CaseResult>) -> CompareResults {
    let mut stats = Vec::new();
    for &m in &h.methods {
        for &l in &h.lightings {
            let all: Vec<Vec<(&'static str, Option<f64>)>> = cases
                .iter()
                .filter(|c| c.method == m && c.lighting == l)
                .map(metrics)
                .collect();
            let mut map = std::collections::BTreeMap::new();
            if let Some(firstm) = all.first() {
                for (k, (key, _)) in firstm.iter().enumerate() {
                    let vals: Vec<Option<f64>> = all.iter().map(|v| v[k].1).collect();
                    map.insert((*key).to_string(), Stat::of(&vals));
                }
            }
            stats.push(CaseStats {
                method: m,
                lighting: l,
                metrics: map,
            });
        }
    }
    let claims = crate::claims::tests(&h, &cases);
    CompareResults {
        site: h.site,
        site_file: h.site_file,
        width_px: h.width_px,
        height_px: h.height_px,
        fps: h.fps,
        seconds: h.seconds,
        seeds: h.seeds,
        methods: h.methods,
        lightings: h.lightings,
        cases,
        stats,
        claims,
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    #[test]
    fn frames_to_stay_counts_to_the_last_excursion_and_says_never() {
        let inside = |t: f64| (t / 100.0 - 1.0).abs() <= 0.05;
        assert_eq!(
            frames_to_stay(&[300.0, 120.0, 101.0, 110.0, 99.0], inside),
            Some(4)
        );
        assert_eq!(frames_to_stay(&[100.0, 102.0], inside), Some(0));
        // Never there at the end: never, however close it came.
        assert_eq!(frames_to_stay(&[100.0, 101.0, 300.0], inside), None);
        // A frozen series far from the optimum.
        assert_eq!(frames_to_stay(&[1000.0; 50], inside), None);
        assert_eq!(frames_to_stay(&[], inside), None);
    }

    #[test]
    fn optimum_of_a_sweep_by_hand() {
        // M peaks between the third and fourth exposures (a parabola in log t through
        // 4, 9, 9: its vertex is half a step past the third), detection from the second.
        let r = OPTIMUM_SWEEP_RATIO;
        let e: Vec<f64> = (0..6).map(|k| 100.0 * r.powi(k)).collect();
        let m = [1.0, 4.0, 9.0, 9.0, 4.0, 1.0];
        let det = [0.0, 0.5, 1.0, 1.0, 0.97, 0.0];
        let o = optimum_of(&e, &m, &det);
        assert!(
            (o.m_argmax_us / (e[2] * r.sqrt()) - 1.0).abs() < 1e-9,
            "{o:?}"
        );
        assert_eq!(o.m_max, 9.0);
        assert_eq!(o.m_band_us, [e[2], e[3]]);
        assert_eq!(o.detection_best, 1.0);
        assert_eq!(o.detection_band_us, Some([e[2], e[4]]));
        // Never detected: no band.
        assert_eq!(optimum_of(&e, &m, &[0.0; 6]).detection_band_us, None);
        // The band is widened by half a step when a run is measured against it.
        assert!(in_band(e[2] / r.sqrt() * 1.001, o.m_band_us));
        assert!(!in_band(e[1], o.m_band_us));
    }

    #[test]
    fn crossings_count_overshoots() {
        // Monotone approach: no crossing.
        assert_eq!(band_crossings(&[10.0, 5.0, 2.0, 1.0, 1.0], 1.0, 0.05), 0);
        // One overshoot below, then back into the band.
        assert_eq!(band_crossings(&[10.0, 0.5, 1.0, 1.0], 1.0, 0.05), 1);
        // Ringing.
        assert_eq!(band_crossings(&[2.0, 0.5, 1.5, 0.8, 1.0], 1.0, 0.05), 3);
    }

    #[test]
    fn polyline_and_pairwise_distances() {
        let line = [Vector3::new(0.0, 0.0, 0.0), Vector3::new(1.0, 0.0, 0.0)];
        let d = distance_to_polyline(&Vector3::new(0.5, 0.3, 0.4), &line);
        assert!((d - 0.5).abs() < 1e-12);
        let d = distance_to_polyline(&Vector3::new(2.0, 0.0, 0.0), &line);
        assert!((d - 1.0).abs() < 1e-12);
        let p = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 3.0, 0.0),
            Vector3::new(0.0, 0.0, 4.0),
        ];
        assert_eq!(max_pairwise_distance(&p), Some(5.0));
        assert_eq!(max_pairwise_distance(&p[..1]), None);
    }

    #[test]
    fn stats_over_seeds() {
        let s = Stat::of(&[Some(1.0), None, Some(3.0)]);
        assert_eq!(s.n, 2);
        assert_eq!(s.mean, Some(2.0));
        assert!((s.sd.unwrap_or(0.0) - 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(Stat::of(&[None]).mean, None);
    }
}
