//! Where a live run's frames come from: the `--camera` URL, and the stream cameras with
//! their control channel. Recorded frames, V4L2 and GenICam cameras live in
//! `markhold-camera`.

use std::path::PathBuf;
use std::str::FromStr;
use std::time::{Duration, Instant};

#[cfg(feature = "genicam")]
use markhold_camera::genicam;
use markhold_camera::{Camera, CameraError, ExposureLimits, Frame, RecordedCamera, V4l2Camera};

use super::run::StartupError;
use markhold_core::params::{ControlExposure, LoadedSite};
use markhold_core::signal::ShutdownFlag;

pub mod attribution;
// The exposure control of a stream camera (and its HTTP client) lives in markhold-core:
// the site file names it.
pub use markhold_core::control::{self, http};
pub mod rtsp_guard;
pub mod stream;
pub mod worker;

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
    /// `udp:PORT`, `rtsp://...` or `gst:PIPELINE`: a video stream through GStreamer.
    Stream(stream::StreamSource),
}

impl FromStr for CameraUrl {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if let Some(parsed) = stream::StreamSource::parse(s) {
            return parsed.map(Self::Stream);
        }
        match s.split_once(':') {
            Some(("v4l2", dev)) if !dev.is_empty() => Ok(Self::V4l2(dev.to_string())),
            Some(("frames", dir)) if !dir.is_empty() => Ok(Self::Frames(PathBuf::from(dir))),
            Some(("genicam", id)) => Ok(Self::Genicam(id.to_string())),
            _ => Err(format!(
                "{s}: expected v4l2:/dev/videoN, frames:DIR, genicam:<device id>, udp:PORT, rtsp://HOST:PORT/PATH or gst:PIPELINE"
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
            Self::Stream(src) => src.fmt(f),
        }
    }
}

/// How long one `grab` waits for a frame before it hands control back to the loop, so
/// the supervisor sees loop time pass while the camera is stalled.
pub const NO_FRAME_TICK: Duration = Duration::from_millis(50);

/// Where a live run's frames come from: a recording (paced, it plays as a real-time
/// camera: frames whose time has passed while the loop was busy are passed over unread)
/// or a camera.
enum Source {
    Recorded(RecordedCamera),
    Other(Box<dyn Camera>),
}

impl Source {
    fn cam(&mut self) -> &mut dyn Camera {
        match self {
            Self::Recorded(c) => c,
            Self::Other(c) => c.as_mut(),
        }
    }
    fn cam_ref(&self) -> &dyn Camera {
        match self {
            Self::Recorded(c) => c,
            Self::Other(c) => c.as_ref(),
        }
    }
}

/// How old each frame the loop acted on was when the loop came back for the next one:
/// the stamp of the newest frame due then minus the frame's own stamp (0 when no newer
/// one was due). Camera time, from stamps; known for paced recordings.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct FrameAge {
    /// Frames measured.
    pub frames: u64,
    pub mean_s: f64,
    pub max_s: f64,
    /// The same, in frame periods of the recording's own rate.
    pub max_frames: u64,
}

/// The opened camera with its next frame kept for the loop (the first one from the
/// start-up check), paced if recorded.
pub struct LiveCamera {
    inner: Source,
    /// Recorded frames passed over by the pacing (the loop was slower than their stamps).
    passed_over: u64,
    /// The stamp of the frame handed out last, until its age at use is known.
    handed_stamp: Option<f64>,
    /// Ages at use: count, sum, max (seconds) and max in frames.
    ages: (u64, f64, f64, u64),
    /// A stream camera's H.264 decoder, as chosen at start.
    decoder: Option<stream::DecoderReport>,
    /// The next frame, grabbed but not handed out yet (buffer allocated once).
    pub(super) next: Frame,
    next_valid: bool,
    pace: bool,
    /// Wall time and stamp of the first frame.
    t0: Option<(Instant, f64)>,
    stop: ShutdownFlag,
    /// Wall time the last frame was handed to the loop.
    delivered_at: Option<Instant>,
    /// The last `grab` returned because no frame was due within [`NO_FRAME_TICK`].
    no_frame: bool,
    /// A stream camera's exposure control (the pilot's camera, shared with BlueOS).
    control: Option<worker::ControlHandle>,
    /// `[camera] control_exposure = "always"`: hold the camera's exposure from the start.
    control_always: bool,
}

impl LiveCamera {
    /// markhold is (or is no longer) engaged: a stream camera's exposure is markhold's
    /// only while engaged (or always, as the site says); otherwise it is put back as
    /// found. Returns true when this changed what is asked of the camera.
    pub fn set_engaged(&mut self, engaged: bool) -> bool {
        let Some(c) = &self.control else {
            return false;
        };
        let take = engaged || self.control_always;
        if c.wants_taken() == take {
            return false;
        }
        c.set_take(take);
        true
    }

    /// Whether the exposure control holds the camera (manual, markhold's values).
    pub fn exposure_taken(&self) -> bool {
        self.control.as_ref().is_some_and(|c| c.applied().taken)
    }

    /// Put the camera's exposure back as found (waiting at most `timeout`) and stop the
    /// control's worker. Nothing to do for a camera without one.
    pub fn finish_control(&mut self, timeout: Duration) -> Result<(), String> {
        match self.control.take() {
            Some(c) => c.finish(timeout),
            None => Ok(()),
        }
    }

    /// True (once) if the last grab failed only because no frame came in time.
    pub fn take_no_frame(&mut self) -> bool {
        std::mem::take(&mut self.no_frame)
    }

    /// Wall time since the last frame was handed to the loop.
    pub fn since_last_frame(&self) -> Duration {
        self.delivered_at.map_or(Duration::ZERO, |t| t.elapsed())
    }

    /// A stream camera's H.264 decoder, as chosen at start.
    pub fn decoder(&self) -> Option<&stream::DecoderReport> {
        self.decoder.as_ref()
    }

    /// The ages at use of the frames the loop acted on (paced recordings; None for other
    /// cameras, or before one was measured).
    pub fn frame_age(&self) -> Option<FrameAge> {
        let (n, sum, max, max_frames) = self.ages;
        (n > 0).then(|| FrameAge {
            frames: n,
            mean_s: sum / n as f64,
            max_s: max,
            max_frames,
        })
    }

    /// A paced recording plays as a real-time camera that keeps only its newest frame:
    /// the frame held, and each one after it whose successor's time has come, are passed
    /// over unread, so a loop slower than the recording acts on the newest frame due
    /// instead of working through a growing backlog. Also measures the age at use of the
    /// frame handed out last.
    fn drop_stale(&mut self) {
        let Source::Recorded(rec) = &mut self.inner else {
            return;
        };
        let first = if self.next_valid {
            Some(self.next.meta.stamp_s)
        } else {
            rec.peek_stamp_s(0)
        };
        let Some(first) = first else { return };
        let (w0, s0) = *self.t0.get_or_insert((Instant::now(), first));
        let now_s = s0 + w0.elapsed().as_secs_f64();
        let mut newest = None;
        let mut dropped = 0u64;
        if self.next_valid {
            if first <= now_s {
                newest = Some(first);
            }
            if rec.peek_stamp_s(0).is_some_and(|s| s <= now_s) {
                self.next_valid = false;
                dropped += 1;
            }
        }
        if !self.next_valid {
            while rec.peek_stamp_s(1).is_some_and(|s| s <= now_s) {
                rec.skip();
                dropped += 1;
            }
            if let Some(s) = rec.peek_stamp_s(0).filter(|s| *s <= now_s) {
                newest = Some(s);
            }
        }
        self.passed_over += dropped;
        if let Some(last) = self.handed_stamp.take() {
            let age = newest.map_or(0.0, |n| (n - last).max(0.0));
            // In frames: the recording's own spacing around the frame (1/fps).
            let fps = rec.exposure_limits().fps;
            let frames = if fps > 0.0 {
                (age * fps).round() as u64
            } else {
                0
            };
            let (n, sum, max, max_frames) = &mut self.ages;
            *n += 1;
            *sum += age;
            *max = max.max(age);
            *max_frames = (*max_frames).max(frames);
        }
    }
}

impl Drop for LiveCamera {
    fn drop(&mut self) {
        // Every way out of a run leaves the camera as found (a normal end did already).
        if let Err(why) = self.finish_control(CONTROL_FINISH) {
            tracing::warn!("{why}");
        }
    }
}

impl Camera for LiveCamera {
    fn name(&self) -> &str {
        self.inner.cam_ref().name()
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.inner.cam_ref().exposure_limits()
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.inner.cam().set_exposure_us(exposure_us)
    }
    fn frames_passed_over(&self) -> u64 {
        self.inner.cam_ref().frames_passed_over() + self.passed_over
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        if self.pace {
            self.drop_stale();
        }
        if !self.next_valid {
            if let Err(e) = self.inner.cam().grab(&mut self.next) {
                // A stream with no frame this tick: the supervisor's stall clock runs on.
                if matches!(&e, CameraError::Read { reason, .. } if reason.starts_with(stream::NO_FRAME_REASON))
                {
                    self.no_frame = true;
                }
                return Err(e);
            }
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
                        device: self.inner.cam_ref().name().to_string(),
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
        if self.pace {
            self.handed_stamp = Some(frame.meta.stamp_s);
        }
        Ok(())
    }
}

pub fn open_camera(
    site: &LoadedSite,
    url: &CameraUrl,
    initial_us: f64,
    stop: &ShutdownFlag,
    pace: bool,
) -> Result<LiveCamera, StartupError> {
    let name = url.to_string();
    let cam = &site.site.camera;
    let mut control = None;
    let mut decoder = None;
    let (mut inner, paced) = match url {
        CameraUrl::V4l2(dev) => {
            let c = V4l2Camera::open(dev, cam.width_px, cam.height_px, cam.fps).map_err(|e| {
                StartupError::Camera {
                    url: name.clone(),
                    reason: e.to_string(),
                }
            })?;
            (
                Source::Other(Box::new(c.with_exposure_limits(site.limits()))),
                false,
            )
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
            (Source::Recorded(c), pace)
        }
        #[cfg(not(feature = "genicam"))]
        CameraUrl::Genicam(_) => {
            return Err(StartupError::Camera {
                url: name,
                reason: "this build has no GenICam support (built without the cargo feature \
                         `genicam`, which needs Aravis)"
                    .into(),
            })
        }
        #[cfg(feature = "genicam")]
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
            (Source::Other(Box::new(c)), false)
        }
        CameraUrl::Stream(src) => {
            let (cam, handle) = open_stream(site, src, initial_us, &name, stop)?;
            control = Some(handle);
            decoder = cam.decoder().cloned();
            (Source::Other(Box::new(cam)), false)
        }
    };
    let first = match first_frame(site, inner.cam(), initial_us, &name) {
        Ok(f) => f,
        Err(e) => {
            // The camera goes back as found (it may have been taken already).
            if let Some(c) = &control {
                if let Err(why) = c.finish(CONTROL_FINISH) {
                    tracing::warn!("{why}");
                }
            }
            return Err(e);
        }
    };
    Ok(LiveCamera {
        inner,
        passed_over: 0,
        handed_stamp: None,
        ages: (0, 0.0, 0.0, 0),
        decoder,
        next: first,
        next_valid: true,
        pace: paced,
        t0: None,
        stop: stop.clone(),
        delivered_at: None,
        no_frame: false,
        control,
        control_always: cam.control_exposure == ControlExposure::Always,
    })
}

/// How long putting the camera's exposure back may take at the end of a run (a few
/// requests of the control's own deadline).
pub const CONTROL_FINISH: Duration = Duration::from_secs(5);

/// The start-up exposure and the first frame, whose size must be the calibration's.
fn first_frame(
    site: &LoadedSite,
    inner: &mut dyn Camera,
    initial_us: f64,
    name: &str,
) -> Result<Frame, StartupError> {
    inner
        .set_exposure_us(initial_us)
        .map_err(|e| StartupError::Exposure {
            url: name.to_string(),
            exposure_us: initial_us,
            reason: e.to_string(),
        })?;
    let mut first = Frame::new(0, 0);
    inner
        .grab(&mut first)
        .map_err(|e| StartupError::FirstFrame {
            url: name.to_string(),
            reason: e.to_string(),
        })?;
    let calib = &site.calibration;
    if first.width != calib.width || first.height != calib.height {
        return Err(StartupError::Resolution {
            url: name.to_string(),
            width: first.width,
            height: first.height,
            calib_width: calib.width,
            calib_height: calib.height,
        });
    }
    Ok(first)
}

/// A stream camera with the site's `[camera.control]` for its exposure: the control
/// only reads the camera at start (after putting back what a run that died left), and
/// holds it from the start only with `control_exposure = "always"`.
fn open_stream(
    site: &LoadedSite,
    src: &stream::StreamSource,
    initial_us: f64,
    name: &str,
    stop: &ShutdownFlag,
) -> Result<(stream::StreamCamera, worker::ControlHandle), StartupError> {
    let cam = &site.site.camera;
    let limits = site.limits();
    let control_err = |reason: String| StartupError::Camera {
        url: name.to_string(),
        reason: format!("exposure control: {reason}"),
    };
    let mut control: Box<dyn control::ExposureControl> = match &cam.control {
        control::ControlConfig::None => Box::new(control::NoControl),
        control::ControlConfig::BlueosRest { url, device } => Box::new(
            control::BlueosRest::open(url, device, &limits)
                .map_err(|e| control_err(e.to_string()))?,
        ),
        control::ControlConfig::V4l2 { device } => Box::new(
            control::V4l2Control::open(device, &limits).map_err(|e| control_err(e.to_string()))?,
        ),
    };
    let state = worker::state_path(&site.path);
    let found = worker::recover(control.as_mut(), Some(&state)).map_err(control_err)?;
    let handle = worker::ControlHandle::spawn(control, found, Some(state))
        .map_err(|e| control_err(format!("starting its thread: {e}")))?;
    handle.request(initial_us);
    if cam.control_exposure == ControlExposure::Always {
        handle.set_take(true);
    }
    let cfg = stream::StreamConfig {
        fps: cam.fps,
        limits,
        initial_us,
        first_frame_timeout: Duration::from_secs(5),
        restart: true,
        stop: stop.clone(),
    };
    let camera = stream::StreamCamera::open(src, &cfg, handle.clone()).map_err(|e| {
        StartupError::Camera {
            url: name.to_string(),
            reason: e.to_string(),
        }
    })?;
    Ok((camera, handle))
}
