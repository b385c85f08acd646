//! The flight-mode controllers of the simulated autopilot: what ArduSub's MANUAL,
//! STABILIZE, ALT_HOLD, POSHOLD and GUIDED modes do with pilot input and targets, reduced
//! to PD/PID loops that output the mixer's normalized efforts. Not ArduSub's tuning or
//! code: enough to fly the simulated vehicle the way a client expects each mode to.
//!
//! Pilot input is read per channel and mode as ArduSub reads it (ArduSub/mode_manual.cpp,
//! mode_stabilize.cpp, mode_althold.cpp; libraries/RC_Channel/RC_Channel.cpp; see
//! docs/design/hil.md): channels that drive thrusters directly go through `norm_input()`
//! (no dead zone), channels that become setpoints through `get_control_in()` (RCn_DZ), the
//! ALT_HOLD throttle then through the THR_DZ climb-rate dead band, and the yaw rate
//! through a dead zone of RC4_DZ x joystick gain.

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::{mode, GuidedTarget};
use crate::vehicle::VehicleState;
use markhold_config::{Checks, ConfigError};

/// Controller gains (efforts are normalized -1..1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlGains {
    /// Attitude hold: effort per radian of error.
    pub attitude_kp: f64,
    /// Attitude hold: effort per rad/s of body rate.
    pub attitude_kd: f64,
    /// Roll / pitch at full stick in the stabilized modes, degrees.
    pub max_tilt_deg: f64,
    /// Yaw rate at full stick, degrees per second.
    pub max_yaw_rate_dps: f64,
    /// Depth hold: effort per metre, per metre-second (integral), per m/s.
    pub depth_kp: f64,
    pub depth_ki: f64,
    pub depth_kd: f64,
    /// Largest integral effort of the depth hold (trims buoyancy).
    pub depth_i_max: f64,
    /// Climb / descent rate at full throttle stick in ALT_HOLD and POSHOLD, m/s.
    pub max_climb_mps: f64,
    /// Position loop: commanded speed per metre of error, 1/s.
    pub position_kp: f64,
    /// Velocity loop: effort per m/s of velocity error.
    pub velocity_kp: f64,
    /// Speed limit of the position loop, m/s.
    pub max_speed_mps: f64,
}

impl Default for ControlGains {
    fn default() -> Self {
        Self {
            attitude_kp: 2.0,
            attitude_kd: 0.6,
            max_tilt_deg: 30.0,
            max_yaw_rate_dps: 60.0,
            depth_kp: 1.5,
            depth_ki: 0.4,
            depth_kd: 1.2,
            depth_i_max: 0.3,
            max_climb_mps: 0.5,
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
            .non_negative("attitude_kp", self.attitude_kp, nn)
            .non_negative("attitude_kd", self.attitude_kd, nn)
            .non_negative("max_tilt_deg", self.max_tilt_deg, nn)
            .non_negative("max_yaw_rate_dps", self.max_yaw_rate_dps, nn)
            .non_negative("depth_kp", self.depth_kp, nn)
            .non_negative("depth_ki", self.depth_ki, nn)
            .non_negative("depth_kd", self.depth_kd, nn)
            .non_negative("depth_i_max", self.depth_i_max, nn)
            .non_negative("max_climb_mps", self.max_climb_mps, nn)
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
    pub fn climb_fraction(pwm: u16, rc3_dz: u16, thr_dz: u16) -> f64 {
        let ctrl = range_dz(pwm, rc3_dz) as f64;
        let mid = range_mid(rc3_dz) as f64;
        let thr_dz = f64::from(thr_dz.min(400));
        let (top, bottom) = (mid + thr_dz, mid - thr_dz);
        if ctrl < bottom && bottom > 0.0 {
            (ctrl - bottom) / bottom
        } else if ctrl > top && top < RANGE_MAX as f64 {
            (ctrl - top) / (RANGE_MAX as f64 - top)
        } else {
            0.0
        }
    }
}

/// ArduSub's input parameters that decide how pilot input is read (`[endpoint]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct InputParams {
    /// RC1_DZ .. RC4_DZ (pitch, roll, throttle, yaw), us.
    pub rc_dz_us: [u16; 4],
    /// THR_DZ: the ALT_HOLD climb-rate dead band about centre stick, throttle units.
    pub thr_dz: u16,
    /// The joystick gain (JS_GAIN): scales the yaw dead zone.
    pub joystick_gain: f64,
}

impl InputParams {
    /// The yaw dead zone ArduSub uses in STABILIZE / ALT_HOLD: RC4_DZ x gain, truncated
    /// to whole microseconds (`channel_yaw->get_dead_zone() * sub.gain` passed as uint16).
    pub fn yaw_dz(&self) -> u16 {
        (f64::from(self.rc_dz_us[3]) * self.joystick_gain) as u16
    }
}

/// The pilot's input as a mode reads it: `[forward, lateral, throttle, roll, pitch, yaw]`.
/// Forward and lateral are normalized efforts (`norm_input`); throttle is a direct
/// effort (MANUAL, STABILIZE: + up) or a climb-rate fraction (ALT_HOLD, POSHOLD: + up);
/// roll and pitch are fractions of the largest lean angle, yaw of the largest yaw rate
/// (MANUAL: efforts).
pub(crate) fn read_input(mode: u32, rc: &[u16; 6], p: &InputParams) -> [f64; 6] {
    let n = rc::norm_input;
    if mode == super::mode::MANUAL {
        // mode_manual.cpp: every channel straight into the mixer (ACRO_YAW_P at its
        // default leaves yaw unscaled).
        return [n(rc[0]), n(rc[1]), n(rc[2]), n(rc[3]), n(rc[4]), n(rc[5])];
    }
    let angle = |pwm: u16, dz: u16| f64::from(rc::angle_dz(pwm, dz)) / f64::from(rc::ANGLE_MAX);
    let throttle = if mode == super::mode::STABILIZE {
        // set_throttle_out((norm_input() + 1) / 2): direct throttle, no dead zone.
        n(rc[2])
    } else {
        rc::climb_fraction(rc[2], p.rc_dz_us[2], p.thr_dz)
    };
    [
        n(rc[0]),
        n(rc[1]),
        throttle,
        angle(rc[3], p.rc_dz_us[1]),
        angle(rc[4], p.rc_dz_us[0]),
        angle(rc[5], p.yaw_dz()),
    ]
}

pub(crate) struct Controller {
    gains: ControlGains,
    input: InputParams,
    yaw_target: Option<f64>,
    depth_target: Option<f64>,
    depth_i: f64,
    hold_position: Option<Vector3<f64>>,
    last_nav: Option<NavEstimate>,
    /// The throttle stick was out of its dead zone on the last update.
    climbing: bool,
    /// GUIDED followed a velocity-only target on the last update.
    guided_moving: bool,
}

impl Controller {
    pub fn new(gains: ControlGains, input: InputParams) -> Self {
        Self {
            gains,
            input,
            yaw_target: None,
            depth_target: None,
            depth_i: 0.0,
            hold_position: None,
            last_nav: None,
            climbing: false,
            guided_moving: false,
        }
    }

    /// Forget every hold target (arming, mode change).
    pub fn reset(&mut self) {
        self.yaw_target = None;
        self.depth_target = None;
        self.depth_i = 0.0;
        self.hold_position = None;
        self.climbing = false;
        self.guided_moving = false;
    }

    /// A depth target from the client (ALT_HOLD via SET_POSITION_TARGET_GLOBAL_INT).
    pub fn set_depth_target(&mut self, depth_m: f64) {
        self.depth_target = Some(depth_m);
        self.climbing = false;
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
        let [fwd, lat, thr, s_roll, s_pitch, s_yaw] = read_input(mode, rc, &self.input);
        if mode == mode::MANUAL {
            // Straight through; throttle up = heave up (negative).
            return [fwd, lat, -thr, s_roll, s_pitch, s_yaw];
        }
        let g = &self.gains;
        let (roll, pitch, yaw) = state.t_world_vehicle.rotation.euler_angles();
        let w = state.angvel_body_rps;
        let depth = state.t_world_vehicle.translation.vector.z;
        let vz = state.velocity_world_mps.z;
        // POSHOLD holds position while forward and lateral are within their RCn_DZ.
        let steering = rc::angle_dz(rc[0], 30) != 0 || rc::angle_dz(rc[1], 30) != 0;

        // Heading: yaw stick turns the target at a rate; released, the target holds.
        let mut yaw_t = *self.yaw_target.get_or_insert(yaw);
        let mut guided_vel = None;
        let mut guided_pos = None;
        if mode == mode::GUIDED {
            if let (Some(t), Some(nav)) = (guided, nav) {
                // Targets are in the nav frame: rotate yaw targets by the nav-world offset.
                if let Some(y) = t.yaw {
                    yaw_t = y - (nav.yaw - yaw);
                } else if let Some(r) = t.yaw_rate {
                    yaw_t += r * dt;
                }
                guided_pos = t.position;
                guided_vel = t.velocity;
                if guided_pos.is_some() {
                    self.hold_position = guided_pos;
                }
            }
        } else if s_yaw != 0.0 {
            yaw_t += s_yaw * g.max_yaw_rate_dps.to_radians() * dt;
        }
        // Keep the target within reach so that a stuck vehicle does not wind up.
        yaw_t = yaw + wrap_pi(yaw_t - yaw).clamp(-0.5, 0.5);
        self.yaw_target = Some(yaw_t);
        let (roll_t, pitch_t) = if mode == mode::GUIDED {
            (0.0, 0.0)
        } else {
            let m = g.max_tilt_deg.to_radians();
            (s_roll * m, s_pitch * m)
        };
        let att =
            |err: f64, rate: f64| (g.attitude_kp * err - g.attitude_kd * rate).clamp(-1.0, 1.0);
        let e_roll = att(wrap_pi(roll_t - roll), w.x);
        let e_pitch = att(wrap_pi(pitch_t - pitch), w.y);
        let e_yaw = att(wrap_pi(yaw_t - yaw), w.z);

        if mode == mode::STABILIZE {
            return [fwd, lat, -thr, e_roll, e_pitch, e_yaw];
        }

        // Depth hold (ALT_HOLD, POSHOLD, GUIDED).
        if mode == mode::ALT_HOLD || mode == mode::POSHOLD {
            let heave = if thr != 0.0 {
                // Throttle up = climb = depth decreasing.
                let rate = -thr * g.max_climb_mps;
                let t = self.depth_target.unwrap_or(depth) + rate * dt;
                let t = depth + (t - depth).clamp(-0.1, 0.1);
                self.depth_target = Some(t);
                self.climbing = true;
                self.depth_pid(t, rate, depth, vz, dt)
            } else {
                if self.climbing {
                    // Stick released: hold where the vehicle will stop, not where the
                    // moving target had got to.
                    self.climbing = false;
                    self.depth_target = Some(depth + vz.abs() * vz * 0.5);
                }
                let t = *self.depth_target.get_or_insert(depth);
                self.depth_pid(t, 0.0, depth, vz, dt)
            };
            let (mut surge, mut sway) = (fwd, lat);
            if mode == mode::POSHOLD {
                match nav {
                    Some(nav) if !steering => {
                        let hold = *self
                            .hold_position
                            .get_or_insert(nav.pose.translation.vector);
                        let e = self.horizontal_effort(&nav, &hold, &Vector3::zeros());
                        surge = e.x;
                        sway = e.y;
                    }
                    _ => self.hold_position = None,
                }
            }
            return [surge, sway, heave, e_roll, e_pitch, e_yaw];
        }

        // GUIDED.
        let Some(nav) = nav else {
            // No position estimate: hold depth and heading only.
            let t = *self.depth_target.get_or_insert(depth);
            return [
                0.0,
                0.0,
                self.depth_pid(t, 0.0, depth, vz, dt),
                e_roll,
                e_pitch,
                e_yaw,
            ];
        };
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
        let e = self.horizontal_effort(&nav, &target, &ff);
        // Vertical: position error to a climb rate, then depth PID on it. The nav frame's
        // z is the vision frame's; its offset to true depth is fixed between updates.
        let z_off = depth - p.z;
        let t = target.z + z_off;
        self.depth_target = Some(t);
        let heave = self.depth_pid(t, ff.z, depth, vz, dt);
        [e.x, e.y, heave, e_roll, e_pitch, e_yaw]
    }

    /// Heave effort (+down) holding `target_depth` with feed-forward climb rate `ff_vz`.
    fn depth_pid(&mut self, target_depth: f64, ff_vz: f64, depth: f64, vz: f64, dt: f64) -> f64 {
        let g = &self.gains;
        let err = target_depth - depth;
        self.depth_i = (self.depth_i + g.depth_ki * err * dt).clamp(-g.depth_i_max, g.depth_i_max);
        (g.depth_kp * err + self.depth_i - g.depth_kd * (vz - ff_vz)).clamp(-1.0, 1.0)
    }

    /// Body-frame surge / sway efforts that bring the nav position to `target` with
    /// feed-forward velocity `ff` (nav frame).
    fn horizontal_effort(
        &self,
        nav: &NavEstimate,
        target: &Vector3<f64>,
        ff: &Vector3<f64>,
    ) -> Vector3<f64> {
        let g = &self.gains;
        let mut err = target - nav.pose.translation.vector;
        err.z = 0.0;
        let mut v_des = ff + err * g.position_kp;
        v_des.z = 0.0;
        let speed = v_des.norm();
        if speed > g.max_speed_mps && speed > 0.0 {
            v_des *= g.max_speed_mps / speed;
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

    const P: InputParams = InputParams {
        rc_dz_us: [30, 30, 30, 40],
        thr_dz: 100,
        joystick_gain: 0.5,
    };
    const NEUTRAL: [u16; 6] = [1500; 6];

    fn with(ch: usize, pwm: u16) -> [u16; 6] {
        let mut rc = NEUTRAL;
        rc[ch] = pwm;
        rc
    }

    #[test]
    fn forward_and_lateral_have_no_dead_zone_in_any_mode() {
        for m in [mode::MANUAL, mode::STABILIZE, mode::ALT_HOLD] {
            // 1530 us forward in ALT_HOLD is 30/400 of full effort, not zero.
            let i = read_input(m, &with(0, 1530), &P);
            assert_eq!(i[0], 30.0 / 400.0, "mode {m}");
            let i = read_input(m, &with(1, 1499), &P);
            assert_eq!(i[1], -1.0 / 400.0, "mode {m}");
            assert_eq!(read_input(m, &NEUTRAL, &P), [0.0; 6], "mode {m}");
        }
    }

    #[test]
    fn setpoint_channels_go_through_their_dead_zones() {
        for m in [mode::STABILIZE, mode::ALT_HOLD] {
            // Yaw inside RC4_DZ x gain (40 x 0.5 = 20 us) is zeroed; just outside is not.
            assert_eq!(read_input(m, &with(5, 1520), &P)[5], 0.0);
            assert_eq!(read_input(m, &with(5, 1480), &P)[5], 0.0);
            // pwm_to_angle_dz: 4500 x (1530 - 1520) / 380 = 118 (integer) of 4500.
            assert_eq!(read_input(m, &with(5, 1530), &P)[5], 118.0 / 4500.0);
            // Roll and pitch inside RC2_DZ / RC1_DZ (30 us): zero.
            assert_eq!(read_input(m, &with(3, 1530), &P)[3], 0.0);
            assert_eq!(read_input(m, &with(4, 1470), &P)[4], 0.0);
            assert!(read_input(m, &with(3, 1531), &P)[3] > 0.0);
            assert!(read_input(m, &with(4, 1469), &P)[4] < 0.0);
            assert_eq!(read_input(m, &with(4, 1900), &P)[4], 1.0);
        }
        // MANUAL: the same channels are straight efforts.
        assert_eq!(
            read_input(mode::MANUAL, &with(5, 1520), &P)[5],
            20.0 / 400.0
        );
    }

    #[test]
    fn throttle_is_direct_in_stabilize_and_a_climb_rate_with_thr_dz_in_alt_hold() {
        assert_eq!(read_input(mode::STABILIZE, &with(2, 1540), &P)[2], 0.1);
        // control_in = 1000 (pwm - 1130) / 770, centre 480, THR_DZ 100: climb above 580
        // (1578 us), descend below 380 (1422 us).
        assert_eq!(rc::range_mid(30), 480);
        for pwm in [1423, 1500, 1540, 1577] {
            assert_eq!(
                read_input(mode::ALT_HOLD, &with(2, pwm), &P)[2],
                0.0,
                "{pwm}"
            );
        }
        assert!(read_input(mode::ALT_HOLD, &with(2, 1578), &P)[2] > 0.0);
        assert!(read_input(mode::ALT_HOLD, &with(2, 1422), &P)[2] < 0.0);
        assert_eq!(read_input(mode::ALT_HOLD, &with(2, 1900), &P)[2], 1.0);
        assert_eq!(read_input(mode::ALT_HOLD, &with(2, 1100), &P)[2], -1.0);
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
