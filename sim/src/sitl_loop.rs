//! `markhold sitl-loop`: the real ArduSub (SITL) as the autopilot, markhold's physics as
//! its JSON backend, and the camera rendered from that same physics state.
//!
//! ArduPilot's JSON backend (libraries/SITL/SIM_JSON.cpp, `JSON::output_servos` and
//! `JSON::recv_fdm`) sends one servo packet per physics step and blocks until the state
//! comes back; its clock advances only by the difference of the states' `timestamp`s.
//! So ArduSub's time is the physics' time, and it stands still while markhold holds a
//! reply: at each camera frame time the runner holds the reply, renders the frame from the
//! physics pose of that very step, runs the loop (which reads ArduSub's telemetry and
//! sends its pilot input over MAVLink), and only then answers. No telemetry staleness in
//! the camera, no wall clock in the loop; the run goes as fast as both sides compute
//! (`--speedup` lets ArduSub skip its own real-time pacing).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::error::{ensure, SimError, StepContext};
use markhold_autopilot::{ArduSubMode, VehicleLink};
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use markhold_hil::camera::UnderwaterCamera;
use markhold_hil::scene::Scene;
use markhold_hil::{SitlConfig, SitlServer, Truth};
use nalgebra::Isometry3;

use super::hil::{camera_model, lighting_of, loop_start, site_scene, start_offset, HilOptions};
use super::hold::{HoldFigures, HoldSeries};
use super::summary::{RunStats, Summary};
use markhold_core::engage::EngagedLink;
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::{CommandLink, Observers, Pipeline};

/// ArduPilot SITL's MAVLink TCP port for SERIAL0 (`SITL_cmdline.cpp`, BASE_PORT) and its
/// JSON servo port (SIM_OUT_PORT); instance `-I N` adds 10 * N to both.
const BASE_PORT: u16 = 5760;
const JSON_PORT: u16 = 9002;
/// ArduSub's home for a started binary: Tools/autotest/ardusub.py's SITL_START_LOCATION
/// (lat, lon, altitude 0 m, heading).
const HOME: &str = "33.810313,-118.393867,0,185";
/// Simulated seconds ArduSub gets to settle its EKF (held still at the surface) before
/// the vehicle is carried down.
const ARM_SETTLE_S: f64 = 10.0;
/// Speed the vehicle is carried down to its start at, m/s.
const DESCENT_MPS: f64 = 0.25;
/// Held still at the start this long before it is armed, s.
const HOLD_BEFORE_ARM_S: f64 = 2.0;
/// The depth-sensor noise a started ArduSub SITL gets (`SIM_BARO_RND`, m): the value
/// ArduSub's own sub-6dof.parm sets under the name `BARO_RND`, which ArduSub does not
/// read (SITL's parameters carry the `SIM_` prefix: ArduSub/Parameters.cpp `GOBJECT(sitl,
/// "SIM_", SITL::SITL)`), so without it SITL keeps its aircraft default of 0.2 m.
pub const SITL_DEPTH_NOISE_M: f64 = 0.02;
/// The parameter file markhold adds after the user's `--defaults`, in ArduSub's folder.
const SENSOR_PARM: &str = "markhold-sitl.parm";

/// How the SITL-in-the-loop run finds its ArduSub.
#[derive(Debug, Clone)]
pub struct SitlLoopOptions {
    /// The `ardusub` binary to start (`--model JSON`); None: an ArduSub already running
    /// (e.g. `sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON`) sends to the
    /// JSON port and listens at `vehicle_url`.
    pub ardusub: Option<PathBuf>,
    /// Parameter defaults for the started binary (`--defaults`), e.g.
    /// Tools/autotest/default_params/sub-6dof.parm.
    pub defaults: Option<PathBuf>,
    /// SITL's depth-sensor noise, `SIM_BARO_RND` (m of water; SITL adds it uniformly in
    /// +-this to the altitude its baro reads, AP_Baro_SITL.cpp `_timer`): written to a
    /// parameter file read after `defaults`.
    pub depth_noise_m: f64,
    /// SITL instance: ports 5760 + 10 N (MAVLink) and 9002 + 10 N (JSON).
    pub instance: u16,
    /// ArduSub's `--speedup` (its real-time pacing; the lockstep holds either way).
    pub speedup: u32,
    /// ArduSub's MAVLink (default tcp:127.0.0.1:5760 + 10 N).
    pub vehicle_url: Option<String>,
    /// Where the started ArduSub runs and logs (default: a new folder under the
    /// system's temporary folder, removed after a clean run).
    pub work_dir: Option<PathBuf>,
    /// Simulated seconds to wait for ArduSub to arm in the site's mode (its EKF settles,
    /// the vehicle is carried down from the surface).
    pub arm_timeout_s: f64,
    /// Longest wall time without a servo packet before ArduSub is taken for dead.
    pub peer_timeout: Duration,
    /// The JSON port instead of 9002 + 10 N (an ArduSub started with `--sim-port-out`).
    pub json_port: Option<u16>,
}

impl Default for SitlLoopOptions {
    fn default() -> Self {
        Self {
            ardusub: None,
            defaults: None,
            depth_noise_m: SITL_DEPTH_NOISE_M,
            instance: 0,
            speedup: 100,
            vehicle_url: None,
            work_dir: None,
            arm_timeout_s: 180.0,
            peer_timeout: Duration::from_secs(10),
            json_port: None,
        }
    }
}

impl SitlLoopOptions {
    fn json_port(&self) -> u16 {
        self.json_port.unwrap_or(JSON_PORT + 10 * self.instance)
    }

    fn vehicle_url(&self) -> String {
        self.vehicle_url
            .clone()
            .unwrap_or_else(|| format!("tcp:127.0.0.1:{}", BASE_PORT + 10 * self.instance))
    }
}

/// ArduSub's `--defaults` for a started SITL: the user's file (if any), then markhold's
/// own in `dir` setting the depth-sensor noise, comma-separated as
/// AP_Param::load_defaults_file reads them (a later file's value wins).
pub fn sitl_defaults(
    user: Option<&Path>,
    dir: &Path,
    depth_noise_m: f64,
) -> Result<std::ffi::OsString, SimError> {
    ensure(
        depth_noise_m.is_finite() && (0.0..=1.0).contains(&depth_noise_m),
        || {
            SimError::Usage {
            reason: format!(
                "--depth-noise-m {depth_noise_m}: expected SITL's depth-sensor noise in metres, 0 to 1"
            ),
        }
        },
    )?;
    let ours = dir.join(SENSOR_PARM);
    std::fs::write(
        &ours,
        format!(
            "# Written by markhold sitl-loop: SITL's depth-sensor noise (uniform +-m).\n\
             SIM_BARO_RND {depth_noise_m}\n"
        ),
    )
    .map_err(|source| SimError::File {
        action: "writing",
        path: ours.clone(),
        source,
    })?;
    // ArduSub splits the list at commas: neither path may hold one.
    let resolve = |path: &Path, flag: &str| -> Result<PathBuf, SimError> {
        let p = std::fs::canonicalize(path)
            .step(|| format!("{flag} {}: no such file", path.display()))?;
        ensure(!p.as_os_str().to_string_lossy().contains(','), || {
            SimError::Usage {
            reason: format!(
                "{flag} {}: ArduSub reads a comma as a separator between files; use a path without one",
                p.display()
            ),
        }
        })?;
        Ok(p)
    };
    let mut arg = std::ffi::OsString::new();
    if let Some(d) = user {
        arg.push(resolve(d, "--defaults")?);
        arg.push(",");
    }
    arg.push(resolve(&ours, "--work-dir")?);
    Ok(arg)
}

/// A started `ardusub`: killed and reaped on drop, its folder removed if it was ours and
/// the run ended cleanly.
pub struct ArduSubProcess {
    child: Child,
    dir: PathBuf,
    remove_dir: bool,
}

impl ArduSubProcess {
    /// Start `bin --model JSON` in its own folder (it writes eeprom.bin and logs there).
    pub fn start(opts: &SitlLoopOptions, bin: &Path) -> Result<Self, SimError> {
        let (dir, remove_dir) = match &opts.work_dir {
            Some(d) => (d.clone(), false),
            None => (
                std::env::temp_dir().join(format!(
                    "markhold-sitl-{}-{}",
                    std::process::id(),
                    opts.instance
                )),
                true,
            ),
        };
        std::fs::create_dir_all(&dir)
            .step(|| format!("creating ArduSub's folder {}", dir.display()))?;
        let log = std::fs::File::create(dir.join("ardusub.log"))
            .step(|| format!("creating {}", dir.join("ardusub.log").display()))?;
        // Resolved here: the process starts in its own folder.
        let bin = std::fs::canonicalize(bin)
            .step(|| format!("--ardusub {}: no such file", bin.display()))?;
        let mut cmd = Command::new(&bin);
        cmd.current_dir(&dir)
            .args(["--model", "JSON", "-w"])
            .args(["--speedup", &opts.speedup.max(1).to_string()])
            .args(["-I", &opts.instance.to_string()])
            // At sea level: ArduSub's simulated depth sensor reads the water pressure of
            // the altitude below home (AP_Baro_SITL.cpp, `SimpleUnderWaterAtmosphere(
            // -sim_alt)`), meaningless at sim_vehicle.py's default 584 m. The autotest's
            // own ArduSub start (ardusub.py, SITL_START_LOCATION) is at 0 m too.
            .args(["--home", HOME]);
        cmd.arg("--defaults").arg(sitl_defaults(
            opts.defaults.as_deref(),
            &dir,
            opts.depth_noise_m,
        )?);
        let child = cmd
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .step(|| format!("starting ArduSub SITL {}", bin.display()))?;
        Ok(Self {
            child,
            dir,
            remove_dir,
        })
    }

    /// Fails when the process has ended.
    fn check_alive(&mut self) -> Result<(), SimError> {
        if let Some(status) = self.child.try_wait()? {
            return Err(SimError::Run {
                reason: format!(
                    "ArduSub SITL exited ({status}); its log: {}",
                    self.dir.join("ardusub.log").display()
                ),
            });
        }
        Ok(())
    }

    /// The run ended cleanly: the folder may go with the process.
    fn done(&mut self) {
        if self.remove_dir {
            self.remove_dir = false;
            let _ = self.child.kill();
            let _ = self.child.wait();
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

impl Drop for ArduSubProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// hil's underwater camera, rendering from the physics state the runner sets before each
/// frame: the pose and time of the physics step whose reply ArduSub is waiting for.
pub struct LockstepCamera {
    scene: Scene,
    camera: UnderwaterCamera,
    t_vehicle_cam: Isometry3<f64>,
    t_world_vehicle: Isometry3<f64>,
    time_s: f64,
    limits: ExposureLimits,
    /// The vehicle pose and time of the last frame rendered.
    rendered: Option<(f64, Isometry3<f64>)>,
}

impl LockstepCamera {
    pub fn new(
        scene: Scene,
        camera: UnderwaterCamera,
        t_vehicle_cam: Isometry3<f64>,
        limits: ExposureLimits,
    ) -> Self {
        Self {
            scene,
            camera,
            t_vehicle_cam,
            t_world_vehicle: Isometry3::identity(),
            time_s: 0.0,
            limits,
            rendered: None,
        }
    }

    /// The physics state the next frame is rendered from.
    pub fn set_state(&mut self, time_s: f64, t_world_vehicle: &Isometry3<f64>) {
        self.time_s = time_s;
        self.t_world_vehicle = *t_world_vehicle;
    }

    /// Time and vehicle pose of the last frame rendered.
    pub fn rendered(&self) -> Option<(f64, Isometry3<f64>)> {
        self.rendered
    }
}

impl Camera for LockstepCamera {
    fn name(&self) -> &str {
        "hil-sitl-lockstep"
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        Ok(self.camera.set_exposure_us(exposure_us))
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let t_world_cam = self.t_world_vehicle * self.t_vehicle_cam;
        self.camera.render(
            &self.scene,
            &t_world_cam,
            &self.t_world_vehicle,
            self.time_s,
            frame,
        );
        self.rendered = Some((self.time_s, self.t_world_vehicle));
        Ok(())
    }
}

/// Connect to ArduSub's MAVLink, retrying while a starting SITL has not opened its port.
fn connect(
    site: &LoadedSite,
    url: &str,
    proc: &mut Option<ArduSubProcess>,
) -> Result<VehicleLink, SimError> {
    let mut cfg = site.site.link.clone();
    cfg.url = url.to_string();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        match VehicleLink::connect(&cfg) {
            Ok(l) => return Ok(l),
            Err(e) if Instant::now() < deadline => {
                tracing::debug!(error = %e, "sitl-loop: ArduSub's MAVLink not open yet");
                if let Some(p) = proc.as_mut() {
                    p.check_alive()?;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
            Err(e) => return Err(e).step(|| format!("connecting to ArduSub SITL at {url}")),
        }
    }
}

/// One SITL-in-the-loop run: summary, the hold figures, and the lockstep's counts.
pub struct SitlRun {
    pub summary: Summary,
    pub hold: HoldFigures,
    /// Physics steps (servo packets answered) and camera frames.
    pub steps: u64,
    pub frames: u64,
    /// Simulated seconds from the first servo packet to armed in the site's mode.
    pub armed_after_s: f64,
    /// Frames whose camera pose differed from the physics pose at the frame's time
    /// (always 0: the frame is rendered from the held step).
    pub pose_mismatches: u64,
    /// Each frame's physics time (ArduSub's clock) and the vehicle pose it was rendered
    /// from.
    pub frame_states: Vec<(f64, Isometry3<f64>)>,
}

/// Bind the JSON physics (vehicle at `start`), start ArduSub if asked, and connect to
/// its MAVLink.
pub(crate) fn open_peer(
    site: &LoadedSite,
    opts: &SitlLoopOptions,
    start: &Isometry3<f64>,
    seed: u64,
) -> Result<(Peer, VehicleLink), SimError> {
    let cfg = SitlConfig {
        bind_ip: std::net::IpAddr::from([127, 0, 0, 1]),
        port: opts.json_port(),
    };
    let server = SitlServer::bind(&cfg, &site.site.vehicle, start, seed)
        .step(|| format!("binding the JSON physics on udp 127.0.0.1:{}", cfg.port))?;
    let mut proc = match &opts.ardusub {
        Some(bin) => Some(ArduSubProcess::start(opts, bin)?),
        None => None,
    };
    // SITL waits for a connection on SERIAL0 before it starts: connect first.
    let link = connect(site, &opts.vehicle_url(), &mut proc)?;
    let peer = Peer {
        server,
        proc,
        timeout: opts.peer_timeout,
        last_packet: Instant::now(),
    };
    Ok((peer, link))
}

/// The physics side of a run: the JSON server, ArduSub (maybe started by us), the link.
pub(crate) struct Peer {
    server: SitlServer,
    proc: Option<ArduSubProcess>,
    timeout: Duration,
    last_packet: Instant,
}

impl Peer {
    /// Step the physics by the next servo packet; the reply is held.
    pub(crate) fn step(&mut self) -> Result<(), SimError> {
        loop {
            if self.server.receive(Duration::from_millis(200))?.is_some() && self.server.holding() {
                self.last_packet = Instant::now();
                return Ok(());
            }
            if let Some(p) = self.proc.as_mut() {
                p.check_alive()?;
            }
            ensure(self.last_packet.elapsed() < self.timeout, || {
                SimError::Run {
                    reason: format!(
                        "no servo packet from ArduSub for {:.0} s on udp {} (is it running with \
                 --model JSON, sending to this port?)",
                        self.timeout.as_secs_f64(),
                        self.server
                            .local_addr()
                            .map(|a| a.to_string())
                            .unwrap_or_default()
                    ),
                }
            })?;
        }
    }

    pub(crate) fn time_s(&self) -> f64 {
        self.server.state().time_s
    }

    pub(crate) fn server(&mut self) -> &mut SitlServer {
        &mut self.server
    }

    /// The run ended cleanly (a started ArduSub's folder goes).
    pub(crate) fn done(&mut self) {
        if let Some(p) = self.proc.as_mut() {
            p.done();
        }
    }
}

/// Run the loop with ArduSub SITL as the autopilot for `hil.seconds` simulated seconds.
pub fn run_sitl_loop(
    site: &LoadedSite,
    opts: &SitlLoopOptions,
    hil: &HilOptions,
    observers: Observers,
) -> Result<SitlRun, SimError> {
    let wall = Instant::now();
    let s = &site.site;
    let t_world_marker = site.t_world_marker();
    let t_marker_station = s.station.t_marker_vehicle();
    let offset = if hil.start_on_station {
        Isometry3::identity()
    } else {
        start_offset(&s.vehicle)
    };
    let start = t_world_marker * t_marker_station * offset;
    let (mut peer, mut link) = open_peer(site, opts, &start, hil.seed)?;
    let mode = s.link.mode.ardusub();
    let armed_after_s = arm(&mut peer, &mut link, mode, opts.arm_timeout_s)?;

    // The camera and the loop.
    let lstart = loop_start(site, hil);
    let lighting = lighting_of(site, hil);
    let limits = site.limits();
    let scene = site_scene(site, &lighting, t_world_marker, hil.seed)?;
    let mut ucam = UnderwaterCamera::new(camera_model(site, limits), hil.seed)?;
    ucam.set_exposure_us(lstart.initial_exposure_us);
    let mut cam = LockstepCamera::new(scene, ucam, site.t_vehicle_cam(), limits);
    let link = EngagedLink::new(link, true);
    let mut pipeline = Pipeline::new(site, lstart, link, observers)?;
    let fps = s.camera.fps;
    let frames = (hil.seconds * fps).round().max(1.0) as u64;
    let mut stats = RunStats::new(frames as usize, t_world_marker, t_marker_station);
    let mut hold = HoldSeries::new(frames as usize, t_world_marker, t_marker_station);
    let t0 = peer.time_s();
    let mut frame = 0u64;
    let mut steps = 0u64;
    let mut mismatches = 0u64;
    let mut frame_states = Vec::with_capacity(frames as usize);
    let mut interrupted = false;
    let mut events = Vec::with_capacity(16);
    let result = (|| -> Result<(), SimError> {
        while frame < frames && !interrupted {
            peer.step()?;
            steps += 1;
            let st = peer.server.state();
            let due = t0 + frame as f64 / fps;
            if st.time_s + 1e-9 >= due {
                if hil.stop.as_ref().is_some_and(|s| s.is_set()) {
                    pipeline.set_shutdown(true);
                    interrupted = true;
                }
                // Loop time starts at zero with the first frame.
                let now = st.time_s - t0;
                cam.set_state(now, &st.t_world_vehicle);
                let rec = pipeline.step(&mut cam)?;
                if cam.rendered() != Some((now, st.t_world_vehicle)) {
                    mismatches += 1;
                }
                if let Some((_, pose)) = cam.rendered() {
                    frame_states.push((st.time_s, pose));
                }
                events.clear();
                events.extend_from_slice(pipeline.events());
                pipeline.link_mut().on_events(&events, rec.stamp_s)?;
                let truth = truth_of(&st, &site.t_vehicle_cam(), t_world_marker, &peer.server);
                stats.push(&rec, &truth);
                hold.push(&rec, &truth);
                frame += 1;
            }
            peer.server.reply()?;
        }
        Ok(())
    })();
    // Neutral, then the exit policy, each given simulated time to be read and applied
    // before the link closes.
    let now = peer.time_s() - t0;
    let _ = pipeline.link_mut().send_neutral(now);
    let settle = |peer: &mut Peer, pipeline: &mut Pipeline<EngagedLink>, secs: f64| {
        let end = peer.time_s() + secs;
        while peer.time_s() < end {
            peer.step()?;
            let t = peer.time_s() - t0;
            pipeline.link_mut().inner_mut().tick(t)?;
            peer.server.reply()?;
        }
        Ok::<(), SimError>(())
    };
    let settled = settle(&mut peer, &mut pipeline, 0.5).and_then(|_| {
        let now = peer.time_s() - t0;
        pipeline.link_mut().stop_lockstep(now)?;
        settle(&mut peer, &mut pipeline, 0.5)
    });
    let observed = pipeline.finish_observers();
    result?;
    settled?;
    observed?;
    peer.done();
    let mut summary = stats.summary(
        lstart.method,
        lighting.scenario,
        hil.seed,
        wall.elapsed().as_secs_f64(),
        0,
    );
    summary.interrupted = interrupted;
    super::hil::write_plots_of(site, hil, &stats, &summary)?;
    Ok(SitlRun {
        summary,
        hold: hold.figures(),
        steps,
        frames: frame,
        armed_after_s,
        pose_mismatches: mismatches,
        frame_states,
    })
}

/// The world's truth at a physics state, for the run's statistics.
pub(crate) fn truth_of(
    st: &markhold_hil::VehicleState,
    t_vehicle_cam: &Isometry3<f64>,
    t_world_marker: Isometry3<f64>,
    server: &SitlServer,
) -> Truth {
    let t_world_cam = st.t_world_vehicle * t_vehicle_cam;
    let v = st.velocity_world_mps;
    let mut pwm = [1500u16; 8];
    pwm.copy_from_slice(&server.last_pwm()[..8]);
    Truth {
        time_s: st.time_s,
        t_world_vehicle: st.t_world_vehicle,
        t_world_cam,
        t_cam_marker: t_world_cam.inverse() * t_world_marker,
        velocity_world_mps: [v.x, v.y, v.z],
        armed: true,
        mode: 0,
        pwm,
        lockstep_timeouts: 0,
    }
}

/// Bring ArduSub up as a pilot would: powered on at the surface above the start (its
/// depth sensor takes the surface pressure as zero, `AP_Baro::update_calibration` at
/// boot; ArduSub's surface detection, surface_bottom_detector.cpp, compares depth
/// against SURFACE_DEPTH), held there until its EKF has a position, carried down to the
/// start pose at `DESCENT_MPS`, held still, then armed in `mode` and let go. Serves the
/// physics throughout (neutral input); returns the simulated seconds from the first
/// servo packet to armed. Requests repeat every simulated second.
pub(crate) fn arm(
    peer: &mut Peer,
    link: &mut VehicleLink,
    mode: ArduSubMode,
    timeout_s: f64,
) -> Result<f64, SimError> {
    let start = peer.server.start_pose();
    let mut surface = start;
    surface.translation.z = 0.0;
    peer.step()?;
    let t0 = peer.time_s();
    let mut next_tick = t0;
    let mut next_request = t0;
    // When the descent began and when the vehicle reached the start.
    let mut descent_from: Option<f64> = None;
    let mut at_start_s: Option<f64> = None;
    let depth = start.translation.z.max(0.0);
    loop {
        let t = peer.time_s();
        // Where the hand holds the vehicle now.
        let (pose, vz) = match descent_from {
            None => (surface, 0.0),
            Some(t1) => {
                let z = ((t - t1) * DESCENT_MPS).min(depth);
                let mut p = start;
                p.translation.z = z;
                let moving = z < depth;
                if !moving && at_start_s.is_none() {
                    at_start_s = Some(t);
                }
                (p, if moving { DESCENT_MPS } else { 0.0 })
            }
        };
        peer.server
            .carry(&pose, &nalgebra::Vector3::new(0.0, 0.0, vz));
        if t >= next_tick {
            link.tick(t - t0)?;
            next_tick = t + 0.01;
            let st = link.state();
            let (armed, now_mode, discovered) = (st.armed, st.mode, st.discovered);
            if armed && now_mode == Some(mode) {
                peer.server.reply()?;
                return Ok(t - t0);
            }
            // Its EKF first: a position estimate and the settle time.
            let ready = discovered && st.local_position.is_some() && t - t0 >= ARM_SETTLE_S;
            if ready && descent_from.is_none() {
                descent_from = Some(t);
            }
            let settled = at_start_s.is_some_and(|t2| t - t2 >= HOLD_BEFORE_ARM_S);
            if settled && t >= next_request {
                link.send_neutral(t - t0)?;
                link.request_mode(mode, t - t0)?;
                if now_mode == Some(mode) {
                    link.request_arm(true, t - t0)?;
                }
                next_request = t + 1.0;
            }
            ensure(t - t0 < timeout_s, || SimError::Run {
                reason: format!(
                    "ArduSub did not arm in {mode:?} within {timeout_s} simulated seconds \
                 (heartbeat {}, mode {:?}, armed {})",
                    discovered, now_mode, armed
                ),
            })?;
        }
        peer.server.reply()?;
        peer.step()?;
    }
}

/// `markhold sitl-loop`.
#[derive(clap::Args)]
pub struct SitlLoopArgs {
    /// Dive-site file.
    #[arg(long, default_value = "params/pool.toml")]
    pub site: PathBuf,
    /// The ArduSub SITL binary to start with `--model JSON` (e.g.
    /// build/sitl/bin/ardusub). Without it, an ArduSub already running sends its servo
    /// packets here: `sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON`.
    #[arg(long, value_name = "PATH")]
    pub ardusub: Option<PathBuf>,
    /// Parameter defaults for the started ArduSub (e.g.
    /// Tools/autotest/default_params/sub-6dof.parm).
    #[arg(long, value_name = "FILE.parm")]
    pub defaults: Option<PathBuf>,
    /// The started ArduSub's depth-sensor noise, SITL's SIM_BARO_RND (m, uniform +-),
    /// set after --defaults. SITL's own default, 0.2, is an aircraft's altitude noise:
    /// 0.2 m of water.
    /// [default: 0.02, what ArduSub's sub-6dof.parm means by its BARO_RND]
    #[arg(long, value_name = "M")]
    pub depth_noise_m: Option<f64>,
    /// SITL instance N: MAVLink on 5760 + 10 N, JSON servo packets to 9002 + 10 N.
    #[arg(long, default_value_t = 0)]
    pub instance: u16,
    /// ArduSub's --speedup for the started binary (the lockstep holds at any speed).
    #[arg(long, default_value_t = 100)]
    pub speedup: u32,
    /// ArduSub's MAVLink (default tcp:127.0.0.1:5760 + 10 N; with sim_vehicle.py, whose
    /// MAVProxy takes 5760: tcp:127.0.0.1:5762).
    #[arg(long, value_name = "MAVLINK_URL")]
    pub vehicle: Option<String>,
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Seed of the simulated world.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Write a JSON summary here.
    #[arg(long)]
    pub summary: Option<PathBuf>,
    /// Folder the started ArduSub runs in (its log, eeprom.bin); kept after the run.
    #[arg(long, value_name = "DIR")]
    pub work_dir: Option<PathBuf>,
}

/// The JSON summary of `markhold sitl-loop`: the HIL summary and the hold figures.
#[derive(serde::Serialize)]
struct SitlLoopSummary<'a> {
    summary: &'a Summary,
    hold: &'a HoldFigures,
    physics_steps: u64,
    frames: u64,
    armed_after_s: f64,
    camera_pose_mismatches: u64,
    /// SIM_BARO_RND given to the started ArduSub (none: an ArduSub started elsewhere).
    sitl_depth_noise_m: Option<f64>,
}

pub fn cli(args: SitlLoopArgs) -> Result<(), SimError> {
    let site = markhold_core::params::load(&args.site)?;
    super::hil::check_start(&site)?;
    ensure(
        args.seconds > 0.0 && args.seconds <= super::summary::MAX_SECONDS,
        || SimError::Usage {
            reason: format!(
                "--seconds {}: expected a positive number of simulated seconds, at most {}",
                args.seconds,
                super::summary::MAX_SECONDS
            ),
        },
    )?;
    ensure(args.instance <= 100, || SimError::Usage {
        reason: format!(
            "--instance {}: expected 0..=100 (ports 5760 + 10 N and 9002 + 10 N)",
            args.instance
        ),
    })?;
    ensure(
        args.ardusub.is_some() || args.depth_noise_m.is_none(),
        || SimError::Usage {
            reason: "--depth-noise-m: only for an ArduSub markhold starts (--ardusub); \
                     for one started elsewhere set SIM_BARO_RND in its parameters"
                .to_string(),
        },
    )?;
    let opts = SitlLoopOptions {
        ardusub: args.ardusub,
        defaults: args.defaults,
        depth_noise_m: args.depth_noise_m.unwrap_or(SITL_DEPTH_NOISE_M),
        instance: args.instance,
        speedup: args.speedup,
        vehicle_url: args.vehicle,
        work_dir: args.work_dir,
        ..SitlLoopOptions::default()
    };
    let hil = HilOptions {
        seconds: args.seconds,
        seed: args.seed,
        stop: Some(markhold_core::signal::install()?),
        ..HilOptions::default()
    };
    let run = run_sitl_loop(&site, &opts, &hil, Observers::default())?;
    let h = &run.hold;
    markhold_core::outln!(
        "markhold sitl-loop: {} on ArduSub SITL, seed {}: armed after {:.1} s; {} frames, {} physics steps\n  \
         position RMS {:.1} mm, final error {:.1} mm, heading std {:.2} deg, yaw effort std {:.3}, \
         heave effort std {:.3}, thruster reversals {:.2}/s, marker {:.0} %",
        site.site.site.name,
        args.seed,
        run.armed_after_s,
        run.frames,
        run.steps,
        h.position_rms_m * 1e3,
        h.final_error_m * 1e3,
        h.heading_std_deg,
        h.yaw_effort_std,
        h.heave_effort_std,
        h.thruster_reversals_per_s,
        h.detection_rate * 100.0
    );
    if let Some(path) = &args.summary {
        let out = SitlLoopSummary {
            summary: &run.summary,
            hold: &run.hold,
            physics_steps: run.steps,
            frames: run.frames,
            armed_after_s: run.armed_after_s,
            camera_pose_mismatches: run.pose_mismatches,
            sitl_depth_noise_m: opts.ardusub.is_some().then_some(opts.depth_noise_m),
        };
        let text = serde_json::to_string_pretty(&out)?;
        std::fs::write(path, text).step(|| format!("writing {}", path.display()))?;
    }
    if run.summary.interrupted {
        std::process::exit(markhold_core::signal::INTERRUPTED_EXIT);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("markhold-sitl-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("scratch folder");
        d
    }

    #[test]
    fn sitl_defaults_lists_the_users_file_then_the_depth_noise() {
        let dir = scratch("defaults");
        let user = dir.join("sub-6dof.parm");
        std::fs::write(&user, "BARO_RND 0.02\n").expect("user file");
        let arg = sitl_defaults(Some(&user), &dir, 0.005).expect("defaults");
        let arg = arg.to_string_lossy().into_owned();
        let (first, ours) = arg.split_once(',').expect("two files");
        assert_eq!(Path::new(first), std::fs::canonicalize(&user).unwrap());
        let text = std::fs::read_to_string(ours).expect("markhold's file");
        assert!(text.lines().any(|l| l == "SIM_BARO_RND 0.005"), "{text}");
        // Without a user file, markhold's alone.
        let alone = sitl_defaults(None, &dir, 0.02).expect("defaults");
        assert!(!alone.to_string_lossy().contains(','));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn sitl_defaults_refuses_bad_noise_and_comma_paths() {
        let dir = scratch("refused");
        for bad in [-0.01, f64::NAN, 2.0] {
            let e = sitl_defaults(None, &dir, bad)
                .expect_err("refused")
                .to_string();
            assert!(e.contains("--depth-noise-m"), "{e}");
        }
        let user = dir.join("a,b.parm");
        std::fs::write(&user, "").expect("user file");
        let e = sitl_defaults(Some(&user), &dir, 0.02)
            .expect_err("refused")
            .to_string();
        assert!(e.contains("a,b.parm") && e.contains("comma"), "{e}");
        let e = sitl_defaults(Some(&dir.join("missing.parm")), &dir, 0.02)
            .expect_err("refused")
            .to_string();
        assert!(e.contains("missing.parm"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The started binary gets the list: a stand-in `ardusub` that writes its arguments.
    #[test]
    fn a_started_ardusub_reads_the_depth_noise_after_the_users_defaults() {
        use std::os::unix::fs::PermissionsExt;
        let dir = scratch("spawn");
        let bin = dir.join("ardusub");
        std::fs::write(&bin, "#!/bin/sh\nprintf '%s\\n' \"$@\" > args.txt\n").expect("stand-in");
        std::fs::set_permissions(&bin, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        let user = dir.join("sub.parm");
        std::fs::write(&user, "FRAME_CONFIG 2\n").expect("user file");
        let work = dir.join("work");
        let opts = SitlLoopOptions {
            defaults: Some(user.clone()),
            depth_noise_m: 0.004,
            work_dir: Some(work.clone()),
            ..SitlLoopOptions::default()
        };
        let mut p = ArduSubProcess::start(&opts, &bin).expect("started");
        let deadline = Instant::now() + Duration::from_secs(10);
        while p.child.try_wait().expect("wait").is_none() {
            assert!(Instant::now() < deadline, "stand-in did not exit");
            std::thread::sleep(Duration::from_millis(20));
        }
        let args = std::fs::read_to_string(work.join("args.txt")).expect("args");
        let args: Vec<&str> = args.lines().collect();
        let i = args
            .iter()
            .position(|a| *a == "--defaults")
            .expect("--defaults");
        let files: Vec<&str> = args[i + 1].split(',').collect();
        assert_eq!(files.len(), 2, "{args:?}");
        assert_eq!(Path::new(files[0]), std::fs::canonicalize(&user).unwrap());
        let ours = std::fs::read_to_string(files[1]).expect("markhold's file");
        assert!(ours.contains("SIM_BARO_RND 0.004"), "{ours}");
        drop(p);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
