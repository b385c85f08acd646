//! Recording rotation (`[record.rotation]`): a recording is a series of segments, each a
//! complete MCAP file of bounded size (and, if asked, of bounded frame time), so a crash
//! or a pulled SD card loses at most the open segment's last chunk, and a long dive never
//! makes one file too big to copy. The recording's folder is kept under a quota and its
//! file system above a free-space floor by deleting the oldest recordings in the folder,
//! never the segment being written; when nothing is left to delete and the floor is still
//! not met, the recording stops (its open segment closed, complete) and says why.
//!
//! Segment names: the first is the `--record` path itself, the next ones
//! `<stem>.<n>.mcap` beside it (n from 1). What counts as a recording in the folder: a
//! regular file named `*.mcap` that starts with the MCAP magic. The folder should hold
//! recordings only (the BlueOS extension's `/data/recordings` does).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime};

use foxglove::{Context, McapWriteOptions, McapWriter, McapWriterHandle};
use serde::{Deserialize, Serialize};

use super::{RecordError, RunInfo, Shared, Tracked, METADATA_NAME};

/// One MB (10^6 bytes: the unit `df -H` and SD card labels use).
const MB: f64 = 1e6;
/// The first bytes of every MCAP file.
const MCAP_MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// `[record.rotation]` of a site file.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotationSection {
    /// Close the segment and begin the next once it holds this much, MB. A segment ends
    /// up at most a quarter larger (the MCAP chunk in progress) plus its index.
    #[serde(default = "default_segment_mb")]
    pub segment_mb: f64,
    /// Also close it after this much frame time, s (left out: no time limit).
    #[serde(default)]
    pub segment_s: Option<f64>,
    /// Keep the folder's recordings under this, MB, oldest deleted first (left out: no
    /// quota, only the floor). At least twice `segment_mb`.
    #[serde(default)]
    pub quota_mb: Option<f64>,
    /// Keep at least this much free on the recording's file system, MB, oldest
    /// recordings deleted first; with nothing left to delete, the recording stops.
    #[serde(default = "default_min_free_mb")]
    pub min_free_mb: f64,
}

fn default_segment_mb() -> f64 {
    1000.0
}

fn default_min_free_mb() -> f64 {
    256.0
}

impl Default for RotationSection {
    fn default() -> Self {
        Self {
            segment_mb: default_segment_mb(),
            segment_s: None,
            quota_mb: None,
            min_free_mb: default_min_free_mb(),
        }
    }
}

impl RotationSection {
    pub fn validate(&self) -> Result<(), markhold_config::ConfigError> {
        let mut c = markhold_config::Checks::new("record.rotation")
            .range(
                "segment_mb",
                self.segment_mb,
                0.01..=1e6,
                "a segment size in MB, 0.01..1000000",
            )
            .range(
                "min_free_mb",
                self.min_free_mb,
                0.0..=1e9,
                "free space to keep in MB, 0..1000000000",
            );
        if let Some(s) = self.segment_s {
            c = c.range(
                "segment_s",
                s,
                1.0..=86_400.0,
                "a segment length in seconds, 1..86400",
            );
        }
        if let Some(q) = self.quota_mb {
            c = c.check(
                "quota_mb",
                q,
                q.is_finite() && q >= 2.0 * self.segment_mb && q <= 1e9,
                "a quota in MB of at least twice segment_mb (the open segment is never \
                 deleted), at most 1000000000",
            );
        }
        c.done()
    }

    /// The recorder's settings (bytes and nanoseconds: the same on 32- and 64-bit).
    pub fn config(&self) -> RotationConfig {
        let bytes = |mb: f64| (mb * MB).round() as u64;
        RotationConfig {
            segment_bytes: bytes(self.segment_mb).max(1),
            segment_ns: self.segment_s.map(|s| (s * 1e9).round() as u64),
            quota_bytes: self.quota_mb.map(bytes),
            min_free_bytes: bytes(self.min_free_mb),
        }
    }
}

/// Rotation as the recorder applies it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotationConfig {
    pub segment_bytes: u64,
    pub segment_ns: Option<u64>,
    pub quota_bytes: Option<u64>,
    pub min_free_bytes: u64,
}

impl Default for RotationConfig {
    fn default() -> Self {
        RotationSection::default().config()
    }
}

impl RotationConfig {
    /// The MCAP chunk size for segments of this size: a quarter of a segment, at most
    /// the mcap crate's default (1 MiB), so a segment overshoots by at most that.
    pub fn chunk_bytes(&self) -> u64 {
        (self.segment_bytes / 4).clamp(4096, 1 << 20)
    }

    /// Whether a segment of `bytes` bytes spanning `span_ns` of frame time is full.
    pub fn segment_full(&self, bytes: u64, span_ns: u64) -> bool {
        bytes >= self.segment_bytes || self.segment_ns.is_some_and(|n| span_ns >= n)
    }
}

/// The segment paths of one recording.
#[derive(Debug, Clone)]
pub struct SegmentNames {
    first: PathBuf,
    dir: PathBuf,
    stem: String,
}

impl SegmentNames {
    pub fn new(first: &Path) -> Self {
        let dir = match first.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let stem = first
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "recording".into());
        Self {
            first: first.to_path_buf(),
            dir,
            stem,
        }
    }

    /// Segment `n` (0: the path given).
    pub fn path(&self, n: u32) -> PathBuf {
        if n == 0 {
            self.first.clone()
        } else {
            self.dir.join(format!("{}.{n}.mcap", self.stem))
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

/// Bytes free for an unprivileged writer on the file system holding `dir`.
pub fn free_bytes(dir: &Path) -> std::io::Result<u64> {
    let st = rustix::fs::statvfs(dir)?;
    Ok(st.f_bavail.saturating_mul(st.f_frsize))
}

/// A recording in the folder that rotation may delete.
#[derive(Debug, Clone)]
struct Candidate {
    path: PathBuf,
    modified: SystemTime,
    bytes: u64,
}

fn is_recording(path: &Path) -> bool {
    use std::io::Read;
    if path.extension().and_then(|e| e.to_str()) != Some("mcap") {
        return false;
    }
    let mut magic = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok_and(|()| &magic == MCAP_MAGIC)
}

/// The folder's recordings other than `open`, oldest first (by modification time, then
/// name length and name).
fn candidates(dir: &Path, open: Option<&Path>) -> std::io::Result<Vec<Candidate>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let path = entry.path();
        // Not followed: a link to a file elsewhere is not this folder's recording.
        let Ok(meta) = std::fs::symlink_metadata(&path) else {
            continue;
        };
        if !meta.is_file() || open.is_some_and(|o| same_file(o, &path)) || !is_recording(&path) {
            continue;
        }
        out.push(Candidate {
            modified: meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
            bytes: meta.len(),
            path,
        });
    }
    // Equal times (a coarse clock): the shorter name first, so `run.9` before `run.10`.
    let name_len = |c: &Candidate| c.path.as_os_str().len();
    out.sort_by(|a, b| {
        a.modified
            .cmp(&b.modified)
            .then(name_len(a).cmp(&name_len(b)))
            .then(a.path.cmp(&b.path))
    });
    Ok(out)
}

fn same_file(a: &Path, b: &Path) -> bool {
    a == b
        || a.file_name().is_some_and(|n| Some(n) == b.file_name()) && {
            let canon = |p: &Path| std::fs::canonicalize(p).ok();
            canon(a).is_some() && canon(a) == canon(b)
        }
}

/// What [`enforce`] did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Enforced {
    /// Recordings deleted, oldest first.
    pub deleted: Vec<PathBuf>,
    /// The folder's recordings after the deletions, open segment included, bytes.
    pub total_bytes: u64,
    /// Free bytes after the deletions.
    pub free_bytes: u64,
    /// The floor is not met and nothing is left to delete.
    pub below_floor: bool,
}

/// Keep `dir` under the quota and its file system above the floor: delete the oldest
/// recordings, never `open` (the segment being written, `open_bytes` long so far).
/// `free` reads the free space (a parameter so tests can play a small disk).
pub fn enforce(
    dir: &Path,
    open: Option<&Path>,
    open_bytes: u64,
    cfg: &RotationConfig,
    free: &mut dyn FnMut(&Path) -> std::io::Result<u64>,
) -> std::io::Result<Enforced> {
    let mut list = candidates(dir, open)?;
    let mut out = Enforced {
        total_bytes: list.iter().map(|c| c.bytes).sum::<u64>() + open_bytes,
        free_bytes: free(dir)?,
        ..Enforced::default()
    };
    let over = |o: &Enforced| {
        cfg.quota_bytes.is_some_and(|q| o.total_bytes > q) || o.free_bytes < cfg.min_free_bytes
    };
    list.reverse();
    while over(&out) {
        let Some(c) = list.pop() else { break };
        std::fs::remove_file(&c.path)?;
        tracing::warn!(
            "recording: deleted {} ({:.1} MB) to keep the quota and free-space floor",
            c.path.display(),
            c.bytes as f64 / MB
        );
        out.total_bytes = out.total_bytes.saturating_sub(c.bytes);
        out.free_bytes = free(dir)?;
        out.deleted.push(c.path);
    }
    out.below_floor = out.free_bytes < cfg.min_free_bytes;
    Ok(out)
}

/// How often the writer thread looks at the controls while no frame comes.
pub(super) const IDLE_POLL: Duration = Duration::from_millis(100);
/// Names tried for one segment before giving up (a name left by another run is skipped).
const NAME_TRIES: u32 = 100;

/// Where a file recording stands, for the web page and the run's report.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct RecordingState {
    /// A segment is open and frames go to it.
    pub recording: bool,
    /// The open segment (the last one, once stopped).
    pub segment: Option<PathBuf>,
    /// Bytes written to it so far.
    pub segment_bytes: u64,
    /// Segments begun.
    pub segments: u64,
    /// Older recordings deleted for the quota and the floor.
    pub deleted: u64,
    /// Free bytes on the recording's file system at the last check.
    pub free_bytes: Option<u64>,
    /// Why the recording stopped by itself (the floor), until it starts again.
    pub stopped: Option<String>,
}

#[derive(Default)]
struct ControlInner {
    /// Asked to stop (the web page's button); cleared by a start.
    stop: AtomicBool,
    bytes: AtomicU64,
    state: Mutex<RecordingState>,
}

/// Starts and stops a file recording while the run goes on (each start begins a new
/// segment), and tells where it stands. The loop reads one flag per frame; the writer
/// thread does the rest.
#[derive(Clone, Default)]
pub struct RecordControl(Arc<ControlInner>);

impl RecordControl {
    /// Record again from the next frame, into a new segment.
    pub fn start(&self) {
        self.0.stop.store(false, Ordering::Relaxed);
    }

    /// Close the open segment (complete) and record nothing until [`Self::start`].
    pub fn stop(&self) {
        self.0.stop.store(true, Ordering::Relaxed);
    }

    /// Frames are wanted in the file.
    pub fn wanted(&self) -> bool {
        !self.0.stop.load(Ordering::Relaxed)
    }

    pub fn state(&self) -> RecordingState {
        let mut s = self.lock().clone();
        if s.recording {
            s.segment_bytes = self.0.bytes.load(Ordering::Relaxed);
        }
        s
    }

    pub(super) fn add_bytes(&self, n: u64) {
        self.0.bytes.fetch_add(n, Ordering::Relaxed);
    }

    fn lock(&self) -> MutexGuard<'_, RecordingState> {
        // Plain assignments under the lock: what a panicking holder left is consistent.
        self.0.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Wrap `writer` as an MCAP segment on `context`'s channels, with the run's metadata
/// (`replay` needs nothing but the file, also for a later segment).
pub(super) fn open_segment<W: Write + Seek + Send + 'static>(
    context: &Arc<Context>,
    writer: W,
    shared: &Arc<Shared>,
    metadata: &BTreeMap<String, String>,
    cfg: &RotationConfig,
) -> Result<McapWriterHandle<Tracked<W>>, RecordError> {
    let options = McapWriteOptions::default().chunk_size(Some(cfg.chunk_bytes()));
    shared.control.0.bytes.store(0, Ordering::Relaxed);
    let handle = McapWriter::with_options(options)
        .context(context)
        .create(Tracked {
            inner: writer,
            shared: shared.clone(),
        })
        .map_err(|source| RecordError::Writer { source })?;
    handle
        .write_metadata(METADATA_NAME, metadata.clone())
        .map_err(|source| RecordError::Writer { source })?;
    Ok(handle)
}

type OpenFn<W> = dyn FnMut(
        &Arc<Context>,
        &Arc<Shared>,
        u32,
    ) -> Result<Option<(PathBuf, McapWriterHandle<Tracked<W>>)>, RecordError>
    + Send;

/// A recording's first segment and the way to the next ones (none: it is the only one).
pub(super) type Output<W> = (McapWriterHandle<Tracked<W>>, Option<Opener<W>>);

/// Opens segment `n` of a file recording (`None`: its name is taken, try the next).
pub(super) struct Opener<W: Write + Seek + Send + 'static> {
    first: PathBuf,
    dir: PathBuf,
    open: Box<OpenFn<W>>,
}

/// The segments after `first` of a file recording: `<stem>.<n>.mcap` beside it, each
/// with the run's metadata and its number (`segment`).
pub(super) fn file_opener(
    first: &Path,
    info: &RunInfo,
    cfg: &RotationConfig,
) -> Opener<BufWriter<File>> {
    let names = SegmentNames::new(first);
    let metadata = info.to_metadata();
    let cfg = *cfg;
    Opener {
        first: first.to_path_buf(),
        dir: names.dir().to_path_buf(),
        open: Box::new(move |context, shared, n| {
            let path = names.path(n);
            let file = match File::create_new(&path) {
                Ok(f) => f,
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => return Ok(None),
                Err(source) => return Err(RecordError::Create { path, source }),
            };
            let mut meta = metadata.clone();
            meta.insert("segment".into(), n.to_string());
            let writer = BufWriter::with_capacity(1 << 20, file);
            match open_segment(context, writer, shared, &meta, &cfg) {
                Ok(h) => Ok(Some((path, h))),
                Err(e) => {
                    let _ = std::fs::remove_file(&path);
                    Err(e)
                }
            }
        }),
    }
}

/// The writer thread's output: the open segment, and for a file recording the way to the
/// next one, the quota and the floor.
pub(super) struct SegmentWriter<W: Write + Seek + Send + 'static> {
    handle: Option<McapWriterHandle<Tracked<W>>>,
    next: Option<Opener<W>>,
    context: Arc<Context>,
    shared: Arc<Shared>,
    cfg: RotationConfig,
    /// Number of the open (or last) segment.
    index: u32,
    /// Frame time of the open segment's first frame, ns.
    first_ns: Option<u64>,
    /// The folder's other recordings at the last look, bytes (for the quota).
    others_bytes: u64,
    /// Segment bytes at the last free-space check.
    checked_at: u64,
    /// The first error closing a segment.
    result: Result<(), RecordError>,
}

impl<W: Write + Seek + Send + 'static> SegmentWriter<W> {
    pub(super) fn new(
        handle: McapWriterHandle<Tracked<W>>,
        next: Option<Opener<W>>,
        context: Arc<Context>,
        shared: &Arc<Shared>,
        cfg: RotationConfig,
    ) -> Self {
        let mut w = Self {
            handle: Some(handle),
            context,
            shared: shared.clone(),
            cfg,
            index: 0,
            first_ns: None,
            others_bytes: 0,
            checked_at: 0,
            result: Ok(()),
            next: None,
        };
        {
            let mut st = w.shared.control.lock();
            st.recording = true;
            st.segments = 1;
            st.segment = next.as_ref().map(|o| o.first.clone());
        }
        w.next = next;
        // Room for the first segment: older recordings go first, else it stops at once.
        if !w.make_room(0) {
            w.close();
        }
        w
    }

    fn rotating(&self) -> bool {
        self.next.is_some()
    }

    /// Before a frame's messages: close or open a segment as the controls say.
    pub(super) fn before_frame(&mut self, stamp_ns: u64) {
        let wanted = self.shared.control.wanted();
        if !wanted && self.handle.is_some() {
            self.close();
        } else if wanted && self.handle.is_none() && self.rotating() {
            self.open_next();
        }
        if self.handle.is_some() && self.first_ns.is_none() {
            self.first_ns = Some(stamp_ns);
        }
    }

    /// After a frame's messages: a full segment is closed (the next opens with the next
    /// frame), and the quota and floor are kept.
    pub(super) fn after_frame(&mut self, stamp_ns: u64) {
        if self.handle.is_none() || !self.rotating() {
            return;
        }
        let bytes = self.shared.control.0.bytes.load(Ordering::Relaxed);
        let span = stamp_ns.saturating_sub(self.first_ns.unwrap_or(stamp_ns));
        if self.cfg.segment_full(bytes, span) {
            self.close();
            // Rotation, not a stop: the next segment opens with the next frame.
            let _ = self.make_room(0);
            return;
        }
        let over_quota = self
            .cfg
            .quota_bytes
            .is_some_and(|q| self.others_bytes + bytes > q);
        if over_quota || bytes - self.checked_at.min(bytes) >= self.cfg.chunk_bytes() {
            // A statvfs per chunk; the folder is listed only when something must go.
            self.checked_at = bytes;
            let low = self
                .next
                .as_ref()
                .and_then(|n| free_bytes(&n.dir).ok())
                .is_some_and(|f| {
                    self.shared.control.lock().free_bytes = Some(f);
                    f < self.cfg.min_free_bytes
                });
            if (over_quota || low) && !self.make_room(bytes) {
                self.close();
            }
        }
    }

    /// No frame for a while: a stop still closes the file.
    pub(super) fn idle(&mut self) {
        if !self.shared.control.wanted() && self.handle.is_some() {
            self.close();
        }
    }

    /// Keep the quota and the floor with `open_bytes` in the open segment; false when the
    /// floor cannot be met (the recording stops and says why).
    fn make_room(&mut self, open_bytes: u64) -> bool {
        let Some(next) = &self.next else { return true };
        let open = self.handle.as_ref().map(|_| self.open_path());
        let dir = next.dir.clone();
        match enforce(
            &dir,
            open.as_deref(),
            open_bytes,
            &self.cfg,
            &mut free_bytes,
        ) {
            Ok(e) => {
                self.others_bytes = e.total_bytes.saturating_sub(open_bytes);
                let mut st = self.shared.control.lock();
                st.deleted += e.deleted.len() as u64;
                st.free_bytes = Some(e.free_bytes);
                if e.below_floor {
                    let why = format!(
                        "{:.0} MB free on the file system of {}, below record.rotation.min_free_mb                          = {:.0}, and no older recording left to delete: recording stopped",
                        e.free_bytes as f64 / MB,
                        dir.display(),
                        self.cfg.min_free_bytes as f64 / MB
                    );
                    tracing::error!("{why}");
                    st.stopped = Some(why);
                    drop(st);
                    self.shared.control.stop();
                    return false;
                }
                true
            }
            Err(e) => {
                tracing::warn!(
                    "recording: cannot keep the quota and floor in {}: {e}",
                    dir.display()
                );
                true
            }
        }
    }

    fn open_path(&self) -> PathBuf {
        self.shared
            .control
            .lock()
            .segment
            .clone()
            .unwrap_or_default()
    }

    fn open_next(&mut self) {
        if !self.make_room(0) {
            return;
        }
        let Some(next) = self.next.as_mut() else {
            return;
        };
        for _ in 0..NAME_TRIES {
            self.index += 1;
            match (next.open)(&self.context, &self.shared, self.index) {
                Ok(Some((path, handle))) => {
                    tracing::info!("recording: segment {}", path.display());
                    self.handle = Some(handle);
                    self.first_ns = None;
                    self.checked_at = 0;
                    let mut st = self.shared.control.lock();
                    st.recording = true;
                    st.segment = Some(path);
                    st.segments += 1;
                    st.stopped = None;
                    return;
                }
                Ok(None) => continue,
                Err(e) => {
                    self.shared.report_error(&e);
                    self.shared.control.stop();
                    return;
                }
            }
        }
        self.shared.report_error(&format!(
            "no free name for a recording segment after {NAME_TRIES} tries"
        ));
        self.shared.control.stop();
    }

    /// Finalize the open segment (summary and footer): a complete MCAP file.
    fn close(&mut self) {
        let Some(handle) = self.handle.take() else {
            return;
        };
        let closed = match handle.close() {
            Ok(mut inner) => inner.flush().map_err(|e| RecordError::Write {
                reason: e.to_string(),
            }),
            Err(e) => Err(RecordError::Write {
                reason: e.to_string(),
            }),
        };
        if let Err(e) = closed {
            self.shared.report_error(&e);
            if self.result.is_ok() {
                self.result = Err(e);
            }
        }
        let mut st = self.shared.control.lock();
        st.recording = false;
        st.segment_bytes = self.shared.control.0.bytes.load(Ordering::Relaxed);
    }

    pub(super) fn finish(mut self) -> Result<(), RecordError> {
        self.close();
        self.result
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;
    use std::time::Duration;

    fn scratch(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("markhold-rotation-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A fake recording of `bytes` bytes modified `age_s` seconds ago.
    fn recording(dir: &Path, name: &str, bytes: usize, age_s: u64) -> PathBuf {
        let p = dir.join(name);
        let mut data = MCAP_MAGIC.to_vec();
        data.resize(bytes.max(8), 0);
        std::fs::write(&p, data).unwrap();
        let t = SystemTime::now() - Duration::from_secs(age_s);
        std::fs::File::options()
            .write(true)
            .open(&p)
            .unwrap()
            .set_modified(t)
            .unwrap();
        p
    }

    #[test]
    fn oldest_recordings_go_first_and_never_the_open_one_or_other_files() {
        let d = scratch("quota");
        let old = recording(&d, "a.mcap", 400, 300);
        let mid = recording(&d, "b.mcap", 400, 200);
        let open = recording(&d, "c.mcap", 400, 100);
        let notes = d.join("notes.mcap");
        std::fs::write(&notes, vec![b'x'; 4000]).unwrap();
        let other = d.join("site.toml");
        std::fs::write(&other, vec![b'x'; 4000]).unwrap();
        let cfg = RotationConfig {
            segment_bytes: 400,
            segment_ns: None,
            quota_bytes: Some(900),
            min_free_bytes: 0,
        };
        let out = enforce(&d, Some(&open), 400, &cfg, &mut |_| Ok(u64::MAX)).unwrap();
        assert_eq!(out.deleted, vec![old.clone()]);
        assert_eq!(out.total_bytes, 800);
        assert!(!old.exists() && mid.exists() && open.exists());
        assert!(notes.exists() && other.exists(), "not recordings: kept");
        // A quota below the open segment alone: everything else goes, never the open one.
        let tight = RotationConfig {
            quota_bytes: Some(100),
            ..cfg
        };
        let out = enforce(&d, Some(&open), 400, &tight, &mut |_| Ok(u64::MAX)).unwrap();
        assert_eq!(out.deleted, vec![mid]);
        assert!(open.exists());
    }

    #[test]
    fn the_floor_deletes_until_met_and_says_when_it_cannot_be() {
        let d = scratch("floor");
        let a = recording(&d, "a.mcap", 1000, 30);
        let b = recording(&d, "b.mcap", 1000, 20);
        let open = d.join("c.mcap");
        let cfg = RotationConfig {
            segment_bytes: 1000,
            segment_ns: None,
            quota_bytes: None,
            min_free_bytes: 1500,
        };
        // A disk with 600 bytes free plus what was deleted.
        let mut disk = |dir: &Path| -> std::io::Result<u64> {
            let left: u64 = std::fs::read_dir(dir)?
                .filter_map(|e| e.ok()?.metadata().ok())
                .map(|m| m.len())
                .sum();
            Ok(600 + 2000 - left)
        };
        let out = enforce(&d, Some(&open), 0, &cfg, &mut disk).unwrap();
        assert_eq!(out.deleted, vec![a]);
        assert!(!out.below_floor && b.exists());
        let higher = RotationConfig {
            min_free_bytes: 10_000,
            ..cfg
        };
        let out = enforce(&d, Some(&open), 0, &higher, &mut disk).unwrap();
        assert_eq!(out.deleted, vec![b]);
        assert!(out.below_floor, "nothing left to delete: {out:?}");
    }

    #[test]
    fn segment_names_and_limits() {
        let n = SegmentNames::new(Path::new("/data/rec/markhold-1.mcap"));
        assert_eq!(n.path(0), Path::new("/data/rec/markhold-1.mcap"));
        assert_eq!(n.path(2), Path::new("/data/rec/markhold-1.2.mcap"));
        assert_eq!(
            SegmentNames::new(Path::new("x.mcap")).path(1),
            Path::new("./x.1.mcap")
        );
        let c = RotationSection {
            segment_mb: 2.0,
            segment_s: Some(60.0),
            quota_mb: Some(10.0),
            min_free_mb: 1.0,
        }
        .config();
        assert_eq!(c.segment_bytes, 2_000_000);
        assert_eq!(c.quota_bytes, Some(10_000_000));
        assert!(c.segment_full(2_000_000, 0));
        assert!(c.segment_full(10, 60_000_000_000));
        assert!(!c.segment_full(1_999_999, 59_999_999_999));
        assert_eq!(c.chunk_bytes(), 500_000);
        assert!(free_bytes(Path::new(".")).is_ok());
    }

    #[test]
    fn a_quota_smaller_than_two_segments_names_the_key() {
        let bad = RotationSection {
            quota_mb: Some(1500.0),
            ..RotationSection::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(
            e.contains("record.rotation.quota_mb") && e.contains("1500"),
            "{e}"
        );
        assert!(RotationSection::default().validate().is_ok());
    }
}
