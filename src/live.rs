//! `markhold run`: the loop on a real camera and a real ArduSub link, with start-up
//! checks, Ctrl-C / SIGTERM handling, recording and the Foxglove live view.
//!
//! Time is the camera's: frame stamps are the loop's clock. The wall clock only bounds
//! start-up waits and paces a recorded-frames camera to its stamps.

use std::path::PathBuf;
use std::str::FromStr;
use std::time::{Duration, Instant};

use markhold_autopilot::{CommandStatus, Directive, FailsafeEvent, VehicleLink};
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use markhold_vision::{RecordedCamera, V4l2Camera};
use serde::Serialize;

use crate::params::LoadedSite;
use crate::pipeline::{FailsafeActions, Pipeline};
use crate::record::{record_step, RecordConfig, RecordStats, Recorder, RunInfo};
use crate::replay::build_pipeline;
use crate::signal::ShutdownFlag;

/// `genicam:<device id>` cameras through Aravis.
#[path = "genicam.rs"]
pub mod genicam;

/// Where frames come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CameraUrl {
    /// `v4l2:/dev/videoN`.
    V4l2(String),
    /// `frames:DIR`: a recorded-frames folder (PNGs and `frames.csv`).
    Frames(PathBuf),
    /// `genicam:<device id>` (Aravis id or a GigE camera's IP address; empty: the first
    /// camera found).
    Genicam(String),
}

impl FromStr for CameraUrl {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.split_once(':') {
            Some(("v4l2", dev)) if !dev.is_empty() => Ok(Self::V4l2(dev.to_string())),
            Some(("frames", dir)) if !dir.is_empty() => Ok(Self::Frames(PathBuf::from(dir))),
            Some(("genicam", id)) => Ok(Self::Genicam(id.to_string())),
            _ => Err(format!(
                "{s}: expected v4l2:/dev/videoN, frames:DIR or genicam:<device id>"
            )),
        }
    }
}

impl std::fmt::Display for CameraUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::V4l2(d) => write!(f, "v4l2:{d}"),
            Self::Frames(p) => write!(f, "frames:{}", p.display()),
            Self::Genicam(id) => write!(f, "genicam:{id}"),
        }
    }
}

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
    Record { source: crate::record::RecordError },
    #[error("--foxglove: {reason}")]
    LiveView { reason: String },
}

/// Why the loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    Signal,
    EndOfStream,
    MaxSeconds,
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
    /// Where the live view listened, if it was on.
    pub foxglove_addr: Option<String>,
    /// Times the camera stalled long enough for the vision-stall failsafe (neutral).
    pub vision_stalls: u64,
    /// Disarm on exit (`link.disarm_on_exit` and a signal): how the request ended.
    pub disarm: Option<CommandStatus>,
    /// Frames the camera took that the loop was too slow to see (it acts on the newest).
    pub frames_passed_over: u64,
}

/// How long one `grab` waits for a frame before it hands control back to the loop, so
/// the supervisor sees loop time pass while the camera is stalled.
pub const NO_FRAME_TICK: Duration = Duration::from_millis(50);

/// The opened camera with its next frame kept for the loop (the first one from the
/// start-up check), paced if recorded.
struct LiveCamera {
    inner: Box<dyn Camera>,
    /// The next frame, grabbed but not handed out yet (buffer allocated once).
    next: Frame,
    next_valid: bool,
    pace: bool,
    /// Wall time and stamp of the first frame.
    t0: Option<(Instant, f64)>,
    stop: ShutdownFlag,
    /// Wall time the last frame was handed to the loop.
    delivered_at: Option<Instant>,
    /// The last `grab` returned because no frame was due within [`NO_FRAME_TICK`].
    no_frame: bool,
}

impl LiveCamera {
    /// True (once) if the last grab failed only because no frame came in time.
    fn take_no_frame(&mut self) -> bool {
        std::mem::take(&mut self.no_frame)
    }

    /// Wall time since the last frame was handed to the loop.
    fn since_last_frame(&self) -> Duration {
        self.delivered_at.map_or(Duration::ZERO, |t| t.elapsed())
    }
}

impl Camera for LiveCamera {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.inner.exposure_limits()
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.inner.set_exposure_us(exposure_us)
    }
    fn frames_passed_over(&self) -> u64 {
        self.inner.frames_passed_over()
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        if !self.next_valid {
            self.inner.grab(&mut self.next)?;
            self.next_valid = true;
        }
        if self.pace {
            let stamp = self.next.meta.stamp_s;
            let (w0, s0) = *self.t0.get_or_insert((Instant::now(), stamp));
            let due = w0 + Duration::from_secs_f64((stamp - s0).clamp(0.0, 3600.0));
            let give_up = Instant::now() + NO_FRAME_TICK;
            // Short sleeps: a signal must not wait for a long gap in the recording, and
            // the loop gets control back every NO_FRAME_TICK while no frame is due.
            while !self.stop.is_set() {
                let now = Instant::now();
                if now >= due {
                    break;
                }
                if now >= give_up {
                    self.no_frame = true;
                    return Err(CameraError::Read {
                        device: self.inner.name().to_string(),
                        seq: self.next.meta.seq,
                        reason: format!("no frame within {} ms", NO_FRAME_TICK.as_millis()),
                    });
                }
                std::thread::sleep((due.min(give_up) - now).min(Duration::from_millis(20)));
            }
        }
        // Hand the frame over by swapping buffers (no copy, no allocation once both
        // have the camera's size).
        std::mem::swap(frame, &mut self.next);
        self.next_valid = false;
        self.delivered_at = Some(Instant::now());
        Ok(())
    }
}

fn open_camera(
    site: &LoadedSite,
    url: &CameraUrl,
    initial_us: f64,
    stop: &ShutdownFlag,
    pace: bool,
) -> Result<LiveCamera, StartupError> {
    let name = url.to_string();
    let cam = &site.site.camera;
    let (mut inner, paced): (Box<dyn Camera>, bool) = match url {
        CameraUrl::V4l2(dev) => {
            let c = V4l2Camera::open(dev, cam.width_px, cam.height_px, cam.fps).map_err(|e| {
                StartupError::Camera {
                    url: name.clone(),
                    reason: e.to_string(),
                }
            })?;
            (Box::new(c.with_exposure_limits(site.limits())), false)
        }
        CameraUrl::Frames(dir) => {
            let c = RecordedCamera::open(dir).map_err(|e| StartupError::Camera {
                url: name.clone(),
                reason: e.to_string(),
            })?;
            if c.is_empty() {
                return Err(StartupError::Camera {
                    url: name,
                    reason: "the folder's frames.csv lists no frames".into(),
                });
            }
            (Box::new(c), pace)
        }
        CameraUrl::Genicam(id) => {
            let cfg = genicam::GenicamConfig {
                width: site.calibration.width,
                height: site.calibration.height,
                fps: cam.fps,
                limits: site.limits(),
                initial_us,
                gain_db: cam.gain_db,
                buffers: genicam::DEFAULT_BUFFERS,
                frame_timeout_s: (4.0 / cam.fps.max(0.1)).max(1.0),
            };
            let c = genicam::GenicamCamera::open(id, &cfg).map_err(|e| StartupError::Camera {
                url: name.clone(),
                reason: e.to_string(),
            })?;
            (Box::new(c), false)
        }
    };
    inner
        .set_exposure_us(initial_us)
        .map_err(|e| StartupError::Exposure {
            url: name.clone(),
            exposure_us: initial_us,
            reason: e.to_string(),
        })?;
    let mut first = Frame::new(0, 0);
    inner
        .grab(&mut first)
        .map_err(|e| StartupError::FirstFrame {
            url: name.clone(),
            reason: e.to_string(),
        })?;
    let calib = &site.calibration;
    if first.width != calib.width || first.height != calib.height {
        return Err(StartupError::Resolution {
            url: name,
            width: first.width,
            height: first.height,
            calib_width: calib.width,
            calib_height: calib.height,
        });
    }
    Ok(LiveCamera {
        inner,
        next: first,
        next_valid: true,
        pace: paced,
        t0: None,
        stop: stop.clone(),
        delivered_at: None,
        no_frame: false,
    })
}

/// Open the link and wait (wall clock, bounded) for the vehicle's heartbeat; `now_s`
/// is the loop time of the first frame.
fn open_link(
    site: &LoadedSite,
    opts: &RunOptions,
    now_s: f64,
    stop: &ShutdownFlag,
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

fn is_end_of_stream(e: &anyhow::Error) -> bool {
    matches!(
        e.downcast_ref::<CameraError>(),
        Some(CameraError::EndOfStream { .. })
    )
}

/// Run the loop until a signal, the end of a recorded stream or `max_seconds`.
/// Start-up checks come first, in the order: record path, camera (opens, accepts
/// exposure, resolution matches the calibration), vehicle heartbeat. A failed check
/// removes the recording it had started.
pub fn run_live(
    site: &LoadedSite,
    opts: &RunOptions,
    stop: &ShutdownFlag,
) -> anyhow::Result<RunReport> {
    let s = &site.site;
    let method = s.exposure.method;
    let initial_us = site.limits().clamp(s.camera.initial_exposure_us);
    let mut recorder = match &opts.record {
        Some(path) => {
            let info = RunInfo::new(
                "run",
                site,
                method,
                initial_us,
                format!(
                    "run --site {} --camera {} --link {}",
                    site.path.display(),
                    opts.camera,
                    opts.link_url.as_deref().unwrap_or(&s.link.url)
                ),
            )
            .map_err(|source| StartupError::Record { source })?;
            Some(
                Recorder::create(path, &info, RecordConfig::default())
                    .map_err(|source| StartupError::Record { source })?,
            )
        }
        None => match opts.foxglove_port {
            Some(_) => Some(
                Recorder::live_only(RecordConfig::default())
                    .map_err(|source| StartupError::Record { source })?,
            ),
            None => None,
        },
    };
    let mut foxglove_addr = None;
    if let (Some(port), Some(r)) = (opts.foxglove_port, recorder.as_mut()) {
        match r.serve_live(port) {
            Ok(p) => {
                eprintln!("markhold run: Foxglove live view on ws://127.0.0.1:{p}");
                foxglove_addr = Some(format!("127.0.0.1:{p}"));
            }
            Err(e) => {
                if let Some(r) = recorder.take() {
                    r.abort();
                }
                return Err(StartupError::LiveView {
                    reason: e.to_string(),
                }
                .into());
            }
        }
    }
    let started = (|| -> anyhow::Result<(LiveCamera, Pipeline)> {
        let cam = open_camera(site, &opts.camera, initial_us, stop, opts.pace_frames)?;
        let now0 = cam.next.meta.stamp_s;
        let link = open_link(site, opts, now0, stop)?;
        let pipeline = build_pipeline(site, method, initial_us, link)?;
        Ok((cam, pipeline))
    })();
    let (mut cam, mut pipeline) = match started {
        Ok(v) => v,
        Err(e) => {
            if let Some(r) = recorder.take() {
                r.abort();
            }
            return Err(e);
        }
    };
    tracing::info!(camera = %opts.camera, "running");
    eprintln!(
        "markhold run: running (camera {}, Ctrl-C to stop)",
        opts.camera
    );

    pipeline.failsafe = FailsafeActions::new(Some(s.link.mode.ardusub()));
    if let Some(r) = recorder.as_ref() {
        pipeline.link.set_raw_tap(Some(r.mavlink_tap()));
    }
    let mut frames = 0u64;
    let mut detected = 0u64;
    let mut first_stamp = None;
    let mut last_stamp = cam.next.meta.stamp_s;
    let mut vision_stalls = 0u64;
    let mut disarm_asked = false;
    let stopped_by = loop {
        if stop.is_set() {
            // This frame sends neutral input (the supervisor's shutdown directive).
            pipeline.shutdown = true;
        }
        let rec = match pipeline.step(&mut cam) {
            Ok(r) => r,
            Err(_) if cam.take_no_frame() => {
                // No frame yet: loop time is the last frame's stamp plus the time waited
                // (the only place the wall clock enters the loop: without frames there
                // is no other clock), so the supervisor can call the camera stalled.
                let now = last_stamp + cam.since_last_frame().as_secs_f64();
                let d = pipeline.tick_without_frame(now)?;
                vision_stalls += pipeline
                    .events
                    .iter()
                    .filter(|e| matches!(e, FailsafeEvent::VisionStalled { .. }))
                    .count() as u64;
                if let Directive::Shutdown { disarm } = d {
                    disarm_asked = disarm;
                    break StopReason::Signal;
                }
                continue;
            }
            Err(e) if is_end_of_stream(&e) => break StopReason::EndOfStream,
            Err(e) => {
                let _ = pipeline.link.send_neutral(last_stamp);
                if let Some(r) = recorder.take() {
                    let _ = r.finish();
                }
                return Err(e.context(format!("frame {frames}")));
            }
        };
        if let Some(r) = recorder.as_mut() {
            record_step(r, &pipeline, &rec);
        }
        frames += 1;
        detected += rec.detected as u64;
        last_stamp = rec.stamp_s;
        let t0 = *first_stamp.get_or_insert(rec.stamp_s);
        if let Directive::Shutdown { disarm } = rec.directive {
            disarm_asked = disarm;
            break StopReason::Signal;
        }
        if opts.max_seconds.is_some_and(|m| rec.stamp_s - t0 >= m) {
            break StopReason::MaxSeconds;
        }
    };
    // Leave the vehicle with neutral pilot input, whatever ended the loop.
    pipeline.link.send_neutral(last_stamp)?;
    let disarm = if disarm_asked {
        Some(disarm_on_exit(&mut pipeline.link, last_stamp))
    } else {
        None
    };
    let record = match recorder {
        Some(r) if opts.record.is_some() => Some(r.finish()?),
        Some(r) => {
            r.finish()?;
            None
        }
        None => None,
    };
    Ok(RunReport {
        frames,
        detected,
        loop_seconds: first_stamp.map_or(0.0, |t0| last_stamp - t0),
        stopped_by,
        record,
        foxglove_addr,
        vision_stalls,
        disarm,
        frames_passed_over: cam.frames_passed_over(),
    })
}

/// After the shutdown's neutral input: disarm, acknowledged and retried by the link, on
/// loop time `t0` plus the time waited (no frames come any more), bounded by the link's
/// own retries. Neutral input keeps going out (the link's keep-alive) until it settles.
fn disarm_on_exit(link: &mut VehicleLink, t0: f64) -> CommandStatus {
    let cfg = link.config().clone();
    let started = Instant::now();
    let limit = cfg.command_timeout_s * f64::from(cfg.command_retries + 1) + 0.5;
    let now = |started: Instant| t0 + started.elapsed().as_secs_f64();
    if let Err(e) = link.request_arm(false, now(started)) {
        tracing::warn!(error = %e, "disarm on exit: request not sent");
        return CommandStatus::TimedOut;
    }
    eprintln!("markhold run: disarming (link.disarm_on_exit)");
    let status = loop {
        let t = now(started);
        if let Err(e) = link.tick(t) {
            tracing::warn!(error = %e, "disarm on exit: link");
        }
        let st = link.state();
        match st.arm_command {
            CommandStatus::Pending { .. } | CommandStatus::Idle if st.armed => {}
            CommandStatus::Pending { .. } | CommandStatus::Idle => break CommandStatus::Accepted,
            other => break other,
        }
        if t - t0 > limit {
            break CommandStatus::TimedOut;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    tracing::info!(?status, armed = link.state().armed, "disarm on exit");
    eprintln!(
        "markhold run: disarm on exit: {status:?} (vehicle armed: {})",
        link.state().armed
    );
    status
}
