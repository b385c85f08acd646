//! The SITL JSON physics server, checked with a client written to ArduPilot's published
//! packet format (libraries/SITL/SIM_JSON): binary servo packets out, JSON states back.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use markhold_hil::sitl::{MAGIC_16, MAGIC_32};
use markhold_hil::{SitlConfig, SitlServer, VehicleConfig};
use nalgebra::Isometry3;
use serde_json::Value;

struct Ardu {
    sock: UdpSocket,
    to: SocketAddr,
}

impl Ardu {
    fn packet(magic: u16, rate: u16, frame: u32, pwm: &[u16]) -> Vec<u8> {
        let mut b = Vec::with_capacity(8 + 2 * pwm.len());
        b.extend_from_slice(&magic.to_le_bytes());
        b.extend_from_slice(&rate.to_le_bytes());
        b.extend_from_slice(&frame.to_le_bytes());
        for p in pwm {
            b.extend_from_slice(&p.to_le_bytes());
        }
        b
    }

    /// Send one packet and read the reply (None if nothing within 300 ms).
    fn exchange(&self, bytes: &[u8]) -> Option<Value> {
        self.sock.send_to(bytes, self.to).unwrap();
        let mut buf = [0u8; 2048];
        match self.sock.recv_from(&mut buf) {
            Ok((n, _)) => {
                let text = std::str::from_utf8(&buf[..n]).unwrap();
                // ArduPilot's framing: one object between newlines, compact.
                assert!(text.starts_with('\n') && text.ends_with('\n'), "{text:?}");
                assert!(!text.contains("\": "), "space after a colon: {text}");
                Some(serde_json::from_str(text.trim()).unwrap())
            }
            Err(_) => None,
        }
    }

    fn servo(&self, rate: u16, frame: u32, pwm: [u16; 16]) -> Value {
        self.exchange(&Self::packet(MAGIC_16, rate, frame, &pwm))
            .expect("reply")
    }
}

fn v3(v: &Value, key: &str) -> [f64; 3] {
    let a = v.pointer(key).unwrap().as_array().unwrap();
    assert_eq!(a.len(), 3, "{key}");
    [
        a[0].as_f64().unwrap(),
        a[1].as_f64().unwrap(),
        a[2].as_f64().unwrap(),
    ]
}

fn with_server(n_packets: u64, f: impl FnOnce(&Ardu)) -> markhold_hil::sitl::SitlStats {
    let cfg = SitlConfig {
        port: 0,
        ..Default::default()
    };
    let start = Isometry3::translation(0.0, 0.0, 5.0);
    let mut server = SitlServer::bind(&cfg, &VehicleConfig::default(), &start, 3).unwrap();
    let to = server.local_addr().unwrap();
    let handle = std::thread::spawn(move || {
        server
            .run_bounded(n_packets, Duration::from_secs(20))
            .unwrap()
    });
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    f(&Ardu { sock, to });
    handle.join().unwrap()
}

#[test]
fn at_rest_the_imu_reads_gravity_in_frd_and_time_advances_lock_step() {
    let stats = with_server(403, |a| {
        let idle = [1500u16; 16];
        let mut last_t = 0.0;
        let mut last = Value::Null;
        for frame in 1..=400u32 {
            let s = a.servo(400, frame, idle);
            let t = s["timestamp"].as_f64().unwrap();
            assert!(
                (t - frame as f64 / 400.0).abs() < 1e-9,
                "frame {frame}: t {t}"
            );
            assert!(t > last_t);
            last_t = t;
            last = s;
        }
        let acc = v3(&last, "/imu/accel_body");
        assert!(acc[0].abs() < 0.02 && acc[1].abs() < 0.02, "{acc:?}");
        assert!((acc[2] + 9.81).abs() < 0.1, "{acc:?}");
        let gyro = v3(&last, "/imu/gyro");
        assert!(gyro.iter().all(|g| g.abs() < 1e-3), "{gyro:?}");
        let p = v3(&last, "/position");
        assert!(p[0].abs() < 1e-3 && p[1].abs() < 1e-3, "{p:?}");
        // Slightly buoyant: after 1 s it is rising, a little above 5 m.
        assert!(p[2] < 5.0 && p[2] > 4.9, "{p:?}");
        let v = v3(&last, "/velocity");
        assert!(v[2] < 0.0, "{v:?}");
        let q = last["quaternion"].as_array().unwrap();
        assert_eq!(q.len(), 4);
        assert!((q[0].as_f64().unwrap() - 1.0).abs() < 1e-6, "{q:?}");

        // A repeated frame count is answered without stepping.
        let again = a.servo(400, 400, idle);
        assert_eq!(again["timestamp"], last["timestamp"]);
        assert_eq!(again["position"], last["position"]);
        // A frame count that goes back means ArduPilot restarted: the world resets.
        let reset = a.servo(400, 1, idle);
        assert!((reset["timestamp"].as_f64().unwrap() - 1.0 / 400.0).abs() < 1e-9);
        assert!((v3(&reset, "/position")[2] - 5.0).abs() < 1e-3);
        // Missed frames still step once per packet.
        let skip = a.servo(400, 10, idle);
        assert!((skip["timestamp"].as_f64().unwrap() - 2.0 / 400.0).abs() < 1e-9);
    });
    assert_eq!(stats.replies, 403);
    assert_eq!(stats.repeated, 1);
    assert_eq!(stats.resets, 1);
    assert_eq!(stats.missed_frames, 8);
}

#[test]
fn thrusters_move_the_vehicle_with_32_channel_packets_and_other_rates() {
    with_server(1200, |a| {
        // Motor outputs for "forward" on the Heavy: 1, 2 reverse, 3, 4 forward.
        let mut pwm = [1500u16; 32];
        pwm[..4].copy_from_slice(&[1300, 1300, 1700, 1700]);
        pwm[20] = 1900; // channels past the motors are ignored
        let mut last = Value::Null;
        for frame in 0..1200u32 {
            last = a
                .exchange(&Ardu::packet(MAGIC_32, 1200, frame, &pwm))
                .expect("reply");
        }
        assert!((last["timestamp"].as_f64().unwrap() - 1200.0 / 1200.0).abs() < 1e-9);
        let v = v3(&last, "/velocity");
        assert!(v[0] > 0.2, "north speed {v:?}");
        assert!(v[1].abs() < 0.05 * v[0], "{v:?}");
        let p = v3(&last, "/position");
        assert!(p[0] > 0.1, "{p:?}");
        // Accelerating forward: the accelerometer's x reads positive.
        let acc = v3(&last, "/imu/accel_body");
        assert!(acc[0] > 0.0, "{acc:?}");
    });
}

#[test]
fn malformed_packets_are_rejected_without_a_reply_and_the_link_survives() {
    let stats = with_server(5, |a| {
        assert!(a.exchange(b"hello").is_none());
        assert!(a
            .exchange(&Ardu::packet(12345, 400, 1, &[1500; 16]))
            .is_none());
        assert!(a
            .exchange(&Ardu::packet(MAGIC_32, 400, 1, &[1500; 16]))
            .is_none());
        assert!(a
            .exchange(&Ardu::packet(MAGIC_16, 0, 1, &[1500; 16]))
            .is_none());
        let s = a.servo(400, 1, [1500; 16]);
        assert!((s["timestamp"].as_f64().unwrap() - 1.0 / 400.0).abs() < 1e-9);
    });
    assert_eq!(stats.rejected, 4);
    assert_eq!(stats.replies, 1);
}
