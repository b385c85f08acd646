//! Helpers shared by the integration tests: the built binary, paths in the repository,
//! the small fixture site, scratch paths, a WebSocket frame reader for the live view, a
//! hostile HTTP server, the pymavlink vehicle and summaries compared with committed result
//! files (`results.rs`); with the simulator (`sim`), the simulated world as a free-running
//! vehicle (`sim.rs`).
#![allow(dead_code)]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::io::Read;
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

mod results;
// Not every binary compares result files.
#[allow(unused_imports)]
pub use results::*;
#[cfg(feature = "sim")]
mod sim;
// Not every binary uses the simulated world.
#[cfg(feature = "sim")]
#[allow(unused_imports)]
pub use sim::*;

/// The built `markhold` binary.
pub fn markhold() -> Command {
    Command::new(env!("CARGO_BIN_EXE_markhold"))
}

/// `markhold ARGS` run to its end: its exit status and output.
pub fn run_markhold(args: &[&str]) -> Output {
    markhold().args(args).output().unwrap()
}

/// A path in the repository.
pub fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The small test site: 640x480 at 30 fps, in a pool.
pub fn site_path() -> PathBuf {
    repo("tests/fixtures/pool-640.toml")
}

/// `name` in a scratch directory of this test process (`markhold-{prefix}-{pid}`), with
/// no file or folder left there by an earlier run. The tests of a binary share its
/// process: each file uses its own `prefix`, each test its own `name`.
/// Scratch folders of earlier test processes that have ended are removed on first use of a
/// prefix, so runs do not pile recordings up in the temp folder.
pub fn tmp_path(prefix: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("markhold-{prefix}-{}", std::process::id()));
    if !dir.exists() {
        remove_ended_runs(prefix);
    }
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    let _ = std::fs::remove_dir_all(&p);
    let _ = std::fs::remove_file(&p);
    p
}

/// Removes `markhold-{prefix}-{pid}` folders whose process no longer runs (Linux: no
/// `/proc/{pid}`).
fn remove_ended_runs(prefix: &str) {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    let head = format!("markhold-{prefix}-");
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name.to_str().and_then(|n| n.strip_prefix(&head)) else {
            continue;
        };
        if pid.parse::<u32>().is_ok() && !Path::new("/proc").join(pid).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// An empty scratch folder: [`tmp_path`] created.
pub fn tmp_dir(prefix: &str, name: &str) -> PathBuf {
    let d = tmp_path(prefix, name);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Read one unmasked server frame (text or binary) from a WebSocket stream:
/// (opcode, payload).
pub fn ws_read_frame(s: &mut TcpStream) -> std::io::Result<(u8, Vec<u8>)> {
    use std::io::Read;
    let mut h = [0u8; 2];
    s.read_exact(&mut h)?;
    let mut len = (h[1] & 0x7f) as u64;
    if len == 126 {
        let mut b = [0u8; 2];
        s.read_exact(&mut b)?;
        len = u16::from_be_bytes(b) as u64;
    } else if len == 127 {
        let mut b = [0u8; 8];
        s.read_exact(&mut b)?;
        len = u64::from_be_bytes(b);
    }
    let mut data = vec![0u8; len as usize];
    s.read_exact(&mut data)?;
    Ok((h[0] & 0x0f, data))
}

/// An HTTP server on loopback that answers every request by `answer`, which writes to
/// the connection (and may drip, hang or flood). Stops when dropped.
pub struct Hostile {
    pub url: String,
    stop: Arc<AtomicBool>,
}

impl Hostile {
    pub fn start(answer: impl Fn(&mut TcpStream, &str) + Send + Sync + 'static) -> Self {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.set_nonblocking(true).unwrap();
        let url = format!("http://{}", l.local_addr().unwrap());
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let answer = Arc::new(answer);
        std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                match l.accept() {
                    Ok((mut c, _)) => {
                        let a = answer.clone();
                        let s2 = s.clone();
                        std::thread::spawn(move || {
                            c.set_nonblocking(false).unwrap();
                            c.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
                            let mut buf = [0u8; 4096];
                            let mut req = Vec::new();
                            while !req.windows(4).any(|w| w == b"\r\n\r\n") {
                                match c.read(&mut buf) {
                                    Ok(0) | Err(_) => return,
                                    Ok(n) => req.extend_from_slice(&buf[..n]),
                                }
                            }
                            let line = String::from_utf8_lossy(&req)
                                .lines()
                                .next()
                                .unwrap_or("")
                                .to_string();
                            if !s2.load(Ordering::Relaxed) {
                                a(&mut c, &line);
                            }
                        });
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(5)),
                }
            }
        });
        Self { url, stop }
    }
}

impl Drop for Hostile {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// autopilot/tests/pymav_vehicle.py as a vehicle; killed on drop if still running.
pub struct PymavVehicle(pub std::process::Child);

impl Drop for PymavVehicle {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start the pymavlink vehicle with `args`; its UDP port.
pub fn pymav_vehicle(args: &[&str]) -> (PymavVehicle, u16) {
    use std::io::BufRead;
    markhold_testkit::require_pymavlink();
    let mut child = Command::new("python3")
        .arg(repo("autopilot/tests/pymav_vehicle.py"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .expect("spawn python3");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .unwrap();
    let port = line
        .trim()
        .strip_prefix("UDP ")
        .unwrap_or_else(|| panic!("vehicle said {line:?}"))
        .parse()
        .unwrap();
    (PymavVehicle(child), port)
}

/// The vehicle's verdict, its last stdout line (it ends 1.5 s after markhold falls
/// silent).
pub fn pymav_verdict(v: &mut PymavVehicle) -> serde_json::Value {
    let mut out = String::new();
    v.0.stdout
        .as_mut()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    let _ = v.0.wait();
    let last = out.lines().last().unwrap_or_default();
    serde_json::from_str(last).unwrap_or_else(|e| panic!("verdict {out:?}: {e}"))
}
