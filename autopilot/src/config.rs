//! Site-file sections owned by this crate: `[station]`, `[controller]`, `[link]`.

use std::path::PathBuf;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use markhold_config::{Checks, ConfigError};

use crate::error::AutopilotError;

// The wording of the expected values, shared by every section of this crate.
const FINITE: &str = "a finite number";
const POSITIVE: &str = "a finite number > 0";
const NON_NEGATIVE: &str = "a finite number >= 0";

/// `[station]`: where the vehicle should sit relative to the marker (docs/frames.md).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StationConfig {
    /// Distance in front of the printed face (marker +z), metres.
    pub distance_m: f64,
    /// Offset toward the marker's +x (the vehicle's right when facing it), metres.
    pub lateral_m: f64,
    /// Offset toward the marker's +y (up), metres.
    pub vertical_m: f64,
    /// Heading offset from facing the marker, degrees, positive = turned right (FRD yaw).
    pub yaw_deg: f64,
}

impl Default for StationConfig {
    fn default() -> Self {
        Self {
            distance_m: 1.0,
            lateral_m: 0.0,
            vertical_m: 0.0,
            yaw_deg: 0.0,
        }
    }
}

/// Rotation of a vehicle facing the marker (x_b = -z_m, y_b = x_m, z_b = -y_m), as `R_marker_body`.
pub fn r_marker_body_facing() -> Rotation3<f64> {
    // Columns are the body axes expressed in the marker frame.
    Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        Vector3::new(0.0, 0.0, -1.0),
        Vector3::new(1.0, 0.0, 0.0),
        Vector3::new(0.0, -1.0, 0.0),
    ]))
}

impl StationConfig {
    /// Checks every key.
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("station")
            .positive("distance_m", self.distance_m, POSITIVE)
            .finite("lateral_m", self.lateral_m, FINITE)
            .finite("vertical_m", self.vertical_m, FINITE)
            .finite("yaw_deg", self.yaw_deg, FINITE)
            .range("yaw_deg", self.yaw_deg, -180.0..=180.0, "must lie in -180..180")
            .done()
    }

    /// Desired vehicle pose in the marker frame.
    pub fn t_marker_vehicle(&self) -> Isometry3<f64> {
        let facing = r_marker_body_facing();
        let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_deg.to_radians());
        let r = UnitQuaternion::from_rotation_matrix(&(facing * yaw));
        Isometry3::from_parts(
            Translation3::new(self.lateral_m, self.vertical_m, self.distance_m),
            r,
        )
    }
}

/// Gains and limits of one PID axis. Units: effort (-1..1) per metre (translation axes)
/// or per radian (rotation axes); `ki` per unit error and second, `kd` per unit error rate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AxisConfig {
    /// Proportional gain.
    pub kp: f64,
    /// Integral gain (per second).
    pub ki: f64,
    /// Derivative gain (seconds), on the filtered measurement rate.
    pub kd: f64,
    /// Largest proportional contribution (effort).
    pub p_limit: f64,
    /// Largest integral contribution (effort): the integral clamp.
    pub i_limit: f64,
    /// Largest derivative contribution (effort).
    pub d_limit: f64,
    /// Largest output (effort, <= 1).
    pub output_limit: f64,
}

impl Default for AxisConfig {
    fn default() -> Self {
        Self {
            kp: 0.5,
            ki: 0.05,
            kd: 0.3,
            p_limit: 1.0,
            i_limit: 0.2,
            d_limit: 0.5,
            output_limit: 0.6,
        }
    }
}

impl AxisConfig {
    fn with(kp: f64, ki: f64, kd: f64, i_limit: f64, output_limit: f64) -> Self {
        Self {
            kp,
            ki,
            kd,
            p_limit: 1.0,
            i_limit,
            d_limit: 0.5,
            output_limit,
        }
    }

    #[rustfmt::skip]
    fn validate(&self, axis: &str) -> Result<(), ConfigError> {
        Checks::new(format!("controller.{axis}"))
            .non_negative("kp", self.kp, NON_NEGATIVE)
            .non_negative("ki", self.ki, NON_NEGATIVE)
            .non_negative("kd", self.kd, NON_NEGATIVE)
            .non_negative("p_limit", self.p_limit, NON_NEGATIVE)
            .non_negative("i_limit", self.i_limit, NON_NEGATIVE)
            .non_negative("d_limit", self.d_limit, NON_NEGATIVE)
            .non_negative("output_limit", self.output_limit, NON_NEGATIVE)
            .range("output_limit", self.output_limit, ..=1.0, "<= 1 (efforts are normalized)")
            .done()
    }
}

/// What to do once the marker has been lost for `marker_lost_action_after_s`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MarkerLostAction {
    /// Stay neutral in the current mode.
    None,
    /// Switch to SURFACE mode.
    Surface,
    /// Switch to ALT_HOLD (hold depth).
    AltHold,
}

/// `[controller]`: the station keeper's six PID axes, filter and marker-loss behaviour.
/// Keys left out keep their defaults, also inside a partly given axis table (so
/// `[controller.yaw] kp = 0.8` keeps yaw's own limits).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "ControllerConfigToml")]
pub struct ControllerConfig {
    /// Forward (body x) axis, per metre.
    pub surge: AxisConfig,
    /// Right (body y) axis, per metre.
    pub sway: AxisConfig,
    /// Down (body z) axis, per metre.
    pub heave: AxisConfig,
    /// Roll axis, per radian.
    pub roll: AxisConfig,
    /// Pitch axis, per radian.
    pub pitch: AxisConfig,
    /// Yaw axis, per radian.
    pub yaw: AxisConfig,
    /// Fixed rate of the PID steps on the loop's clock, Hz.
    pub rate_hz: f64,
    /// Cut-off of the first-order filter on the measured rate (derivative term), Hz.
    pub derivative_filter_hz: f64,
    /// Output dead band of every axis, effort (0 = off): an axis commands once its output
    /// reaches this and stops once it falls below half of it.
    pub output_deadband: f64,
    /// After the last measurement, keep the last command this long, seconds.
    pub marker_lost_hold_s: f64,
    /// After this long without the marker, request `marker_lost_action`, seconds.
    pub marker_lost_action_after_s: f64,
    /// Optional action on a long marker loss.
    pub marker_lost_action: MarkerLostAction,
    /// Pose filter process noise for translation, m^2 per second (random walk).
    pub filter_q_trans_m2_per_s: f64,
    /// Pose filter process noise for rotation, rad^2 per second (random walk).
    pub filter_q_rot_rad2_per_s: f64,
    /// Innovation gate in standard deviations (0 = off): a measurement this far from the
    /// prediction on any axis is ignored; three in a row restart the filter.
    pub filter_gate_sigma: f64,
    /// A frame gap longer than this resets the controller (stale state), seconds.
    pub max_gap_s: f64,
    /// The camera frames stop arriving for this long: vision stalled, seconds.
    pub vision_stall_s: f64,
    /// ALT_HOLD: the heave axis's output is multiplied by this before it goes out as the
    /// throttle stick, which ArduSub reads as a climb rate (PILOT_SPEED_UP, 5 m/s at full
    /// stick in ArduSub 4.5): 0.1 gives the heave gains 0.5 m/s of climb per unit effort,
    /// the plant they are tuned on. 1 = the stick as computed.
    pub climb_stick_scale: f64,
    /// STABILIZE and ALT_HOLD: the yaw axis's output is multiplied by this before it goes
    /// out as the yaw stick, which ArduSub reads as a yaw rate (stick x ACRO_YAW_P, 151.9
    /// deg/s at full stick with ArduSub 4.5's 3.375): 0.3, 46 deg/s per unit effort, less
    /// than the 60 deg/s the gains are tuned on because ArduSub's heading capture (250 ms
    /// after the stick is centred) adds lag (docs/design/autopilot.md). 1 = the stick as
    /// computed.
    pub yaw_rate_stick_scale: f64,
}

impl Default for ControllerConfig {
    fn default() -> Self {
        // Gains for a BlueROV2 Heavy at 1 m in MANUAL with dead-band compensation: the
        // translation axes get ~0.25 effort at 0.3 m, yaw ~0.2 effort at 20 degrees. The
        // rate sticks of STABILIZE and ALT_HOLD are scaled down to the same loop gains
        // (`climb_stick_scale`, `yaw_rate_stick_scale`).
        Self {
            surge: AxisConfig::with(0.8, 0.08, 0.6, 0.2, 0.5),
            sway: AxisConfig::with(0.8, 0.08, 0.6, 0.2, 0.5),
            heave: AxisConfig::with(1.0, 0.15, 0.5, 0.3, 0.6),
            roll: AxisConfig::with(0.4, 0.0, 0.1, 0.0, 0.3),
            pitch: AxisConfig::with(0.4, 0.0, 0.1, 0.0, 0.3),
            yaw: AxisConfig::with(0.6, 0.03, 0.3, 0.15, 0.4),
            rate_hz: 50.0,
            // 2 Hz and a 0.005 band: at rest the command changes sign about twice a second
            // on its busiest axis. With the stock frame-to-thrust delay a 20 Hz filter
            // (and surge / sway kp 0.6) holds the simulated pool tighter, but swings the
            // heading on ArduSub SITL (docs/design/autopilot.md, "Gains and the delay").
            derivative_filter_hz: 2.0,
            output_deadband: 0.005,
            marker_lost_hold_s: 0.5,
            marker_lost_action_after_s: 10.0,
            marker_lost_action: MarkerLostAction::None,
            filter_q_trans_m2_per_s: 0.02,
            filter_q_rot_rad2_per_s: 0.02,
            filter_gate_sigma: 6.0,
            max_gap_s: 1.0,
            vision_stall_s: 0.5,
            // 0.5 / 5.0 (m/s per unit effort tuned on / PILOT_SPEED_UP); yaw below
            // 60 / 151.9 (deg/s) for the heading capture's lag: pool at rest, 60 s, holds
            // 2.8-2.9 mm RMS at 0.2-0.3 and chatters 5.6/s at 0.4; at 0.25 the slower first
            // turn at lamp-map lost its lit marker for 2 s.
            climb_stick_scale: 0.1,
            yaw_rate_stick_scale: 0.3,
        }
    }
}

/// One axis as written in the site file: every key optional.
#[derive(Clone, Copy, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct AxisToml {
    kp: Option<f64>,
    ki: Option<f64>,
    kd: Option<f64>,
    p_limit: Option<f64>,
    i_limit: Option<f64>,
    d_limit: Option<f64>,
    output_limit: Option<f64>,
}

impl AxisToml {
    fn over(self, mut a: AxisConfig) -> AxisConfig {
        let set = |dst: &mut f64, v: Option<f64>| {
            if let Some(v) = v {
                *dst = v;
            }
        };
        set(&mut a.kp, self.kp);
        set(&mut a.ki, self.ki);
        set(&mut a.kd, self.kd);
        set(&mut a.p_limit, self.p_limit);
        set(&mut a.i_limit, self.i_limit);
        set(&mut a.d_limit, self.d_limit);
        set(&mut a.output_limit, self.output_limit);
        a
    }
}

/// `[controller]` as written: merged over the defaults key by key.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct ControllerConfigToml {
    surge: AxisToml,
    sway: AxisToml,
    heave: AxisToml,
    roll: AxisToml,
    pitch: AxisToml,
    yaw: AxisToml,
    rate_hz: Option<f64>,
    derivative_filter_hz: Option<f64>,
    output_deadband: Option<f64>,
    marker_lost_hold_s: Option<f64>,
    marker_lost_action_after_s: Option<f64>,
    marker_lost_action: Option<MarkerLostAction>,
    filter_q_trans_m2_per_s: Option<f64>,
    filter_q_rot_rad2_per_s: Option<f64>,
    filter_gate_sigma: Option<f64>,
    max_gap_s: Option<f64>,
    vision_stall_s: Option<f64>,
    climb_stick_scale: Option<f64>,
    yaw_rate_stick_scale: Option<f64>,
}

impl From<ControllerConfigToml> for ControllerConfig {
    fn from(t: ControllerConfigToml) -> Self {
        let d = ControllerConfig::default();
        ControllerConfig {
            surge: t.surge.over(d.surge),
            sway: t.sway.over(d.sway),
            heave: t.heave.over(d.heave),
            roll: t.roll.over(d.roll),
            pitch: t.pitch.over(d.pitch),
            yaw: t.yaw.over(d.yaw),
            rate_hz: t.rate_hz.unwrap_or(d.rate_hz),
            derivative_filter_hz: t.derivative_filter_hz.unwrap_or(d.derivative_filter_hz),
            output_deadband: t.output_deadband.unwrap_or(d.output_deadband),
            marker_lost_hold_s: t.marker_lost_hold_s.unwrap_or(d.marker_lost_hold_s),
            marker_lost_action_after_s: t
                .marker_lost_action_after_s
                .unwrap_or(d.marker_lost_action_after_s),
            marker_lost_action: t.marker_lost_action.unwrap_or(d.marker_lost_action),
            filter_q_trans_m2_per_s: t
                .filter_q_trans_m2_per_s
                .unwrap_or(d.filter_q_trans_m2_per_s),
            filter_q_rot_rad2_per_s: t
                .filter_q_rot_rad2_per_s
                .unwrap_or(d.filter_q_rot_rad2_per_s),
            filter_gate_sigma: t.filter_gate_sigma.unwrap_or(d.filter_gate_sigma),
            max_gap_s: t.max_gap_s.unwrap_or(d.max_gap_s),
            vision_stall_s: t.vision_stall_s.unwrap_or(d.vision_stall_s),
            climb_stick_scale: t.climb_stick_scale.unwrap_or(d.climb_stick_scale),
            yaw_rate_stick_scale: t.yaw_rate_stick_scale.unwrap_or(d.yaw_rate_stick_scale),
        }
    }
}

impl ControllerConfig {
    /// Checks every key.
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, axis) in self.axes_named() {
            axis.validate(name)?;
        }
        Checks::new("controller")
            .positive("rate_hz", self.rate_hz, POSITIVE)
            .range("rate_hz", self.rate_hz, ..=1000.0, "<= 1000")
            .positive("derivative_filter_hz", self.derivative_filter_hz, POSITIVE)
            .finite_range("output_deadband", self.output_deadband, 0.0..=0.2, "0..=0.2 (effort; 0 = off)")
            .non_negative("marker_lost_hold_s", self.marker_lost_hold_s, NON_NEGATIVE)
            .non_negative("marker_lost_action_after_s", self.marker_lost_action_after_s, NON_NEGATIVE)
            .positive("filter_q_trans_m2_per_s", self.filter_q_trans_m2_per_s, POSITIVE)
            .positive("filter_q_rot_rad2_per_s", self.filter_q_rot_rad2_per_s, POSITIVE)
            .non_negative("filter_gate_sigma", self.filter_gate_sigma, NON_NEGATIVE)
            .positive("max_gap_s", self.max_gap_s, POSITIVE)
            .positive("vision_stall_s", self.vision_stall_s, POSITIVE)
            .finite_range("climb_stick_scale", self.climb_stick_scale, 0.001..=1.0, "0.001..=1")
            .finite_range("yaw_rate_stick_scale", self.yaw_rate_stick_scale, 0.001..=1.0, "0.001..=1")
            .done()
    }

    /// The six axes in effort order with their key names.
    pub fn axes_named(&self) -> [(&'static str, &AxisConfig); 6] {
        [
            ("surge", &self.surge),
            ("sway", &self.sway),
            ("heave", &self.heave),
            ("roll", &self.roll),
            ("pitch", &self.pitch),
            ("yaw", &self.yaw),
        ]
    }
}

/// How efforts reach the vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandKind {
    /// Pilot input (RC override or MANUAL_CONTROL) from the station keeper's efforts.
    Effort,
    /// GUIDED position targets plus vision pose estimates.
    Setpoint,
}

impl CommandKind {
    /// Key value as written in the site file.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Effort => "effort",
            Self::Setpoint => "setpoint",
        }
    }
}

/// Which pilot-input message carries efforts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PilotInput {
    /// RC_CHANNELS_OVERRIDE (70): full PWM range, no joystick gain.
    RcOverride,
    /// MANUAL_CONTROL (69): scaled by ArduSub's joystick gain.
    ManualControl,
}

/// Flight mode to run in (`link.mode`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LinkMode {
    /// MANUAL (19): efforts straight into the mixer.
    Manual,
    /// STABILIZE (0): attitude held by ArduSub, input dead zones apply.
    Stabilize,
    /// ALT_HOLD (2): depth held by ArduSub, input dead zones apply.
    AltHold,
    /// GUIDED (4): position targets (setpoint command only).
    Guided,
}

impl LinkMode {
    /// The ArduSub mode number.
    pub fn ardusub(self) -> crate::types::ArduSubMode {
        use crate::types::ArduSubMode;
        match self {
            Self::Manual => ArduSubMode::Manual,
            Self::Stabilize => ArduSubMode::Stabilize,
            Self::AltHold => ArduSubMode::AltHold,
            Self::Guided => ArduSubMode::Guided,
        }
    }

    /// True where ArduSub applies its pilot-input dead zones (to roll, pitch, yaw and
    /// the ALT_HOLD throttle; forward and lateral have none in any mode).
    pub fn has_input_dead_zone(self) -> bool {
        matches!(self, Self::Stabilize | Self::AltHold)
    }
}

/// What markhold leaves behind when it stops (`link.on_exit`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnExit {
    /// Neutral input until the pilot's own input is heard, then none, the vehicle left
    /// armed and the pilot told (STATUSTEXT); with no pilot input within
    /// `hand_back_timeout_s`, disarm and say so.
    HandBack,
    /// Neutral input, then disarm.
    Disarm,
}

/// `[link]`: the MAVLink connection to ArduSub and how it is driven.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LinkConfig {
    /// A connection string as pymavlink reads it: `udpin:HOST:PORT` or `udp:HOST:PORT`
    /// (listen), `udpout:HOST:PORT` (send to), `tcp:HOST:PORT` / `tcpout:HOST:PORT`
    /// (connect), `tcpin:HOST:PORT` (accept), `serial:/dev/ttyACM0:115200` or
    /// `/dev/ttyACM0,115200` ([`crate::transport::Endpoint::parse`]).
    pub url: String,
    /// The vehicle's SYSID_MYGCS (255): ArduSub takes pilot input (RC_CHANNELS_OVERRIDE,
    /// MANUAL_CONTROL) from this system id only, so markhold's pilot input, and nothing
    /// else, goes out as it, and only while engaged. A HEARTBEAT from it with another
    /// component id is the pilot's station (QGroundControl: 255/190).
    pub gcs_system_id: u8,
    /// markhold's component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER) on everything it
    /// sends: as a component of the vehicle's system (HEARTBEAT, STATUSTEXT,
    /// NAMED_VALUE_FLOAT, vision, commands, parameter reads) and on its pilot input, which
    /// the pilot's station (component 190) tells apart by it.
    #[serde(alias = "gcs_component_id")]
    pub component_id: u8,
    /// Vehicle system id used until its heartbeat is seen.
    pub vehicle_system_id: u8,
    /// Vehicle (autopilot) component id: only its heartbeats count (1 = MAV_COMP_ID_AUTOPILOT1).
    pub vehicle_component_id: u8,
    /// `effort` or `setpoint`.
    pub command: CommandKind,
    /// `rc_override` or `manual_control`.
    pub pilot_input: PilotInput,
    /// `manual`, `stabilize`, `alt_hold` (effort) or `guided` (setpoint).
    pub mode: LinkMode,
    /// UDP only: read datagrams in `tick` on the caller's thread (true: what arrived before
    /// the tick is applied in it, deterministic in HIL) or in a tokio task (false).
    pub udp_receive_on_tick: bool,
    /// 32-byte MAVLink 2 signing key: raw 32 bytes, or 64 hex digits.
    pub signing_key_file: Option<PathBuf>,
    /// Signing link id.
    pub signing_link_id: u8,
    /// GCS heartbeat rate, Hz (ArduSub's GCS failsafe needs about 1 Hz).
    pub heartbeat_hz: f64,
    /// Requested telemetry rate for each stream, Hz.
    pub stream_hz: f64,
    /// Stream requests are repeated this often (a rebooted vehicle forgets them), seconds.
    pub stream_rerequest_s: f64,
    /// Neutral pilot input is sent at this rate when nothing is commanded, Hz (>= 5 keeps
    /// FS_PILOT_INPUT quiet; ArduSub wants >= 20 for smooth control).
    pub pilot_input_hz: f64,
    /// The vehicle not heard for this long (no message from its autopilot): link lost,
    /// no pilot input until it is heard again, seconds. Telemetry streams (ATTITUDE at
    /// `stream_hz`) are what keep it fresh: `vehicle_timeout_s x stream_hz` must be >= 4.
    /// Loss is seen on the first frame after the timeout, so 0.9 s (the default) keeps
    /// "silent within 1 s of the cut" at >= 15 frames/s.
    pub vehicle_timeout_s: f64,
    /// Wait for COMMAND_ACK this long before retrying, seconds.
    pub command_timeout_s: f64,
    /// On Ctrl-C / SIGTERM, disarm after sending neutral pilot input (the same as
    /// `on_exit = "disarm"`).
    pub disarm_on_exit: bool,
    /// At the end of a run: `hand_back` (default) or `disarm`.
    pub on_exit: OnExit,
    /// `hand_back`: disarm if no pilot input is heard this long after markhold stops, s.
    pub hand_back_timeout_s: f64,
    /// Retries after the first COMMAND_LONG.
    pub command_retries: u32,
    /// The thrusters' ESC dead band half-width around 1500 us that compensation skips
    /// (the last offset with no thrust), us: measure it on the vehicle. 30 is a T200 on a
    /// Basic ESC at a 4S pack's nominal 14.8 V in Blue Robotics' table (32 us at 14 V,
    /// 28 us at 16 V).
    pub thruster_deadband_us: f64,
    /// ArduSub's RC1_DZ..RC3_DZ (pitch, roll, throttle input dead zones), us: they apply
    /// to roll and pitch in STABILIZE / ALT_HOLD and to the ALT_HOLD throttle, never to
    /// forward and lateral.
    pub input_deadzone_us: f64,
    /// ArduSub's RC4_DZ (yaw input dead zone), us; STABILIZE / ALT_HOLD use it times the
    /// joystick gain (`manual_control_gain`).
    pub yaw_deadzone_us: f64,
    /// ArduSub's THR_DZ: the ALT_HOLD climb-rate dead band about centre throttle, in
    /// throttle control units (0..1000 over the stick travel above RC3_DZ); ArduSub 4.5
    /// applies it times the joystick gain (`manual_control_gain`).
    pub thr_dz: f64,
    /// Efforts below this magnitude are sent as exact neutral (no compensation).
    pub effort_epsilon: f64,
    /// ArduSub's joystick gain (JS_GAIN_DEFAULT), undone for MANUAL_CONTROL; it also
    /// scales the yaw dead zone.
    pub manual_control_gain: f64,
    /// Surface air pressure for depth from SCALED_PRESSURE2, Pa.
    pub surface_pressure_pa: f64,
    /// Water density for depth, kg/m^3 (fresh 997, sea 1025).
    pub water_density_kg_m3: f64,
    /// SET_GPS_GLOBAL_ORIGIN latitude for setpoint mode, degrees.
    pub origin_lat_deg: f64,
    /// SET_GPS_GLOBAL_ORIGIN longitude, degrees.
    pub origin_lon_deg: f64,
    /// SET_GPS_GLOBAL_ORIGIN altitude (AMSL), metres.
    pub origin_alt_m: f64,
    /// Setpoint mode: the vision pose's covariance is multiplied by this before it goes to
    /// the EKF (1 = as measured; above 1 trusts vision less).
    pub vision_covariance_scale: f64,
    /// The vehicle's GCS failsafe timeout, s, until it reports its own FS_GCS_TIMEOUT
    /// (the link reads it when it discovers the vehicle, preflight shows it). 2.5 s is
    /// ArduSub's up to 4.5, which has no parameter (FS_GCS_TIMEOUT_MS in
    /// ArduSub/defines.h); later versions default to 5 s. The pilot's station silent for
    /// [`station_timeout_s`] of it stops markhold's SYSID_MYGCS traffic.
    pub fs_gcs_timeout_s: f64,
    /// At exit, how long markhold waits for the vehicle to show its neutral input
    /// applied (RC_CHANNELS, or SERVO_OUTPUT_RAW in MANUAL) before it goes on, s.
    pub exit_confirm_timeout_s: f64,
}

/// Shortest pilot-station silence that counts as lost, s: QGroundControl heartbeats at
/// 1 Hz, and a live station must never be taken for a lost one.
pub const STATION_TIMEOUT_MIN_S: f64 = 1.2;
/// Longest, s: markhold's SYSID_MYGCS traffic ends within 1.5 s of the station's last
/// heartbeat (this, a frame, and the release) whatever FS_GCS_TIMEOUT is.
pub const STATION_TIMEOUT_MAX_S: f64 = 1.4;

/// How long the pilot's station may be silent before markhold stops every SYSID_MYGCS
/// frame, for a vehicle whose GCS failsafe fires after `fs_gcs_timeout_s`. ArduSub
/// counts markhold's own RC override and MANUAL_CONTROL as ground-station contact
/// (`GCS_MAVLINK::handle_rc_channels_override`, `GCS_MAVLINK_Sub::handleMessage`), so
/// with markhold commanding the failsafe fires this much later than without it: half
/// of the timeout, kept within [`STATION_TIMEOUT_MIN_S`] (one heartbeat period of a
/// live station and its jitter) and [`STATION_TIMEOUT_MAX_S`].
pub fn station_timeout_s(fs_gcs_timeout_s: f64) -> f64 {
    let half = if fs_gcs_timeout_s.is_finite() {
        0.5 * fs_gcs_timeout_s
    } else {
        STATION_TIMEOUT_MAX_S
    };
    half.clamp(STATION_TIMEOUT_MIN_S, STATION_TIMEOUT_MAX_S)
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            url: "tcp:127.0.0.1:5777".into(),
            gcs_system_id: 255,
            component_id: 191,
            vehicle_system_id: 1,
            vehicle_component_id: 1,
            command: CommandKind::Effort,
            pilot_input: PilotInput::RcOverride,
            mode: LinkMode::Manual,
            udp_receive_on_tick: true,
            signing_key_file: None,
            signing_link_id: 0,
            heartbeat_hz: 1.0,
            stream_hz: 10.0,
            stream_rerequest_s: 10.0,
            pilot_input_hz: 20.0,
            vehicle_timeout_s: 0.9,
            command_timeout_s: 1.0,
            disarm_on_exit: false,
            on_exit: OnExit::HandBack,
            hand_back_timeout_s: 10.0,
            command_retries: 3,
            thruster_deadband_us: 30.0,
            input_deadzone_us: 30.0,
            yaw_deadzone_us: 40.0,
            thr_dz: 100.0,
            effort_epsilon: 1e-3,
            manual_control_gain: 0.5,
            surface_pressure_pa: 101_325.0,
            water_density_kg_m3: 997.0,
            origin_lat_deg: 0.0,
            origin_lon_deg: 0.0,
            origin_alt_m: 0.0,
            vision_covariance_scale: 1.0,
            fs_gcs_timeout_s: 2.5,
            exit_confirm_timeout_s: 1.0,
        }
    }
}

impl LinkConfig {
    /// Disarm when markhold stops: `on_exit = "disarm"` or `disarm_on_exit = true`.
    pub fn disarms_on_exit(&self) -> bool {
        self.disarm_on_exit || self.on_exit == OnExit::Disarm
    }

    /// Checks every key (the URL is parsed too).
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        crate::transport::Endpoint::parse(&self.url).map_err(|e| url_error(&self.url, e))?;
        let mode = format!("{:?}", self.mode).to_lowercase();
        let guided = self.mode == LinkMode::Guided;
        let effort = self.command == CommandKind::Effort;
        let timeout_covers = self.vehicle_timeout_s * self.stream_hz >= 4.0;
        let below_200 = "< 200 us";
        let covers_4 = "must cover at least 4 telemetry messages at link.stream_hz \
                        (vehicle_timeout_s x stream_hz >= 4)";
        Checks::new("link")
            .range("gcs_system_id", self.gcs_system_id, 1.., "1..255 (ArduSub expects SYSID_MYGCS, default 255)")
            .range("vehicle_system_id", self.vehicle_system_id, 1.., "1..255")
            .check("mode", &mode, !(effort && guided), "effort commands need manual, stabilize or alt_hold")
            .check("mode", &mode, effort || guided, "setpoint commands need guided")
            .positive("heartbeat_hz", self.heartbeat_hz, POSITIVE)
            .positive("stream_hz", self.stream_hz, POSITIVE)
            .positive("stream_rerequest_s", self.stream_rerequest_s, POSITIVE)
            .positive("pilot_input_hz", self.pilot_input_hz, POSITIVE)
            .range("pilot_input_hz", self.pilot_input_hz, 5.0.., ">= 5 or ArduSub's pilot-input failsafe disarms")
            .positive("vehicle_timeout_s", self.vehicle_timeout_s, POSITIVE)
            .check("vehicle_timeout_s", self.vehicle_timeout_s, timeout_covers, covers_4)
            .positive("command_timeout_s", self.command_timeout_s, POSITIVE)
            .range("hand_back_timeout_s", self.hand_back_timeout_s, 1.0..=60.0, "must lie in 1..60 s")
            .non_negative("thruster_deadband_us", self.thruster_deadband_us, NON_NEGATIVE)
            .range("thruster_deadband_us", self.thruster_deadband_us, ..200.0, below_200)
            .non_negative("input_deadzone_us", self.input_deadzone_us, NON_NEGATIVE)
            .range("input_deadzone_us", self.input_deadzone_us, ..=200.0, "<= 200 us (ArduSub RCn_DZ range)")
            .non_negative("yaw_deadzone_us", self.yaw_deadzone_us, NON_NEGATIVE)
            .range("yaw_deadzone_us", self.yaw_deadzone_us, ..=200.0, "<= 200 us (ArduSub RCn_DZ range)")
            .non_negative("thr_dz", self.thr_dz, NON_NEGATIVE)
            .range("thr_dz", self.thr_dz, ..=400.0, "<= 400 (ArduSub THR_DZ range)")
            .non_negative("effort_epsilon", self.effort_epsilon, NON_NEGATIVE)
            .range("effort_epsilon", self.effort_epsilon, ..0.5, "< 0.5")
            .positive("surface_pressure_pa", self.surface_pressure_pa, POSITIVE)
            .positive("water_density_kg_m3", self.water_density_kg_m3, POSITIVE)
            .range("manual_control_gain", self.manual_control_gain, 0.1..=1.0, "must lie in 0.1..1 (ArduSub JS_GAIN range)")
            .range("origin_lat_deg", self.origin_lat_deg, -90.0..=90.0, "must lie in -90..90")
            .range("origin_lon_deg", self.origin_lon_deg, -180.0..=180.0, "must lie in -180..180")
            .finite("origin_alt_m", self.origin_alt_m, FINITE)
            .range("vision_covariance_scale", self.vision_covariance_scale, 1e-6..=1e6, "must lie in 1e-6..1e6")
            .range("fs_gcs_timeout_s", self.fs_gcs_timeout_s, 0.1..=600.0, "must lie in 0.1..600 s (the vehicle's FS_GCS_TIMEOUT)")
            .range("exit_confirm_timeout_s", self.exit_confirm_timeout_s, 0.1..=10.0, "must lie in 0.1..10 s")
            .done()
    }
}

/// The link URL's parse error as the error of the `link.url` key.
fn url_error(url: &str, e: AutopilotError) -> ConfigError {
    let expected = match e {
        AutopilotError::InvalidUrl { reason, .. } => format!("a link url ({reason})"),
        other => other.to_string(),
    };
    ConfigError::new("link.url", format!("{url:?}"), expected)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn default_station_matches_frames_doc() {
        let t = StationConfig::default().t_marker_vehicle();
        // On station the vehicle sits at (0, 0, 1) in the marker frame.
        assert!((t.translation.vector - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-12);
        // Its forward axis points at the marker (-z_m), right = x_m, down = -y_m.
        let r = t.rotation;
        assert!((r * Vector3::x() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        assert!((r * Vector3::y() - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!((r * Vector3::z() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        // The marker centre is 1 m straight ahead in the body frame.
        let p_b = t.inverse() * Point3::origin();
        assert!((p_b.coords - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn positive_station_yaw_turns_right() {
        let st = StationConfig {
            yaw_deg: 90.0,
            ..Default::default()
        };
        let r = st.t_marker_vehicle().rotation;
        // Turned right by 90 degrees, forward is what was the right (x_m).
        assert!((r * Vector3::x() - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn validation_names_key_and_value() {
        let mut c = ControllerConfig::default();
        c.yaw.output_limit = 1.5;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("controller.yaw.output_limit"), "{e}");
        assert!(e.contains("1.5"), "{e}");

        let l = LinkConfig {
            pilot_input_hz: 2.0,
            ..Default::default()
        };
        let e = l.validate().unwrap_err().to_string();
        assert!(e.contains("link.pilot_input_hz") && e.contains('2'), "{e}");

        let l = LinkConfig {
            url: "bogus:1".into(),
            ..Default::default()
        };
        assert!(l.validate().is_err());

        let l = LinkConfig {
            thr_dz: 500.0,
            ..Default::default()
        };
        let e = l.validate().unwrap_err().to_string();
        assert!(e.contains("link.thr_dz") && e.contains("500"), "{e}");
        let l = LinkConfig {
            thruster_deadband_us: -1.0,
            ..Default::default()
        };
        let e = l.validate().unwrap_err().to_string();
        assert!(e.contains("link.thruster_deadband_us"), "{e}");

        let s = StationConfig {
            distance_m: -1.0,
            ..Default::default()
        };
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .contains("station.distance_m"));
    }

    #[test]
    fn site_file_sections_parse_with_defaults_and_reject_unknown_keys() {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Site {
            station: StationConfig,
            controller: ControllerConfig,
            link: LinkConfig,
        }
        let text = r#"
            [station]
            distance_m = 1.5
            yaw_deg = 10.0

            [controller]
            rate_hz = 40.0
            marker_lost_action = "alt_hold"

            [controller.yaw]
            kp = 0.9

            [link]
            url = "tcpout:127.0.0.1:5760"
            command = "effort"
            pilot_input = "manual_control"
            mode = "alt_hold"
            signing_key_file = "/etc/markhold/key"
        "#;
        let s: Site = toml::from_str(text).unwrap();
        assert_eq!(s.station.distance_m, 1.5);
        assert_eq!(s.station.lateral_m, 0.0);
        assert_eq!(s.controller.rate_hz, 40.0);
        assert_eq!(s.controller.marker_lost_action, MarkerLostAction::AltHold);
        // A partly given axis keeps that axis' own defaults for the other keys.
        let d = ControllerConfig::default();
        assert_eq!(s.controller.yaw.kp, 0.9);
        assert_eq!(s.controller.yaw.output_limit, d.yaw.output_limit);
        assert_eq!(s.controller.yaw.ki, d.yaw.ki);
        assert_eq!(s.controller.surge, d.surge);
        assert_eq!(s.link.pilot_input, PilotInput::ManualControl);
        assert_eq!(s.link.mode, LinkMode::AltHold);
        assert_eq!(s.link.gcs_system_id, 255);
        s.link.validate().unwrap();
        s.controller.validate().unwrap();

        for bad in [
            "[station]\ndistance = 1.0\n[controller]\n[link]\n",
            "[station]\n[controller.yaw]\nkp_gain = 1\n[link]\n",
            "[station]\n[controller]\nrate = 5\n[link]\n",
            "[station]\n[controller]\n[link]\nmode = \"acro\"\n",
        ] {
            assert!(toml::from_str::<Site>(bad).is_err(), "accepted: {bad}");
        }
    }

    #[test]
    fn defaults_validate() {
        StationConfig::default().validate().unwrap();
        ControllerConfig::default().validate().unwrap();
        LinkConfig::default().validate().unwrap();
    }
}
