//! Ctrl-C and SIGTERM for `markhold run` and `markhold hil`: the first sets a flag the loop reads once per
//! frame (it then sends neutral input, closes the recording and exits 0); a second one
//! ends the process at once, for a loop stuck waiting on a camera.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

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

/// Set once a shutdown was asked for.
#[derive(Debug, Clone, Default)]
pub struct ShutdownFlag(Arc<AtomicBool>);

impl ShutdownFlag {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
    pub fn set(&self) {
        self.0.store(true, Ordering::Relaxed);
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
