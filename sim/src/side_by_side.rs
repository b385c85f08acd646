//! `markhold sitl-compare`: the same site and seed flown by markhold's simulated ArduSub
//! (`hil`) and by the real ArduSub in SITL (`sitl-loop`), the keeper unchanged, and both
//! reported: hold figures, and the vehicle's response to keeper-effort steps in each
//! flight mode (what a plant model of ArduSub has to reproduce).

use std::path::{Path, PathBuf};

use crate::error::{Required, SimError, StepContext};
use markhold_autopilot::{Effort, LinkMode};
use markhold_exposure::{Camera, Frame};
use nalgebra::Isometry3;
use serde::Serialize;

use super::hil::{HilOptions, HilRun};
use super::hold::{HoldFigures, HoldSeries};
use super::sitl_loop::{arm, open_peer, run_sitl_loop, SitlLoopOptions, SITL_DEPTH_NOISE_M};
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::Observers;

/// One step of the stick-step test: an effort on one axis from `STEP_AT_S` for
/// `STEP_S`, then neutral for `STEP_S`.
const STEP_AT_S: f64 = 1.0;
const STEP_S: f64 = 2.0;
/// The effort of the step (a keeper command of this size, dead zones compensated as
/// the keeper's are).
pub const STEP_EFFORT: f64 = 0.2;

/// An axis stepped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StepAxis {
    Surge,
    Heave,
    Yaw,
}

impl StepAxis {
    pub const ALL: [StepAxis; 3] = [StepAxis::Surge, StepAxis::Heave, StepAxis::Yaw];

    fn effort(self, v: f64) -> Effort {
        let mut e = Effort::NEUTRAL;
        match self {
            Self::Surge => e.surge = v,
            Self::Heave => e.heave = v,
            Self::Yaw => e.yaw = v,
        }
        e
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Surge => "surge",
            Self::Heave => "heave",
            Self::Yaw => "yaw",
        }
    }

    fn unit(self) -> &'static str {
        match self {
            Self::Surge | Self::Heave => "m/s",
            Self::Yaw => "deg/s",
        }
    }
}

/// The response to one step: the rate reached in the step's second half (forward speed,
/// down speed or yaw rate), and the displacement after the stick came back (metres or
/// degrees moved in the following `STEP_S`: coasting, or a hold that captures late).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StepResponse {
    pub mode: &'static str,
    pub axis: StepAxis,
    pub rate: f64,
    pub after_release: f64,
}

/// One vehicle's pose series during a step test, to read the responses from.
#[derive(Default)]
struct PoseTrace {
    t: Vec<f64>,
    pose: Vec<Isometry3<f64>>,
}

impl PoseTrace {
    fn push(&mut self, t: f64, p: &Isometry3<f64>) {
        self.t.push(t);
        self.pose.push(*p);
    }

    /// The pose nearest time `t`.
    fn at(&self, t: f64) -> Option<&Isometry3<f64>> {
        let i = self.t.partition_point(|&x| x < t);
        self.pose.get(i.min(self.pose.len().saturating_sub(1)))
    }

    /// Rate and post-release displacement of `axis`, in the start pose's frame.
    fn response(&self, mode: &'static str, axis: StepAxis) -> Option<StepResponse> {
        let p0 = *self.at(0.0)?;
        let coord = |p: &Isometry3<f64>| -> f64 {
            let d = p0.inverse() * p;
            match axis {
                StepAxis::Surge => d.translation.x,
                StepAxis::Heave => d.translation.z,
                StepAxis::Yaw => d.rotation.euler_angles().2.to_degrees(),
            }
        };
        let (a, b) = (STEP_AT_S + STEP_S / 2.0, STEP_AT_S + STEP_S);
        if *self.t.last()? < b + STEP_S - 1e-6 {
            // The trace ends before the coast does.
            return None;
        }
        let rate = (coord(self.at(b)?) - coord(self.at(a)?)) / (b - a);
        let after = coord(self.at(b + STEP_S)?) - coord(self.at(b)?);
        Some(StepResponse {
            mode,
            axis,
            rate,
            after_release: after,
        })
    }
}

/// The effort at time `t` (from arming) of a step test on `axis`.
fn step_effort(axis: StepAxis, t: f64) -> Effort {
    if (STEP_AT_S..STEP_AT_S + STEP_S).contains(&t) {
        axis.effort(STEP_EFFORT)
    } else {
        Effort::NEUTRAL
    }
}

const STEP_MODES: [(LinkMode, &str); 3] = [
    (LinkMode::Manual, "MANUAL"),
    (LinkMode::Stabilize, "STABILIZE"),
    (LinkMode::AltHold, "ALT_HOLD"),
];

fn site_in_mode(site: &LoadedSite, mode: LinkMode) -> LoadedSite {
    let mut s = site.clone();
    s.site.link.mode = mode;
    s
}

/// The site as SITL flies it: lock-step frames reach the real ArduSub with only its own
/// main loop in between, so the simulated side keeps that stage of `[vehicle.delay]` and
/// drops the camera and link stages SITL does not have.
fn as_sitl_flies(mut site: LoadedSite) -> LoadedSite {
    let d = &mut site.site.vehicle.delay;
    *d = markhold_hil::DelayConfig {
        ardusub_loop_ms: d.ardusub_loop_ms,
        ..markhold_hil::DelayConfig::NONE
    };
    site
}

/// Stick steps on markhold's simulated ArduSub, every mode and axis, from the station.
fn steps_on_ours(site: &LoadedSite, seed: u64) -> Result<Vec<StepResponse>, SimError> {
    let mut out = Vec::new();
    for (mode, name) in STEP_MODES {
        for axis in StepAxis::ALL {
            let site = site_in_mode(site, mode);
            let opts = HilOptions {
                seed,
                start_on_station: true,
                ..HilOptions::default()
            };
            let mut run = HilRun::build(&site, &opts, Observers::new())?;
            run.arm(mode.ardusub())?;
            let fps = site.site.camera.fps;
            let mut frame = Frame::new(1, 1);
            let mut trace = PoseTrace::default();
            let t0 = run.rig.truth().time_s;
            let n = ((STEP_AT_S + 2.0 * STEP_S + 0.5) * fps).ceil() as u64;
            for _ in 0..n {
                let t = run.rig.truth().time_s - t0;
                let link = run.pipeline.link_mut();
                link.tick(t)?;
                link.send_effort(&step_effort(axis, t), t)?;
                run.rig.grab(&mut frame)?;
                let truth = run.rig.truth();
                trace.push(truth.time_s - t0, &truth.t_world_vehicle);
            }
            if let Some(r) = trace.response(name, axis) {
                out.push(r);
            }
        }
    }
    Ok(out)
}

/// Stick steps on ArduSub SITL, every mode and axis, from the station.
fn steps_on_sitl(
    site: &LoadedSite,
    opts: &SitlLoopOptions,
    seed: u64,
) -> Result<Vec<StepResponse>, SimError> {
    let mut out = Vec::new();
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    for (mode, name) in STEP_MODES {
        // One ArduSub per mode: each axis is stepped from where the last one left it.
        let site = site_in_mode(site, mode);
        let (mut peer, mut link) = open_peer(&site, opts, &start, seed)?;
        arm(&mut peer, &mut link, mode.ardusub(), opts.arm_timeout_s)?;
        for axis in StepAxis::ALL {
            let mut trace = PoseTrace::default();
            peer.step()?;
            let t0 = peer.time_s();
            let mut next = t0;
            loop {
                let t = peer.time_s() - t0;
                if peer.time_s() >= next {
                    link.tick(t)?;
                    link.send_effort(&step_effort(axis, t), t)?;
                    trace.push(t, &peer.server().state().t_world_vehicle);
                    next += 0.02;
                }
                peer.server().reply()?;
                if t > STEP_AT_S + 2.0 * STEP_S + 0.5 {
                    break;
                }
                peer.step()?;
            }
            if let Some(r) = trace.response(name, axis) {
                out.push(r);
            }
        }
        link.send_neutral(peer.time_s())?;
        peer.done();
    }
    Ok(out)
}

/// One site flown by both.
#[derive(Debug, Clone, Serialize)]
pub struct SiteComparison {
    pub site: String,
    pub ours: HoldFigures,
    pub sitl: HoldFigures,
}

/// The whole comparison.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub seed: u64,
    pub seconds: f64,
    pub ardusub: String,
    /// SIM_BARO_RND given to ArduSub SITL (m).
    pub depth_noise_m: f64,
    pub sites: Vec<SiteComparison>,
    pub steps_ours: Vec<StepResponse>,
    pub steps_sitl: Vec<StepResponse>,
}

/// The hold figures of a run on markhold's simulated ArduSub.
pub fn hold_on_ours(site: &LoadedSite, opts: &HilOptions) -> Result<HoldFigures, SimError> {
    let mut run = HilRun::build(site, opts, Observers::new())?;
    run.arm(site.site.link.mode.ardusub())?;
    let frames = (opts.seconds * site.site.camera.fps).round().max(1.0) as usize;
    let mut hold = HoldSeries::new(frames, run.t_world_marker, run.t_marker_station);
    for _ in 0..frames {
        let (rec, truth) = run.step()?;
        hold.push(&rec, &truth);
    }
    let now = run.rig.truth().time_s;
    run.pipeline.link_mut().send_neutral(now)?;
    Ok(hold.figures())
}

/// The markdown report of a comparison.
pub fn report(c: &Comparison) -> String {
    let mut s = format!(
        "Seed {}, {} simulated seconds a run, figures over each run's last half; ArduSub: {} \
         (its depth-sensor noise SIM_BARO_RND {} m).\n\n\
         | site | vehicle | position RMS mm | final error mm | heading std deg | yaw effort std | heave effort std | thruster reversals /s | marker % |\n\
         |---|---|---|---|---|---|---|---|---|\n",
        c.seed, c.seconds, c.ardusub, c.depth_noise_m
    );
    for site in &c.sites {
        for (who, f) in [
            ("simulated ArduSub", &site.ours),
            ("ArduSub SITL", &site.sitl),
        ] {
            s += &format!(
                "| {} | {} | {:.1} | {:.1} | {:.2} | {:.3} | {:.3} | {:.2} | {:.0} |\n",
                site.site,
                who,
                f.position_rms_m * 1e3,
                f.final_error_m * 1e3,
                f.heading_std_deg,
                f.yaw_effort_std,
                f.heave_effort_std,
                f.thruster_reversals_per_s,
                f.detection_rate * 100.0
            );
        }
    }
    s += &format!(
        "\nKeeper-effort steps of {STEP_EFFORT} for {STEP_S} s from the station: the rate in the \
         step's second half, and how far the vehicle moved in the {STEP_S} s after the \
         stick came back.\n\n\
         | mode | axis | unit | simulated rate | SITL rate | simulated after release | SITL after release |\n\
         |---|---|---|---|---|---|---|\n"
    );
    for o in &c.steps_ours {
        let Some(r) = c
            .steps_sitl
            .iter()
            .find(|r| r.mode == o.mode && r.axis == o.axis)
        else {
            continue;
        };
        let after_unit = if o.axis == StepAxis::Yaw { "deg" } else { "m" };
        s += &format!(
            "| {} | {} | {} | {:.3} | {:.3} | {:.3} {after_unit} | {:.3} {after_unit} |\n",
            o.mode,
            o.axis.name(),
            o.axis.unit(),
            o.rate,
            r.rate,
            o.after_release,
            r.after_release
        );
    }
    s
}

/// `markhold sitl-compare`.
#[derive(clap::Args)]
pub struct SitlCompareArgs {
    /// Dive-site files (default: every params/*.toml).
    #[arg(long = "site", value_name = "FILE")]
    pub sites: Vec<PathBuf>,
    /// The ArduSub SITL binary (build/sitl/bin/ardusub of an ArduSub build).
    #[arg(long, value_name = "PATH")]
    pub ardusub: PathBuf,
    /// Its parameter defaults (Tools/autotest/default_params/sub-6dof.parm).
    #[arg(long, value_name = "FILE.parm")]
    pub defaults: Option<PathBuf>,
    /// ArduSub SITL's depth-sensor noise, SIM_BARO_RND (m, uniform +-), set after
    /// --defaults. SITL's own default, 0.2, is an aircraft's altitude noise: 0.2 m of
    /// water.
    #[arg(long, value_name = "M", default_value_t = SITL_DEPTH_NOISE_M)]
    pub depth_noise_m: f64,
    /// The ArduSub version flown, as the report names it (e.g. "ArduSub V4.2.0-dev
    /// b6606a8f5d").
    #[arg(long, default_value = "ArduSub SITL")]
    pub ardusub_version: String,
    /// SITL instance N (ports 5760 + 10 N, 9002 + 10 N).
    #[arg(long, default_value_t = 0)]
    pub instance: u16,
    /// Simulated seconds of each hold run.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// No stick-step tests (hold runs only).
    #[arg(long)]
    pub no_steps: bool,
    /// Write the report (markdown) here; results.json beside it.
    #[arg(long, value_name = "FILE.md")]
    pub out: Option<PathBuf>,
}

pub fn cli(args: SitlCompareArgs) -> Result<(), SimError> {
    let mut sites = args.sites.clone();
    if sites.is_empty() {
        for e in std::fs::read_dir("params").step(|| "listing params/".to_string())? {
            let p = e?.path();
            if p.extension().is_some_and(|x| x == "toml") {
                sites.push(p);
            }
        }
        sites.sort();
    }
    // The report's folder exists before an hour of runs, not after.
    if let Some(dir) = args.out.as_deref().and_then(Path::parent) {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).map_err(|source| SimError::File {
                action: "creating --out's folder",
                path: dir.to_path_buf(),
                source,
            })?;
        }
    }
    let opts = SitlLoopOptions {
        ardusub: Some(args.ardusub.clone()),
        defaults: args.defaults.clone(),
        depth_noise_m: args.depth_noise_m,
        instance: args.instance,
        ..SitlLoopOptions::default()
    };
    let hil = HilOptions {
        seconds: args.seconds,
        seed: args.seed,
        ..HilOptions::default()
    };
    let mut out = Comparison {
        seed: args.seed,
        seconds: args.seconds,
        ardusub: args.ardusub_version.clone(),
        depth_noise_m: args.depth_noise_m,
        sites: Vec::new(),
        steps_ours: Vec::new(),
        steps_sitl: Vec::new(),
    };
    for path in &sites {
        let site = as_sitl_flies(markhold_core::params::load(path)?);
        let name = site.site.site.name.clone();
        eprintln!("markhold sitl-compare: {name}: simulated ArduSub");
        let ours = hold_on_ours(&site, &hil)?;
        eprintln!("markhold sitl-compare: {name}: ArduSub SITL");
        let sitl = run_sitl_loop(&site, &opts, &hil, Observers::new())
            .step(|| format!("{name} on ArduSub SITL"))?
            .hold;
        out.sites.push(SiteComparison {
            site: name,
            ours,
            sitl,
        });
    }
    if !args.no_steps {
        let site = as_sitl_flies(markhold_core::params::load(
            sites.first().required(|| "no site".to_string())?,
        )?);
        eprintln!("markhold sitl-compare: stick steps");
        out.steps_ours = steps_on_ours(&site, args.seed)?;
        out.steps_sitl = steps_on_sitl(&site, &opts, args.seed)?;
    }
    let text = report(&out);
    markhold_core::outln!("{text}");
    if let Some(path) = &args.out {
        std::fs::write(path, &text).step(|| format!("writing {}", path.display()))?;
        let json = path.with_file_name("results.json");
        std::fs::write(&json, serde_json::to_string_pretty(&out)?)
            .step(|| format!("writing {}", json.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A vehicle that moves forward at 0.5 m/s and turns at 20 deg/s during the step,
    /// then coasts at half that for the rest: the rate is read in the step's second half,
    /// the displacement over the 2 s after release.
    #[test]
    fn step_response_reads_the_rate_and_the_coast() {
        let mut tr = PoseTrace::default();
        let start = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5),
        );
        let end = STEP_AT_S + STEP_S;
        for i in 0..=300 {
            let t = i as f64 * 0.02;
            let moving = (t - STEP_AT_S).clamp(0.0, STEP_S);
            let coasting = (t - end).clamp(0.0, STEP_S);
            let x = 0.5 * moving + 0.25 * coasting;
            let yaw = (20.0 * moving + 10.0 * coasting).to_radians();
            let local = Isometry3::from_parts(
                Translation3::new(x, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            );
            tr.push(t, &(start * local));
        }
        let s = tr.response("MANUAL", StepAxis::Surge).unwrap();
        assert!(
            (s.rate - 0.5).abs() < 1e-9 && (s.after_release - 0.5).abs() < 1e-9,
            "{s:?}"
        );
        let y = tr.response("MANUAL", StepAxis::Yaw).unwrap();
        assert!(
            (y.rate - 20.0).abs() < 1e-6 && (y.after_release - 20.0).abs() < 1e-6,
            "{y:?}"
        );
        let h = tr.response("MANUAL", StepAxis::Heave).unwrap();
        assert!(h.rate.abs() < 1e-9 && h.after_release.abs() < 1e-9, "{h:?}");
        // A trace that ends before the coast does has no response.
        let mut short = PoseTrace::default();
        short.push(0.0, &start);
        short.push(end, &start);
        assert!(short.response("MANUAL", StepAxis::Yaw).is_none());
        assert!(PoseTrace::default()
            .response("MANUAL", StepAxis::Yaw)
            .is_none());
    }

    #[test]
    fn step_effort_is_the_step_and_neutral_around_it() {
        assert_eq!(step_effort(StepAxis::Yaw, 0.5), Effort::NEUTRAL);
        assert_eq!(step_effort(StepAxis::Yaw, STEP_AT_S).yaw, STEP_EFFORT);
        assert_eq!(
            step_effort(StepAxis::Heave, STEP_AT_S + 1.0).heave,
            STEP_EFFORT
        );
        assert_eq!(
            step_effort(StepAxis::Surge, STEP_AT_S + STEP_S),
            Effort::NEUTRAL
        );
    }
}
