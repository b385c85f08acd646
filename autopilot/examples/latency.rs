//! Frame-to-wire latency of the autopilot's share of the loop: from the moment a frame's
//! pose is available to the RC override arriving at a loopback UDP socket (station keeper
//! update + link tick + send). Prints p50 / p99 / max in ms.
//!
//! cargo run --release -p markhold-autopilot --example latency [frames]

use std::net::UdpSocket;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use markhold_autopilot::*;
use nalgebra::{Isometry3, Matrix6, Translation3};

fn main() {
    let frames: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(3000);
    let rx_sock = UdpSocket::bind("127.0.0.1:0").expect("bind");
    rx_sock
        .set_read_timeout(Some(Duration::from_millis(200)))
        .expect("timeout");
    let addr = rx_sock.local_addr().expect("addr");
    let (tx, rx) = mpsc::channel::<Instant>();
    let recv = std::thread::spawn(move || {
        let mut buf = [0u8; 512];
        let mut idle = 0;
        while idle < 5 {
            match rx_sock.recv_from(&mut buf) {
                Ok((n, _)) => {
                    idle = 0;
                    // MAVLink 2, message id 70 = RC_CHANNELS_OVERRIDE.
                    if n > 10 && buf[0] == 0xFD && buf[7] == 70 && buf[8] == 0 && buf[9] == 0 {
                        let _ = tx.send(Instant::now());
                    }
                }
                Err(_) => idle += 1,
            }
        }
    });

    let cfg = LinkConfig {
        url: format!("udpout:{addr}"),
        ..Default::default()
    };
    let mut link = VehicleLink::connect(&cfg).expect("link");
    let cam = markhold_testkit::forward_camera(0.2, 0.0);
    let mut keeper =
        StationKeeper::new(&StationConfig::default(), &ControllerConfig::default(), cam)
            .expect("keeper");
    let goal = StationConfig::default().t_marker_vehicle();
    let mut stamps = Vec::with_capacity(frames);
    for i in 0..frames {
        let now = i as f64 / 30.0;
        let off = Isometry3::from_parts(
            Translation3::new(0.1 * (now * 0.7).sin(), 0.05, 1.0 + 0.1 * now.cos()),
            goal.rotation,
        );
        let meas = PoseMeasurement {
            stamp_s: now,
            t_cam_marker: (off * cam).inverse(),
            cov_cam: Matrix6::identity() * 1e-5,
        };
        let t_frame = Instant::now();
        link.tick(now).expect("tick");
        let e = keeper.update(now, Some(&meas));
        link.send_effort(&e, now).expect("send");
        stamps.push(t_frame);
        // Pace at 500 Hz so arrivals pair with frames in order.
        std::thread::sleep(Duration::from_millis(2));
    }
    drop(link);
    let _ = recv.join();
    let arrivals: Vec<Instant> = rx.try_iter().collect();
    if arrivals.len() != stamps.len() {
        eprintln!(
            "warning: {} frames sent, {} overrides received",
            stamps.len(),
            arrivals.len()
        );
    }
    let mut lat: Vec<f64> = stamps
        .iter()
        .zip(&arrivals)
        .map(|(s, a)| a.duration_since(*s).as_secs_f64() * 1e3)
        .collect();
    lat.sort_by(f64::total_cmp);
    let pct = |p: f64| lat[((lat.len() as f64 - 1.0) * p).round() as usize];
    println!(
        "frames {} loop_latency_p50_ms {:.4} loop_latency_p99_ms {:.4} max_ms {:.4}",
        lat.len(),
        pct(0.5),
        pct(0.99),
        lat.last().copied().unwrap_or(f64::NAN)
    );
}
