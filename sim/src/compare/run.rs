//! Running a sweep: its cases on threads, five HIL runs per case, and the scene's
//! exposure optimum per lighting and seed.

use super::*;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use crate::error::{Required, SimError, StepContext};
use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use markhold_hil::VehicleMotion;
use tracing::Span;
use tracing_indicatif::span_ext::IndicatifSpanExt;

use crate::hil::{station_corners, station_frames_each, HilOptions, HilRun};
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::Observers;

/// One queued run.
#[derive(Debug, Clone, Copy)]
pub(super) struct Job {
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
) -> Result<CompareOutput, SimError> {
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
) -> Result<CasesRun, SimError> {
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
pub(super) fn run_jobs(
    site: &LoadedSite,
    opts: &CompareOptions,
    jobs: &[Job],
    frames: u64,
    progress: &Span,
) -> Result<Vec<RunSeries>, SimError> {
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
    run: impl Fn(&J) -> Result<R, SimError> + Sync,
    describe: impl Fn(&J) -> String,
) -> Result<Vec<R>, SimError> {
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<Result<R, SimError>>>> =
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
    let out = out.into_inner().map_err(|_| SimError::Run {
        reason: "a worker panicked".to_string(),
    })?;
    let mut results = Vec::with_capacity(jobs.len());
    for (r, job) in out.into_iter().zip(jobs) {
        match r {
            Some(r) => results.push(r.step(|| describe(job))?),
            None => {
                return Err(SimError::Run {
                    reason: "a run was not executed (an earlier run failed)".to_string(),
                })
            }
        }
    }
    Ok(results)
}

pub(super) fn run_one(
    site: &LoadedSite,
    opts: &CompareOptions,
    job: &Job,
    frames: u64,
    progress: &Span,
) -> Result<RunSeries, SimError> {
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

/// A lighting and seed with its scene's optimum.
pub(super) type SceneOptimumOf = ((LightingScenario, u64), SceneOptimum);

/// The scene optimum of every (lighting, seed) among `cases` (it does not depend on the
/// method, so each is swept once), on `opts.jobs` threads.
pub(super) fn scene_optima(
    site: &LoadedSite,
    opts: &CompareOptions,
    cases: &[CaseKey],
) -> Result<Vec<SceneOptimumOf>, SimError> {
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
) -> Result<SceneOptimum, SimError> {
    use markhold_exposure::{
        code_region, PaperMetric, PaperMetricEval, PaperMetricParams, Response,
    };
    let hil = HilOptions {
        lighting: Some(lighting),
        seed,
        ..HilOptions::default()
    };
    let light = crate::hil::lighting_of(site, &hil);
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
        .required(|| {
            "the marker is not in the image from the station: no optimum to sweep".to_string()
        })?;
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
    station_frames_each::<SimError>(site, seed, &light, &repeated, |f| {
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
