//! MAVLink 2 signing timestamps that survive a restart.
//!
//! A signing timestamp counts 10 microsecond units since 2015-01-01 and must increase on
//! every frame of a link: a receiver drops a frame whose timestamp is not above the last
//! one it accepted on that stream, which is what stops a recorded frame from being
//! replayed. rust-mavlink's `SigningData` starts from the wall clock, so after a restart
//! on a computer whose clock stepped back (no real-time clock before NTP) it would sign
//! with timestamps the vehicle has already seen.
//!
//! The last timestamp used is kept in a state file beside the key (`<key file>.timestamp`,
//! one decimal number), written atomically (temporary file, `fsync`, rename) by a
//! background thread whenever the signing time has moved [`SAVE_EVERY`] past the last
//! save, and once more when the link is dropped. On start the link signs from
//! `max(wall clock, saved + MARGIN)`; [`MARGIN`] exceeds [`SAVE_EVERY`], so a crash between
//! two saves cannot reuse a timestamp.
//!
//! A missing state file is a first start (wall clock). A state file that cannot be read,
//! or does not hold one number, is an error naming the file: the link refuses to start
//! rather than sign with timestamps that may already have been used. The state file is
//! only ever replaced whole, so this happens only when something else wrote it; deleting
//! it restarts from the wall clock.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::thread::JoinHandle;

use mavlink::dialects::ardupilotmega::{MavMessage, HEARTBEAT_DATA};
use mavlink::{MAVLinkV2MessageRaw, MavHeader, SigningConfig, SigningData};

use crate::error::AutopilotError;

/// Ten-microsecond units per second.
pub const UNITS_PER_S: u64 = 100_000;
/// Signing time between two saves of the state file (5 s).
pub const SAVE_EVERY: u64 = 5 * UNITS_PER_S;
/// Added to the saved timestamp on start (10 s, more than [`SAVE_EVERY`]).
pub const MARGIN: u64 = 10 * UNITS_PER_S;
/// Largest state file read (a decimal u64 and a newline fit easily).
const MAX_STATE_BYTES: u64 = 64;
/// The signing timestamp is 48 bits on the wire.
const TIMESTAMP_MAX: u64 = (1 << 48) - 1;

/// The state file of a key file: `<key file>.timestamp`.
pub fn state_path(key_file: &Path) -> PathBuf {
    let mut s = key_file.as_os_str().to_owned();
    s.push(".timestamp");
    PathBuf::from(s)
}

fn state_error(path: &Path, reason: impl Into<String>) -> AutopilotError {
    AutopilotError::SigningTimestamp {
        path: path.display().to_string(),
        reason: reason.into(),
    }
}

/// The saved timestamp, `None` when there is no state file yet.
pub fn read_state(path: &Path) -> Result<Option<u64>, AutopilotError> {
    let meta = match std::fs::metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(state_error(path, e.to_string())),
    };
    if !meta.is_file() {
        return Err(state_error(path, "not a regular file"));
    }
    if meta.len() > MAX_STATE_BYTES {
        return Err(state_error(
            path,
            format!(
                "{} bytes, expected one decimal number (delete the file to restart from the \
                 wall clock)",
                meta.len()
            ),
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| state_error(path, e.to_string()))?;
    let t = text.trim();
    match t.parse::<u64>() {
        Ok(v) if v <= TIMESTAMP_MAX => Ok(Some(v)),
        _ => Err(state_error(
            path,
            format!(
                "expected one decimal number of 10 us units since 2015-01-01, found `{}` \
                 (delete the file to restart from the wall clock)",
                t.escape_debug()
            ),
        )),
    }
}

/// Writes `value` to `path` atomically: `<path>.<pid>.<n>.tmp` (unique, so links of
/// several runs sharing a key never write into each other's file), fsync, rename.
pub fn write_state(path: &Path, value: u64) -> std::io::Result<()> {
    use std::io::Write;
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(format!(
        ".{}.{}.tmp",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    ));
    let tmp = PathBuf::from(tmp);
    {
        let mut f = std::fs::File::create(&tmp)?;
        writeln!(f, "{value}")?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)
}

/// The wall clock as a signing timestamp (0 before 2015).
pub fn wall_clock_timestamp() -> u64 {
    let us = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_micros())
        .unwrap_or(0);
    (us.saturating_sub(1_420_070_400u128 * 1_000_000) / 10) as u64
}

/// The first timestamp to sign with: `max(wall, saved + MARGIN)`.
pub fn start_timestamp(wall: u64, saved: Option<u64>) -> u64 {
    match saved {
        Some(s) => wall.max(s.saturating_add(MARGIN).min(TIMESTAMP_MAX)),
        None => wall,
    }
}

/// `SigningData` for `key` whose next signed frame carries a timestamp of at least
/// `start`.
///
/// rust-mavlink has no setter for the signing state's timestamp; it raises it to the
/// timestamp of every frame whose signature verifies. So a frame signed with `key` at
/// `start` is verified once here. Its stream is (link id, system 0, component 0): system
/// id 0 is broadcast and never a sender, so no real stream is affected.
pub fn signing_data_from(key: [u8; 32], link_id: u8, start: u64) -> SigningData {
    let sd = SigningData::from_config(SigningConfig::new(key, link_id, true, false));
    let mut raw = MAVLinkV2MessageRaw::new();
    let header = MavHeader {
        system_id: 0,
        component_id: 0,
        sequence: 0,
    };
    raw.serialize_message_for_signing(header, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()));
    *raw.signature_link_id_mut() = link_id;
    let start = start.min(TIMESTAMP_MAX);
    raw.signature_timestamp_bytes_mut()
        .copy_from_slice(&start.to_le_bytes()[..6]);
    let mut sig = [0u8; 6];
    raw.calculate_signature(&key, &mut sig);
    raw.signature_value_mut().copy_from_slice(&sig);
    let accepted = sd.verify_signature(&raw);
    debug_assert!(accepted, "a frame signed with our own key verifies");
    sd
}

/// The timestamp a signed frame carries (its last 13 bytes are link id, 6-byte
/// timestamp, 6-byte signature); `None` for a frame too short to be signed.
pub fn frame_timestamp(frame: &[u8]) -> Option<u64> {
    let n = frame.len();
    if n < 13 + 12 {
        return None;
    }
    let mut b = [0u8; 8];
    b[..6].copy_from_slice(&frame[n - 12..n - 6]);
    Some(u64::from_le_bytes(b))
}

/// Keeps the state file up to date from the timestamps of the frames the link signs.
pub struct TimestampKeeper {
    path: PathBuf,
    last_used: u64,
    last_saved: u64,
    tx: Option<SyncSender<u64>>,
    worker: Option<JoinHandle<()>>,
}

impl TimestampKeeper {
    /// Reads the state file beside `key_file` and returns the keeper and the start
    /// timestamp (`max(wall clock, saved + MARGIN)`). The start is saved at once, so a
    /// state file that cannot be written is reported before the first frame.
    pub fn open(key_file: &Path) -> Result<(Self, u64), AutopilotError> {
        let path = state_path(key_file);
        let saved = read_state(&path)?;
        let start = start_timestamp(wall_clock_timestamp(), saved);
        write_state(&path, start).map_err(|e| state_error(&path, e.to_string()))?;
        let (tx, rx) = sync_channel::<u64>(1);
        let p = path.clone();
        let worker = std::thread::Builder::new()
            .name("signing-timestamp".into())
            .spawn(move || {
                let mut failing = false;
                while let Ok(v) = rx.recv() {
                    match write_state(&p, v) {
                        Ok(()) => failing = false,
                        Err(e) if !failing => {
                            failing = true;
                            tracing::warn!(file = %p.display(), error = %e,
                                "cannot save the signing timestamp");
                        }
                        Err(_) => {}
                    }
                }
            })
            .map_err(|e| state_error(&path, e.to_string()))?;
        Ok((
            Self {
                path,
                last_used: start,
                last_saved: start,
                tx: Some(tx),
                worker: Some(worker),
            },
            start,
        ))
    }

    /// The state file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Notes a signed frame just written; hands a save to the writer thread when the
    /// signing time moved [`SAVE_EVERY`] past the last save (never waits: a save the
    /// thread cannot take yet is retried on the next frame).
    pub fn used(&mut self, frame: &[u8]) {
        let Some(ts) = frame_timestamp(frame) else {
            return;
        };
        self.last_used = self.last_used.max(ts);
        if self.last_used >= self.last_saved.saturating_add(SAVE_EVERY) {
            if let Some(tx) = &self.tx {
                match tx.try_send(self.last_used) {
                    Ok(()) => self.last_saved = self.last_used,
                    Err(TrySendError::Full(_)) => {}
                    Err(TrySendError::Disconnected(_)) => self.tx = None,
                }
            }
        }
    }
}

impl Drop for TimestampKeeper {
    /// Saves the last timestamp used, after any save still queued.
    fn drop(&mut self) {
        if let Some(tx) = self.tx.take() {
            let _ = tx.send(self.last_used);
        }
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_key(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "markhold-signing-clock-{}-{name}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let key = dir.join("vehicle.key");
        std::fs::write(&key, [7u8; 32]).expect("key");
        let _ = std::fs::remove_file(state_path(&key));
        key
    }

    fn sign_one(sd: &SigningData) -> Vec<u8> {
        let mut buf = [0u8; 300];
        let mut cur = std::io::Cursor::new(&mut buf[..]);
        let header = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        };
        let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        let n = mavlink::write_v2_msg_signed(&mut cur, header, &msg, Some(sd)).expect("sign");
        buf[..n].to_vec()
    }

    #[test]
    fn the_start_after_a_saved_future_timestamp_is_above_it() {
        let key = temp_key("future");
        let future = wall_clock_timestamp() + 1000 * UNITS_PER_S;
        write_state(&state_path(&key), future).expect("state");
        let (keeper, start) = TimestampKeeper::open(&key).expect("open");
        assert!(start > future, "start {start} not above saved {future}");
        assert_eq!(start, future + MARGIN);
        let sd = signing_data_from([7u8; 32], 1, start);
        let frame = sign_one(&sd);
        let ts = frame_timestamp(&frame).expect("signed");
        assert!(ts >= start && ts > future, "first frame signed at {ts}");
        drop(keeper);
    }

    #[test]
    fn the_last_timestamp_is_saved_at_drop_and_the_next_start_is_above_it() {
        let key = temp_key("restart");
        let (mut keeper, start) = TimestampKeeper::open(&key).expect("open");
        let sd = signing_data_from([7u8; 32], 1, start);
        let mut last = 0;
        for _ in 0..50 {
            let f = sign_one(&sd);
            last = frame_timestamp(&f).expect("signed");
            keeper.used(&f);
        }
        drop(keeper);
        let saved = read_state(&state_path(&key)).expect("read").expect("saved");
        assert_eq!(saved, last);
        assert!(start_timestamp(0, Some(saved)) > last);
    }

    #[test]
    fn a_corrupt_state_file_is_an_error_naming_it() {
        let key = temp_key("corrupt");
        let p = state_path(&key);
        std::fs::write(&p, "twelve\n").expect("write");
        let e = TimestampKeeper::open(&key)
            .err()
            .expect("refused")
            .to_string();
        assert!(
            e.contains(&p.display().to_string()) && e.contains("twelve"),
            "{e}"
        );
        std::fs::write(&p, [b'1'; 100]).expect("write");
        let e = TimestampKeeper::open(&key)
            .err()
            .expect("refused")
            .to_string();
        assert!(e.contains("100 bytes"), "{e}");
    }

    #[test]
    fn no_state_file_starts_from_the_wall_clock() {
        assert_eq!(start_timestamp(1234, None), 1234);
        assert_eq!(start_timestamp(5 * MARGIN, Some(1)), 5 * MARGIN);
        let key = temp_key("fresh");
        let (_k, start) = TimestampKeeper::open(&key).expect("open");
        assert!(start > 0);
        assert_eq!(read_state(&state_path(&key)).expect("read"), Some(start));
    }
}
