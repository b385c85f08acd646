//! The flight-mode controllers of the simulated autopilot: what ArduSub 4.5's MANUAL,
//! STABILIZE, ALT_HOLD, POSHOLD, SURFACE and GUIDED modes do with pilot input and targets.
//!
//! Pilot input follows ArduSub's source (ArduSub/mode_manual.cpp, mode_stabilize.cpp,
//! mode_althold.cpp, mode_poshold.cpp, mode_surface.cpp, Attitude.cpp;
//! libraries/RC_Channel/RC_Channel.cpp; docs/design/hil.md "Conformance"): channels that
//! drive thrusters directly go through `norm_input()` (no dead zone), channels that become
//! setpoints through `get_control_in()` (RCn_DZ); yaw becomes a rate (stick x ACRO_YAW_P,
//! dead zone RC4_DZ x joystick gain) and the heading is re-captured 250 ms after the stick
//! returns to centre; roll and pitch become lean angles up to ANGLE_MAX; the ALT_HOLD /
//! POSHOLD throttle a climb rate up to PILOT_SPEED_UP outside THR_DZ x gain; POSHOLD's
//! forward and lateral sticks velocity targets up to PILOT_SPEED. The inner loops (attitude,
//! depth, position) have ArduSub's structure but not its PIDs: `ControlGains`.

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::params::ArduSubParams;
use super::{mode, GuidedTarget};
use crate::vehicle::VehicleState;
use markhold_config::{Checks, ConfigError};

/// Gains of the simulated autopilot's inner loops (efforts are normalized -1..1). Not
/// ArduSub's PIDs: loops of the same structure (angle P to a rate target, rate PI to an
/// effort, as in AC_AttitudeControl; position to velocity to effort, as in AC_PosControl)
/// with gains tuned for the simulated BlueROV2.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlGains {
    /// Attitude: rate target per radian of angle error, 1/s.
    pub attitude_angle_p: f64,
    /// Attitude: effort per rad/s of rate error.
    pub attitude_rate_p: f64,
    /// Attitude: effort per radian of integrated rate error.
    pub attitude_rate_i: f64,
    /// Largest integral effort of each attitude axis.
    pub attitude_i_max: f64,
    /// Depth: climb-rate target per metre of depth error, 1/s.
    pub depth_pos_p: f64,
    /// Depth: effort per m/s of climb-rate error, and per metre of its integral.
    pub depth_vel_p: f64,
    pub depth_vel_i: f64,
    /// Largest integral effort of the depth loop (trims buoyancy).
    pub depth_i_max: f64,
    /// Position loop: commanded speed per metre of error, 1/s.
    pub position_kp: f64,
    /// Velocity loop: effort per m/s of velocity error.
    pub velocity_kp: f64,
    /// Speed limit of GUIDED's position loop, m/s.
    pub max_speed_mps: f64,
}

impl Default for ControlGains {
    fn default() -> Self {
        Self {
            attitude_angle_p: 3.3,
            attitude_rate_p: 0.6,
            attitude_rate_i: 0.5,
            attitude_i_max: 0.5,
            depth_pos_p: 1.2,
            depth_vel_p: 1.2,
            depth_vel_i: 1.0,
            depth_i_max: 0.5,
            position_kp: 0.8,
            velocity_kp: 2.0,
            max_speed_mps: 0.5,
        }
    }
}

impl ControlGains {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let nn = "a finite number >= 0";
        Checks::new("endpoint.gains")
            .non_negative("attitude_angle_p", self.attitude_angle_p, nn)
            .non_negative("attitude_rate_p", self.attitude_rate_p, nn)
            .non_negative("attitude_rate_i", self.attitude_rate_i, nn)
            .non_negative("attitude_i_max", self.attitude_i_max, nn)
            .non_negative("depth_pos_p", self.depth_pos_p, nn)
            .non_negative("depth_vel_p", self.depth_vel_p, nn)
            .non_negative("depth_vel_i", self.depth_vel_i, nn)
            .non_negative("depth_i_max", self.depth_i_max, nn)
            .non_negative("position_kp", self.position_kp, nn)
            .non_negative("velocity_kp", self.velocity_kp, nn)
            .non_negative("max_speed_mps", self.max_speed_mps, nn)
            .done()
    }
}

/// The autopilot's position estimate in its navigation frame (the frame of the vision
/// position estimates it receives).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct NavEstimate {
    pub pose: Isometry3<f64>,
    pub velocity: Vector3<f64>,
    pub yaw: f64,
}

impl NavEstimate {
    pub fn new(pose: &Isometry3<f64>, velocity: &Vector3<f64>) -> Self {
        Self {
            pose: *pose,
            velocity: *velocity,
            yaw: pose.rotation.euler_angles().2,
        }
    }
}

fn wrap_pi(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let r = (a + std::f64::consts::PI).rem_euclid(t) - std::f64::consts::PI;
    if r.is_finite() {
        r
    } else {
        0.0
    }
}

/// ArduSub's reading of one RC input channel (RC_Channel with RCn_MIN 1100, RCn_TRIM
/// 1500, RCn_MAX 1900, not reversed), in its integer arithmetic.
pub(crate) mod rc {
    const MIN: i32 = 1100;
    const TRIM: i32 = 1500;
    const MAX: i32 = 1900;
    /// ROLL_PITCH_INPUT_MAX: the angle channels' control_in range (+-4500).
    pub const ANGLE_MAX: i32 = 4500;
    /// The throttle channel's control_in range (0..1000, `set_range(1000)`).
    pub const RANGE_MAX: i32 = 1000;

    /// `RC_Channel::norm_input()`: -1..1 about trim, no dead zone.
    pub fn norm_input(pwm: u16) -> f64 {
        let r = i32::from(pwm);
        let v = if r < TRIM {
            (r - TRIM) as f64 / (TRIM - MIN) as f64
        } else {
            (r - TRIM) as f64 / (MAX - TRIM) as f64
        };
        v.clamp(-1.0, 1.0)
    }

    /// `RC_Channel::pwm_to_angle_dz_trim(dz, trim)`: -4500..4500, zero within `dz` us of
    /// trim (an angle channel's `get_control_in()` with dz = RCn_DZ).
    pub fn angle_dz(pwm: u16, dz: u16) -> i32 {
        let r = i32::from(pwm).clamp(MIN, MAX);
        let (high, low) = (TRIM + i32::from(dz), TRIM - i32::from(dz));
        if r > high && MAX != high {
            ANGLE_MAX * (r - high) / (MAX - high)
        } else if r < low && low != MIN {
            ANGLE_MAX * (r - low) / (low - MIN)
        } else {
            0
        }
    }

    /// `RC_Channel::pwm_to_range_dz(dz)`: 0..1000, the dead zone at the bottom of the
    /// range (the throttle channel's `get_control_in()` with dz = RC3_DZ).
    pub fn range_dz(pwm: u16, dz: u16) -> i32 {
        let r = i32::from(pwm).clamp(MIN, MAX);
        let low = MIN + i32::from(dz);
        if r > low {
            RANGE_MAX * (r - low) / (MAX - low)
        } else {
            0
        }
    }

    /// `RC_Channel::get_control_mid()` of the throttle channel: centre stick as control_in.
    pub fn range_mid(dz: u16) -> i32 {
        let low = MIN + i32::from(dz);
        RANGE_MAX * ((MIN + MAX) / 2 - low) / (MAX - low)
    }

    /// `Sub::get_pilot_desired_climb_rate()` as a fraction of the pilot's up / down
    /// speed limit (-1..1, + up): zero within `thr_dz` (THR_DZ) of centre stick.
    pub fn climb_fraction(pwm: u16, rc3_dz: u16, thr_dz: f64) -> f64 {
        let ctrl = range_dz(pwm, rc3_dz) as f64;
        let mid = range_mid(rc3_dz) as f64;
        let thr_dz = thr_dz.clamp(0.0, 400.0);
        let (top, bottom) = (mid + thr_dz, mid - thr_dz);
        if ctrl < bottom && bottom > 0.0 {
            (ctrl - bottom) / bottom
        } else if ctrl > top && top < RANGE_MAX as f64 {
            (ctrl - top) / (RANGE_MAX as f64 - top)
        } else {
            0.0
        }
    }

    /// `Sub::get_pilot_desired_horizontal_rate()` as a fraction of PILOT_SPEED (-1..1):
    /// `norm_input()` less a dead band of THR_DZ x 2 / (RCn_MAX - RCn_MIN) x gain, not
    /// rescaled (full stick gives 1 - the dead band).
    pub fn horizontal_fraction(pwm: u16, thr_dz: f64, gain: f64) -> f64 {
        let c = norm_input(pwm);
        let dz = thr_dz * 2.0 / f64::from(MAX - MIN) * gain;
        if c < -dz {
            c + dz
        } else if c > dz {
            c - dz
        } else {
            0.0
        }
    }
}

/// The pilot's input as a mode reads it (ArduSub/mode_*.cpp, Attitude.cpp).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(crate) struct PilotInput {
    /// Forward and lateral: `norm_input()` efforts (MANUAL, STABILIZE, ALT_HOLD,
    /// SURFACE) or fractions of PILOT_SPEED (POSHOLD, `horizontal_fraction`).
    pub forward: f64,
    pub lateral: f64,
    /// MANUAL / STABILIZE: throttle effort -1..1 (+ up). ALT_HOLD / POSHOLD: climb rate,
    /// m/s (+ up), within -PILOT_SPEED_DN..PILOT_SPEED_UP.
    pub throttle: f64,
    /// Lean angle targets, radians (MANUAL: roll and pitch efforts).
    pub roll: f64,
    pub pitch: f64,
    /// Yaw rate target, rad/s (MANUAL: yaw effort).
    pub yaw: f64,
}

/// `Sub::get_pilot_desired_lean_angles`: stick control_in (-4500..4500) to lean angle
/// targets in radians: scaled to ANGLE_MAX, limited to `angle_max` on a circle, roll
/// converted from lateral tilt to an Euler angle.
pub(crate) fn lean_angles(roll_in: i32, pitch_in: i32, p: &ArduSubParams) -> (f64, f64) {
    let angle_max = p.angle_max_cdeg.clamp(1000.0, 8000.0);
    let scaler = angle_max / f64::from(rc::ANGLE_MAX);
    let (mut r, mut q) = (f64::from(roll_in) * scaler, f64::from(pitch_in) * scaler);
    let total = r.hypot(q);
    if total > angle_max {
        r *= angle_max / total;
        q *= angle_max / total;
    }
    let cd = |a: f64| (a / 100.0).to_radians();
    let roll = (cd(q).cos() * cd(r).tan()).atan();
    (roll, cd(q))
}

/// Reads the six input channels `[forward, lateral, throttle, roll, pitch, yaw]` (PWM) as
/// mode `mode` of ArduSub 4.5 does, with joystick gain `gain`.
pub(crate) fn read_input(mode: u32, rc: &[u16; 6], p: &ArduSubParams, gain: f64) -> PilotInput {
    let n = rc::norm_input;
    let [fwd, lat, thr, roll, pitch, yaw] = *rc;
    if mode == super::mode::MANUAL {
        // mode_manual.cpp: every channel straight into the mixer, yaw scaled by
        // ACRO_YAW_P / its default.
        return PilotInput {
            forward: n(fwd),
            lateral: n(lat),
            throttle: n(thr),
            roll: n(roll),
            pitch: n(pitch),
            yaw: n(yaw) * p.acro_yaw_p / ACRO_YAW_P_DEFAULT,
        };
    }
    let (roll_t, pitch_t) = lean_angles(
        rc::angle_dz(roll, p.rc_dz_us[1]),
        rc::angle_dz(pitch, p.rc_dz_us[0]),
        p,
    );
    // STABILIZE / ALT_HOLD / POSHOLD read yaw with a dead zone of RC4_DZ x gain
    // (truncated to uint16); SURFACE with RC4_DZ (`get_control_in()`).
    let yaw_dz = if mode == super::mode::SURFACE {
        p.rc_dz_us[3]
    } else {
        (f64::from(p.rc_dz_us[3]) * gain) as u16
    };
    let yaw_cds = f64::from(rc::angle_dz(yaw, yaw_dz)) * p.acro_yaw_p;
    let yaw_max = p.atc_rate_y_max_dps.to_radians();
    let yaw_rate = (yaw_cds / 100.0).to_radians().clamp(-yaw_max, yaw_max);
    let throttle = if mode == super::mode::STABILIZE {
        // set_throttle_out((norm_input() + 1) / 2): direct throttle, no dead zone.
        n(thr)
    } else {
        // get_pilot_desired_climb_rate: THR_DZ x gain about centre stick.
        let f = rc::climb_fraction(thr, p.rc_dz_us[2], p.thr_dz * gain);
        let cms = if f < 0.0 {
            f * p.pilot_speed_dn()
        } else {
            f * p.pilot_speed_up_cms
        };
        cms.clamp(-p.pilot_speed_dn(), p.pilot_speed_up_cms) / 100.0
    };
    let (forward, lateral) = if mode == super::mode::POSHOLD {
        (
            rc::horizontal_fraction(fwd, p.thr_dz, gain),
            rc::horizontal_fraction(lat, p.thr_dz, gain),
        )
    } else {
        (n(fwd), n(lat))
    };
    PilotInput {
        forward,
        lateral,
        throttle,
        roll: roll_t,
        pitch: pitch_t,
        yaw: yaw_rate,
    }
}

/// ACRO_YAW_P's compiled-in default (config.h): MANUAL scales yaw by ACRO_YAW_P over it.
const ACRO_YAW_P_DEFAULT: f64 = 3.375;

/// How long after the yaw stick returns to centre the heading is re-captured (ArduSub
/// mode_stabilize.cpp / mode_althold.cpp / mode_poshold.cpp: 250 ms).
const YAW_RECAPTURE_S: f64 = 0.25;

/// Moves `v` toward `target` by at most `max_step`.
fn slew(v: f64, target: f64, max_step: f64) -> f64 {
    v + (target - v).clamp(-max_step, max_step)
}

pub(crate) struct Controller {
    gains: ControlGains,
    p: ArduSubParams,
    /// The joystick gain in use (JS_GAIN_DEFAULT at boot).
    gain: f64,
    /// Attitude target: yaw (world), and its shaped rate, rad and rad/s.
    yaw_target: Option<f64>,
    yaw_rate_target: f64,
    /// `last_pilot_heading` and `last_pilot_yaw_input_ms` of ArduSub's stabilized modes.
    pilot_heading: Option<f64>,
    last_yaw_input_s: f64,
    /// Rate integrators, roll, pitch, yaw (efforts).
    att_i: [f64; 3],
    /// Depth target (m, down) and its shaped rate (m/s, down).
    depth_target: Option<f64>,
    climb_target: f64,
    depth_i: f64,
    /// Last heave effort (+down): the depth target stops where the thrusters saturate.
    last_heave: f64,
    hold_position: Option<Vector3<f64>>,
    /// POSHOLD's shaped velocity target, nav frame, m/s.
    vel_target: Vector3<f64>,
    last_nav: Option<NavEstimate>,
    /// GUIDED followed a velocity-only target on the last update.
    guided_moving: bool,
}

/// Which of ArduSub's yaw inputs the mode gives the attitude controller.
enum YawInput {
    /// `input_euler_angle_roll_pitch_euler_rate_yaw`: a rate.
    Rate(f64),
    /// `input_euler_angle_roll_pitch_yaw`: a heading.
    Heading(f64),
}

impl Controller {
    pub fn new(gains: ControlGains, p: ArduSubParams) -> Self {
        Self {
            gains,
            gain: p.js_gain_default,
            p,
            yaw_target: None,
            yaw_rate_target: 0.0,
            pilot_heading: None,
            last_yaw_input_s: f64::NEG_INFINITY,
            att_i: [0.0; 3],
            depth_target: None,
            climb_target: 0.0,
            depth_i: 0.0,
            last_heave: 0.0,
            hold_position: None,
            vel_target: Vector3::zeros(),
            last_nav: None,
            guided_moving: false,
        }
    }

    /// The joystick gain in use (scales MANUAL_CONTROL and the dead bands).
    pub fn gain(&self) -> f64 {
        self.gain
    }

    /// Forget every hold target (arming, mode change).
    pub fn reset(&mut self) {
        self.yaw_target = None;
        self.yaw_rate_target = 0.0;
        self.pilot_heading = None;
        self.last_yaw_input_s = f64::NEG_INFINITY;
        self.att_i = [0.0; 3];
        self.depth_target = None;
        self.climb_target = 0.0;
        self.depth_i = 0.0;
        self.last_heave = 0.0;
        self.hold_position = None;
        self.vel_target = Vector3::zeros();
        self.guided_moving = false;
    }

    /// A depth target from the client (ALT_HOLD via SET_POSITION_TARGET_GLOBAL_INT).
    pub fn set_depth_target(&mut self, depth_m: f64) {
        self.depth_target = Some(depth_m);
        self.climb_target = 0.0;
    }

    pub fn last_nav(&self) -> Option<NavEstimate> {
        self.last_nav
    }

    pub fn observe(&mut self, _state: &VehicleState, nav: Option<NavEstimate>) {
        self.last_nav = nav;
    }

    /// Efforts `[surge, sway, heave, roll, pitch, yaw]` for `mode`, given the RC input as
    /// `[forward, lateral, throttle, roll, pitch, yaw]` PWM.
    pub fn update(
        &mut self,
        mode: u32,
        rc: &[u16; 6],
        state: &VehicleState,
        nav: Option<NavEstimate>,
        guided: Option<&GuidedTarget>,
        dt: f64,
    ) -> [f64; 6] {
        self.last_nav = nav;
        let input = read_input(mode, rc, &self.p, self.gain);
        if mode == mode::MANUAL {
            // Straight through; throttle up = heave up (negative).
            return [
                input.forward,
                input.lateral,
                -input.throttle,
                input.roll,
                input.pitch,
                input.yaw,
            ];
        }
        let now = state.time_s;
        let (_, _, yaw) = state.t_world_vehicle.rotation.euler_angles();
        let depth = state.t_world_vehicle.translation.vector.z;
        let vz = state.velocity_world_mps.z;

        // Heading.
        let yaw_in = match mode {
            mode::GUIDED => self.guided_yaw(guided, nav, yaw),
            // mode_surface.cpp: always a rate, no heading hold.
            mode::SURFACE => YawInput::Rate(input.yaw),
            _ => {
                if input.yaw != 0.0 {
                    self.pilot_heading = Some(yaw);
                    self.last_yaw_input_s = now;
                    YawInput::Rate(input.yaw)
                } else if now < self.last_yaw_input_s + YAW_RECAPTURE_S {
                    // Decelerate; the heading to hold is where the vehicle is.
                    self.pilot_heading = Some(yaw);
                    YawInput::Rate(0.0)
                } else {
                    YawInput::Heading(*self.pilot_heading.get_or_insert(yaw))
                }
            }
        };
        let (roll_t, pitch_t) = if mode == mode::GUIDED {
            (0.0, 0.0)
        } else {
            (input.roll, input.pitch)
        };
        let [e_roll, e_pitch, e_yaw] = self.attitude(state, roll_t, pitch_t, yaw_in, dt);

        if mode == mode::STABILIZE {
            return [
                input.forward,
                input.lateral,
                -input.throttle,
                e_roll,
                e_pitch,
                e_yaw,
            ];
        }

        // Depth (ALT_HOLD, POSHOLD, SURFACE): a climb-rate target (+ up) shaped by
        // PILOT_ACCEL_Z, integrated into the depth target.
        if mode != mode::GUIDED {
            let climb = if mode == mode::SURFACE {
                // mode_surface.cpp: WPNAV_SPEED_UP, within 1 cm/s..PILOT_SPEED_UP.
                self.p
                    .wpnav_speed_up_cms
                    .abs()
                    .clamp(1.0, self.p.pilot_speed_up_cms.max(1.0))
                    / 100.0
            } else {
                input.throttle
            };
            let heave = self.depth_from_climb(-climb, depth, vz, dt);
            let (mut surge, mut sway) = (input.forward, input.lateral);
            if mode == mode::POSHOLD {
                let e = self.poshold_horizontal(&input, nav, dt);
                surge = e.0;
                sway = e.1;
            }
            return [surge, sway, heave, e_roll, e_pitch, e_yaw];
        }

        // GUIDED.
        let Some(nav) = nav else {
            // No position estimate: hold depth and heading only.
            let t = *self.depth_target.get_or_insert(depth);
            let heave = self.depth_pid(t, 0.0, depth, vz, dt);
            return [0.0, 0.0, heave, e_roll, e_pitch, e_yaw];
        };
        let (guided_pos, guided_vel) = guided.map_or((None, None), |t| (t.position, t.velocity));
        if guided_pos.is_some() {
            self.hold_position = guided_pos;
        }
        let p = nav.pose.translation.vector;
        let target = match (guided_pos, guided_vel) {
            (Some(pos), _) => pos,
            (None, Some(v)) => {
                // Velocity only: a set-point moving at the target velocity, so that the
                // position loop removes the velocity loop's lag; kept within 0.5 m.
                let h = self.hold_position.get_or_insert(p);
                *h += v * dt;
                let lead = *h - p;
                if lead.norm() > 0.5 {
                    *h = p + lead * (0.5 / lead.norm());
                }
                *h
            }
            (None, None) => {
                if self.guided_moving {
                    // A velocity target just ended (timed out): stop where the vehicle is.
                    self.hold_position = Some(p);
                }
                *self.hold_position.get_or_insert(p)
            }
        };
        self.guided_moving = guided_pos.is_none() && guided_vel.is_some();
        let ff = guided_vel.unwrap_or_else(Vector3::zeros);
        let e = self.horizontal_effort(&nav, &target, &ff, self.gains.max_speed_mps);
        // Vertical: the depth PID on the target. The nav frame's z is the vision frame's;
        // its offset to true depth is fixed between updates.
        let z_off = depth - p.z;
        let t = target.z + z_off;
        self.depth_target = Some(t);
        let heave = self.depth_pid(t, ff.z, depth, vz, dt);
        [e.x, e.y, heave, e_roll, e_pitch, e_yaw]
    }

    /// GUIDED's heading: the target's yaw (nav frame, rotated to the world), its yaw rate,
    /// or the heading held.
    fn guided_yaw(
        &mut self,
        guided: Option<&GuidedTarget>,
        nav: Option<NavEstimate>,
        yaw: f64,
    ) -> YawInput {
        if let (Some(t), Some(nav)) = (guided, nav) {
            if let Some(y) = t.yaw {
                let h = y - (nav.yaw - yaw);
                self.pilot_heading = Some(h);
                return YawInput::Heading(h);
            }
            if let Some(r) = t.yaw_rate {
                self.pilot_heading = Some(yaw);
                return YawInput::Rate(r);
            }
        }
        YawInput::Heading(*self.pilot_heading.get_or_insert(yaw))
    }

    /// The attitude controller: targets roll, pitch (angles) and yaw (rate or heading) to
    /// roll, pitch and yaw efforts. The yaw target moves at a rate shaped by
    /// ATC_ACCEL_Y_MAX within ATC_RATE_Y_MAX; angle errors become rate targets
    /// (`attitude_angle_p`), rate errors efforts (PI).
    fn attitude(
        &mut self,
        state: &VehicleState,
        roll_t: f64,
        pitch_t: f64,
        yaw_in: YawInput,
        dt: f64,
    ) -> [f64; 3] {
        let (roll, pitch, yaw) = state.t_world_vehicle.rotation.euler_angles();
        let w = state.angvel_body_rps;
        let accel = (self.p.atc_accel_y_max_cdss / 100.0).to_radians();
        let step = if accel > 0.0 {
            accel * dt
        } else {
            f64::INFINITY
        };
        let yaw_max = self.p.atc_rate_y_max_dps.to_radians();
        let mut yaw_t = *self.yaw_target.get_or_insert(yaw);
        match yaw_in {
            YawInput::Rate(r) => {
                self.yaw_rate_target = slew(self.yaw_rate_target, r.clamp(-yaw_max, yaw_max), step);
                yaw_t += self.yaw_rate_target * dt;
            }
            YawInput::Heading(h) => {
                self.yaw_rate_target = slew(self.yaw_rate_target, 0.0, step);
                yaw_t = h;
            }
        }
        // Keep the target within reach so that a stuck vehicle does not wind up.
        yaw_t = yaw + wrap_pi(yaw_t - yaw).clamp(-0.5, 0.5);
        self.yaw_target = Some(yaw_t);
        let g = &self.gains;
        let errors = [
            wrap_pi(roll_t - roll),
            wrap_pi(pitch_t - pitch),
            wrap_pi(yaw_t - yaw),
        ];
        let ff = [0.0, 0.0, self.yaw_rate_target];
        let mut out = [0.0; 3];
        for i in 0..3 {
            let rate_err = ff[i] + g.attitude_angle_p * errors[i] - w[i];
            let imax = g.attitude_i_max;
            self.att_i[i] = (self.att_i[i] + g.attitude_rate_i * rate_err * dt).clamp(-imax, imax);
            out[i] = (g.attitude_rate_p * rate_err + self.att_i[i]).clamp(-1.0, 1.0);
        }
        out
    }

    /// Heave effort (+down) from a climb-rate target `rate_down` (m/s, + down): the rate
    /// is shaped by PILOT_ACCEL_Z and moves the depth target, which stops while the
    /// thrusters are saturated in its direction (AC_PosControl's limit flags).
    fn depth_from_climb(&mut self, rate_down: f64, depth: f64, vz: f64, dt: f64) -> f64 {
        let accel = self.p.pilot_accel_z_cmss / 100.0;
        self.climb_target = slew(self.climb_target, rate_down, accel * dt);
        let mut t = *self.depth_target.get_or_insert(depth);
        let saturated =
            self.last_heave.abs() >= 1.0 && self.last_heave.signum() == self.climb_target.signum();
        if !saturated {
            t += self.climb_target * dt;
        }
        self.depth_target = Some(t);
        let heave = self.depth_pid(t, self.climb_target, depth, vz, dt);
        self.last_heave = heave;
        heave
    }

    /// POSHOLD's surge and sway (mode_poshold.cpp `control_horizontal`): with a position
    /// estimate, the sticks are velocity targets (PILOT_SPEED, shaped by PILOT_ACCEL_Z)
    /// for a position controller that always runs; without one, the stick fraction is the
    /// effort.
    fn poshold_horizontal(
        &mut self,
        input: &PilotInput,
        nav: Option<NavEstimate>,
        dt: f64,
    ) -> (f64, f64) {
        let speed = self.p.pilot_speed_cms / 100.0;
        let Some(nav) = nav else {
            self.hold_position = None;
            self.vel_target = Vector3::zeros();
            return (input.forward, input.lateral);
        };
        let r = UnitQuaternion::from_euler_angles(0.0, 0.0, nav.yaw);
        let want = r * Vector3::new(input.forward * speed, input.lateral * speed, 0.0);
        let step = self.p.pilot_accel_z_cmss / 100.0 * dt;
        let dv = want - self.vel_target;
        let n = dv.norm();
        self.vel_target += if n > step { dv * (step / n) } else { dv };
        let p = nav.pose.translation.vector;
        let h = self.hold_position.get_or_insert(p);
        *h += self.vel_target * dt;
        let lead = *h - p;
        let mut lead_xy = lead;
        lead_xy.z = 0.0;
        if lead_xy.norm() > 0.5 {
            *h -= lead_xy * (1.0 - 0.5 / lead_xy.norm());
        }
        let target = *h;
        let ff = self.vel_target;
        let e = self.horizontal_effort(&nav, &target, &ff, speed.max(self.gains.max_speed_mps));
        (e.x, e.y)
    }

    /// Heave effort (+down) holding `target_depth` with feed-forward climb rate `ff_vz`
    /// (+ down): depth error to a rate target, rate error to an effort (PI), as
    /// AC_PosControl's vertical position and velocity loops.
    fn depth_pid(&mut self, target_depth: f64, ff_vz: f64, depth: f64, vz: f64, dt: f64) -> f64 {
        let g = &self.gains;
        let rate_err = ff_vz + g.depth_pos_p * (target_depth - depth) - vz;
        let imax = g.depth_i_max;
        self.depth_i = (self.depth_i + g.depth_vel_i * rate_err * dt).clamp(-imax, imax);
        (g.depth_vel_p * rate_err + self.depth_i).clamp(-1.0, 1.0)
    }

    /// Body-frame surge / sway efforts that bring the nav position to `target` with
    /// feed-forward velocity `ff` (nav frame), at most `max_speed` m/s.
    fn horizontal_effort(
        &self,
        nav: &NavEstimate,
        target: &Vector3<f64>,
        ff: &Vector3<f64>,
        max_speed: f64,
    ) -> Vector3<f64> {
        let g = &self.gains;
        let mut err = target - nav.pose.translation.vector;
        err.z = 0.0;
        let mut v_des = ff + err * g.position_kp;
        v_des.z = 0.0;
        let speed = v_des.norm();
        if speed > max_speed && speed > 0.0 {
            v_des *= max_speed / speed;
        }
        let mut dv = v_des - nav.velocity;
        dv.z = 0.0;
        // Into the heading frame (yaw only): surge/sway act in the horizontal plane.
        let r = UnitQuaternion::from_euler_angles(0.0, 0.0, nav.yaw);
        let e = r.inverse_transform_vector(&dv) * g.velocity_kp;
        Vector3::new(e.x.clamp(-1.0, 1.0), e.y.clamp(-1.0, 1.0), 0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NEUTRAL: [u16; 6] = [1500; 6];

    fn p() -> ArduSubParams {
        ArduSubParams::default()
    }

    fn with(ch: usize, pwm: u16) -> [u16; 6] {
        let mut rc = NEUTRAL;
        rc[ch] = pwm;
        rc
    }

    fn input(m: u32, rc: [u16; 6]) -> PilotInput {
        read_input(m, &rc, &p(), 0.5)
    }

    #[test]
    fn forward_and_lateral_have_no_dead_zone_outside_poshold() {
        for m in [mode::MANUAL, mode::STABILIZE, mode::ALT_HOLD, mode::SURFACE] {
            // 1530 us forward in ALT_HOLD is 30/400 of full effort, not zero.
            assert_eq!(input(m, with(0, 1530)).forward, 30.0 / 400.0, "mode {m}");
            assert_eq!(input(m, with(1, 1499)).lateral, -1.0 / 400.0, "mode {m}");
        }
        // POSHOLD: a velocity fraction with THR_DZ x 2 / 800 x gain = 0.125 dead band.
        assert_eq!(input(mode::POSHOLD, with(0, 1540)).forward, 0.0);
        let f = input(mode::POSHOLD, with(0, 1900)).forward;
        assert!((f - 0.875).abs() < 1e-12, "{f}");
    }

    #[test]
    fn yaw_is_a_rate_of_stick_times_acro_yaw_p_outside_rc4_dz_times_gain() {
        for m in [mode::STABILIZE, mode::ALT_HOLD, mode::POSHOLD] {
            // Yaw inside RC4_DZ x gain (40 x 0.5 = 20 us) is zeroed; just outside is not.
            assert_eq!(input(m, with(5, 1520)).yaw, 0.0);
            assert_eq!(input(m, with(5, 1480)).yaw, 0.0);
            // pwm_to_angle_dz: 4500 x (1530 - 1520) / 380 = 118 (integer) x 3.375 cdeg/s.
            let y = input(m, with(5, 1530)).yaw;
            assert!((y - (118.0 * 3.375 / 100.0_f64).to_radians()).abs() < 1e-12);
            // Full stick: 4500 x 3.375 = 151.875 deg/s.
            let y = input(m, with(5, 1900)).yaw.to_degrees();
            assert!((y - 151.875).abs() < 1e-9, "{y}");
        }
        // SURFACE reads yaw through RC4_DZ alone.
        assert_eq!(input(mode::SURFACE, with(5, 1540)).yaw, 0.0);
        assert!(input(mode::SURFACE, with(5, 1541)).yaw > 0.0);
        // MANUAL: an effort scaled by ACRO_YAW_P / 3.375.
        assert_eq!(input(mode::MANUAL, with(5, 1520)).yaw, 20.0 / 400.0);
        let mut half = p();
        half.acro_yaw_p /= 2.0;
        assert_eq!(
            read_input(mode::MANUAL, &with(5, 1900), &half, 0.5).yaw,
            0.5
        );
    }

    #[test]
    fn roll_and_pitch_are_lean_angles_up_to_angle_max() {
        for m in [
            mode::STABILIZE,
            mode::ALT_HOLD,
            mode::POSHOLD,
            mode::SURFACE,
        ] {
            assert_eq!(input(m, with(3, 1530)).roll, 0.0);
            assert_eq!(input(m, with(4, 1470)).pitch, 0.0);
            assert!((input(m, with(3, 1900)).roll.to_degrees() - 45.0).abs() < 1e-9);
            assert!((input(m, with(4, 1100)).pitch.to_degrees() + 45.0).abs() < 1e-9);
        }
        // Both sticks full: limited to ANGLE_MAX on a circle, roll as an Euler angle.
        let i = input(mode::STABILIZE, [1500, 1500, 1500, 1900, 1900, 1500]);
        let q = 45.0_f64 / 2f64.sqrt();
        assert!((i.pitch.to_degrees() - q).abs() < 1e-9);
        let r = (q.to_radians().cos() * q.to_radians().tan()).atan();
        assert!((i.roll - r).abs() < 1e-12);
    }

    #[test]
    fn throttle_is_direct_in_stabilize_and_a_climb_rate_outside_thr_dz_times_gain() {
        assert_eq!(input(mode::STABILIZE, with(2, 1540)).throttle, 0.1);
        // control_in = 1000 (pwm - 1130) / 770, centre 480, THR_DZ x gain = 50: climb
        // above 530 (1539 us), descend below 430 (1461 us).
        assert_eq!(rc::range_mid(30), 480);
        for pwm in [1462, 1500, 1538] {
            assert_eq!(input(mode::ALT_HOLD, with(2, pwm)).throttle, 0.0, "{pwm}");
        }
        assert!(input(mode::ALT_HOLD, with(2, 1540)).throttle > 0.0);
        assert!(input(mode::ALT_HOLD, with(2, 1460)).throttle < 0.0);
        // Full stick: PILOT_SPEED_UP (500 cm/s) up, PILOT_SPEED_DN = 0 means the same down.
        assert_eq!(input(mode::ALT_HOLD, with(2, 1900)).throttle, 5.0);
        assert_eq!(input(mode::ALT_HOLD, with(2, 1100)).throttle, -5.0);
        let mut q = p();
        q.pilot_speed_dn_cms = 100.0;
        assert_eq!(
            read_input(mode::ALT_HOLD, &with(2, 1100), &q, 0.5).throttle,
            -1.0
        );
    }

    #[test]
    fn wrap_stays_within_pi() {
        assert!(
            (wrap_pi(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-9
                || (wrap_pi(3.0 * std::f64::consts::PI) + std::f64::consts::PI).abs() < 1e-9
        );
        assert!((wrap_pi(0.1 - std::f64::consts::TAU) - 0.1).abs() < 1e-9);
    }
}
