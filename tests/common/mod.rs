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
use std::process::{Child, Command, ExitStatus, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

/// `markhold run --engage --no-preflight --site SITE --camera CAMERA`: the loop engaged
/// from the start, without the pre-flight checks.
pub fn run_engaged(site: &Path, camera: &str) -> Command {
    let mut c = markhold();
    c.args(["run", "--engage", "--no-preflight", "--site"])
        .arg(site)
        .args(["--camera", camera]);
    c
}

/// `frames:DIR`: the recorded-frames camera playing `dir`.
pub fn frames_camera(dir: &Path) -> String {
    format!("frames:{}", dir.display())
}

/// Runs `cmd` to its end; the test fails, showing its stderr, unless it exits 0.
pub fn run_ok(cmd: &mut Command) -> Output {
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

/// `markhold map --site SITE --SOURCE PATH ARGS` run to its end, SOURCE `frames` or
/// `recording`.
pub fn run_map(site: &Path, source: &str, path: &Path, args: &[&str]) -> Output {
    let (site, path) = (site.to_str().unwrap(), path.to_str().unwrap());
    let source = format!("--{source}");
    run_markhold(&[&["map", "--site", site, &source, path], args].concat())
}

/// A camera at `c` looking at `target` (site frame, image x along the site's x): the
/// site's pose in the camera.
pub fn look_at(
    c: nalgebra::Vector3<f64>,
    target: nalgebra::Vector3<f64>,
) -> nalgebra::Isometry3<f64> {
    use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
    let z = (target - c).normalize();
    let x = z.cross(&Vector3::y()).normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(Translation3::from(c), UnitQuaternion::from(r)).inverse()
}

/// `markhold ARGS --quiet --summary OUT`, which must succeed: its summary.
pub fn run_summary(args: &[&str], out: &Path) -> serde_json::Value {
    let o = markhold()
        .args(args)
        .args(["--quiet", "--summary"])
        .arg(out)
        .output()
        .expect("run markhold");
    assert!(
        o.status.success(),
        "markhold {args:?} failed: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    read_json(out)
}

/// `markhold hil --site SITE ARGS --quiet --summary OUT`, which must succeed: its summary.
pub fn hil_summary(site: &Path, args: &[&str], out: &Path) -> serde_json::Value {
    let site = site.to_str().unwrap();
    run_summary(&[&["hil", "--site", site], args].concat(), out)
}

/// `markhold hil --quiet --seconds SECONDS --site SITE --vehicle VEHICLE`: the loop run
/// against an external vehicle at the `--vehicle` URL.
pub fn hil_on_vehicle(site: &Path, seconds: &str, vehicle: &str) -> Command {
    let mut c = markhold();
    c.args(["hil", "--quiet", "--seconds", seconds, "--site"])
        .arg(site)
        .args(["--vehicle", vehicle]);
    c
}

/// `cmd` run to its end: (exit code, -1 when a signal ended it; stdout; stderr).
pub fn outcome(cmd: &mut Command) -> (i32, String, String) {
    let o = cmd.output().expect("run markhold");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// The stderr of a run that must have exited with `code`.
pub fn stderr_of_exit(o: &Output, code: i32) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(code), "{err}");
    err
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

/// The JSON file at `path` (a summary, a report), parsed.
pub fn read_json(path: impl AsRef<Path>) -> serde_json::Value {
    let path = path.as_ref();
    let text =
        std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A loopback UDP port nobody listens on (bound, then released).
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Sends SIGTERM to `child` (what a service manager does to stop it); whether `kill`
/// did.
pub fn sigterm(child: &Child) -> bool {
    Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .is_ok_and(|s| s.success())
}

/// `child`'s exit status once it has exited; past `deadline` it is killed and the test
/// fails with `what`.
pub fn exit_status_by(child: &mut Child, deadline: Instant, what: &str) -> ExitStatus {
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("{what}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `cmd` started with its stdout discarded and its stderr piped.
pub fn spawn_quiet(cmd: &mut Command) -> Child {
    cmd.stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// A thread reading `child`'s piped stderr to its end (so that a chatty child never
/// blocks on a full pipe); joined, it gives the text.
pub fn stderr_on_thread(child: &mut Child) -> std::thread::JoinHandle<String> {
    let err = child.stderr.take().unwrap();
    std::thread::spawn(move || String::from_utf8_lossy(&read_all(err)).into_owned())
}

/// All that `r` gives to its end (what it gave before an error, if one came).
pub fn read_all(mut r: impl Read) -> Vec<u8> {
    let mut b = Vec::new();
    let _ = r.read_to_end(&mut b);
    b
}

/// The largest resident set process `pid` reached so far, kB (`VmHWM`).
pub fn peak_rss_kb(pid: u32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// All that `child` writes to its (piped) stderr, to its end.
pub fn stderr_text(child: &mut Child) -> String {
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    err
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

/// A request's head (through its empty line) read from `c`; `None` if the peer went or
/// the read timed out first.
pub fn read_request_head(c: &mut TcpStream) -> Option<Vec<u8>> {
    let mut buf = [0u8; 4096];
    let mut req = Vec::new();
    while !req.windows(4).any(|w| w == b"\r\n\r\n") {
        match c.read(&mut buf) {
            Ok(0) | Err(_) => return None,
            Ok(n) => req.extend_from_slice(&buf[..n]),
        }
    }
    Some(req)
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
                            let Some(req) = read_request_head(&mut c) else {
                                return;
                            };
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

/// The STATUSTEXTs the vehicle's verdict lists, in order.
pub fn pymav_texts(verdict: &serde_json::Value) -> Vec<String> {
    verdict["texts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t[2].as_str().unwrap().to_string())
        .collect()
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
