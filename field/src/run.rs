//! `markhold run`: the loop on a real camera and a real ArduSub link, with start-up
//! checks, Ctrl-C / SIGTERM handling, recording and the Foxglove live view.
//!
//! Time is the camera's: frame stamps are the loop's clock. The wall clock only bounds
//! start-up waits and paces a recorded-frames camera to its stamps.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use markhold_autopilot::{CommandStatus, Directive, FailsafeEvent, VehicleLink};
use markhold_exposure::{Camera, CameraError};
use serde::Serialize;

use super::camera::stream::DecoderReport;
use super::camera::{open_camera, CameraUrl, FrameAge, LiveCamera};
use super::preflight::{self, Checklist};
pub use markhold_core::engage::HandBack;
use markhold_core::engage::{EngagedLink, ExitPolicy, ExitReport, Transition};
use markhold_core::error::{Chain, CoreError};

use crate::FieldError;
use markhold_core::observe::{Snapshots, StatusBoard, TraceWriter};
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::{CommandLink, LoopStart, Observers, Pipeline};
use markhold_core::record::{RecordConfig, RecordStats, RecordStatsHandle, Recorder, RunInfo};
use markhold_core::signal::ShutdownFlag;

/// `markhold run`'s options.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// MAVLink URL (default: the site's `[link] url`).
    pub link_url: Option<String>,
    pub camera: CameraUrl,
    pub record: Option<PathBuf>,
    /// Serve the Foxglove WebSocket live view on 127.0.0.1 at this port (0: any free).
    pub foxglove_port: Option<u16>,
    /// Wall seconds to wait for the vehicle's first heartbeat.
    pub heartbeat_timeout_s: f64,
    /// Request the site's mode and arm before the first frame.
    pub arm: bool,
    /// Stop after this many seconds of loop time.
    pub max_seconds: Option<f64>,
    /// Play a recorded-frames camera at the pace of its stamps (a real camera paces itself).
    pub pace_frames: bool,
    /// Write one CSV row per frame here.
    pub trace: Option<PathBuf>,
    /// Save every `frames_every`-th camera frame here as a recorded-frames folder (what
    /// `--camera frames:DIR` plays back).
    pub frames_dir: Option<PathBuf>,
    pub frames_every: u64,
    /// Engage as soon as the vehicle is heard (else the pilot engages from the console).
    pub engage: bool,
    /// Check the vehicle's parameters before arming (`markhold preflight`).
    pub preflight: bool,
    /// The web page (`--web`).
    pub web: markhold_core::web::WebArgs,
    /// Address the live view listens on (`--foxglove-bind`).
    pub foxglove_bind: std::net::IpAddr,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            link_url: None,
            camera: CameraUrl::V4l2("/dev/video0".into()),
            record: None,
            foxglove_port: None,
            heartbeat_timeout_s: 5.0,
            arm: false,
            max_seconds: None,
            pace_frames: true,
            trace: None,
            frames_dir: None,
            frames_every: 1,
            engage: false,
            preflight: true,
            web: markhold_core::web::WebArgs::default(),
            foxglove_bind: std::net::Ipv4Addr::LOCALHOST.into(),
        }
    }
}

/// A start-up check that failed: the run does not start.
#[derive(Debug, thiserror::Error)]
pub enum StartupError {
    #[error("camera {url}: cannot open it: {reason}")]
    Camera { url: String, reason: String },
    #[error("camera {url}: the driver refused manual exposure ({exposure_us} us): {reason}")]
    Exposure {
        url: String,
        exposure_us: f64,
        reason: String,
    },
    #[error("camera {url}: no first frame: {reason}")]
    FirstFrame { url: String, reason: String },
    #[error("camera {url} gives {width}x{height} frames but the site's calibration is for {calib_width}x{calib_height}: recalibrate or set camera.width_px / height_px")]
    Resolution {
        url: String,
        width: u32,
        height: u32,
        calib_width: u32,
        calib_height: u32,
    },
    #[error("link {url}: cannot open it: {reason}")]
    Link { url: String, reason: String },
    #[error("link {url}: no vehicle heartbeat within {timeout_s} s (is the vehicle on, and this the right address/port?)")]
    NoHeartbeat { url: String, timeout_s: f64 },
    #[error("link {url}: the vehicle did not arm in {mode:?} within {timeout_s} s")]
    Arm {
        url: String,
        mode: markhold_autopilot::ArduSubMode,
        timeout_s: f64,
    },
    #[error("--record: {source}")]
    Record {
        source: markhold_core::record::RecordError,
    },
    #[error("--foxglove: {reason}")]
    LiveView { reason: String },
    #[error("{0}")]
    Web(#[from] markhold_core::web::WebError),
    #[error("{flag}: {reason}")]
    Output { flag: &'static str, reason: String },
    #[error("link {url}: the vehicle failed the preflight check ({fails} failed: {names}); fix it or run with --no-preflight")]
    Preflight {
        url: String,
        fails: usize,
        names: String,
    },
}

/// Why the loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    Signal,
    EndOfStream,
    /// `--seconds` of camera time, or of wall time since the loop started.
    MaxSeconds,
    /// No camera frame for `[camera] stall_exit_s`.
    CameraLost,
}

/// What a `run` did.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub frames: u64,
    pub detected: u64,
    /// Loop time from the first frame to the last, seconds.
    pub loop_seconds: f64,
    pub stopped_by: StopReason,
    pub record: Option<RecordStats>,
    /// The recording or live view failed to close cleanly (the run itself went on).
    pub record_error: Option<String>,
    /// Where the live view listened, if it was on.
    pub foxglove_addr: Option<String>,
    /// Times the camera stalled long enough for the vision-stall failsafe (neutral).
    pub vision_stalls: u64,
    /// Disarm on exit (`link.disarm_on_exit` and a signal): how the request ended.
    pub disarm: Option<CommandStatus>,
    /// Frames the camera took that the loop was too slow to see (it acts on the newest).
    pub frames_passed_over: u64,
    /// Frames the loop acted on per second of camera time (frame stamps).
    pub effective_fps: Option<f64>,
    /// Frames the camera gave per second of camera time, those passed over included.
    pub camera_fps: Option<f64>,
    /// The frame rate the keeper was designed and checked at: the site's `[camera] fps`.
    pub designed_fps: f64,
    /// Times the loop's rate over a window of camera time fell under the designed rate
    /// (each one warned on the console and in the log).
    pub rate_warnings: u64,
    /// How old the frames the loop acted on were when it came back for the next one
    /// (paced recordings).
    pub frame_age: Option<FrameAge>,
    /// A stream camera's H.264 decoder: the element, hardware or not, and the decoders
    /// tried before it with the reason each was passed over.
    pub stream_decoder: Option<DecoderReport>,
    /// Times the pilot (or `--engage`) engaged markhold.
    pub engagements: u64,
    /// Engagement changes with their loop time.
    pub engagement: Vec<(f64, Transition)>,
    /// Pilot input the loop computed while disengaged (not sent).
    pub withheld: u64,
    /// STATUSTEXT messages sent to the pilot.
    pub statustexts: u64,
    /// `on_exit = "hand_back"`: how the hand-back ended.
    pub hand_back: Option<HandBack>,
    /// The exit: the neutral input seen applied, the policy, the link's close.
    pub exit: ExitReport,
    /// The preflight checklist, when it ran.
    pub preflight: Option<Checklist>,
    /// Times a stream camera's exposure was taken (engaged) and put back as found.
    pub camera_taken: u64,
    pub camera_restored: u64,
    /// The camera's exposure could not be put back at the end (the state file beside the
    /// site stays, and the next start puts it back).
    pub camera_restore_error: Option<String>,
    /// Wall seconds of the loop, from the first frame to the end.
    pub wall_seconds: f64,
}

/// Open the link and wait (wall clock, bounded) for the vehicle's heartbeat; `now_s`
/// is the loop time of the first frame.
fn open_link(
    site: &LoadedSite,
    opts: &RunOptions,
    now_s: f64,
    stop: &ShutdownFlag,
    checklist_out: &mut Option<Checklist>,
) -> Result<VehicleLink, StartupError> {
    let mut cfg = site.site.link.clone();
    if let Some(u) = &opts.link_url {
        cfg.url = u.clone();
    }
    let url = cfg.url.clone();
    let link_err = |reason: String| StartupError::Link {
        url: url.clone(),
        reason,
    };
    let mut link = VehicleLink::connect(&cfg).map_err(|e| link_err(e.to_string()))?;
    // No pilot input before the pilot (or --engage) engages.
    link.set_pilot_keepalive(false);
    // Loop time is the camera's clock, which jumps at start-up and when a stream is
    // built again: whether the vehicle is heard is judged on the link's own clock.
    link.set_monotonic_liveness(true);
    let timeout = Duration::from_secs_f64(opts.heartbeat_timeout_s.clamp(0.0, 600.0));
    let deadline = Instant::now() + timeout;
    loop {
        link.tick(now_s).map_err(|e| link_err(e.to_string()))?;
        if link.state().last_heartbeat_s.is_some() {
            break;
        }
        if Instant::now() >= deadline || stop.is_set() {
            return Err(StartupError::NoHeartbeat {
                url,
                timeout_s: opts.heartbeat_timeout_s,
            });
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    if opts.preflight {
        let list = preflight::check(&mut link, site, now_s, stop);
        eprint!("{}", list.render());
        if list.failed() > 0 {
            return Err(StartupError::Preflight {
                url,
                fails: list.failed(),
                names: list.failed_names(),
            });
        }
        checklist_out.replace(list);
    }
    if opts.arm {
        let mode = site.site.link.mode.ardusub();
        link.request_mode(mode, now_s)
            .map_err(|e| link_err(e.to_string()))?;
        link.request_arm(true, now_s)
            .map_err(|e| link_err(e.to_string()))?;
        let deadline = Instant::now() + timeout;
        while !link.state().armed {
            if Instant::now() >= deadline || stop.is_set() {
                return Err(StartupError::Arm {
                    url,
                    mode,
                    timeout_s: opts.heartbeat_timeout_s,
                });
            }
            std::thread::sleep(Duration::from_millis(10));
            link.tick(now_s).map_err(|e| link_err(e.to_string()))?;
        }
    }
    Ok(link)
}

fn is_end_of_stream(e: &CoreError) -> bool {
    matches!(e.camera(), Some(CameraError::EndOfStream { .. }))
}

/// The observers, the recording's counters, the live view's address and the web page's
/// board.
type Attached = (
    Observers,
    Option<RecordStatsHandle>,
    Option<String>,
    Option<StatusBoard>,
);

/// The recording, the live view and the web page a run asked for, as observers of its
/// loop.
fn observers(
    site: &LoadedSite,
    opts: &RunOptions,
    start: &LoopStart,
) -> Result<Attached, StartupError> {
    let record_err = |source| StartupError::Record { source };
    let mut recorder = match &opts.record {
        Some(path) => {
            let options = format!(
                "run --site {} --camera {} --link {}",
                site.path.display(),
                opts.camera,
                opts.link_url.as_deref().unwrap_or(&site.site.link.url)
            );
            let info = RunInfo::new(
                "run",
                site,
                start.method,
                start.initial_exposure_us,
                options,
            )
            .map_err(record_err)?;
            Some(
                Recorder::create(
                    path,
                    &info,
                    site.site
                        .record
                        .config(markhold_core::record::ImageFormat::Jpeg),
                )
                .map_err(record_err)?,
            )
        }
        None if opts.foxglove_port.is_some() => {
            Some(Recorder::live_only(RecordConfig::default()).map_err(record_err)?)
        }
        None => None,
    };
    let mut foxglove_addr = None;
    if let (Some(port), Some(r)) = (opts.foxglove_port, recorder.as_mut()) {
        match r.serve_live_on(opts.foxglove_bind, port, &site.site.live) {
            Ok(p) => {
                let addr = std::net::SocketAddr::new(opts.foxglove_bind, p);
                eprintln!("markhold run: Foxglove live view on ws://{addr}");
                foxglove_addr = Some(addr.to_string());
            }
            Err(e) => {
                if let Some(r) = recorder.take() {
                    r.abort();
                }
                return Err(StartupError::LiveView {
                    reason: e.to_string(),
                });
            }
        }
    }
    let stats = recorder
        .as_ref()
        .filter(|_| opts.record.is_some())
        .map(Recorder::stats_handle);
    let control = recorder
        .as_ref()
        .filter(|_| opts.record.is_some())
        .map(Recorder::control);
    let live = opts
        .foxglove_port
        .is_some()
        .then(|| markhold_core::web::LiveInfo {
            port: foxglove_addr
                .as_deref()
                .and_then(|a| a.parse::<std::net::SocketAddr>().ok())
                .map_or(0, |a| a.port()),
            loopback: opts.foxglove_bind.is_loopback(),
        });
    let mut list = Observers::new();
    if let Some(r) = recorder {
        list.push(r);
    }
    let attached = files(opts, &mut list).and_then(|()| {
        Ok(markhold_core::web::attach(
            site, &opts.web, "run", control, live, &mut list,
        )?)
    });
    match attached {
        Ok(web) => Ok((list, stats, foxglove_addr, web.map(|(board, _)| board))),
        Err(e) => {
            // Nothing half-made is left behind (the recording file is removed).
            list.abort();
            Err(e)
        }
    }
}

/// The trace and the recorded-frames folder a run asked for.
fn files(opts: &RunOptions, list: &mut Observers) -> Result<(), StartupError> {
    if let Some(p) = &opts.trace {
        let t = TraceWriter::create(p).map_err(|e| StartupError::Output {
            flag: "--trace",
            reason: Chain(&e).to_string(),
        })?;
        list.push(t);
    }
    if let Some(dir) = &opts.frames_dir {
        let s = Snapshots::create(dir, opts.frames_every).map_err(|e| StartupError::Output {
            flag: "--record-frames",
            reason: Chain(&e).to_string(),
        })?;
        list.push(s);
    }
    Ok(())
}

/// The loop of a live run: the site's start, a real link (behind engagement in `run`),
/// the run's observers.
pub fn build_loop<L: CommandLink>(
    site: &LoadedSite,
    link: L,
    observers: Observers,
) -> Result<Pipeline<L>, CoreError> {
    Pipeline::new(site, LoopStart::of_site(site), link, observers)
}

/// The loop's rate falls under this fraction of the designed rate: warned.
pub const RATE_WARN_FRACTION: f64 = 0.9;
/// The loop's rate is judged over windows of this much camera time.
pub const RATE_WINDOW_S: f64 = 2.0;
/// Test-only: milliseconds the loop sleeps after each frame, to show a loop slower than
/// its camera acting on the newest frame. Never set in the field; a run says so when it is.
pub const TEST_DELAY_ENV: &str = "MARKHOLD_TEST_LOOP_DELAY_MS";

/// The test-only delay per frame from [`TEST_DELAY_ENV`] (at most 1 s), if set.
fn test_delay() -> Result<Option<Duration>, FieldError> {
    let Ok(v) = std::env::var(TEST_DELAY_ENV) else {
        return Ok(None);
    };
    let ms: u64 = v
        .trim()
        .parse()
        .ok()
        .filter(|ms| *ms <= 1000)
        .ok_or_else(|| FieldError::Env {
            name: TEST_DELAY_ENV,
            value: v.clone(),
            expected: "milliseconds 0..=1000",
        })?;
    Ok(Some(Duration::from_millis(ms)))
}

/// The loop's frame rate over windows of camera time, against the designed rate.
struct RateWatch {
    designed_fps: f64,
    window_start_s: Option<f64>,
    frames: u64,
    below: bool,
    warnings: u64,
}

impl RateWatch {
    fn new(designed_fps: f64) -> Self {
        Self {
            designed_fps,
            window_start_s: None,
            frames: 0,
            below: false,
            warnings: 0,
        }
    }

    /// A frame acted on at `stamp_s`: at the end of a window, the window's rate and
    /// whether it just fell under the designed rate (warn once until it recovers).
    fn frame(&mut self, stamp_s: f64) -> Option<(f64, bool)> {
        let Some(t0) = self.window_start_s else {
            self.window_start_s = Some(stamp_s);
            return None;
        };
        self.frames += 1;
        let span = stamp_s - t0;
        if span < RATE_WINDOW_S {
            // A stamp going back (a rebuilt stream) starts the window again.
            if span < 0.0 {
                self.window_start_s = Some(stamp_s);
                self.frames = 0;
            }
            return None;
        }
        let rate = self.frames as f64 / span;
        self.window_start_s = Some(stamp_s);
        self.frames = 0;
        let low = rate < RATE_WARN_FRACTION * self.designed_fps;
        let fell = low && !self.below;
        self.below = low;
        if fell {
            self.warnings += 1;
        }
        Some((rate, fell))
    }
}

/// Counters of the loop while it runs.
#[derive(Default)]
struct Counts {
    frames: u64,
    detected: u64,
    first_stamp: Option<f64>,
    last_stamp: f64,
    vision_stalls: u64,
    disarm_asked: bool,
    /// The last frame's supervisor events (a buffer reused every frame).
    events: Vec<FailsafeEvent>,
    /// The web page's board: it shows the engagement.
    board: Option<StatusBoard>,
    camera_taken: u64,
    camera_restored: u64,
}

/// What the pilot is told after a frame (or a tick without one): the supervisor's
/// transitions, exposure at a limit, and the station error while engaged.
fn tell_pilot(
    pipeline: &mut Pipeline<EngagedLink>,
    site: &LoadedSite,
    rec: Option<&markhold_core::pipeline::FrameRecord>,
    now_s: f64,
    events: &mut Vec<FailsafeEvent>,
) -> Result<(), FieldError> {
    // A copy into a buffer kept across frames (no allocation): the link is borrowed
    // mutably while the events are read.
    events.clear();
    events.extend_from_slice(pipeline.events());
    pipeline.link_mut().on_events(events, now_s)?;
    let searching = pipeline.keeper_status() == markhold_autopilot::KeeperStatus::Searching;
    pipeline.link_mut().searching(searching, now_s)?;
    let Some(rec) = rec else { return Ok(()) };
    let limits = site.limits();
    let e = rec.exposure.exposure_us;
    let at_limit = e <= limits.min_us * 1.001 || e >= limits.effective_max_us() * 0.999;
    pipeline.link_mut().exposure_at_limit(at_limit, now_s)?;
    if let Some(t_cam_marker) = rec.t_cam_marker {
        let meas = (site.t_vehicle_cam() * t_cam_marker).inverse();
        let goal = site.site.station.t_marker_vehicle();
        let err = markhold_autopilot::keeper::body_error(&meas, &goal);
        let dist = (err[0] * err[0] + err[1] * err[1] + err[2] * err[2]).sqrt();
        pipeline
            .link_mut()
            .station_error(dist, err[5].to_degrees(), now_s)?;
    }
    Ok(())
}

/// The camera's exposure is markhold's only while engaged (`[camera] control_exposure`).
fn sync_camera(pipeline: &Pipeline<EngagedLink>, cam: &mut LiveCamera, n: &mut Counts) {
    let engaged = pipeline.link().engager().engaged();
    if cam.set_engaged(engaged) {
        if engaged {
            n.camera_taken += 1;
        } else {
            n.camera_restored += 1;
        }
        tracing::info!(
            engaged,
            "camera exposure {}",
            if engaged {
                "taken"
            } else {
                "put back as found"
            }
        );
    }
}

/// Step until a signal, the end of a recorded stream, `max_seconds` (camera or wall
/// time) or `[camera] stall_exit_s` without frames.
#[allow(clippy::too_many_arguments)]
fn drive(
    pipeline: &mut Pipeline<EngagedLink>,
    cam: &mut LiveCamera,
    site: &LoadedSite,
    opts: &RunOptions,
    stop: &ShutdownFlag,
    n: &mut Counts,
    rate: &mut RateWatch,
    delay: Option<Duration>,
) -> Result<StopReason, FieldError> {
    let started = Instant::now();
    let stall_exit = Duration::from_secs_f64(site.site.camera.stall_exit_s);
    // Without frames the loop ticks no faster than the link's pilot-input rate, so the
    // neutral it sends never exceeds it.
    let idle_period_s = 1.0 / site.site.link.pilot_input_hz;
    let mut last_idle_s: Option<f64> = None;
    let mut said_stall = false;
    loop {
        if stop.is_set() {
            // This frame sends neutral input (the supervisor's shutdown directive).
            pipeline.set_shutdown(true);
        }
        sync_camera(pipeline, cam, n);
        if opts
            .max_seconds
            .is_some_and(|m| started.elapsed().as_secs_f64() >= m)
        {
            return Ok(StopReason::MaxSeconds);
        }
        let rec = match pipeline.step(cam) {
            Ok(r) => r,
            Err(_) if cam.take_no_frame() => {
                // No frame yet: loop time is the last frame's stamp plus the time waited
                // (the only place the wall clock enters the loop: without frames there
                // is no other clock), so the supervisor can call the camera stalled.
                let waited = cam.since_last_frame();
                if waited >= stall_exit {
                    eprintln!(
                        "markhold run: no camera frame for {:.1} s (camera.stall_exit_s): stopping",
                        waited.as_secs_f64()
                    );
                    return Ok(StopReason::CameraLost);
                }
                if !said_stall && waited >= stall_exit / 4 {
                    said_stall = true;
                    eprintln!(
                        "markhold run: no camera frame for {:.1} s: neutral input; the run ends after {:.0} s without frames",
                        waited.as_secs_f64(),
                        stall_exit.as_secs_f64()
                    );
                }
                let now = n.last_stamp + waited.as_secs_f64();
                if !stop.is_set() && last_idle_s.is_some_and(|t| now - t < idle_period_s) {
                    continue;
                }
                last_idle_s = Some(now);
                let d = pipeline.tick_without_frame(now)?;
                n.vision_stalls += pipeline
                    .events()
                    .iter()
                    .filter(|e| matches!(e, FailsafeEvent::VisionStalled { .. }))
                    .count() as u64;
                tell_pilot(pipeline, site, None, now, &mut n.events)?;
                if let Some(b) = &n.board {
                    b.set_engagement(pipeline.link().engager().state());
                }
                if let Directive::Shutdown { disarm } = d {
                    n.disarm_asked = disarm;
                    return Ok(StopReason::Signal);
                }
                continue;
            }
            Err(e) if is_end_of_stream(&e) => return Ok(StopReason::EndOfStream),
            Err(source) => {
                return Err(FieldError::Frame {
                    frame: n.frames,
                    source: Box::new(source),
                })
            }
        };
        last_idle_s = None;
        said_stall = false;
        n.frames += 1;
        n.detected += u64::from(rec.detected);
        n.last_stamp = rec.stamp_s;
        if let Some((fps, fell)) = rate.frame(rec.stamp_s) {
            if fell {
                tracing::warn!(
                    fps,
                    designed_fps = rate.designed_fps,
                    "loop slower than designed"
                );
                eprintln!(
                    "markhold run: acting on {fps:.1} frames a second, under the {:.0} fps the keeper is designed for ([camera] fps): the loop takes the newest frame (older ones are passed over), but each command comes later",
                    rate.designed_fps
                );
            }
        }
        if let Some(d) = delay {
            std::thread::sleep(d);
        }
        tell_pilot(pipeline, site, Some(&rec), rec.stamp_s, &mut n.events)?;
        if let Some(b) = &n.board {
            b.set_engagement(pipeline.link().engager().state());
        }
        let t0 = *n.first_stamp.get_or_insert(rec.stamp_s);
        if let Directive::Shutdown { disarm } = rec.directive {
            n.disarm_asked = disarm;
            return Ok(StopReason::Signal);
        }
        if opts.max_seconds.is_some_and(|m| rec.stamp_s - t0 >= m) {
            return Ok(StopReason::MaxSeconds);
        }
    }
}

/// The longest the end of a run takes: hand-back or disarm with its retries, putting
/// the camera back, closing the recording.
fn exit_budget(site: &LoadedSite) -> Duration {
    let l = &site.site.link;
    let disarm = l.command_timeout_s * f64::from(l.command_retries + 1) + 0.5;
    let neutral_and_close = l.exit_confirm_timeout_s + markhold_core::engage::CLOSE_TIMEOUT_S;
    Duration::from_secs_f64(l.hand_back_timeout_s + disarm + neutral_and_close)
        + super::camera::CONTROL_FINISH
        + Duration::from_secs(5)
}

/// Says which stream decoder runs, and the test-only delay when set; returns the delay.
fn say_decoder_and_delay(cam: &LiveCamera) -> Result<Option<Duration>, FieldError> {
    if let Some(d) = cam.decoder() {
        eprintln!("markhold run: stream decoder {d}");
    }
    let delay = test_delay()?;
    if let Some(d) = delay {
        eprintln!(
            "markhold run: {TEST_DELAY_ENV}={}: the loop sleeps that long after each frame (a test setting)",
            d.as_millis()
        );
    }
    Ok(delay)
}

/// The loop's and the camera's frame rates over the run (frames acted on, and those with
/// the ones passed over, per second of camera time); a loop under the designed rate is
/// said on the console.
fn run_rates(
    acted: u64,
    passed_over: u64,
    loop_seconds: f64,
    designed_fps: f64,
) -> (Option<f64>, Option<f64>) {
    let per_s =
        |frames: u64| (loop_seconds > 0.0).then(|| frames.saturating_sub(1) as f64 / loop_seconds);
    let effective_fps = per_s(acted);
    if let Some(fps) = effective_fps.filter(|f| *f < RATE_WARN_FRACTION * designed_fps) {
        eprintln!(
            "markhold run: the loop acted on {fps:.1} frames a second over the run, under the {designed_fps:.0} fps the keeper is designed for ([camera] fps); {passed_over} camera frames passed over"
        );
    }
    (effective_fps, per_s(acted + passed_over))
}

/// Run the loop until a signal, the end of a recorded stream or `max_seconds`.
/// Start-up checks come first, in the order: record path, camera (opens, accepts
/// exposure, resolution matches the calibration), vehicle heartbeat, preflight. A failed
/// check removes the recording it had started.
pub fn run_live(
    site: &LoadedSite,
    opts: &RunOptions,
    stop: &ShutdownFlag,
) -> Result<RunReport, FieldError> {
    let start = LoopStart::of_site(site);
    let (mut observers, record_stats, foxglove_addr, board) = observers(site, opts, &start)?;
    let mut checklist = None;
    let started = (|| -> Result<(LiveCamera, VehicleLink), FieldError> {
        let cam = open_camera(
            site,
            &opts.camera,
            start.initial_exposure_us,
            stop,
            opts.pace_frames,
        )?;
        let link = open_link(site, opts, cam.next.meta.stamp_s, stop, &mut checklist)?;
        Ok((cam, link))
    })();
    let (mut cam, link) = match started {
        Ok(v) => v,
        Err(e) => {
            observers.abort();
            return Err(e);
        }
    };
    let link = EngagedLink::new(link, opts.engage);
    let mut pipeline = build_loop(site, link, observers)?;
    tracing::info!(camera = %opts.camera, "running");
    eprintln!(
        "markhold run: running (camera {}, {}, Ctrl-C to stop)",
        opts.camera,
        if opts.engage {
            "engaged at start".to_string()
        } else {
            format!(
                "the pilot engages by arming in {:?}",
                site.site.link.mode.ardusub()
            )
        }
    );
    let delay = say_decoder_and_delay(&cam)?;
    let mut n = Counts {
        last_stamp: cam.next.meta.stamp_s,
        events: Vec::with_capacity(16),
        board,
        ..Counts::default()
    };
    let designed_fps = site.site.camera.fps;
    let mut rate = RateWatch::new(designed_fps);
    let loop_started = Instant::now();
    let stopped = drive(
        &mut pipeline,
        &mut cam,
        site,
        opts,
        stop,
        &mut n,
        &mut rate,
        delay,
    );
    let wall_seconds = loop_started.elapsed().as_secs_f64();
    // The exit below is bounded: after a signal, the watchdog waits for it.
    stop.allow_exit_within(exit_budget(site));
    // The camera goes back as found at once (on the control's thread, beside the exit).
    if cam.set_engaged(false) {
        n.camera_restored += 1;
    }
    // Leave the vehicle as the site says, whatever ended the loop (the same exit as
    // `hil --vehicle`): neutral seen applied while markhold was commanding, then disarm
    // or hand back, then the link closed; then the recording (it keeps the exit's
    // MAVLink), also after an error. An error hands back rather than disarming.
    let site_policy = ExitPolicy::of(pipeline.link().inner().config());
    let policy = if stopped.is_ok() && (n.disarm_asked || site_policy == ExitPolicy::Disarm) {
        ExitPolicy::Disarm
    } else {
        ExitPolicy::HandBack
    };
    let exit = pipeline.link_mut().exit(policy, n.last_stamp);
    let (disarm, hand_back) = (exit.disarm, exit.hand_back);
    let observers_done = pipeline.finish_observers();
    let camera_restore_error = cam.finish_control(super::camera::CONTROL_FINISH).err();
    if let Some(e) = &camera_restore_error {
        eprintln!("markhold run: {e}");
    }
    let stopped_by = stopped?;
    let link = pipeline.link();
    let loop_seconds = n.first_stamp.map_or(0.0, |t0| n.last_stamp - t0);
    let passed_over = cam.frames_passed_over();
    let (effective_fps, camera_fps) = run_rates(n.frames, passed_over, loop_seconds, designed_fps);
    Ok(RunReport {
        frames: n.frames,
        detected: n.detected,
        loop_seconds,
        stopped_by,
        record: record_stats.map(|h| h.get()),
        record_error: observers_done.err().map(|e| Chain(&e).to_string()),
        foxglove_addr,
        vision_stalls: n.vision_stalls,
        disarm,
        frames_passed_over: passed_over,
        effective_fps,
        camera_fps,
        designed_fps,
        rate_warnings: rate.warnings,
        frame_age: cam.frame_age(),
        stream_decoder: cam.decoder().cloned(),
        engagements: link.engager().engagements(),
        engagement: link.transitions.clone(),
        withheld: link.withheld,
        statustexts: link.inner().state().counters.statustexts_sent,
        hand_back,
        exit,
        preflight: checklist,
        camera_taken: n.camera_taken,
        camera_restored: n.camera_restored,
        camera_restore_error,
        wall_seconds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rate_is_judged_per_window_and_warned_once_per_fall() {
        let mut w = RateWatch::new(30.0);
        let mut ends = Vec::new();
        // 3 s at 30 fps, 4 s at 15 fps, 6 s at 30 fps again, 5 s at 10 fps.
        let mut t = 0.0;
        let mut feed = |w: &mut RateWatch, fps: f64, secs: f64, t: &mut f64| {
            for _ in 0..(fps * secs).round() as u32 {
                *t += 1.0 / fps;
                if let Some(e) = w.frame(*t) {
                    ends.push(e);
                }
            }
        };
        feed(&mut w, 30.0, 3.0, &mut t);
        feed(&mut w, 15.0, 4.0, &mut t);
        feed(&mut w, 30.0, 6.0, &mut t);
        feed(&mut w, 10.0, 5.0, &mut t);
        let fell: Vec<bool> = ends.iter().map(|e| e.1).collect();
        assert_eq!(fell.iter().filter(|f| **f).count(), 2, "{ends:?}");
        assert_eq!(w.warnings, 2);
        // Full windows report their rate.
        assert!(ends.iter().any(|e| (e.0 - 15.0).abs() < 0.6), "{ends:?}");
        assert!(ends.iter().any(|e| (e.0 - 30.0).abs() < 0.6), "{ends:?}");
        // A stamp going back starts the window again instead of a negative rate.
        let mut w = RateWatch::new(30.0);
        assert!(w.frame(5.0).is_none());
        assert!(w.frame(0.1).is_none());
        assert!(w.frame(2.2).is_some_and(|(r, _)| r > 0.0));
    }
}
