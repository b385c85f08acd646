//! Helpers shared by the end-to-end tests: the built binary, the small fixture site,
//! scratch paths, the simulated world as a free-running vehicle, and a WebSocket frame
//! reader for the live view.
#![allow(dead_code)]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use markhold::params::{self, LoadedSite};
use markhold::sim::hil::{camera_model, marker_spec};
use markhold_exposure::{Camera, Frame};
use markhold_hil::endpoint::EndpointStats;
use markhold_hil::{EndpointConfig, HilRig, HilSetup, Truth, VehicleMotion};
use nalgebra::Isometry3;

/// The built `markhold` binary.
pub fn markhold() -> Command {
    Command::new(env!("CARGO_BIN_EXE_markhold"))
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
/// no file left there by an earlier run.
pub fn tmp_path(prefix: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("markhold-{prefix}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    let _ = std::fs::remove_file(&p);
    p
}

/// The site's simulated world with a free vehicle starting at `t_world_vehicle_start`.
pub fn rig_at(
    site: &LoadedSite,
    t_world_vehicle_start: Isometry3<f64>,
    seed: u64,
    lock_step: bool,
) -> HilRig {
    let s = &site.site;
    HilRig::new(HilSetup {
        vehicle: s.vehicle.clone(),
        endpoint: EndpointConfig::default(),
        water: s.water.clone(),
        lighting: s.lighting.clone(),
        camera: camera_model(site, site.limits()),
        t_vehicle_cam: site.t_vehicle_cam(),
        marker: marker_spec(site).unwrap(),
        t_world_marker: site.t_world_marker(),
        map: Vec::new(),
        t_world_vehicle_start,
        motion: VehicleMotion::Free,
        seed,
        lock_step,
    })
    .unwrap()
}

/// The test site's simulated world with the vehicle on station (seed 5).
pub fn station_rig(lock_step: bool) -> HilRig {
    let site = params::load(&site_path()).unwrap();
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    rig_at(&site, start, 5, lock_step)
}

/// `n` frames rendered on station at 3000 us, written as a recorded-frames folder `dir`
/// (what `--camera frames:DIR` plays back).
pub fn station_frames(dir: PathBuf, n: usize) -> PathBuf {
    let mut rig = station_rig(false);
    rig.set_exposure_us(3000.0).unwrap();
    let mut rec = markhold_camera::FrameRecorder::create(&dir).unwrap();
    let mut f = Frame::default();
    for _ in 0..n {
        rig.grab(&mut f).unwrap();
        rec.write(&f).unwrap();
    }
    dir
}

/// What a [`RealTimeVehicle`] reports when stopped.
#[derive(Debug)]
pub struct VehicleEnd {
    /// Its MAVLink endpoint's counters.
    pub stats: EndpointStats,
    /// The world's truth at the end, `armed` included.
    pub truth: Truth,
}

/// A simulated world run as a vehicle of its own, the way ArduSub (or SITL) runs
/// whatever markhold does: on its own thread, one frame per camera period in real time,
/// until stopped or for at most [`RealTimeVehicle::MAX_RUN`].
pub struct RealTimeVehicle {
    /// Its MAVLink UDP address.
    pub addr: SocketAddr,
    stop: Arc<AtomicBool>,
    thread: JoinHandle<VehicleEnd>,
}

impl RealTimeVehicle {
    /// The longest a vehicle runs when nobody stops it.
    pub const MAX_RUN: Duration = Duration::from_secs(60);

    pub fn start(mut rig: HilRig) -> Self {
        let addr = rig.mavlink_udp_addr();
        let period = Duration::from_secs_f64(1.0 / rig.exposure_limits().fps);
        let stop = Arc::new(AtomicBool::new(false));
        let stopped = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut frame = Frame::default();
            let t0 = Instant::now();
            let mut k = 0u32;
            while !stopped.load(Ordering::Relaxed) && t0.elapsed() < Self::MAX_RUN {
                rig.grab(&mut frame).unwrap();
                k += 1;
                if let Some(w) = (t0 + period * k).checked_duration_since(Instant::now()) {
                    std::thread::sleep(w);
                }
            }
            // Take in what arrived after the last frame.
            rig.pump().unwrap();
            VehicleEnd {
                stats: rig.endpoint_stats(),
                truth: rig.truth(),
            }
        });
        Self { addr, stop, thread }
    }

    /// Stop it and report.
    pub fn finish(self) -> VehicleEnd {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap()
    }
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

/// `GET /v4l` as the simulated camera manager answers it (auto exposure, 2 ms).
pub fn sources_json() -> String {
    let limits = markhold_exposure::ExposureLimits {
        min_us: 20.0,
        max_us: 30000.0,
        fps: 30.0,
    };
    let mgr = markhold::sim::stream::SimCameraManager::start(limits, 2000.0).unwrap();
    let url = mgr.url();
    let addr = url.strip_prefix("http://").unwrap();
    let mut s = TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET /v4l HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out.split_once("\r\n\r\n").unwrap().1.to_string()
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
