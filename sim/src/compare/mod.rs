//! `markhold compare`: the paper's four experiments (static precision, motion tracking,
//! convergence, station keeping) in HIL, for every exposure method x lighting x seed.
//!
//! Every run is single-threaded and deterministic (lock-step HIL, seeded world); runs are
//! spread over threads with a shared work index, so the numbers do not depend on `jobs`.

mod metrics;
mod report;
mod run;
pub mod shard;

pub use metrics::*;
pub use report::*;
pub use run::*;

use crate::error::{ensure, SimError};
use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use serde::{Deserialize, Serialize};

use markhold_core::params::LoadedSite;

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
    pub fn validate(&self) -> Result<(), SimError> {
        ensure(
            self.seconds > 0.0 && self.seconds <= MAX_RUN_SECONDS,
            || SimError::Usage {
                reason: format!(
                    "--seconds {}: expected a positive number of simulated seconds, at most \
             {MAX_RUN_SECONDS} (an hour; each run keeps its series in memory)",
                    self.seconds
                ),
            },
        )?;
        ensure(!self.seeds.is_empty(), || SimError::Usage {
            reason: "--seeds 0: expected at least 1".to_string(),
        })?;
        ensure(self.seeds.len() <= MAX_SEEDS, || SimError::Usage {
            reason: format!("--seeds {}: expected at most {MAX_SEEDS}", self.seeds.len()),
        })?;
        ensure(!self.methods.is_empty(), || SimError::Usage {
            reason: "--methods: expected at least one".to_string(),
        })?;
        ensure(!self.lightings.is_empty(), || SimError::Usage {
            reason: "--lightings: expected at least one".to_string(),
        })?;
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
/// [`crate::stats`]) of a metric over seeds (defined values only).
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
        let m = crate::stats::mean_ci95(&v);
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
    pub claims: Vec<crate::claims::ClaimTest>,
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

/// One method x lighting x seed: the unit of a shard (its five runs belong together: the
/// convergence runs start from the static run's final exposure).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CaseKey {
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub seed: u64,
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
    pub shard: Option<shard::Shard>,
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
pub fn cli(args: CompareArgs) -> Result<(), SimError> {
    if let Some(CompareCommand::Merge { dirs, out }) = &args.command {
        let merged = shard::merge(dirs)?;
        let files = write_outputs(&merged, out)?;
        markhold_core::outln!(
            "markhold compare merge: {} cases from {} folder(s); wrote {} files to {}",
            merged.results.cases.len(),
            dirs.len(),
            files.len(),
            out.display()
        );
        for f in files {
            markhold_core::outln!("  {}", out.join(f).display());
        }
        return Ok(());
    }
    let Some(out_dir) = args.out.as_deref() else {
        return Err(SimError::Usage {
            reason: "--out DIR: required".to_string(),
        });
    };
    ensure((1..=MAX_SEEDS as u64).contains(&args.seeds), || {
        SimError::Usage {
            reason: format!("--seeds {}: expected 1..{MAX_SEEDS}", args.seeds),
        }
    })?;
    let site = markhold_core::params::load(&args.site)?;
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
        ensure(j > 0, || SimError::Usage {
            reason: "--jobs 0: expected at least 1".to_string(),
        })?;
        opts.jobs = j;
    }
    opts.validate()?;
    let bar = markhold_core::observe::bar_span(
        0,
        "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames, eta {eta}",
        args.quiet,
    );
    if let Some(shard) = args.shard {
        return shard::run_shard(&site, &opts, shard, out_dir, &bar);
    }
    let out = run_compare(&site, &opts, &bar)?;
    drop(bar); // clears the bar
    let files = write_outputs(&out, out_dir)?;
    markhold_core::outln!(
        "markhold compare: {} runs of {} s on {}; wrote {} files to {}",
        out.series.len(),
        opts.seconds,
        site.site.site.name,
        files.len(),
        out_dir.display()
    );
    for f in files {
        markhold_core::outln!("  {}", out_dir.join(f).display());
    }
    Ok(())
}
