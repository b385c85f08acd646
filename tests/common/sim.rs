//! The simulated world for the tests that need one (the `sim` feature).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
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

use super::site_path;

/// The site's simulated world with a free vehicle starting at `t_world_vehicle_start`:
/// the vehicle as ArduSub (or SITL) is, pilot input acting as it arrives; a loop in front
/// of it brings its own delays (camera, telemetry, its own loop), real ones here.
pub fn rig_at(
    site: &LoadedSite,
    t_world_vehicle_start: Isometry3<f64>,
    seed: u64,
    lock_step: bool,
) -> HilRig {
    let s = &site.site;
    HilRig::new(HilSetup {
        vehicle: markhold_hil::VehicleConfig {
            delay: markhold_hil::DelayConfig::NONE,
            ..s.vehicle.clone()
        },
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

/// The HIL loop of `site` with `opts`, the vehicle armed in the site's mode.
pub fn armed_hil(
    site: &LoadedSite,
    opts: &markhold::sim::hil::HilOptions,
) -> markhold::sim::hil::HilRun {
    let mut hil =
        markhold::sim::hil::HilRun::build(site, opts, markhold::pipeline::Observers::new())
            .unwrap();
    hil.arm(site.site.link.mode.ardusub()).unwrap();
    hil
}

/// A UDP socket on loopback that waits at most 1 ms for a datagram: a sender of its own
/// beside the loop's link.
pub fn side_socket() -> std::net::UdpSocket {
    let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    s.set_read_timeout(Some(Duration::from_millis(1))).unwrap();
    s
}

/// The test site's simulated world with the vehicle on station (seed 5).
pub fn station_rig(lock_step: bool) -> HilRig {
    let site = params::load(&site_path()).unwrap();
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    rig_at(&site, start, 5, lock_step)
}

/// The station rig exposed at 3000 us, and its first frame.
pub fn station_camera() -> (HilRig, Frame) {
    let mut rig = station_rig(false);
    rig.set_exposure_us(3000.0).unwrap();
    let mut frame = Frame::default();
    rig.grab(&mut frame).unwrap();
    (rig, frame)
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

    /// Its `--link` URL (markhold sends to it).
    pub fn link(&self) -> String {
        format!("udpout:{}", self.addr)
    }

    /// Stop it and report.
    pub fn finish(self) -> VehicleEnd {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap()
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
