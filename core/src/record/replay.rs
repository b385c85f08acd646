//! `markhold replay FILE.mcap`: the recorded frames through the same [`Pipeline`], on
//! the recorded clock, with a link that only keeps the commands; each command is
//! compared bit for bit with the recorded one.

use crate::CoreError;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use foxglove::schemas::CompressedImage;
use foxglove::Decode;
use markhold_autopilot::Effort;
use markhold_exposure::{Camera, CameraError, ExposureLimits, ExposureMethod, Frame, FrameMeta};
use markhold_vision::CameraCalibration;
use opencv::prelude::*;
use serde::Serialize;

use crate::params::{LoadedSite, Site};
use crate::pipeline::{CommandLink, LoopStart, Observers, Pipeline};
use crate::record::{
    CommandMsg, FrameMsg, RunInfo, METADATA_NAME, TOPIC_COMMAND, TOPIC_FRAME, TOPIC_IMAGE,
};

/// What replay sent: per frame, the effort, or `None` for neutral input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SentCommand {
    pub stamp_s: f64,
    pub effort: Option<Effort>,
}

/// A link that keeps the commands and reports the recorded heartbeat.
#[derive(Debug, Default)]
pub struct SinkLink {
    /// The vehicle heartbeat to report on the coming frame (from the recording).
    pub heartbeat_s: Option<f64>,
    pub sent: Vec<SentCommand>,
}

impl CommandLink for SinkLink {
    fn tick(&mut self, _now_s: f64) -> Result<(), CoreError> {
        Ok(())
    }
    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> Result<(), CoreError> {
        self.sent.push(SentCommand {
            stamp_s: now_s,
            effort: Some(*effort),
        });
        Ok(())
    }
    fn send_neutral(&mut self, now_s: f64) -> Result<(), CoreError> {
        self.sent.push(SentCommand {
            stamp_s: now_s,
            effort: None,
        });
        Ok(())
    }
    fn vehicle_heartbeat_s(&self) -> Option<f64> {
        self.heartbeat_s
    }
}

/// Hands out the one frame replay loaded; exposure requests are only noted.
struct ReplayCamera {
    frame: Frame,
    ready: bool,
    limits: ExposureLimits,
    requested_us: f64,
}

impl Camera for ReplayCamera {
    fn name(&self) -> &str {
        "replay"
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.requested_us = exposure_us;
        Ok(exposure_us)
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        if !self.ready {
            return Err(CameraError::EndOfStream {
                device: "replay".into(),
            });
        }
        self.ready = false;
        frame.resize(self.frame.width, self.frame.height);
        frame.data.copy_from_slice(&self.frame.data);
        frame.meta = self.frame.meta;
        Ok(())
    }
}

/// The first command that differs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mismatch {
    pub seq: u64,
    pub stamp_s: f64,
    /// `directive`, `effort.surge` .. `effort.yaw`, `seq`, `image` (dropped when
    /// recording: replay cannot go past it) or `count`.
    pub field: String,
    pub recorded: String,
    pub replayed: String,
}

/// `--summary` of a replay.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplaySummary {
    pub file: PathBuf,
    /// The command that recorded the file (`hil`, `run`).
    pub recorded_by: String,
    pub exposure_method: String,
    pub frames_recorded: u64,
    pub frames_replayed: u64,
    pub commands_compared: u64,
    pub commands_match: bool,
    pub first_mismatch: Option<Mismatch>,
    /// The file ended early (truncated or never finalized): what was replayed is what its
    /// complete chunks held.
    pub recovered: Option<Recovered>,
    /// Images recorded lossy (JPEG): the loop saw other pixels than when recording, so
    /// the commands are not expected to match bit for bit.
    pub lossy_images: u64,
}

/// A recording read up to its last complete chunk.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Recovered {
    pub file_bytes: u64,
    /// Why reading stopped.
    pub reason: String,
}

fn mcap_err(path: &Path) -> impl Fn(mcap::McapError) -> CoreError + '_ {
    move |e| CoreError::NotMcap {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

/// The recording `path` is not what replay reads, for `reason`.
pub(crate) fn recording(path: &Path, reason: String) -> CoreError {
    CoreError::Recording {
        path: path.to_path_buf(),
        reason,
    }
}

/// The recording `path` gave no run description: it ended early (`ended_early`: why)
/// or it is not a markhold recording.
pub(crate) fn no_run_info(path: &Path, ended_early: Option<String>) -> CoreError {
    match ended_early {
        Some(reason) => CoreError::NotMcap {
            path: path.to_path_buf(),
            reason,
        },
        None => recording(
            path,
            format!("no `{METADATA_NAME}` metadata: not a markhold recording"),
        ),
    }
}

/// A part of the recording `path` could not be read, for the error `source`.
fn part(
    path: &Path,
    part: impl Into<String>,
    source: impl Into<Box<dyn std::error::Error + Send + Sync + 'static>>,
) -> CoreError {
    CoreError::RecordingPart {
        path: path.to_path_buf(),
        part: part.into(),
        source: source.into(),
    }
}

/// Reading the file `path` failed.
fn reading(path: &Path, source: std::io::Error) -> CoreError {
    CoreError::File {
        action: "reading",
        path: path.to_path_buf(),
        source,
    }
}

/// The largest record replay accepts (a chunk holds a few frames; a hostile length
/// must not become an allocation).
pub(crate) const MAX_RECORD_BYTES: usize = 256 << 20;

/// The run description of a recording's metadata record, checked like a site file.
pub fn run_info_of(
    path: &Path,
    metadata: &BTreeMap<String, String>,
) -> Result<(RunInfo, LoadedSite), CoreError> {
    let info = RunInfo::from_metadata(metadata)
        .map_err(|k| recording(path, format!("run metadata key {k} missing or bad")))?;
    let site: Site =
        toml::from_str(&info.site_toml).map_err(|e| part(path, "the recorded site", e))?;
    crate::params::check(&site).map_err(|e| part(path, "the recorded site is not valid", e))?;
    let calibration: CameraCalibration = toml::from_str(&info.calibration_toml)
        .map_err(|e| part(path, "the recorded calibration", e))?;
    calibration
        .check_resolution(site.camera.width_px, site.camera.height_px)
        .map_err(|e| part(path, "the recorded calibration", e))?;
    calibration
        .validate()
        .map_err(|e| part(path, "the recorded calibration", e))?;
    let limits = ExposureLimits {
        min_us: site.camera.exposure_min_us,
        max_us: site.camera.exposure_max_us,
        fps: site.camera.fps,
    };
    if !(info.initial_exposure_us.is_finite()
        && (limits.min_us..=limits.max_us).contains(&info.initial_exposure_us))
    {
        return Err(CoreError::RecordedExposure {
            path: path.to_path_buf(),
            exposure_us: info.initial_exposure_us,
        });
    }
    Ok((
        info,
        LoadedSite {
            path: path.to_path_buf(),
            site,
            calibration,
        },
    ))
}

/// Read the run description of a whole recording held in memory (its summary section).
pub fn read_run_info(path: &Path, buf: &[u8]) -> Result<(RunInfo, LoadedSite), CoreError> {
    let summary = mcap::Summary::read(buf)
        .map_err(mcap_err(path))?
        .ok_or_else(|| {
            recording(
                path,
                "no MCAP summary (was the recording finalized?)".into(),
            )
        })?;
    let idx = summary
        .metadata_indexes
        .iter()
        .find(|i| i.name == METADATA_NAME)
        .ok_or_else(|| {
            recording(
                path,
                format!("no `{METADATA_NAME}` metadata: not a markhold recording"),
            )
        })?;
    let meta = mcap::read::metadata(buf, idx).map_err(mcap_err(path))?;
    run_info_of(path, &meta.metadata)
}

/// A recorded PNG or JPEG into `out`, which has the recorded site's size.
pub(crate) fn decode_image(encoded: &[u8], out: &mut Frame) -> Result<(), CoreError> {
    // The size the header states, before a decoder allocates it.
    markhold_camera::check_encoded_size(encoded, Some((out.width, out.height)))
        .map_err(|reason| CoreError::Image { reason })?;
    let buf = opencv::core::Mat::from_slice(encoded)?;
    let img = opencv::imgcodecs::imdecode(&buf, opencv::imgcodecs::IMREAD_UNCHANGED)?;
    if img.empty() || img.channels() != 1 || img.depth() != opencv::core::CV_8U {
        return Err(CoreError::Image {
            reason: "not an 8-bit grey image".into(),
        });
    }
    let (w, h) = (img.cols() as u32, img.rows() as u32);
    if (w, h) != (out.width, out.height) {
        return Err(CoreError::Image {
            reason: format!(
                "a {w}x{h} image in a recording of a {}x{} camera",
                out.width, out.height
            ),
        });
    }
    out.resize(w, h);
    let bytes = img.data_bytes()?;
    let n = (w * h) as usize;
    if !img.is_continuous() || bytes.len() < n {
        return Err(CoreError::Image {
            reason: "decoded image is not contiguous".into(),
        });
    }
    out.data.copy_from_slice(&bytes[..n]);
    Ok(())
}

fn compare(recorded: &CommandMsg, replayed: &CommandMsg) -> Option<Mismatch> {
    let mm = |field: &str, a: String, b: String| Mismatch {
        seq: recorded.seq,
        stamp_s: recorded.stamp_s,
        field: field.to_string(),
        recorded: a,
        replayed: b,
    };
    if recorded.seq != replayed.seq {
        return Some(mm(
            "seq",
            recorded.seq.to_string(),
            replayed.seq.to_string(),
        ));
    }
    if recorded.directive != replayed.directive {
        return Some(mm(
            "directive",
            recorded.directive.clone(),
            replayed.directive.clone(),
        ));
    }
    const AXES: [&str; 6] = ["surge", "sway", "heave", "roll", "pitch", "yaw"];
    for (i, axis) in AXES.iter().enumerate() {
        if recorded.effort_bits[i] != replayed.effort_bits[i] {
            let v = |b: u64| format!("{:e} (bits {b:016x})", f64::from_bits(b));
            return Some(mm(
                &format!("effort.{axis}"),
                v(recorded.effort_bits[i]),
                v(replayed.effort_bits[i]),
            ));
        }
    }
    None
}

/// The recorded loop again: the recorded site and start, a link that keeps the
/// commands, and no mode requests (there is no vehicle to ask).
pub fn build_loop(
    site: &LoadedSite,
    method: ExposureMethod,
    info: &RunInfo,
) -> Result<Pipeline<SinkLink>, CoreError> {
    let start = LoopStart {
        method,
        initial_exposure_us: info.initial_exposure_us,
        site_mode: None,
    };
    Pipeline::new(site, start, SinkLink::default(), Observers::new())
}

/// Whether every string and map length a Channel or Metadata record declares lies
/// within the record (other records: true).
pub(crate) fn lengths_fit(opcode: u8, data: &[u8]) -> bool {
    fn prefixed(data: &[u8], at: &mut usize, end: usize) -> Option<()> {
        let len_end = at.checked_add(4).filter(|e| *e <= end)?;
        let n = u32::from_le_bytes(data.get(*at..len_end)?.try_into().ok()?) as usize;
        *at = len_end.checked_add(n).filter(|e| *e <= end)?;
        Some(())
    }
    let check = || -> Option<()> {
        let (mut at, strings) = match opcode {
            mcap::records::op::CHANNEL => (4, 2),
            mcap::records::op::METADATA => (0, 1),
            _ => return Some(()),
        };
        for _ in 0..strings {
            prefixed(data, &mut at, data.len())?;
        }
        // The map: its byte length, then key and value strings within it.
        let map_start = at;
        prefixed(data, &mut at, data.len())?;
        let end = at;
        at = map_start + 4;
        while at < end {
            prefixed(data, &mut at, end)?;
            prefixed(data, &mut at, end)?;
        }
        Some(())
    };
    check().is_some()
}

/// The topics replay reads.
#[derive(Debug, Clone, Copy)]
enum Topic {
    Image,
    Frame,
    Command,
    Other,
}

/// Replay a recording and compare its commands. The file is read record by record
/// (memory does not grow with its length); a file that ends early (a crash, a full disk,
/// a copy cut short) is replayed up to its last complete chunk and the summary says so.
pub fn replay(path: &Path) -> Result<ReplaySummary, CoreError> {
    let file =
        crate::params::open_regular(path, u64::MAX).map_err(|source| reading(path, source))?;
    let size = file.metadata().map(|m| m.len()).unwrap_or(0);
    replay_from(path, std::io::BufReader::with_capacity(1 << 20, file), size)
}

/// Reads the MCAP recording `src` (named `path` in messages) record by record and hands
/// `f` every channel, metadata and message record; memory does not grow with the file.
/// Chunks are checked whole (CRC) before any of their records is handed on, so a chunk
/// cut short by the end of the file gives nothing, and only the records handed on are
/// parsed, and only when every length they declare fits in them: the mcap crate reserves
/// a declared string length before reading it (a hostile 4 GB length in a 20-byte
/// record). Returns why the file ended early (truncated, never finalized, a bad record),
/// `None` when it was read to its end.
pub(crate) fn for_each_record<E: From<CoreError>>(
    path: &Path,
    mut src: impl std::io::Read,
    mut f: impl FnMut(mcap::records::Record<'_>) -> Result<(), E>,
) -> Result<Option<String>, E> {
    use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    );
    while let Some(event) = reader.next_event() {
        let (opcode, data) = match event {
            Ok(LinearReadEvent::ReadRequest(n)) => {
                let got = src
                    .read(reader.insert(n.min(MAX_RECORD_BYTES)))
                    .map_err(|source| reading(path, source))?;
                reader.notify_read(got);
                continue;
            }
            Ok(LinearReadEvent::Record { opcode, data }) => (opcode, data),
            Err(e) => return Ok(Some(e.to_string())),
        };
        if !matches!(
            opcode,
            mcap::records::op::CHANNEL | mcap::records::op::METADATA | mcap::records::op::MESSAGE
        ) {
            continue;
        }
        if !lengths_fit(opcode, data) {
            return Ok(Some(format!(
                "a record (opcode {opcode:#04x}) declares a string longer than itself"
            )));
        }
        match mcap::parse_record(opcode, data) {
            Ok(record) => f(record)?,
            Err(e) => return Ok(Some(e.to_string())),
        }
    }
    Ok(None)
}

/// [`replay`] of the recording `src` (`size` bytes long), named `path` in messages.
pub fn replay_from(
    path: &Path,
    mut src: impl std::io::Read,
    size: u64,
) -> Result<ReplaySummary, CoreError> {
    use mcap::records::Record;

    let mut topics: HashMap<u16, Topic> = HashMap::new();
    let mut replayer: Option<Replayer<'_>> = None;
    let ended_early = for_each_record(path, &mut src, |record| {
        match record {
            Record::Channel(c) => {
                let topic = match c.topic.as_str() {
                    TOPIC_IMAGE => Topic::Image,
                    TOPIC_FRAME => Topic::Frame,
                    TOPIC_COMMAND => Topic::Command,
                    _ => Topic::Other,
                };
                topics.insert(c.id, topic);
            }
            Record::Metadata(m) if m.name == METADATA_NAME && replayer.is_none() => {
                let (info, site) = run_info_of(path, &m.metadata)?;
                replayer = Some(Replayer::start(path, &site, &info)?);
            }
            Record::Message { header, data } => {
                let Some(r) = replayer.as_mut() else {
                    return Err(recording(
                        path,
                        format!("messages before the `{METADATA_NAME}` metadata: not a markhold recording"),
                    ));
                };
                match topics.get(&header.channel_id) {
                    Some(Topic::Image) => r.image(header.log_time, &data)?,
                    Some(Topic::Frame) => r.frame(header.log_time, &data)?,
                    Some(Topic::Command) => r.command(&data)?,
                    Some(Topic::Other) => {}
                    None => {
                        return Err(recording(
                            path,
                            format!(
                                "a message on channel {} that was never described",
                                header.channel_id
                            ),
                        ))
                    }
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    let Some(r) = replayer else {
        return Err(no_run_info(path, ended_early));
    };
    let mut out = r.finish();
    if let Some(why) = ended_early {
        out.recovered = Some(Recovered {
            file_bytes: size,
            reason: why,
        });
    }
    Ok(out)
}

/// The replay in progress: the loop, its camera, the last image and the last command
/// replayed, and what was compared so far.
struct Replayer<'a> {
    path: &'a Path,
    pipeline: Pipeline<SinkLink>,
    camera: ReplayCamera,
    out: ReplaySummary,
    /// The last image message: its log time and PNG.
    image: Option<(u64, Vec<u8>)>,
    /// The command of the last frame replayed, until its recorded one comes.
    replayed: Option<CommandMsg>,
    /// A frame could not be replayed: the loop's state has diverged from here on.
    stopped: bool,
}

impl<'a> Replayer<'a> {
    /// The recorded loop, ready for the recorded frames.
    fn start(path: &'a Path, site: &LoadedSite, info: &RunInfo) -> Result<Self, CoreError> {
        let method: ExposureMethod =
            info.exposure_method
                .parse()
                .map_err(|e| CoreError::RecordedValue {
                    path: path.to_path_buf(),
                    key: "exposure_method",
                    value: info.exposure_method.clone(),
                    reason: e,
                })?;
        let pipeline = build_loop(site, method, info).map_err(|e| CoreError::Rebuild {
            source: Box::new(e),
        })?;
        Ok(Self::new(path, pipeline, site, info))
    }

    fn new(
        path: &'a Path,
        pipeline: Pipeline<SinkLink>,
        site: &LoadedSite,
        info: &RunInfo,
    ) -> Self {
        Self {
            path,
            pipeline,
            camera: ReplayCamera {
                frame: Frame::new(site.calibration.width, site.calibration.height),
                ready: false,
                limits: site.limits(),
                requested_us: info.initial_exposure_us,
            },
            out: ReplaySummary {
                file: path.to_path_buf(),
                recorded_by: info.command.clone(),
                exposure_method: info.exposure_method.clone(),
                frames_recorded: 0,
                frames_replayed: 0,
                commands_compared: 0,
                commands_match: true,
                first_mismatch: None,
                recovered: None,
                lossy_images: 0,
            },
            image: None,
            replayed: None,
            stopped: false,
        }
    }

    fn image(&mut self, log_time: u64, data: &[u8]) -> Result<(), CoreError> {
        let img = CompressedImage::decode(data)
            .map_err(|e| recording(self.path, format!("image at {log_time} ns: {e}")))?;
        match img.format.as_str() {
            "png" => {}
            "jpeg" => self.out.lossy_images += 1,
            other => {
                return Err(recording(
                    self.path,
                    format!("image at {log_time} ns: format {other:?}: expected png or jpeg"),
                ))
            }
        }
        // The buffer of the last image is reused: nothing grows with the file.
        let mut buf = self.image.take().map(|(_, b)| b).unwrap_or_default();
        buf.clear();
        buf.extend_from_slice(&img.data);
        self.image = Some((log_time, buf));
        Ok(())
    }

    /// A recorded frame: its image and meta through the loop.
    fn frame(&mut self, log_time: u64, data: &[u8]) -> Result<(), CoreError> {
        let path = self.path;
        self.out.frames_recorded += 1;
        if self.stopped {
            return Ok(());
        }
        let f: FrameMsg =
            serde_json::from_slice(data).map_err(|e| part(path, "frame message", e))?;
        let png = match self.image.take() {
            Some((t, png)) if t == log_time && f.image => png,
            _ => {
                // Without the pixels the loop's state diverges: stop here.
                self.stopped = true;
                if self.out.first_mismatch.is_none() {
                    self.out.first_mismatch = Some(Mismatch {
                        seq: f.seq,
                        stamp_s: f.stamp_s,
                        field: "image".into(),
                        recorded: "dropped while recording".into(),
                        replayed: "not replayed".into(),
                    });
                }
                return Ok(());
            }
        };
        decode_image(&png, &mut self.camera.frame)
            .map_err(|e| part(path, format!("image of frame {}", f.seq), e))?;
        self.camera.frame.meta = FrameMeta {
            seq: f.seq,
            stamp_s: f64::from_bits(f.bits.stamp),
            exposure_us: f64::from_bits(f.bits.exposure),
            gain_db: f64::from_bits(f.bits.gain),
        };
        self.camera.ready = true;
        self.pipeline.link_mut().heartbeat_s = f.bits.heartbeat.map(f64::from_bits);
        self.pipeline.set_shutdown(f.shutdown);
        let rec = self.pipeline.step(&mut self.camera)?;
        self.out.frames_replayed += 1;
        self.replayed = Some(CommandMsg::from_record(&rec));
        Ok(())
    }

    /// A recorded command: compared with the one the last frame replayed gave.
    fn command(&mut self, data: &[u8]) -> Result<(), CoreError> {
        if self.stopped {
            return Ok(());
        }
        let recorded: CommandMsg =
            serde_json::from_slice(data).map_err(|e| part(self.path, "command message", e))?;
        let Some(mine) = self.replayed.take() else {
            return Ok(());
        };
        self.out.commands_compared += 1;
        if self.out.first_mismatch.is_none() {
            self.out.first_mismatch = compare(&recorded, &mine);
        }
        Ok(())
    }

    fn finish(self) -> ReplaySummary {
        let mut out = self.out;
        if out.commands_compared != out.frames_replayed && out.first_mismatch.is_none() {
            out.first_mismatch = Some(Mismatch {
                seq: 0,
                stamp_s: 0.0,
                field: "count".into(),
                recorded: format!("{} commands", out.commands_compared),
                replayed: format!("{} frames", out.frames_replayed),
            });
        }
        out.commands_match = out.first_mismatch.is_none() && out.frames_replayed > 0;
        let _ = self.camera.requested_us;
        out
    }
}

#[cfg(test)]
mod tests {
    use super::lengths_fit;
    use mcap::records::op;

    #[test]
    fn declared_lengths_must_fit_in_the_record() {
        // Metadata: name "ab", a map of one pair "k" -> "v".
        let mut ok = Vec::new();
        ok.extend_from_slice(&2u32.to_le_bytes());
        ok.extend_from_slice(b"ab");
        ok.extend_from_slice(&10u32.to_le_bytes());
        ok.extend_from_slice(&1u32.to_le_bytes());
        ok.extend_from_slice(b"k");
        ok.extend_from_slice(&1u32.to_le_bytes());
        ok.extend_from_slice(b"v");
        assert!(lengths_fit(op::METADATA, &ok));
        // A name that claims 4 GB; a map entry past the map's end; a truncated map.
        let mut huge = ok.clone();
        huge[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(!lengths_fit(op::METADATA, &huge));
        let mut past = ok.clone();
        past[6..10].copy_from_slice(&9u32.to_le_bytes());
        assert!(!lengths_fit(op::METADATA, &past));
        assert!(!lengths_fit(op::METADATA, &ok[..ok.len() - 1]));
        // Channel: ids, then two strings and the map.
        let mut chan = vec![1, 0, 0, 0];
        chan.extend_from_slice(&0u32.to_le_bytes());
        chan.extend_from_slice(&ok);
        assert!(lengths_fit(op::CHANNEL, &chan));
        chan[4..8].copy_from_slice(&1_000_000u32.to_le_bytes());
        assert!(!lengths_fit(op::CHANNEL, &chan));
    }
}
