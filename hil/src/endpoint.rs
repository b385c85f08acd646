//! A vehicle endpoint that speaks MAVLink like ArduSub, over UDP (and optionally TCP) on
//! loopback: heartbeat, arming, modes, pilot input with ArduSub's filters, guided targets,
//! vision position estimates, requested telemetry streams, and the pilot-input and GCS
//! failsafes. Every time it sees is simulation time passed in by the caller.
//!
//! Facts from ArduSub 4.5 (see docs/reference/ardusub.md and docs/design/hil.md
//! "Conformance"): pilot input only from the GCS system id, MANUAL_CONTROL's target must be
//! our system id, manual control is scaled by the joystick gain, an RC override that
//! expires (RC_OVERRIDE_TIME) or is released leaves the channel at its last value (no RC
//! receiver) until the pilot-input failsafe centres every control and disarms
//! (FS_PILOT_INPUT, FS_PILOT_TIMEOUT), each mode reads each channel as ArduSub does (see
//! `control`), ALT_HOLD and SURFACE need a healthy depth sensor and a failed one switches
//! the depth modes to MANUAL, and the GCS failsafe acts after FS_GCS_TIMEOUT. The
//! parameters are one [`ArduSubParams`] (ArduSub 4.5's defaults, or a vehicle's file).
//!
//! Telemetry can be sent late (`set_telemetry_latency`): attitude, position, depth and
//! the other sensor messages then report the vehicle's state that much simulation time
//! ago, stamped with the time they are sent, like an estimate that lags its sensors.

pub mod consistency;
mod control;
pub mod params;
pub mod signing;

use std::collections::VecDeque;
use std::io::ErrorKind;
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::path::PathBuf;

use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavFrame, MavMessage, MavModeFlag, MavResult, MavState, MavType,
    PositionTargetTypemask, ATTITUDE_DATA, ATTITUDE_QUATERNION_DATA, COMMAND_ACK_DATA,
    COMMAND_LONG_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, MANUAL_CONTROL_DATA,
    RC_CHANNELS_DATA, RC_CHANNELS_OVERRIDE_DATA, SCALED_PRESSURE2_DATA, SERVO_OUTPUT_RAW_DATA,
    SET_POSITION_TARGET_GLOBAL_INT_DATA, SET_POSITION_TARGET_LOCAL_NED_DATA,
    VISION_POSITION_ESTIMATE_DATA,
};
use mavlink::error::MessageReadError;
use mavlink::{MAVLinkMessageRaw, MavHeader, MavlinkReader, MavlinkVersion};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

pub use consistency::VisionNees;
pub use control::ControlGains;
use control::{Controller, NavEstimate};
pub use params::ArduSubParams;
use signing::{Signing, Verdict};

use crate::mixer::MAX_MOTORS;
use crate::vehicle::{VehicleState, GRAVITY_MPS2};
use crate::HilError;
use markhold_config::{Checks, ConfigError};

/// ArduSub flight modes (HEARTBEAT.custom_mode).
pub mod mode {
    pub const STABILIZE: u32 = 0;
    pub const ALT_HOLD: u32 = 2;
    pub const GUIDED: u32 = 4;
    pub const SURFACE: u32 = 9;
    pub const POSHOLD: u32 = 16;
    pub const MANUAL: u32 = 19;

    /// Modes this endpoint flies.
    pub const SUPPORTED: [u32; 6] = [STABILIZE, ALT_HOLD, GUIDED, SURFACE, POSHOLD, MANUAL];

    /// Modes that need a depth sensor (`control_check_barometer` in their `init`).
    pub fn needs_depth(mode: u32) -> bool {
        matches!(mode, ALT_HOLD | SURFACE)
    }

    /// Modes that need a position estimate (`requires_GPS`).
    pub fn needs_position(mode: u32) -> bool {
        matches!(mode, GUIDED | POSHOLD)
    }

    pub fn name(mode: u32) -> &'static str {
        match mode {
            STABILIZE => "STABILIZE",
            ALT_HOLD => "ALT_HOLD",
            GUIDED => "GUIDED",
            SURFACE => "SURFACE",
            POSHOLD => "POSHOLD",
            MANUAL => "MANUAL",
            _ => "UNKNOWN",
        }
    }
}

/// Telemetry messages that can be requested with SET_MESSAGE_INTERVAL.
pub const STREAMABLE_IDS: [u32; 6] = [30, 31, 32, 36, 65, 137];

/// `[endpoint]` section: how the simulated vehicle talks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EndpointConfig {
    /// Our MAVLink system id (ArduSub SYSID_THISMAV).
    pub system_id: u8,
    pub component_id: u8,
    /// Only pilot input from this system id is used (SYSID_MYGCS / MAV_GCS_SYSID).
    pub gcs_system_id: u8,
    /// Address the UDP (and TCP) sockets listen on: loopback unless configured.
    pub bind_ip: IpAddr,
    /// UDP port on `bind_ip` (0 = any free port).
    pub udp_port: u16,
    /// Also serve MAVLink over TCP on `bind_ip`.
    pub tcp_enabled: bool,
    /// TCP port on `bind_ip` (0 = any free port).
    pub tcp_port: u16,
    /// MAVLink 2 signing key (32 raw bytes or 64 hex digits, the format of markhold's
    /// `link.signing_key_file`): everything sent is signed, everything received verified.
    pub signing_key_file: Option<PathBuf>,
    /// Signing link id of what we send.
    pub signing_link_id: u8,
    /// With a key: also accept unsigned frames (MAVLink 1, unsigned MAVLink 2). False:
    /// signing is required and unsigned input is dropped.
    pub signing_accept_unsigned: bool,
    /// ArduSub's parameters (joystick gain, dead zones, pilot speeds, failsafes, ...):
    /// ArduSub 4.5's defaults unless a vehicle's parameter file gives them
    /// (`[vehicle] params_file`, set by the rig).
    #[serde(skip)]
    pub params: ArduSubParams,
    /// The vehicle has a depth sensor (ALT_HOLD and SURFACE need one).
    pub depth_sensor: bool,
    /// Guided targets expire after this long.
    pub guided_timeout_s: f64,
    /// Vision position estimates older than this are not used.
    pub vision_timeout_s: f64,
    /// Heartbeat rate, Hz.
    pub heartbeat_hz: f64,
    /// Mode at start-up (ArduSub boots in MANUAL on a BlueROV2 image).
    pub initial_mode: u32,
    /// Gains of the stabilized, depth, position and guided controllers.
    pub gains: ControlGains,
}

impl Default for EndpointConfig {
    fn default() -> Self {
        Self {
            system_id: 1,
            component_id: 1,
            gcs_system_id: 255,
            bind_ip: IpAddr::from([127, 0, 0, 1]),
            udp_port: 0,
            tcp_enabled: false,
            tcp_port: 0,
            signing_key_file: None,
            signing_link_id: 0,
            signing_accept_unsigned: false,
            params: ArduSubParams::default(),
            depth_sensor: true,
            guided_timeout_s: 3.0,
            vision_timeout_s: 2.0,
            heartbeat_hz: 1.0,
            initial_mode: mode::MANUAL,
            gains: ControlGains::default(),
        }
    }
}

impl EndpointConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let ip = self.bind_ip;
        let positive = "a positive number";
        let unicast = !(ip.is_multicast() || ip.is_unspecified());
        let modes = "0 (STABILIZE), 2 (ALT_HOLD), 4 (GUIDED), 9 (SURFACE), 16 (POSHOLD) or 19 (MANUAL)";
        Checks::new("endpoint")
            .range("system_id", self.system_id, 1.., "1..=255")
            .check("bind_ip", ip, unicast, "one unicast address (127.0.0.1 by default; not 0.0.0.0)")
            .positive("guided_timeout_s", self.guided_timeout_s, positive)
            .positive("vision_timeout_s", self.vision_timeout_s, positive)
            .positive("heartbeat_hz", self.heartbeat_hz, positive)
            .one_of("initial_mode", self.initial_mode, &mode::SUPPORTED, modes)
            .then(|| self.gains.validate())
            .then(|| self.params.validate())
            .done()
    }
}

/// The UDP side: a non-blocking socket, its receive buffer, and the last peer (a udpin
/// endpoint answers the last peer that spoke, like ArduPilot and BlueOS). A sender becomes
/// the peer only with a datagram that holds a CRC-valid MAVLink frame that parses (and,
/// with signing, carries a valid signature): garbage or unsigned traffic from another
/// port cannot take the telemetry away.
struct UdpLink {
    socket: UdpSocket,
    buf: Box<[u8; 65536]>,
    peer: Option<SocketAddr>,
}

/// Every CRC-valid MAVLink frame in one datagram, in order. Each datagram is parsed on
/// its own (a datagram holds whole frames), so garbage or a truncated frame in one
/// datagram cannot swallow the next, and a claimed-but-bogus frame is resynchronised
/// one byte later. Allocation-free (the stream reader of the mavlink crate is used for
/// TCP, where bytes do flow across reads). `on_frame` also gets the whole frame's bytes
/// (magic to signature), for signature checks.
pub(crate) fn scan_datagram(
    d: &[u8],
    mut on_frame: impl FnMut(MavHeader, Result<MavMessage, mavlink::error::ParserError>, &[u8]),
) {
    use mavlink::Message;
    let mut i = 0;
    while i < d.len() {
        let rest = &d[i..];
        let (v2, header_len) = match rest[0] {
            0xFD => (true, 10),
            0xFE => (false, 6),
            _ => {
                i += 1;
                continue;
            }
        };
        if rest.len() < header_len {
            break;
        }
        let payload_len = rest[1] as usize;
        let (signature_len, msg_id, header) = if v2 {
            // Only the "signed" incompatibility flag is understood.
            if rest[2] & !0x01 != 0 {
                i += 1;
                continue;
            }
            let sig = if rest[2] & 0x01 != 0 { 13 } else { 0 };
            let id = u32::from_le_bytes([rest[7], rest[8], rest[9], 0]);
            let h = MavHeader {
                sequence: rest[4],
                system_id: rest[5] as u32,
                component_id: rest[6],
            };
            (sig, id, h)
        } else {
            let h = MavHeader {
                sequence: rest[2],
                system_id: rest[3] as u32,
                component_id: rest[4],
            };
            (0, rest[5] as u32, h)
        };
        let crc_at = header_len + payload_len;
        let total = crc_at + 2 + signature_len;
        if rest.len() < total {
            i += 1;
            continue;
        }
        let expected = u16::from_le_bytes([rest[crc_at], rest[crc_at + 1]]);
        if mavlink::calculate_crc(&rest[1..crc_at], MavMessage::extra_crc(msg_id)) != expected {
            i += 1;
            continue;
        }
        let version = if v2 {
            MavlinkVersion::V2
        } else {
            MavlinkVersion::V1
        };
        on_frame(
            header,
            MavMessage::parse(version, msg_id, &rest[header_len..crc_at]),
            &rest[..total],
        );
        i += total;
    }
}

/// A TCP stream as the frame decoder's byte source.
struct TcpSource(TcpStream);

impl std::io::Read for TcpSource {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.0.read(buf)
    }
}

struct TcpClient {
    reader: MavlinkReader<TcpSource>,
    peer: SocketAddr,
}

/// Pilot input as ArduSub's RC input channels (1-based: 1 pitch, 2 roll, 3 throttle,
/// 4 yaw, 5 forward, 6 lateral, ...), PWM us: `radio_in`. An override that expires
/// (RC_OVERRIDE_TIME) or is released leaves the channel at its last value: with no RC
/// receiver, `RC_Channel::update()` keeps `radio_in` when it has no override
/// (libraries/RC_Channel/RC_Channel.cpp). Channels 1-8 start at 1500 (`init_rc_in`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct RcInput {
    pwm: [u16; 18],
}

impl RcInput {
    fn new() -> Self {
        Self { pwm: [1500; 18] }
    }

    /// Channel `ch` (1-based) now.
    fn channel(&self, ch: usize) -> u16 {
        self.pwm[ch - 1]
    }

    /// `Sub::set_neutral_controls()`: the six control channels to 1500.
    fn neutral(&mut self) {
        self.pwm[..6].fill(1500);
    }
}

/// A guided-mode target in the navigation frame (the frame of the vision estimates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct GuidedTarget {
    pub position: Option<Vector3<f64>>,
    pub velocity: Option<Vector3<f64>>,
    pub yaw: Option<f64>,
    pub yaw_rate: Option<f64>,
    pub stamp_s: f64,
}

/// Counters a test or the rig can read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EndpointStats {
    /// Messages decoded (all senders).
    pub messages: u64,
    /// Pilot inputs accepted (RC_CHANNELS_OVERRIDE, MANUAL_CONTROL from the GCS id).
    pub pilot_inputs: u64,
    /// Pilot inputs dropped (wrong sender or target).
    pub pilot_inputs_dropped: u64,
    /// Guided position / velocity targets accepted.
    pub guided_targets: u64,
    /// ALT_HOLD depth targets accepted (SET_POSITION_TARGET_GLOBAL_INT).
    pub depth_targets: u64,
    /// Inputs a lock-step client sends once per frame that arrived addressed to us,
    /// accepted or not: RC_CHANNELS_OVERRIDE, MANUAL_CONTROL, SET_POSITION_TARGET_*.
    pub lockstep_inputs: u64,
    /// Frames that failed to decode (bad CRC is skipped silently by the decoder; this
    /// counts payloads that did not parse).
    pub parse_errors: u64,
    /// UDP datagrams with no acceptable frame in them (garbage, truncated, CRC-invalid,
    /// unsigned or badly signed): their sender never becomes the peer.
    pub rejected_datagrams: u64,
    /// Frames dropped because signing is required and they were unsigned (or MAVLink 1).
    pub rejected_unsigned: u64,
    /// Frames dropped for a signature that is not ours (wrong key) or a replayed one.
    pub rejected_signature: u64,
    /// Failsafe disarms.
    pub failsafe_pilot: u64,
    pub failsafe_gcs: u64,
    /// Delayed inputs applied early because the delay queue was full.
    pub delay_overflows: u64,
}

/// Inputs held back by the frame-to-thrust delay at most at once: several messages a
/// frame for up to 1 s at 30 frames a second, with room to spare.
const DELAY_QUEUE: usize = 256;

/// The simulated autopilot's MAVLink side.
pub struct VehicleEndpoint {
    cfg: EndpointConfig,
    udp: UdpLink,
    tcp: Option<TcpListener>,
    tcp_clients: Vec<TcpClient>,
    sequence: u8,
    armed: bool,
    mode: u32,
    arm_time_s: f64,
    last_pilot_s: Option<f64>,
    last_gcs_heartbeat_s: Option<f64>,
    /// The pilot-input and GCS failsafes have acted (each once, until input returns).
    pilot_failsafe: bool,
    gcs_failsafe: bool,
    /// The depth sensor reads (and its failure was acted on).
    depth_healthy: bool,
    depth_failsafe: bool,
    rc: RcInput,
    guided: Option<GuidedTarget>,
    vision: Option<(f64, Isometry3<f64>)>,
    /// Navigation frame alignment: t_nav_world from the last vision estimate.
    t_nav_world: Option<Isometry3<f64>>,
    vision_aligned_at: Option<f64>,
    streams: Vec<(u32, f64, f64)>,
    next_heartbeat_s: f64,
    stats: EndpointStats,
    controller: Controller,
    /// Pending COMMAND_ACKs and one-off replies, sent on the next `tick`.
    outbox: Vec<MavMessage>,
    /// Frames of one datagram, reused.
    rx_frames: Vec<(MavHeader, MavMessage)>,
    /// MAVLink 2 signing, when a key is configured.
    signing: Option<Signing>,
    now_s: f64,
    tx: [u8; 300],
    /// Telemetry latency, simulation seconds (0 = report the state of the tick).
    telemetry_latency_s: f64,
    /// The states of the last `telemetry_latency_s`, oldest first (capacity reserved when
    /// the latency is set: no allocation per step).
    history: VecDeque<VehicleState>,
    /// NEES of the vision estimates against the truth (`set_vision_frame` turns it on).
    consistency: consistency::Consistency,
    /// Frame to thrust, simulation seconds: pilot input and guided and depth targets take
    /// effect this long after they arrive.
    input_delay_s: f64,
    /// Inputs waiting for their time, oldest first: (due time, header, message).
    delayed: VecDeque<(f64, MavHeader, MavMessage)>,
}

fn socket_err(
    what: &'static str,
    addr: impl std::fmt::Display,
    source: std::io::Error,
) -> HilError {
    HilError::Socket {
        what,
        addr: addr.to_string(),
        source,
    }
}

impl VehicleEndpoint {
    /// Bind UDP (and TCP when enabled) on `cfg.bind_ip` (127.0.0.1 by default); read the
    /// signing key when one is configured.
    pub fn bind(cfg: &EndpointConfig) -> Result<Self, HilError> {
        cfg.validate()?;
        let signing = match &cfg.signing_key_file {
            Some(path) => Some(Signing::new(
                signing::read_key(path)?,
                cfg.signing_link_id,
                cfg.signing_accept_unsigned,
            )),
            None => None,
        };
        let addr = SocketAddr::new(cfg.bind_ip, cfg.udp_port);
        let socket = UdpSocket::bind(addr).map_err(|e| socket_err("bind udp", addr, e))?;
        socket
            .set_nonblocking(true)
            .map_err(|e| socket_err("set_nonblocking udp", addr, e))?;
        let tcp = if cfg.tcp_enabled {
            let addr = SocketAddr::new(cfg.bind_ip, cfg.tcp_port);
            let l = TcpListener::bind(addr).map_err(|e| socket_err("bind tcp", addr, e))?;
            l.set_nonblocking(true)
                .map_err(|e| socket_err("set_nonblocking tcp", addr, e))?;
            Some(l)
        } else {
            None
        };
        Ok(Self {
            cfg: cfg.clone(),
            udp: UdpLink {
                socket,
                buf: Box::new([0; 65536]),
                peer: None,
            },
            tcp,
            tcp_clients: Vec::with_capacity(4),
            sequence: 0,
            armed: false,
            mode: cfg.initial_mode,
            arm_time_s: 0.0,
            last_pilot_s: None,
            last_gcs_heartbeat_s: None,
            pilot_failsafe: false,
            gcs_failsafe: false,
            depth_healthy: true,
            depth_failsafe: false,
            rc: RcInput::new(),
            guided: None,
            vision: None,
            t_nav_world: None,
            vision_aligned_at: None,
            streams: Vec::with_capacity(STREAMABLE_IDS.len()),
            next_heartbeat_s: 0.0,
            stats: EndpointStats::default(),
            controller: Controller::new(cfg.gains.clone(), cfg.params),
            outbox: Vec::with_capacity(16),
            rx_frames: Vec::with_capacity(64),
            signing,
            now_s: 0.0,
            tx: [0; 300],
            telemetry_latency_s: 0.0,
            history: VecDeque::with_capacity(2),
            consistency: consistency::Consistency::default(),
            input_delay_s: 0.0,
            delayed: VecDeque::with_capacity(DELAY_QUEUE),
        })
    }

    /// Apply pilot input and guided and depth targets `delay_s` (simulation time) after
    /// they arrive: the frame-to-thrust delay of the loop that sends them.
    pub fn set_input_delay(&mut self, delay_s: f64) {
        self.input_delay_s = if delay_s.is_finite() {
            delay_s.max(0.0)
        } else {
            0.0
        };
    }

    /// Apply the delayed inputs whose time has come (`now_s`, simulation time).
    fn release_due(&mut self, now_s: f64) {
        while let Some(&(due, _, _)) = self.delayed.front() {
            // Due later than a whole delay from now: the clock went back (a reset), apply.
            let clock_went_back = due > now_s + self.input_delay_s + 1e-6;
            if due > now_s + 1e-9 && !clock_went_back {
                break;
            }
            if let Some((_, h, m)) = self.delayed.pop_front() {
                self.apply(h, m);
            }
        }
    }

    /// Report the vehicle's state `latency_s` late (simulation time) in telemetry, for
    /// ticks every `step_s` (the physics step): room for the states in between is
    /// reserved now.
    pub fn set_telemetry_latency(&mut self, latency_s: f64, step_s: f64) {
        self.telemetry_latency_s = if latency_s.is_finite() {
            latency_s.max(0.0)
        } else {
            0.0
        };
        let steps = if step_s > 0.0 && step_s.is_finite() {
            (self.telemetry_latency_s / step_s).ceil() as usize
        } else {
            0
        };
        self.history = VecDeque::with_capacity(steps + 2);
    }

    /// The state telemetry reports at `state.time_s`: the newest one at least the
    /// latency old (the oldest kept, before a full latency has passed).
    fn reported_state(&mut self, state: &VehicleState) -> VehicleState {
        if self.history.back().is_some_and(|b| b.time_s > state.time_s) {
            // Time went back (SITL reset, teleport with a new clock): start over.
            self.history.clear();
        }
        if self.history.back().is_none_or(|b| b.time_s < state.time_s) {
            self.history.push_back(*state);
        }
        let due = state.time_s - self.telemetry_latency_s + 1e-9;
        while self.history.len() > 1 && self.history[1].time_s <= due {
            self.history.pop_front();
        }
        self.history.front().copied().unwrap_or(*state)
    }

    pub fn config(&self) -> &EndpointConfig {
        &self.cfg
    }

    /// The UDP address clients send to (`udpout:<addr>`).
    pub fn udp_addr(&self) -> SocketAddr {
        self.udp
            .socket
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::new(self.cfg.bind_ip, 0))
    }

    /// The TCP address (`tcpout:<addr>`), when TCP is enabled.
    pub fn tcp_addr(&self) -> Option<SocketAddr> {
        self.tcp.as_ref().and_then(|l| l.local_addr().ok())
    }

    pub fn armed(&self) -> bool {
        self.armed
    }

    pub fn mode(&self) -> u32 {
        self.mode
    }

    pub fn stats(&self) -> EndpointStats {
        self.stats
    }

    /// Whether MAVLink 2 signing is on (a key was configured).
    pub fn signing(&self) -> bool {
        self.signing.is_some()
    }

    /// The UDP peer telemetry goes to, once one has spoken acceptably.
    pub fn udp_peer(&self) -> Option<SocketAddr> {
        self.udp.peer
    }

    /// Whether any client has spoken to us (over UDP or TCP).
    pub fn has_peer(&self) -> bool {
        self.udp.peer.is_some() || !self.tcp_clients.is_empty()
    }

    /// Block (at most `timeout`, wall clock) until a datagram is waiting on the UDP socket;
    /// with TCP clients connected, sleep a short while instead. Used by lock-step waits.
    pub fn wait_readable(&mut self, timeout: std::time::Duration) -> Result<(), HilError> {
        if timeout.is_zero() {
            return Ok(());
        }
        if !self.tcp_clients.is_empty() || self.tcp.is_some() {
            std::thread::sleep(timeout.min(std::time::Duration::from_micros(500)));
            return Ok(());
        }
        let addr = self.udp_addr();
        let sock = &self.udp.socket;
        sock.set_nonblocking(false)
            .map_err(|e| socket_err("set_nonblocking udp", addr, e))?;
        sock.set_read_timeout(Some(timeout))
            .map_err(|e| socket_err("set_read_timeout udp", addr, e))?;
        let mut one = [0u8; 1];
        let r = sock.peek_from(&mut one);
        sock.set_nonblocking(true)
            .map_err(|e| socket_err("set_nonblocking udp", addr, e))?;
        match r {
            Ok(_) => Ok(()),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => Ok(()),
            // A truncated peek or an ICMP error: let poll() sort it out.
            Err(_) => Ok(()),
        }
    }

    /// Read and handle every pending message; `now_s` is simulation time. Returns the
    /// number of messages handled. Garbage bytes are skipped by the frame decoder.
    pub fn poll(&mut self, now_s: f64) -> Result<usize, HilError> {
        self.now_s = now_s;
        let mut handled = self.poll_udp()?;
        self.accept_tcp_clients();
        let mut i = 0;
        while i < self.tcp_clients.len() {
            let (n, closed) = self.poll_tcp_client(i);
            handled += n;
            if closed {
                self.tcp_clients.swap_remove(i);
            } else {
                i += 1;
            }
        }
        Ok(handled)
    }

    /// Handles every datagram waiting on the UDP socket; the sender of the last one that
    /// held an acceptable frame becomes the peer. Returns the messages handled.
    fn poll_udp(&mut self) -> Result<usize, HilError> {
        let mut handled = 0;
        loop {
            match self.udp.socket.recv_from(&mut self.udp.buf[..]) {
                Ok((n, from)) => {
                    let mut frames = std::mem::take(&mut self.rx_frames);
                    let stats = &mut self.stats;
                    let signing = &mut self.signing;
                    scan_datagram(&self.udp.buf[..n], |h, m, raw| {
                        if let Some(s) = signing.as_mut() {
                            match s.verify(raw) {
                                Verdict::Accepted => {}
                                Verdict::Unsigned => {
                                    stats.rejected_unsigned += 1;
                                    return;
                                }
                                Verdict::BadSignature => {
                                    stats.rejected_signature += 1;
                                    return;
                                }
                            }
                        }
                        match m {
                            Ok(m) => frames.push((h, m)),
                            Err(e) => {
                                stats.parse_errors += 1;
                                tracing::debug!(error = %e, "mavlink payload did not parse; skipped");
                            }
                        }
                    });
                    if frames.is_empty() {
                        self.stats.rejected_datagrams += 1;
                    } else if self.udp.peer != Some(from) {
                        tracing::info!(peer = %from, "udp peer");
                        self.udp.peer = Some(from);
                    }
                    for (h, m) in frames.drain(..) {
                        self.handle(h, m);
                        handled += 1;
                    }
                    self.rx_frames = frames;
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                // ICMP port unreachable from a client that went away: keep serving.
                Err(e) if e.kind() == ErrorKind::ConnectionReset => continue,
                Err(e) => return Err(socket_err("recv udp", self.udp_addr(), e)),
            }
        }
        Ok(handled)
    }

    /// Takes every TCP client waiting on the listener (when TCP is on).
    fn accept_tcp_clients(&mut self) {
        let Some(listener) = &self.tcp else {
            return;
        };
        loop {
            match listener.accept() {
                Ok((stream, peer)) => {
                    if stream.set_nonblocking(true).is_ok() {
                        let _ = stream.set_nodelay(true);
                        tracing::info!(%peer, "tcp client connected");
                        self.tcp_clients.push(TcpClient {
                            reader: MavlinkReader::new(TcpSource(stream)),
                            peer,
                        });
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) => {
                    tracing::warn!(error = %e, "tcp accept failed");
                    break;
                }
            }
        }
    }

    /// Handles every frame TCP client `i` has sent; returns the messages handled and
    /// whether the client closed.
    fn poll_tcp_client(&mut self, i: usize) -> (usize, bool) {
        let mut handled = 0;
        loop {
            match self.tcp_clients[i]
                .reader
                .read_any_raw_message::<MavMessage>()
            {
                Ok(raw) => {
                    if let Some(s) = self.signing.as_mut() {
                        let bytes = match &raw {
                            MAVLinkMessageRaw::V1(r) => r.raw_bytes(),
                            MAVLinkMessageRaw::V2(r) => r.raw_bytes(),
                        };
                        match s.verify(bytes) {
                            Verdict::Accepted => {}
                            Verdict::Unsigned => {
                                self.stats.rejected_unsigned += 1;
                                continue;
                            }
                            Verdict::BadSignature => {
                                self.stats.rejected_signature += 1;
                                continue;
                            }
                        }
                    }
                    let h = MavHeader {
                        system_id: raw.system_id(),
                        component_id: raw.component_id(),
                        sequence: raw.sequence(),
                    };
                    match <MavMessage as mavlink::Message>::parse(
                        raw.version(),
                        raw.message_id(),
                        raw.payload(),
                    ) {
                        Ok(m) => {
                            self.handle(h, m);
                            handled += 1;
                        }
                        Err(e) => {
                            self.stats.parse_errors += 1;
                            tracing::debug!(error = %e, "mavlink payload did not parse; skipped");
                        }
                    }
                }
                Err(MessageReadError::Io(e)) if e.kind() == ErrorKind::WouldBlock => {
                    return (handled, false)
                }
                Err(MessageReadError::Parse(e)) => {
                    self.stats.parse_errors += 1;
                    tracing::debug!(error = %e, "mavlink payload did not parse; skipped");
                }
                Err(MessageReadError::Io(e)) => {
                    tracing::info!(peer = %self.tcp_clients[i].peer, error = %e, "tcp client closed");
                    return (handled, true);
                }
            }
        }
    }

    fn is_for_us(&self, target_system: u8) -> bool {
        target_system == 0 || target_system == self.cfg.system_id
    }

    fn pilot_input_accepted(&mut self) {
        self.stats.pilot_inputs += 1;
        self.last_pilot_s = Some(self.now_s);
    }

    /// Inputs a lock-step client sends once per frame, addressed to us (accepted or not).
    fn is_lockstep_input(&self, msg: &MavMessage) -> bool {
        match msg {
            MavMessage::MANUAL_CONTROL(m) => m.target == self.cfg.system_id,
            MavMessage::RC_CHANNELS_OVERRIDE(m) => self.is_for_us(m.target_system),
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(t) => self.is_for_us(t.target_system),
            MavMessage::SET_POSITION_TARGET_GLOBAL_INT(t) => self.is_for_us(t.target_system),
            _ => false,
        }
    }

    /// A message on arrival: counted, then applied now or, when it carries what the loop
    /// computed from a frame, after the frame-to-thrust delay.
    fn handle(&mut self, h: MavHeader, msg: MavMessage) {
        self.stats.messages += 1;
        let lockstep = self.is_lockstep_input(&msg);
        if lockstep {
            self.stats.lockstep_inputs += 1;
        }
        // Vision estimates are not held back: they carry their frame's time and
        // ArduSub's EKF fuses them at that time (VISO_DELAY_MS, AP_VisualOdom.cpp).
        if !lockstep || self.input_delay_s == 0.0 {
            self.apply(h, msg);
            return;
        }
        if self.delayed.len() == DELAY_QUEUE {
            // Never grow on the per-frame path: the oldest goes early.
            self.stats.delay_overflows += 1;
            if let Some((_, oh, om)) = self.delayed.pop_front() {
                self.apply(oh, om);
            }
        }
        self.delayed
            .push_back((self.now_s + self.input_delay_s, h, msg));
    }

    // SET_MODE is deprecated in MAVLink but ArduSub still obeys it, and GCSs still send it.
    #[allow(deprecated)]
    fn apply(&mut self, h: MavHeader, msg: MavMessage) {
        let from_gcs = h.system_id == self.cfg.gcs_system_id as u32;
        match msg {
            MavMessage::HEARTBEAT(_) if from_gcs => {
                self.last_gcs_heartbeat_s = Some(self.now_s);
            }
            MavMessage::MANUAL_CONTROL(m) => {
                if !from_gcs || m.target != self.cfg.system_id {
                    self.stats.pilot_inputs_dropped += 1;
                    return;
                }
                self.apply_manual_control(&m);
                self.pilot_input_accepted();
            }
            MavMessage::RC_CHANNELS_OVERRIDE(m) => {
                if !from_gcs || !self.is_for_us(m.target_system) {
                    self.stats.pilot_inputs_dropped += 1;
                    return;
                }
                self.apply_rc_override(&m);
                self.pilot_input_accepted();
            }
            MavMessage::COMMAND_LONG(c) if self.is_for_us(c.target_system) => {
                let result = self.command(&c);
                self.outbox.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command: c.command,
                    result,
                    progress: 0,
                    result_param2: 0,
                    target_system: h.system_id.min(255) as u8,
                    target_component: h.component_id,
                }));
            }
            MavMessage::SET_MODE(m) if self.is_for_us(m.target_system) => {
                self.set_mode(m.custom_mode);
            }
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(t) if self.is_for_us(t.target_system) => {
                self.guided_target(&t);
            }
            MavMessage::SET_POSITION_TARGET_GLOBAL_INT(t) if self.is_for_us(t.target_system) => {
                self.global_target(&t);
            }
            MavMessage::VISION_POSITION_ESTIMATE(v) => self.vision_estimate(&v),
            MavMessage::ODOMETRY(o) => {
                // ArduSub takes ODOMETRY (frame LOCAL_FRD, child BODY_FRD) as a vision
                // position source too; q is w, x, y, z.
                let vals = [o.x, o.y, o.z, o.q[0], o.q[1], o.q[2], o.q[3]];
                if vals.iter().all(|v| v.is_finite()) {
                    let q = nalgebra::Quaternion::new(
                        o.q[0] as f64,
                        o.q[1] as f64,
                        o.q[2] as f64,
                        o.q[3] as f64,
                    );
                    if q.norm() > 0.5 {
                        let pose = Isometry3::from_parts(
                            Translation3::new(o.x as f64, o.y as f64, o.z as f64),
                            UnitQuaternion::from_quaternion(q),
                        );
                        self.vision = Some((self.now_s, pose));
                    }
                }
            }
            _ => {}
        }
    }

    fn apply_manual_control(&mut self, m: &MANUAL_CONTROL_DATA) {
        // ArduSub (Sub::transform_manual_control_to_rc_override, joystick.cpp) maps the
        // joystick onto the RC input channels: 1500 + v x 0.4 x gain, throttle
        // 1500 - 500 x s + z x s with s = 0.8 x gain (JS_THR_GAIN 1), truncated to
        // whole microseconds by the conversion to int16 and constrained to 1100..1900.
        let g = self.controller.gain();
        let axis = |v: i16| {
            (1500.0 + f64::from(v) * 0.4 * g)
                .trunc()
                .clamp(1100.0, 1900.0) as u16
        };
        let s = 0.8 * g * self.cfg.params.js_thr_gain;
        let thr = (1500.0 - 500.0 * s + f64::from(m.z) * s)
            .trunc()
            .clamp(1100.0, 1900.0) as u16;
        let mut set = |ch: usize, pwm: u16| {
            self.rc.pwm[ch - 1] = pwm;
        };
        set(3, thr);
        set(4, axis(m.r));
        set(5, axis(m.x));
        set(6, axis(m.y));
        // MAVLink 2 extensions: bit 0 pitch (s), bit 1 roll (t).
        if m.enabled_extensions & 1 != 0 {
            set(1, axis(m.s));
        }
        if m.enabled_extensions & 2 != 0 {
            set(2, axis(m.t));
        }
    }

    fn apply_rc_override(&mut self, m: &RC_CHANNELS_OVERRIDE_DATA) {
        let raw = [
            m.chan1_raw,
            m.chan2_raw,
            m.chan3_raw,
            m.chan4_raw,
            m.chan5_raw,
            m.chan6_raw,
            m.chan7_raw,
            m.chan8_raw,
            m.chan9_raw,
            m.chan10_raw,
            m.chan11_raw,
            m.chan12_raw,
            m.chan13_raw,
            m.chan14_raw,
            m.chan15_raw,
            m.chan16_raw,
            m.chan17_raw,
            m.chan18_raw,
        ];
        for (i, &v) in raw.iter().enumerate() {
            // Channels 1-8: 0 releases, UINT16_MAX leaves unchanged. Channels 9-18: 0 and
            // UINT16_MAX both leave unchanged, and UINT16_MAX - 1 releases. A released
            // channel keeps its last value (no RC receiver).
            let release = if i < 8 { v == 0 } else { v == u16::MAX - 1 };
            let ignore = if i < 8 {
                v == u16::MAX
            } else {
                v == 0 || v == u16::MAX
            };
            if ignore || release {
                continue;
            }
            self.rc.pwm[i] = v.clamp(1100, 1900);
        }
    }

    fn command(&mut self, c: &COMMAND_LONG_DATA) -> MavResult {
        match c.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                if c.param1 == 1.0 {
                    if !self.armed {
                        self.armed = true;
                        self.arm_time_s = self.now_s;
                        self.controller.reset();
                        tracing::info!(t = self.now_s, "armed");
                    }
                    MavResult::MAV_RESULT_ACCEPTED
                } else if c.param1 == 0.0 {
                    self.disarm("command");
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_DO_SET_MODE => {
                let custom = (c.param1 as u32)
                    & MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits() as u32;
                if custom == 0 || !c.param2.is_finite() || c.param2 < 0.0 {
                    return MavResult::MAV_RESULT_DENIED;
                }
                if self.set_mode(c.param2 as u32) {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = c.param1;
                if !id.is_finite() || !STREAMABLE_IDS.contains(&(id as u32)) || id.fract() != 0.0 {
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.set_interval(id as u32, c.param2 as f64);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => {
                let id = c.param1;
                if id.is_finite() && (STREAMABLE_IDS.contains(&(id as u32)) || id == 0.0) {
                    // Sent with the next tick, once the state is known.
                    self.streams.retain(|s| !(s.0 == id as u32 && s.1 < 0.0));
                    self.streams.push((id as u32, -1.0, self.now_s));
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }

    /// Change mode; false (and no change) when the mode is not supported or lacks the
    /// position estimate it needs.
    fn set_mode(&mut self, m: u32) -> bool {
        if !mode::SUPPORTED.contains(&m) {
            tracing::warn!(mode = m, "mode not supported");
            return false;
        }
        if mode::needs_position(m) && !self.has_position(self.now_s) {
            tracing::warn!(mode = mode::name(m), "mode needs a position estimate");
            return false;
        }
        if mode::needs_depth(m) && !self.depth_ok() {
            // ModeAlthold::init / ModeSurface::init: `control_check_barometer()`.
            tracing::warn!(mode = mode::name(m), "mode needs a depth sensor");
            return false;
        }
        self.enter_mode(m);
        true
    }

    fn enter_mode(&mut self, m: u32) {
        if m != self.mode {
            tracing::info!(
                from = mode::name(self.mode),
                to = mode::name(m),
                "mode change"
            );
            self.mode = m;
            self.controller.reset();
            self.guided = None;
        }
    }

    fn set_interval(&mut self, id: u32, interval_us: f64) {
        self.streams.retain(|s| s.0 != id || s.1 < 0.0);
        if !interval_us.is_finite() || interval_us < 0.0 {
            return; // -1 stops the stream
        }
        // 0 asks for the default rate: 4 Hz.
        let period = if interval_us == 0.0 {
            0.25
        } else {
            interval_us * 1e-6
        };
        self.streams.push((id, period, self.now_s));
    }

    // BODY_NED / BODY_OFFSET_NED are deprecated but ArduSub's GUIDED still accepts them.
    #[allow(deprecated)]
    fn guided_target(&mut self, t: &SET_POSITION_TARGET_LOCAL_NED_DATA) {
        let mask = t.type_mask;
        let ignore_pos = mask.intersects(
            PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE,
        );
        let ignore_vel = mask.intersects(
            PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE,
        );
        let ignore_yaw = mask.contains(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE);
        let ignore_rate =
            mask.contains(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE);
        let p = Vector3::new(t.x as f64, t.y as f64, t.z as f64);
        let v = Vector3::new(t.vx as f64, t.vy as f64, t.vz as f64);
        if p.iter().chain(v.iter()).any(|x| !x.is_finite()) {
            return;
        }
        let Some(nav) = self.nav_estimate_cached() else {
            tracing::debug!("guided target without a position estimate: ignored");
            return;
        };
        let yaw_now = nav.yaw;
        let r_yaw = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_now);
        let r_body = nav.pose.rotation;
        let (position, velocity) = match t.coordinate_frame {
            MavFrame::MAV_FRAME_LOCAL_NED => (Some(p), Some(v)),
            MavFrame::MAV_FRAME_LOCAL_OFFSET_NED => {
                (Some(nav.pose.translation.vector + p), Some(v))
            }
            MavFrame::MAV_FRAME_BODY_NED => (Some(p), Some(r_yaw.transform_vector(&v))),
            MavFrame::MAV_FRAME_BODY_OFFSET_NED => (
                Some(nav.pose.translation.vector + r_yaw.transform_vector(&p)),
                Some(r_yaw.transform_vector(&v)),
            ),
            MavFrame::MAV_FRAME_BODY_FRD => (
                Some(nav.pose.translation.vector + r_body.transform_vector(&p)),
                Some(r_body.transform_vector(&v)),
            ),
            other => {
                tracing::debug!(frame = ?other, "guided target frame not supported: ignored");
                return;
            }
        };
        let yaw = (!ignore_yaw && t.yaw.is_finite()).then_some(t.yaw as f64);
        let yaw_rate = (!ignore_rate && t.yaw_rate.is_finite()).then_some(t.yaw_rate as f64);
        self.guided = Some(GuidedTarget {
            position: if ignore_pos { None } else { position },
            velocity: if ignore_vel { None } else { velocity },
            yaw,
            yaw_rate,
            stamp_s: self.now_s,
        });
        self.stats.guided_targets += 1;
    }

    /// SET_POSITION_TARGET_GLOBAL_INT as ArduSub takes it in ALT_HOLD
    /// (`GCS_MAVLINK_Sub::handleMessage`, ArduSub/GCS_Mavlink.cpp): when none of the
    /// three position-ignore bits is set (`type_mask & MAVLINK_SET_POS_TYPE_MASK_POS_IGNORE`,
    /// x, y and z: any one of them ignores the position),
    /// `pos_control.set_alt_target(alt*100)`, an altitude in metres above the EKF origin,
    /// up; the frame, latitude and longitude are not read, and nothing else is done. ALT_HOLD then holds that target
    /// while the throttle stick is centred (`Sub::control_depth`). Here the altitude is
    /// in the frame of the LOCAL_POSITION_NED this endpoint reports (its z is the nav
    /// frame's once vision aligned it, else the world's depth). GUIDED's global targets
    /// need a global position this vehicle lacks: ignored, as in every other mode.
    fn global_target(&mut self, t: &SET_POSITION_TARGET_GLOBAL_INT_DATA) {
        let pos_ignore = t.type_mask.intersects(
            PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE,
        );
        if self.mode != mode::ALT_HOLD || pos_ignore || !t.alt.is_finite() {
            return;
        }
        // LOCAL_POSITION_NED's z = world depth + the nav frame's offset (a yaw-only
        // rotation leaves z alone).
        let z_off = self.t_nav_world.map_or(0.0, |n| n.translation.vector.z);
        self.controller.set_depth_target(-f64::from(t.alt) - z_off);
        self.stats.depth_targets += 1;
    }

    fn vision_estimate(&mut self, v: &VISION_POSITION_ESTIMATE_DATA) {
        let vals = [v.x, v.y, v.z, v.roll, v.pitch, v.yaw];
        if vals.iter().any(|x| !x.is_finite()) {
            return;
        }
        let pose = Isometry3::from_parts(
            Translation3::new(v.x as f64, v.y as f64, v.z as f64),
            UnitQuaternion::from_euler_angles(v.roll as f64, v.pitch as f64, v.yaw as f64),
        );
        self.vision = Some((self.now_s, pose));
        self.check_vision_covariance(v);
    }

    /// The estimate's covariance against the truth (when the vision frame is known).
    fn check_vision_covariance(&mut self, v: &VISION_POSITION_ESTIMATE_DATA) {
        let x = [v.x, v.y, v.z, v.roll, v.pitch, v.yaw].map(f64::from);
        self.consistency
            .observe(v.usec as f64 * 1e-6, x, &v.covariance);
    }

    /// Where the vision estimates' frame lies in the simulated world (`t_world_vision`):
    /// from now on each estimate's covariance is checked against the vehicle's true pose
    /// in that frame ([`Self::vision_nees`]).
    pub fn set_vision_frame(&mut self, t_world_vision: Isometry3<f64>) {
        self.consistency.set_frame(t_world_vision);
    }

    /// NEES of the vision estimates received since `set_vision_frame` (none before).
    pub fn vision_nees(&self) -> Option<VisionNees> {
        self.consistency.nees()
    }

    fn has_position(&self, now_s: f64) -> bool {
        matches!(self.vision, Some((t, _)) if now_s - t <= self.cfg.vision_timeout_s)
    }

    /// The navigation estimate from the last `tick`'s alignment.
    fn nav_estimate_cached(&self) -> Option<NavEstimate> {
        self.controller.last_nav()
    }

    fn disarm(&mut self, why: &str) {
        if self.armed {
            tracing::info!(t = self.now_s, reason = why, "disarmed");
        }
        self.armed = false;
        self.controller.reset();
    }

    /// Failsafes, then the efforts the autopilot commands now (the mixer input), given the
    /// vehicle's state. Call once per physics step.
    pub fn efforts(&mut self, state: &VehicleState, dt_s: f64) -> [f64; 6] {
        let now = state.time_s;
        self.now_s = now;
        self.release_due(now);
        self.failsafes(now);
        // Navigation: when a vision estimate is fresh, align the nav frame to it (an EKF
        // that trusts vision for position and yaw, the IMU in between).
        if let Some((t, pose)) = self.vision {
            if now - t <= self.cfg.vision_timeout_s {
                if self.vision_aligned_at != Some(t) {
                    // Align heading and position only; roll and pitch come from the IMU.
                    let truth = state.t_world_vehicle;
                    let (_, _, yaw_v) = pose.rotation.euler_angles();
                    let (_, _, yaw_t) = truth.rotation.euler_angles();
                    let r = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_v - yaw_t);
                    let trans = pose.translation.vector - r * truth.translation.vector;
                    self.t_nav_world = Some(Isometry3::from_parts(Translation3::from(trans), r));
                    self.vision_aligned_at = Some(t);
                }
            } else {
                self.t_nav_world = None;
            }
        }
        let nav = self.t_nav_world.map(|t| {
            NavEstimate::new(
                &(t * state.t_world_vehicle),
                &(t.rotation * state.velocity_world_mps),
            )
        });
        if !self.armed {
            self.controller.observe(state, nav);
            return [0.0; 6];
        }
        let ch = |c: usize| self.rc.channel(c);
        let raw = [ch(5), ch(6), ch(3), ch(2), ch(1), ch(4)];
        let guided = self
            .guided
            .filter(|g| now - g.stamp_s <= self.cfg.guided_timeout_s);
        let efforts = self
            .controller
            .update(self.mode, &raw, state, nav, guided.as_ref(), dt_s);
        // ModeSurface::run: at the surface, hold depth there (ALT_HOLD).
        let depth_cm = state.t_world_vehicle.translation.vector.z * 100.0;
        if self.mode == mode::SURFACE && depth_cm <= -self.cfg.params.surface_depth_cm {
            self.set_mode(mode::ALT_HOLD);
        }
        efforts
    }

    /// Whether the depth sensor is present and reads (`control_check_barometer`).
    fn depth_ok(&self) -> bool {
        self.cfg.depth_sensor && self.depth_healthy
    }

    /// Make the simulated depth sensor fail (false) or read again (true). A failure
    /// switches ALT_HOLD, SURFACE, POSHOLD and GUIDED to MANUAL
    /// (`Sub::failsafe_sensors_check`).
    pub fn set_depth_sensor_healthy(&mut self, healthy: bool) {
        self.depth_healthy = healthy;
    }

    fn failsafes(&mut self, now: f64) {
        let p = self.cfg.params;
        // Sub::failsafe_sensors_check: once per failure.
        if self.cfg.depth_sensor && !self.depth_healthy {
            if !self.depth_failsafe {
                self.depth_failsafe = true;
                if mode::needs_depth(self.mode) || mode::needs_position(self.mode) {
                    tracing::warn!(from = mode::name(self.mode), "depth sensor error: MANUAL");
                    self.enter_mode(mode::MANUAL);
                }
            }
        } else {
            self.depth_failsafe = false;
        }
        // Sub::failsafe_pilot_input_check: once, until pilot input returns; centres the
        // controls (the held RC values go) and disarms with FS_PILOT_INPUT = 2.
        if p.fs_pilot_input != 0 {
            let last = self
                .last_pilot_s
                .unwrap_or(self.arm_time_s)
                .max(self.arm_time_s);
            if now - last < p.fs_pilot_timeout_s {
                self.pilot_failsafe = false;
            } else if !self.pilot_failsafe {
                self.pilot_failsafe = true;
                self.rc.neutral();
                if p.fs_pilot_input == 2 && self.armed {
                    self.stats.failsafe_pilot += 1;
                    self.disarm("pilot input failsafe");
                }
            }
        }
        // Sub::failsafe_gcs_check: once a GCS was heard, FS_GCS_TIMEOUT without its
        // heartbeat (or pilot input) acts once: 2 disarm, 3 POSHOLD (ALT_HOLD without a
        // position), 4 SURFACE.
        if p.fs_gcs_enable != 0 {
            if let Some(last) = self.last_gcs_heartbeat_s {
                if now - last <= p.fs_gcs_timeout_s {
                    self.gcs_failsafe = false;
                } else if !self.gcs_failsafe && self.armed {
                    self.gcs_failsafe = true;
                    self.stats.failsafe_gcs += 1;
                    match p.fs_gcs_enable {
                        2 => self.disarm("GCS heartbeat failsafe"),
                        3 => {
                            if !self.set_mode(mode::POSHOLD) {
                                self.set_mode(mode::ALT_HOLD);
                            }
                        }
                        4 => {
                            self.set_mode(mode::SURFACE);
                        }
                        _ => tracing::warn!("GCS heartbeat lost"),
                    }
                }
            }
        }
    }

    /// Send what is due at simulation time `state.time_s`: command acks, the heartbeat
    /// (`heartbeat_hz`), and the requested streams. `pwm` are the servo outputs now.
    pub fn tick(&mut self, state: &VehicleState, pwm: &[u16; MAX_MOTORS]) -> Result<(), HilError> {
        let now = state.time_s;
        self.now_s = now;
        self.consistency.set_truth(now, &state.t_world_vehicle);
        let reported = self.reported_state(state);
        let mut outbox = std::mem::take(&mut self.outbox);
        for m in outbox.drain(..) {
            self.send(&m)?;
        }
        self.outbox = outbox;
        if now + 1e-9 >= self.next_heartbeat_s {
            let hb = self.heartbeat();
            self.send(&hb)?;
            let period = 1.0 / self.cfg.heartbeat_hz;
            self.next_heartbeat_s = if self.next_heartbeat_s + period > now {
                self.next_heartbeat_s + period
            } else {
                now + period
            };
        }
        let mut i = 0;
        while i < self.streams.len() {
            let (id, period, due) = self.streams[i];
            if now + 1e-9 < due {
                i += 1;
                continue;
            }
            let msg = self.telemetry(id, now, &reported, pwm);
            if let Some(m) = msg {
                self.send(&m)?;
            }
            if period < 0.0 {
                self.streams.remove(i);
                continue;
            }
            let next = due + period;
            self.streams[i].2 = if next > now { next } else { now + period };
            i += 1;
        }
        Ok(())
    }

    fn heartbeat(&self) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED;
        if self.mode != mode::MANUAL {
            base |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
        }
        if self.mode == mode::GUIDED {
            base |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED;
        }
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.mode,
            mavtype: MavType::MAV_TYPE_SUBMARINE,
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: base,
            system_status: if self.armed {
                MavState::MAV_STATE_ACTIVE
            } else {
                MavState::MAV_STATE_STANDBY
            },
            mavlink_version: 3,
        })
    }

    /// Message `id` sent at `now`, reporting `state` (late by the telemetry latency).
    fn telemetry(
        &self,
        id: u32,
        now: f64,
        state: &VehicleState,
        pwm: &[u16; MAX_MOTORS],
    ) -> Option<MavMessage> {
        let t_ms = (now * 1000.0).max(0.0) as u32;
        let (roll, pitch, yaw) = state.t_world_vehicle.rotation.euler_angles();
        let w = state.angvel_body_rps;
        Some(match id {
            0 => self.heartbeat(),
            30 => MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms: t_ms,
                roll: roll as f32,
                pitch: pitch as f32,
                yaw: yaw as f32,
                rollspeed: w.x as f32,
                pitchspeed: w.y as f32,
                yawspeed: w.z as f32,
            }),
            31 => {
                let q = state.t_world_vehicle.rotation.quaternion();
                MavMessage::ATTITUDE_QUATERNION(ATTITUDE_QUATERNION_DATA {
                    time_boot_ms: t_ms,
                    q1: q.w as f32,
                    q2: q.i as f32,
                    q3: q.j as f32,
                    q4: q.k as f32,
                    rollspeed: w.x as f32,
                    pitchspeed: w.y as f32,
                    yawspeed: w.z as f32,
                    repr_offset_q: [0.0; 4],
                })
            }
            32 => {
                // The EKF's local position: in the vision frame once aligned, else the
                // world frame (as if a DVL/USBL gave an absolute fix).
                let (p, v) = match self.t_nav_world {
                    Some(t) => (
                        (t * state.t_world_vehicle).translation.vector,
                        t.rotation * state.velocity_world_mps,
                    ),
                    None => (
                        state.t_world_vehicle.translation.vector,
                        state.velocity_world_mps,
                    ),
                };
                MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                    time_boot_ms: t_ms,
                    x: p.x as f32,
                    y: p.y as f32,
                    z: p.z as f32,
                    vx: v.x as f32,
                    vy: v.y as f32,
                    vz: v.z as f32,
                })
            }
            36 => MavMessage::SERVO_OUTPUT_RAW(SERVO_OUTPUT_RAW_DATA {
                time_usec: (now * 1e6).max(0.0) as u64 as u32,
                servo1_raw: pwm[0],
                servo2_raw: pwm[1],
                servo3_raw: pwm[2],
                servo4_raw: pwm[3],
                servo5_raw: pwm[4],
                servo6_raw: pwm[5],
                servo7_raw: pwm[6],
                servo8_raw: pwm[7],
                ..Default::default()
            }),
            65 => {
                let c = |i: usize| self.rc.channel(i);
                MavMessage::RC_CHANNELS(RC_CHANNELS_DATA {
                    time_boot_ms: t_ms,
                    chan1_raw: c(1),
                    chan2_raw: c(2),
                    chan3_raw: c(3),
                    chan4_raw: c(4),
                    chan5_raw: c(5),
                    chan6_raw: c(6),
                    chan7_raw: c(7),
                    chan8_raw: c(8),
                    chan9_raw: c(9),
                    chan10_raw: c(10),
                    chan11_raw: c(11),
                    chan12_raw: c(12),
                    chan13_raw: c(13),
                    chan14_raw: c(14),
                    chan15_raw: c(15),
                    chan16_raw: c(16),
                    chan17_raw: c(17),
                    chan18_raw: c(18),
                    chancount: 18,
                    rssi: 255,
                })
            }
            137 => {
                // The external depth sensor (Bar30): absolute pressure in hPa.
                let depth = state.t_world_vehicle.translation.vector.z;
                let press_hpa = 1013.25 + 1025.0 * GRAVITY_MPS2 * depth / 100.0;
                MavMessage::SCALED_PRESSURE2(SCALED_PRESSURE2_DATA {
                    time_boot_ms: t_ms,
                    press_abs: press_hpa as f32,
                    press_diff: 0.0,
                    temperature: 1500,
                    temperature_press_diff: 0,
                })
            }
            _ => return None,
        })
    }

    /// Send one message to the last UDP peer and every TCP client.
    fn send(&mut self, msg: &MavMessage) -> Result<(), HilError> {
        let header = MavHeader {
            system_id: self.cfg.system_id as u32,
            component_id: self.cfg.component_id,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        let n = {
            let mut w: &mut [u8] = &mut self.tx[..];
            let signing = self.signing.as_ref().map(Signing::data);
            match mavlink::write_v2_msg_signed(&mut w, header, msg, signing) {
                Ok(n) => n,
                Err(e) => {
                    tracing::warn!(error = %e, "mavlink message did not serialize");
                    return Ok(());
                }
            }
        };
        let bytes = &self.tx[..n];
        let udp = &self.udp;
        if let Some(peer) = udp.peer {
            match udp.socket.send_to(bytes, peer) {
                Ok(_) => {}
                // A full buffer or a vanished peer loses this message, as on a real link.
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::WouldBlock | ErrorKind::ConnectionRefused
                    ) => {}
                Err(e) => return Err(socket_err("send udp", peer, e)),
            }
        }
        for c in &mut self.tcp_clients {
            use std::io::Write;
            if let Err(e) = c.reader.get_mut().0.write_all(bytes) {
                tracing::debug!(peer = %c.peer, error = %e, "tcp send failed");
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn telemetry_reports_the_state_the_latency_ago_without_allocating() {
        let mut ep = VehicleEndpoint::bind(&EndpointConfig::default()).unwrap();
        let dt = 0.0025;
        ep.set_telemetry_latency(0.1, dt);
        let cap = ep.history.capacity();
        let state = |t: f64| VehicleState {
            time_s: t,
            t_world_vehicle: Isometry3::translation(0.0, 0.0, t),
            velocity_world_mps: Vector3::zeros(),
            angvel_body_rps: Vector3::zeros(),
            specific_force_body_mps2: Vector3::zeros(),
            water_velocity_world_mps: Vector3::zeros(),
        };
        for i in 0..2000 {
            let t = i as f64 * dt;
            let r = ep.reported_state(&state(t));
            let expect = (t - 0.1).max(0.0);
            assert!((r.time_s - expect).abs() < 1e-9, "at {t}: {}", r.time_s);
            assert!((r.t_world_vehicle.translation.z - expect).abs() < 1e-9);
        }
        assert_eq!(ep.history.capacity(), cap);
        // A clock restarted at zero (SITL reset) starts the history over.
        assert_eq!(ep.reported_state(&state(0.0)).time_s, 0.0);
        // Without latency: the state of the tick.
        ep.set_telemetry_latency(0.0, dt);
        assert_eq!(ep.reported_state(&state(1.0)).time_s, 1.0);
        assert_eq!(ep.reported_state(&state(1.0025)).time_s, 1.0025);
    }

    #[test]
    fn config_errors_name_the_key_and_unknown_keys_are_refused() {
        let mut c = EndpointConfig::default();
        c.params.js_gain_default = 2.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("JS_GAIN_DEFAULT") && e.contains('2'), "{e}");
        let mut c = EndpointConfig::default();
        c.params.rc_dz_us[2] = 250;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("RC3_DZ") && e.contains("250"), "{e}");
        let c = EndpointConfig {
            initial_mode: 7,
            ..Default::default()
        };
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("endpoint.initial_mode"));
        let mut c = EndpointConfig::default();
        c.gains.depth_pos_p = f64::NAN;
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("endpoint.gains.depth_pos_p"));
        assert!(serde_json::from_str::<EndpointConfig>(r#"{"gcs_sysid":255}"#).is_err());
        let c: EndpointConfig = serde_json::from_str(r#"{"gcs_system_id":254}"#).unwrap();
        assert_eq!((c.gcs_system_id, c.system_id), (254, 1));
    }

    #[test]
    fn datagram_scanner_resyncs_after_a_bogus_start() {
        let mut bytes = vec![0xFEu8, 0xFD, 0x00];
        let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        let h = MavHeader {
            system_id: 255,
            component_id: 0,
            sequence: 7,
        };
        let mut one = Vec::new();
        mavlink::write_versioned_msg(&mut one, MavlinkVersion::V2, h, &msg).unwrap();
        bytes.extend_from_slice(&one);
        mavlink::write_versioned_msg(&mut bytes, MavlinkVersion::V1, h, &msg).unwrap();
        bytes.extend_from_slice(&one[..5]); // truncated tail
        let mut seen = Vec::new();
        scan_datagram(&bytes, |h, m, _| seen.push((h.sequence, m.is_ok())));
        assert_eq!(seen, vec![(7, true), (7, true)]);
    }
}
