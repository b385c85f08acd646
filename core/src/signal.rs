//! Ctrl-C and SIGTERM for `markhold run` and `markhold hil`: the first sets a flag the loop reads once per
//! frame (it then sends neutral input, closes the recording and exits 0); a second one
//! ends the process at once. The first also starts a watchdog: if the process is still
//! there [`EXIT_GRACE`] later (a peer holding a thread, a driver call that never
//! returns), it ends it (exit 130). The orderly exit, once under way, extends that by
//! its own bounded duration ([`ShutdownFlag::allow_exit_within`]).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Debug, thiserror::Error)]
pub enum SignalError {
    #[error("installing the Ctrl-C / SIGTERM handler: {source}")]
    Install { source: std::io::Error },
    #[error("the signal thread stopped before its handlers were installed")]
    Thread,
}

/// Exit status of a second signal while the first is being handled (128 + SIGINT).
pub const FORCED_EXIT: i32 = 130;

/// Exit status of `hil` stopped by Ctrl-C or SIGTERM (the run's recording and summary
/// are complete up to the stop; 128 + SIGINT, as a shell reports an interrupted command).
pub const INTERRUPTED_EXIT: i32 = 130;

/// How long after the first signal the process may take to notice it and start its
/// orderly exit before the watchdog ends it.
pub const EXIT_GRACE: Duration = Duration::from_secs(10);

#[derive(Debug)]
struct Inner {
    set: AtomicBool,
    epoch: Instant,
    /// Milliseconds after `epoch` when the watchdog ends the process (0: not armed).
    deadline_ms: AtomicU64,
}

impl Default for Inner {
    fn default() -> Self {
        Self {
            set: AtomicBool::new(false),
            epoch: Instant::now(),
            deadline_ms: AtomicU64::new(0),
        }
    }
}

/// Set once a shutdown was asked for.
#[derive(Debug, Clone, Default)]
pub struct ShutdownFlag(Arc<Inner>);

impl ShutdownFlag {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn is_set(&self) -> bool {
        self.0.set.load(Ordering::Relaxed)
    }
    pub fn set(&self) {
        self.0.set.store(true, Ordering::Relaxed);
    }

    fn ms_from_now(&self, d: Duration) -> u64 {
        (self.0.epoch.elapsed() + d).as_millis().max(1) as u64
    }

    /// The orderly exit is under way and takes at most `d`: an armed watchdog waits
    /// that long from now (it never shortens its wait).
    pub fn allow_exit_within(&self, d: Duration) {
        let at = self.ms_from_now(d);
        let _ = self
            .0
            .deadline_ms
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |cur| {
                (cur != 0 && at > cur).then_some(at)
            });
    }

    /// Arms the watchdog: `on_expiry` runs on its thread when `grace` (or a later
    /// deadline set by [`Self::allow_exit_within`]) has passed.
    pub fn start_watchdog(
        &self,
        grace: Duration,
        on_expiry: impl FnOnce() + Send + 'static,
    ) -> std::io::Result<()> {
        let at = self.ms_from_now(grace);
        if self
            .0
            .deadline_ms
            .compare_exchange(0, at, Ordering::Relaxed, Ordering::Relaxed)
            .is_err()
        {
            return Ok(());
        }
        let inner = self.0.clone();
        std::thread::Builder::new()
            .name("markhold-watchdog".into())
            .spawn(move || loop {
                let due = inner.deadline_ms.load(Ordering::Relaxed);
                let now = inner.epoch.elapsed().as_millis() as u64;
                if now >= due {
                    on_expiry();
                    return;
                }
                std::thread::sleep(Duration::from_millis((due - now).min(100)));
            })
            .map(|_| ())
    }
}

/// Install the handlers on a small thread with a current-thread tokio runtime. Returns
/// once they are installed, so a signal sent right after is not missed.
pub fn install() -> Result<ShutdownFlag, SignalError> {
    let flag = ShutdownFlag::new();
    let set = flag.clone();
    let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<Result<(), std::io::Error>>(1);
    std::thread::Builder::new()
        .name("markhold-signals".into())
        .spawn(move || {
            let rt = match tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            {
                Ok(rt) => rt,
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            rt.block_on(async move {
                use tokio::signal::unix::{signal, SignalKind};
                let (mut int, mut term) = match (
                    signal(SignalKind::interrupt()),
                    signal(SignalKind::terminate()),
                ) {
                    (Ok(i), Ok(t)) => (i, t),
                    (Err(e), _) | (_, Err(e)) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                let _ = ready_tx.send(Ok(()));
                let mut seen = 0u32;
                loop {
                    let name = tokio::select! {
                        _ = int.recv() => "SIGINT",
                        _ = term.recv() => "SIGTERM",
                    };
                    seen += 1;
                    if seen == 1 {
                        tracing::warn!("{name}: stopping (neutral input, recording closed)");
                        set.set();
                        let armed = set.start_watchdog(EXIT_GRACE, move || {
                            eprintln!(
                                "markhold: {name}: still running {} s later: exiting now",
                                EXIT_GRACE.as_secs()
                            );
                            std::process::exit(FORCED_EXIT);
                        });
                        if let Err(e) = armed {
                            tracing::warn!("the exit watchdog did not start: {e}");
                        }
                    } else {
                        eprintln!("markhold: {name} again: exiting now");
                        std::process::exit(FORCED_EXIT);
                    }
                }
            });
        })
        .map_err(|source| SignalError::Install { source })?;
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(flag),
        Ok(Err(source)) => Err(SignalError::Install { source }),
        Err(_) => Err(SignalError::Thread),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;

    #[test]
    fn the_watchdog_fires_after_its_grace_and_waits_for_an_orderly_exit() {
        let flag = ShutdownFlag::new();
        let (tx, rx) = mpsc::channel();
        let t0 = Instant::now();
        flag.start_watchdog(Duration::from_millis(100), move || {
            let _ = tx.send(t0.elapsed());
        })
        .unwrap_or_else(|e| panic!("{e}"));
        // The orderly exit says it needs 400 ms: the watchdog waits for it.
        flag.allow_exit_within(Duration::from_millis(400));
        let fired = rx
            .recv_timeout(Duration::from_secs(5))
            .unwrap_or_else(|e| panic!("the watchdog did not fire: {e}"));
        assert!(fired >= Duration::from_millis(400), "{fired:?}");
        // Not armed: extending does not arm it.
        let idle = ShutdownFlag::new();
        idle.allow_exit_within(Duration::from_secs(1));
        assert_eq!(idle.0.deadline_ms.load(Ordering::Relaxed), 0);
    }
}
