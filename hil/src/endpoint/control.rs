//! The flight-mode controllers of the simulated autopilot: what ArduSub's MANUAL,
//! STABILIZE, ALT_HOLD, POSHOLD and GUIDED modes do with pilot input and targets, reduced
//! to PD/PID loops that output the mixer's normalized efforts. Not ArduSub's tuning or
//! code: enough to fly the simulated vehicle the way a client expects each mode to.

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

/// Stick deflection -1..1 from PWM with a dead zone (the stabilized modes' input filter).
fn stick(pwm: u16, dead_zone_us: f64) -> f64 {
    let d = pwm as f64 - 1500.0;
    if d.abs() <= dead_zone_us {
        0.0
    } else {
        ((d.abs() - dead_zone_us) / (400.0 - dead_zone_us)).min(1.0) * d.signum()
    }
}

pub(crate) struct Controller {
    gains: ControlGains,
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
    pub fn new(gains: ControlGains) -> Self {
        Self {
            gains,
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
        if mode == mode::MANUAL {
            // Straight through, no dead zone; throttle up = heave up (negative).
            let n = |p: u16| (p as f64 - 1500.0) / 400.0;
            return [n(rc[0]), n(rc[1]), -n(rc[2]), n(rc[3]), n(rc[4]), n(rc[5])];
        }
        let g = &self.gains;
        let (roll, pitch, yaw) = state.t_world_vehicle.rotation.euler_angles();
        let w = state.angvel_body_rps;
        let depth = state.t_world_vehicle.translation.vector.z;
        let vz = state.velocity_world_mps.z;
        let (fwd, lat, thr) = (stick(rc[0], 30.0), stick(rc[1], 30.0), stick(rc[2], 30.0));
        let (s_roll, s_pitch, s_yaw) = (stick(rc[3], 30.0), stick(rc[4], 30.0), stick(rc[5], 40.0));

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
                    Some(nav) if fwd == 0.0 && lat == 0.0 => {
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

    #[test]
    fn dead_zone_and_wrap() {
        assert_eq!(stick(1530, 30.0), 0.0);
        assert_eq!(stick(1470, 30.0), 0.0);
        assert!(stick(1531, 30.0) > 0.0);
        assert_eq!(stick(1900, 30.0), 1.0);
        assert_eq!(stick(1100, 40.0), -1.0);
        assert!(
            (wrap_pi(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-9
                || (wrap_pi(3.0 * std::f64::consts::PI) + std::f64::consts::PI).abs() < 1e-9
        );
        assert!((wrap_pi(0.1 - std::f64::consts::TAU) - 0.1).abs() < 1e-9);
    }
}
