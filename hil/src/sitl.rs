//! ArduPilot SITL JSON physics server: lets a user's ArduSub SITL
//! (`sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON`) fly our simulated vehicle.
//!
//! Protocol (ArduPilot libraries/SITL/SIM_JSON, see docs/reference/ardusub.md): ArduPilot sends
//! little-endian servo packets `u16 magic (18458 = 16 channels, 29569 = 32), u16
//! frame_rate, u32 frame_count, u16 pwm[16 | 32]` to UDP 9002; the physics answers each
//! with exactly one newline-framed compact JSON state (ArduPilot scans the text for
//! `"key":[` and reads the numbers; it has no JSON parser, so no spaces after colons).
//! A repeated frame_count is answered without stepping; a smaller one means ArduPilot
//! restarted, so the world resets (and time restarts, which ArduPilot reads as a reset).

use std::io::Write;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::mixer::MAX_MOTORS;
use crate::vehicle::{Vehicle, VehicleConfig, VehicleState};
use crate::HilError;
use markhold_config::{Checks, ConfigError};

/// Magic of a 16-channel servo packet.
pub const MAGIC_16: u16 = 18458;
/// Magic of a 32-channel servo packet.
pub const MAGIC_32: u16 = 29569;

/// `[sitl]` settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SitlConfig {
    /// Address to bind (ArduPilot's `--sim-address`, default loopback).
    pub bind_ip: std::net::IpAddr,
    /// UDP port (ArduPilot uses 9002, +10 per extra instance).
    pub port: u16,
}

impl Default for SitlConfig {
    fn default() -> Self {
        Self {
            bind_ip: std::net::IpAddr::from([127, 0, 0, 1]),
            port: 9002,
        }
    }
}

/// Why a servo packet was rejected (logged, not answered).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reject {
    /// Length matches neither 40 (16 channels) nor 72 (32 channels) bytes.
    Length(usize),
    /// Unknown magic number.
    Magic(u16),
    /// Length and magic disagree (e.g. 16-channel magic in a 72-byte packet).
    MagicLength { magic: u16, len: usize },
    /// Frame rate outside 10..=10000 Hz (step would be out of ArduPilot's 0..0.1 s).
    FrameRate(u16),
}

impl std::fmt::Display for Reject {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Reject::Length(n) => write!(f, "length {n} bytes, expected 40 or 72"),
            Reject::Magic(m) => write!(f, "magic {m}, expected {MAGIC_16} or {MAGIC_32}"),
            Reject::MagicLength { magic, len } => {
                write!(f, "magic {magic} does not match length {len}")
            }
            Reject::FrameRate(r) => write!(f, "frame_rate {r} Hz outside 10..=10000"),
        }
    }
}

/// A decoded servo packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServoPacket {
    pub frame_rate: u16,
    pub frame_count: u32,
    /// Channels 1..=16 or 1..=32 (the rest zero), PWM us.
    pub pwm: [u16; 32],
    pub channels: usize,
}

/// Decode a servo packet (little endian).
pub fn parse_servo_packet(b: &[u8]) -> Result<ServoPacket, Reject> {
    let channels = match b.len() {
        40 => 16,
        72 => 32,
        n => return Err(Reject::Length(n)),
    };
    let magic = u16::from_le_bytes([b[0], b[1]]);
    match (magic, channels) {
        (MAGIC_16, 16) | (MAGIC_32, 32) => {}
        (MAGIC_16, _) | (MAGIC_32, _) => {
            return Err(Reject::MagicLength {
                magic,
                len: b.len(),
            })
        }
        _ => return Err(Reject::Magic(magic)),
    }
    let frame_rate = u16::from_le_bytes([b[2], b[3]]);
    if !(10..=10_000).contains(&frame_rate) {
        return Err(Reject::FrameRate(frame_rate));
    }
    let frame_count = u32::from_le_bytes([b[4], b[5], b[6], b[7]]);
    let mut pwm = [0u16; 32];
    for (i, p) in pwm.iter_mut().take(channels).enumerate() {
        *p = u16::from_le_bytes([b[8 + 2 * i], b[9 + 2 * i]]);
    }
    Ok(ServoPacket {
        frame_rate,
        frame_count,
        pwm,
        channels,
    })
}

/// Counters of a server run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SitlStats {
    pub packets: u64,
    pub replies: u64,
    pub steps: u64,
    pub repeated: u64,
    pub resets: u64,
    pub missed_frames: u64,
    pub rejected: u64,
}

/// The physics server.
pub struct SitlServer {
    socket: UdpSocket,
    vehicle_cfg: VehicleConfig,
    start: Isometry3<f64>,
    seed: u64,
    vehicle: Vehicle,
    last_frame: Option<u32>,
    stats: SitlStats,
    rx: [u8; 512],
    tx: Vec<u8>,
    /// Where the held reply goes (see `receive`).
    pending: Option<SocketAddr>,
    last_pwm: [u16; 16],
}

fn finite(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// Write one JSON state, newline framed, compact (ArduPilot scans for `"key":[`).
pub fn write_state_json(out: &mut Vec<u8>, s: &VehicleState) {
    out.clear();
    let g = s.angvel_body_rps;
    let a = s.specific_force_body_mps2;
    let p = s.t_world_vehicle.translation.vector;
    let v = s.velocity_world_mps;
    let q = s.t_world_vehicle.rotation.quaternion();
    // Writing into a Vec cannot fail.
    let _ = write!(
        out,
        "\n{{\"timestamp\":{},\"imu\":{{\"gyro\":[{},{},{}],\"accel_body\":[{},{},{}]}},\
         \"position\":[{},{},{}],\"velocity\":[{},{},{}],\"quaternion\":[{},{},{},{}]}}\n",
        finite(s.time_s),
        finite(g.x),
        finite(g.y),
        finite(g.z),
        finite(a.x),
        finite(a.y),
        finite(a.z),
        finite(p.x),
        finite(p.y),
        finite(p.z),
        finite(v.x),
        finite(v.y),
        finite(v.z),
        finite(q.w),
        finite(q.i),
        finite(q.j),
        finite(q.k),
    );
}

impl SitlServer {
    /// Bind the server; the vehicle starts at `start` (world NED), at rest.
    pub fn bind(
        cfg: &SitlConfig,
        vehicle: &VehicleConfig,
        start: &Isometry3<f64>,
        seed: u64,
    ) -> Result<Self, HilError> {
        let addr = SocketAddr::new(cfg.bind_ip, cfg.port);
        let socket = UdpSocket::bind(addr).map_err(|source| HilError::Socket {
            what: "bind sitl udp",
            addr: addr.to_string(),
            source,
        })?;
        Ok(Self {
            socket,
            vehicle_cfg: vehicle.clone(),
            start: *start,
            seed,
            vehicle: Vehicle::new(vehicle, start, seed)?,
            last_frame: None,
            stats: SitlStats::default(),
            rx: [0; 512],
            tx: Vec::with_capacity(512),
            pending: None,
            last_pwm: [1500; 16],
        })
    }

    pub fn local_addr(&self) -> Result<SocketAddr, HilError> {
        self.socket.local_addr().map_err(|source| HilError::Socket {
            what: "local_addr sitl udp",
            addr: String::new(),
            source,
        })
    }

    pub fn stats(&self) -> SitlStats {
        self.stats
    }

    /// The simulated vehicle's state now.
    pub fn state(&self) -> VehicleState {
        self.vehicle.state()
    }

    /// Handle one datagram: `Ok(reply)` to send back, `Err(reason)` for a rejected packet
    /// (no reply, as ArduPilot expects nothing for a packet it did not send).
    pub fn handle_packet(&mut self, bytes: &[u8]) -> Result<&[u8], Reject> {
        self.stats.packets += 1;
        let pkt = match parse_servo_packet(bytes) {
            Ok(p) => p,
            Err(r) => {
                self.stats.rejected += 1;
                return Err(r);
            }
        };
        if (pkt.frame_rate as f64 - self.vehicle_cfg.physics_hz).abs() > 1e-9 {
            // ArduPilot asks for its own physics rate: rebuild the vehicle stepping at it.
            tracing::info!(
                from_hz = self.vehicle_cfg.physics_hz,
                to_hz = pkt.frame_rate,
                "sitl: physics rate set by ArduPilot"
            );
            let pose = self.vehicle.state().t_world_vehicle;
            self.vehicle_cfg.physics_hz = pkt.frame_rate as f64;
            match Vehicle::new(&self.vehicle_cfg, &pose, self.seed) {
                Ok(v) => self.vehicle = v,
                Err(e) => {
                    tracing::warn!(error = %e, "sitl: vehicle rebuild failed");
                    self.stats.rejected += 1;
                    return Err(Reject::FrameRate(pkt.frame_rate));
                }
            }
        }
        match self.last_frame {
            Some(last) if pkt.frame_count == last => {
                // Same frame again (ArduPilot re-sent it): answer, do not step.
                self.stats.repeated += 1;
            }
            Some(last) if pkt.frame_count < last => {
                tracing::info!(
                    last,
                    now = pkt.frame_count,
                    "sitl: frame count went back: reset"
                );
                self.stats.resets += 1;
                self.vehicle.reset(&self.start);
                self.step(&pkt);
            }
            Some(last) => {
                let gap = (pkt.frame_count - last - 1) as u64;
                if gap > 0 {
                    tracing::debug!(gap, "sitl: frames missed");
                    self.stats.missed_frames += gap;
                }
                self.step(&pkt);
            }
            None => self.step(&pkt),
        }
        self.last_frame = Some(pkt.frame_count);
        let state = self.vehicle.state();
        write_state_json(&mut self.tx, &state);
        self.stats.replies += 1;
        Ok(&self.tx)
    }

    fn step(&mut self, pkt: &ServoPacket) {
        // ArduSub's motor outputs 1..=8 are the thrusters. A channel with no pulse
        // (0) idles its ESC.
        let mut pwm = [1500u16; MAX_MOTORS];
        for (o, &p) in pwm.iter_mut().zip(pkt.pwm.iter()) {
            *o = if p == 0 { 1500 } else { p };
        }
        for (o, &p) in self.last_pwm.iter_mut().zip(pkt.pwm.iter()) {
            *o = if p == 0 { 1500 } else { p };
        }
        self.vehicle.step(&pwm);
        self.stats.steps += 1;
    }

    /// Receive one datagram (waiting at most `timeout`, wall clock) and step the physics
    /// by it, but hold the reply: ArduPilot waits for it (SIM_JSON.cpp `JSON::recv_fdm`
    /// blocks until a state arrives, and its clock advances only by the state's
    /// timestamp), so its time stands still until [`SitlServer::reply`]. Whatever the
    /// caller does in between (render a frame, run a control step at `state()`) happens at
    /// exactly this physics time: lockstep. `Ok(None)` when nothing arrived; a rejected
    /// packet is logged and leaves nothing to reply.
    pub fn receive(&mut self, timeout: Duration) -> Result<Option<SitlStats>, HilError> {
        let t = timeout.max(Duration::from_millis(1));
        self.socket
            .set_read_timeout(Some(t))
            .map_err(|source| HilError::Socket {
                what: "set_read_timeout sitl udp",
                addr: String::new(),
                source,
            })?;
        let (n, from) = match self.socket.recv_from(&mut self.rx) {
            Ok(x) => x,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::ConnectionReset
                ) =>
            {
                return Ok(None)
            }
            Err(source) => {
                return Err(HilError::Socket {
                    what: "recv sitl udp",
                    addr: String::new(),
                    source,
                })
            }
        };
        let rx = self.rx;
        match self.handle_packet(&rx[..n]) {
            Ok(_) => self.pending = Some(from),
            Err(reason) => {
                tracing::warn!(%from, len = n, %reason, "sitl: servo packet rejected");
            }
        }
        Ok(Some(self.stats))
    }

    /// Hold the vehicle at `pose`, at rest (time goes on), and make the held reply say
    /// so: a vehicle held still by hand until its autopilot is ready, as on a real dive.
    pub fn hold_at(&mut self, pose: &Isometry3<f64>) {
        self.carry(pose, &nalgebra::Vector3::zeros());
    }

    /// Carry the vehicle by hand: put it at `pose` moving at `velocity_world_mps` (world
    /// NED), level flight through the water with no acceleration (the accelerometer reads
    /// gravity only), and make the held reply say so. The physics restarts from rest at
    /// `pose` when let go.
    pub fn carry(&mut self, pose: &Isometry3<f64>, velocity_world_mps: &nalgebra::Vector3<f64>) {
        self.vehicle.teleport(pose);
        let mut state = self.vehicle.state();
        state.velocity_world_mps = *velocity_world_mps;
        state.angvel_body_rps = nalgebra::Vector3::zeros();
        state.specific_force_body_mps2 = pose.rotation.inverse()
            * nalgebra::Vector3::new(0.0, 0.0, -crate::vehicle::GRAVITY_MPS2);
        write_state_json(&mut self.tx, &state);
    }

    /// The start pose the server was bound with.
    pub fn start_pose(&self) -> Isometry3<f64> {
        self.start
    }

    /// A reply is held (a packet was received and not yet answered).
    pub fn holding(&self) -> bool {
        self.pending.is_some()
    }

    /// Send the held reply (the state after the last step), if any.
    pub fn reply(&mut self) -> Result<(), HilError> {
        if let Some(from) = self.pending.take() {
            if let Err(e) = self.socket.send_to(&self.tx, from) {
                tracing::warn!(%from, error = %e, "sitl: reply not sent");
            }
        }
        Ok(())
    }

    /// The servo outputs of the last packet that stepped the physics (1500 where a
    /// channel had no pulse), channels 1..=16.
    pub fn last_pwm(&self) -> [u16; 16] {
        self.last_pwm
    }

    /// Receive and answer one datagram, waiting at most `timeout` (wall clock).
    /// Returns false when nothing arrived.
    pub fn serve_one(&mut self, timeout: Duration) -> Result<bool, HilError> {
        let got = self.receive(timeout)?.is_some();
        self.reply()?;
        Ok(got)
    }

    /// Serve until `max_packets` datagrams were handled or `max_wall` elapsed (tests).
    pub fn run_bounded(
        &mut self,
        max_packets: u64,
        max_wall: Duration,
    ) -> Result<SitlStats, HilError> {
        let start = Instant::now();
        let first = self.stats.packets;
        while self.stats.packets - first < max_packets {
            let Some(left) = max_wall.checked_sub(start.elapsed()) else {
                break;
            };
            self.serve_one(left.min(Duration::from_millis(100)))?;
        }
        Ok(self.stats)
    }

    /// Serve until `stop` is set (checked at least every 100 ms).
    pub fn run_until(&mut self, stop: &AtomicBool) -> Result<SitlStats, HilError> {
        while !stop.load(Ordering::Relaxed) {
            self.serve_one(Duration::from_millis(100))?;
        }
        Ok(self.stats)
    }

    /// Serve forever (`markhold sitl`).
    pub fn run(&mut self) -> Result<(), HilError> {
        let never = AtomicBool::new(false);
        self.run_until(&never).map(|_| ())
    }
}

impl SitlConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.port == 0 {
            // Port 0 works (tests) but ArduPilot could never find it.
            tracing::debug!("sitl.port = 0: an ephemeral port, for tests");
        }
        let ip = self.bind_ip;
        Checks::new("sitl")
            .check("bind_ip", ip, !ip.is_multicast(), "a unicast address")
            .done()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn packet(magic: u16, rate: u16, frame: u32, pwm: &[u16]) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&magic.to_le_bytes());
        b.extend_from_slice(&rate.to_le_bytes());
        b.extend_from_slice(&frame.to_le_bytes());
        for p in pwm {
            b.extend_from_slice(&p.to_le_bytes());
        }
        b
    }

    #[test]
    fn parses_16_and_32_channel_packets_and_rejects_the_rest() {
        let mut pwm = [1500u16; 32];
        pwm[0] = 1600;
        pwm[31] = 1234;
        let p = parse_servo_packet(&packet(MAGIC_16, 400, 7, &pwm[..16])).unwrap();
        assert_eq!(
            (p.frame_rate, p.frame_count, p.channels, p.pwm[0]),
            (400, 7, 16, 1600)
        );
        assert_eq!(p.pwm[16], 0);
        let p = parse_servo_packet(&packet(MAGIC_32, 1200, 9, &pwm)).unwrap();
        assert_eq!((p.channels, p.pwm[31]), (32, 1234));
        assert_eq!(
            parse_servo_packet(&packet(MAGIC_16, 400, 7, &pwm)),
            Err(Reject::MagicLength {
                magic: MAGIC_16,
                len: 72
            })
        );
        assert_eq!(
            parse_servo_packet(&packet(1, 400, 7, &pwm[..16])),
            Err(Reject::Magic(1))
        );
        assert_eq!(parse_servo_packet(&[0u8; 12]), Err(Reject::Length(12)));
        assert_eq!(
            parse_servo_packet(&packet(MAGIC_16, 5, 7, &pwm[..16])),
            Err(Reject::FrameRate(5))
        );
    }

    #[test]
    fn json_is_compact_and_scannable() {
        let cfg = VehicleConfig::default();
        let v = Vehicle::new(&cfg, &Isometry3::translation(1.0, 2.0, 3.0), 1).unwrap();
        let mut out = Vec::new();
        write_state_json(&mut out, &v.state());
        let text = std::str::from_utf8(&out).unwrap();
        assert!(text.starts_with("\n{") && text.ends_with("}\n"));
        assert!(!text.contains(": ") && !text.contains(", "), "{text}");
        assert!(text.contains("\"position\":[1,2,3]"), "{text}");
        assert!(text.contains("\"quaternion\":[1,0,0,0]"), "{text}");
    }
}
