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

/// Lockstep as the SITL-in-the-loop runner uses it: the server holds each reply while
/// a camera frame is rendered from its state. A fake ArduPilot (its own thread, written
/// to SIM_JSON.cpp's exchange: send a servo packet, block on the state) sees its time
/// advance only by the states' timestamps; every frame's pose is the pose of the state
/// ArduPilot is then sent, at that state's time; and while a reply is held ArduPilot
/// gets nothing (it cannot run ahead of the frame).
#[test]
fn held_replies_keep_the_peer_in_lockstep_and_frames_see_the_replied_pose() {
    let start = Isometry3::translation(0.5, -0.2, 3.0);
    let cfg = SitlConfig {
        port: 0,
        ..SitlConfig::default()
    };
    let mut server = SitlServer::bind(&cfg, &VehicleConfig::default(), &start, 1).unwrap();
    let addr = server.local_addr().unwrap();
    let packets = 400u32;
    let rate = 400u16;
    // The fake ArduPilot: a full-thrust vertical pulse so that the pose changes.
    let peer = std::thread::spawn(move || {
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let a = Ardu { sock, to: addr };
        let mut replies = Vec::new();
        for frame in 0..packets {
            let mut pwm = [1500u16; 16];
            for p in &mut pwm[4..8] {
                *p = 1700;
            }
            let v = a.servo(rate, frame, pwm);
            let t = v["timestamp"].as_f64().unwrap();
            let p = v3(&v, "/position");
            let q = v.pointer("/quaternion").unwrap().as_array().unwrap();
            let q: Vec<f64> = q.iter().map(|x| x.as_f64().unwrap()).collect();
            replies.push((t, p, q));
        }
        replies
    });
    // The runner's side: a frame every 25 steps (16 Hz against 400 Hz physics), held
    // for a while (a slow frame); the peer must be blocked meanwhile.
    let mut frames = Vec::new();
    let mut stepped = 0u32;
    while stepped < packets {
        if server.receive(Duration::from_secs(10)).unwrap().is_none() {
            panic!("the fake ArduPilot stopped sending");
        }
        assert!(server.holding());
        stepped += 1;
        if stepped.is_multiple_of(25) {
            let st = server.state();
            // A slow frame: nothing else arrives while the reply is held.
            let before = server.stats().packets;
            std::thread::sleep(Duration::from_millis(30));
            assert_eq!(server.stats().packets, before);
            frames.push((st.time_s, st.t_world_vehicle));
        }
        server.reply().unwrap();
        assert!(!server.holding());
    }
    let replies = peer.join().unwrap();
    assert_eq!(replies.len(), packets as usize);
    // Time advances by exactly one physics step per exchange (no step twice, none lost).
    for (k, (t, _, _)) in replies.iter().enumerate() {
        let want = (k + 1) as f64 / f64::from(rate);
        assert!((t - want).abs() < 1e-9, "reply {k}: t {t}, want {want}");
    }
    // Each frame's pose is the pose ArduPilot was sent at that frame's time.
    assert_eq!(frames.len(), (packets / 25) as usize);
    let mut moved = 0.0f64;
    for (t, pose) in &frames {
        let (_, p, q) = replies
            .iter()
            .find(|(tr, _, _)| (tr - t).abs() < 1e-12)
            .unwrap_or_else(|| panic!("no reply at frame time {t}"));
        let tr = pose.translation.vector;
        for i in 0..3 {
            assert_eq!(p[i], tr[i], "position at {t}");
        }
        let rq = pose.rotation.quaternion();
        assert_eq!(q, &vec![rq.w, rq.i, rq.j, rq.k], "attitude at {t}");
        moved = moved.max((tr - start.translation.vector).norm());
    }
    // The pulse moved the vehicle: the poses compared are not all the start.
    assert!(moved > 1e-3, "moved {moved}");
}
