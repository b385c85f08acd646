//! `markhold robustness`: the station keeper in HIL against a grid of model errors and
//! disturbances (thrust scale, ESC dead band, buoyancy, current, tether, telemetry
//! latency), with the site's own gains. Per cell: position RMS, the worst excursion and
//! the command's sign changes a second (chatter) over the last half of the run, and
//! whether it held (see [`Bounds`]). Runs go through compare's worker pool
//! ([`super::compare::run_parallel`]); every run is deterministic for its seed.

use std::path::Path;
use std::time::Instant;

use crate::error::{ensure, SimError, StepContext};
use serde::{Deserialize, Serialize};
use tracing::Span;
use tracing_indicatif::span_ext::IndicatifSpanExt;

use super::compare::run_parallel;
use super::hil::{HilOptions, HilRun};
use super::summary::rms;
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::Observers;

/// Direction the current flows toward in every cell, degrees from north: 45 degrees
/// between the line of sight (the vehicle faces north, toward the marker) and across it,
/// so that both horizontal axes have to hold against it.
pub const CURRENT_DIRECTION_DEG: f64 = 45.0;

/// Seconds at the end of a run over which the integrators' drift is measured.
pub const SETTLE_WINDOW_S: f64 = 5.0;

/// A cell's current change comes this far into the run (before the last half, which
/// is graded), as a fraction of it.
pub const CURRENT_CHANGE_AT: f64 = 0.3;

/// Settled: from the last disturbance onset (the start offset, or the current change)
/// the vehicle stays within this of its station to the end of the run, metres.
pub const SETTLE_BAND_M: f64 = 0.02;

/// One cell of the grid: the model errors and disturbances of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    pub name: String,
    /// Factor on every thruster's thrust (`vehicle.model_error.thrust_scale`).
    pub thrust_scale: f64,
    /// ESC dead band half width, us (`vehicle.thruster.dead_band_half_us`); the keeper
    /// keeps compensating the site's `link.thruster_deadband_us`.
    pub dead_band_half_us: f64,
    /// `vehicle.model_error.buoyancy_offset_n`.
    pub buoyancy_offset_n: f64,
    /// Current speed, m/s, toward [`CURRENT_DIRECTION_DEG`].
    pub current_mps: f64,
    /// The site's tether (or the default Fathom tether when the site has none).
    pub tether: bool,
    /// `vehicle.telemetry_latency_ms`.
    pub latency_ms: f64,
    /// Frame to thrust, milliseconds (`vehicle.delay`, its stages scaled to this sum).
    #[serde(default)]
    pub delay_ms: f64,
    /// Gusts: RMS of the water's horizontal gust speed, m/s (`vehicle.gust_std_mps` of
    /// this / sqrt 2 on each horizontal axis, half that vertically).
    #[serde(default)]
    pub gust_mps: f64,
    /// The current changes by this much, m/s toward [`CURRENT_DIRECTION_DEG`], at
    /// [`CURRENT_CHANGE_AT`] of the run.
    #[serde(default)]
    pub current_change_mps: f64,
}

impl Cell {
    /// The site's own vehicle: no model error, no current, no tether, no latency.
    pub fn nominal(site: &LoadedSite) -> Self {
        Self {
            name: "nominal".into(),
            thrust_scale: 1.0,
            dead_band_half_us: site.site.vehicle.thruster.dead_band_half_us,
            buoyancy_offset_n: 0.0,
            current_mps: 0.0,
            tether: false,
            latency_ms: 0.0,
            delay_ms: site.site.vehicle.delay.total_ms(),
            gust_mps: 0.0,
            current_change_mps: 0.0,
        }
    }

    /// The site with this cell's errors and disturbances, for a run of `seconds`.
    pub fn apply(&self, site: &LoadedSite, seconds: f64) -> LoadedSite {
        let mut s = site.clone();
        let v = &mut s.site.vehicle;
        v.model_error.thrust_scale = self.thrust_scale;
        v.model_error.buoyancy_offset_n = self.buoyancy_offset_n;
        v.thruster.dead_band_half_us = self.dead_band_half_us;
        let (sn, cs) = CURRENT_DIRECTION_DEG.to_radians().sin_cos();
        v.current_mps = [self.current_mps * cs, self.current_mps * sn, 0.0];
        v.tether = if self.tether {
            Some(site.site.vehicle.tether.unwrap_or_default())
        } else {
            None
        };
        v.telemetry_latency_ms = self.latency_ms;
        v.delay = v.delay.scaled_to(self.delay_ms);
        let axis = self.gust_mps / std::f64::consts::SQRT_2;
        v.gust_std_mps = [axis, axis, 0.5 * axis];
        v.current_change_mps = [
            self.current_change_mps * cs,
            self.current_change_mps * sn,
            0.0,
        ];
        v.current_change_at_s = self.change_at_s(seconds);
        s
    }

    /// When this cell's current changes in a run of `seconds` (0 when it does not).
    pub fn change_at_s(&self, seconds: f64) -> f64 {
        if self.current_change_mps != 0.0 {
            CURRENT_CHANGE_AT * seconds
        } else {
            0.0
        }
    }
}

/// The default grid: the nominal cell, each error alone at both ends of its range
/// (one-at-a-time), and the three worst corners (everything against the keeper at once:
/// weak thrust with the widest dead band, strong thrust with the narrowest, each with
/// the strongest current, the tether and the longest latency, and the buoyancy both
/// ways). 15 runs instead of a full factorial's 2^6 x 3 = 192: the one-at-a-time cells
/// say which error costs what, the corners whether they add up to a failure.
pub fn default_grid(site: &LoadedSite) -> Vec<Cell> {
    let n = Cell::nominal(site);
    let mut cells = vec![n.clone()];
    let one = |name: &str, f: &dyn Fn(&mut Cell)| {
        let mut c = n.clone();
        c.name = name.to_string();
        f(&mut c);
        c
    };
    cells.push(one("thrust-0.8", &|c| c.thrust_scale = 0.8));
    cells.push(one("thrust-1.2", &|c| c.thrust_scale = 1.2));
    cells.push(one("deadband-20us", &|c| c.dead_band_half_us = 20.0));
    cells.push(one("deadband-45us", &|c| c.dead_band_half_us = 45.0));
    cells.push(one("buoyancy-minus-3n", &|c| c.buoyancy_offset_n = -3.0));
    cells.push(one("buoyancy-plus-3n", &|c| c.buoyancy_offset_n = 3.0));
    cells.push(one("current-0.1", &|c| c.current_mps = 0.1));
    cells.push(one("current-0.2", &|c| c.current_mps = 0.2));
    cells.push(one("tether", &|c| c.tether = true));
    cells.push(one("latency-50ms", &|c| c.latency_ms = 50.0));
    cells.push(one("latency-100ms", &|c| c.latency_ms = 100.0));
    cells.push(one("delay-0ms", &|c| c.delay_ms = 0.0));
    cells.push(one("delay-150ms", &|c| c.delay_ms = 150.0));
    cells.push(one("delay-300ms", &|c| c.delay_ms = 300.0));
    cells.push(one("gust-0.1", &|c| c.gust_mps = 0.1));
    cells.push(one("current-change-0.1", &|c| c.current_change_mps = 0.1));
    let worst = |name: &str, thrust: f64, band: f64, buoy: f64| {
        one(name, &|c| {
            c.thrust_scale = thrust;
            c.dead_band_half_us = band;
            c.buoyancy_offset_n = buoy;
            c.current_mps = 0.2;
            c.tether = true;
            c.latency_ms = 100.0;
        })
    };
    cells.push(worst("worst-weak-sinking", 0.8, 45.0, -3.0));
    cells.push(worst("worst-weak-floating", 0.8, 45.0, 3.0));
    cells.push(worst("worst-strong-narrow", 1.2, 20.0, 3.0));
    cells
}

/// What "held" means: over the last half of the run (after the start offset has been
/// taken out), ground truth, vehicle to station.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    /// Position RMS at most this, metres.
    pub rms_m: f64,
    /// Largest distance from the station at most this, metres.
    pub excursion_m: f64,
    /// The marker detected in at least this fraction of the frames.
    pub detection: f64,
}

impl Default for Bounds {
    fn default() -> Self {
        Self {
            rms_m: 0.05,
            excursion_m: 0.10,
            detection: 0.9,
        }
    }
}

/// The figures of one cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellResult {
    pub cell: Cell,
    pub frames: u64,
    /// Marker detections, last half.
    pub detection_rate: f64,
    /// Vehicle to station, RMS over the last half, metres.
    pub position_rms_m: f64,
    /// Largest vehicle-to-station distance over the last half, metres.
    pub worst_excursion_m: f64,
    pub final_error_m: f64,
    /// Seconds from the last disturbance onset (the start, or the current change) until
    /// the vehicle stays within [`SETTLE_BAND_M`] of its station to the end; `None` when
    /// it never does.
    #[serde(default)]
    pub settling_s: Option<f64>,
    /// Sign changes a second of the keeper's command per axis (surge, sway, heave, roll,
    /// pitch, yaw), last half; commands under the link's `effort_epsilon` count as none.
    pub chatter_hz: [f64; 6],
    /// The largest of `chatter_hz`.
    pub chatter_max_hz: f64,
    /// The keeper's integral terms at the end (effort).
    pub final_integrals: [f64; 6],
    /// Range (max - min) of each integral term over the last [`SETTLE_WINDOW_S`].
    pub integral_drift: [f64; 6],
    pub held: bool,
    /// Why not, when it did not hold.
    pub failed: Vec<String>,
    pub wall_seconds: f64,
}

/// Sign changes of `v` a second over `seconds`: values under `epsilon` in magnitude are
/// no command and do not break a run of one sign.
pub fn sign_changes_per_s(v: &[f64], epsilon: f64, seconds: f64) -> f64 {
    let mut last = 0.0f64;
    let mut n = 0u64;
    for &x in v {
        if !x.is_finite() || x.abs() < epsilon {
            continue;
        }
        let s = x.signum();
        if last != 0.0 && s != last {
            n += 1;
        }
        last = s;
    }
    if seconds > 0.0 {
        n as f64 / seconds
    } else {
        0.0
    }
}

/// Seconds from `onset_s` until `err` (at `time`) stays within `band` to the end: `None`
/// when the last sample is outside it.
pub fn settling_time(time: &[f64], err: &[f64], onset_s: f64, band: f64) -> Option<f64> {
    let last_out = time
        .iter()
        .zip(err)
        .rposition(|(&t, &e)| t >= onset_s && (e.is_nan() || e > band));
    match last_out {
        None => Some(0.0),
        Some(i) if i + 1 < time.len() => Some(time[i + 1] - onset_s),
        Some(_) => None,
    }
}

/// Run one cell: the site with the cell applied, from the site's start offset.
pub fn run_cell(
    site: &LoadedSite,
    cell: &Cell,
    seconds: f64,
    seed: u64,
    bounds: &Bounds,
    progress: &Span,
) -> Result<CellResult, SimError> {
    let span = tracing::error_span!(parent: None, "cell", name = %cell.name);
    let _entered = span.enter();
    let wall = Instant::now();
    let site = cell.apply(site, seconds);
    let opts = HilOptions {
        seconds,
        seed,
        ..HilOptions::default()
    };
    let mut run = HilRun::build(&site, &opts, Observers::new())?;
    run.arm(site.site.link.mode.ardusub())?;
    let frames = (seconds * site.site.camera.fps).round().max(1.0) as usize;
    let t_marker_world = run.t_world_marker.inverse();
    let t_station_marker = run.t_marker_station.inverse();
    let mut time = Vec::with_capacity(frames);
    let mut err = Vec::with_capacity(frames);
    let mut detected = Vec::with_capacity(frames);
    let mut effort = Vec::with_capacity(frames);
    let mut integrals = Vec::with_capacity(frames);
    for _ in 0..frames {
        let (rec, truth) = run.step()?;
        let e = t_station_marker * t_marker_world * truth.t_world_vehicle;
        time.push(truth.time_s);
        err.push(e.translation.vector.norm());
        detected.push(rec.detected);
        effort.push(rec.effort.to_array());
        integrals.push(run.pipeline.keeper_integrals());
        progress.pb_inc(1);
    }
    let now = run.rig.truth().time_s;
    run.pipeline.link_mut().send_neutral(now)?;

    let half = frames / 2;
    let tail = &err[half..];
    let tail_s =
        (time.last().copied().unwrap_or(0.0) - time.get(half).copied().unwrap_or(0.0)).max(1e-9);
    let detection_rate =
        detected[half..].iter().filter(|d| **d).count() as f64 / tail.len().max(1) as f64;
    let position_rms_m = rms(tail);
    let worst_excursion_m = tail.iter().copied().fold(0.0, f64::max);
    let eps = site.site.link.effort_epsilon;
    let chatter_hz = [0, 1, 2, 3, 4, 5].map(|a| {
        let v: Vec<f64> = effort[half..].iter().map(|e| e[a]).collect();
        sign_changes_per_s(&v, eps, tail_s)
    });
    let settle = ((SETTLE_WINDOW_S * site.site.camera.fps).round() as usize).min(frames);
    let window = &integrals[frames - settle..];
    let integral_drift = [0, 1, 2, 3, 4, 5].map(|a| {
        let (lo, hi) = window
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), i| {
                (lo.min(i[a]), hi.max(i[a]))
            });
        if hi >= lo {
            hi - lo
        } else {
            0.0
        }
    });
    let mut failed = Vec::new();
    if detection_rate < bounds.detection {
        failed.push(format!(
            "detection {:.1} % < {:.0} %",
            detection_rate * 100.0,
            bounds.detection * 100.0
        ));
    }
    if position_rms_m.is_nan() || position_rms_m > bounds.rms_m {
        failed.push(format!(
            "position RMS {:.1} mm > {:.0} mm",
            position_rms_m * 1e3,
            bounds.rms_m * 1e3
        ));
    }
    if worst_excursion_m.is_nan() || worst_excursion_m > bounds.excursion_m {
        failed.push(format!(
            "worst excursion {:.1} mm > {:.0} mm",
            worst_excursion_m * 1e3,
            bounds.excursion_m * 1e3
        ));
    }
    // The change is at that simulation time; without one, the run's first frame.
    let onset_s = time
        .first()
        .copied()
        .unwrap_or(0.0)
        .max(cell.change_at_s(seconds));
    let settling_s = settling_time(&time, &err, onset_s, SETTLE_BAND_M);
    Ok(CellResult {
        cell: cell.clone(),
        frames: frames as u64,
        settling_s,
        detection_rate,
        position_rms_m,
        worst_excursion_m,
        final_error_m: err.last().copied().unwrap_or(f64::NAN),
        chatter_max_hz: chatter_hz.iter().copied().fold(0.0, f64::max),
        chatter_hz,
        final_integrals: integrals.last().copied().unwrap_or([0.0; 6]),
        integral_drift,
        held: failed.is_empty(),
        failed,
        wall_seconds: wall.elapsed().as_secs_f64(),
    })
}

/// `results.json`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RobustnessResults {
    pub site: String,
    pub site_file: String,
    pub seconds: f64,
    pub seed: u64,
    pub current_direction_deg: f64,
    pub bounds: Bounds,
    pub cells: Vec<CellResult>,
    /// Every cell held.
    pub all_held: bool,
    /// The largest position RMS and worst excursion over the cells, as fractions of
    /// their bounds (the margins are 1 minus these).
    pub rms_used: f64,
    pub excursion_used: f64,
}

/// The longest cell `robustness` runs, simulated seconds: each cell keeps its per-frame
/// series (about 120 bytes a frame), so an hour at 30 fps is 13 MB per running cell.
pub const MAX_CELL_SECONDS: f64 = 3600.0;

/// Run `cells` on `jobs` threads.
pub fn run_robustness(
    site: &LoadedSite,
    cells: &[Cell],
    seconds: f64,
    seed: u64,
    jobs: usize,
    progress: &Span,
) -> Result<RobustnessResults, SimError> {
    ensure(seconds > 0.0 && seconds <= MAX_CELL_SECONDS, || {
        SimError::Usage {
            reason: format!(
                "--seconds {seconds}: expected a positive number of simulated seconds, at most \
         {MAX_CELL_SECONDS} (an hour; each cell keeps its series in memory)"
            ),
        }
    })?;
    ensure(!cells.is_empty(), || SimError::Run {
        reason: "no cells to run".to_string(),
    })?;
    let bounds = Bounds::default();
    let frames = (seconds * site.site.camera.fps).round().max(1.0) as u64;
    progress.pb_set_length(frames * cells.len() as u64);
    let results = run_parallel(
        cells,
        jobs,
        |c| run_cell(site, c, seconds, seed, &bounds, progress),
        |c| format!("robustness cell {}", c.name),
    )?;
    let rms_used = results
        .iter()
        .map(|r| r.position_rms_m / bounds.rms_m)
        .fold(0.0, f64::max);
    let excursion_used = results
        .iter()
        .map(|r| r.worst_excursion_m / bounds.excursion_m)
        .fold(0.0, f64::max);
    Ok(RobustnessResults {
        site: site.site.site.name.clone(),
        site_file: site.path.display().to_string(),
        seconds,
        seed,
        current_direction_deg: CURRENT_DIRECTION_DEG,
        bounds,
        all_held: results.iter().all(|r| r.held),
        cells: results,
        rms_used,
        excursion_used,
    })
}

/// report.md: the grid as a table.
pub fn report_md(r: &RobustnessResults) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let b = &r.bounds;
    let _ = writeln!(
        s,
        "# Robustness: {} ({})\n\n{} s a cell, seed {}, current toward {} degrees. Held: \
         over the last half, position RMS <= {:.0} mm, worst excursion <= {:.0} mm, \
         detection >= {:.0} %. Settled: seconds from the start (or the current change, at \
         {:.0} % of the run) until the vehicle stays within {:.0} mm of its station. Chatter: sign changes a second of the keeper's command, \
         largest axis (axis order surge, sway, heave, roll, pitch, yaw).\n",
        r.site,
        r.site_file,
        r.seconds,
        r.seed,
        r.current_direction_deg,
        b.rms_m * 1e3,
        b.excursion_m * 1e3,
        b.detection * 100.0,
        CURRENT_CHANGE_AT * 100.0,
        SETTLE_BAND_M * 1e3
    );
    let _ = writeln!(
        s,
        "| cell | thrust | dead band | buoyancy | current | tether | telemetry | frame to thrust | gusts | current change | RMS | worst | settled | chatter | held |"
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for c in &r.cells {
        let k = &c.cell;
        let _ = writeln!(
            s,
            "| {} | {:.2} | {:.0} us | {:+.1} N | {:.2} m/s | {} | {:.0} ms | {:.0} ms | {:.2} m/s | {:+.2} m/s | {:.1} mm | {:.1} mm | {} | {:.2}/s | {} |",
            k.name,
            k.thrust_scale,
            k.dead_band_half_us,
            k.buoyancy_offset_n,
            k.current_mps,
            if k.tether { "on" } else { "off" },
            k.latency_ms,
            k.delay_ms,
            k.gust_mps,
            k.current_change_mps,
            c.position_rms_m * 1e3,
            c.worst_excursion_m * 1e3,
            c.settling_s
                .map_or_else(|| "never".to_string(), |t| format!("{t:.1} s")),
            c.chatter_max_hz,
            if c.held {
                "yes".to_string()
            } else {
                format!("no: {}", c.failed.join("; "))
            }
        );
    }
    let _ = writeln!(
        s,
        "\n{} of {} cells held. Largest position RMS: {:.0} % of its bound; largest \
         excursion: {:.0} % of its bound.",
        r.cells.iter().filter(|c| c.held).count(),
        r.cells.len(),
        r.rms_used * 100.0,
        r.excursion_used * 100.0
    );
    s
}

/// report.md, results.json and the heat map (PNG and SVG) into `dir`.
pub fn write_outputs(r: &RobustnessResults, dir: &Path) -> Result<Vec<String>, SimError> {
    std::fs::create_dir_all(dir).step(|| format!("creating {}", dir.display()))?;
    let json = serde_json::to_string_pretty(r)?;
    let p = dir.join("results.json");
    std::fs::write(&p, json).step(|| format!("writing {}", p.display()))?;
    let p = dir.join("report.md");
    std::fs::write(&p, report_md(r)).step(|| format!("writing {}", p.display()))?;
    let mut files = vec!["report.md".to_string(), "results.json".to_string()];
    files.extend(super::robustness_plot::write_heat_map(r, dir)?);
    Ok(files)
}

/// `markhold robustness`.
#[derive(clap::Args, Debug)]
pub struct RobustnessArgs {
    /// Dive-site file (its gains are the ones under test).
    #[arg(long, default_value = "params/pool.toml")]
    pub site: std::path::PathBuf,
    /// Output folder: report.md, results.json, heat_map.png and heat_map.svg.
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// Simulated seconds of each cell.
    #[arg(long, default_value_t = 40.0)]
    pub seconds: f64,
    /// World seed of every cell.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only these cells of the default grid, comma-separated names (default all).
    #[arg(long, value_delimiter = ',')]
    pub cells: Vec<String>,
    /// Parallel runs (default: the number of cores).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Run `markhold robustness`; exit code 1 (an error) when a cell did not hold.
pub fn cli(args: RobustnessArgs) -> Result<(), SimError> {
    let site = markhold_core::params::load(&args.site)?;
    let mut cells = default_grid(&site);
    if !args.cells.is_empty() {
        for name in &args.cells {
            ensure(cells.iter().any(|c| &c.name == name), || SimError::Usage {
                reason: format!(
                    "--cells {name}: no such cell; the grid has {}",
                    cells
                        .iter()
                        .map(|c| c.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            })?;
        }
        cells.retain(|c| args.cells.contains(&c.name));
    }
    let jobs = match args.jobs {
        Some(0) => {
            return Err(SimError::Usage {
                reason: "--jobs 0: expected at least 1".to_string(),
            })
        }
        Some(j) => j,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let bar = markhold_core::observe::bar_span(
        0,
        "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames, eta {eta}",
        args.quiet,
    );
    let r = run_robustness(&site, &cells, args.seconds, args.seed, jobs, &bar)?;
    drop(bar);
    let files = write_outputs(&r, &args.out)?;
    markhold_core::outln!(
        "markhold robustness: {} of {} cells held on {} ({} s each); wrote {} files to {}",
        r.cells.iter().filter(|c| c.held).count(),
        r.cells.len(),
        r.site,
        r.seconds,
        files.len(),
        args.out.display()
    );
    for c in r.cells.iter().filter(|c| !c.held) {
        markhold_core::outln!("  {} did not hold: {}", c.cell.name, c.failed.join("; "));
    }
    ensure(r.all_held, || SimError::Run {
        reason: format!(
            "not every cell held (see {})",
            args.out.join("report.md").display()
        ),
    })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settling_is_the_time_from_onset_to_staying_inside_the_band() {
        let t = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0];
        let e = [0.3, 0.1, 0.01, 0.03, 0.01, 0.005];
        // Last outside at 3 s: settled from 4 s on.
        assert_eq!(settling_time(&t, &e, 0.0, 0.02), Some(4.0));
        // From an onset at 3.5 s it never left the band.
        assert_eq!(settling_time(&t, &e, 3.5, 0.02), Some(0.0));
        // Outside at the end: never.
        assert_eq!(
            settling_time(&t, &[0.0, 0.0, 0.0, 0.0, 0.0, 0.5], 0.0, 0.02),
            None
        );
        // NaN is outside.
        assert_eq!(
            settling_time(&t, &[0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0], 0.0, 0.02),
            Some(2.0)
        );
    }

    #[test]
    fn sign_changes_skip_small_commands() {
        let v = [0.1, 0.0005, -0.0005, 0.2, -0.1, -0.2, 0.0, 0.3];
        // + (small ones ignored) + - - + : two changes in 2 s.
        assert_eq!(sign_changes_per_s(&v, 1e-3, 2.0), 1.0);
        assert_eq!(sign_changes_per_s(&[], 1e-3, 2.0), 0.0);
        assert_eq!(sign_changes_per_s(&[0.1, -0.1], 1e-3, 0.0), 0.0);
    }
}
