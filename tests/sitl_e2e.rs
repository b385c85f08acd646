//! `markhold sitl` end to end: a client written to ArduPilot's published JSON-backend
//! packet format sends servo packets over loopback UDP and checks the replies.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::UdpSocket;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// 16-channel servo packet: u16 magic 18458, u16 frame_rate, u32 frame_count, u16 pwm[16].
fn servo_packet(frame_count: u32, pwm: u16) -> Vec<u8> {
    let mut b = Vec::with_capacity(40);
    b.extend_from_slice(&18458u16.to_le_bytes());
    b.extend_from_slice(&400u16.to_le_bytes());
    b.extend_from_slice(&frame_count.to_le_bytes());
    for _ in 0..16 {
        b.extend_from_slice(&pwm.to_le_bytes());
    }
    b
}

/// The numbers after `"key":[` in ArduPilot's way of reading them.
fn vec_after(json: &str, key: &str) -> Vec<f64> {
    let pat = format!("\"{key}\":[");
    let start = json
        .find(&pat)
        .unwrap_or_else(|| panic!("no {key} in {json}"))
        + pat.len();
    let end = start + json[start..].find(']').unwrap();
    json[start..end]
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect()
}

fn num_after(json: &str, key: &str) -> f64 {
    let pat = format!("\"{key}\":");
    let start = json.find(&pat).unwrap() + pat.len();
    let end = start + json[start..].find([',', '}']).unwrap();
    json[start..end].trim().parse().unwrap()
}

#[test]
fn sitl_json_server_answers_lock_step_at_rest() {
    let port = free_udp_port();
    let packets = 40u32;
    let child = Command::new(env!("CARGO_BIN_EXE_markhold"))
        .args([
            "sitl",
            "--port",
            &port.to_string(),
            "--max-packets",
            &packets.to_string(),
        ])
        .args(["--max-seconds", "30"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let server = format!("127.0.0.1:{port}");
    let mut buf = [0u8; 2048];

    // The server may still be starting: repeat frame 1 until it answers (bounded).
    // Every datagram that reaches the server counts toward --max-packets; one sent before
    // it bound is lost, and a retry may race with a late reply, so count replies too.
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut sent = 0u32;
    let first = loop {
        assert!(Instant::now() < deadline, "no reply from markhold sitl");
        sock.send_to(&servo_packet(1, 1500), &server).unwrap();
        sent += 1;
        if let Ok(n) = sock.recv(&mut buf) {
            break String::from_utf8_lossy(&buf[..n]).into_owned();
        }
    };
    // Retries before the bind were dropped by the kernel: only the answered one counted.
    sent = sent.min(1);
    let mut last_t = num_after(&first, "timestamp");
    let mut last = first;
    for frame in 2..=20u32 {
        sock.send_to(&servo_packet(frame, 1500), &server).unwrap();
        sent += 1;
        let n = sock.recv(&mut buf).expect("one reply per servo packet");
        last = String::from_utf8_lossy(&buf[..n]).into_owned();
        let t = num_after(&last, "timestamp");
        assert!(
            t > last_t && t - last_t < 0.1,
            "time must advance by one step: {last_t} -> {t}"
        );
        last_t = t;
    }
    // ArduPilot scans the text, it does not parse JSON: newline framing, no spaces.
    assert!(last.starts_with('\n') && last.ends_with('\n'), "{last:?}");
    assert!(!last.contains(": "), "{last}");
    let accel = vec_after(&last, "accel_body");
    assert!(accel[0].abs() < 0.2 && accel[1].abs() < 0.2, "{accel:?}");
    assert!(
        (accel[2] + 9.81).abs() < 0.3,
        "at rest, specific force ~ -g on z: {accel:?}"
    );
    let q = vec_after(&last, "quaternion");
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((norm - 1.0).abs() < 1e-6, "{q:?}");
    let gyro = vec_after(&last, "gyro");
    assert!(gyro.iter().all(|g| g.abs() < 0.05), "{gyro:?}");

    // A repeated frame count is answered without advancing time.
    sock.send_to(&servo_packet(20, 1500), &server).unwrap();
    sent += 1;
    let n = sock.recv(&mut buf).unwrap();
    let again = String::from_utf8_lossy(&buf[..n]).into_owned();
    assert_eq!(num_after(&again, "timestamp"), last_t);

    // Garbage is rejected, not answered, and does not stop the server.
    sock.send_to(b"not a servo packet", &server).unwrap();
    sent += 1;
    assert!(sock.recv(&mut buf).is_err(), "garbage must not be answered");
    while sent < packets {
        sock.send_to(&servo_packet(21 + sent, 1500), &server)
            .unwrap();
        sent += 1;
        sock.recv(&mut buf).expect("still answering after garbage");
    }
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("1 rejected"), "{stdout}");
}

/// A free loopback UDP port (bound on port 0) that `want` accepts, found in a bounded
/// number of tries.
fn free_udp_port_where(want: impl Fn(u16) -> bool) -> u16 {
    for _ in 0..1000 {
        let p = free_udp_port();
        if want(p) {
            return p;
        }
    }
    panic!("no free port of the kind asked for in 1000 tries");
}

/// `markhold sitl --port P --max-packets 0`: binds, prints its hint and exits; the
/// stderr, within a bounded wait.
fn sitl_hint(port: u16) -> String {
    let mut child = Command::new(env!("CARGO_BIN_EXE_markhold"))
        .args(["sitl", "--port", &port.to_string(), "--max-packets", "0"])
        .args(["--max-seconds", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("markhold sitl --max-packets 0 did not exit within 30 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{out:?}");
    String::from_utf8(out.stderr).unwrap()
}

/// The `sim_vehicle.py` hint reaches the port actually bound: `-I N` for 9002 + 10 N,
/// and `--sim-port-out` with a note when no instance number does.
#[test]
fn sitl_hint_names_the_port_bound() {
    let port = free_udp_port_where(|p| p >= 9002 && (p - 9002) % 10 == 0);
    let err = sitl_hint(port);
    let n = (port - 9002) / 10;
    assert!(err.contains(&format!("on udp 127.0.0.1:{port}")), "{err}");
    assert!(
        err.contains(&format!("--model JSON -I {n}\n")),
        "port {port} needs instance {n}: {err}"
    );
    assert!(
        !err.contains("9002\n") && !err.contains("--sim-port-out"),
        "{err}"
    );

    let port = free_udp_port_where(|p| p < 9002 || (p - 9002) % 10 != 0);
    let err = sitl_hint(port);
    assert!(err.contains("no instance number"), "{err}");
    assert!(
        err.contains(&format!("-A \"--sim-port-out {port}\"")),
        "port {port}: {err}"
    );
    assert!(!err.contains(" -I "), "{err}");
}
