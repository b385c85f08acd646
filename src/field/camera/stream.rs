//! Stream cameras: H.264 over RTP/UDP (BlueOS's default stream), RTSP, or any GStreamer
//! pipeline ending in an appsink, decoded to 8-bit grey.
//!
//! The decoder's output is used as it comes: its first (luma) plane is the grey image.
//! GStreamer through gstreamer-rs: appsink hands over each frame with its timestamp
//! (the pipeline's running time) and, with `drop=true max-buffers=1`, keeps only the
//! newest decoded frame, so the loop never works through a backlog. Frames it passed
//! over are counted from the gaps between timestamps. The jitter buffer runs with
//! `mode=none latency=0`: nothing is held back for reordering, and timestamps follow
//! the sender's RTP timestamps (the camera's clock), not the arrival times. Exposure goes out through an
//! [`ExposureControl`]; which exposure each frame had comes from [`Attribution`].

use std::time::{Duration, Instant};

use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};

use super::attribution::Attribution;
use super::control::{quantize, ExposureControl};

/// How long one `grab` waits before handing control back (the caller's stall clock).
pub const GRAB_TICK: Duration = Duration::from_millis(50);

/// Where a stream comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StreamSource {
    /// RTP H.264 on a UDP port (`udp:PORT` listens on every address, `udp:HOST:PORT` on
    /// one).
    Udp { host: Option<String>, port: u16 },
    /// `rtsp://...`.
    Rtsp(String),
    /// `gst:PIPELINE` ending in an appsink.
    Gst(String),
}

impl StreamSource {
    /// Parses `udp:...`, `rtsp://...` or `gst:...`; None for other schemes.
    pub fn parse(s: &str) -> Option<Result<Self, String>> {
        if s.starts_with("rtsp://") || s.starts_with("rtsps://") {
            let rest = s.split_once("://").map_or("", |(_, r)| r);
            if rest.is_empty() || rest.contains(['"', ' ', '!']) {
                return Some(Err(format!("{s}: expected rtsp://HOST[:PORT]/PATH")));
            }
            return Some(Ok(Self::Rtsp(s.to_string())));
        }
        if let Some(p) = s.strip_prefix("gst:") {
            if !p.contains("appsink") {
                return Some(Err(format!(
                    "{s}: a gst: pipeline must end in an appsink (... ! appsink)"
                )));
            }
            return Some(Ok(Self::Gst(p.to_string())));
        }
        let rest = s.strip_prefix("udp:")?;
        let (host, port) = match rest.rsplit_once(':') {
            Some((h, p)) => (Some(h.to_string()), p),
            None => (None, rest),
        };
        let bad = || format!("{s}: expected udp:PORT or udp:HOST:PORT (PORT 1..65535)");
        let Ok(port) = port.parse::<u16>() else {
            return Some(Err(bad()));
        };
        if port == 0
            || host
                .as_deref()
                .is_some_and(|h| h.is_empty() || h.contains([' ', '"', '!']))
        {
            return Some(Err(bad()));
        }
        Some(Ok(Self::Udp { host, port }))
    }

    /// The GStreamer pipeline description.
    pub fn pipeline(&self) -> String {
        const DECODE: &str =
            "rtph264depay ! h264parse ! avdec_h264 max-threads=1 ! appsink name=markhold_sink";
        match self {
            Self::Udp { host, port } => {
                let addr = host
                    .as_ref()
                    .map_or(String::new(), |h| format!(" address={h}"));
                format!(
                    "udpsrc port={port}{addr} caps=\"application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,payload=96\" buffer-size=8388608 ! rtpjitterbuffer mode=none latency=0 ! {DECODE}"
                )
            }
            Self::Rtsp(url) => {
                format!("rtspsrc location=\"{url}\" latency=0 buffer-mode=none ! {DECODE}")
            }
            Self::Gst(p) => p.clone(),
        }
    }
}

impl std::fmt::Display for StreamSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Udp { host: None, port } => write!(f, "udp:{port}"),
            Self::Udp {
                host: Some(h),
                port,
            } => write!(f, "udp:{h}:{port}"),
            Self::Rtsp(u) => f.write_str(u),
            Self::Gst(p) => write!(f, "gst:{p}"),
        }
    }
}

/// Options of a stream camera.
pub struct StreamConfig {
    pub fps: f64,
    pub limits: ExposureLimits,
    pub initial_us: f64,
    /// How long `open` waits for the first frame.
    pub first_frame_timeout: Duration,
}

/// A stream camera.
pub struct StreamCamera {
    name: String,
    pipeline: gst::Pipeline,
    sink: gst_app::AppSink,
    bus: gst::Bus,
    control: Box<dyn ExposureControl>,
    attribution: Attribution,
    limits: ExposureLimits,
    step_us: f64,
    fps: f64,
    /// The exposure in force (the last one the control accepted).
    current_us: f64,
    /// The loop's last request, before rounding to the camera's step.
    requested_us: f64,
    /// Frames the camera took (counted from timestamps), the last delivered one's
    /// seq and time.
    seq: u64,
    last_pts: Option<gst::ClockTime>,
    passed_over: u64,
    /// Why the stream stopped, once it has.
    stopped: Option<String>,
    warned_control: bool,
    /// The first frame, pulled while waiting for it at start-up.
    held: Option<gst::Sample>,
    /// A frame was delivered already.
    delivered: bool,
    /// Luma to grey, for the range the stream's caps say (video or full).
    lut: [u8; 256],
    lut_limited: bool,
}

/// True when the caps' luma is video range (16..235): YUV unless its colorimetry says
/// full range (`jpeg`, `sRGB`, or a `range:matrix:transfer:primaries` string starting
/// with 1).
fn limited_range(format: &str, colorimetry: Option<&str>) -> bool {
    if format == "GRAY8" {
        return false;
    }
    match colorimetry {
        Some("jpeg" | "sRGB") => false,
        Some(c) if c.contains(':') => !c.starts_with("1:"),
        _ => true,
    }
}

fn range_lut(limited: bool) -> [u8; 256] {
    let mut lut = [0u8; 256];
    for (i, v) in lut.iter_mut().enumerate() {
        *v = if limited {
            ((i as f64 - 16.0) * 255.0 / 219.0)
                .round()
                .clamp(0.0, 255.0) as u8
        } else {
            i as u8
        };
    }
    lut
}

#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error("{url}: GStreamer: {reason}")]
    Gst { url: String, reason: String },
    #[error("{url}: {reason}")]
    Pipeline { url: String, reason: String },
    #[error("{url}: no frame within {waited_ms} ms{why}")]
    NoFirstFrame {
        url: String,
        waited_ms: u128,
        why: String,
    },
    #[error(transparent)]
    Control(#[from] super::control::ControlError),
}

/// Initializes GStreamer once; an error names what failed.
pub fn init() -> Result<(), String> {
    gst::init().map_err(|e| format!("GStreamer does not start: {e}"))
}

/// The first error or end-of-stream on `bus`, without waiting.
fn bus_problem(bus: &gst::Bus) -> Option<String> {
    while let Some(msg) = bus.pop_filtered(&[gst::MessageType::Error, gst::MessageType::Eos]) {
        match msg.view() {
            gst::MessageView::Error(e) => {
                let src = e
                    .src()
                    .map_or_else(String::new, |s| format!("{}: ", s.name()));
                return Some(format!("{src}{}", e.error()));
            }
            gst::MessageView::Eos(_) => return Some("end of stream".into()),
            _ => {}
        }
    }
    None
}

impl StreamCamera {
    /// Builds and starts the pipeline and waits (bounded) for the first frame.
    pub fn open(
        source: &StreamSource,
        cfg: &StreamConfig,
        control: Box<dyn ExposureControl>,
    ) -> Result<Self, StreamError> {
        let mut cam = Self::start(source, cfg, control)?;
        cam.wait_first_frame(cfg.first_frame_timeout)?;
        Ok(cam)
    }

    /// Builds and starts the pipeline (its sockets are bound on return).
    pub fn start(
        source: &StreamSource,
        cfg: &StreamConfig,
        mut control: Box<dyn ExposureControl>,
    ) -> Result<Self, StreamError> {
        let url = source.to_string();
        let gst_err = |reason: String| StreamError::Gst {
            url: url.clone(),
            reason,
        };
        init().map_err(gst_err)?;
        let desc = source.pipeline();
        let element = gst::parse::launch(&desc).map_err(|e| gst_err(format!("{e}")))?;
        let pipeline = element
            .downcast::<gst::Pipeline>()
            .map_err(|_| gst_err("the description is not a pipeline (one element?)".into()))?;
        let sink = find_appsink(&pipeline).ok_or_else(|| StreamError::Pipeline {
            url: url.clone(),
            reason: "the pipeline has no appsink".into(),
        })?;
        sink.set_drop(true);
        sink.set_max_buffers(1);
        sink.set_sync(false);
        // Grey, or planar YUV whose first plane is the grey image (no conversion: a
        // 1080p videoconvert to GRAY8 costs several times the decode).
        sink.set_caps(Some(
            &gst::Caps::builder("video/x-raw")
                .field("format", gst::List::new(LUMA_FIRST_FORMATS))
                .build(),
        ));
        let bus = pipeline.bus().ok_or_else(|| gst_err("no bus".into()))?;
        let step_us = control.step_us();
        let initial = quantize(cfg.limits.clamp(cfg.initial_us), step_us);
        let current_us = control.set_exposure_us(initial)?;
        let cam = Self {
            name: url.clone(),
            pipeline,
            sink,
            bus,
            control,
            attribution: Attribution::new(current_us),
            limits: cfg.limits,
            step_us,
            fps: cfg.fps.max(0.1),
            current_us,
            requested_us: current_us,
            seq: 0,
            last_pts: None,
            passed_over: 0,
            stopped: None,
            warned_control: false,
            held: None,
            delivered: false,
            lut: range_lut(false),
            lut_limited: false,
        };
        cam.pipeline.set_state(gst::State::Playing).map_err(|_| {
            let why = bus_problem(&cam.bus).unwrap_or_else(|| "state change failed".into());
            gst_err(format!("does not start: {why}"))
        })?;
        if let Some(why) = bus_problem(&cam.bus) {
            return Err(gst_err(format!("does not start: {why}")));
        }
        Ok(cam)
    }

    /// Waits until a first frame is ready (bounded), or says why none came.
    pub fn wait_first_frame(&mut self, timeout: Duration) -> Result<(), StreamError> {
        let t0 = Instant::now();
        loop {
            if let Some(sample) = self.sink.try_pull_sample(gst::ClockTime::from_mseconds(20)) {
                self.held = Some(sample);
                return Ok(());
            }
            if let Some(why) = bus_problem(&self.bus) {
                return Err(StreamError::NoFirstFrame {
                    url: self.name.clone(),
                    waited_ms: t0.elapsed().as_millis(),
                    why: format!(": {why}"),
                });
            }
            if t0.elapsed() >= timeout {
                return Err(StreamError::NoFirstFrame {
                    url: self.name.clone(),
                    waited_ms: t0.elapsed().as_millis(),
                    why: " (is the stream sent to this port/URL?)".into(),
                });
            }
        }
    }

    /// The delay from command to frame, frames, as estimated so far.
    pub fn delay_frames(&self) -> Option<u32> {
        self.attribution.delay_frames()
    }

    /// The attribution state (delay estimates).
    pub fn attribution(&self) -> &Attribution {
        &self.attribution
    }

    /// Why the stream stopped, if it has.
    pub fn stopped(&self) -> Option<&str> {
        self.stopped.as_deref()
    }

    fn read_err(&self, reason: String) -> CameraError {
        CameraError::Read {
            device: self.name.clone(),
            seq: self.seq,
            reason,
        }
    }
}

impl Drop for StreamCamera {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}

fn find_appsink(pipeline: &gst::Pipeline) -> Option<gst_app::AppSink> {
    if let Some(e) = pipeline.by_name("markhold_sink") {
        return e.downcast::<gst_app::AppSink>().ok();
    }
    pipeline
        .iterate_recurse()
        .into_iter()
        .flatten()
        .find_map(|e| e.downcast::<gst_app::AppSink>().ok())
}

/// Raw formats whose first plane is 8-bit luma in rows padded to 4 bytes (GStreamer's
/// default layout, which appsink gets: it does not ask for custom strides).
const LUMA_FIRST_FORMATS: [&str; 7] = ["GRAY8", "I420", "YV12", "NV12", "NV21", "Y42B", "Y444"];

/// The grab's failure when no frame came within one tick (the stall clock runs on).
pub const NO_FRAME_REASON: &str = "no frame within the grab tick";

impl Camera for StreamCamera {
    fn name(&self) -> &str {
        &self.name
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.requested_us = exposure_us;
        let want = quantize(self.limits.clamp(exposure_us), self.step_us);
        if (want - self.current_us).abs() < 0.5 {
            return Ok(self.current_us);
        }
        match self.control.set_exposure_us(want) {
            Ok(got) => {
                self.current_us = got;
                self.warned_control = false;
                self.attribution.commanded(got);
            }
            Err(e) => {
                // The camera keeps its last exposure; the loop goes on with it.
                if !self.warned_control {
                    tracing::warn!("{e}; keeping exposure {} us", self.current_us);
                    self.warned_control = true;
                }
            }
        }
        Ok(self.current_us)
    }
    fn frames_passed_over(&self) -> u64 {
        self.passed_over
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        if let Some(why) = &self.stopped {
            return Err(self.read_err(format!("{NO_FRAME_REASON}: the stream stopped: {why}")));
        }
        let Some(sample) = self.held.take().or_else(|| {
            self.sink
                .try_pull_sample(gst::ClockTime::from_nseconds(GRAB_TICK.as_nanos() as u64))
        }) else {
            if let Some(why) = bus_problem(&self.bus) {
                tracing::warn!(camera = %self.name, "the stream stopped: {why}");
                self.stopped = Some(why);
            }
            return Err(self.read_err(NO_FRAME_REASON.into()));
        };
        let buffer = sample
            .buffer()
            .ok_or_else(|| self.read_err("a sample without a buffer".into()))?;
        let st = sample
            .caps()
            .and_then(|c| c.structure(0))
            .ok_or_else(|| self.read_err("a sample without caps".into()))?;
        let (w, h) = st
            .get::<i32>("width")
            .ok()
            .zip(st.get::<i32>("height").ok())
            .ok_or_else(|| self.read_err("a sample without width/height caps".into()))?;
        let limited = limited_range(
            st.get::<&str>("format").unwrap_or("GRAY8"),
            st.get::<&str>("colorimetry").ok(),
        );
        if limited != self.lut_limited {
            self.lut = range_lut(limited);
            self.lut_limited = limited;
        }
        let (w, h) = (w.max(0) as u32, h.max(0) as u32);
        let map = buffer
            .map_readable()
            .map_err(|e| self.read_err(format!("cannot map the buffer: {e}")))?;
        let n = w as usize * h as usize;
        let stride = (w as usize).next_multiple_of(4);
        if map.len() < stride * h as usize {
            return Err(self.read_err(format!("{} bytes for {w}x{h}", map.len())));
        }
        if frame.data.len() != n {
            frame.data.resize(n, 0);
        }
        frame.width = w;
        frame.height = h;
        let mut sum = 0u64;
        for (dst, src) in frame
            .data
            .chunks_exact_mut(w as usize)
            .zip(map.chunks(stride))
        {
            // Video-range luma (16..235) to full-range grey (0..255), as a table.
            for (d, &v) in dst.iter_mut().zip(&src[..w as usize]) {
                *d = self.lut[usize::from(v)];
            }
            // Every 8th pixel is enough for the step response.
            sum += dst.iter().step_by(8).map(|&v| u64::from(v)).sum::<u64>();
        }
        let sampled = (h as u64) * (w as u64).div_ceil(8);
        let mean = sum as f64 / sampled.max(1) as f64;
        let pts = buffer.pts();
        // Frames the camera took in between, from the timestamps.
        let gap = match (self.last_pts, pts) {
            (Some(a), Some(b)) if b > a => {
                let dt = (b - a).nseconds() as f64 * 1e-9;
                ((dt * self.fps).round() as u64).max(1)
            }
            _ => 1,
        };
        if self.delivered {
            // The first frame is seq 0, as with every camera.
            if self.last_pts.is_some() {
                self.passed_over += gap - 1;
            }
            self.seq += gap;
        }
        self.delivered = true;
        self.last_pts = pts.or(self.last_pts);
        frame.meta.seq = self.seq;
        frame.meta.stamp_s = pts.map_or(self.seq as f64 / self.fps, |p| p.nseconds() as f64 * 1e-9);
        let taken = self.attribution.frame(self.seq, mean);
        // A frame taken at the step the last request rounds to is labelled with the
        // request: the controller sees it exposed as commanded (the true value is at
        // most half a step away).
        let request_step = quantize(self.limits.clamp(self.requested_us), self.step_us);
        frame.meta.exposure_us = if (taken - request_step).abs() < 0.5 {
            self.requested_us
        } else {
            taken
        };
        frame.meta.gain_db = 0.0;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_stream_urls() {
        assert_eq!(
            StreamSource::parse("udp:5600"),
            Some(Ok(StreamSource::Udp {
                host: None,
                port: 5600
            }))
        );
        assert_eq!(
            StreamSource::parse("udp:127.0.0.1:5600"),
            Some(Ok(StreamSource::Udp {
                host: Some("127.0.0.1".into()),
                port: 5600
            }))
        );
        for bad in [
            "udp:",
            "udp:0",
            "udp:70000",
            "udp:x",
            "rtsp://",
            "gst:videotestsrc ! fakesink",
        ] {
            assert!(matches!(StreamSource::parse(bad), Some(Err(_))), "{bad}");
        }
        assert!(StreamSource::parse("v4l2:/dev/video0").is_none());
    }

    #[test]
    fn video_range_luma_is_expanded_to_full_range_grey() {
        assert!(limited_range("I420", Some("bt709")));
        assert!(limited_range("I420", None));
        assert!(limited_range("NV12", Some("2:3:5:1")));
        assert!(!limited_range("I420", Some("jpeg")));
        assert!(!limited_range("I420", Some("1:4:0:0")));
        assert!(!limited_range("GRAY8", Some("bt709")));
        let lut = range_lut(true);
        assert_eq!(
            (lut[0], lut[16], lut[126], lut[235], lut[255]),
            (0, 0, 128, 255, 255)
        );
        assert_eq!(range_lut(false)[77], 77);
    }
}
