//! `markhold sitl` end to end: a client written to ArduPilot's published JSON-backend
//! packet format sends servo packets over loopback UDP and checks the replies.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::net::UdpSocket;
use std::process::Stdio;
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
    let child = common::markhold()
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
    let mut child = common::markhold()
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

/// A fake ArduSub for `sitl-loop`'s own logic (no ArduSub binary in CI): a MAVLink
/// vehicle on loopback TCP that arms and changes mode on command and reports its
/// heartbeat, attitude and local position, and a JSON client written to SIM_JSON.cpp's
/// exchange (send a servo packet, block on the state) that records every state.
mod fake_ardusub {
    use std::io::{Read, Write};
    use std::net::{SocketAddr, TcpListener, UdpSocket};
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::{Arc, Mutex};
    use std::thread::JoinHandle;
    use std::time::{Duration, Instant};

    use markhold_autopilot::mavlink::dialects::ardupilotmega::*;
    use markhold_autopilot::mavlink::{self, MavHeader, MavlinkReader};

    #[derive(Default, Debug)]
    pub struct Vehicle {
        pub armed: bool,
        pub mode: u32,
        pub commands: u32,
        pub other: u32,
    }

    fn frame(seq: u8, msg: &MavMessage) -> Vec<u8> {
        let h = MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: seq,
        };
        let mut v = Vec::new();
        mavlink::write_v2_msg(&mut v, h, msg).unwrap();
        v
    }

    /// Whole MAVLink 2 frames out of `acc` (a partial one stays).
    fn parse(acc: &mut Vec<u8>, out: &mut Vec<MavMessage>) {
        loop {
            let Some(start) = acc.iter().position(|b| *b == 0xFD) else {
                acc.clear();
                return;
            };
            acc.drain(..start);
            if acc.len() < 10 {
                return;
            }
            let sig = if acc[2] & 1 != 0 { 13 } else { 0 };
            let total = 10 + acc[1] as usize + 2 + sig;
            if acc.len() < total {
                return;
            }
            let mut r = MavlinkReader::new(&acc[..total]);
            match r.read_any_message::<MavMessage>() {
                Ok((_, m)) => {
                    out.push(m);
                    acc.drain(..total);
                }
                Err(_) => {
                    acc.drain(..1);
                }
            }
        }
    }

    /// The simulated clock the two sides share, milliseconds: the JSON side's time, and
    /// the time the MAVLink side last sent its telemetry for. Like ArduSub, which sends
    /// its telemetry in its own loop before its next servo packet, the JSON side waits
    /// for the telemetry of each 20 ms before it goes on.
    #[derive(Default)]
    pub struct Clock {
        pub sim_ms: AtomicU64,
        pub sent_ms: AtomicU64,
    }

    /// The MAVLink side: listens on a loopback port, serves one client until `stop`.
    pub fn mavlink_vehicle(
        stop: Arc<AtomicBool>,
        clock: Arc<Clock>,
    ) -> (SocketAddr, Arc<Mutex<Vehicle>>, JoinHandle<()>) {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let state = Arc::new(Mutex::new(Vehicle::default()));
        let st = state.clone();
        let h = std::thread::spawn(move || {
            listener.set_nonblocking(true).unwrap();
            let deadline = Instant::now() + Duration::from_secs(120);
            let mut s = loop {
                if let Ok((s, _)) = listener.accept() {
                    break s;
                }
                if stop.load(Ordering::SeqCst) || Instant::now() > deadline {
                    return;
                }
                std::thread::sleep(Duration::from_millis(5));
            };
            s.set_read_timeout(Some(Duration::from_millis(1))).unwrap();
            let (mut acc, mut buf, mut msgs) = (Vec::new(), [0u8; 4096], Vec::new());
            let mut seq = 0u8;
            let mut sent_once = false;
            while !stop.load(Ordering::SeqCst) && Instant::now() < deadline {
                match s.read(&mut buf) {
                    Ok(0) => return,
                    Ok(n) => acc.extend_from_slice(&buf[..n]),
                    Err(_) => {}
                }
                msgs.clear();
                parse(&mut acc, &mut msgs);
                let mut out = Vec::new();
                for m in msgs.drain(..) {
                    let MavMessage::COMMAND_LONG(c) = m else {
                        st.lock().unwrap().other += 1;
                        continue;
                    };
                    let mut v = st.lock().unwrap();
                    v.commands += 1;
                    match c.command {
                        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => v.armed = c.param1 > 0.5,
                        MavCmd::MAV_CMD_DO_SET_MODE => v.mode = c.param2 as u32,
                        _ => {}
                    }
                    out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                        command: c.command,
                        result: MavResult::MAV_RESULT_ACCEPTED,
                        ..Default::default()
                    }));
                }
                let now_ms = clock.sim_ms.load(Ordering::SeqCst);
                if !sent_once || now_ms >= clock.sent_ms.load(Ordering::SeqCst) + 20 {
                    sent_once = true;
                    clock.sent_ms.store(now_ms, Ordering::SeqCst);
                    let v = st.lock().unwrap();
                    let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
                    if v.armed {
                        base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
                    }
                    out.push(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                        custom_mode: v.mode,
                        mavtype: MavType::MAV_TYPE_SUBMARINE,
                        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                        base_mode: base,
                        system_status: MavState::MAV_STATE_ACTIVE,
                        mavlink_version: 3,
                    }));
                    out.push(MavMessage::ATTITUDE(ATTITUDE_DATA::default()));
                    out.push(MavMessage::LOCAL_POSITION_NED(
                        LOCAL_POSITION_NED_DATA::default(),
                    ));
                }
                for m in &out {
                    seq = seq.wrapping_add(1);
                    if s.write_all(&frame(seq, m)).is_err() {
                        return;
                    }
                }
            }
        });
        (addr, state, h)
    }

    /// One state as ArduPilot reads it: timestamp, position, quaternion (w, x, y, z).
    pub type State = (f64, Vec<f64>, Vec<f64>);

    /// The JSON side: exchanges servo packets with `to` in lockstep until the server
    /// stops answering (2 s) or `stop`; returns every state received.
    pub fn json_client(
        to: SocketAddr,
        stop: Arc<AtomicBool>,
        clock: Arc<Clock>,
    ) -> JoinHandle<Vec<State>> {
        std::thread::spawn(move || {
            let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
            sock.set_read_timeout(Some(Duration::from_millis(50)))
                .unwrap();
            let mut states = Vec::new();
            let mut buf = [0u8; 2048];
            let mut frame_count = 0u32;
            let mut silent_since: Option<Instant> = None;
            let deadline = Instant::now() + Duration::from_secs(120);
            'outer: while !stop.load(Ordering::SeqCst) && Instant::now() < deadline {
                let pkt = super::servo_packet(frame_count, 1500);
                sock.send_to(&pkt, to).unwrap();
                loop {
                    match sock.recv(&mut buf) {
                        Ok(n) => {
                            let text = String::from_utf8_lossy(&buf[..n]).into_owned();
                            let t = super::num_after(&text, "timestamp");
                            states.push((
                                t,
                                super::vec_after(&text, "position"),
                                super::vec_after(&text, "quaternion"),
                            ));
                            let ms = (t * 1e3) as u64;
                            clock.sim_ms.store(ms, Ordering::SeqCst);
                            // The telemetry of this 20 ms first (bounded).
                            let wait = Instant::now() + Duration::from_secs(2);
                            while clock.sent_ms.load(Ordering::SeqCst) + 20 <= ms
                                && Instant::now() < wait
                                && !stop.load(Ordering::SeqCst)
                            {
                                std::thread::sleep(Duration::from_micros(50));
                            }
                            silent_since = None;
                            frame_count += 1;
                            break;
                        }
                        Err(_) => {
                            // A held reply (a frame being rendered), the server not yet
                            // bound, or the run over.
                            let since = *silent_since.get_or_insert_with(Instant::now);
                            if !states.is_empty() && since.elapsed() > Duration::from_secs(2) {
                                break 'outer;
                            }
                            if states.is_empty() && since.elapsed() > Duration::from_millis(200) {
                                // Before the first reply: send again, as SIM_JSON does.
                                silent_since = None;
                                continue 'outer;
                            }
                        }
                    }
                }
            }
            states
        })
    }
}

/// `markhold sitl-loop`'s exchange against a fake ArduSub: the JSON peer advances in
/// lockstep (one physics step per exchange, none repeated or skipped, time only from the
/// states), the loop's frames are taken at the camera's frame times on that clock, and
/// each frame is rendered from exactly the physics pose ArduSub was sent for that time.
#[test]
fn sitl_loop_renders_each_frame_from_the_physics_state_it_holds() {
    use markhold::pipeline::Observers;
    use markhold::sim::hil::HilOptions;
    use markhold::sim::sitl_loop::{run_sitl_loop, SitlLoopOptions};
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;

    let stop = Arc::new(AtomicBool::new(false));
    let clock = Arc::new(fake_ardusub::Clock::default());
    let (mav_addr, vehicle, mav) = fake_ardusub::mavlink_vehicle(stop.clone(), clock.clone());
    let json_port = free_udp_port();
    let json = fake_ardusub::json_client(
        format!("127.0.0.1:{json_port}").parse().unwrap(),
        stop.clone(),
        clock,
    );
    let site = markhold::params::load(std::path::Path::new("params/pool.toml")).unwrap();
    let opts = SitlLoopOptions {
        vehicle_url: Some(format!("tcp:{mav_addr}")),
        json_port: Some(json_port),
        peer_timeout: std::time::Duration::from_secs(20),
        ..SitlLoopOptions::default()
    };
    let hil = HilOptions {
        seconds: 1.0,
        seed: 3,
        ..HilOptions::default()
    };
    let run = run_sitl_loop(&site, &opts, &hil, Observers::new());
    stop.store(true, Ordering::SeqCst);
    let states = json.join().unwrap();
    mav.join().unwrap();
    let run = run.unwrap_or_else(|e| panic!("{e:#}; fake vehicle {:?}", vehicle.lock().unwrap()));
    {
        let v = vehicle.lock().unwrap();
        assert!(v.armed && v.mode == 2, "armed in ALT_HOLD: {v:?}");
    }
    let fps = site.site.camera.fps;
    assert_eq!(run.frames, fps as u64);
    assert_eq!(run.frame_states.len(), run.frames as usize);
    assert_eq!(run.pose_mismatches, 0);
    // Lockstep: each state is one physics step after the one before (the JSON server
    // steps at the servo packets' frame rate, 400 Hz here).
    let dt = 1.0 / 400.0;
    for w in states.windows(2) {
        assert!(
            (w[1].0 - w[0].0 - dt).abs() < 1e-9,
            "states at {} then {}",
            w[0].0,
            w[1].0
        );
    }
    let (t0, _) = run.frame_states[0];
    for (k, (t, pose)) in run.frame_states.iter().enumerate() {
        // Frame k at the first physics step at or after the frame's time, k / fps after
        // the first frame's (within a physics step).
        let due = t0 + k as f64 / fps;
        assert!((t - due).abs() < dt + 1e-9, "frame {k} at {t}, due {due}");
        // ... rendered from the very pose ArduSub was sent at that time.
        let (_, p, q) = states
            .iter()
            .find(|s| s.0 == *t)
            .unwrap_or_else(|| panic!("frame {k}: no state at {t}"));
        let tr = pose.translation.vector;
        assert_eq!(p, &vec![tr.x, tr.y, tr.z], "frame {k} position");
        let rq = pose.rotation.quaternion();
        assert_eq!(q, &vec![rq.w, rq.i, rq.j, rq.k], "frame {k} attitude");
    }
    // The vehicle was free and driven: the frames do not all see the start pose.
    let first = run.frame_states[0].1.translation.vector;
    let last = run.frame_states.last().unwrap().1.translation.vector;
    assert!((last - first).norm() > 1e-4, "{first} {last}");
}
