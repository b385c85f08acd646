//! The ArduSub session over MAVLink 2: markhold's heartbeat, vehicle discovery, stream
//! requests, arm/mode commands with COMMAND_ACK and retries, pilot input, GUIDED setpoints
//! with vision pose estimates, and telemetry parsing into `VehicleState`.
//!
//! Identity: markhold is a component of the vehicle's system. Everything goes out as
//! the vehicle's system id (learned from its heartbeat) and `link.component_id` (191),
//! except pilot input (RC_CHANNELS_OVERRIDE, MANUAL_CONTROL), which ArduSub takes only
//! from SYSID_MYGCS and which goes out as `link.gcs_system_id`. Once the pilot's station
//! (a HEARTBEAT from SYSID_MYGCS with another component id) has been heard, pilot input
//! goes out only while it is heard (`station`), so markhold never keeps ArduSub's GCS
//! failsafe quiet by itself (docs/design/pilot.md).
//!
//! Synchronous facade: every call is non-blocking. Bytes go on the wire from the caller's
//! thread at the call. UDP is read by `tick` on the caller's thread (by default); TCP and
//! serial by a tokio task into a bounded queue that `tick` drains. All session timing
//! (heartbeat, retries, timeouts) runs on the caller's loop time `now_s`, never the wall
//! clock.

use std::io::Cursor;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

// SET_GPS_GLOBAL_ORIGIN is marked superseded upstream, but ArduSub's GUIDED setup still
// documents it; keep sending it.
#[allow(deprecated)]
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavFrame, MavMessage, MavModeFlag, MavResult, MavState, MavType,
    PositionTargetTypemask, ATTITUDE_DATA, COMMAND_ACK_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA,
    LOCAL_POSITION_NED_DATA, MANUAL_CONTROL_DATA, RC_CHANNELS_DATA, RC_CHANNELS_OVERRIDE_DATA,
    SCALED_PRESSURE2_DATA, SERVO_OUTPUT_RAW_DATA, SET_GPS_GLOBAL_ORIGIN_DATA,
    SET_POSITION_TARGET_LOCAL_NED_DATA, VISION_POSITION_ESTIMATE_DATA,
};
use mavlink::{MavHeader, Message, SigningData};
use nalgebra::{Isometry3, Vector3};
use serde::Serialize;

use crate::config::{CommandKind, LinkConfig, PilotInput};
use crate::error::AutopilotError;
use crate::pilot::PilotMap;
use crate::transport::{Incoming, Transport, WriteOutcome, MAX_FRAME};
pub use crate::types::ArduSubMode;
use crate::types::{wrap_pi, Effort};
use crate::vision_pose::{t_vision_marker, upper_triangle, VisionPose};

mod depth;
mod exit;
mod gcs;
mod station;
pub use depth::depth_target_mask;
pub use exit::{CloseReport, NeutralShown, Settled};
pub use gcs::{PilotSeen, Severity, NAMED_VALUE_MAX, STATUSTEXT_MAX};
pub use station::{StationSeen, STATION_RELAY_S};

/// One MAVLink frame as it crossed the wire, for a recorder: fixed size, copied into a
/// bounded channel (no allocation per message; dropped and counted when the channel is
/// full, so the loop never waits on the recorder).
#[derive(Clone, Copy, Debug)]
pub struct RawFrame {
    /// Loop time of the tick (incoming) or of the last tick before the write (outgoing).
    pub stamp_s: f64,
    /// Written by us (true) or read from the vehicle (false).
    pub outgoing: bool,
    len: u16,
    bytes: [u8; MAX_FRAME],
}

impl RawFrame {
    fn new(stamp_s: f64, outgoing: bool, frame: &[u8]) -> Self {
        let n = frame.len().min(MAX_FRAME);
        let mut bytes = [0u8; MAX_FRAME];
        bytes[..n].copy_from_slice(&frame[..n]);
        Self {
            stamp_s,
            outgoing,
            len: n as u16,
            bytes,
        }
    }

    /// The frame, magic byte to signature.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }
}

/// At most this many incoming messages are applied per `tick` (socket and queue each):
/// a sender that floods faster than the loop reads cannot keep one tick spinning. What
/// is left stays in the socket buffer for the next tick.
pub const MAX_MESSAGES_PER_TICK: usize = 4096;

/// Progress of an acknowledged command (arm, mode).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum CommandStatus {
    /// Nothing requested.
    Idle,
    /// Sent, waiting for COMMAND_ACK (attempt number, from 1).
    Pending {
        /// Attempts made so far.
        attempt: u32,
    },
    /// ACK with MAV_RESULT_ACCEPTED (or the heartbeat shows the result).
    Accepted,
    /// ACK with another result (MAV_RESULT number).
    Rejected {
        /// MAV_RESULT value.
        result: u8,
    },
    /// No ACK after every retry.
    TimedOut,
}

/// ATTITUDE (30).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Attitude {
    /// Loop time it was applied.
    pub stamp_s: f64,
    /// Vehicle boot time, ms.
    pub time_boot_ms: u32,
    /// Roll, rad.
    pub roll: f64,
    /// Pitch, rad.
    pub pitch: f64,
    /// Yaw, rad.
    pub yaw: f64,
    /// Body rates p, q, r, rad/s.
    pub rates: [f64; 3],
}

impl Attitude {
    fn of(a: &ATTITUDE_DATA, now_s: f64) -> Self {
        Self {
            stamp_s: now_s,
            time_boot_ms: a.time_boot_ms,
            roll: f64::from(a.roll),
            pitch: f64::from(a.pitch),
            yaw: f64::from(a.yaw),
            rates: [
                f64::from(a.rollspeed),
                f64::from(a.pitchspeed),
                f64::from(a.yawspeed),
            ],
        }
    }
}

/// LOCAL_POSITION_NED (32).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LocalPosition {
    /// Loop time it was applied.
    pub stamp_s: f64,
    /// Vehicle boot time, ms.
    pub time_boot_ms: u32,
    /// Position NED, m.
    pub position: [f64; 3],
    /// Velocity NED, m/s.
    pub velocity: [f64; 3],
}

impl LocalPosition {
    fn of(p: &LOCAL_POSITION_NED_DATA, now_s: f64) -> Self {
        Self {
            stamp_s: now_s,
            time_boot_ms: p.time_boot_ms,
            position: [f64::from(p.x), f64::from(p.y), f64::from(p.z)],
            velocity: [f64::from(p.vx), f64::from(p.vy), f64::from(p.vz)],
        }
    }
}

/// Depth from SCALED_PRESSURE2 (137), the external pressure sensor.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Depth {
    /// Loop time it was applied.
    pub stamp_s: f64,
    /// Absolute pressure, hPa.
    pub press_abs_hpa: f64,
    /// Depth below the surface, m (+ down).
    pub depth_m: f64,
    /// Water temperature, degC.
    pub temperature_c: f64,
}

/// SERVO_OUTPUT_RAW (36): the motor PWMs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ServoOutputs {
    /// Loop time it was applied.
    pub stamp_s: f64,
    /// Servo 1..16, us.
    pub pwm: [u16; 16],
}

impl ServoOutputs {
    fn of(s: &SERVO_OUTPUT_RAW_DATA, now_s: f64) -> Self {
        Self {
            stamp_s: now_s,
            pwm: [
                s.servo1_raw,
                s.servo2_raw,
                s.servo3_raw,
                s.servo4_raw,
                s.servo5_raw,
                s.servo6_raw,
                s.servo7_raw,
                s.servo8_raw,
                s.servo9_raw,
                s.servo10_raw,
                s.servo11_raw,
                s.servo12_raw,
                s.servo13_raw,
                s.servo14_raw,
                s.servo15_raw,
                s.servo16_raw,
            ],
        }
    }
}

/// RC_CHANNELS (65): the input channels as the vehicle applies them (an override or
/// MANUAL_CONTROL turned into one shows here).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct RcChannels {
    /// Loop time it was applied.
    pub stamp_s: f64,
    /// Channels 1..8, us (0: no value).
    pub pwm: [u16; 8],
}

impl RcChannels {
    fn of(r: &RC_CHANNELS_DATA, now_s: f64) -> Self {
        Self {
            stamp_s: now_s,
            pwm: [
                r.chan1_raw,
                r.chan2_raw,
                r.chan3_raw,
                r.chan4_raw,
                r.chan5_raw,
                r.chan6_raw,
                r.chan7_raw,
                r.chan8_raw,
            ],
        }
    }

    /// Channels 1..6 (the ones markhold commands) at neutral.
    pub fn neutral(&self) -> bool {
        self.pwm[..6]
            .iter()
            .all(|&p| p == crate::pilot::PWM_NEUTRAL)
    }
}

/// Traffic counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LinkCounters {
    /// Frames written.
    pub sent: u64,
    /// Frames decoded and applied.
    pub received: u64,
    /// Frames not written (no peer yet, buffers full).
    pub send_dropped: u64,
    /// Frames not written because the socket reported an error (network down).
    pub send_errors: u64,
    /// Pilot-input frames written (RC override / MANUAL_CONTROL).
    pub pilot_inputs: u64,
    /// Frames written as SYSID_MYGCS (pilot input and its release: nothing else).
    pub gcs_frames: u64,
    /// Pilot-input frames not written because the pilot's station is silent.
    pub gcs_withheld: u64,
    /// markhold's own heartbeats written.
    pub heartbeats: u64,
    /// Incoming frames dropped because the queue was full.
    pub receive_dropped: u64,
    /// Frames that failed to parse (unknown id, bad payload).
    pub parse_errors: u64,
    /// Frames dropped by signing: signed with a key that is not ours, or replayed.
    pub rejected_bad_signature: u64,
    /// Frames dropped by signing: unsigned (or MAVLink 1) while signing is on.
    pub rejected_unsigned: u64,
    /// Ticks that stopped reading at `MAX_MESSAGES_PER_TICK` with input still waiting.
    pub receive_batch_full: u64,
    /// Stream transport reconnections.
    pub reconnects: u64,
    /// STATUSTEXT messages written.
    pub statustexts_sent: u64,
    /// RC_CHANNELS reports from the vehicle.
    pub rc_reports: u64,
    /// Of them, the last ones in a row with channels 1..6 at neutral.
    pub rc_neutral_run: u64,
    /// SERVO_OUTPUT_RAW reports from the vehicle.
    pub servo_reports: u64,
    /// Of them, the last ones in a row with every output within the thrusters' dead band.
    pub servo_neutral_run: u64,
}

/// What the link knows about the vehicle.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VehicleState {
    /// Vehicle system id (configured until discovered).
    pub system_id: u8,
    /// Vehicle component id.
    pub component_id: u8,
    /// A vehicle heartbeat has set the ids.
    pub discovered: bool,
    /// HEARTBEAT.base_mode has SAFETY_ARMED.
    pub armed: bool,
    /// Mode from the last heartbeat.
    pub mode: Option<ArduSubMode>,
    /// Raw custom_mode of the last heartbeat.
    pub custom_mode: u32,
    /// Mode changes seen in heartbeats (compare between frames to reset the keeper).
    pub mode_changes: u64,
    /// MAV_TYPE of the vehicle's heartbeat.
    pub vehicle_type: u8,
    /// Loop time the vehicle was last heard: the link-loss clock (the name is from when
    /// only heartbeats counted). Any message from the vehicle's autopilot (its system and
    /// component id, once a heartbeat discovered it) counts; ATTITUDE and the other
    /// streams at `stream_hz` keep it fresh.
    pub last_heartbeat_s: Option<f64>,
    /// Loop time of the last HEARTBEAT message from the vehicle.
    pub last_vehicle_heartbeat_s: Option<f64>,
    /// Vehicle heartbeats seen.
    pub heartbeats: u64,
    /// The vehicle is heard: `last_heartbeat_s` within `vehicle_timeout_s`.
    pub heartbeat_ok: bool,
    /// Stream transport up (always true for UDP).
    pub transport_connected: bool,
    /// Last ATTITUDE.
    pub attitude: Option<Attitude>,
    /// Last LOCAL_POSITION_NED.
    pub local_position: Option<LocalPosition>,
    /// Last depth from SCALED_PRESSURE2.
    pub depth: Option<Depth>,
    /// Last SERVO_OUTPUT_RAW.
    pub servo_outputs: Option<ServoOutputs>,
    /// Last RC_CHANNELS.
    pub rc_channels: Option<RcChannels>,
    /// Arm/disarm command progress.
    pub arm_command: CommandStatus,
    /// Set-mode command progress.
    pub mode_command: CommandStatus,
    /// Traffic counters.
    pub counters: LinkCounters,
    /// The pilot's own input (another sender's MANUAL_CONTROL / RC override).
    pub pilot: PilotSeen,
    /// The pilot's station: a HEARTBEAT from SYSID_MYGCS that is not markhold's.
    pub station: StationSeen,
    /// STATUSTEXT messages the vehicle sent.
    pub statustexts: u64,
    /// The vehicle's last STATUSTEXT.
    pub last_statustext: Option<String>,
    /// SYS_STATUS: sensors enabled but not healthy (MAV_SYS_STATUS_SENSOR bits).
    pub sensors_unhealthy: u32,
    /// PARAM_VALUE.param_count: how many parameters the vehicle has.
    pub param_count: Option<u16>,
    /// AUTOPILOT_VERSION.flight_sw_version (major << 24 | minor << 16 | patch << 8 | type).
    pub flight_sw_version: Option<u32>,
    /// The heartbeat's system_status is CRITICAL or EMERGENCY: ArduSub sets CRITICAL while
    /// any failsafe (pilot input, battery, GCS, EKF, terrain) is active.
    pub vehicle_failsafe: bool,
}

impl VehicleState {
    fn new(cfg: &LinkConfig) -> Self {
        Self {
            system_id: cfg.vehicle_system_id,
            component_id: cfg.vehicle_component_id,
            discovered: false,
            armed: false,
            mode: None,
            custom_mode: 0,
            mode_changes: 0,
            vehicle_type: 0,
            last_heartbeat_s: None,
            last_vehicle_heartbeat_s: None,
            heartbeats: 0,
            heartbeat_ok: false,
            transport_connected: false,
            attitude: None,
            local_position: None,
            depth: None,
            servo_outputs: None,
            rc_channels: None,
            arm_command: CommandStatus::Idle,
            mode_command: CommandStatus::Idle,
            counters: LinkCounters::default(),
            pilot: PilotSeen::default(),
            station: StationSeen::default(),
            statustexts: 0,
            last_statustext: None,
            sensors_unhealthy: 0,
            param_count: None,
            flight_sw_version: None,
            vehicle_failsafe: false,
        }
    }
}

const CMD_ARM: u16 = 400;
const CMD_SET_MODE: u16 = 176;
const CMD_SET_MESSAGE_INTERVAL: u16 = 511;
const ARM_MAGIC_FORCE: f32 = 21196.0;
/// Streams requested with SET_MESSAGE_INTERVAL: ATTITUDE, LOCAL_POSITION_NED,
/// SERVO_OUTPUT_RAW, RC_CHANNELS, SCALED_PRESSURE2.
pub const STREAMS: [u32; 5] = [30, 32, 36, 65, 137];
const LOCAL_POSITION_NED_ID: u32 = 32;
/// LOCAL_POSITION_NED is asked for at least this often on an ALT_HOLD site: the depth
/// target is rebased on it each camera frame.
pub const LOCAL_POSITION_MIN_HZ: f64 = 50.0;
const GRAVITY: f64 = 9.80665;

#[derive(Clone, Copy, Debug)]
struct PendingCommand {
    command: MavCmd,
    params: [f32; 7],
    sent_s: f64,
    attempt: u32,
}

/// The vehicle link.
pub struct VehicleLink {
    cfg: LinkConfig,
    map: PilotMap,
    transport: Transport,
    signing: Option<Arc<SigningData>>,
    /// Saves the signing timestamps used beside the key (signing on only).
    signing_clock: Option<crate::signing_clock::TimestampKeeper>,
    /// MAVLink sequence of the frames sent as the vehicle's system id, and of those sent
    /// as SYSID_MYGCS: a receiver counts loss per sender.
    seq: u8,
    seq_gcs: u8,
    state: VehicleState,
    /// The vehicle's GCS failsafe timeout (FS_GCS_TIMEOUT, or the site's until read) and
    /// the station silence it allows ([`crate::config::station_timeout_s`]).
    fs_gcs_timeout_s: f64,
    station_timeout_s: f64,
    /// FS_GCS_TIMEOUT came from the vehicle.
    fs_gcs_timeout_read: bool,
    /// The transport was closed ([`VehicleLink::close`]): nothing more goes out.
    closed: bool,
    last_hb_sent_s: Option<f64>,
    last_pilot_s: Option<f64>,
    /// Last pilot input the caller sent (not the keep-alive).
    last_commanded_s: Option<f64>,
    last_streams_s: Option<f64>,
    arm_pending: Option<PendingCommand>,
    mode_pending: Option<PendingCommand>,
    requested_mode: Option<ArduSubMode>,
    requested_arm: Option<bool>,
    origin_sent: bool,
    /// Setpoint mode: the last target sent (LOCAL_NED position, yaw), repeated while the
    /// marker is not seen.
    last_target: Option<([f64; 3], f64)>,
    /// Setpoint mode: vision estimates written / withheld for want of a covariance.
    vision_sent: u64,
    vision_withheld: u64,
    /// ALT_HOLD depth targets written ([`VehicleLink::send_depth_target`]).
    depth_targets: u64,
    last_tick_s: Option<f64>,
    /// Keep-alive neutral pilot input while the vehicle's heartbeat is current.
    pilot_keepalive: bool,
    /// The last write failed (logged once per failing stretch).
    send_failing: bool,
    /// Signing rejections already reported in the log.
    signing_reported: u64,
    /// Raw traffic tap (a recorder), and the frames it could not take.
    tap: Option<std::sync::mpsc::SyncSender<RawFrame>>,
    tap_dropped: u64,
    /// PARAM_VALUE answers: value and the loop time they arrived.
    params: std::collections::BTreeMap<String, (f32, f64)>,
    /// Liveness on this link's monotonic clock (`set_monotonic_liveness`), and when the
    /// vehicle was last heard on it.
    monotonic_liveness: bool,
    heard_at: Option<std::time::Instant>,
}

/// The RC_CHANNELS_OVERRIDE that asks `target_system` / `target_component` for effort
/// `e`: channels 1 to 6 from the pilot map, 7 and 8 released (0 = back to the RC
/// receiver / joystick).
pub fn rc_override(
    map: &PilotMap,
    e: &Effort,
    target_system: u8,
    target_component: u8,
) -> MavMessage {
    let ch = map.rc_channels(e);
    MavMessage::RC_CHANNELS_OVERRIDE(RC_CHANNELS_OVERRIDE_DATA {
        chan1_raw: ch[0],
        chan2_raw: ch[1],
        chan3_raw: ch[2],
        chan4_raw: ch[3],
        chan5_raw: ch[4],
        chan6_raw: ch[5],
        chan7_raw: 0,
        chan8_raw: 0,
        target_system,
        target_component,
        ..Default::default()
    })
}

/// A MAVLink 2 signing key file: 32 raw bytes, or 64 hex digits.
pub fn read_key(path: &std::path::Path) -> Result<[u8; 32], AutopilotError> {
    let p = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| AutopilotError::SigningKey {
        path: p.clone(),
        reason: e.to_string(),
    })?;
    if bytes.len() == 32 {
        let mut k = [0u8; 32];
        k.copy_from_slice(&bytes);
        return Ok(k);
    }
    let text = String::from_utf8_lossy(&bytes);
    let hex = text.trim();
    if hex.len() == 64 && hex.chars().all(|c| c.is_ascii_hexdigit()) {
        let mut k = [0u8; 32];
        for (i, kb) in k.iter_mut().enumerate() {
            *kb = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).map_err(|e| {
                AutopilotError::SigningKey {
                    path: p.clone(),
                    reason: e.to_string(),
                }
            })?;
        }
        return Ok(k);
    }
    Err(AutopilotError::SigningKey {
        path: p,
        reason: format!(
            "expected 32 raw bytes or 64 hex digits, found {} bytes",
            bytes.len()
        ),
    })
}

impl VehicleLink {
    /// Why the last connect (tcp) or open (serial) failed, until one succeeds: so a
    /// caller waiting for the vehicle can say "connection refused" at once.
    pub fn transport_error(&self) -> Option<String> {
        self.transport.last_error()
    }

    /// Opens the transport named by `cfg.url` (validated first; a bad URL is a clear
    /// error). Sockets that must exist are bound here; TCP/serial connect in the background.
    pub fn connect(cfg: &LinkConfig) -> Result<Self, AutopilotError> {
        cfg.validate()?;
        let (signing, signing_clock) = match &cfg.signing_key_file {
            Some(path) => {
                let key = read_key(path)?;
                let (keeper, start) = crate::signing_clock::TimestampKeeper::open(path)?;
                let sd = crate::signing_clock::signing_data_from(key, cfg.signing_link_id, start);
                (Some(Arc::new(sd)), Some(keeper))
            }
            None => (None, None),
        };
        let transport = Transport::open(
            &cfg.url,
            signing.clone(),
            cfg.udp_receive_on_tick,
            (cfg.vehicle_system_id, cfg.vehicle_component_id),
        )?;
        let mut state = VehicleState::new(cfg);
        state.transport_connected = transport.always_connected;
        tracing::info!(
            url = %cfg.url,
            compid = cfg.component_id,
            gcs_sysid = cfg.gcs_system_id,
            "vehicle link open"
        );
        Ok(Self {
            cfg: cfg.clone(),
            map: PilotMap::from_config(cfg),
            transport,
            signing,
            signing_clock,
            seq: 0,
            seq_gcs: 0,
            state,
            fs_gcs_timeout_s: cfg.fs_gcs_timeout_s,
            station_timeout_s: crate::config::station_timeout_s(cfg.fs_gcs_timeout_s),
            fs_gcs_timeout_read: false,
            closed: false,
            last_hb_sent_s: None,
            last_pilot_s: None,
            last_commanded_s: None,
            last_streams_s: None,
            arm_pending: None,
            mode_pending: None,
            requested_mode: None,
            requested_arm: None,
            origin_sent: false,
            last_target: None,
            vision_sent: 0,
            vision_withheld: 0,
            depth_targets: 0,
            last_tick_s: None,
            pilot_keepalive: true,
            send_failing: false,
            signing_reported: 0,
            tap: None,
            tap_dropped: 0,
            params: std::collections::BTreeMap::new(),
            monotonic_liveness: false,
            heard_at: None,
        })
    }

    /// Copy every frame written and every frame read (as `tick` applies it) to `tap` (a
    /// recorder's bounded channel): fixed-size copies, `try_send`, never waits.
    pub fn set_raw_tap(&mut self, tap: Option<std::sync::mpsc::SyncSender<RawFrame>>) {
        self.tap = tap;
    }

    /// Frames the tap's channel was too full to take.
    pub fn raw_tap_dropped(&self) -> u64 {
        self.tap_dropped
    }

    fn tap_frame(&mut self, outgoing: bool, frame: &[u8], stamp_s: f64) {
        if let Some(tx) = &self.tap {
            if tx
                .try_send(RawFrame::new(stamp_s, outgoing, frame))
                .is_err()
            {
                self.tap_dropped += 1;
            }
        }
    }

    /// The receive buffer (SO_RCVBUF) the kernel granted the UDP socket, bytes.
    pub fn udp_recv_buffer(&self) -> Option<usize> {
        self.transport.udp_recv_buffer
    }

    /// Why the vehicle is not heard, when the link can tell: frames dropped by signing
    /// (another key, or a vehicle that does not sign), or, with signing on, nothing at all
    /// from a vehicle (one keyed differently drops our frames and, on UDP, never answers
    /// a sender it could not authenticate). None otherwise.
    pub fn signing_diagnosis(&self) -> Option<String> {
        let c = &self.state.counters;
        if c.rejected_bad_signature > 0 {
            return Some(format!(
                "{} MAVLink frames dropped for a signature made with another key: the vehicle \
                 signs with a key that is not link.signing_key_file's",
                c.rejected_bad_signature
            ));
        }
        if c.rejected_unsigned > 0 {
            return Some(format!(
                "{} unsigned MAVLink frames dropped: link.signing_key_file is set but the \
                 vehicle does not sign",
                c.rejected_unsigned
            ));
        }
        if self.signing.is_some() && !self.state.discovered {
            return Some(format!(
                "no MAVLink frame accepted from the vehicle ({} sent) with signing on \
                 (link.signing_key_file): a vehicle with another key drops our frames and \
                 does not answer them; check that both sides use the same key",
                c.sent
            ));
        }
        None
    }

    /// Local socket address for `udpin:`/`udpout:`/`tcpin:` (handy with port 0).
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.transport.local_addr()
    }

    /// The configuration in use.
    pub fn config(&self) -> &LinkConfig {
        &self.cfg
    }

    /// Judge liveness on this link's monotonic clock (how long ago the vehicle was last
    /// heard) instead of the caller's loop time: for a live run whose loop time is a
    /// camera's clock, which may jump (start-up, a stream restarted) or run apart from
    /// the vehicle's. `last_heartbeat_s` is then kept as `now_s` minus that age, so
    /// everything reading it sees the true age. Off by default (simulation time).
    pub fn set_monotonic_liveness(&mut self, on: bool) {
        self.monotonic_liveness = on;
    }

    /// Turns the automatic neutral pilot input (sent while nothing is commanded and the
    /// vehicle's heartbeat is current) on or off. On by default.
    pub fn set_pilot_keepalive(&mut self, on: bool) {
        self.pilot_keepalive = on;
    }

    /// The sender of `msg`: SYSID_MYGCS for pilot input (the only messages ArduSub takes
    /// from it alone), the vehicle's system id for everything else; our component id.
    fn header(&mut self, pilot: bool) -> MavHeader {
        let (system_id, seq) = if pilot {
            (self.cfg.gcs_system_id, &mut self.seq_gcs)
        } else {
            (self.state.system_id, &mut self.seq)
        };
        let h = MavHeader {
            system_id: u32::from(system_id),
            component_id: self.cfg.component_id,
            sequence: *seq,
        };
        *seq = seq.wrapping_add(1);
        h
    }

    /// Serializes and writes one message now, on this thread. Pilot input goes out as
    /// SYSID_MYGCS, and not at all while the pilot's station is silent (counted).
    fn send(&mut self, msg: &MavMessage) -> Result<bool, AutopilotError> {
        let pilot = is_pilot_input(msg);
        if pilot && !self.gcs_traffic_allowed() {
            self.state.counters.gcs_withheld += 1;
            return Ok(false);
        }
        if self.closed {
            self.state.counters.send_dropped += 1;
            return Ok(false);
        }
        let header = self.header(pilot);
        let mut buf = [0u8; MAX_FRAME];
        let mut cur = Cursor::new(&mut buf[..]);
        let n = mavlink::write_v2_msg_signed(&mut cur, header, msg, self.signing.as_deref())
            .map_err(|e| AutopilotError::Send {
                message: msg.message_name(),
                source: std::io::Error::other(e.to_string()),
            })?;
        if let Some(clock) = &mut self.signing_clock {
            clock.used(&buf[..n]);
        }
        match self.transport.writer.write(&buf[..n]) {
            Ok(WriteOutcome::Sent) => {
                self.state.counters.sent += 1;
                if pilot {
                    self.state.counters.gcs_frames += 1;
                }
                if self.tap.is_some() {
                    let stamp = self.last_tick_s.unwrap_or(0.0);
                    self.tap_frame(true, &buf[..n], stamp);
                }
                if self.send_failing {
                    self.send_failing = false;
                    tracing::info!("vehicle link sends again");
                }
                Ok(true)
            }
            Ok(WriteOutcome::NoPeer | WriteOutcome::Dropped) => {
                self.state.counters.send_dropped += 1;
                Ok(false)
            }
            // A network that goes away (tether unplugged, interface down) must not stop the
            // loop: count it, log the first, and let heartbeat loss drive the failsafes.
            Err(e) => {
                self.state.counters.send_errors += 1;
                if !self.send_failing {
                    self.send_failing = true;
                    tracing::warn!(message = msg.message_name(), error = %e, "vehicle link send failed");
                }
                Ok(false)
            }
        }
    }

    fn command_long(
        &mut self,
        command: MavCmd,
        params: [f32; 7],
        confirmation: u8,
    ) -> Result<bool, AutopilotError> {
        let msg = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: params[0],
            param2: params[1],
            param3: params[2],
            param4: params[3],
            param5: params[4],
            param6: params[5],
            param7: params[6],
            command,
            target_system: self.state.system_id,
            target_component: self.state.component_id,
            confirmation,
        });
        self.send(&msg)
    }

    /// markhold's heartbeat, as a component of the vehicle: an onboard controller, not
    /// a ground station (ArduSub's `GCS_MAVLINK::handle_heartbeat` takes any heartbeat
    /// from SYSID_MYGCS as ground-station contact; this one is from the vehicle's id).
    fn send_heartbeat(&mut self) -> Result<(), AutopilotError> {
        let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        });
        if self.send(&msg)? {
            self.state.counters.heartbeats += 1;
        }
        Ok(())
    }

    fn request_streams(&mut self) -> Result<(), AutopilotError> {
        for id in STREAMS {
            // The depth target is the local position's depth plus the camera's error
            // (`send_depth_target`): its age is the target's error on a moving estimate.
            // Only where the depth target is sent: elsewhere the position would come
            // five times as often as the attitude, and a camera placed from telemetry
            // (`hil --vehicle`) would pair a new position with an old attitude.
            let depth_target = matches!(self.cfg.mode, crate::config::LinkMode::AltHold);
            let hz = if id == LOCAL_POSITION_NED_ID && depth_target {
                self.cfg.stream_hz.max(LOCAL_POSITION_MIN_HZ)
            } else {
                self.cfg.stream_hz
            };
            let interval_us = (1e6 / hz) as f32;
            self.command_long(
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                [id as f32, interval_us, 0.0, 0.0, 0.0, 0.0, 0.0],
                0,
            )?;
        }
        Ok(())
    }

    /// The vehicle was heard at `now_s` (liveness).
    fn heard(&mut self, was_ok: bool, now_s: f64) {
        self.state.last_heartbeat_s = Some(now_s);
        self.heard_at = Some(std::time::Instant::now());
        self.state.heartbeat_ok = true;
        if !was_ok {
            // A returning (maybe rebooted) vehicle forgets its streams.
            self.last_streams_s = None;
            self.origin_sent = false;
            // Its EKF's frame may have restarted: no stale target is repeated.
            self.last_target = None;
        }
    }

    fn apply(&mut self, h: &MavHeader, msg: &MavMessage, now_s: f64) {
        self.state.counters.received += 1;
        self.observe_station(h, msg, now_s);
        if let MavMessage::HEARTBEAT(hb) = msg {
            self.apply_heartbeat(h, hb, now_s);
            return;
        }
        if self.observe_pilot(h, msg, now_s) {
            return;
        }
        if !self.state.discovered || h.system_id != u32::from(self.state.system_id) {
            return;
        }
        // Liveness: anything from the autopilot (a camera or companion computer on the
        // same system id has another component id and does not count).
        if h.component_id == self.state.component_id {
            let was_ok = self.state.heartbeat_ok;
            self.heard(was_ok, now_s);
        }
        match msg {
            MavMessage::ATTITUDE(a) => self.state.attitude = Some(Attitude::of(a, now_s)),
            MavMessage::LOCAL_POSITION_NED(p) => {
                self.state.local_position = Some(LocalPosition::of(p, now_s));
            }
            MavMessage::SCALED_PRESSURE2(p) => self.state.depth = Some(self.depth_of(p, now_s)),
            // Port 0 carries servos 1..16 (the extension fields hold 9..16).
            MavMessage::SERVO_OUTPUT_RAW(s) if s.port == 0 => {
                let out = ServoOutputs::of(s, now_s);
                let c = &mut self.state.counters;
                c.servo_reports += 1;
                let band = self.cfg.thruster_deadband_us;
                let neutral = out.pwm[..8]
                    .iter()
                    .filter(|&&p| p != 0)
                    .all(|&p| (f64::from(p) - f64::from(crate::pilot::PWM_NEUTRAL)).abs() <= band);
                c.servo_neutral_run = if neutral { c.servo_neutral_run + 1 } else { 0 };
                self.state.servo_outputs = Some(out);
            }
            MavMessage::RC_CHANNELS(r) => {
                let rc = RcChannels::of(r, now_s);
                let c = &mut self.state.counters;
                c.rc_reports += 1;
                c.rc_neutral_run = if rc.neutral() {
                    c.rc_neutral_run + 1
                } else {
                    0
                };
                self.state.rc_channels = Some(rc);
            }
            MavMessage::COMMAND_ACK(ack) => self.apply_ack(ack),
            _ => self.apply_gcs(msg, now_s),
        }
    }

    /// A HEARTBEAT: discovers the vehicle, then follows its arm state and mode.
    fn apply_heartbeat(&mut self, h: &MavHeader, hb: &HEARTBEAT_DATA, now_s: f64) {
        // GCSes and companions on the same link also heartbeat: only a vehicle counts.
        // Cameras, gimbals and routers heartbeat too: only the autopilot component counts.
        if hb.mavtype == MavType::MAV_TYPE_GCS
            || hb.autopilot == MavAutopilot::MAV_AUTOPILOT_INVALID
            || h.component_id != self.cfg.vehicle_component_id
        {
            return;
        }
        let Ok(sysid) = u8::try_from(h.system_id) else {
            return;
        };
        if self.state.discovered && sysid != self.state.system_id {
            return;
        }
        if !self.state.discovered {
            tracing::info!(sysid, compid = h.component_id, "vehicle discovered");
        }
        let was_ok = self.state.heartbeat_ok;
        self.state.system_id = sysid;
        self.state.component_id = h.component_id;
        self.state.discovered = true;
        self.state.vehicle_type = hb.mavtype as u8;
        let armed = hb
            .base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
        if armed != self.state.armed {
            tracing::info!(armed, "vehicle arm state changed");
        }
        self.state.armed = armed;
        let mode = ArduSubMode::from_custom_mode(hb.custom_mode);
        if mode != self.state.mode {
            tracing::info!(?mode, "vehicle mode changed");
            if self.state.mode.is_some() {
                self.state.mode_changes += 1;
            }
        }
        self.state.mode = mode;
        self.state.custom_mode = hb.custom_mode;
        let failsafe = matches!(
            hb.system_status,
            MavState::MAV_STATE_CRITICAL | MavState::MAV_STATE_EMERGENCY
        );
        if failsafe != self.state.vehicle_failsafe {
            if failsafe {
                tracing::warn!(status = ?hb.system_status, "vehicle reports a failsafe (heartbeat system_status)");
            } else {
                tracing::info!("vehicle failsafe cleared (heartbeat system_status)");
            }
            self.state.vehicle_failsafe = failsafe;
        }
        self.state.last_vehicle_heartbeat_s = Some(now_s);
        self.state.heartbeats += 1;
        self.heard(was_ok, now_s);
        // The heartbeat confirms a pending request even if its ACK was lost.
        if self.mode_pending.is_some() && mode.is_some() && mode == self.requested_mode {
            self.mode_pending = None;
            self.state.mode_command = CommandStatus::Accepted;
        }
        if self.arm_pending.is_some() && self.requested_arm == Some(armed) {
            self.arm_pending = None;
            self.state.arm_command = CommandStatus::Accepted;
        }
    }

    /// Depth from SCALED_PRESSURE2 (the depth sensor), with the site's water and surface.
    fn depth_of(&self, p: &SCALED_PRESSURE2_DATA, now_s: f64) -> Depth {
        let pa = f64::from(p.press_abs) * 100.0;
        let depth = (pa - self.cfg.surface_pressure_pa) / (self.cfg.water_density_kg_m3 * GRAVITY);
        Depth {
            stamp_s: now_s,
            press_abs_hpa: f64::from(p.press_abs),
            depth_m: depth,
            temperature_c: f64::from(p.temperature) / 100.0,
        }
    }

    /// A COMMAND_ACK settles the pending arm or mode request it answers.
    fn apply_ack(&mut self, ack: &COMMAND_ACK_DATA) {
        let cmd = ack.command as u16;
        let accepted = ack.result == MavResult::MAV_RESULT_ACCEPTED;
        let in_progress = ack.result == MavResult::MAV_RESULT_IN_PROGRESS;
        let status = if accepted {
            CommandStatus::Accepted
        } else {
            CommandStatus::Rejected {
                result: ack.result as u8,
            }
        };
        if in_progress {
            return;
        }
        if cmd == CMD_ARM && self.arm_pending.is_some() {
            self.arm_pending = None;
            self.state.arm_command = status;
            tracing::info!(?status, "arm/disarm acknowledged");
        } else if cmd == CMD_SET_MODE && self.mode_pending.is_some() {
            self.mode_pending = None;
            self.state.mode_command = status;
            tracing::info!(?status, "set mode acknowledged");
        } else if cmd == CMD_SET_MESSAGE_INTERVAL && !accepted {
            tracing::debug!(result = ack.result as u8, "stream request refused");
        }
    }

    fn retry(&mut self, which: u16, now_s: f64) -> Result<(), AutopilotError> {
        let pending = if which == CMD_ARM {
            &mut self.arm_pending
        } else {
            &mut self.mode_pending
        };
        let Some(p) = pending.as_mut() else {
            return Ok(());
        };
        if now_s - p.sent_s < self.cfg.command_timeout_s {
            return Ok(());
        }
        if p.attempt > self.cfg.command_retries {
            *pending = None;
            tracing::warn!(command = which, "command timed out without COMMAND_ACK");
            if which == CMD_ARM {
                self.state.arm_command = CommandStatus::TimedOut;
            } else {
                self.state.mode_command = CommandStatus::TimedOut;
            }
            return Ok(());
        }
        p.attempt += 1;
        p.sent_s = now_s;
        let (cmd, params, attempt) = (p.command, p.params, p.attempt);
        let status = CommandStatus::Pending { attempt };
        if which == CMD_ARM {
            self.state.arm_command = status;
        } else {
            self.state.mode_command = status;
        }
        tracing::debug!(command = which, attempt, "command retry");
        // COMMAND_LONG.confirmation counts retransmissions.
        self.command_long(cmd, params, (attempt - 1).min(255) as u8)?;
        Ok(())
    }

    /// Drive the session at loop time `now_s`: receive and apply incoming messages, GCS
    /// heartbeat, stream requests (and re-requests), command retries, link-loss detection,
    /// reconnect, pilot-input keep-alive. Call every frame.
    ///
    /// Network errors never fail this or the `send_*`/`request_*` calls: they are counted in
    /// `state().counters` (`send_errors`, `send_dropped`) and show up as heartbeat loss.
    pub fn tick(&mut self, now_s: f64) -> Result<(), AutopilotError> {
        if !now_s.is_finite() {
            return Ok(());
        }
        if self.last_tick_s.is_some_and(|last| now_s < last) {
            self.restart_schedules();
        }
        let prev_tick = self.last_tick_s;
        self.last_tick_s = Some(now_s);
        self.transport.writer.flush();
        self.drain_socket(now_s);
        self.drain_queue(now_s);
        self.read_task_counters();
        if let (true, Some(at)) = (self.monotonic_liveness, self.heard_at) {
            self.state.last_heartbeat_s = Some(now_s - at.elapsed().as_secs_f64());
        }
        self.check_link_loss(now_s);
        self.check_station(now_s);
        self.send_scheduled(now_s)?;
        self.keep_pilot_alive(now_s, prev_tick)
    }

    /// The loop clock restarted (replay, new HIL run): restart the schedules.
    fn restart_schedules(&mut self) {
        self.last_hb_sent_s = None;
        self.last_pilot_s = None;
        self.last_commanded_s = None;
        self.last_streams_s = None;
        self.state.last_heartbeat_s = None;
        self.state.last_vehicle_heartbeat_s = None;
        self.state.station.last_s = None;
        self.state.station.lost = false;
    }

    /// Applies what the socket holds (UDP read on this thread) until it would block, at
    /// most a batch per tick.
    fn drain_socket(&mut self, now_s: f64) {
        let mut n = 0;
        while let Some((h, m)) = self.transport.poll_tick() {
            if let Some(tx) = &self.tap {
                let f = RawFrame::new(now_s, false, self.transport.last_tick_frame());
                if tx.try_send(f).is_err() {
                    self.tap_dropped += 1;
                }
            }
            self.apply(&h, &m, now_s);
            n += 1;
            if n == MAX_MESSAGES_PER_TICK {
                self.state.counters.receive_batch_full += 1;
                break;
            }
        }
    }

    /// Applies what the transport task queued (messages, connection changes), at most a
    /// batch per tick.
    fn drain_queue(&mut self, now_s: f64) {
        let mut n = 0;
        while let Ok(inc) = self.transport.rx.try_recv() {
            n += 1;
            if n == MAX_MESSAGES_PER_TICK {
                self.state.counters.receive_batch_full += 1;
            }
            match inc {
                Incoming::Msg(h, m, raw) => {
                    if let Some(tx) = &self.tap {
                        if tx
                            .try_send(RawFrame::new(now_s, false, raw.as_slice()))
                            .is_err()
                        {
                            self.tap_dropped += 1;
                        }
                    }
                    self.apply(&h, &m, now_s)
                }
                Incoming::Connected(peer) => {
                    tracing::info!(%peer, "transport connected");
                    self.state.transport_connected = true;
                    // A new stream may be a new vehicle boot: ask again.
                    self.last_streams_s = None;
                }
                Incoming::Disconnected(why) => {
                    tracing::warn!(%why, "transport disconnected");
                    self.state.transport_connected = self.transport.always_connected;
                }
            }
            if n >= MAX_MESSAGES_PER_TICK {
                break;
            }
        }
    }

    /// Copies the transport task's counters into the state; the first signing rejection
    /// is explained in the log once.
    fn read_task_counters(&mut self) {
        let c = &self.transport.counters;
        self.state.counters.receive_dropped = c.dropped_rx.load(Ordering::Relaxed);
        self.state.counters.parse_errors = c.parse_errors.load(Ordering::Relaxed);
        self.state.counters.reconnects = c.reconnects.load(Ordering::Relaxed);
        self.state.counters.rejected_bad_signature = c.bad_signature.load(Ordering::Relaxed);
        self.state.counters.rejected_unsigned = c.unsigned.load(Ordering::Relaxed);
        let rejected =
            self.state.counters.rejected_bad_signature + self.state.counters.rejected_unsigned;
        if rejected > 0 && self.signing_reported == 0 {
            // Once: a wrong key shows up as a vehicle that is never heard.
            if let Some(why) = self.signing_diagnosis() {
                tracing::warn!("{why}");
            }
            self.signing_reported = rejected;
        }
    }

    /// Link loss: the vehicle not heard for `vehicle_timeout_s`.
    fn check_link_loss(&mut self, now_s: f64) {
        if let Some(t) = self.state.last_heartbeat_s {
            let ok = now_s - t <= self.cfg.vehicle_timeout_s;
            if self.state.heartbeat_ok && !ok {
                tracing::warn!(age_s = now_s - t, "vehicle not heard: link lost");
                // A half-open TCP connection never errors: make a new one.
                self.transport.request_reconnect();
            }
            self.state.heartbeat_ok = ok;
        }
    }

    /// The GCS heartbeat, stream (re-)requests and command retries that are due.
    fn send_scheduled(&mut self, now_s: f64) -> Result<(), AutopilotError> {
        let hb_period = 1.0 / self.cfg.heartbeat_hz;
        if self.last_hb_sent_s.is_none_or(|t| now_s - t >= hb_period) {
            self.send_heartbeat()?;
            self.last_hb_sent_s = Some(now_s);
        }
        if self.state.discovered
            && self.state.heartbeat_ok
            && self
                .last_streams_s
                .is_none_or(|t| now_s - t >= self.cfg.stream_rerequest_s)
        {
            self.request_streams()?;
            self.last_streams_s = Some(now_s);
            if !self.fs_gcs_timeout_read {
                // How long the vehicle's GCS failsafe waits decides how long the pilot's
                // station may be silent (ArduSub after 4.5 has the parameter).
                self.request_param(station::FS_GCS_TIMEOUT)?;
            }
        }
        self.retry(CMD_ARM, now_s)?;
        self.retry(CMD_SET_MODE, now_s)
    }

    /// Keep-alive: the loop sends pilot input after `tick` in each frame; if the previous
    /// frame sent none, centre the sticks now (at most twice `pilot_input_hz` when ticks
    /// come fast) so that ArduSub's pilot-input failsafe never fires.
    fn keep_pilot_alive(
        &mut self,
        now_s: f64,
        prev_tick: Option<f64>,
    ) -> Result<(), AutopilotError> {
        let idle = match (self.last_commanded_s, prev_tick) {
            (None, _) | (_, None) => true,
            (Some(p), Some(prev)) => p < prev,
        };
        let not_too_fast = self
            .last_pilot_s
            .is_none_or(|p| now_s - p >= 0.5 / self.cfg.pilot_input_hz);
        // In setpoint mode too: ArduSub's pilot-input failsafe does not look at the mode.
        if self.pilot_keepalive && self.state.heartbeat_ok && idle && not_too_fast {
            self.send_pilot(&Effort::NEUTRAL, now_s)?;
        }
        Ok(())
    }

    /// COMMAND_LONG 400 (arm 1 / disarm 0), retried until COMMAND_ACK or the heartbeat
    /// confirms. A new request replaces a pending one. Progress in `state().arm_command`.
    pub fn request_arm(&mut self, arm: bool, now_s: f64) -> Result<(), AutopilotError> {
        self.request_arm_with(arm, false, now_s)
    }

    /// Like `request_arm`, optionally forced (param2 = 21196 skips ArduSub's checks).
    pub fn request_arm_with(
        &mut self,
        arm: bool,
        force: bool,
        now_s: f64,
    ) -> Result<(), AutopilotError> {
        let params = [
            if arm { 1.0 } else { 0.0 },
            if force { ARM_MAGIC_FORCE } else { 0.0 },
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ];
        self.arm_pending = Some(PendingCommand {
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            params,
            sent_s: now_s,
            attempt: 1,
        });
        self.requested_arm = Some(arm);
        self.state.arm_command = CommandStatus::Pending { attempt: 1 };
        tracing::info!(arm, "arm request");
        self.command_long(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, params, 0)?;
        Ok(())
    }

    /// COMMAND_LONG 176 (param1 = 1 custom mode, param2 = mode), retried until COMMAND_ACK
    /// or the heartbeat shows the mode. Progress in `state().mode_command`.
    pub fn request_mode(&mut self, mode: ArduSubMode, now_s: f64) -> Result<(), AutopilotError> {
        let params = [1.0, mode.number() as f32, 0.0, 0.0, 0.0, 0.0, 0.0];
        self.mode_pending = Some(PendingCommand {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            params,
            sent_s: now_s,
            attempt: 1,
        });
        self.requested_mode = Some(mode);
        self.state.mode_command = CommandStatus::Pending { attempt: 1 };
        tracing::info!(?mode, "mode request");
        self.command_long(MavCmd::MAV_CMD_DO_SET_MODE, params, 0)?;
        Ok(())
    }

    fn send_pilot(&mut self, e: &Effort, now_s: f64) -> Result<(), AutopilotError> {
        let msg = match self.cfg.pilot_input {
            PilotInput::RcOverride => {
                rc_override(&self.map, e, self.state.system_id, self.state.component_id)
            }
            PilotInput::ManualControl => {
                let v = self.map.manual_control(e);
                MavMessage::MANUAL_CONTROL(MANUAL_CONTROL_DATA {
                    x: v[0],
                    y: v[1],
                    z: v[2],
                    r: v[3],
                    buttons: 0,
                    target: self.state.system_id,
                    // bit 0: pitch (s) valid, bit 1: roll (t) valid.
                    enabled_extensions: 0b11,
                    s: v[4],
                    t: v[5],
                    ..Default::default()
                })
            }
        };
        if self.send(&msg)? {
            self.state.counters.pilot_inputs += 1;
        }
        self.last_pilot_s = Some(now_s);
        Ok(())
    }

    /// Pilot input from efforts (RC override or MANUAL_CONTROL per `link.pilot_input`),
    /// dead zones compensated, written now.
    pub fn send_effort(&mut self, e: &Effort, now_s: f64) -> Result<(), AutopilotError> {
        if self.cfg.command != CommandKind::Effort {
            return Err(AutopilotError::WrongCommandMode {
                configured: self.cfg.command.as_str(),
                requested: "effort",
            });
        }
        self.last_commanded_s = Some(now_s);
        self.send_pilot(&e.clamped(), now_s)
    }

    /// Neutral pilot input (all channels 1500 / sticks centred), written now. Works in
    /// either command style, so a shutdown can always centre the sticks.
    pub fn send_neutral(&mut self, now_s: f64) -> Result<(), AutopilotError> {
        self.last_commanded_s = Some(now_s);
        self.send_pilot(&Effort::NEUTRAL, now_s)
    }

    /// Setpoint mode, once per camera frame. With this frame's measurement `meas`, the
    /// vehicle pose goes out as VISION_POSITION_ESTIMATE with its covariance (scaled by
    /// `vision_covariance_scale`) and the goal as SET_POSITION_TARGET_LOCAL_NED (position
    /// and yaw). A measurement whose covariance cannot be stated (not finite, a zero
    /// variance, pitch at +-90 degrees) sends no estimate: ArduSub would take NaN in any
    /// variance but the first as NaN noise. Without a measurement no estimate goes out and
    /// the last target is repeated, so the vehicle holds where it was sent while the
    /// marker is briefly lost (ArduSub drops a target after 3 s). Also sends
    /// SET_GPS_GLOBAL_ORIGIN once per vehicle boot.
    ///
    /// Frames (docs/frames.md, design/autopilot.md): the estimate is in the vision frame
    /// `L`, the marker frame turned so that a vehicle on station facing the marker is
    /// level with yaw 0: x_L = -z_m, y_L = x_m, z_L = -y_m (NED-like, origin at the
    /// marker). With ArduSub's EKF on external navigation for XY and yaw but the
    /// barometer for Z, the target is sent as the EKF's own position
    /// (LOCAL_POSITION_NED, ATTITUDE yaw) plus the remaining offset, so the two frames'
    /// origins need not agree; before that telemetry arrives the `L` goal is sent.
    pub fn send_setpoint(
        &mut self,
        meas: Option<&VisionPose>,
        t_marker_vehicle_goal: &Isometry3<f64>,
        now_s: f64,
    ) -> Result<(), AutopilotError> {
        if self.cfg.command != CommandKind::Setpoint {
            return Err(AutopilotError::WrongCommandMode {
                configured: self.cfg.command.as_str(),
                requested: "setpoint",
            });
        }
        if !self.origin_sent && self.state.discovered {
            #[allow(deprecated)]
            let msg = MavMessage::SET_GPS_GLOBAL_ORIGIN(SET_GPS_GLOBAL_ORIGIN_DATA {
                latitude: (self.cfg.origin_lat_deg * 1e7).round() as i32,
                longitude: (self.cfg.origin_lon_deg * 1e7).round() as i32,
                altitude: (self.cfg.origin_alt_m * 1000.0).round() as i32,
                target_system: self.state.system_id,
                time_usec: 0,
            });
            if self.send(&msg)? {
                self.origin_sent = true;
            }
        }
        let Some(meas) = meas else {
            if let Some((target, yaw)) = self.last_target {
                self.send_target(target, yaw, now_s)?;
            }
            return Ok(());
        };
        let Some(x) = self.send_vision_estimate(meas)? else {
            return Ok(());
        };

        let goal = t_vision_marker() * t_marker_vehicle_goal;
        let (_, _, gy) = goal.rotation.euler_angles();
        let delta = goal.translation.vector - Vector3::new(x[0], x[1], x[2]);
        let dyaw = wrap_pi(gy - x[5]);
        let (target, yaw) = match (self.state.local_position, self.state.attitude) {
            (Some(lp), Some(att)) => (
                [
                    lp.position[0] + delta.x,
                    lp.position[1] + delta.y,
                    lp.position[2] + delta.z,
                ],
                wrap_pi(att.yaw + dyaw),
            ),
            _ => {
                let g = goal.translation.vector;
                ([g.x, g.y, g.z], wrap_pi(gy))
            }
        };
        self.last_target = Some((target, yaw));
        self.send_target(target, yaw, now_s)
    }

    /// The vision estimate alone (no target): what the vehicle's EKF needs before the
    /// pilot can select GUIDED, so a field run sends it also while not engaged. Returns
    /// the pose sent as (x, y, z, roll, pitch, yaw) in `L`, or none when its covariance
    /// cannot be stated (nothing sent, counted).
    pub fn send_vision_estimate(
        &mut self,
        meas: &VisionPose,
    ) -> Result<Option<[f64; 6]>, AutopilotError> {
        if self.cfg.command != CommandKind::Setpoint {
            return Err(AutopilotError::WrongCommandMode {
                configured: self.cfg.command.as_str(),
                requested: "setpoint",
            });
        }
        let Some((x, cov)) = meas.euler_with_covariance() else {
            self.vision_withheld += 1;
            return Ok(None);
        };
        let usec = (meas.stamp_s.max(0.0) * 1e6) as u64;
        let vpe = MavMessage::VISION_POSITION_ESTIMATE(VISION_POSITION_ESTIMATE_DATA {
            usec,
            x: x[0] as f32,
            y: x[1] as f32,
            z: x[2] as f32,
            roll: x[3] as f32,
            pitch: x[4] as f32,
            yaw: x[5] as f32,
            covariance: upper_triangle(&cov, self.cfg.vision_covariance_scale),
            reset_counter: 0,
        });
        if self.send(&vpe)? {
            self.vision_sent += 1;
        }
        Ok(Some(x))
    }

    /// Vision estimates written (setpoint mode), and measurements whose covariance could
    /// not be stated (no estimate sent).
    pub fn vision_estimates(&self) -> (u64, u64) {
        (self.vision_sent, self.vision_withheld)
    }

    fn send_target(
        &mut self,
        target: [f64; 3],
        yaw: f64,
        now_s: f64,
    ) -> Result<(), AutopilotError> {
        let mask = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE;
        let sp = MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
            time_boot_ms: (now_s.max(0.0) * 1e3) as u32,
            x: target[0] as f32,
            y: target[1] as f32,
            z: target[2] as f32,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
            afx: 0.0,
            afy: 0.0,
            afz: 0.0,
            yaw: yaw as f32,
            yaw_rate: 0.0,
            type_mask: mask,
            target_system: self.state.system_id,
            target_component: self.state.component_id,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        });
        self.send(&sp)?;
        Ok(())
    }

    /// What the link knows about the vehicle.
    pub fn state(&self) -> &VehicleState {
        &self.state
    }

    /// Frames written to the wire.
    pub fn messages_sent(&self) -> u64 {
        self.state.counters.sent
    }

    /// Frames received and applied.
    pub fn messages_received(&self) -> u64 {
        self.state.counters.received
    }
}

/// RC_CHANNELS_OVERRIDE and MANUAL_CONTROL: what ArduSub takes only from SYSID_MYGCS
/// (`GCS_MAVLINK::handle_rc_channels_override`; `GCS_MAVLINK_Sub::handleMessage` for
/// MANUAL_CONTROL), so what markhold sends as it.
fn is_pilot_input(msg: &MavMessage) -> bool {
    matches!(
        msg,
        MavMessage::RC_CHANNELS_OVERRIDE(_) | MavMessage::MANUAL_CONTROL(_)
    )
}
