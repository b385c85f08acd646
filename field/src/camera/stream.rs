//! Stream cameras: H.264 over RTP/UDP (BlueOS's default stream), RTSP, or any GStreamer
//! pipeline ending in an appsink, decoded to 8-bit grey.
//!
//! The decoder is the platform's hardware H.264 decoder where one is installed and starts
//! (`v4l2h264dec` on a Raspberry Pi), else libav's software decoder; which one runs is
//! reported ([`DecoderReport`]). Its output is used as it comes: its first (luma) plane
//! is the grey image.
//! GStreamer through gstreamer-rs: appsink hands over each frame with its timestamp
//! (the pipeline's running time) and, with `drop=true max-buffers=1`, keeps only the
//! newest decoded frame, so the loop never works through a backlog. Frames it passed
//! over are counted from the gaps between timestamps. The jitter buffer runs with
//! `mode=none latency=0`: nothing is held back for reordering, and timestamps follow
//! the sender's RTP timestamps (the camera's clock), not the arrival times. Exposure goes
//! out through a [`ControlHandle`] (a worker thread: the loop never waits on the camera);
//! which exposure each frame had comes from [`Attribution`]. A stream that ends or fails
//! is built again with a back-off; its stamps go on from the last frame's.

use std::time::{Duration, Instant};

use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};

use super::attribution::Attribution;
use super::control::quantize;
use super::rtsp_guard::{self, RtspGuard};
use super::worker::ControlHandle;
use markhold_core::signal::ShutdownFlag;

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

    /// The GStreamer pipeline description with the software decoder.
    pub fn pipeline(&self) -> String {
        self.pipeline_with(SOFTWARE_H264)
    }

    /// The GStreamer pipeline description with the H.264 decoder `decoder` (an element
    /// name; a `gst:` pipeline is as given).
    pub fn pipeline_with(&self, decoder: &str) -> String {
        let decode = format!(
            "rtph264depay ! h264parse ! {} ! appsink name=markhold_sink",
            decoder_desc(decoder)
        );
        match self {
            Self::Udp { host, port } => {
                let addr = host
                    .as_ref()
                    .map_or(String::new(), |h| format!(" address={h}"));
                format!(
                    "udpsrc port={port}{addr} caps=\"application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,payload=96\" buffer-size=8388608 ! rtpjitterbuffer mode=none latency=0 ! {decode}"
                )
            }
            Self::Rtsp(url) => {
                format!("rtspsrc location=\"{url}\" latency=0 buffer-mode=none ! {decode}")
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

/// Hardware H.264 decoders, tried in this order: the Raspberry Pi's stateful V4L2 decoder
/// (bcm2835-codec, `/dev/video10`), a stateless V4L2 one (other ARM boards), VA-API on
/// x86 (the `va` plugin, then the older `vaapi` one). GStreamer registers the V4L2 ones
/// only where the device exists, the VA ones only where a VA driver answers.
pub const HARDWARE_H264: [&str; 4] = ["v4l2h264dec", "v4l2slh264dec", "vah264dec", "vaapih264dec"];
/// The software decoder every host has (gstreamer1.0-libav), the fallback.
pub const SOFTWARE_H264: &str = "avdec_h264";
/// Environment variable: the H.264 decoders to try before the software one, comma
/// separated (`software`: none), instead of [`HARDWARE_H264`].
pub const DECODER_ENV: &str = "MARKHOLD_H264_DECODER";
/// The decoder element's name in the pipeline (its errors name it).
const DECODER_NAME: &str = "markhold_decoder";

/// The element and options of decoder `name` in a pipeline description.
fn decoder_desc(name: &str) -> String {
    if name == SOFTWARE_H264 {
        // One thread: frame threads would add a frame of latency each.
        format!("{name} name={DECODER_NAME} max-threads=1")
    } else {
        format!("{name} name={DECODER_NAME}")
    }
}

/// Which H.264 decoders a stream tries before the software one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecoderChoice {
    pub preferred: Vec<String>,
}

impl DecoderChoice {
    /// The platform's hardware decoders ([`HARDWARE_H264`]).
    pub fn auto() -> Self {
        Self::prefer(HARDWARE_H264)
    }

    /// The software decoder alone.
    pub fn software() -> Self {
        Self {
            preferred: Vec::new(),
        }
    }

    /// These elements first, in order.
    pub fn prefer<S: AsRef<str>>(names: impl IntoIterator<Item = S>) -> Self {
        Self {
            preferred: names.into_iter().map(|n| n.as_ref().to_string()).collect(),
        }
    }

    /// From `value` ([`DECODER_ENV`]'s form): element names, comma separated, or
    /// `software`.
    pub fn parse(value: &str) -> Result<Self, String> {
        let mut names = Vec::new();
        for n in value.split(',').map(str::trim).filter(|n| !n.is_empty()) {
            if n == "software" || n == SOFTWARE_H264 {
                continue;
            }
            let ok = n
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
            if !ok {
                return Err(format!(
                    "{DECODER_ENV}={value}: '{n}' is not a GStreamer element name (letters, digits, '_', '-'; names comma separated, or 'software')"
                ));
            }
            names.push(n.to_string());
        }
        Ok(Self { preferred: names })
    }

    /// [`DECODER_ENV`] if set, else [`Self::auto`].
    pub fn from_env() -> Result<Self, String> {
        match std::env::var(DECODER_ENV) {
            Ok(v) => Self::parse(&v),
            Err(_) => Ok(Self::auto()),
        }
    }
}

/// A decoder tried first and not used, and why.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct DecoderSkipped {
    pub element: String,
    pub reason: String,
}

/// The H.264 decoder a stream runs, reported at start and in a run's summary.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct DecoderReport {
    /// The decoding element (its factory name).
    pub element: String,
    /// Its factory's class says `Hardware`.
    pub hardware: bool,
    /// The decoders tried before it, with the reason each was not used: a fallback, not
    /// an error.
    pub passed_over: Vec<DecoderSkipped>,
}

impl std::fmt::Display for DecoderReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = if self.hardware {
            "hardware"
        } else {
            "software"
        };
        write!(f, "{} ({kind})", self.element)?;
        for (i, s) in self.passed_over.iter().enumerate() {
            let sep = if i == 0 { "; before it " } else { ", " };
            write!(f, "{sep}{}: {}", s.element, s.reason)?;
        }
        Ok(())
    }
}

/// True when the element factory's class says it is hardware.
fn is_hardware(factory: &gst::ElementFactory) -> bool {
    factory.klass().contains("Hardware")
}

/// The video decoder in a built pipeline (a `gst:` pipeline's own), if any.
fn find_decoder(pipeline: &gst::Pipeline) -> Option<DecoderReport> {
    pipeline
        .iterate_recurse()
        .into_iter()
        .flatten()
        .find_map(|e| {
            let f = e.factory()?;
            let klass = f.klass();
            (klass.contains("Decoder") && klass.contains("Video")).then(|| DecoderReport {
                element: f.name().to_string(),
                hardware: is_hardware(&f),
                passed_over: Vec::new(),
            })
        })
}

/// Options of a stream camera.
pub struct StreamConfig {
    pub fps: f64,
    pub limits: ExposureLimits,
    pub initial_us: f64,
    /// How long `open` waits for the first frame.
    pub first_frame_timeout: Duration,
    /// After an end of stream or an error, build the pipeline again (after 0.5 s, then
    /// twice as long each time up to 8 s, until a frame comes). Off for a simulation,
    /// which drives the stream itself.
    pub restart: bool,
    /// A signal: the first-frame wait gives up.
    pub stop: ShutdownFlag,
}

/// The first wait before building a stopped pipeline again.
pub const RESTART_FIRST: Duration = Duration::from_millis(500);
/// The longest wait between two restarts.
pub const RESTART_MAX: Duration = Duration::from_secs(8);
/// A running stream silent this long is built again.
pub const STALL_RESTART: Duration = Duration::from_secs(2);

/// A built pipeline with its appsink and bus.
struct Built {
    pipeline: gst::Pipeline,
    sink: gst_app::AppSink,
    bus: gst::Bus,
}

impl Built {
    /// Parses `desc`, finds the appsink and sets it to keep only the newest frame.
    fn new(url: &str, desc: &str) -> Result<Self, StreamError> {
        let gst_err = |reason: String| StreamError::Gst {
            url: url.to_string(),
            reason,
        };
        let element = gst::parse::launch(desc).map_err(|e| gst_err(format!("{e}")))?;
        let pipeline = element
            .downcast::<gst::Pipeline>()
            .map_err(|_| gst_err("the description is not a pipeline (one element?)".into()))?;
        let sink = find_appsink(&pipeline).ok_or_else(|| StreamError::Pipeline {
            url: url.to_string(),
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
        Ok(Self {
            pipeline,
            sink,
            bus,
        })
    }

    /// Builds and starts `desc`; a pipeline that does not start is stopped here (its
    /// sockets released) before the error returns.
    fn start(url: &str, desc: &str) -> Result<Self, StreamError> {
        let b = Self::new(url, desc)?;
        match b.play(url) {
            Ok(()) => Ok(b),
            Err(e) => {
                let _ = b.pipeline.set_state(gst::State::Null);
                Err(e)
            }
        }
    }

    fn play(&self, url: &str) -> Result<(), StreamError> {
        let gst_err = |reason: String| StreamError::Gst {
            url: url.to_string(),
            reason,
        };
        self.pipeline.set_state(gst::State::Playing).map_err(|_| {
            let why = bus_problem(&self.bus).unwrap_or_else(|| "state change failed".into());
            gst_err(format!("does not start: {why}"))
        })?;
        if let Some(why) = bus_problem(&self.bus) {
            return Err(gst_err(format!("does not start: {why}")));
        }
        Ok(())
    }

    /// Stops the pipeline on a thread of its own: an element stuck on a peer must not
    /// hold the caller.
    fn retire(self) {
        let spawned = std::thread::Builder::new()
            .name("markhold-stream-stop".into())
            .spawn(move || {
                let _ = self.pipeline.set_state(gst::State::Null);
            });
        if let Err(e) = spawned {
            tracing::warn!("stopping an old stream pipeline: {e}");
        }
    }
}

/// A stream camera.
pub struct StreamCamera {
    name: String,
    /// The pipeline description (built again on a restart).
    desc: String,
    built: Option<Built>,
    /// rtsp://: the guard rtspsrc talks through.
    guard: Option<RtspGuard>,
    control: ControlHandle,
    attribution: Attribution,
    limits: ExposureLimits,
    step_us: f64,
    fps: f64,
    /// The control's report last seen (its `seq`).
    applied_seq: u64,
    /// The loop's last request, before rounding to the camera's step.
    requested_us: f64,
    /// Frames the camera took (counted from timestamps), the last delivered one's
    /// seq and time.
    seq: u64,
    last_pts: Option<gst::ClockTime>,
    passed_over: u64,
    /// Why the stream stopped, once it has, and when to build it again.
    stopped: Option<String>,
    restart: bool,
    restart_at: Option<Instant>,
    backoff: Duration,
    /// Restarts so far.
    restarts: u64,
    /// Stamps: pipeline time plus this offset (changed at a restart so stamps go on
    /// from the last one), the last stamp and when it was delivered.
    stamp_offset: f64,
    rebase: bool,
    last_stamp: Option<f64>,
    delivered_at: Option<Instant>,
    /// When the running pipeline was built.
    built_at: Option<Instant>,
    stop: ShutdownFlag,
    /// The first frame, pulled while waiting for it at start-up.
    held: Option<gst::Sample>,
    /// The H.264 decoder running (None: a `gst:` pipeline without a video decoder).
    decoder: Option<DecoderReport>,
    /// `udp:` / `rtsp://`: the source the pipeline is made for (the guard's address for
    /// RTSP), to build it with the software decoder when a hardware one fails before the
    /// first frame.
    local: Option<StreamSource>,
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
    /// Builds and starts the pipeline and waits (bounded) for the first frame; the
    /// decoders tried are [`DecoderChoice::from_env`]'s.
    pub fn open(
        source: &StreamSource,
        cfg: &StreamConfig,
        control: ControlHandle,
    ) -> Result<Self, StreamError> {
        let choice = Self::env_choice(source)?;
        Self::open_with(source, cfg, control, &choice)
    }

    /// [`Self::open`] trying `choice`'s decoders before the software one.
    pub fn open_with(
        source: &StreamSource,
        cfg: &StreamConfig,
        control: ControlHandle,
        choice: &DecoderChoice,
    ) -> Result<Self, StreamError> {
        let mut cam = Self::start_with(source, cfg, control, choice)?;
        cam.wait_first_frame(cfg.first_frame_timeout)?;
        Ok(cam)
    }

    fn env_choice(source: &StreamSource) -> Result<DecoderChoice, StreamError> {
        DecoderChoice::from_env().map_err(|reason| StreamError::Pipeline {
            url: source.to_string(),
            reason,
        })
    }

    /// Builds and starts the pipeline (its sockets are bound on return) with the
    /// software decoder: the simulation's stream (`hil --camera-transport h264-rtp`)
    /// repeats bit for bit for a seed whatever decoders the host has.
    pub fn start(
        source: &StreamSource,
        cfg: &StreamConfig,
        control: ControlHandle,
    ) -> Result<Self, StreamError> {
        Self::start_with(source, cfg, control, &DecoderChoice::software())
    }

    /// [`Self::start`] trying `choice`'s decoders before the software one: each that is
    /// installed is built and set playing; the first that plays decodes, and the ones
    /// before it are reported with the reason (not installed, does not start).
    pub fn start_with(
        source: &StreamSource,
        cfg: &StreamConfig,
        control: ControlHandle,
        choice: &DecoderChoice,
    ) -> Result<Self, StreamError> {
        let url = source.to_string();
        init().map_err(|reason| StreamError::Gst {
            url: url.clone(),
            reason,
        })?;
        // rtsp://: rtspsrc talks to the server through the guard.
        let (local, guard) = match source {
            StreamSource::Rtsp(u) => {
                let (server, path) =
                    rtsp_guard::split_url(u).ok_or_else(|| StreamError::Pipeline {
                        url: url.clone(),
                        reason: "expected rtsp://HOST[:PORT]/PATH".into(),
                    })?;
                let guard = RtspGuard::start(&server).map_err(|e| StreamError::Pipeline {
                    url: url.clone(),
                    reason: format!("{server}: {e}"),
                })?;
                let local = StreamSource::Rtsp(format!("rtsp://127.0.0.1:{}{path}", guard.port()));
                (Some(local), Some(guard))
            }
            StreamSource::Udp { .. } => (Some(source.clone()), None),
            StreamSource::Gst(_) => (None, None),
        };
        let (built, desc, decoder) = match &local {
            Some(local) => {
                let (b, desc, report) = start_decoding(&url, local, choice)?;
                (b, desc, Some(report))
            }
            None => {
                let desc = source.pipeline();
                let b = Built::start(&url, &desc)?;
                let report = find_decoder(&b.pipeline);
                (b, desc, report)
            }
        };
        match &decoder {
            Some(d) => tracing::info!(camera = %url, pipeline = %desc, "stream decoder {d}"),
            None => {
                tracing::info!(camera = %url, pipeline = %desc, "stream pipeline (no video decoder)")
            }
        }
        let step_us = control.step_us();
        let applied = control.applied();
        Ok(Self {
            name: url,
            desc,
            built: Some(built),
            guard,
            attribution: Attribution::new(applied.exposure_us),
            applied_seq: applied.seq,
            control,
            limits: cfg.limits,
            step_us,
            fps: cfg.fps.max(0.1),
            requested_us: cfg.initial_us,
            seq: 0,
            last_pts: None,
            passed_over: 0,
            stopped: None,
            restart: cfg.restart,
            restart_at: None,
            backoff: RESTART_FIRST,
            restarts: 0,
            stamp_offset: 0.0,
            rebase: false,
            last_stamp: None,
            delivered_at: None,
            built_at: Some(Instant::now()),
            stop: cfg.stop.clone(),
            held: None,
            decoder,
            local,
            delivered: false,
            lut: range_lut(false),
            lut_limited: false,
        })
    }

    /// Waits until a first frame is ready (bounded, and a signal ends the wait), or
    /// says why none came.
    pub fn wait_first_frame(&mut self, timeout: Duration) -> Result<(), StreamError> {
        let t0 = Instant::now();
        let no_frame = |cam: &Self, why: String| StreamError::NoFirstFrame {
            url: cam.name.clone(),
            waited_ms: t0.elapsed().as_millis(),
            why,
        };
        loop {
            let Some(built) = &self.built else {
                return Err(no_frame(self, ": the stream is stopped".into()));
            };
            if let Some(sample) = built
                .sink
                .try_pull_sample(gst::ClockTime::from_mseconds(20))
            {
                self.held = Some(sample);
                return Ok(());
            }
            if let Some(why) = self.guard.as_ref().and_then(RtspGuard::failure) {
                return Err(no_frame(self, format!(": {why}")));
            }
            if let Some(why) = bus_problem(&built.bus) {
                if self.software_after(&why)? {
                    continue;
                }
                return Err(no_frame(self, format!(": {why}")));
            }
            if self.stop.is_set() {
                return Err(no_frame(self, ": stopped by a signal".into()));
            }
            if t0.elapsed() >= timeout {
                return Err(no_frame(
                    self,
                    " (is the stream sent to this port/URL?)".into(),
                ));
            }
        }
    }

    /// The pipeline with a decoder other than the software one failed (`why`, from the
    /// bus) before the first frame: it is built again with the software decoder and the
    /// failure reported as a fallback. False when the software decoder was running.
    fn software_after(&mut self, why: &str) -> Result<bool, StreamError> {
        let (Some(local), Some(report)) = (&self.local, &mut self.decoder) else {
            return Ok(false);
        };
        // Any error before the first frame: a decoder that cannot negotiate may leave the
        // error to the source element ("internal data flow error").
        if report.element == SOFTWARE_H264 {
            return Ok(false);
        }
        tracing::warn!(camera = %self.name, "{}: {why}; decoding in software", report.element);
        report.passed_over.push(DecoderSkipped {
            element: report.element.clone(),
            reason: format!("failed before the first frame: {why}"),
        });
        let desc = local.pipeline_with(SOFTWARE_H264);
        if let Some(b) = self.built.take() {
            let _ = b.pipeline.set_state(gst::State::Null);
        }
        self.built = Some(Built::start(&self.name, &desc)?);
        self.built_at = Some(Instant::now());
        report.element = SOFTWARE_H264.into();
        report.hardware = false;
        self.desc = desc;
        Ok(true)
    }

    /// The H.264 decoder running (None: a `gst:` pipeline without a video decoder).
    pub fn decoder(&self) -> Option<&DecoderReport> {
        self.decoder.as_ref()
    }

    /// The delay from command to frame, frames, as estimated so far.
    pub fn delay_frames(&self) -> Option<u32> {
        self.attribution.delay_frames()
    }

    /// The attribution state (delay estimates).
    pub fn attribution(&self) -> &Attribution {
        &self.attribution
    }

    /// The exposure control's handle.
    pub fn control(&self) -> &ControlHandle {
        &self.control
    }

    /// Why the stream stopped, if it has (and is not running again).
    pub fn stopped(&self) -> Option<&str> {
        self.stopped.as_deref()
    }

    /// Pipelines built again after the stream stopped.
    pub fn restarts(&self) -> u64 {
        self.restarts
    }

    fn read_err(&self, reason: String) -> CameraError {
        CameraError::Read {
            device: self.name.clone(),
            seq: self.seq,
            reason,
        }
    }

    /// The stream stopped (end of stream, an error, the guard cut it): retire the
    /// pipeline and plan a restart.
    fn on_stopped(&mut self, why: String) {
        let why = match self.guard.as_ref().and_then(RtspGuard::failure) {
            Some(g) => format!("{why} ({g})"),
            None => why,
        };
        if self.restart {
            tracing::warn!(camera = %self.name, "the stream stopped: {why}; building it again in {:.1} s", self.backoff.as_secs_f64());
        } else {
            tracing::warn!(camera = %self.name, "the stream stopped: {why}");
        }
        if let Some(b) = self.built.take() {
            b.retire();
        }
        self.held = None;
        self.stopped = Some(why);
        self.restart_at = Some(Instant::now() + self.backoff);
    }

    /// Builds the pipeline again if the back-off has passed.
    fn try_restart(&mut self) {
        if !self.restart || self.restart_at.is_some_and(|t| Instant::now() < t) {
            return;
        }
        self.backoff = (self.backoff * 2).min(RESTART_MAX);
        self.restart_at = Some(Instant::now() + self.backoff);
        self.restarts += 1;
        let built = Built::start(&self.name, &self.desc);
        match built {
            Ok(b) => {
                tracing::warn!(camera = %self.name, restarts = self.restarts, "stream pipeline built again");
                self.built = Some(b);
                self.built_at = Some(Instant::now());
                self.stopped = None;
                // Its clock starts again: stamps go on from the last one.
                self.rebase = true;
                self.last_pts = None;
            }
            Err(e) => {
                tracing::warn!(camera = %self.name, "building the stream again: {e}");
            }
        }
    }

    /// Wall time since the last frame was delivered (or the pipeline was built).
    fn silent_for(&self) -> Duration {
        match (self.delivered_at, self.built_at) {
            (Some(a), Some(b)) => a.max(b).elapsed(),
            (Some(t), None) | (None, Some(t)) => t.elapsed(),
            (None, None) => Duration::ZERO,
        }
    }

    /// How long a running stream may stay silent before it is built again: 2 s, or 4
    /// frame periods of a slower camera.
    fn silence_limit(&self) -> Duration {
        STALL_RESTART.max(Duration::from_secs_f64(4.0 / self.fps))
    }

    /// The control's newest report: a change in force goes to the attribution.
    fn poll_control(&mut self) {
        let a = self.control.applied();
        if a.seq != self.applied_seq {
            self.applied_seq = a.seq;
            self.attribution.commanded(a.exposure_us);
        }
    }

    /// The stamp of a frame at pipeline time `raw_s`: continuous across restarts and
    /// always increasing.
    fn stamp(&mut self, raw_s: f64) -> f64 {
        let now = Instant::now();
        if self.rebase {
            self.rebase = false;
            if let (Some(last), Some(at)) = (self.last_stamp, self.delivered_at) {
                self.stamp_offset = last + now.duration_since(at).as_secs_f64() - raw_s;
            }
        }
        let mut t = raw_s + self.stamp_offset;
        if let (Some(last), Some(at)) = (self.last_stamp, self.delivered_at) {
            if t <= last {
                let next = last + 1.0 / self.fps;
                self.stamp_offset += next - t;
                t = next;
            }
            // After a wait of a grab tick or more the loop has ticked on its own clock
            // (the last stamp plus the time waited): a stream whose clock fell behind
            // meanwhile is moved up to it, so loop time never goes back.
            let waited = now.duration_since(at);
            if waited >= GRAB_TICK {
                let floor = last + waited.as_secs_f64();
                if t < floor {
                    self.stamp_offset += floor - t;
                    t = floor;
                }
            }
        }
        self.last_stamp = Some(t);
        self.delivered_at = Some(now);
        t
    }
}

impl Drop for StreamCamera {
    fn drop(&mut self) {
        // Connections first: an rtspsrc blocked on its server returns at once.
        if let Some(g) = &self.guard {
            g.close_all();
        }
        if let Some(b) = self.built.take() {
            let _ = b.pipeline.set_state(gst::State::Null);
        }
    }
}

/// Builds and starts `local`'s pipeline with the first of `choice`'s decoders that is
/// installed and starts, else with the software decoder (whose failure is the error).
fn start_decoding(
    url: &str,
    local: &StreamSource,
    choice: &DecoderChoice,
) -> Result<(Built, String, DecoderReport), StreamError> {
    let mut passed_over = Vec::new();
    for name in choice.preferred.iter().filter(|n| *n != SOFTWARE_H264) {
        let Some(factory) = gst::ElementFactory::find(name) else {
            passed_over.push(DecoderSkipped {
                element: name.clone(),
                reason: "not installed (no such GStreamer element on this host)".into(),
            });
            continue;
        };
        let desc = local.pipeline_with(name);
        match Built::start(url, &desc) {
            Ok(b) => {
                let report = DecoderReport {
                    element: name.clone(),
                    hardware: is_hardware(&factory),
                    passed_over,
                };
                return Ok((b, desc, report));
            }
            Err(e) => {
                tracing::info!(camera = %url, "decoder {name}: {e}; trying the next");
                passed_over.push(DecoderSkipped {
                    element: name.clone(),
                    reason: format!("does not start: {e}"),
                });
            }
        }
    }
    let desc = local.pipeline_with(SOFTWARE_H264);
    let b = Built::start(url, &desc)?;
    let report = DecoderReport {
        element: SOFTWARE_H264.into(),
        hardware: false,
        passed_over,
    };
    Ok((b, desc, report))
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
        // To the worker: never waits on the camera (the newest request wins).
        self.control.request(want);
        let a = self.control.applied();
        Ok(if a.exposure_us.is_finite() {
            a.exposure_us
        } else {
            want
        })
    }
    fn frames_passed_over(&self) -> u64 {
        self.passed_over
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        self.poll_control();
        if self.built.is_none() {
            self.try_restart();
        }
        let Some(built) = &self.built else {
            // Stopped: wait the tick out (the loop's clock runs on), never spin.
            std::thread::sleep(GRAB_TICK);
            let why = self.stopped.as_deref().unwrap_or("stopped");
            return Err(self.read_err(format!("{NO_FRAME_REASON}: the stream stopped: {why}")));
        };
        let Some(sample) = self.held.take().or_else(|| {
            built
                .sink
                .try_pull_sample(gst::ClockTime::from_nseconds(GRAB_TICK.as_nanos() as u64))
        }) else {
            if let Some(why) = bus_problem(&built.bus) {
                self.on_stopped(why);
            } else if let Some(why) = self.guard.as_ref().and_then(RtspGuard::failure) {
                self.on_stopped(why);
            } else if self.restart && self.silent_for() >= self.silence_limit() {
                // Running but silent (a decoder or jitter buffer stuck after bad
                // packets): built again like a stream that ended.
                let why = format!("no frame for {:.1} s", self.silent_for().as_secs_f64());
                self.on_stopped(why);
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
        if !(1..=MAX_SIDE_PX).contains(&w) || !(1..=MAX_SIDE_PX).contains(&h) {
            return Err(self.read_err(format!(
                "a {w}x{h} frame (sides 1..{MAX_SIDE_PX} pixels expected)"
            )));
        }
        let limited = limited_range(
            st.get::<&str>("format").unwrap_or("GRAY8"),
            st.get::<&str>("colorimetry").ok(),
        );
        if limited != self.lut_limited {
            self.lut = range_lut(limited);
            self.lut_limited = limited;
        }
        let (w, h) = (w as u32, h as u32);
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
        drop(map);
        // Frames the camera took in between, from the timestamps.
        let gap = match (self.last_pts, pts) {
            (Some(a), Some(b)) if b > a => {
                let dt = (b - a).nseconds() as f64 * 1e-9;
                ((dt * self.fps).round().min(1e9) as u64).max(1)
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
        // A frame came: the next stop waits the shortest back-off again.
        self.backoff = RESTART_FIRST;
        frame.meta.seq = self.seq;
        let raw = pts.map_or(self.seq as f64 / self.fps, |p| p.nseconds() as f64 * 1e-9);
        frame.meta.stamp_s = self.stamp(raw);
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

/// The longest side of a frame accepted from a stream, pixels.
pub const MAX_SIDE_PX: i32 = 8192;

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
    fn decoder_preferences_parse_and_reports_name_the_fallback() {
        assert_eq!(DecoderChoice::auto().preferred, HARDWARE_H264.to_vec());
        assert_eq!(
            DecoderChoice::parse(" v4l2h264dec , vah264dec,").unwrap(),
            DecoderChoice::prefer(["v4l2h264dec", "vah264dec"])
        );
        assert!(DecoderChoice::parse("software")
            .unwrap()
            .preferred
            .is_empty());
        assert!(DecoderChoice::parse("avdec_h264")
            .unwrap()
            .preferred
            .is_empty());
        let e = DecoderChoice::parse("v4l2h264dec ! fakesink").unwrap_err();
        assert!(
            e.contains(DECODER_ENV) && e.contains("v4l2h264dec ! fakesink"),
            "{e}"
        );
        assert_eq!(
            decoder_desc(SOFTWARE_H264),
            "avdec_h264 name=markhold_decoder max-threads=1"
        );
        let udp = StreamSource::Udp {
            host: None,
            port: 5600,
        };
        assert!(udp
            .pipeline_with("v4l2h264dec")
            .contains("h264parse ! v4l2h264dec name=markhold_decoder ! appsink"));
        let r = DecoderReport {
            element: SOFTWARE_H264.into(),
            hardware: false,
            passed_over: vec![DecoderSkipped {
                element: "v4l2h264dec".into(),
                reason: "not installed".into(),
            }],
        };
        assert_eq!(
            r.to_string(),
            "avdec_h264 (software); before it v4l2h264dec: not installed"
        );
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
