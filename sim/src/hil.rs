//! `markhold hil`: the loop against the simulated world, on simulation time.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use std::path::Path;

use crate::error::{ensure, SimError, StepContext};
use markhold_autopilot::{ArduSubMode, VehicleLink};
use markhold_exposure::{Camera, ExposureMethod};
use markhold_hil::camera::{CameraModel, RenderLoops};
use markhold_hil::scene::{LightingConfig, LightingScenario, MarkerSpec};
use markhold_hil::{EndpointConfig, HilRig, HilSetup, Truth, VehicleMotion};
use markhold_vision::marker_bitmap;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::faults::{
    CameraFaults, Cover, FaultKind, FaultMonitor, FaultPlan, FaultRig, FaultSpec, FaultyCamera,
    LinkRelay, Projection,
};
use super::summary::{RunStats, Summary};
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::{FrameRecord, LoopStart, Observers, Pipeline};
use markhold_core::record::{ImageFormat, RecordConfig, RecordError, Recorder, RunInfo};

/// Options of one HIL run (the command line's flags, or an experiment of `compare`).
#[derive(Debug, Clone)]
pub struct HilOptions {
    pub seconds: f64,
    pub seed: u64,
    pub exposure: Option<ExposureMethod>,
    pub lighting: Option<LightingScenario>,
    pub initial_exposure_us: Option<f64>,
    pub motion: VehicleMotion,
    /// Start exactly on station instead of the site's initial offset.
    pub start_on_station: bool,
    pub snapshot_dir: Option<PathBuf>,
    /// Save every n-th frame when `snapshot_dir` is set.
    pub snapshot_every: u64,
    /// Write the run's plots (PNG and SVG) into this folder after the run (`--plots`).
    pub plots_dir: Option<PathBuf>,
    /// Faults to inject (`--fault`), seeded with `seed`.
    pub faults: Vec<FaultSpec>,
    /// MAVLink 2 signing key of the simulated vehicle. None: the site's
    /// `link.signing_key_file`, so a signing markhold meets a vehicle that signs with the
    /// same key and requires signed input.
    pub vehicle_signing_key_file: Option<PathBuf>,
    /// The renderer's loops, up to this build (`--render-loops`); None: the widest the CPU
    /// runs. Every build renders the same frames; only the world's speed differs.
    pub render_loops: Option<RenderLoops>,
    /// Set by Ctrl-C / SIGTERM: the next frame sends neutral input and the run ends
    /// there (the recording is finalized, the summary says `interrupted`).
    pub stop: Option<markhold_core::signal::ShutdownFlag>,
    /// How the camera's frames and exposure commands travel (`--camera-transport`).
    pub camera_transport: super::stream::CameraTransport,
    /// The simulated camera's actuation delay, frames (`--camera-delay-frames`); None:
    /// the site's `camera.actuation_delay_frames`.
    pub camera_delay_frames: Option<u32>,
}

impl Default for HilOptions {
    fn default() -> Self {
        Self {
            seconds: 60.0,
            seed: 1,
            exposure: None,
            lighting: None,
            initial_exposure_us: None,
            motion: VehicleMotion::Free,
            start_on_station: false,
            snapshot_dir: None,
            snapshot_every: 30,
            plots_dir: None,
            faults: Vec::new(),
            vehicle_signing_key_file: None,
            render_loops: None,
            stop: None,
            camera_transport: super::stream::CameraTransport::InProcess,
            camera_delay_frames: None,
        }
    }
}

/// Everything a HIL run is made of, built from a site and options.
pub struct HilRun {
    pub rig: HilRig,
    pub pipeline: Pipeline,
    pub method: ExposureMethod,
    pub lighting: LightingScenario,
    pub t_world_marker: Isometry3<f64>,
    pub t_marker_station: Isometry3<f64>,
    /// Fault injection, when `HilOptions::faults` is not empty.
    pub faults: Option<FaultRig>,
    /// The H.264/RTP transport (`--camera-transport h264-rtp`).
    pub stream: Option<super::stream::StreamHil>,
    /// Setpoint mode: GUIDED is requested once the vehicle has a vision estimate (it
    /// refuses GUIDED without a position, like ArduSub).
    guided_after_vision: bool,
}

/// The site's initial offset from the station, in the station (vehicle body) frame.
///
/// 0.3 m by default, split equally over surge (back), sway and heave so every axis has
/// to act, with the yaw turned toward the marker: the camera sits 0.2 m ahead of the
/// centre of gravity, 0.8 m from the marker, and a sideways offset with the yaw turned
/// away would start with the marker outside a 62-degree field of view.
pub fn start_offset(v: &markhold_hil::VehicleConfig) -> Isometry3<f64> {
    let d = v.initial_offset_m / 3f64.sqrt();
    Isometry3::from_parts(
        Translation3::from(Vector3::new(-d, d, d)),
        UnitQuaternion::from_euler_angles(0.0, 0.0, -v.initial_offset_deg.to_radians()),
    )
}

/// The simulator's start pose in the marker frame for an `initial_offset_m` (with the
/// site's `initial_offset_deg`).
pub fn start_in_marker(site: &markhold_core::params::Site, offset_m: f64) -> Isometry3<f64> {
    let v = markhold_hil::VehicleConfig {
        initial_offset_m: offset_m,
        ..site.vehicle.clone()
    };
    site.station.t_marker_vehicle() * start_offset(&v)
}

/// Refuses a start from which the camera does not see the marker
/// ([`markhold_core::feasibility::check_start`]); the error is located in the site file.
pub fn check_start(site: &LoadedSite) -> Result<(), markhold_core::params::ParamsError> {
    let v = &site.site.vehicle;
    markhold_core::feasibility::check_start(
        &site.site,
        &site.calibration,
        v.initial_offset_m,
        v.initial_offset_deg,
        |d| start_in_marker(&site.site, d),
    )
    .map_err(|e| markhold_core::params::locate(&site.path, e))
}

/// The vehicle's start pose: the station, displaced by the site's initial offset.
fn start_pose(site: &LoadedSite, station: &Isometry3<f64>, on_station: bool) -> Isometry3<f64> {
    let t_world_station = site.t_world_marker() * station;
    if on_station {
        return t_world_station;
    }
    t_world_station * start_offset(&site.site.vehicle)
}

/// The simulated camera of a site: its calibration, limits, response and sensor.
pub fn camera_model(site: &LoadedSite, limits: markhold_exposure::ExposureLimits) -> CameraModel {
    let s = &site.site;
    let calib = &site.calibration;
    CameraModel {
        width: calib.width,
        height: calib.height,
        fx: calib.fx,
        fy: calib.fy,
        cx: calib.cx,
        cy: calib.cy,
        dist: dist5(&calib.dist),
        fps: s.camera.fps,
        limits,
        gain_db: s.camera.gain_db,
        delay_frames: s.camera.actuation_delay_frames,
        response: s.camera.response.clone(),
        sensor: s.camera.sensor.clone(),
    }
}

/// The site's marker as printed (from the dictionary), for rendering.
pub fn marker_spec(site: &LoadedSite) -> Result<MarkerSpec, SimError> {
    let m = &site.site.marker;
    let bitmap =
        marker_bitmap(m.family, m.id).step(|| format!("marker {} id {}", m.family, m.id))?;
    Ok(MarkerSpec {
        cells: bitmap.cells,
        white: bitmap.white,
        size_m: m.size_m,
        plate_margin_m: m.size_m * 0.25,
    })
}

/// The map's other markers as printed, each with its pose in the site frame, for
/// rendering (empty for a map of one).
pub fn map_specs(site: &LoadedSite) -> Result<Vec<(MarkerSpec, Isometry3<f64>)>, SimError> {
    let m = &site.site.marker;
    m.map
        .iter()
        .map(|e| {
            let bitmap = marker_bitmap(m.family, e.id)
                .step(|| format!("marker.map: marker {} id {}", m.family, e.id))?;
            let spec = MarkerSpec {
                cells: bitmap.cells,
                white: bitmap.white,
                size_m: e.size_m,
                plate_margin_m: e.size_m * 0.25,
            };
            Ok((spec, e.t_site_marker()))
        })
        .collect()
}

/// The site's scene: the origin marker at `t_world_marker` and every other marker of
/// the map at its pose.
pub fn site_scene(
    site: &LoadedSite,
    lighting: &LightingConfig,
    t_world_marker: Isometry3<f64>,
    seed: u64,
) -> Result<markhold_hil::scene::Scene, SimError> {
    let s = &site.site;
    let mut scene = markhold_hil::scene::Scene::new(
        &s.water,
        lighting,
        marker_spec(site)?,
        t_world_marker,
        seed,
    )?;
    for (spec, t_site_marker) in map_specs(site)? {
        scene.add_map_marker(spec, t_site_marker)?;
    }
    Ok(scene)
}

/// The loop's start for a HIL run with `opts`: the site's, with the command line's
/// exposure method and initial exposure where given.
pub fn loop_start(site: &LoadedSite, opts: &HilOptions) -> LoopStart {
    let own = LoopStart::of_site(site);
    LoopStart {
        method: opts.exposure.unwrap_or(own.method),
        initial_exposure_us: opts
            .initial_exposure_us
            .map_or(own.initial_exposure_us, |t| site.limits().clamp(t)),
        ..own
    }
}

/// The site's lighting, with the command line's scenario where given.
pub fn lighting_of(site: &LoadedSite, opts: &HilOptions) -> LightingConfig {
    let mut lighting = site.site.lighting.clone();
    if let Some(l) = opts.lighting {
        lighting.scenario = l;
    }
    lighting
}

/// Open `--record FILE` for a HIL run with `opts`. It waits for the writer when the
/// queue is full: simulated time waits too, and a lossless recording keeps replay exact.
pub fn open_recorder(
    site: &LoadedSite,
    opts: &HilOptions,
    path: &Path,
) -> Result<Recorder, RecordError> {
    let LoopStart {
        method,
        initial_exposure_us: initial,
        ..
    } = loop_start(site, opts);
    let options = format!(
        "hil --site {} --seconds {} --seed {} --exposure {method} --initial-exposure-us {initial}",
        site.path.display(),
        opts.seconds,
        opts.seed
    );
    let info = RunInfo::new("hil", site, method, initial, options)?;
    let cfg = RecordConfig {
        wait_when_full: true,
        ..site.site.record.config(ImageFormat::Png)
    };
    Recorder::create(path, &info, cfg)
}

impl HilRun {
    /// The simulated world and the loop against it, with `observers` attached.
    pub fn build(
        site: &LoadedSite,
        opts: &HilOptions,
        observers: Observers,
    ) -> Result<Self, SimError> {
        let s = &site.site;
        let start = loop_start(site, opts);
        let method = start.method;
        let lighting_cfg = lighting_of(site, opts);
        let lighting = lighting_cfg.scenario;
        let limits = site.limits();
        let initial_us = start.initial_exposure_us;

        let mut model = camera_model(site, limits);
        if let Some(d) = opts.camera_delay_frames {
            model.delay_frames = d;
        }
        let stream_transport = opts.camera_transport == super::stream::CameraTransport::H264Rtp;
        ensure(!stream_transport || opts.faults.is_empty(), || {
            SimError::Usage {
                reason: "--camera-transport h264-rtp with --fault is not supported".to_string(),
            }
        })?;
        let t_marker_station = s.station.t_marker_vehicle();
        let t_world_marker = site.t_world_marker();
        let setup = HilSetup {
            vehicle: s.vehicle.clone(),
            endpoint: EndpointConfig {
                gcs_system_id: s.link.gcs_system_id,
                signing_key_file: opts
                    .vehicle_signing_key_file
                    .clone()
                    .or_else(|| s.link.signing_key_file.clone()),
                ..EndpointConfig::default()
            },
            water: s.water.clone(),
            lighting: lighting_cfg,
            camera: model,
            t_vehicle_cam: site.t_vehicle_cam(),
            marker: marker_spec(site)?,
            t_world_marker,
            map: map_specs(site)?,
            t_world_vehicle_start: start_pose(site, &t_marker_station, opts.start_on_station),
            motion: opts.motion,
            seed: opts.seed,
            lock_step: true,
        };
        let mut rig = HilRig::new(setup).step(|| "building the HIL world".to_string())?;
        if s.link.command == markhold_autopilot::CommandKind::Setpoint {
            // The vehicle checks each vision estimate's covariance against the truth in
            // the estimates' frame L (docs/frames.md).
            let t_vision_marker = markhold_autopilot::vision_pose::t_vision_marker();
            rig.set_vision_frame(t_world_marker * t_vision_marker.inverse());
        }
        if let Some(want) = opts.render_loops {
            let got = rig.set_render_loops(want);
            if got != want {
                tracing::warn!(
                    "--render-loops {want}: this CPU runs up to {got}; rendering with {got}"
                );
            }
        }
        rig.set_exposure_us(initial_us)?;
        let stream = if stream_transport {
            let frames = (opts.seconds * s.camera.fps).round().max(1.0) as usize;
            Some(super::stream::StreamHil::start(
                &rig, limits, initial_us, frames,
            )?)
        } else {
            None
        };
        let faults = if opts.faults.is_empty() {
            None
        } else {
            Some(fault_rig(
                site,
                opts,
                &rig,
                initial_us,
                t_world_marker,
                t_marker_station,
            )?)
        };
        if faults.is_some() {
            // Dropped frames and a silent link leave frames without input; every datagram
            // is on loopback before the grab, so waiting the full lock-step time is waste.
            rig.set_lockstep_wait(Duration::from_millis(20));
        }
        let vehicle_addr = match faults.as_ref().and_then(|f| f.relay.as_ref()) {
            Some(r) => r.addr()?,
            None => rig.mavlink_udp_addr(),
        };

        let mut link_cfg = s.link.clone();
        link_cfg.url = format!("udpout:{vehicle_addr}");
        let link =
            VehicleLink::connect(&link_cfg).step(|| "connecting to the HIL vehicle".to_string())?;
        let pipeline = Pipeline::new(site, start, link, observers)?;
        Ok(Self {
            rig,
            pipeline,
            method,
            lighting,
            t_world_marker,
            t_marker_station,
            faults,
            stream,
            guided_after_vision: false,
        })
    }

    /// Arm in the configured mode before the first frame. The handshake is bounded by a
    /// wall-clock deadline: it waits on sockets, not on simulated time.
    /// GUIDED needs a position estimate first: the vehicle is armed in its own mode and
    /// GUIDED requested after the first vision estimate went out.
    pub fn arm(&mut self, mode: ArduSubMode) -> Result<(), SimError> {
        let link = self.pipeline.link_mut();
        if mode == ArduSubMode::Guided {
            self.guided_after_vision = true;
        } else {
            link.request_mode(mode, 0.0)?;
        }
        link.request_arm(true, 0.0)?;
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Some(f) = self.faults.as_mut() {
                f.pump_relay(0.0)?;
            }
            self.rig.pump()?;
            if let Some(f) = self.faults.as_mut() {
                f.pump_relay(0.0)?;
            }
            link.tick(0.0)?;
            if link.state().armed && self.rig.truth().armed {
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Err(SimError::Run {
            reason: match link.signing_diagnosis() {
                Some(why) => format!("the HIL vehicle did not arm within 5 s: {why}"),
                None => "the HIL vehicle did not arm within 5 s (no COMMAND_ACK over loopback UDP)"
                    .to_string(),
            },
        })
    }

    /// NEES of the vision estimates the simulated vehicle has graded so far (setpoint
    /// mode; none otherwise). Running sums: the difference of two readings is the
    /// frames between them.
    pub fn vision_nees(&self) -> Option<markhold_hil::endpoint::VisionNees> {
        self.rig.vision_nees()
    }

    /// One frame of the loop, with the world's truth after it.
    pub fn step(&mut self) -> Result<(FrameRecord, Truth), SimError> {
        if self.guided_after_vision && self.pipeline.link().vision_estimates().0 > 0 {
            let now_s = self.rig.sim_time_s();
            self.pipeline
                .link_mut()
                .request_mode(ArduSubMode::Guided, now_s)?;
            self.guided_after_vision = false;
        }
        if let Some(s) = self.stream.as_mut() {
            let rec = self.pipeline.step(&mut s.camera(&mut self.rig))?;
            return Ok((rec, self.rig.truth()));
        }
        let Some(f) = self.faults.as_mut() else {
            let rec = self.pipeline.step(&mut self.rig)?;
            return Ok((rec, self.rig.truth()));
        };
        let now_s = self.rig.sim_time_s();
        let mut cam = FaultyCamera {
            inner: &mut self.rig,
            faults: &mut f.camera,
            relay: f.relay.as_mut(),
            now_s,
        };
        let rec = self.pipeline.step(&mut cam)?;
        let truth = self.rig.truth();
        let link = self.pipeline.link().state();
        f.monitor.observe(
            &rec,
            &truth,
            self.pipeline.events(),
            &self.pipeline.failsafe().transitions,
            link.armed,
            link.heartbeat_ok,
        );
        Ok((rec, truth))
    }
}

/// The fault machinery of a run: the relay exists only for a link cut.
fn fault_rig(
    site: &LoadedSite,
    opts: &HilOptions,
    rig: &HilRig,
    initial_us: f64,
    t_world_marker: Isometry3<f64>,
    t_marker_station: Isometry3<f64>,
) -> Result<FaultRig, SimError> {
    let plan = FaultPlan {
        specs: opts.faults.clone(),
        seed: opts.seed,
    };
    let relay = if plan.has(FaultKind::LinkCut) {
        Some(LinkRelay::bind(rig.mavlink_udp_addr())?)
    } else {
        None
    };
    let m = &site.site.marker;
    let covers: Vec<Cover> = m
        .markers()
        .map(|p| Cover::new(p.id, p.t_site_marker, 0.75 * p.size_m))
        .collect();
    for spec in plan.specs.iter().filter(|s| s.kind == FaultKind::Occlude) {
        if let Some(id) = spec.marker.filter(|id| covers.iter().all(|c| c.id != *id)) {
            let ids: Vec<String> = covers.iter().map(|c| c.id.to_string()).collect();
            return Err(SimError::Usage {
                reason: format!(
                    "--fault occlude:{id}@{}: marker {id} is not in {}'s map (marker ids {})",
                    spec.start_s,
                    site.path.display(),
                    ids.join(", ")
                ),
            });
        }
    }
    let cam = rig.camera_model();
    Ok(FaultRig {
        monitor: FaultMonitor::new(&plan, t_world_marker, t_marker_station),
        camera: CameraFaults::new(
            plan,
            Projection::of(cam),
            covers,
            cam.width,
            cam.height,
            initial_us,
        ),
        relay,
    })
}

fn dist5(d: &[f64]) -> [f64; 5] {
    let mut out = [0.0; 5];
    for (o, v) in out.iter_mut().zip(d) {
        *o = *v;
    }
    out
}

/// Run a whole HIL session with `observers` attached and summarize it.
pub fn run_hil(
    site: &LoadedSite,
    opts: &HilOptions,
    observers: Observers,
) -> Result<Summary, SimError> {
    let wall = Instant::now();
    let mut run = HilRun::build(site, opts, observers)?;
    run.arm(site.site.link.mode.ardusub())?;
    let frames = (opts.seconds * site.site.camera.fps).round().max(1.0) as u64;
    let mut stats = RunStats::new(frames as usize, run.t_world_marker, run.t_marker_station);
    let mut interrupted = false;
    let stepped = (0..frames).try_for_each(|_| {
        if interrupted {
            return Ok::<(), SimError>(());
        }
        if opts.stop.as_ref().is_some_and(|s| s.is_set()) {
            // This frame sends neutral input (the supervisor's shutdown directive) and
            // is the last.
            run.pipeline.set_shutdown(true);
            interrupted = true;
        }
        let (rec, truth) = run.step()?;
        stats.push(&rec, &truth);
        Ok::<(), SimError>(())
    });
    // Leave the vehicle with neutral pilot input, and close the observers (a recording
    // is finalized), also after an error.
    let now = run.rig.truth().time_s;
    let neutral = run.pipeline.link_mut().send_neutral(now);
    let wall_seconds = wall.elapsed().as_secs_f64();
    let observed = run.pipeline.finish_observers();
    stepped?;
    neutral?;
    if let Some(f) = run.faults.as_mut() {
        f.pump_relay(now)?;
    }
    observed?;
    let mut summary = run.summary(&stats, opts, wall_seconds);
    summary.interrupted = interrupted;
    write_plots_of(site, opts, &stats, &summary)?;
    Ok(summary)
}

/// `--plots DIR`: the run's plots from its series, after the run (they only read).
pub fn write_plots_of(
    site: &LoadedSite,
    opts: &HilOptions,
    stats: &RunStats,
    summary: &Summary,
) -> Result<(), SimError> {
    let Some(dir) = &opts.plots_dir else {
        return Ok(());
    };
    let info = super::run_plots::RunPlotInfo {
        title: format!(
            "{}, {}, {} lighting, seed {}",
            site.site.site.name, summary.exposure_method, summary.lighting, summary.seed
        ),
        marker_size_m: site.site.marker.size_m,
    };
    super::run_plots::write_run_plots(stats, &info, dir)
        .step(|| format!("writing --plots {}", dir.display()))?;
    Ok(())
}

impl HilRun {
    /// The run's summary from its statistics and the world's own timing.
    fn summary(&mut self, stats: &RunStats, opts: &HilOptions, wall_seconds: f64) -> Summary {
        let mut summary = stats.summary(
            self.method,
            self.lighting,
            opts.seed,
            wall_seconds,
            self.rig.truth().lockstep_timeouts,
        );
        summary.frame_to_thrust_ms = Some(self.rig.frame_to_thrust_ms());
        let world = self.rig.world_wall_seconds();
        summary.world_wall_seconds = world;
        summary.render_loops = self.rig.render_loops().to_string();
        if world > 0.0 {
            summary.world_realtime_factor = summary.sim_seconds / world;
        }
        if let Some(f) = self.faults.take() {
            summary.faults = f.monitor.into_reports();
        }
        summary.vision_nees = self
            .rig
            .vision_nees()
            .map(|n| super::summary::VisionNeesSummary::of(&n));
        summary.exposure_gate_stall = self.pipeline.exposure_controller().gate_stall();
        if let Some(s) = &self.stream {
            summary.camera_transport = Some(opts.camera_transport.to_string());
            summary.stream_delay_estimate_frames = s.delay_estimate_frames();
            let mut l = s.added_latency_s.clone();
            l.sort_by(f64::total_cmp);
            let at = |q: f64| {
                l.get(((l.len() as f64 - 1.0) * q).round() as usize)
                    .map(|v| v * 1e3)
            };
            summary.stream_added_latency_p50_ms = at(0.5);
            summary.stream_added_latency_p99_ms = at(0.99);
        }
        summary
    }
}

/// Frames of the site's marker seen from the station by the site's HIL camera (the
/// site's lighting, `seed`), at `steps` exposures spaced geometrically over the
/// camera's range: the exposure sweep `markhold response fit` calibrates from.
pub fn exposure_sweep(
    site: &LoadedSite,
    seed: u64,
    steps: usize,
) -> Result<Vec<markhold_exposure::Frame>, SimError> {
    ensure(steps >= 2, || SimError::Usage {
        reason: format!("--steps {steps}: expected 2 or more exposures"),
    })?;
    let limits = site.limits();
    let (lo, hi) = (limits.min_us, limits.effective_max_us());
    let exposures: Vec<f64> = (0..steps)
        .map(|k| lo * (hi / lo).powf(k as f64 / (steps - 1) as f64))
        .collect();
    station_frames(site, seed, &site.site.lighting, &exposures)
}

/// The site's marker seen from the station (vehicle on station, not moving) by the
/// site's HIL camera in `lighting`, one frame at each of `exposures` (clamped to the
/// camera's limits), and the marker's corners in those frames (projected, not detected).
pub fn station_frames(
    site: &LoadedSite,
    seed: u64,
    lighting: &LightingConfig,
    exposures: &[f64],
) -> Result<Vec<markhold_exposure::Frame>, SimError> {
    let mut out = Vec::with_capacity(exposures.len());
    station_frames_each::<SimError>(site, seed, lighting, exposures, |f| {
        out.push(f.clone());
        Ok(())
    })?;
    Ok(out)
}

/// [`station_frames`] one frame at a time into `each` (nothing kept: a full-size sweep
/// of hundreds of frames). Consecutive equal exposures give consecutive frames of the
/// same exposure (the noise and a caustic light change between them).
pub fn station_frames_each<E: From<SimError>>(
    site: &LoadedSite,
    seed: u64,
    lighting: &LightingConfig,
    exposures: &[f64],
    mut each: impl FnMut(&markhold_exposure::Frame) -> Result<(), E>,
) -> Result<(), E> {
    use markhold_hil::camera::UnderwaterCamera;
    let s = &site.site;
    let limits = site.limits();
    let t_world_marker = site.t_world_marker();
    let scene = site_scene(site, lighting, t_world_marker, seed)?;
    let t_world_vehicle = t_world_marker * s.station.t_marker_vehicle();
    let t_world_cam = t_world_vehicle * site.t_vehicle_cam();
    let mut camera =
        UnderwaterCamera::new(camera_model(site, limits), seed).map_err(SimError::from)?;
    let dt = 1.0 / s.camera.fps;
    let mut time_s = 0.0;
    let mut frame = markhold_exposure::Frame::new(1, 1);
    for &want in exposures {
        let t = camera.set_exposure_us(want);
        // A new exposure takes effect a few frames late: render until it has.
        for _ in 0..=s.camera.actuation_delay_frames + 1 {
            camera.render(&scene, &t_world_cam, &t_world_vehicle, time_s, &mut frame);
            time_s += dt;
            if (frame.meta.exposure_us - t).abs() <= 1e-6 * t {
                break;
            }
        }
        each(&frame)?;
    }
    Ok(())
}

/// The marker's corners (aruco order) as the site's camera sees them from the station.
pub fn station_corners(site: &LoadedSite) -> Option<markhold_exposure::Corners> {
    let s = &site.site;
    let half = s.marker.size_m / 2.0;
    let t_world_vehicle = site.t_world_marker() * s.station.t_marker_vehicle();
    let t_cam_marker = (t_world_vehicle * site.t_vehicle_cam()).inverse() * site.t_world_marker();
    let model = camera_model(site, site.limits());
    let mut corners = [[0f32; 2]; 4];
    for (c, (x, y)) in
        corners
            .iter_mut()
            .zip([(-half, half), (half, half), (half, -half), (-half, -half)])
    {
        let p = model.project(&(t_cam_marker * nalgebra::Point3::new(x, y, 0.0)))?;
        *c = [p[0] as f32, p[1] as f32];
    }
    Some(corners)
}
