//! Recording a run to MCAP (`--record FILE.mcap`), written by the foxglove crate.
//!
//! The control thread only copies the frame into a pooled buffer and hands a fixed-size
//! item to a bounded channel; a writer thread encodes the image (PNG, lossless so replay
//! sees the same pixels, or JPEG, a quarter of the size: `[record] image_format`) and
//! writes every channel. When the pool or the channel is full
//! the image (or the whole item) is dropped and counted: the loop never waits on the disk.
//! A write error is reported once and the loop goes on.
//!
//! Channels (Foxglove well-known schemas where one fits, JSON otherwise):
//! - [`TOPIC_IMAGE`] `foxglove.CompressedImage` (png or jpeg), one per frame unless dropped;
//! - [`TOPIC_ANNOTATIONS`] `foxglove.ImageAnnotations`: marker corners and the metered
//!   RoI drawn over the image, one per frame;
//! - [`TOPIC_FRAME`] JSON: frame metadata, the vehicle heartbeat the supervisor saw and
//!   the shutdown flag, with exact f64 bit patterns for replay;
//! - [`TOPIC_EXPOSURE`] JSON: exposure used and commanded, metric, metered RoI;
//! - [`TOPIC_DETECTION`] JSON: detected, corners, pose, 6x6 covariance, reprojection RMS;
//! - [`TOPIC_POSE`] `foxglove.PoseInFrame` (marker in the camera frame), when detected;
//! - [`TOPIC_COMMAND`] JSON: directive and effort (with bits);
//! - [`TOPIC_VEHICLE`] JSON: the link's vehicle state (mode, armed, telemetry, counters);
//! - [`TOPIC_FAILSAFE`] `foxglove.Log`: supervisor transitions;
//! - [`TOPIC_MAVLINK_RAW`] (when a link is tapped, [`Recorder::mavlink_tap`]): every
//!   MAVLink frame on the wire, encoding `markhold.mavlink-raw`: one byte direction
//!   (0 = from the vehicle, 1 = to it) then the frame as sent (magic to signature); log
//!   time = the loop time of the link's tick.
//!
//! Metadata record [`METADATA_NAME`] holds the effective site, its calibration and the
//! run options, so `replay` needs nothing but the file.

use crate::CoreError;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use foxglove::schemas::points_annotation::Type as PointsType;
use foxglove::schemas::{Color, ImageAnnotations, Point2, PointsAnnotation};
use foxglove::schemas::{CompressedImage, Log, Pose, PoseInFrame, Quaternion, Timestamp, Vector3};
use foxglove::{ChannelBuilder, Context, PartialMetadata, RawChannel, Schema};
use markhold_autopilot::{Directive, FailsafeEvent, VehicleState};
use markhold_exposure::{Frame, FrameMeta};
use serde::{Deserialize, Serialize};

use crate::params::LoadedSite;
use crate::pipeline::{FrameRecord, FrameView, Observer};

pub mod images;
pub mod live;
pub mod replay;
pub mod rotation;

pub use rotation::{RecordControl, RecordingState};

pub const TOPIC_IMAGE: &str = "/camera/image";
pub const TOPIC_ANNOTATIONS: &str = "/camera/annotations";
pub const TOPIC_FRAME: &str = "/markhold/frame";
pub const TOPIC_EXPOSURE: &str = "/markhold/exposure";
pub const TOPIC_DETECTION: &str = "/markhold/detection";
pub const TOPIC_POSE: &str = "/markhold/marker_pose";
pub const TOPIC_COMMAND: &str = "/markhold/command";
pub const TOPIC_VEHICLE: &str = "/markhold/vehicle";
pub const TOPIC_FAILSAFE: &str = "/markhold/failsafe";
/// Raw MAVLink traffic (only when a link is tapped: not in [`TOPICS`]).
pub const TOPIC_MAVLINK_RAW: &str = "/mavlink/raw";
/// Message encoding of [`TOPIC_MAVLINK_RAW`].
pub const MAVLINK_RAW_ENCODING: &str = "markhold.mavlink-raw";
/// Raw frames that may wait for the writer thread; beyond, they are dropped and counted
/// by the link (`VehicleLink::raw_tap_dropped`).
pub const MAVLINK_TAP_QUEUE: usize = 8192;
/// Every topic a recording has channels for.
pub const TOPICS: [&str; 9] = [
    TOPIC_IMAGE,
    TOPIC_ANNOTATIONS,
    TOPIC_FRAME,
    TOPIC_EXPOSURE,
    TOPIC_DETECTION,
    TOPIC_POSE,
    TOPIC_COMMAND,
    TOPIC_VEHICLE,
    TOPIC_FAILSAFE,
];
/// Name of the MCAP metadata record describing the run.
pub const METADATA_NAME: &str = "markhold.run";
/// Failsafe events kept per frame (the supervisor makes at most a few per frame).
const EVENTS_PER_FRAME: usize = 4;

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("record file {path}: {source}")]
    Create {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("starting the MCAP writer: {source}")]
    Writer { source: foxglove::FoxgloveError },
    #[error("recording options: {key} = {value}: {expected}")]
    Options {
        key: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error("serializing the run description: {source}")]
    Describe { source: toml::ser::Error },
    #[error("the recorder's writer thread failed")]
    WriterThread,
    #[error("starting the live view on {ip}:{port}: {source}")]
    Live {
        ip: std::net::IpAddr,
        port: u16,
        source: std::io::Error,
    },
    #[error("writing the recording: {reason}")]
    Write { reason: String },
}

/// How a run was started: stored in the recording so `replay` rebuilds the same loop.
#[derive(Debug, Clone, PartialEq)]
pub struct RunInfo {
    /// `hil` or `run`.
    pub command: String,
    /// The site as loaded (defaults filled in), TOML.
    pub site_toml: String,
    /// Its camera calibration, TOML.
    pub calibration_toml: String,
    /// The site file as written by the user (for people; replay uses `site_toml`).
    pub site_source: String,
    /// Exposure method the loop ran.
    pub exposure_method: String,
    /// Exposure the controller started from, microseconds.
    pub initial_exposure_us: f64,
    /// The command line's options, for people.
    pub options: String,
}

impl RunInfo {
    pub fn new(
        command: &str,
        site: &LoadedSite,
        exposure_method: markhold_exposure::ExposureMethod,
        initial_exposure_us: f64,
        options: String,
    ) -> Result<Self, RecordError> {
        Ok(Self {
            command: command.to_string(),
            site_toml: toml::to_string(&site.site)
                .map_err(|source| RecordError::Describe { source })?,
            calibration_toml: toml::to_string(&site.calibration)
                .map_err(|source| RecordError::Describe { source })?,
            site_source: std::fs::read_to_string(&site.path).unwrap_or_default(),
            exposure_method: exposure_method.to_string(),
            initial_exposure_us,
            options,
        })
    }

    pub fn to_metadata(&self) -> BTreeMap<String, String> {
        let mut m = BTreeMap::new();
        m.insert("format".into(), "markhold-recording-1".into());
        m.insert("command".into(), self.command.clone());
        m.insert("site_toml".into(), self.site_toml.clone());
        m.insert("calibration_toml".into(), self.calibration_toml.clone());
        m.insert("site_source".into(), self.site_source.clone());
        m.insert("exposure_method".into(), self.exposure_method.clone());
        // Bits, so replay starts the controller from exactly this value.
        m.insert(
            "initial_exposure_bits".into(),
            format!("{:016x}", self.initial_exposure_us.to_bits()),
        );
        m.insert(
            "initial_exposure_us".into(),
            self.initial_exposure_us.to_string(),
        );
        m.insert("options".into(), self.options.clone());
        m
    }

    /// Read back what [`RunInfo::to_metadata`] wrote; `None` names the missing key.
    pub fn from_metadata(m: &BTreeMap<String, String>) -> Result<Self, String> {
        // The site and calibration texts are parsed as site files are: of at most the
        // size a site file may have.
        let limit = markhold_config::MAX_CONFIG_FILE_BYTES;
        for k in ["site_toml", "calibration_toml", "site_source"] {
            if let Some(v) = m.get(k).filter(|v| v.len() as u64 > limit) {
                return Err(format!(
                    "{k} ({} bytes: a site file is at most {limit})",
                    v.len()
                ));
            }
        }
        let get = |k: &str| m.get(k).cloned().ok_or_else(|| k.to_string());
        let bits = get("initial_exposure_bits")?;
        let bits = u64::from_str_radix(&bits, 16)
            .map_err(|_| format!("initial_exposure_bits = {bits}"))?;
        Ok(Self {
            command: get("command")?,
            site_toml: get("site_toml")?,
            calibration_toml: get("calibration_toml")?,
            site_source: m.get("site_source").cloned().unwrap_or_default(),
            exposure_method: get("exposure_method")?,
            initial_exposure_us: f64::from_bits(bits),
            options: m.get("options").cloned().unwrap_or_default(),
        })
    }
}

/// How a recording stores the camera's frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// Lossless: `replay` sees the same pixels and gives bit-identical commands.
    Png,
    /// About a quarter of PNG's size; `replay` says it is not bit-exact.
    Jpeg,
}

impl ImageFormat {
    /// The `format` of a `foxglove.CompressedImage`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Png => "png",
            Self::Jpeg => "jpeg",
        }
    }
}

/// `[record]` of a site file: how `--record` stores frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordSection {
    /// `png` or `jpeg`; left out: `png` for `hil` (replay-exact), `jpeg` for `run`.
    #[serde(default)]
    pub image_format: Option<ImageFormat>,
    /// JPEG quality 1..100.
    #[serde(default = "default_jpeg_quality")]
    pub jpeg_quality: u8,
    /// `[record.rotation]`: segments, quota and free-space floor.
    #[serde(default)]
    pub rotation: rotation::RotationSection,
}

fn default_jpeg_quality() -> u8 {
    90
}

impl Default for RecordSection {
    fn default() -> Self {
        Self {
            image_format: None,
            jpeg_quality: default_jpeg_quality(),
            rotation: rotation::RotationSection::default(),
        }
    }
}

impl RecordSection {
    pub fn validate(&self) -> Result<(), markhold_config::ConfigError> {
        markhold_config::Checks::new("record")
            .range(
                "jpeg_quality",
                self.jpeg_quality,
                1..=100,
                "a JPEG quality, 1..100",
            )
            .done()?;
        self.rotation.validate()
    }

    /// The recorder's settings for a command whose default format is `default`.
    pub fn config(&self, default: ImageFormat) -> RecordConfig {
        RecordConfig {
            image_format: self.image_format.unwrap_or(default),
            jpeg_quality: i32::from(self.jpeg_quality),
            rotation: self.rotation.config(),
            ..RecordConfig::default()
        }
    }
}

/// Recorder sizing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordConfig {
    /// Frames whose image may wait for the writer; beyond, images are dropped.
    pub image_queue_frames: usize,
    /// Items (per-frame records) that may wait; beyond, whole frames are dropped.
    pub queue_frames: usize,
    /// PNG compression level 0..9 (lossless at every level; higher is smaller, slower).
    pub png_level: i32,
    /// Wait for the writer instead of dropping: for simulated time (`hil`), where the
    /// loop's clock waits too and a lossless recording keeps replay exact.
    pub wait_when_full: bool,
    /// How frames are stored.
    pub image_format: ImageFormat,
    /// JPEG quality 1..100 (with `image_format` jpeg).
    pub jpeg_quality: i32,
    /// Segments, quota and free-space floor of a file recording.
    #[serde(default)]
    pub rotation: rotation::RotationConfig,
}

impl Default for RecordConfig {
    fn default() -> Self {
        Self {
            image_queue_frames: 8,
            queue_frames: 64,
            png_level: 1,
            wait_when_full: false,
            image_format: ImageFormat::Png,
            jpeg_quality: 90,
            rotation: rotation::RotationConfig::default(),
        }
    }
}

impl RecordConfig {
    pub fn validate(&self) -> Result<(), RecordError> {
        if self.image_queue_frames == 0 || self.image_queue_frames > self.queue_frames {
            return Err(RecordError::Options {
                key: "image_queue_frames",
                value: self.image_queue_frames.to_string(),
                expected: "between 1 and queue_frames",
            });
        }
        if !(0..=9).contains(&self.png_level) {
            return Err(RecordError::Options {
                key: "png_level",
                value: self.png_level.to_string(),
                expected: "0..9",
            });
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return Err(RecordError::Options {
                key: "jpeg_quality",
                value: self.jpeg_quality.to_string(),
                expected: "1..100",
            });
        }
        Ok(())
    }
}

/// What a recording holds and what it lost.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct RecordStats {
    /// Frames handed to the recorder.
    pub frames: u64,
    /// Frames recorded without their image (pool or queue full).
    pub images_dropped: u64,
    /// Frames not recorded at all (queue full).
    pub frames_dropped: u64,
    /// The first write error, if any (later ones are not reported again).
    pub write_error: Option<String>,
    /// Segment files begun (`[record.rotation]`; 1 for a recording never rotated).
    pub segments: u64,
    /// Older recordings deleted to keep the quota and the free-space floor.
    pub deleted: u64,
    /// Why the recording stopped before the run did (the free-space floor), if it did.
    pub stopped: Option<String>,
}

#[derive(Default)]
struct Shared {
    frames: AtomicU64,
    images_dropped: AtomicU64,
    frames_dropped: AtomicU64,
    write_error: Mutex<Option<String>>,
    /// Start / stop, the open segment and its bytes, what rotation deleted.
    control: RecordControl,
}

impl Shared {
    fn report_error(&self, e: &dyn std::fmt::Display) {
        if let Ok(mut slot) = self.write_error.lock() {
            if slot.is_none() {
                tracing::error!("recording: write failed, the loop goes on without it: {e}");
                *slot = Some(e.to_string());
            }
        }
    }
    fn stats(&self) -> RecordStats {
        let c = self.control.state();
        RecordStats {
            frames: self.frames.load(Ordering::Relaxed),
            images_dropped: self.images_dropped.load(Ordering::Relaxed),
            frames_dropped: self.frames_dropped.load(Ordering::Relaxed),
            write_error: self.write_error.lock().ok().and_then(|s| s.clone()),
            segments: c.segments,
            deleted: c.deleted,
            stopped: c.stopped,
        }
    }
    fn failed(&self) -> bool {
        self.write_error.lock().map(|s| s.is_some()).unwrap_or(true)
    }
}

/// A writer that remembers its first error (the MCAP sink only logs them).
struct Tracked<W> {
    inner: W,
    shared: Arc<Shared>,
}

impl<W: Write> Write for Tracked<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner
            .write(buf)
            .inspect(|n| {
                self.shared.control.add_bytes(*n as u64);
            })
            .inspect_err(|e| self.shared.report_error(e))
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner
            .flush()
            .inspect_err(|e| self.shared.report_error(e))
    }
}

impl<W: Seek> Seek for Tracked<W> {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.inner
            .seek(pos)
            .inspect_err(|e| self.shared.report_error(e))
    }
}

/// The writer type of a recorder without a file (never written to).
struct NoFile;

impl Write for NoFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for NoFile {
    fn seek(&mut self, _pos: SeekFrom) -> std::io::Result<u64> {
        Ok(0)
    }
}

/// What the link knew when a frame was decided.
#[derive(Debug, Clone)]
pub struct LinkSnapshot {
    /// Loop time of the vehicle heartbeat the supervisor saw.
    pub heartbeat_s: Option<f64>,
    /// The vehicle's state, when the link is a real one.
    pub vehicle: Option<VehicleState>,
}

/// One frame's worth of recording: fixed size, no heap except the pooled image.
struct Item {
    rec: FrameRecord,
    meta: FrameMeta,
    width: u32,
    height: u32,
    image: Option<Vec<u8>>,
    heartbeat_s: Option<f64>,
    shutdown: bool,
    vehicle: Option<VehicleState>,
    events: [Option<FailsafeEvent>; EVENTS_PER_FRAME],
}

/// Records a run to MCAP from the control thread without blocking it.
pub struct Recorder {
    tx: Option<SyncSender<Item>>,
    free: Receiver<Vec<u8>>,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<Result<(), RecordError>>>,
    path: Option<PathBuf>,
    spare: Option<Vec<u8>>,
    wait_when_full: bool,
    live: Option<live::LiveServer>,
    /// The recorder's foxglove context: a live view can attach to the same channels.
    context: Arc<Context>,
    /// Sender side of the raw MAVLink tap (handed to the link).
    tap: SyncSender<markhold_autopilot::RawFrame>,
}

impl Recorder {
    /// Create `path` (it must not exist: a recording is never overwritten) and start
    /// the writer thread.
    pub fn create(path: &Path, info: &RunInfo, cfg: RecordConfig) -> Result<Self, RecordError> {
        cfg.validate()?;
        let file = File::create_new(path).map_err(|source| RecordError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        // The segments after the first (`[record.rotation]`).
        let next = rotation::file_opener(path, info, &cfg.rotation);
        match Self::to_writer_with(
            BufWriter::with_capacity(1 << 20, file),
            info,
            cfg,
            Some(next),
        ) {
            Ok(mut r) => {
                r.path = Some(path.to_path_buf());
                Ok(r)
            }
            Err(e) => {
                // Nothing half-written left behind.
                let _ = std::fs::remove_file(path);
                Err(e)
            }
        }
    }

    /// Record into any seekable writer (tests use failing writers).
    pub fn to_writer<W: Write + Seek + Send + 'static>(
        writer: W,
        info: &RunInfo,
        cfg: RecordConfig,
    ) -> Result<Self, RecordError> {
        Self::to_writer_with(writer, info, cfg, None)
    }

    /// Record into `writer`, then into the segments `next` opens (a rotating file
    /// recording) or nothing more (`None`).
    fn to_writer_with<W: Write + Seek + Send + 'static>(
        writer: W,
        info: &RunInfo,
        cfg: RecordConfig,
        next: Option<rotation::Opener<W>>,
    ) -> Result<Self, RecordError> {
        cfg.validate()?;
        let shared = Arc::new(Shared::default());
        let context = Context::new();
        let handle = rotation::open_segment(
            &context,
            writer,
            &shared,
            &info.to_metadata(),
            &cfg.rotation,
        )?;
        Self::spawn(Some((handle, next)), context, shared, cfg)
    }

    /// No file: the channels only feed a live view ([`Recorder::serve_live`]).
    pub fn live_only(cfg: RecordConfig) -> Result<Self, RecordError> {
        cfg.validate()?;
        Self::spawn::<NoFile>(None, Context::new(), Arc::new(Shared::default()), cfg)
    }

    /// Starts and stops the file recording while the run goes on, and tells where it is.
    pub fn control(&self) -> RecordControl {
        self.shared.control.clone()
    }

    /// Serve the channels to Foxglove over WebSocket on 127.0.0.1 (`port` 0: any free
    /// port) to clients the site's `[live]` section lets in ([`live`]); returns the port.
    /// The server stops with the recorder.
    pub fn serve_live(
        &mut self,
        port: u16,
        access: &live::LiveSection,
    ) -> Result<u16, RecordError> {
        self.serve_live_on(std::net::Ipv4Addr::LOCALHOST.into(), port, access)
    }

    /// [`Recorder::serve_live`] on `ip` (`0.0.0.0`: every address, for the topside).
    pub fn serve_live_on(
        &mut self,
        ip: std::net::IpAddr,
        port: u16,
        access: &live::LiveSection,
    ) -> Result<u16, RecordError> {
        let server = live::LiveServer::start_on(&self.context, ip, port, access)
            .map_err(|source| RecordError::Live { ip, port, source })?;
        let port = server.port();
        self.live = Some(server);
        Ok(port)
    }

    fn spawn<W: Write + Seek + Send + 'static>(
        output: Option<rotation::Output<W>>,
        context: Arc<Context>,
        shared: Arc<Shared>,
        cfg: RecordConfig,
    ) -> Result<Self, RecordError> {
        let channels = Channels::new(&context)?;
        let (tx, rx) = sync_channel::<Item>(cfg.queue_frames);
        let (tap, tap_rx) = sync_channel::<markhold_autopilot::RawFrame>(MAVLINK_TAP_QUEUE);
        let (free_tx, free) = sync_channel::<Vec<u8>>(cfg.image_queue_frames);
        for _ in 0..cfg.image_queue_frames {
            let _ = free_tx.try_send(Vec::new());
        }
        let shared_w = shared.clone();
        let (ext, params) = match cfg.image_format {
            ImageFormat::Png => (
                ".png",
                [opencv::imgcodecs::IMWRITE_PNG_COMPRESSION, cfg.png_level],
            ),
            ImageFormat::Jpeg => (
                ".jpg",
                [opencv::imgcodecs::IMWRITE_JPEG_QUALITY, cfg.jpeg_quality],
            ),
        };
        let format = cfg.image_format;
        let rotation_cfg = cfg.rotation;
        let context_w = context.clone();
        let thread = std::thread::Builder::new()
            .name("markhold-recorder".into())
            .spawn(move || {
                let mut w = WriterThread {
                    channels,
                    shared: shared_w,
                    png: opencv::core::Vector::new(),
                    png_params: opencv::core::Vector::from_slice(&params),
                    ext,
                    format,
                    json: Vec::with_capacity(4096),
                    raw: Vec::with_capacity(1 + 280),
                };
                let mut out = output.map(|(handle, next)| {
                    rotation::SegmentWriter::new(handle, next, context_w, &w.shared, rotation_cfg)
                });
                loop {
                    let mut item = match rx.recv_timeout(rotation::IDLE_POLL) {
                        Ok(item) => item,
                        Err(RecvTimeoutError::Timeout) => {
                            // A stop asked for while no frame comes still closes the file.
                            out.iter_mut().for_each(|o| o.idle());
                            continue;
                        }
                        Err(RecvTimeoutError::Disconnected) => break,
                    };
                    let t = stamp_ns(item.meta.stamp_s);
                    out.iter_mut().for_each(|o| o.before_frame(t));
                    // The link's raw frames so far (at most a frame late in the file).
                    w.raw_frames(&tap_rx);
                    if !w.shared.failed() {
                        w.write(&item);
                    }
                    out.iter_mut().for_each(|o| o.after_frame(t));
                    if let Some(buf) = item.image.take() {
                        let _ = free_tx.try_send(buf);
                    }
                }
                w.raw_frames(&tap_rx);
                // Finalize: summary section and footer.
                out.map_or(Ok(()), rotation::SegmentWriter::finish)
            })
            .map_err(|source| RecordError::Create {
                path: PathBuf::from("<recorder thread>"),
                source,
            })?;
        Ok(Self {
            tx: Some(tx),
            free,
            shared,
            thread: Some(thread),
            path: None,
            spare: None,
            wait_when_full: cfg.wait_when_full,
            context,
            live: None,
            tap,
        })
    }

    /// A sender for `VehicleLink::set_raw_tap`: the link's raw frames go to
    /// [`TOPIC_MAVLINK_RAW`], written by the writer thread (the control thread only copies
    /// a fixed-size frame into a bounded channel).
    pub fn mavlink_tap(&self) -> SyncSender<markhold_autopilot::RawFrame> {
        self.tap.clone()
    }

    /// The foxglove context the recording's channels live in.
    pub fn context(&self) -> &Arc<Context> {
        &self.context
    }

    /// Record one frame. Never blocks and never fails: losses are counted.
    pub fn record(
        &mut self,
        rec: &FrameRecord,
        frame: &Frame,
        link: &LinkSnapshot,
        shutdown: bool,
        events: &[FailsafeEvent],
    ) {
        let Some(tx) = &self.tx else { return };
        if self.path.is_some() && self.live.is_none() && !self.shared.control.wanted() {
            // The file recording is stopped and nobody watches live.
            return;
        }
        self.shared.frames.fetch_add(1, Ordering::Relaxed);
        let wait = self.wait_when_full;
        let image = match self.spare.take().ok_or(()).or_else(|_| {
            if wait {
                self.free.recv().map_err(|_| ())
            } else {
                self.free.try_recv().map_err(|_| ())
            }
        }) {
            Ok(mut buf) => {
                buf.clear();
                buf.extend_from_slice(&frame.data);
                Some(buf)
            }
            Err(_) => {
                self.shared.images_dropped.fetch_add(1, Ordering::Relaxed);
                None
            }
        };
        let mut ev = [None; EVENTS_PER_FRAME];
        for (slot, e) in ev.iter_mut().zip(events) {
            *slot = Some(*e);
        }
        let item = Item {
            rec: *rec,
            meta: frame.meta,
            width: frame.width,
            height: frame.height,
            image,
            heartbeat_s: link.heartbeat_s,
            shutdown,
            vehicle: link.vehicle.clone(),
            events: ev,
        };
        if wait {
            if tx.send(item).is_err() {
                self.shared.frames_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        match tx.try_send(item) {
            Ok(()) => {}
            Err(TrySendError::Full(item)) | Err(TrySendError::Disconnected(item)) => {
                self.shared.frames_dropped.fetch_add(1, Ordering::Relaxed);
                if let Some(buf) = item.image {
                    // Back to the pool; the image of a dropped frame was never written.
                    self.shared.images_dropped.fetch_add(1, Ordering::Relaxed);
                    self.recycle(buf);
                }
            }
        }
    }

    fn recycle(&mut self, buf: Vec<u8>) {
        // The pool's sender belongs to the writer thread: a buffer that never left
        // waits here for the next frame.
        self.spare = Some(buf);
    }

    /// Counters so far.
    pub fn stats(&self) -> RecordStats {
        self.shared.stats()
    }

    /// A handle on the counters that outlives the recorder.
    pub fn stats_handle(&self) -> RecordStatsHandle {
        RecordStatsHandle(self.shared.clone())
    }

    /// Write what is queued, finalize the file and return what was recorded.
    pub fn finish(mut self) -> Result<RecordStats, RecordError> {
        self.tx = None;
        drop(self.live.take());
        let joined = match self.thread.take() {
            Some(t) => t.join().map_err(|_| RecordError::WriterThread)?,
            None => Ok(()),
        };
        if let Err(e) = joined {
            self.shared.report_error(&e);
        }
        Ok(self.stats())
    }

    /// Stop and delete the file (start-up failed after the recorder was created).
    pub fn abort(mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        if let Some(p) = self.path.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        // Finalize on every exit path (an error or a panic unwinding the loop).
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// An f64 that may be NaN (JSON writes it as `null`): `null` reads back as NaN.
fn f64_or_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

fn effort_or_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<[f64; 6], D::Error> {
    Ok(<[Option<f64>; 6]>::deserialize(d)?.map(|v| v.unwrap_or(f64::NAN)))
}

/// `/markhold/frame`: what replay needs to feed a frame through the loop again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameMsg {
    pub seq: u64,
    pub stamp_s: f64,
    /// NaN (`null`) when not known: a stream camera's frame in its own auto exposure or
    /// while a command takes effect. Replay uses the exact bits in `bits`.
    #[serde(deserialize_with = "f64_or_nan")]
    pub exposure_us: f64,
    #[serde(deserialize_with = "f64_or_nan")]
    pub gain_db: f64,
    pub width: u32,
    pub height: u32,
    /// False when the image was dropped (recorder queue full).
    pub image: bool,
    /// Vehicle heartbeat the supervisor saw on this frame (loop time).
    pub heartbeat_s: Option<f64>,
    pub shutdown: bool,
    /// Exact f64 bit patterns of stamp, exposure, gain and heartbeat (JSON numbers are
    /// for people and plots; replay must not depend on decimal round trips).
    pub bits: FrameBits,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FrameBits {
    pub stamp: u64,
    pub exposure: u64,
    pub gain: u64,
    pub heartbeat: Option<u64>,
}

/// `/markhold/command`: the frame's directive and the keeper's effort.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandMsg {
    pub seq: u64,
    pub stamp_s: f64,
    /// `command`, `neutral`, `silent`, `shutdown` or `shutdown_disarm`.
    pub directive: String,
    /// surge, sway, heave, roll, pitch, yaw (docs/frames.md); `null` reads back as NaN.
    #[serde(deserialize_with = "effort_or_nan")]
    pub effort: [f64; 6],
    pub effort_bits: [u64; 6],
}

impl CommandMsg {
    pub fn from_record(rec: &FrameRecord) -> Self {
        let e = &rec.effort;
        let effort = [e.surge, e.sway, e.heave, e.roll, e.pitch, e.yaw];
        Self {
            seq: rec.seq,
            stamp_s: rec.stamp_s,
            directive: directive_name(rec.directive).to_string(),
            effort,
            effort_bits: effort.map(f64::to_bits),
        }
    }
}

pub fn directive_name(d: Directive) -> &'static str {
    match d {
        Directive::Command => "command",
        Directive::Neutral => "neutral",
        Directive::Silent => "silent",
        Directive::Shutdown { disarm: false } => "shutdown",
        Directive::Shutdown { disarm: true } => "shutdown_disarm",
    }
}

#[derive(Serialize)]
struct ExposureMsg {
    seq: u64,
    stamp_s: f64,
    exposure_used_us: f64,
    exposure_next_us: f64,
    gain_db: f64,
    metric: Option<f64>,
    used_frame: bool,
    roi: Option<markhold_exposure::Roi>,
}

#[derive(Serialize)]
struct DetectionMsg {
    seq: u64,
    stamp_s: f64,
    detected: bool,
    corners_px: Option<[[f32; 2]; 4]>,
    /// Marker position in the camera frame, metres.
    translation_m: Option<[f64; 3]>,
    /// Marker orientation in the camera frame, quaternion x, y, z, w.
    rotation_xyzw: Option<[f64; 4]>,
    /// 6x6 covariance of the pose, row-major (docs/frames.md order).
    covariance: Option<Vec<f64>>,
    reproj_rms_px: Option<f64>,
}

#[derive(Serialize)]
struct VehicleMsg<'a> {
    seq: u64,
    stamp_s: f64,
    state: &'a VehicleState,
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// Loop seconds to MCAP nanoseconds (negative or non-finite stamps to 0).
pub fn stamp_ns(stamp_s: f64) -> u64 {
    if stamp_s.is_finite() && stamp_s > 0.0 {
        (stamp_s * 1e9).round().min(u64::MAX as f64) as u64
    } else {
        0
    }
}

fn timestamp(stamp_s: f64) -> Timestamp {
    let ns = stamp_ns(stamp_s);
    let sec = u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX);
    Timestamp::new_checked(sec, (ns % 1_000_000_000) as u32).unwrap_or(Timestamp::MAX)
}

struct Channels {
    image: foxglove::Channel<CompressedImage>,
    annotations: foxglove::Channel<ImageAnnotations>,
    pose: foxglove::Channel<PoseInFrame>,
    failsafe: foxglove::Channel<Log>,
    frame: Arc<RawChannel>,
    exposure: Arc<RawChannel>,
    detection: Arc<RawChannel>,
    command: Arc<RawChannel>,
    vehicle: Arc<RawChannel>,
    mavlink_raw: Arc<RawChannel>,
}

fn json_channel(
    ctx: &Arc<Context>,
    topic: &str,
    name: &str,
) -> Result<Arc<RawChannel>, RecordError> {
    ChannelBuilder::new(topic)
        .context(ctx)
        .message_encoding("json")
        .schema(Schema::new(
            name,
            "jsonschema",
            br#"{"type":"object"}"#.as_slice(),
        ))
        .build_raw()
        .map_err(|source| RecordError::Writer { source })
}

impl Channels {
    fn new(ctx: &Arc<Context>) -> Result<Self, RecordError> {
        Ok(Self {
            image: ChannelBuilder::new(TOPIC_IMAGE).context(ctx).build(),
            annotations: ChannelBuilder::new(TOPIC_ANNOTATIONS).context(ctx).build(),
            pose: ChannelBuilder::new(TOPIC_POSE).context(ctx).build(),
            failsafe: ChannelBuilder::new(TOPIC_FAILSAFE).context(ctx).build(),
            frame: json_channel(ctx, TOPIC_FRAME, "markhold.Frame")?,
            exposure: json_channel(ctx, TOPIC_EXPOSURE, "markhold.Exposure")?,
            detection: json_channel(ctx, TOPIC_DETECTION, "markhold.Detection")?,
            command: json_channel(ctx, TOPIC_COMMAND, "markhold.Command")?,
            vehicle: json_channel(ctx, TOPIC_VEHICLE, "markhold.Vehicle")?,
            mavlink_raw: ChannelBuilder::new(TOPIC_MAVLINK_RAW)
                .context(ctx)
                .message_encoding(MAVLINK_RAW_ENCODING)
                .build_raw()
                .map_err(|source| RecordError::Writer { source })?,
        })
    }
}

struct WriterThread {
    channels: Channels,
    shared: Arc<Shared>,
    /// The encoded image and the encoder's parameters.
    png: opencv::core::Vector<u8>,
    png_params: opencv::core::Vector<i32>,
    /// `.png` or `.jpg`, for OpenCV's encoder.
    ext: &'static str,
    format: ImageFormat,
    json: Vec<u8>,
    raw: Vec<u8>,
}

impl WriterThread {
    /// Write every raw MAVLink frame waiting in the tap.
    fn raw_frames(&mut self, tap: &Receiver<markhold_autopilot::RawFrame>) {
        while let Ok(f) = tap.try_recv() {
            if self.shared.failed() {
                continue;
            }
            self.raw.clear();
            self.raw.push(u8::from(f.outgoing));
            self.raw.extend_from_slice(f.bytes());
            self.channels.mavlink_raw.log_with_meta(
                &self.raw,
                PartialMetadata {
                    log_time: Some(stamp_ns(f.stamp_s)),
                },
            );
        }
    }

    fn json<T: Serialize>(&mut self, ch: &RawChannel, log_time: u64, msg: &T) {
        self.json.clear();
        match serde_json::to_writer(&mut self.json, msg) {
            Ok(()) => ch.log_with_meta(
                &self.json,
                PartialMetadata {
                    log_time: Some(log_time),
                },
            ),
            Err(e) => self.shared.report_error(&e),
        }
    }

    fn encode_png(&mut self, width: u32, height: u32, data: &[u8]) -> Result<(), opencv::Error> {
        use opencv::prelude::*;
        let n = width as usize * height as usize;
        let pixels = data.get(..n).ok_or_else(|| {
            opencv::Error::new(
                opencv::core::StsBadArg,
                "frame buffer shorter than its size",
            )
        })?;
        let img =
            opencv::core::Mat::new_rows_cols_with_data::<u8>(height as i32, width as i32, pixels)?;
        self.png.clear();
        opencv::imgcodecs::imencode(self.ext, &img, &mut self.png, &self.png_params)?;
        let _ = img.typ();
        Ok(())
    }

    /// Corners (green) and the metered RoI (yellow) for Foxglove's Image panel.
    fn annotate(&mut self, it: &Item) {
        let r = &it.rec;
        let ts = timestamp(it.meta.stamp_s);
        let outline = |points: Vec<Point2>, color: Color| PointsAnnotation {
            timestamp: Some(ts),
            r#type: PointsType::LineLoop as i32,
            points,
            outline_color: Some(color),
            outline_colors: Vec::new(),
            fill_color: None,
            thickness: 2.0,
            metadata: Vec::new(),
        };
        let mut points = Vec::with_capacity(2);
        if let Some(c) = &r.corners {
            let p = c
                .iter()
                .map(|[x, y]| Point2 {
                    x: *x as f64,
                    y: *y as f64,
                })
                .collect();
            points.push(outline(
                p,
                Color {
                    r: 0.1,
                    g: 0.9,
                    b: 0.2,
                    a: 1.0,
                },
            ));
        }
        if let Some(roi) = r.exposure.roi {
            let (x0, y0) = (roi.x as f64, roi.y as f64);
            let (x1, y1) = (x0 + roi.width as f64, y0 + roi.height as f64);
            let p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
                .into_iter()
                .map(|(x, y)| Point2 { x, y })
                .collect();
            points.push(outline(
                p,
                Color {
                    r: 1.0,
                    g: 0.85,
                    b: 0.0,
                    a: 1.0,
                },
            ));
        }
        let msg = ImageAnnotations {
            timestamp: Some(ts),
            circles: Vec::new(),
            points,
            texts: Vec::new(),
            metadata: Vec::new(),
        };
        self.channels.annotations.log_with_meta(
            &msg,
            PartialMetadata {
                log_time: Some(stamp_ns(it.meta.stamp_s)),
            },
        );
    }

    /// One frame's messages, in this order: image, annotations, frame, exposure,
    /// detection, pose, command, vehicle, failsafe events.
    fn write(&mut self, it: &Item) {
        let t = stamp_ns(it.meta.stamp_s);
        let image_written = self.write_image(it, t);
        self.annotate(it);
        self.write_frame(it, t, image_written);
        self.write_exposure(it, t);
        self.write_detection(it, t);
        self.write_pose(it, t);
        let ch = self.channels.command.clone();
        self.json(&ch, t, &CommandMsg::from_record(&it.rec));
        self.write_vehicle(it, t);
        self.write_failsafe_events(it, t);
    }

    /// The frame's PNG, if it carries pixels; true when it was written.
    fn write_image(&mut self, it: &Item, t: u64) -> bool {
        let Some(img) = &it.image else {
            return false;
        };
        match self.encode_png(it.width, it.height, img) {
            Ok(()) => {
                let msg = CompressedImage {
                    timestamp: Some(timestamp(it.meta.stamp_s)),
                    frame_id: "camera".into(),
                    data: foxglove::bytes::Bytes::copy_from_slice(self.png.as_slice()),
                    format: self.format.name().into(),
                };
                self.channels
                    .image
                    .log_with_meta(&msg, PartialMetadata { log_time: Some(t) });
                true
            }
            Err(e) => {
                self.shared.report_error(&e);
                false
            }
        }
    }

    fn write_frame(&mut self, it: &Item, t: u64, image_written: bool) {
        let m = it.meta;
        let frame = FrameMsg {
            seq: m.seq,
            stamp_s: m.stamp_s,
            exposure_us: m.exposure_us,
            gain_db: m.gain_db,
            width: it.width,
            height: it.height,
            image: image_written,
            heartbeat_s: it.heartbeat_s,
            shutdown: it.shutdown,
            bits: FrameBits {
                stamp: m.stamp_s.to_bits(),
                exposure: m.exposure_us.to_bits(),
                gain: m.gain_db.to_bits(),
                heartbeat: it.heartbeat_s.map(f64::to_bits),
            },
        };
        let ch = self.channels.frame.clone();
        self.json(&ch, t, &frame);
    }

    fn write_exposure(&mut self, it: &Item, t: u64) {
        let (r, m) = (&it.rec, it.meta);
        let exposure = ExposureMsg {
            seq: m.seq,
            stamp_s: m.stamp_s,
            exposure_used_us: r.exposure_used_us,
            exposure_next_us: r.exposure.exposure_us,
            gain_db: m.gain_db,
            metric: finite(r.exposure.metric),
            used_frame: r.exposure.used_frame,
            roi: r.exposure.roi,
        };
        let ch = self.channels.exposure.clone();
        self.json(&ch, t, &exposure);
    }

    fn write_detection(&mut self, it: &Item, t: u64) {
        let (r, m) = (&it.rec, it.meta);
        let q = r.t_cam_marker.map(|p| p.rotation.into_inner().coords);
        let detection = DetectionMsg {
            seq: m.seq,
            stamp_s: m.stamp_s,
            detected: r.detected,
            corners_px: r.corners,
            translation_m: r.t_cam_marker.map(|p| p.translation.vector.into()),
            rotation_xyzw: q.map(|c| [c.x, c.y, c.z, c.w]),
            covariance: r.cov_cam.map(|c| c.transpose().as_slice().to_vec()),
            reproj_rms_px: finite(r.reproj_rms_px),
        };
        let ch = self.channels.detection.clone();
        self.json(&ch, t, &detection);
    }

    /// The marker's pose in the camera frame, when it was measured.
    fn write_pose(&mut self, it: &Item, t: u64) {
        let Some(p) = it.rec.t_cam_marker else {
            return;
        };
        let v = p.translation.vector;
        let q = p.rotation.into_inner().coords;
        let msg = PoseInFrame {
            timestamp: Some(timestamp(it.meta.stamp_s)),
            frame_id: "camera".into(),
            pose: Some(Pose {
                position: Some(Vector3 {
                    x: v.x,
                    y: v.y,
                    z: v.z,
                }),
                orientation: Some(Quaternion {
                    x: q.x,
                    y: q.y,
                    z: q.z,
                    w: q.w,
                }),
            }),
        };
        self.channels
            .pose
            .log_with_meta(&msg, PartialMetadata { log_time: Some(t) });
    }

    /// The vehicle's state, when the item carries one.
    fn write_vehicle(&mut self, it: &Item, t: u64) {
        if let Some(state) = &it.vehicle {
            let ch = self.channels.vehicle.clone();
            self.json(
                &ch,
                t,
                &VehicleMsg {
                    seq: it.meta.seq,
                    stamp_s: it.meta.stamp_s,
                    state,
                },
            );
        }
    }

    fn write_failsafe_events(&mut self, it: &Item, t: u64) {
        for e in it.events.iter().flatten() {
            let msg = Log {
                timestamp: Some(timestamp(it.meta.stamp_s)),
                level: foxglove::schemas::log::Level::Warning as i32,
                message: format!("{e:?}"),
                name: "supervisor".into(),
                file: String::new(),
                line: 0,
            };
            self.channels
                .failsafe
                .log_with_meta(&msg, PartialMetadata { log_time: Some(t) });
        }
    }
}

/// Reads a recorder's counters, also after the recorder was handed to the loop and
/// finished there.
#[derive(Clone)]
pub struct RecordStatsHandle(Arc<Shared>);

impl RecordStatsHandle {
    pub fn get(&self) -> RecordStats {
        self.0.stats()
    }
}

impl Observer for Recorder {
    fn name(&self) -> &'static str {
        if self.path.is_some() {
            "recorder"
        } else {
            "live view"
        }
    }
    fn frame(&mut self, v: &FrameView<'_>) {
        let link = LinkSnapshot {
            heartbeat_s: v.heartbeat_s,
            vehicle: v.vehicle.cloned(),
        };
        self.record(v.rec, v.frame, &link, v.shutdown, v.events);
    }
    /// Finalize the file and say what it holds; a write error met during the run (the
    /// run went on without the recording) is an error here.
    fn finish(self: Box<Self>) -> Result<(), CoreError> {
        let path = self.path.clone();
        let stats = (*self).finish()?;
        let Some(path) = path else { return Ok(()) };
        eprintln!(
            "markhold: recorded {} frames to {} ({} images dropped, {} frames dropped)",
            stats.frames,
            path.display(),
            stats.images_dropped,
            stats.frames_dropped
        );
        if stats.segments > 1 || stats.deleted > 0 {
            eprintln!(
                "markhold: the recording is {} segments beside {}; {} older recordings deleted \
                 for the quota and the free-space floor",
                stats.segments,
                path.display(),
                stats.deleted
            );
        }
        if let Some(reason) = stats.write_error.as_ref().or(stats.stopped.as_ref()) {
            return Err(RecordError::Write {
                reason: format!("{}: {reason}", path.display()),
            }
            .into());
        }
        Ok(())
    }
    fn abort(self: Box<Self>) {
        (*self).abort();
    }
    fn mavlink_tap(&self) -> Option<SyncSender<markhold_autopilot::RawFrame>> {
        Some(self.tap.clone())
    }
}
