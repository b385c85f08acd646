//! Interop with pymavlink: a pymavlink script (tests/pymav_vehicle.py) plays the vehicle,
//! checks what the link sends and sends telemetry the link must parse. Runs over UDP with
//! RC overrides and over a pseudo-terminal (the serial transport) with MANUAL_CONTROL.
//! A second script (tests/pymav_connection.py) opens pymavlink's own
//! `mavutil.mavlink_connection(URL)`, to check that `udp:` means listen on both sides.
//! pymavlink comes from scripts/install-deps; without it the tests fail and say so.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use markhold_autopilot::*;

const FRAME_S: f64 = 1.0 / 30.0;

struct Vehicle {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl Drop for Vehicle {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Run a pymavlink script from tests/ with `args`; the script and the first line it
/// prints (its address), within 20 s.
fn spawn_script(script: &str, args: &[&str], what: &str) -> (Vehicle, String) {
    markhold_testkit::require_pymavlink();
    let path = format!("{}/tests/{script}", env!("CARGO_MANIFEST_DIR"));
    let mut child = Command::new("python3")
        .arg(path)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn python3");
    let out = child.stdout.take().expect("stdout");
    let rx = markhold_testkit::lines_on_channel(out);
    let first = rx
        .recv_timeout(Duration::from_secs(20))
        .unwrap_or_else(|_| panic!("{what} did not start"));
    (Vehicle { child, lines: rx }, first)
}

fn spawn(mode: &str, pilot: &str) -> (Vehicle, String) {
    let args = ["--mode", mode, "--pilot", pilot, "--deadline", "25"];
    spawn_script("pymav_vehicle.py", &args, "pymavlink vehicle")
}

/// Runs the loop in real time at 30 Hz (the script checks wall-clock rates): arm in
/// MANUAL, then one axis at a time at effort 0.5, then neutral, then disarm.
fn drive(cfg: LinkConfig) -> VehicleLink {
    let mut link = VehicleLink::connect(&cfg).unwrap();
    let t0 = Instant::now();
    let mut frame = 0u64;
    let mut next = t0;
    let mut phase_start = None;
    let axes: [fn(&mut Effort); 6] = [
        |e| e.surge = 0.5,
        |e| e.sway = -0.5,
        |e| e.heave = 0.5,
        |e| e.yaw = 0.5,
        |e| e.roll = 0.5,
        |e| e.pitch = -0.5,
    ];
    loop {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "interop loop timed out: {:?}",
            link.state()
        );
        let now = frame as f64 * FRAME_S;
        link.tick(now).unwrap();
        let s = link.state();
        if s.discovered && s.mode_command == CommandStatus::Idle {
            link.request_mode(ArduSubMode::Manual, now).unwrap();
            link.request_arm(true, now).unwrap();
        }
        let s = link.state();
        if s.armed && s.mode == Some(ArduSubMode::Manual) && phase_start.is_none() {
            phase_start = Some(now);
        }
        if let Some(p0) = phase_start {
            let k = ((now - p0) / 0.3) as usize;
            if k < axes.len() {
                let mut e = Effort::NEUTRAL;
                axes[k](&mut e);
                link.send_effort(&e, now).unwrap();
            } else if k < axes.len() + 2 {
                link.send_neutral(now).unwrap();
            } else {
                // Shutdown order: neutral pilot input, then disarm.
                link.send_neutral(now).unwrap();
                link.request_arm(false, now).unwrap();
                break;
            }
        }
        frame += 1;
        next += Duration::from_secs_f64(FRAME_S);
        if let Some(d) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(d);
        }
    }
    // Let the disarm be acknowledged and show in the heartbeat.
    let t1 = Instant::now();
    while t1.elapsed() < Duration::from_secs(3)
        && (link.state().arm_command != CommandStatus::Accepted || link.state().armed)
    {
        frame += 1;
        link.tick(frame as f64 * FRAME_S).unwrap();
        std::thread::sleep(Duration::from_millis(10));
    }
    link
}

fn verdict(v: &mut Vehicle) -> String {
    let t0 = Instant::now();
    loop {
        if let Ok(l) = v.lines.recv_timeout(Duration::from_millis(200)) {
            if l.starts_with('{') {
                let _ = v.child.wait();
                return l;
            }
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no verdict from the pymavlink vehicle"
        );
    }
}

fn check_telemetry(s: &VehicleState) {
    let a = s.attitude.expect("ATTITUDE parsed");
    assert!(
        (a.roll - 0.05).abs() < 1e-6 && (a.pitch + 0.04).abs() < 1e-6 && (a.yaw - 1.5).abs() < 1e-6
    );
    assert!((a.rates[2] - 0.2).abs() < 1e-6);
    let d = s.depth.expect("SCALED_PRESSURE2 parsed");
    assert!((d.depth_m - 3.0).abs() < 0.01, "{d:?}");
    assert!((d.temperature_c - 15.0).abs() < 1e-9);
    let so = s.servo_outputs.expect("SERVO_OUTPUT_RAW parsed");
    assert_eq!(
        so.pwm[..8],
        [1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800]
    );
    let lp = s.local_position.expect("LOCAL_POSITION_NED parsed");
    assert_eq!(lp.position.map(|v| (v * 10.0).round()), [10.0, -20.0, 30.0]);
    assert_eq!(lp.velocity.map(|v| (v * 10.0).round()), [1.0, 2.0, 3.0]);
    assert_eq!((s.system_id, s.component_id, s.vehicle_type), (1, 1, 12));
    assert!(!s.armed, "disarm not reflected");
}

/// Drives the vehicle `v` over a link with `cfg`; its verdict is ok and the telemetry
/// came through.
fn drive_and_judge(v: &mut Vehicle, cfg: LinkConfig) {
    let link = drive(cfg);
    let verdict = verdict(v);
    assert!(
        verdict.contains("\"ok\": true"),
        "pymavlink vehicle: {verdict}"
    );
    check_telemetry(link.state());
}

#[test]
fn pymavlink_vehicle_over_udp_with_rc_override() {
    let (mut v, first) = spawn("udp", "rc");
    let port: u16 = first
        .strip_prefix("UDP ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("unexpected first line {first:?}"));
    drive_and_judge(
        &mut v,
        LinkConfig {
            url: format!("udpout:127.0.0.1:{port}"),
            ..Default::default()
        },
    );
}

#[test]
fn pymavlink_vehicle_over_serial_pty_with_manual_control() {
    let (mut v, first) = spawn("pty", "manual");
    let path = first
        .strip_prefix("PTY ")
        .unwrap_or_else(|| panic!("unexpected first line {first:?}"))
        .to_string();
    drive_and_judge(
        &mut v,
        LinkConfig {
            url: format!("serial:{path}:115200"),
            pilot_input: PilotInput::ManualControl,
            ..Default::default()
        },
    );
}

/// A peer opened with `mavutil.mavlink_connection(url)`; returns it and its local port.
fn spawn_connection(url: &str) -> (Vehicle, u16) {
    let (v, first) = spawn_script(
        "pymav_connection.py",
        &["--url", url, "--deadline", "15"],
        "pymavlink peer",
    );
    let port = first
        .strip_prefix("PORT ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("unexpected first line {first:?}"));
    (v, port)
}

/// Ticks the link (bounded) until it has heard the vehicle and the peer has given its
/// verdict on markhold's heartbeat.
fn exchange(link: &mut VehicleLink, peer: &mut Vehicle) -> String {
    let t0 = Instant::now();
    let mut frame = 0u64;
    loop {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "no exchange with the pymavlink peer: {:?}",
            link.state()
        );
        link.tick(frame as f64 * FRAME_S).unwrap();
        frame += 1;
        if let Ok(l) = peer.lines.recv_timeout(Duration::from_millis(30)) {
            if l.starts_with('{') {
                let _ = peer.child.wait();
                // Whatever the peer sent before its verdict is read in a few more ticks.
                let t1 = Instant::now();
                while !link.state().discovered && t1.elapsed() < Duration::from_secs(2) {
                    link.tick(frame as f64 * FRAME_S).unwrap();
                    frame += 1;
                    std::thread::sleep(Duration::from_millis(10));
                }
                return l;
            }
        }
    }
}

/// `udp:` means listen in markhold as in pymavlink: markhold listens on `udp:` and a
/// pymavlink `udpout:` peer reaches it; a pymavlink `udp:` peer listens and markhold's
/// `udpout:` reaches it. Either way both sides hear each other.
#[test]
fn udp_means_listen_as_in_pymavlink() {
    // markhold `udp:` (listen) <- pymavlink `udpout:` (send to).
    let mut link = VehicleLink::connect(&LinkConfig {
        url: "udp:127.0.0.1:0".into(),
        ..Default::default()
    })
    .unwrap();
    let port = link
        .local_addr()
        .expect("a listening link has an address")
        .port();
    let (mut peer, _) = spawn_connection(&format!("udpout:127.0.0.1:{port}"));
    let verdict = exchange(&mut link, &mut peer);
    assert!(
        verdict.contains("\"ok\": true"),
        "pymavlink udpout peer: {verdict}"
    );
    assert!(verdict.contains("\"udp_server\": false"), "{verdict}");
    assert!(
        link.state().discovered,
        "markhold's udp: link did not hear pymavlink"
    );

    // pymavlink `udp:` (listen) <- markhold `udpout:` (send to).
    let (mut peer, port) = spawn_connection("udp:127.0.0.1:0");
    let mut link = VehicleLink::connect(&LinkConfig {
        url: format!("udpout:127.0.0.1:{port}"),
        ..Default::default()
    })
    .unwrap();
    let verdict = exchange(&mut link, &mut peer);
    assert!(
        verdict.contains("\"ok\": true"),
        "pymavlink udp peer: {verdict}"
    );
    assert!(
        verdict.contains("\"udp_server\": true"),
        "pymavlink did not listen on udp: {verdict}"
    );
    assert!(
        link.state().discovered,
        "markhold's udpout: link did not hear pymavlink"
    );
}
