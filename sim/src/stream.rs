//! `hil --camera-transport h264-rtp`: the HIL camera behind the stock BlueROV2's stack.
//!
//! Each rendered frame is encoded by a real GStreamer H.264 encoder (x264enc,
//! `tune=zerolatency speed-preset=ultrafast`) into RTP and sent to a loopback UDP port,
//! where the loop receives it through the same [`StreamCamera`] as `run --camera
//! udp:PORT`. Exposure commands go through a loopback HTTP server that answers the
//! camera manager's REST API (`GET /v4l`, `POST /v4l`), and reach the simulated camera
//! after the camera model's actuation delay, in the camera's 100 us units.
//!
//! The world stays lock-step: a frame is pushed, then received, before the loop acts.
//! The loop's clock is the rendered frame's simulation stamp (the receiver's timestamps
//! follow the RTP timestamps, which carry the same spacing).

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::error::{ensure, Required, SimError, StepContext};
use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use markhold_hil::HilRig;

use markhold_core::control::{
    quantize, ApiControl, ApiControlType, ApiVideoSource, BlueosRest, CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO, EXPOSURE_MANUAL, V4L2_EXPOSURE_UNIT_US,
};
use markhold_field::camera::stream::{StreamCamera, StreamConfig, StreamSource};
use markhold_field::camera::worker::ControlHandle;

/// The simulated camera's device path on the simulated camera manager.
pub const SIM_DEVICE: &str = "/dev/video2";

/// How the HIL camera reaches the loop (`--camera-transport`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum CameraTransport {
    /// Frames handed over in process.
    #[default]
    InProcess,
    /// H.264 over RTP on loopback UDP, exposure through the camera manager's REST API.
    H264Rtp,
}

impl std::fmt::Display for CameraTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::InProcess => "in-process",
            Self::H264Rtp => "h264-rtp",
        })
    }
}

/// The simulated camera's controls as the camera manager holds them.
#[derive(Debug, Clone, Copy)]
pub struct SimControls {
    pub auto_exposure: i64,
    /// V4L2 exposure_time_absolute, 100 us units.
    pub exposure_units: i64,
    pub min_units: i64,
    pub max_units: i64,
    /// Refuse every request (HTTP 500), as a camera manager that lost the camera does.
    pub refuse: bool,
    /// Requests served, and of them POSTs (writes).
    pub requests: u64,
    pub posts: u64,
}

impl SimControls {
    fn sources(&self) -> Vec<ApiVideoSource> {
        vec![ApiVideoSource {
            name: "Simulated low-light USB camera".into(),
            source: SIM_DEVICE.into(),
            formats: serde_json::json!([]),
            controls: vec![
                ApiControl {
                    name: "Auto Exposure".into(),
                    // The camera manager names menus int32 (video_source_local_linux.rs).
                    cpp_type: "int32".into(),
                    id: CID_EXPOSURE_AUTO,
                    state: serde_json::json!({"is_disabled": false, "is_inactive": false}),
                    configuration: ApiControlType::Menu {
                        default: 3,
                        value: self.auto_exposure,
                        options: serde_json::json!([
                            {"name": "Manual Mode", "value": 1},
                            {"name": "Aperture Priority Mode", "value": 3}
                        ]),
                    },
                },
                ApiControl {
                    name: "Exposure Time, Absolute".into(),
                    cpp_type: "int64".into(),
                    id: CID_EXPOSURE_ABSOLUTE,
                    state: serde_json::json!({
                        "is_disabled": false,
                        "is_inactive": self.auto_exposure != EXPOSURE_MANUAL
                    }),
                    configuration: ApiControlType::Slider {
                        default: 156,
                        value: self.exposure_units,
                        step: 1,
                        max: self.max_units,
                        min: self.min_units,
                    },
                },
            ],
        }]
    }
}

/// A loopback HTTP server answering the camera manager's `/v4l` API.
pub struct SimCameraManager {
    addr: SocketAddr,
    pub controls: Arc<Mutex<SimControls>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl SimCameraManager {
    /// Binds 127.0.0.1:0 and serves until dropped.
    pub fn start(limits: ExposureLimits, initial_us: f64) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let min_units = (limits.min_us / V4L2_EXPOSURE_UNIT_US).ceil().max(1.0) as i64;
        let max_units = (limits.max_us / V4L2_EXPOSURE_UNIT_US).floor() as i64;
        let controls = Arc::new(Mutex::new(SimControls {
            auto_exposure: 3,
            exposure_units: ((initial_us / V4L2_EXPOSURE_UNIT_US).round() as i64)
                .clamp(min_units, max_units.max(min_units)),
            min_units,
            max_units,
            refuse: false,
            requests: 0,
            posts: 0,
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let (c, s) = (controls.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("sim-camera-manager".into())
            .spawn(move || {
                while !s.load(Ordering::Relaxed) {
                    match listener.accept() {
                        Ok((conn, _)) => {
                            let _ = serve(conn, &c);
                        }
                        Err(_) => std::thread::sleep(Duration::from_millis(1)),
                    }
                }
            })?;
        Ok(Self {
            addr,
            controls,
            stop,
            thread: Some(thread),
        })
    }

    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub fn set_refuse(&self, refuse: bool) {
        if let Ok(mut c) = self.controls.lock() {
            c.refuse = refuse;
        }
    }

    pub fn controls(&self) -> SimControls {
        match self.controls.lock() {
            Ok(c) => *c,
            Err(p) => *p.into_inner(),
        }
    }
}

impl Drop for SimCameraManager {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The body of `POST /v4l` as the camera manager parses it.
#[derive(serde::Deserialize)]
struct PostV4l {
    device: String,
    v4l_id: u64,
    value: i64,
}

/// One request on `conn` (HTTP/1.1, answered with `Connection: close`).
fn serve(mut conn: TcpStream, controls: &Mutex<SimControls>) -> std::io::Result<()> {
    conn.set_nonblocking(false)?;
    conn.set_read_timeout(Some(Duration::from_secs(2)))?;
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    let (head_end, content_length) = loop {
        let n = conn.read(&mut chunk)?;
        if n == 0 {
            return Ok(());
        }
        buf.extend_from_slice(&chunk[..n]);
        if let Some(p) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&buf[..p]).to_ascii_lowercase();
            let len = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok())
                .unwrap_or(0);
            break (p + 4, len);
        }
    };
    while buf.len() < head_end + content_length {
        let n = conn.read(&mut chunk)?;
        if n == 0 {
            break;
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    let head = String::from_utf8_lossy(&buf[..head_end]).into_owned();
    let body = &buf[head_end..(head_end + content_length).min(buf.len())];
    let mut parts = head.split_whitespace();
    let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    let (status, reply) = {
        let mut c = match controls.lock() {
            Ok(c) => c,
            Err(p) => p.into_inner(),
        };
        c.requests += 1;
        c.posts += u64::from(method == "POST");
        if c.refuse {
            (500, "Internal error: camera not available".to_string())
        } else {
            match (method, path) {
                ("GET", "/v4l") => (
                    200,
                    serde_json::to_string(&c.sources()).unwrap_or_else(|_| "[]".into()),
                ),
                ("POST", "/v4l") => match serde_json::from_slice::<PostV4l>(body) {
                    Err(e) => (400, format!("Json deserialize error: {e}")),
                    Ok(p) if p.device != SIM_DEVICE => (500, format!("no device {}", p.device)),
                    Ok(p) if p.v4l_id == CID_EXPOSURE_AUTO && (p.value == 1 || p.value == 3) => {
                        c.auto_exposure = p.value;
                        (200, String::new())
                    }
                    // As the camera manager's `validate_control`: an inactive control
                    // (the exposure time in auto exposure) and a value outside the
                    // slider's range are refused.
                    Ok(p) if p.v4l_id == CID_EXPOSURE_ABSOLUTE && c.auto_exposure != EXPOSURE_MANUAL => (
                        500,
                        format!("Internal Server Error: Failed setting {} to {}: Control is inactive", p.v4l_id, p.value),
                    ),
                    Ok(p) if p.v4l_id == CID_EXPOSURE_ABSOLUTE && !(c.min_units..=c.max_units).contains(&p.value) => (
                        500,
                        format!("Internal Server Error: Failed setting {} to {}: Value out of the Control range {}..{}", p.v4l_id, p.value, c.min_units, c.max_units),
                    ),
                    Ok(p) if p.v4l_id == CID_EXPOSURE_ABSOLUTE => {
                        c.exposure_units = p.value;
                        (200, String::new())
                    }
                    Ok(p) => (
                        500,
                        format!("control {} value {} refused", p.v4l_id, p.value),
                    ),
                },
                _ => (404, format!("Page does not exist: {path:?}")),
            }
        }
    };
    let reason = match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        _ => "Internal Server Error",
    };
    let ctype = if status == 200 && method == "GET" {
        "application/json"
    } else {
        "text/plain"
    };
    write!(
        conn,
        "HTTP/1.1 {status} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{reply}",
        reply.len()
    )?;
    conn.flush()
}

/// The H.264 encoder (x264enc) and RTP sender of rendered frames, to a loopback UDP
/// port.
pub struct Sender {
    pipeline: gst::Pipeline,
    src: gst_app::AppSrc,
    buffer_size: usize,
}

impl Sender {
    pub fn start(width: u32, height: u32, fps: f64, port: u16) -> Result<Self, SimError> {
        markhold_field::camera::stream::init().map_err(|reason| SimError::Run { reason })?;
        let fps_n = (fps * 1000.0).round() as i32;
        let desc = format!(
            "appsrc name=src is-live=true format=time do-timestamp=false \
             caps=video/x-raw,format=GRAY8,width={width},height={height},framerate={fps_n}/1000 \
             ! videoconvert ! video/x-raw,format=I420 \
             ! x264enc tune=zerolatency speed-preset=ultrafast key-int-max=30 bitrate=8000 threads=1 \
             ! rtph264pay config-interval=1 pt=96 mtu=1400 \
             ! udpsink host=127.0.0.1 port={port} sync=false async=false"
        );
        let pipeline = gst::parse::launch(&desc)
            .step(|| "the H.264 sender pipeline".to_string())?
            .downcast::<gst::Pipeline>()
            .map_err(|_| SimError::Run {
                reason: "the H.264 sender is not a pipeline".to_string(),
            })?;
        let src = pipeline
            .by_name("src")
            .and_then(|e| e.downcast::<gst_app::AppSrc>().ok())
            .required(|| "the sender's appsrc".to_string())?;
        pipeline.set_state(gst::State::Playing).step(|| {
            "starting the H.264 sender (x264enc from gstreamer1.0-plugins-ugly?)".to_string()
        })?;
        Ok(Self {
            pipeline,
            src,
            buffer_size: width as usize * height as usize,
        })
    }

    /// Encodes and sends `frame`, stamped `stamp_s` (its RTP timestamp).
    pub fn push(&self, frame: &Frame, stamp_s: f64) -> Result<(), SimError> {
        let mut buf =
            gst::Buffer::with_size(self.buffer_size).step(|| "a frame buffer".to_string())?;
        {
            let b = buf
                .get_mut()
                .required(|| "a fresh buffer is writable".to_string())?;
            b.set_pts(gst::ClockTime::from_nseconds(
                (stamp_s.max(0.0) * 1e9) as u64,
            ));
            let mut map = b
                .map_writable()
                .step(|| "mapping a frame buffer".to_string())?;
            let n = self.buffer_size.min(frame.data.len());
            map[..n].copy_from_slice(&frame.data[..n]);
        }
        self.src.push_buffer(buf).map_err(|e| SimError::Run {
            reason: format!("the H.264 sender refused a frame: {e:?}"),
        })?;
        Ok(())
    }
}

impl Drop for Sender {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}

/// The stream transport of a HIL run: sender, simulated camera manager, receiver.
pub struct StreamHil {
    sender: Sender,
    pub manager: SimCameraManager,
    receiver: StreamCamera,
    /// Stamps of frames sent and not yet received.
    sent: VecDeque<f64>,
    rendered: Frame,
    /// The exposure last applied to the simulated camera, 100 us units.
    applied_units: i64,
    /// Wall time from handing a rendered frame to the encoder to having it decoded, per
    /// frame, seconds (allocated for the run at the start).
    pub added_latency_s: Vec<f64>,
}

/// How long the loop waits for a sent frame to come back through the stream.
const RECEIVE_TIMEOUT: Duration = Duration::from_secs(3);

impl StreamHil {
    /// Starts the simulated camera manager, the receiver (the loop's stream camera, with
    /// the REST control) and the sender.
    pub fn start(
        rig: &HilRig,
        limits: ExposureLimits,
        initial_us: f64,
        frames: usize,
    ) -> Result<Self, SimError> {
        markhold_field::camera::stream::init().map_err(|reason| SimError::Run { reason })?;
        let model = rig.camera_model();
        let manager = SimCameraManager::start(limits, initial_us)
            .step(|| "starting the simulated camera manager".to_string())?;
        let control = BlueosRest::open(&manager.url(), SIM_DEVICE, &limits)?;
        // A simulation holds the camera from the start; every request is settled before
        // the next frame is rendered (lock-step, repeatable).
        let control = ControlHandle::spawn(Box::new(control), None, None)?;
        control.set_take(true);
        control.request(quantize(limits.clamp(initial_us), control.step_us()));
        ensure(control.settle(RECEIVE_TIMEOUT), || SimError::Run {
            reason: format!(
                "the simulated camera manager did not take the initial exposure: {}",
                control.last_error().unwrap_or_default()
            ),
        })?;
        // The OS picks a free loopback port; the receiver binds it again at once.
        let port = UdpSocket::bind("127.0.0.1:0")?.local_addr()?.port();
        let source = StreamSource::Udp {
            host: Some("127.0.0.1".into()),
            port,
        };
        let cfg = StreamConfig {
            fps: model.fps,
            limits,
            initial_us,
            first_frame_timeout: RECEIVE_TIMEOUT,
            restart: false,
            stop: markhold_core::signal::ShutdownFlag::new(),
        };
        let receiver = StreamCamera::start(&source, &cfg, control)?;
        let sender = Sender::start(model.width, model.height, model.fps, port)?;
        let applied_units = manager.controls().exposure_units;
        Ok(Self {
            sender,
            manager,
            receiver,
            sent: VecDeque::with_capacity(64),
            rendered: Frame::new(model.width, model.height),
            applied_units,
            added_latency_s: Vec::with_capacity(frames),
        })
    }

    /// The receiver's delay estimate, frames.
    pub fn delay_estimate_frames(&self) -> Option<u32> {
        self.receiver.delay_frames()
    }

    /// The stream camera of the loop, in front of `rig`.
    pub fn camera<'a>(&'a mut self, rig: &'a mut HilRig) -> StreamLoopCamera<'a> {
        StreamLoopCamera { hil: self, rig }
    }
}

/// What the loop grabs from in a stream HIL run.
pub struct StreamLoopCamera<'a> {
    hil: &'a mut StreamHil,
    rig: &'a mut HilRig,
}

impl Camera for StreamLoopCamera<'_> {
    fn name(&self) -> &str {
        self.hil.receiver.name()
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.hil.receiver.exposure_limits()
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.hil.receiver.set_exposure_us(exposure_us)
    }
    fn frames_passed_over(&self) -> u64 {
        self.hil.receiver.frames_passed_over()
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let h = &mut *self.hil;
        // The camera manager's control, applied to the simulated camera (which adds its
        // own actuation delay), once the last request reached it.
        if !h.receiver.control().settle(RECEIVE_TIMEOUT) {
            return Err(CameraError::Read {
                device: "hil h264-rtp".into(),
                seq: h.rendered.meta.seq,
                reason: format!(
                    "the simulated camera manager did not take an exposure within {} s",
                    RECEIVE_TIMEOUT.as_secs()
                ),
            });
        }
        let c = h.manager.controls();
        if c.auto_exposure == EXPOSURE_MANUAL && c.exposure_units != h.applied_units {
            h.applied_units = c.exposure_units;
            self.rig
                .set_exposure_us(c.exposure_units as f64 * V4L2_EXPOSURE_UNIT_US)?;
        }
        self.rig.grab(&mut h.rendered)?;
        let stamp = h.rendered.meta.stamp_s;
        let err = |reason: String| CameraError::Read {
            device: "hil h264-rtp".into(),
            seq: h.rendered.meta.seq,
            reason,
        };
        let t0 = Instant::now();
        h.sender
            .push(&h.rendered, stamp)
            .map_err(|e| err(e.to_string()))?;
        h.sent.push_back(stamp);
        let deadline = Instant::now() + RECEIVE_TIMEOUT;
        let before = h.receiver.frames_passed_over();
        loop {
            match h.receiver.grab(frame) {
                Ok(()) => break,
                Err(e) if Instant::now() >= deadline => {
                    return Err(err(format!(
                        "frame at {stamp:.3} s not back through the stream within {} s: {e}",
                        RECEIVE_TIMEOUT.as_secs()
                    )))
                }
                Err(_) => {}
            }
        }
        if h.added_latency_s.len() < h.added_latency_s.capacity() {
            h.added_latency_s.push(t0.elapsed().as_secs_f64());
        }
        // Frames the receiver passed over were sent too: their stamps go.
        for _ in 0..(h.receiver.frames_passed_over() - before) {
            h.sent.pop_front();
        }
        frame.meta.stamp_s = h.sent.pop_front().unwrap_or(stamp);
        Ok(())
    }
}
