//! `markhold compare`: the paper's four experiments (static precision, motion tracking,
//! convergence, station keeping) in HIL, for every exposure method x lighting x seed.
//!
//! Every run is single-threaded and deterministic (lock-step HIL, seeded world); runs are
//! spread over threads with a shared work index, so the numbers do not depend on `jobs`.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::Context;
use markhold_exposure::{ExposureMethod, METHODS};
use markhold_hil::scene::LightingScenario;
use markhold_hil::VehicleMotion;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use tracing::Span;
use tracing_indicatif::span_ext::IndicatifSpanExt;

use super::hil::{station_corners, station_frames_each, HilOptions, HilRun};
use super::summary::{convergence_frames, cov_det, first_within_frames, rms};
use crate::params::LoadedSite;
use crate::pipeline::Observers;

/// Relative band of "converged" (the 5%).
pub const CONVERGENCE_TOL: f64 = 0.05;
/// Factor of the too-long and too-short starts of the convergence experiment.
pub const CONVERGENCE_FACTOR: f64 = 10.0;
/// Ratio between neighbouring exposures of the sweep that finds a scene's optimum.
pub const OPTIMUM_SWEEP_RATIO: f64 = 1.03;
/// Frames rendered and searched at each exposure of that sweep.
pub const OPTIMUM_FRAMES: usize = 2;

/// The longest experiment run `compare` accepts, simulated seconds.
pub const MAX_RUN_SECONDS: f64 = 3600.0;
/// The most seeds a sweep runs (each is 5 runs per method and lighting).
pub const MAX_SEEDS: usize = 1000;

/// What to run.
#[derive(Debug, Clone)]
pub struct CompareOptions {
    pub seeds: Vec<u64>,
    /// Simulated seconds of each experiment run.
    pub seconds: f64,
    pub methods: Vec<ExposureMethod>,
    pub lightings: Vec<LightingScenario>,
    /// Worker threads (at least 1).
    pub jobs: usize,
}

impl Default for CompareOptions {
    fn default() -> Self {
        Self {
            seeds: vec![1],
            seconds: 60.0,
            methods: ExposureMethod::ALL.to_vec(),
            lightings: vec![
                LightingScenario::Adversarial,
                LightingScenario::Normal,
                LightingScenario::Low,
                LightingScenario::Caustics,
            ],
            jobs: std::thread::available_parallelism().map_or(1, |n| n.get()),
        }
    }
}

impl CompareOptions {
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.seconds > 0.0 && self.seconds <= MAX_RUN_SECONDS,
            "--seconds {}: expected a positive number of simulated seconds, at most \
             {MAX_RUN_SECONDS} (an hour; each run keeps its series in memory)",
            self.seconds
        );
        anyhow::ensure!(!self.seeds.is_empty(), "--seeds 0: expected at least 1");
        anyhow::ensure!(
            self.seeds.len() <= MAX_SEEDS,
            "--seeds {}: expected at most {MAX_SEEDS}",
            self.seeds.len()
        );
        anyhow::ensure!(!self.methods.is_empty(), "--methods: expected at least one");
        anyhow::ensure!(
            !self.lightings.is_empty(),
            "--lightings: expected at least one"
        );
        Ok(())
    }
}

/// The five HIL runs behind the four experiments.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunKind {
    /// Vehicle fixed on station.
    Static,
    /// Camera moved sideways at constant speed past the marker.
    Motion,
    /// Fixed on station, starting at 10x the static run's final exposure.
    ConvergenceLong,
    /// Fixed on station, starting at 1/10 of it.
    ConvergenceShort,
    /// The full loop from the site's initial offset.
    Station,
}

impl RunKind {
    /// The name in results.json and in log lines.
    pub fn name(self) -> &'static str {
        match self {
            Self::Static => "static",
            Self::Motion => "motion",
            Self::ConvergenceLong => "convergence_long",
            Self::ConvergenceShort => "convergence_short",
            Self::Station => "station",
        }
    }
}

/// One frame of a run, as the experiments need it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Sample {
    pub time_s: f64,
    /// Exposure commanded after this frame.
    pub exposure_us: f64,
    pub detected: bool,
    /// Measured marker position in the camera frame, metres.
    pub measured_m: Option<[f64; 3]>,
    /// True marker position in the camera frame, metres.
    pub truth_m: [f64; 3],
    /// True vehicle position in the marker frame, metres.
    pub vehicle_marker_m: [f64; 3],
    /// True vehicle-to-station distance, metres.
    pub station_error_m: f64,
}

/// The per-frame series of one run (kept for the plots; not in results.json, but in a
/// shard's file for the plots of the merge).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RunSeries {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub seed: u64,
    pub kind: RunKind,
    pub initial_exposure_us: f64,
    pub samples: Vec<Sample>,
    pub wall_seconds: f64,
    pub lockstep_timeouts: u64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StaticResult {
    pub frames: u64,
    pub detection_rate: f64,
    /// Determinant of the 3x3 covariance of the measured positions, m^6.
    pub position_cov_det_m6: Option<f64>,
    /// Largest distance between two measured positions.
    pub max_distance_m: Option<f64>,
    /// Mean measured minus true position, norm (bias of the pose estimate).
    pub mean_bias_m: Option<f64>,
    pub final_exposure_us: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct MotionResult {
    pub frames: u64,
    pub speed_mps: f64,
    pub span_m: f64,
    pub detection_rate: f64,
    /// Mean distance from each measured position to the true trajectory (the polyline of
    /// true positions): the paper's metric.
    pub mean_distance_to_trajectory_m: Option<f64>,
    /// Mean distance to the true position at the same frame (stricter: includes lag).
    pub mean_error_m: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ConvergenceStart {
    pub initial_exposure_us: f64,
    pub final_exposure_us: f64,
    /// Frames until the exposure stays within 5% of its final value.
    pub frames: u64,
    pub seconds: f64,
    /// Frames and seconds until the exposure is first within 5% of its final value.
    pub first_within_frames: u64,
    pub first_within_seconds: f64,
    /// Stayed in the band for at least the last second of the run.
    pub settled: bool,
    /// Crossed from above the band to below it (or back) at least twice.
    pub oscillates: bool,
    pub band_crossings: u64,
    /// Final exposure over the static run's final exposure: far from 1 when the method
    /// settled somewhere else (e.g. ran to a limit) instead of back where it belongs.
    pub final_over_reference: f64,
    pub detection_rate: f64,
    /// Against the scene's optimum (none: never, it was not there at the end of the run):
    /// frames until the exposure stays within 5 % of the argmax of M,
    pub frames_to_m_argmax: Option<u64>,
    /// ... until it stays where M is within 5 % of its best,
    pub frames_to_m_band: Option<u64>,
    /// ... until it stays where the swept detection rate is within 5 points of its best.
    pub frames_to_detection_band: Option<u64>,
    /// Final exposure over the argmax of M.
    pub final_over_m_argmax: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ConvergenceResult {
    /// The static run's final exposure: the reference the starts are 10x off.
    pub reference_exposure_us: f64,
    /// The scene's own optimum, from a sweep of the same view (whatever the method).
    pub optimum: SceneOptimum,
    pub from_long: ConvergenceStart,
    pub from_short: ConvergenceStart,
}

/// The optimum of a convergence run's scene (vehicle held on station, the case's
/// lighting and seed), from a sweep of the exposure over the camera's range in 3 % steps,
/// two frames at each, independent of any controller.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SceneOptimum {
    /// The exposure maximizing the paper's M (its published form: `G = Ix^2 + Iy^2`
    /// ranked by `G`, p 0.9, k 5, two frames' mean) on the marker's region by the paper's
    /// rule (corner box + 10 %), refined by a parabola in log exposure.
    pub m_argmax_us: f64,
    pub m_max: f64,
    /// Lowest and highest swept exposure where M is within 5 % of its best.
    pub m_band_us: [f64; 2],
    /// Best detection rate over the sweep (the loop's detector, full search).
    pub detection_best: f64,
    /// Lowest and highest swept exposure whose detection rate is within 5 points of the
    /// best; none when the marker is never detected.
    pub detection_band_us: Option<[f64; 2]>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StationResult {
    pub frames: u64,
    pub detection_rate: f64,
    /// Determinant of the covariance of the true vehicle positions (marker frame) over
    /// the last half of the run, m^6.
    pub position_cov_det_m6: Option<f64>,
    /// The same of the measured marker positions (camera frame), last half.
    pub measured_position_cov_det_m6: Option<f64>,
    /// Vehicle vs station, RMS over the last half.
    pub position_rms_m: f64,
    pub final_position_error_m: f64,
}

/// The four experiments for one method x lighting x seed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CaseResult {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub seed: u64,
    pub static_precision: StaticResult,
    pub motion_tracking: MotionResult,
    pub convergence: ConvergenceResult,
    pub station_keeping: StationResult,
    /// Frames the HIL vehicle stepped without its command (0 in a healthy run).
    pub lockstep_timeouts: u64,
}

/// Mean, sample standard deviation and 95 % confidence interval (Student t, see
/// [`super::stats`]) of a metric over seeds (defined values only).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Stat {
    pub mean: Option<f64>,
    pub sd: Option<f64>,
    /// 95 % confidence interval of the mean (needs two seeds).
    pub ci95_low: Option<f64>,
    pub ci95_high: Option<f64>,
    /// Seeds where the metric was defined.
    pub n: usize,
}

impl Stat {
    pub fn of(values: &[Option<f64>]) -> Self {
        let v: Vec<f64> = values.iter().flatten().copied().collect();
        let m = super::stats::mean_ci95(&v);
        Self {
            mean: m.map(|m| m.mean),
            sd: m.and_then(|m| m.sd),
            ci95_low: m.and_then(|m| m.ci95).map(|c| c.0),
            ci95_high: m.and_then(|m| m.ci95).map(|c| c.1),
            n: v.len(),
        }
    }

    /// Half-width of the 95 % interval.
    pub fn ci95_half(&self) -> Option<f64> {
        Some(0.5 * (self.ci95_high? - self.ci95_low?))
    }
}

/// Every metric of a method x lighting, over seeds, keyed `experiment.metric`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CaseStats {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub metrics: std::collections::BTreeMap<String, Stat>,
}

/// Wall time of one run (`timings.json`: not a function of the seed, so not in
/// results.json).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RunTiming {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub seed: u64,
    pub kind: RunKind,
    pub frames: u64,
    pub wall_seconds: f64,
}

/// `results.json`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CompareResults {
    pub site: String,
    pub site_file: String,
    pub width_px: u32,
    pub height_px: u32,
    pub fps: f64,
    pub seconds: f64,
    pub seeds: Vec<u64>,
    pub methods: Vec<ExposureMethod>,
    pub lightings: Vec<LightingScenario>,
    pub cases: Vec<CaseResult>,
    pub stats: Vec<CaseStats>,
    /// The paper's claims, each a paired comparison over seeds.
    pub claims: Vec<super::claims::ClaimTest>,
}

impl CompareResults {
    pub fn case_stats(&self, m: ExposureMethod, l: LightingScenario) -> Option<&CaseStats> {
        self.stats.iter().find(|s| s.method == m && s.lighting == l)
    }
}

/// Everything `compare` produced: the numbers, the series for the plots, wall times.
pub struct CompareOutput {
    pub results: CompareResults,
    pub series: Vec<RunSeries>,
    pub timings: Vec<RunTiming>,
}

/// One queued run.
#[derive(Debug, Clone, Copy)]
struct Job {
    method: ExposureMethod,
    lighting: LightingScenario,
    seed: u64,
    kind: RunKind,
    initial_exposure_us: Option<f64>,
}

/// Sideways traverse of the motion experiment: the marker centre crosses the middle 80%
/// of the image width at the station distance. Returns (span, speed).
pub fn motion_traverse(site: &LoadedSite, seconds: f64) -> (f64, f64) {
    let c = &site.calibration;
    let cam_x = site.t_vehicle_cam().translation.vector.x;
    let dist = (site.site.station.distance_m - cam_x).max(0.1);
    let half_w = dist * (c.cx.min(c.width as f64 - c.cx) / c.fx);
    let span = (2.0 * (0.8 * half_w - 0.5 * site.site.marker.size_m)).max(0.05);
    (span, span / seconds)
}

/// One method x lighting x seed: the unit of a shard (its five runs belong together: the
/// convergence runs start from the static run's final exposure).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CaseKey {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub seed: u64,
}

impl CompareOptions {
    /// Every case of the sweep, in the order of results.json (method, lighting, seed).
    pub fn cases(&self) -> Vec<CaseKey> {
        let mut v = Vec::new();
        for &method in &self.methods {
            for &lighting in &self.lightings {
                for &seed in &self.seeds {
                    v.push(CaseKey {
                        method,
                        lighting,
                        seed,
                    });
                }
            }
        }
        v
    }
}

/// What a set of cases produced: their results, the series the plots need, wall times.
pub struct CasesRun {
    pub cases: Vec<CaseResult>,
    pub series: Vec<RunSeries>,
    pub timings: Vec<RunTiming>,
}

/// Run every experiment; `progress` (a progress-bar span, or `Span::none()`) counts frames.
pub fn run_compare(
    site: &LoadedSite,
    opts: &CompareOptions,
    progress: &Span,
) -> anyhow::Result<CompareOutput> {
    let run = run_cases(site, opts, &opts.cases(), progress)?;
    let results = assemble(CompareHeader::of(site, opts), run.cases);
    Ok(CompareOutput {
        results,
        series: run.series,
        timings: run.timings,
    })
}

/// Run the five runs of each of `cases` (a whole sweep or one shard's slice of it).
pub fn run_cases(
    site: &LoadedSite,
    opts: &CompareOptions,
    cases: &[CaseKey],
    progress: &Span,
) -> anyhow::Result<CasesRun> {
    opts.validate()?;
    let fps = site.site.camera.fps;
    let frames = (opts.seconds * fps).round().max(1.0) as u64;
    let mut first = Vec::new();
    for c in cases {
        for kind in [RunKind::Static, RunKind::Motion, RunKind::Station] {
            first.push(Job {
                method: c.method,
                lighting: c.lighting,
                seed: c.seed,
                kind,
                initial_exposure_us: None,
            });
        }
    }
    progress.pb_set_length(frames * first.len() as u64 * 5 / 3);
    let mut series = run_jobs(site, opts, &first, frames, progress)?;

    // Convergence starts 10x off the exposure each method settled on in the static run.
    let limits = site.limits();
    let mut second = Vec::new();
    for s in series.iter().filter(|s| s.kind == RunKind::Static) {
        let reference = s.samples.last().map_or(f64::NAN, |x| x.exposure_us);
        for (kind, f) in [
            (RunKind::ConvergenceLong, CONVERGENCE_FACTOR),
            (RunKind::ConvergenceShort, 1.0 / CONVERGENCE_FACTOR),
        ] {
            second.push(Job {
                method: s.method,
                lighting: s.lighting,
                seed: s.seed,
                kind,
                initial_exposure_us: Some(limits.clamp(reference * f)),
            });
        }
    }
    series.extend(run_jobs(site, opts, &second, frames, progress)?);
    let optima = scene_optima(site, opts, cases)?;
    let results = case_results(site, opts, cases, &series, &optima)?;
    let timings = series
        .iter()
        .map(|s| RunTiming {
            method: s.method,
            lighting: s.lighting,
            seed: s.seed,
            kind: s.kind,
            frames: s.samples.len() as u64,
            wall_seconds: s.wall_seconds,
        })
        .collect();
    Ok(CasesRun {
        cases: results,
        series,
        timings,
    })
}

/// Run jobs on `opts.jobs` threads; results come back in job order.
fn run_jobs(
    site: &LoadedSite,
    opts: &CompareOptions,
    jobs: &[Job],
    frames: u64,
    progress: &Span,
) -> anyhow::Result<Vec<RunSeries>> {
    run_parallel(
        jobs,
        opts.jobs,
        |job| run_one(site, opts, job, frames, progress),
        |job| {
            format!(
                "{:?} run, method {}, lighting {}, seed {}",
                job.kind, job.method, job.lighting, job.seed
            )
        },
    )
}

/// Run `run` on every job on up to `workers` threads (a shared work index, so the
/// results do not depend on the thread count); results come back in job order. The
/// first error stops handing out work and is returned with `describe`'s context.
pub fn run_parallel<J: Sync, R: Send>(
    jobs: &[J],
    workers: usize,
    run: impl Fn(&J) -> anyhow::Result<R> + Sync,
    describe: impl Fn(&J) -> String,
) -> anyhow::Result<Vec<R>> {
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<anyhow::Result<R>>>> =
        Mutex::new((0..jobs.len()).map(|_| None).collect());
    let workers = workers.clamp(1, jobs.len().max(1));
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(job) = jobs.get(i) else { break };
                let r = run(job);
                let failed = r.is_err();
                if let Ok(mut o) = out.lock() {
                    o[i] = Some(r);
                }
                if failed {
                    // Stop handing out work: the first error is reported.
                    next.store(jobs.len(), Ordering::Relaxed);
                }
            });
        }
    });
    let out = out
        .into_inner()
        .map_err(|_| anyhow::anyhow!("a worker panicked"))?;
    let mut results = Vec::with_capacity(jobs.len());
    for (r, job) in out.into_iter().zip(jobs) {
        match r {
            Some(r) => results.push(r.with_context(|| describe(job))?),
            None => anyhow::bail!("a run was not executed (an earlier run failed)"),
        }
    }
    Ok(results)
}

fn run_one(
    site: &LoadedSite,
    opts: &CompareOptions,
    job: &Job,
    frames: u64,
    progress: &Span,
) -> anyhow::Result<RunSeries> {
    // Every log line of this run names it (the worker thread enters the span). Error level:
    // the span is there whatever the log level lets through.
    let span = tracing::error_span!(
        parent: None,
        "run",
        method = %job.method,
        lighting = %job.lighting,
        seed = job.seed,
        kind = %job.kind.name()
    );
    let _entered = span.enter();
    let wall = Instant::now();
    let mut site = site.clone();
    let mut hil = HilOptions {
        seconds: opts.seconds,
        seed: job.seed,
        exposure: Some(job.method),
        lighting: Some(job.lighting),
        initial_exposure_us: job.initial_exposure_us,
        ..HilOptions::default()
    };
    match job.kind {
        RunKind::Static | RunKind::ConvergenceLong | RunKind::ConvergenceShort => {
            hil.motion = VehicleMotion::Fixed;
            hil.start_on_station = true;
        }
        RunKind::Motion => {
            // Start half a span to the marker's left (the vehicle's left), move east: the
            // vehicle faces north, so its right is world +y (docs/frames.md).
            let (span, speed) = motion_traverse(&site, opts.seconds);
            site.site.station.lateral_m -= 0.5 * span;
            hil.motion = VehicleMotion::Kinematic {
                velocity_world_mps: [0.0, speed, 0.0],
            };
            hil.start_on_station = true;
        }
        RunKind::Station => {
            hil.motion = VehicleMotion::Free;
            hil.start_on_station = false;
        }
    }
    let mut run = HilRun::build(&site, &hil, Observers::new())?;
    let initial_exposure_us = run.pipeline.start().initial_exposure_us;
    run.arm(site.site.link.mode.ardusub())?;
    let t_marker_world = run.t_world_marker.inverse();
    let t_station_marker = run.t_marker_station.inverse();
    let mut samples = Vec::with_capacity(frames as usize);
    for _ in 0..frames {
        let (rec, truth) = run.step()?;
        let t_marker_vehicle = t_marker_world * truth.t_world_vehicle;
        let err = t_station_marker * t_marker_vehicle;
        samples.push(Sample {
            time_s: truth.time_s,
            exposure_us: rec.exposure.exposure_us,
            detected: rec.detected,
            measured_m: rec.t_cam_marker.map(|t| t.translation.vector.into()),
            truth_m: truth.t_cam_marker.translation.vector.into(),
            vehicle_marker_m: t_marker_vehicle.translation.vector.into(),
            station_error_m: err.translation.vector.norm(),
        });
        progress.pb_inc(1);
    }
    let now = run.rig.truth().time_s;
    run.pipeline.link_mut().send_neutral(now)?;
    Ok(RunSeries {
        method: job.method,
        lighting: job.lighting,
        seed: job.seed,
        kind: job.kind,
        initial_exposure_us,
        samples,
        wall_seconds: wall.elapsed().as_secs_f64(),
        lockstep_timeouts: run.rig.truth().lockstep_timeouts,
    })
}

fn v3(a: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(a[0], a[1], a[2])
}

fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

fn detection_rate(s: &[Sample]) -> f64 {
    s.iter().filter(|x| x.detected).count() as f64 / s.len().max(1) as f64
}

fn measured(s: &[Sample]) -> Vec<Vector3<f64>> {
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

fn static_result(s: &[Sample]) -> StaticResult {
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

fn motion_result(s: &[Sample], span_m: f64, speed_mps: f64) -> MotionResult {
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
fn in_band(t: f64, band: [f64; 2]) -> bool {
    let half = OPTIMUM_SWEEP_RATIO.sqrt();
    t >= band[0] / half && t <= band[1] * half
}

fn convergence_start(
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

fn station_result(s: &[Sample]) -> StationResult {
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
const OPTIMUM_REACH_KEYS: [[&str; 7]; 2] = [
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
fn optimum_reach(
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
fn case_results(
    site: &LoadedSite,
    opts: &CompareOptions,
    cases: &[CaseKey],
    series: &[RunSeries],
    optima: &[((LightingScenario, u64), SceneOptimum)],
) -> anyhow::Result<Vec<CaseResult>> {
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
            .with_context(|| {
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
            .with_context(|| format!("no optimum sweep for {} / seed {}", c.lighting, c.seed))?;
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

/// The scene optimum of every (lighting, seed) among `cases` (it does not depend on the
/// method, so each is swept once), on `opts.jobs` threads.
fn scene_optima(
    site: &LoadedSite,
    opts: &CompareOptions,
    cases: &[CaseKey],
) -> anyhow::Result<Vec<((LightingScenario, u64), SceneOptimum)>> {
    let mut keys: Vec<(LightingScenario, u64)> = Vec::new();
    for c in cases {
        if !keys.contains(&(c.lighting, c.seed)) {
            keys.push((c.lighting, c.seed));
        }
    }
    let optima = run_parallel(
        &keys,
        opts.jobs,
        |&(l, seed)| scene_optimum(site, l, seed),
        |&(l, seed)| format!("optimum sweep, lighting {l}, seed {seed}"),
    )?;
    Ok(keys.into_iter().zip(optima).collect())
}

/// The optimum of the still station view in `lighting` (see [`SceneOptimum`]).
pub fn scene_optimum(
    site: &LoadedSite,
    lighting: LightingScenario,
    seed: u64,
) -> anyhow::Result<SceneOptimum> {
    use markhold_exposure::{
        code_region, PaperMetric, PaperMetricEval, PaperMetricParams, Response,
    };
    let hil = HilOptions {
        lighting: Some(lighting),
        seed,
        ..HilOptions::default()
    };
    let light = super::hil::lighting_of(site, &hil);
    let limits = site.limits();
    let (lo, hi) = (limits.min_us, limits.effective_max_us());
    let mut exposures = Vec::new();
    let mut t = lo;
    while t <= hi * (1.0 + 1e-9) {
        exposures.push(t);
        t *= OPTIMUM_SWEEP_RATIO;
    }
    let repeated: Vec<f64> = exposures
        .iter()
        .flat_map(|&t| std::iter::repeat_n(t, OPTIMUM_FRAMES))
        .collect();
    let (w, h) = (site.calibration.width, site.calibration.height);
    let roi = station_corners(site)
        .and_then(|c| code_region(&c, 0.1, w, h))
        .context("the marker is not in the image from the station: no optimum to sweep")?;
    // M does not depend on the response (only its derivative does).
    let mut eval = PaperMetricEval::new(&Response::linear());
    let params = PaperMetricParams {
        metric: PaperMetric::Published,
        percentile: 0.9,
        weight_power: 5,
    };
    let mut tracker = markhold_vision::MarkerTracker::new(
        &site.site.marker,
        &site.site.vision,
        site.calibration.clone(),
    )?;
    let (mut m, mut det) = (Vec::new(), Vec::new());
    let (mut m_sum, mut det_sum, mut k) = (0.0, 0.0, 0usize);
    station_frames_each(site, seed, &light, &repeated, |f| {
        m_sum += eval
            .evaluate(f.view(), roi, f.meta.exposure_us.max(1.0), &params)
            .map_or(0.0, |v| v.m);
        tracker.reset();
        det_sum += f64::from(u8::from(tracker.process_full(f)?.is_some()));
        k += 1;
        if k == OPTIMUM_FRAMES {
            m.push(m_sum / k as f64);
            det.push(det_sum / k as f64);
            (m_sum, det_sum, k) = (0.0, 0.0, 0);
        }
        Ok(())
    })?;
    Ok(optimum_of(&exposures, &m, &det))
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

/// What a sweep ran, the head of results.json.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CompareHeader {
    pub site: String,
    pub site_file: String,
    pub width_px: u32,
    pub height_px: u32,
    pub fps: f64,
    pub seconds: f64,
    pub seeds: Vec<u64>,
    pub methods: Vec<ExposureMethod>,
    pub lightings: Vec<LightingScenario>,
}

impl CompareHeader {
    pub fn of(site: &LoadedSite, opts: &CompareOptions) -> Self {
        Self {
            site: site.site.site.name.clone(),
            site_file: site.path.display().to_string(),
            width_px: site.calibration.width,
            height_px: site.calibration.height,
            fps: site.site.camera.fps,
            seconds: opts.seconds,
            seeds: opts.seeds.clone(),
            methods: opts.methods.clone(),
            lightings: opts.lightings.clone(),
        }
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
    let claims = super::claims::tests(&h, &cases);
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

/// The paper's numbers for the report, from each method's row of
/// [`markhold_exposure::METHODS`].
mod paper {
    use markhold_exposure::ExposureMethod;
    use markhold_hil::scene::LightingScenario;

    /// Static marker in a river, 1 minute: det(cov) m^6, detection %, max distance m.
    pub fn static_precision(m: ExposureMethod) -> Option<(f64, f64, f64)> {
        m.info().paper.static_precision
    }

    /// Moving camera, adversarial light only: mean distance m, detection %.
    pub fn motion(m: ExposureMethod, l: LightingScenario) -> Option<String> {
        if l != LightingScenario::Adversarial {
            return None;
        }
        m.info().paper.motion_adversarial.map(str::to_string)
    }

    /// Convergence seconds (the paper's AAEC is momentum + RoI; no GEC or Default row).
    pub fn convergence_s(m: ExposureMethod, l: LightingScenario) -> Option<f64> {
        let row = m.info().paper.convergence_s?;
        match l {
            LightingScenario::Adversarial => Some(row[0]),
            LightingScenario::Normal => Some(row[1]),
            LightingScenario::Low => Some(row[2]),
            LightingScenario::Caustics => None,
        }
    }
}

/// How a metric is printed.
#[derive(Clone, Copy)]
enum Fmt {
    Percent,
    Sci,
    Metres,
    Seconds,
    Micros,
    Ratio,
    /// A 0/1 flag: the fraction of seeds where it was set.
    Flag,
}

fn fmt_value(v: f64, f: Fmt) -> String {
    match f {
        Fmt::Percent => format!("{:.1} %", 100.0 * v),
        Fmt::Sci => format!("{v:.2e}"),
        Fmt::Metres => format!("{v:.4}"),
        Fmt::Seconds => format!("{v:.2}"),
        Fmt::Micros => format!("{v:.0}"),
        Fmt::Ratio => format!("{v:.2}"),
        Fmt::Flag => {
            if v == 0.0 {
                "no".to_string()
            } else if v == 1.0 {
                "yes".to_string()
            } else {
                format!("{:.0} % of seeds", 100.0 * v)
            }
        }
    }
}

/// `mean ± h` over seeds, h the half-width of the 95 % interval (symmetric: Student t);
/// `-` where the metric is undefined (e.g. no detection).
fn fmt_stat(s: Option<&Stat>, f: Fmt) -> String {
    let Some(s) = s else { return "-".to_string() };
    match (s.mean, s.ci95_half(), f) {
        (None, _, _) => "-".to_string(),
        (Some(m), _, Fmt::Flag) => fmt_value(m, f),
        (Some(m), Some(h), _) => format!("{} ± {}", fmt_value(m, f), fmt_value(h, f)),
        (Some(m), None, _) => fmt_value(m, f),
    }
}

/// The paper's cell for a method, if it has one.
type PaperColumn<'a> = &'a dyn Fn(ExposureMethod) -> Option<String>;

/// One table: a row per method, the given metric columns, and an optional paper column.
fn table(
    out: &mut String,
    r: &CompareResults,
    l: LightingScenario,
    cols: &[(&str, &str, Fmt)],
    paper: Option<(&str, PaperColumn)>,
) {
    use std::fmt::Write as _;
    let mut head = String::from("| Method |");
    let mut rule = String::from("|---|");
    for (title, _, _) in cols {
        let _ = write!(head, " {title} |");
        rule.push_str("---|");
    }
    if let Some((title, _)) = &paper {
        let _ = write!(head, " {title} |");
        rule.push_str("---|");
    }
    let _ = writeln!(out, "{head}\n{rule}");
    for &m in &r.methods {
        let stats = r.case_stats(m, l);
        let _ = write!(out, "| {} |", m.label());
        for (_, key, f) in cols {
            let _ = write!(
                out,
                " {} |",
                fmt_stat(stats.and_then(|s| s.metrics.get(*key)), *f)
            );
        }
        if let Some((_, p)) = &paper {
            let _ = write!(out, " {} |", p(m).unwrap_or_else(|| "-".to_string()));
        }
        out.push('\n');
    }
    out.push('\n');
}

/// `report.md`: the four experiments laid out like the paper's tables, one block per
/// lighting, mean ± sample sd over seeds, the paper's numbers beside ours where it has them.
pub fn report_markdown(r: &CompareResults, plots: &[String]) -> String {
    let mut o = String::new();
    report_header(&mut o, r);
    report_static_precision(&mut o, r);
    report_motion_tracking(&mut o, r);
    report_convergence(&mut o, r);
    report_convergence_to_optimum(&mut o, r);
    report_station_keeping(&mut o, r);
    report_claims(&mut o, r);
    report_lockstep_timeouts(&mut o, r);
    report_plots(&mut o, plots);
    o
}

/// The title and what the cells mean.
fn report_header(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let seeds = r.seeds.len();
    // markhold's variants of published methods, and what each is.
    let variants: Vec<(&str, &str)> = METHODS
        .iter()
        .filter_map(|i| Some((i.label, i.variant_of?)))
        .collect();
    let _ = writeln!(o, "# markhold compare: {}\n", inline_text(&r.site));
    let _ = writeln!(
        o,
        "Site file `{}`, {}x{} px at {} fps, {} simulated seconds per run, seeds {:?}. \
         Cells are the mean over {} seed(s) ± the half-width of its 95 % confidence \
         interval (Student t with n - 1 degrees of freedom; none with one seed); `-` where \
         the metric is undefined (no detection). {} are the methods as the paper's code ran \
         them; {} are {}. The paper's numbers are from its own camera and water; ours are \
         from the HIL world.\n",
        inline_text(&r.site_file),
        r.width_px,
        r.height_px,
        r.fps,
        r.seconds,
        r.seeds,
        seeds,
        prose_list(METHODS.iter().filter(|i| i.paper_code).map(|i| i.label)),
        prose_list(variants.iter().map(|(label, _)| *label)),
        prose_list(variants.iter().map(|(_, what)| *what)),
    );
}

/// `a`, `a and b`, `a, b and c`.
fn prose_list<'a>(items: impl Iterator<Item = &'a str>) -> String {
    let items: Vec<&str> = items.collect();
    match items.split_last() {
        None => String::new(),
        Some((last, [])) => (*last).to_string(),
        Some((last, rest)) => format!("{} and {last}", rest.join(", ")),
    }
}

/// Text from a results file (a site's name, a path) for one line of Markdown: control
/// characters (newlines, escapes) shown escaped, backticks as quotes, at most 200
/// characters, so it cannot start a heading or leave its code span.
pub fn inline_text(s: &str) -> String {
    let mut out = String::with_capacity(s.len().min(200));
    for (n, c) in s.chars().enumerate() {
        if n == 200 {
            out.push_str("...");
            break;
        }
        match c {
            '`' => out.push('\''),
            c if c.is_control() => out.extend(c.escape_default()),
            c => out.push(c),
        }
    }
    out
}

/// Frames to reach the scene's optimum: the mean over the seeds that reach it ± its
/// interval, "never" when none does, and how many do when not all.
fn fmt_reach(stats: Option<&CaseStats>, frames_key: &str, seeds: usize) -> String {
    let Some(st) = stats.and_then(|s| s.metrics.get(frames_key)) else {
        return "-".to_string();
    };
    if st.n == 0 {
        return "never".to_string();
    }
    let cell = fmt_stat(Some(st), Fmt::Micros);
    if st.n < seeds {
        format!("{cell} ({} of {seeds} seeds)", st.n)
    } else {
        cell
    }
}

/// Section 3b: convergence against the scene's own optimum, a table per lighting.
fn report_convergence_to_optimum(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "### Convergence to the scene's optimum\n\nThe same runs against the optimum of \
         their scene, found by sweeping the exposure over the camera's range in 3 % steps \
         on the still station view (two frames each, whatever the method): the argmax of \
         the paper's M (its published form, G = Ix^2 + Iy^2 ranked by G, on the marker's \
         box + 10 %), the exposures where M is within 5 % of its best, and those whose \
         detection rate is within 5 points of the best. Frames until the exposure stays \
         within 5 % of the argmax / in the M band / in the detection band, mean over the \
         seeds that get there (never: no seed was there at the end of the run).\n"
    );
    let seeds = r.seeds.len();
    for &l in &r.lightings {
        let _ = writeln!(
            o,
            "#### Convergence to the optimum, {l} lighting\n\n| Method | argmax of M [us] | \
             From 10x long: to argmax | to M band | to detection band | final / argmax | \
             From 10x short: to argmax | to M band | to detection band | final / argmax |\n\
             |---|---|---|---|---|---|---|---|---|---|"
        );
        for &m in &r.methods {
            let st = r.case_stats(m, l);
            let get = |k: &str| fmt_stat(st.and_then(|s| s.metrics.get(k)), Fmt::Ratio);
            let _ = write!(
                o,
                "| {} | {} |",
                m.label(),
                fmt_stat(
                    st.and_then(|s| s.metrics.get("convergence.optimum.m_argmax_us")),
                    Fmt::Micros
                )
            );
            let never_seen = st
                .and_then(|s| s.metrics.get("convergence.optimum.detection_best"))
                .and_then(|s| s.mean)
                .is_some_and(|v| v == 0.0);
            for side in ["long", "short"] {
                for k in ["m_argmax", "m_band", "detection_band"] {
                    let key = format!("convergence.{side}.frames_to_{k}");
                    let cell = if k == "detection_band" && never_seen {
                        "no exposure detects".to_string()
                    } else {
                        fmt_reach(st, &key, seeds)
                    };
                    let _ = write!(o, " {cell} |");
                }
                let _ = write!(
                    o,
                    " {} |",
                    get(&format!("convergence.{side}.final_over_m_argmax"))
                );
            }
            o.push('\n');
        }
        o.push('\n');
    }
}

/// Section 1: static precision, a table per lighting.
fn report_static_precision(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 1. Static precision\n\nVehicle held fixed on station for {} s. det(cov): \
         determinant of the 3x3 covariance of the measured marker positions (camera frame, \
         m^6). Paper: a static marker in a river, 1 minute.\n",
        r.seconds
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Static precision, {l} lighting\n");
        let p = |m| {
            paper::static_precision(m)
                .map(|(d, rate, max)| format!("{d:.2e} / {rate} % / {max:.4} m"))
        };
        table(
            o,
            r,
            l,
            &[
                ("det(cov) [m^6]", "static.position_cov_det_m6", Fmt::Sci),
                ("Detection", "static.detection_rate", Fmt::Percent),
                ("Max distance [m]", "static.max_distance_m", Fmt::Metres),
                ("Mean bias [m]", "static.mean_bias_m", Fmt::Metres),
                (
                    "Final exposure [us]",
                    "static.final_exposure_us",
                    Fmt::Micros,
                ),
            ],
            Some(("Paper det / detection / max", &p)),
        );
    }
}

/// Section 2: motion tracking, the traverse, then a table per lighting.
fn report_motion_tracking(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 2. Motion tracking\n\nCamera moved sideways at constant speed so the marker \
         crosses the middle of the view. Distance to trajectory: mean distance from each \
         measured position to the polyline of true positions (the paper's metric); error: \
         to the true position of the same frame.\n"
    );
    if let Some(c) = r.cases.first() {
        let _ = writeln!(
            o,
            "Traverse {:.3} m at {:.4} m/s.\n",
            c.motion_tracking.span_m, c.motion_tracking.speed_mps
        );
    }
    for &l in &r.lightings {
        let _ = writeln!(o, "### Motion tracking, {l} lighting\n");
        let p = move |m| paper::motion(m, l);
        table(
            o,
            r,
            l,
            &[
                (
                    "Distance to trajectory [m]",
                    "motion.mean_distance_to_trajectory_m",
                    Fmt::Metres,
                ),
                ("Detection", "motion.detection_rate", Fmt::Percent),
                ("Same-frame error [m]", "motion.mean_error_m", Fmt::Metres),
            ],
            Some(("Paper distance / detection", &p)),
        );
    }
}

/// Section 3: convergence from 10x long and 10x short, a table per lighting.
fn report_convergence(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 3. Convergence\n\nVehicle fixed on station; exposure started at 10x and 1/10 of \
         the exposure the method settled on in the static run (clamped to the camera's \
         limits). Seconds until the exposure is first within 5% of the run's final value, and \
         until it stays there (an excursion after the first entry counts only in the \
         second); \
         settled: it stayed there for at least the last second; oscillates: it crossed the \
         band from one side to the other at least twice; final / reference: where it ended over \
         where the static run settled (1.00: back where it belongs; a method can also \
         settle, within 5%, at a camera limit). Paper: its AAEC with momentum and RoI, \
         AEC; it has no GEC or Default convergence numbers.\n"
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Convergence, {l} lighting\n");
        let p = move |m| paper::convergence_s(m, l).map(|s| format!("{s} s"));
        table(
            o,
            r,
            l,
            &[
                (
                    "From 10x long: first within [s]",
                    "convergence.long.first_within_seconds",
                    Fmt::Seconds,
                ),
                (
                    "From 10x long: stays within [s]",
                    "convergence.long.seconds",
                    Fmt::Seconds,
                ),
                ("Settled", "convergence.long.settled", Fmt::Flag),
                ("Oscillates", "convergence.long.oscillates", Fmt::Flag),
                (
                    "Final / reference",
                    "convergence.long.final_over_reference",
                    Fmt::Ratio,
                ),
                (
                    "From 10x short: first within [s]",
                    "convergence.short.first_within_seconds",
                    Fmt::Seconds,
                ),
                (
                    "From 10x short: stays within [s]",
                    "convergence.short.seconds",
                    Fmt::Seconds,
                ),
                ("Settled", "convergence.short.settled", Fmt::Flag),
                ("Oscillates", "convergence.short.oscillates", Fmt::Flag),
                (
                    "Final / reference",
                    "convergence.short.final_over_reference",
                    Fmt::Ratio,
                ),
            ],
            Some(("Paper [s]", &p)),
        );
    }
}

/// Section 4: station keeping with the full loop, a table per lighting.
fn report_station_keeping(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 4. Station keeping\n\nThe full loop from the site's initial offset for {} s. \
         det(cov): determinant of the covariance of the true vehicle position (marker \
         frame) over the last half; position RMS: vehicle to station, last half. Paper: \
         AAEC had the smallest determinant in all three lightings (no numbers quoted here).\n",
        r.seconds
    );
    for &l in &r.lightings {
        let _ = writeln!(o, "### Station keeping, {l} lighting\n");
        table(
            o,
            r,
            l,
            &[
                ("det(cov) [m^6]", "station.position_cov_det_m6", Fmt::Sci),
                ("Detection", "station.detection_rate", Fmt::Percent),
                ("Position RMS [m]", "station.position_rms_m", Fmt::Metres),
                (
                    "Measured det(cov) [m^6]",
                    "station.measured_position_cov_det_m6",
                    Fmt::Sci,
                ),
            ],
            None,
        );
    }
}

/// Section 5: the paper's claims, paired over seeds.
fn report_claims(o: &mut String, r: &CompareResults) {
    use super::claims::{Scale, Verdict};
    use std::fmt::Write as _;
    let _ = writeln!(
        o,
        "## 5. The paper's claims, paired over seeds\n\nEach AAEC against each other method \
         on the same seeds: the mean of the per-seed difference (AAEC - other; log10 for \
         determinants) with its 95 % confidence interval, and the two-sided paired-t p-value \
         of no difference. n: seeds where both have the metric; AAEC only / other only: \
         seeds where one of them has it (e.g. only it detects the marker). Holds: AAEC \
         better on average with p < 0.05, or it has the metric on every seed and the other \
         on none.\n"
    );
    if r.claims.is_empty() {
        let _ = writeln!(
            o,
            "No claim applies: the sweep needs an AAEC and another method in a paper \
             lighting.\n"
        );
        return;
    }
    let _ = writeln!(
        o,
        "| Claim | Lighting | AAEC | Other | n | AAEC only / other only | Mean difference [95 % CI] | p | Verdict |\n|---|---|---|---|---|---|---|---|---|"
    );
    for c in &r.claims {
        let unit = match c.scale {
            Scale::Log10 => " (log10)",
            Scale::Linear => "",
        };
        let diff = match (c.mean_diff, c.ci95_low, c.ci95_high) {
            (Some(d), Some(lo), Some(hi)) => format!("{d:.4} [{lo:.4}, {hi:.4}]{unit}"),
            (Some(d), _, _) => format!("{d:.4}{unit}"),
            _ => "-".to_string(),
        };
        let p = c.p.map_or("-".to_string(), |p| {
            if p < 1e-4 {
                format!("{p:.1e}")
            } else {
                format!("{p:.4}")
            }
        });
        let verdict = match c.verdict {
            Verdict::Holds => "holds",
            Verdict::NotSignificant => "not significant",
            Verdict::Against => "against",
            Verdict::Untested => "untested",
        };
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} | {} / {} | {diff} | {p} | {verdict} |",
            c.claim,
            c.lighting,
            c.method.label(),
            c.other.label(),
            c.n,
            c.method_only,
            c.other_only,
        );
    }
    o.push('\n');
}

/// The lock-step timeouts over all runs.
fn report_lockstep_timeouts(o: &mut String, r: &CompareResults) {
    use std::fmt::Write as _;
    let timeouts: u64 = r.cases.iter().map(|c| c.lockstep_timeouts).sum();
    let _ = writeln!(
        o,
        "Lock-step timeouts over all runs: {timeouts} (frames the simulated vehicle stepped \
         without its command; 0 in a healthy run).\n"
    );
}

/// Links to the plots, if any were written.
fn report_plots(o: &mut String, plots: &[String]) {
    use std::fmt::Write as _;
    if !plots.is_empty() {
        let _ = writeln!(o, "## Plots\n");
        for p in plots {
            let _ = writeln!(o, "- [{p}]({p})");
        }
    }
}

/// Write `results.json`, the plots and `report.md` into `dir` (created if missing).
/// Returns the files written, relative to `dir`.
pub fn write_outputs(out: &CompareOutput, dir: &std::path::Path) -> anyhow::Result<Vec<String>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating --out {}", dir.display()))?;
    let json = serde_json::to_string_pretty(&out.results)?;
    let p = dir.join("results.json");
    std::fs::write(&p, json + "\n").with_context(|| format!("writing {}", p.display()))?;
    let mut files = vec!["results.json".to_string()];
    let p = dir.join("timings.json");
    let t = serde_json::to_string_pretty(&out.timings)?;
    std::fs::write(&p, t + "\n").with_context(|| format!("writing {}", p.display()))?;
    files.push("timings.json".to_string());
    let plots = super::plots::write_plots(out, dir)?;
    let md = report_markdown(&out.results, &plots);
    let p = dir.join("report.md");
    std::fs::write(&p, md).with_context(|| format!("writing {}", p.display()))?;
    files.push("report.md".to_string());
    files.extend(plots);
    Ok(files)
}

/// `markhold compare` on the command line.
#[derive(Debug, Clone, clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct CompareArgs {
    #[command(subcommand)]
    pub command: Option<CompareCommand>,
    /// Dive-site file.
    #[arg(long, default_value = "params/pool.toml")]
    pub site: std::path::PathBuf,
    /// Number of seeds (1..=N) per method and lighting.
    #[arg(long, default_value_t = 1)]
    pub seeds: u64,
    /// Output folder: report.md, results.json, timings.json, plots (PNG and SVG); with
    /// --shard, shard-I-of-N.json only. (Required; optional here only because `merge`
    /// has its own.)
    #[arg(long, required = true)]
    pub out: Option<std::path::PathBuf>,
    /// Simulated seconds of each experiment run.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    #[arg(long, value_delimiter = ',', help = format!(
        "Exposure methods, comma-separated (default all: {})",
        ExposureMethod::names(",", ",")
    ))]
    pub methods: Vec<ExposureMethod>,
    /// Lightings, comma-separated (default all: adversarial,normal,low,caustics).
    #[arg(long, value_delimiter = ',')]
    pub lightings: Vec<LightingScenario>,
    /// Parallel runs (default: the number of cores).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Run only the I-th of N deterministic slices of the sweep (1 <= I <= N) and write
    /// DIR/shard-I-of-N.json; `markhold compare merge` makes the report from all N.
    #[arg(long, value_name = "I/N")]
    pub shard: Option<super::shard::Shard>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Debug, Clone, clap::Subcommand)]
pub enum CompareCommand {
    /// Merge the shard files (shard-I-of-N.json) of one sweep found in DIR... into the
    /// report.md, results.json and plots of the unsharded sweep.
    Merge {
        /// Folders holding the shard files (the --out of each `compare --shard`).
        #[arg(required = true)]
        dirs: Vec<std::path::PathBuf>,
        /// Output folder.
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

/// Run `markhold compare` and print where the outputs went.
pub fn cli(args: CompareArgs) -> anyhow::Result<()> {
    if let Some(CompareCommand::Merge { dirs, out }) = &args.command {
        let merged = super::shard::merge(dirs)?;
        let files = write_outputs(&merged, out)?;
        crate::outln!(
            "markhold compare merge: {} cases from {} folder(s); wrote {} files to {}",
            merged.results.cases.len(),
            dirs.len(),
            files.len(),
            out.display()
        );
        for f in files {
            crate::outln!("  {}", out.join(f).display());
        }
        return Ok(());
    }
    let Some(out_dir) = args.out.as_deref() else {
        anyhow::bail!("--out DIR: required");
    };
    anyhow::ensure!(
        (1..=MAX_SEEDS as u64).contains(&args.seeds),
        "--seeds {}: expected 1..{MAX_SEEDS}",
        args.seeds
    );
    let site = crate::params::load(&args.site)?;
    let mut opts = CompareOptions {
        seeds: (1..=args.seeds).collect(),
        seconds: args.seconds,
        ..CompareOptions::default()
    };
    if !args.methods.is_empty() {
        opts.methods = args.methods.clone();
    }
    if !args.lightings.is_empty() {
        opts.lightings = args.lightings.clone();
    }
    if let Some(j) = args.jobs {
        anyhow::ensure!(j > 0, "--jobs 0: expected at least 1");
        opts.jobs = j;
    }
    opts.validate()?;
    let bar = crate::observe::bar_span(
        0,
        "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames, eta {eta}",
        args.quiet,
    );
    if let Some(shard) = args.shard {
        return run_shard(&site, &opts, shard, out_dir, &bar);
    }
    let out = run_compare(&site, &opts, &bar)?;
    drop(bar); // clears the bar
    let files = write_outputs(&out, out_dir)?;
    crate::outln!(
        "markhold compare: {} runs of {} s on {}; wrote {} files to {}",
        out.series.len(),
        opts.seconds,
        site.site.site.name,
        files.len(),
        out_dir.display()
    );
    for f in files {
        crate::outln!("  {}", out_dir.join(f).display());
    }
    Ok(())
}

/// `--shard I/N`: run the slice, write DIR/shard-I-of-N.json.
fn run_shard(
    site: &LoadedSite,
    opts: &CompareOptions,
    shard: super::shard::Shard,
    dir: &std::path::Path,
    bar: &Span,
) -> anyhow::Result<()> {
    let sweep = super::shard::Sweep::of(site, opts)?;
    let cases = shard.cases(opts);
    let run = run_cases(site, opts, &cases, bar)?;
    let first_seed = opts.seeds.first().copied();
    let file = super::shard::ShardFile {
        format: super::shard::FORMAT,
        shard,
        sweep,
        cases: run.cases,
        series: run
            .series
            .into_iter()
            .filter(|s| Some(s.seed) == first_seed)
            .collect(),
        timings: run.timings,
    };
    let path = super::shard::write_shard(dir, &file)?;
    crate::outln!(
        "markhold compare --shard {shard}: {} of {} cases ({} runs of {} s) on {}; wrote {}",
        cases.len(),
        opts.cases().len(),
        5 * cases.len(),
        opts.seconds,
        site.site.site.name,
        path.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
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
