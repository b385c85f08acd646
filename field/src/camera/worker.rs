//! The exposure control off the loop's thread.
//!
//! The loop states what it wants — take the camera or leave it as found, and the
//! exposure while taken — in a one-slot mailbox: a newer request replaces an older one
//! not yet sent (the newest exposure wins), and a request never waits on the network.
//! A worker thread brings the camera to that state through the blocking
//! [`ExposureControl`] (each request bounded by its own deadline) and reports what is in
//! force, which the stream camera uses to attribute frames. While a request fails the
//! worker waits a second before the next try; the camera keeps its last value.
//!
//! Taking the camera first writes a state file beside the site (the mode and value
//! found); putting it back removes the file. A file left by a run that died holding the
//! camera is put back at the next start ([`recover`]).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::control::{ControlError, ExposureControl, Found};

/// After a failed request, how long the worker waits before the next one.
pub const RETRY_AFTER: Duration = Duration::from_secs(1);
/// The largest state file read.
const MAX_STATE_BYTES: u64 = 64 << 10;

/// What the loop asks for.
#[derive(Debug, Clone, Copy)]
struct Target {
    take: bool,
    exposure_us: f64,
    finish: bool,
    /// Bumped on every change.
    gen: u64,
}

/// What the worker reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Applied {
    /// The camera is markhold's (manual exposure, set by markhold).
    pub taken: bool,
    /// The exposure in force, microseconds (NaN: unknown, the camera's own auto).
    pub exposure_us: f64,
    /// Bumped whenever `taken` or `exposure_us` changes.
    pub seq: u64,
    /// Requests that failed.
    pub errors: u64,
}

struct State {
    target: Target,
    applied: Applied,
    /// The target generation the camera matches.
    done_gen: u64,
    finished: bool,
    last_error: Option<String>,
}

struct Shared {
    m: Mutex<State>,
    cv: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.m
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Waits at most `timeout` while `busy` holds (spurious wake-ups included).
    fn wait_while<'a>(
        &self,
        s: MutexGuard<'a, State>,
        timeout: Duration,
        busy: impl FnMut(&mut State) -> bool,
    ) -> MutexGuard<'a, State> {
        self.cv
            .wait_timeout_while(s, timeout, busy)
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .0
    }
}

/// The state file: which control, and what it had before markhold took it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StateRecord {
    pub control: String,
    pub found: Found,
}

/// Where the state file of a site lives: `<site file>.camera-state.json` beside it.
pub fn state_path(site: &Path) -> PathBuf {
    let mut name = site
        .file_name()
        .map_or_else(|| "site".into(), std::ffi::OsStr::to_os_string);
    name.push(".camera-state.json");
    site.with_file_name(name)
}

fn write_state(path: &Path, rec: &StateRecord) -> std::io::Result<()> {
    let text = serde_json::to_string_pretty(rec).map_err(std::io::Error::other)?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, path)
}

/// A state file left behind by a run that died holding the camera, if any.
fn read_state(path: &Path) -> Result<Option<StateRecord>, String> {
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("{}: {e}", path.display())),
    };
    if !meta.is_file() || meta.len() > MAX_STATE_BYTES {
        return Err(format!(
            "{}: not a regular file of at most {MAX_STATE_BYTES} bytes",
            path.display()
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|e| format!("{}: {e}", path.display()))
}

/// At start-up: a state file for this control means the last run died holding the
/// camera: put back what it found, remove the file, and return that as what was found
/// (the camera's present state is the dead run's). Otherwise the control's own reading.
pub fn recover(
    control: &mut dyn ExposureControl,
    state_file: Option<&Path>,
) -> Result<Option<Found>, String> {
    let Some(path) = state_file else {
        return Ok(control.found());
    };
    let Some(rec) = read_state(path)? else {
        return Ok(control.found());
    };
    if rec.control != control.describe() {
        tracing::warn!(
            "{}: left for {}, not this camera ({}): ignored",
            path.display(),
            rec.control,
            control.describe()
        );
        return Ok(control.found());
    }
    control
        .restore_to(&rec.found)
        .map_err(|e| format!("putting back the camera a stopped run left ({e})"))?;
    std::fs::remove_file(path).map_err(|e| format!("{}: {e}", path.display()))?;
    eprintln!(
        "markhold: the last run stopped holding the camera ({}): its exposure is put back \
         (auto_exposure {:?}, exposure_time_absolute {})",
        rec.control, rec.found.auto_exposure, rec.found.exposure_units
    );
    Ok(Some(rec.found))
}

/// The loop's side of the exposure control (cloned wherever it is needed).
#[derive(Clone)]
pub struct ControlHandle {
    shared: Arc<Shared>,
    describe: Arc<str>,
    step_us: f64,
}

impl ControlHandle {
    /// Starts the worker for `control`, which found `found` (the camera is not touched
    /// until taken). `state_file`: where taking it is recorded.
    pub fn spawn(
        control: Box<dyn ExposureControl>,
        found: Option<Found>,
        state_file: Option<PathBuf>,
    ) -> std::io::Result<Self> {
        let known = found.map_or(f64::NAN, |f| f.known_us());
        let shared = Arc::new(Shared {
            m: Mutex::new(State {
                target: Target {
                    take: false,
                    exposure_us: f64::NAN,
                    finish: false,
                    gen: 0,
                },
                applied: Applied {
                    taken: false,
                    exposure_us: if control.controls() { known } else { f64::NAN },
                    seq: 0,
                    errors: 0,
                },
                done_gen: 0,
                finished: false,
                last_error: None,
            }),
            cv: Condvar::new(),
        });
        let describe: Arc<str> = control.describe().into();
        let step_us = control.step_us();
        let worker = Worker {
            shared: shared.clone(),
            control,
            found,
            state_file,
            taken: false,
            current_us: f64::NAN,
        };
        std::thread::Builder::new()
            .name("markhold-exposure".into())
            .spawn(move || worker.run())?;
        Ok(Self {
            shared,
            describe,
            step_us,
        })
    }

    /// A handle whose commands change nothing (exposure left to the camera).
    pub fn none() -> std::io::Result<Self> {
        Self::spawn(Box::new(super::control::NoControl), None, None)
    }

    /// The camera's exposure step, microseconds (0: continuous).
    pub fn step_us(&self) -> f64 {
        self.step_us
    }

    /// Where the commands go.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// The exposure markhold wants while it holds the camera (the newest wins).
    pub fn request(&self, exposure_us: f64) {
        let mut s = self.shared.lock();
        if s.target.exposure_us.to_bits() != exposure_us.to_bits() {
            s.target.exposure_us = exposure_us;
            s.target.gen += 1;
            self.shared.cv.notify_all();
        }
    }

    /// Take the camera (manual exposure, markhold's values) or leave it as found.
    pub fn set_take(&self, take: bool) {
        let mut s = self.shared.lock();
        if s.target.take != take && !s.target.finish {
            s.target.take = take;
            s.target.gen += 1;
            self.shared.cv.notify_all();
        }
    }

    /// Whether markhold asked to hold the camera.
    pub fn wants_taken(&self) -> bool {
        self.shared.lock().target.take
    }

    /// What is in force.
    pub fn applied(&self) -> Applied {
        self.shared.lock().applied
    }

    /// The last failure, if the latest request failed.
    pub fn last_error(&self) -> Option<String> {
        self.shared.lock().last_error.clone()
    }

    /// Waits (at most `timeout`) until the camera matches the latest request. True if it
    /// does. For lock-step simulation only: the loop never waits on the camera.
    pub fn settle(&self, timeout: Duration) -> bool {
        let busy = |s: &mut State| s.done_gen != s.target.gen && !s.finished;
        let mut s = self.shared.wait_while(self.shared.lock(), timeout, busy);
        !busy(&mut s)
    }

    /// Leave the camera as found and stop the worker, waiting at most `timeout`. An
    /// error says why the camera could not be put back (the state file stays for the
    /// next start).
    pub fn finish(&self, timeout: Duration) -> Result<(), String> {
        let mut s = self.shared.lock();
        if !s.target.finish {
            s.target.take = false;
            s.target.finish = true;
            s.target.gen += 1;
            self.shared.cv.notify_all();
        }
        let s = self.shared.wait_while(s, timeout, |s| !s.finished);
        if s.finished {
            return Ok(());
        }
        Err(format!(
            "the camera ({}) was not put back within {} s{}",
            self.describe,
            timeout.as_secs_f64(),
            s.last_error
                .as_ref()
                .map_or(String::new(), |e| format!(": {e}"))
        ))
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let mut s = self.shared.lock();
        s.finished = true;
        self.shared.cv.notify_all();
    }
}

struct Worker {
    shared: Arc<Shared>,
    control: Box<dyn ExposureControl>,
    found: Option<Found>,
    state_file: Option<PathBuf>,
    taken: bool,
    /// The value set while taken (NaN until the first).
    current_us: f64,
}

impl Worker {
    fn run(mut self) {
        let mut failing = false;
        loop {
            let target = {
                let mut s = self.shared.lock();
                while s.done_gen == s.target.gen {
                    if s.target.finish && !self.taken {
                        return;
                    }
                    s = self
                        .shared
                        .cv
                        .wait(s)
                        .unwrap_or_else(std::sync::PoisonError::into_inner);
                }
                s.target
            };
            let result = self.reconcile(&target);
            let mut s = self.shared.lock();
            let before = (s.applied.taken, s.applied.exposure_us.to_bits());
            s.applied.taken = self.taken;
            s.applied.exposure_us = self.known_us();
            if (s.applied.taken, s.applied.exposure_us.to_bits()) != before {
                s.applied.seq += 1;
            }
            match result {
                Ok(()) => {
                    s.done_gen = target.gen;
                    s.last_error = None;
                    if failing {
                        tracing::warn!(
                            "exposure control {}: working again",
                            self.control.describe()
                        );
                    }
                    failing = false;
                    self.shared.cv.notify_all();
                    if target.finish && !self.taken {
                        return;
                    }
                }
                Err(e) => {
                    s.applied.errors += 1;
                    if !failing {
                        tracing::warn!(
                            "{e}; keeping the camera's exposure as it is, retrying every {} s",
                            RETRY_AFTER.as_secs()
                        );
                    }
                    failing = true;
                    s.last_error = Some(e);
                    self.shared.cv.notify_all();
                    // Wait before the next try; a finish request cuts the wait short.
                    s = self
                        .shared
                        .wait_while(s, RETRY_AFTER, |s| !s.target.finish || target.finish);
                }
            }
        }
    }

    /// The exposure in force as far as markhold knows.
    fn known_us(&self) -> f64 {
        if !self.control.controls() {
            return f64::NAN;
        }
        match (self.taken, self.found) {
            (true, _) => self.current_us,
            (false, Some(f)) => f.known_us(),
            (false, None) => f64::NAN,
        }
    }

    /// Brings the camera to `target`.
    fn reconcile(&mut self, target: &Target) -> Result<(), String> {
        let err = |e: ControlError| e.to_string();
        if target.take && !self.taken {
            if let (Some(path), Some(found)) = (&self.state_file, self.found) {
                let rec = StateRecord {
                    control: self.control.describe(),
                    found,
                };
                if let Err(e) = write_state(path, &rec) {
                    // The camera is still put back at a normal exit; only a crash
                    // would leave it.
                    tracing::warn!(
                        "{}: {e}: a run that dies now leaves the camera in manual exposure",
                        path.display()
                    );
                }
            }
            self.control.take().map_err(err)?;
            self.taken = true;
            self.current_us = f64::NAN;
        }
        if target.take && target.exposure_us.is_finite() {
            self.current_us = self
                .control
                .set_exposure_us(target.exposure_us)
                .map_err(err)?;
        }
        if !target.take && self.taken {
            if let Some(found) = self.found {
                self.control.restore_to(&found).map_err(err)?;
            }
            self.taken = false;
            if let Some(path) = &self.state_file {
                if let Err(e) = std::fs::remove_file(path) {
                    if e.kind() != std::io::ErrorKind::NotFound {
                        tracing::warn!("{}: {e}", path.display());
                    }
                }
            }
        }
        Ok(())
    }
}
