//! A tiny fake ArduSub over real loopback sockets: heartbeats, COMMAND_ACKs, telemetry, and
//! a kinematic vehicle moved by the RC overrides it receives (one fixed step per override,
//! so the plant runs on the controller's clock, not on the wall clock).

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavHeader, MavlinkReader};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Hard bound for any fake-vehicle thread.
pub const FAKE_DEADLINE: Duration = Duration::from_secs(60);
pub const STEP_S: f64 = 1.0 / 30.0;

#[derive(Clone, Debug)]
pub struct Rc {
    pub sysid: u32,
    pub compid: u8,
    pub target: (u8, u8),
    pub ch: [u16; 8],
}

#[derive(Clone, Debug, Default)]
pub struct Rec {
    pub rc: Vec<Rc>,
    pub manual: Vec<(u32, MANUAL_CONTROL_DATA)>,
    pub gcs_heartbeats: Vec<(u32, u8, HEARTBEAT_DATA)>,
    pub commands: Vec<(u32, COMMAND_LONG_DATA)>,
    pub other: Vec<(u32, String)>,
    pub setpoints: Vec<SET_POSITION_TARGET_LOCAL_NED_DATA>,
    pub vision: Vec<VISION_POSITION_ESTIMATE_DATA>,
    pub origins: Vec<(u32, i32, i32, i32)>,
    pub armed: bool,
    pub mode: u32,
    /// Vehicle pose in the marker frame: position and yaw offset from facing the marker.
    pub pos_m: [f64; 3],
    pub yaw: f64,
    pub steps: u64,
    pub heartbeats_on: bool,
    /// Drop this many COMMAND_LONGs for arm before acknowledging (tests retries).
    pub drop_arm_commands: u32,
    /// Water current in the marker frame, m/s.
    pub current_m: [f64; 3],
    pub disconnect_now: bool,
}

pub fn facing() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        Vector3::new(0.0, 0.0, -1.0),
        Vector3::new(1.0, 0.0, 0.0),
        Vector3::new(0.0, -1.0, 0.0),
    ]))
}

impl Rec {
    pub fn t_marker_vehicle(&self) -> Isometry3<f64> {
        let r = facing() * Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw);
        Isometry3::from_parts(
            Translation3::new(self.pos_m[0], self.pos_m[1], self.pos_m[2]),
            UnitQuaternion::from_rotation_matrix(&r),
        )
    }

    /// One plant step from an RC override: MANUAL + armed only, T200 dead band applied.
    fn step(&mut self, ch: &[u16; 8]) {
        self.steps += 1;
        if !(self.armed && self.mode == 19) {
            return;
        }
        let n = |p: u16| {
            let d = f64::from(p) - 1500.0;
            if d.abs() < 28.0 {
                0.0
            } else {
                (d - 28.0f64.copysign(d)) / 372.0
            }
        };
        let (surge, sway, heave, yaw) = (n(ch[4]), n(ch[5]), -n(ch[2]), n(ch[3]));
        let v_b = Vector3::new(surge, sway, heave) * 0.5;
        let r = facing() * Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw);
        let v_m = r * v_b + Vector3::from(self.current_m);
        for i in 0..3 {
            self.pos_m[i] += v_m[i] * STEP_S;
        }
        self.yaw += yaw * 1.0 * STEP_S;
    }
}

pub enum Kind {
    /// Fake binds UDP; the link uses udpout to it.
    UdpServer,
    /// Fake listens on TCP; the link uses tcpout.
    TcpServer,
    /// Fake connects to the link's tcpin address.
    TcpClient(SocketAddr),
    /// Fake sends to the link's udpin address.
    UdpClient(SocketAddr),
}

pub struct FakeVehicle {
    pub addr: Option<SocketAddr>,
    pub rec: Arc<Mutex<Rec>>,
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl Drop for FakeVehicle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

enum Io {
    Udp(UdpSocket, Option<SocketAddr>),
    Tcp(TcpStream),
}

fn frame(seq: u8, msg: &MavMessage) -> Vec<u8> {
    let mut v = Vec::new();
    let h = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: seq,
    };
    mavlink::write_v2_msg(&mut v, h, msg).expect("serialize");
    v
}

impl FakeVehicle {
    pub fn start(kind: Kind) -> Self {
        let rec = Arc::new(Mutex::new(Rec {
            heartbeats_on: true,
            pos_m: [0.0, 0.0, 1.0],
            ..Default::default()
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let (addr, listener, io) = match kind {
            Kind::UdpServer => {
                let s = UdpSocket::bind("127.0.0.1:0").unwrap();
                (Some(s.local_addr().unwrap()), None, Some(Io::Udp(s, None)))
            }
            Kind::UdpClient(a) => {
                let s = UdpSocket::bind("127.0.0.1:0").unwrap();
                (None, None, Some(Io::Udp(s, Some(a))))
            }
            Kind::TcpServer => {
                let l = TcpListener::bind("127.0.0.1:0").unwrap();
                (Some(l.local_addr().unwrap()), Some(l), None)
            }
            Kind::TcpClient(a) => {
                let s = TcpStream::connect_timeout(&a, Duration::from_secs(2)).unwrap();
                (None, None, Some(Io::Tcp(s)))
            }
        };
        let r2 = rec.clone();
        let s2 = stop.clone();
        let handle = std::thread::spawn(move || run(io, listener, r2, s2));
        Self {
            addr,
            rec,
            stop,
            handle: Some(handle),
        }
    }

    pub fn rec(&self) -> std::sync::MutexGuard<'_, Rec> {
        self.rec.lock().unwrap()
    }
}

fn run(
    mut io: Option<Io>,
    listener: Option<TcpListener>,
    rec: Arc<Mutex<Rec>>,
    stop: Arc<AtomicBool>,
) {
    let t0 = Instant::now();
    let mut seq = 0u8;
    let mut last_hb = Instant::now() - Duration::from_secs(1);
    let mut last_hb_step = 0u64;
    let mut buf = vec![0u8; 4096];
    let mut tcp_acc: Vec<u8> = Vec::new();
    if let Some(l) = &listener {
        l.set_nonblocking(true).unwrap();
    }
    while !stop.load(Ordering::SeqCst) && t0.elapsed() < FAKE_DEADLINE {
        // Accept a (new) TCP client.
        if io.is_none() {
            if let Some(l) = &listener {
                match l.accept() {
                    Ok((s, _)) => {
                        s.set_nodelay(true).unwrap();
                        io = Some(Io::Tcp(s));
                        tcp_acc.clear();
                    }
                    Err(_) => {
                        std::thread::sleep(Duration::from_millis(2));
                        continue;
                    }
                }
            }
        }
        if rec.lock().unwrap().disconnect_now {
            rec.lock().unwrap().disconnect_now = false;
            if let Some(Io::Tcp(s)) = &io {
                let _ = s.shutdown(std::net::Shutdown::Both);
            }
            io = None;
            continue;
        }
        let Some(cur) = io.as_mut() else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        let mut msgs: Vec<(MavHeader, MavMessage)> = Vec::new();
        let broken = match cur {
            Io::Udp(s, peer) => {
                receive_udp(s, peer, &mut buf, &mut msgs);
                false
            }
            Io::Tcp(s) => receive_tcp(s, &mut buf, &mut tcp_acc, &mut msgs),
        };
        if broken {
            io = None;
            continue;
        }
        let mut out: Vec<MavMessage> = Vec::new();
        {
            let mut g = rec.lock().unwrap();
            for (h, m) in msgs {
                g.answer(&h, m, &mut out);
            }
            // Heartbeat + telemetry: every 10 plant steps or setpoints (loop time), and at
            // least at 10 Hz of wall time when nothing steps the plant.
            let due =
                g.steps >= last_hb_step + 10 || last_hb.elapsed() > Duration::from_millis(100);
            if g.heartbeats_on && due {
                last_hb = Instant::now();
                last_hb_step = g.steps;
                g.telemetry(&mut out);
            }
        }
        for m in out {
            let bytes = frame(seq, &m);
            seq = seq.wrapping_add(1);
            match cur {
                Io::Udp(s, Some(p)) => {
                    let _ = s.send_to(&bytes, *p);
                }
                Io::Udp(_, None) => {}
                Io::Tcp(s) => {
                    let _ = s.write_all(&bytes);
                }
            }
        }
    }
}

/// Block briefly for the first datagram, then drain without waiting (socket timeouts are
/// rounded up to the kernel tick). The sender becomes the peer.
fn receive_udp(
    s: &UdpSocket,
    peer: &mut Option<SocketAddr>,
    buf: &mut [u8],
    msgs: &mut Vec<(MavHeader, MavMessage)>,
) {
    s.set_nonblocking(false).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(2))).unwrap();
    while let Ok((n, from)) = s.recv_from(buf) {
        *peer = Some(from);
        let mut r = MavlinkReader::new(&buf[..n]);
        while let Ok(m) = r.read_any_message::<MavMessage>() {
            msgs.push(m);
        }
        s.set_nonblocking(true).unwrap();
    }
}

/// Reads what the TCP client sent and parses whole frames, keeping a trailing partial
/// frame in `acc`. True when the client closed.
fn receive_tcp(
    s: &mut TcpStream,
    buf: &mut [u8],
    acc: &mut Vec<u8>,
    msgs: &mut Vec<(MavHeader, MavMessage)>,
) -> bool {
    s.set_read_timeout(Some(Duration::from_millis(2))).unwrap();
    let broken = match s.read(buf) {
        Ok(0) => true,
        Ok(n) => {
            acc.extend_from_slice(&buf[..n]);
            false
        }
        Err(_) => false,
    };
    loop {
        let Some(start) = acc.iter().position(|b| *b == 0xFD) else {
            acc.clear();
            break;
        };
        acc.drain(..start);
        if acc.len() < 10 {
            break;
        }
        let sig = if acc[2] & 1 != 0 { 13 } else { 0 };
        let total = 10 + acc[1] as usize + 2 + sig;
        if acc.len() < total {
            break;
        }
        let mut r = MavlinkReader::new(&acc[..total]);
        if let Ok(m) = r.read_any_message::<MavMessage>() {
            msgs.push(m);
            acc.drain(..total);
        } else {
            acc.drain(..1);
        }
    }
    broken
}

impl Rec {
    /// Records one message from the link and queues the vehicle's answer, if any.
    fn answer(&mut self, h: &MavHeader, m: MavMessage, out: &mut Vec<MavMessage>) {
        match m {
            MavMessage::RC_CHANNELS_OVERRIDE(d) => {
                let ch = [
                    d.chan1_raw,
                    d.chan2_raw,
                    d.chan3_raw,
                    d.chan4_raw,
                    d.chan5_raw,
                    d.chan6_raw,
                    d.chan7_raw,
                    d.chan8_raw,
                ];
                self.rc.push(Rc {
                    sysid: h.system_id,
                    compid: h.component_id,
                    target: (d.target_system, d.target_component),
                    ch,
                });
                // ArduSub drops pilot input from anyone but its GCS.
                if h.system_id == 255 {
                    self.step(&ch);
                }
            }
            MavMessage::MANUAL_CONTROL(d) => self.manual.push((h.system_id, d)),
            MavMessage::HEARTBEAT(d) => self.gcs_heartbeats.push((h.system_id, h.component_id, d)),
            MavMessage::COMMAND_LONG(d) => self.command(h, d, out),
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(d) => {
                // In setpoint mode a setpoint is the loop's tick: the fake's
                // heartbeats follow loop time, as they do with overrides.
                self.setpoints.push(d);
                self.steps += 1;
            }
            MavMessage::VISION_POSITION_ESTIMATE(d) => self.vision.push(d),
            #[allow(deprecated)]
            MavMessage::SET_GPS_GLOBAL_ORIGIN(d) => {
                self.origins
                    .push((h.system_id, d.latitude, d.longitude, d.altitude))
            }
            other => self.other.push((h.system_id, format!("{other:?}"))),
        }
    }

    /// A COMMAND_LONG: arm and mode change the vehicle, everything else is accepted; each
    /// is acknowledged (unless arm commands are being dropped).
    fn command(&mut self, h: &MavHeader, d: COMMAND_LONG_DATA, out: &mut Vec<MavMessage>) {
        self.commands.push((h.system_id, d.clone()));
        let result = match d.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                if self.drop_arm_commands > 0 {
                    self.drop_arm_commands -= 1;
                    return;
                }
                self.armed = d.param1 > 0.5;
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_SET_MODE => {
                let m = d.param2 as u32;
                if [0, 1, 2, 3, 4, 7, 9, 16, 19, 20, 21].contains(&m) {
                    self.mode = m;
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            _ => MavResult::MAV_RESULT_ACCEPTED,
        };
        out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command: d.command,
            result,
            target_system: h.system_id as u8,
            target_component: h.component_id,
            ..Default::default()
        }));
    }

    /// The vehicle's heartbeat and telemetry streams, one message each.
    fn telemetry(&self, out: &mut Vec<MavMessage>) {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        out.push(markhold_testkit::sub_heartbeat(self.mode, base));
        out.push(MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: 1000,
            roll: 0.01,
            pitch: -0.02,
            yaw: self.yaw as f32,
            rollspeed: 0.0,
            pitchspeed: 0.0,
            yawspeed: 0.1,
        }));
        // 2 m deep in fresh water.
        out.push(MavMessage::SCALED_PRESSURE2(SCALED_PRESSURE2_DATA {
            time_boot_ms: 1000,
            press_abs: ((101_325.0 + 997.0 * 9.80665 * 2.0) / 100.0) as f32,
            press_diff: 0.0,
            temperature: 1234,
            ..Default::default()
        }));
        out.push(MavMessage::SERVO_OUTPUT_RAW(SERVO_OUTPUT_RAW_DATA {
            time_usec: 1,
            servo1_raw: 1501,
            servo2_raw: 1502,
            servo3_raw: 1503,
            servo4_raw: 1504,
            servo5_raw: 1505,
            servo6_raw: 1506,
            servo7_raw: 1507,
            servo8_raw: 1508,
            port: 0,
            ..Default::default()
        }));
        out.push(MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: 1000,
            x: -(self.pos_m[2] as f32),
            y: self.pos_m[0] as f32,
            z: 2.0,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
        }));
    }
}
