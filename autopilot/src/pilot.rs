//! Efforts to ArduSub pilot input: RC channel map, dead-zone and dead-band compensation,
//! MANUAL_CONTROL scaling.
//!
//! Which channel meets which dead zone follows ArduSub's source (docs/design/autopilot.md):
//! forward and lateral go to the mixer through `RC_Channel::norm_input()` in MANUAL,
//! STABILIZE and ALT_HOLD (no input dead zone), so only the thrusters' ESC dead band
//! applies; roll, pitch and yaw become setpoints through `get_control_in()` (RCn_DZ; the
//! yaw dead zone is RC4_DZ x joystick gain); the throttle is a direct effort in MANUAL and
//! STABILIZE and a climb rate with the THR_DZ dead band in ALT_HOLD.

use serde::Serialize;

use crate::config::{LinkConfig, LinkMode};
use crate::types::Effort;

/// PWM of a centred stick.
pub const PWM_NEUTRAL: u16 = 1500;
/// Lowest PWM ArduSub reads on an input channel.
pub const PWM_MIN: u16 = 1100;
/// Highest PWM ArduSub reads on an input channel.
pub const PWM_MAX: u16 = 1900;
const PWM_SPAN_US: f64 = 400.0;

/// ArduSub's input channels (1-based), for the six axes.
pub mod channel {
    /// Pitch (+ nose up).
    pub const PITCH: usize = 1;
    /// Roll (+ right side down).
    pub const ROLL: usize = 2;
    /// Throttle (+ up, so heave-down efforts lower it).
    pub const THROTTLE: usize = 3;
    /// Yaw (+ right).
    pub const YAW: usize = 4;
    /// Forward.
    pub const FORWARD: usize = 5;
    /// Lateral (+ right).
    pub const LATERAL: usize = 6;
}

/// How an effort becomes a PWM offset: per-axis jump past the dead zones.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PilotMap {
    /// Per axis (surge, sway, heave, roll, pitch, yaw): the largest PWM offset from 1500
    /// that still does nothing (dead zone or dead band), us. A non-zero effort starts
    /// half a microsecond past it, so its rounded PWM is the first one that counts.
    pub offset_us: [f64; 6],
    /// Efforts smaller than this are exact neutral.
    pub epsilon: f64,
    /// MANUAL_CONTROL joystick gain to undo (ArduSub multiplies by it).
    pub joystick_gain: f64,
}

impl PilotMap {
    /// Dead zones for the configured mode. Channels that drive thrusters directly (all in
    /// MANUAL; forward, lateral and throttle in STABILIZE; forward and lateral in
    /// ALT_HOLD) meet only the ESC dead band. Setpoint channels meet ArduSub's input dead
    /// zone, and ArduSub's own loops then push the thrusters past their band: roll and
    /// pitch RCn_DZ, yaw RC4_DZ x joystick gain, the ALT_HOLD throttle THR_DZ x joystick
    /// gain about the centre of its RC3_DZ-reduced range.
    pub fn from_config(cfg: &LinkConfig) -> Self {
        let db = cfg.thruster_deadband_us;
        let dz = cfg.input_deadzone_us;
        // `channel_yaw->get_dead_zone() * sub.gain`, passed on as whole microseconds.
        let dzy = (cfg.yaw_deadzone_us * cfg.manual_control_gain).trunc();
        let climb = climb_dead_zone_us(cfg.input_deadzone_us, cfg.thr_dz, cfg.manual_control_gain);
        let offset_us = match cfg.mode {
            LinkMode::Manual | LinkMode::Guided => [db; 6],
            LinkMode::Stabilize => [db, db, db, dz, dz, dzy],
            LinkMode::AltHold => [db, db, climb, dz, dz, dzy],
        };
        Self {
            offset_us,
            epsilon: cfg.effort_epsilon,
            joystick_gain: cfg.manual_control_gain,
        }
    }

    /// PWM offset from neutral (us, -400..400) for `effort` on `axis` (0..6).
    pub fn offset(&self, axis: usize, effort: f64) -> f64 {
        if !effort.is_finite() || effort.abs() < self.epsilon {
            return 0.0;
        }
        let off = (self.offset_us[axis] + 0.5).clamp(0.0, PWM_SPAN_US);
        let mag = off + effort.abs().min(1.0) * (PWM_SPAN_US - off);
        mag.copysign(effort)
    }

    /// RC_CHANNELS_OVERRIDE channels 1..8 (index 0 = channel 1). Channels 7 and 8 (camera
    /// pan/tilt) are left at neutral.
    pub fn rc_channels(&self, e: &Effort) -> [u16; 8] {
        let pwm = |us: f64| -> u16 {
            (f64::from(PWM_NEUTRAL) + us)
                .round()
                .clamp(f64::from(PWM_MIN), f64::from(PWM_MAX)) as u16
        };
        let mut ch = [PWM_NEUTRAL; 8];
        ch[channel::PITCH - 1] = pwm(self.offset(4, e.pitch));
        ch[channel::ROLL - 1] = pwm(self.offset(3, e.roll));
        ch[channel::THROTTLE - 1] = pwm(-self.offset(2, e.heave));
        ch[channel::YAW - 1] = pwm(self.offset(5, e.yaw));
        ch[channel::FORWARD - 1] = pwm(self.offset(0, e.surge));
        ch[channel::LATERAL - 1] = pwm(self.offset(1, e.sway));
        ch
    }

    /// MANUAL_CONTROL axes (x, y, z, r, s = pitch, t = roll): -1000..1000, z 0..1000 with
    /// 500 neutral. ArduSub maps them to 1500 + v x 0.4 x gain (throttle: (z - 500) x 0.8
    /// x gain) and truncates to whole microseconds, so each axis is the value whose
    /// truncated PWM is the RC_CHANNELS_OVERRIDE PWM (aimed at the middle of that
    /// microsecond, clear of rounding).
    pub fn manual_control(&self, e: &Effort) -> [i16; 6] {
        let g = self.joystick_gain.max(1e-3);
        // Axis units for a PWM offset, `per_unit` us each: truncation of the (positive)
        // PWM is a floor, so offset u lands on [u, u + 1) us at (u + 0.5) / per_unit.
        let units = |us: f64, per_unit: f64| -> f64 {
            let u = us.round();
            if u == 0.0 {
                0.0
            } else {
                ((u + 0.5) / per_unit).round()
            }
        };
        let v = |us: f64| units(us, 0.4 * g).clamp(-1000.0, 1000.0);
        let x = v(self.offset(0, e.surge));
        let y = v(self.offset(1, e.sway));
        let z = (500.0 + units(-self.offset(2, e.heave), 0.8 * g)).clamp(0.0, 1000.0);
        let r = v(self.offset(5, e.yaw));
        let s = v(self.offset(4, e.pitch));
        let t = v(self.offset(3, e.roll));
        [x, y, z, r, s, t].map(|f| f as i16)
    }
}

/// The ALT_HOLD throttle's dead zone, us from 1500 (the larger of up and down): the
/// largest offset whose `Sub::get_pilot_desired_climb_rate()` is zero, from
/// `RC_Channel::pwm_to_range_dz()` (RC3_DZ = `rc3_dz_us`, range 0..1000) and THR_DZ
/// times the joystick gain about `get_control_mid()` (ArduSub 4.5's `Attitude.cpp`), in
/// ArduSub's arithmetic (30 us, 100 and gain 0.5: 38 us; at gain 1: 77 us).
pub fn climb_dead_zone_us(rc3_dz_us: f64, thr_dz: f64, gain: f64) -> f64 {
    let low = 1100 + rc3_dz_us.clamp(0.0, 200.0) as i32;
    let ctrl = |pwm: i32| {
        if pwm > low {
            1000 * (pwm - low) / (1900 - low)
        } else {
            0
        }
    };
    let mid = f64::from(1000 * (1500 - low) / (1900 - low));
    // THR_DZ is an integer parameter; `gain` scales it as a float.
    let dz = thr_dz.clamp(0.0, 400.0).trunc() * gain;
    let climbs = |pwm: i32| {
        let c = f64::from(ctrl(pwm));
        c > mid + dz || c < mid - dz
    };
    let up = (0..=400).find(|k| climbs(1500 + k)).unwrap_or(401);
    let down = (0..=400).find(|k| climbs(1500 - k)).unwrap_or(401);
    f64::from(up.max(down) - 1).clamp(0.0, PWM_SPAN_US)
}

/// Inverse of the channel map in MANUAL without compensation: the normalized inputs
/// ArduSub's mixer sees, (surge, sway, heave, roll, pitch, yaw). Used by tests and tools.
pub fn effort_seen_by_mixer(ch: &[u16; 8]) -> Effort {
    let n = |p: u16| (f64::from(p) - f64::from(PWM_NEUTRAL)) / PWM_SPAN_US;
    Effort {
        surge: n(ch[channel::FORWARD - 1]),
        sway: n(ch[channel::LATERAL - 1]),
        heave: -n(ch[channel::THROTTLE - 1]),
        roll: n(ch[channel::ROLL - 1]),
        pitch: n(ch[channel::PITCH - 1]),
        yaw: n(ch[channel::YAW - 1]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manual() -> PilotMap {
        PilotMap::from_config(&LinkConfig::default())
    }

    #[test]
    fn neutral_is_1500_everywhere() {
        assert_eq!(manual().rc_channels(&Effort::NEUTRAL), [1500; 8]);
        let mc = manual().manual_control(&Effort::NEUTRAL);
        assert_eq!(mc, [0, 0, 500, 0, 0, 0]);
    }

    #[test]
    fn channel_map_and_directions() {
        let m = manual();
        let one = |f: fn(&mut Effort)| {
            let mut e = Effort::NEUTRAL;
            f(&mut e);
            m.rc_channels(&e)
        };
        // Full efforts hit the ends of the range on the right channel only.
        let c = one(|e| e.surge = 1.0);
        assert_eq!(c, [1500, 1500, 1500, 1500, 1900, 1500, 1500, 1500]);
        let c = one(|e| e.sway = -1.0);
        assert_eq!(c, [1500, 1500, 1500, 1500, 1500, 1100, 1500, 1500]);
        // Heave is + down; throttle is + up.
        let c = one(|e| e.heave = 1.0);
        assert_eq!(c, [1500, 1500, 1100, 1500, 1500, 1500, 1500, 1500]);
        let c = one(|e| e.yaw = 1.0);
        assert_eq!(c, [1500, 1500, 1500, 1900, 1500, 1500, 1500, 1500]);
        let c = one(|e| e.roll = 1.0);
        assert_eq!(c, [1500, 1900, 1500, 1500, 1500, 1500, 1500, 1500]);
        let c = one(|e| e.pitch = -1.0);
        assert_eq!(c, [1100, 1500, 1500, 1500, 1500, 1500, 1500, 1500]);
        // Out-of-range efforts saturate inside 1100..1900.
        let c = m.rc_channels(&Effort::from_array([5.0, -5.0, 9.0, f64::NAN, 1e9, -1e9]));
        assert!(c.iter().all(|p| (1100..=1900).contains(p)), "{c:?}");
        assert_eq!(c[channel::ROLL - 1], 1500);
    }

    #[test]
    fn small_efforts_jump_the_dead_band() {
        let m = manual();
        let mut e = Effort::NEUTRAL;
        e.surge = 0.01;
        let c = m.rc_channels(&e);
        // 1500 + 30.5 (past the T200 band) + 0.01 * 369.5.
        assert_eq!(c[channel::FORWARD - 1], 1534);
        e.surge = -0.01;
        assert_eq!(m.rc_channels(&e)[channel::FORWARD - 1], 1466);
        // Below epsilon: exact neutral.
        e.surge = 1e-4;
        assert_eq!(m.rc_channels(&e)[channel::FORWARD - 1], 1500);
    }

    #[test]
    fn each_channel_meets_the_dead_zone_ardusub_applies_to_it() {
        let smallest = |mode: LinkMode| {
            let m = PilotMap::from_config(&LinkConfig {
                mode,
                ..Default::default()
            });
            let e = Effort::from_array([
                1e-3 + 1e-9,
                -1e-3 - 1e-9,
                -1e-3 - 1e-9,
                1e-3 + 1e-9,
                -1e-3 - 1e-9,
                1e-3 + 1e-9,
            ]);
            let c = m.rc_channels(&e);
            [
                c[channel::FORWARD - 1],
                c[channel::LATERAL - 1],
                c[channel::THROTTLE - 1],
                c[channel::ROLL - 1],
                c[channel::PITCH - 1],
                c[channel::YAW - 1],
            ]
        };
        // Forward and lateral: only the ESC band (30 us), in every mode: the first PWM
        // past it. ALT_HOLD throttle: past THR_DZ x gain (38 us with RC3_DZ 30, THR_DZ 100,
        // gain 0.5); roll
        // and pitch past RCn_DZ (30); yaw past RC4_DZ x gain (40 x 0.5 = 20).
        assert_eq!(
            smallest(LinkMode::AltHold),
            [1531, 1469, 1539, 1531, 1469, 1521]
        );
        assert_eq!(
            smallest(LinkMode::Stabilize),
            [1531, 1469, 1531, 1531, 1469, 1521]
        );
        assert_eq!(
            smallest(LinkMode::Manual),
            [1531, 1469, 1531, 1531, 1469, 1531]
        );
        assert_eq!(climb_dead_zone_us(30.0, 100.0, 0.5), 38.0);
        assert_eq!(climb_dead_zone_us(30.0, 100.0, 1.0), 77.0);
        assert_eq!(climb_dead_zone_us(30.0, 0.0, 0.5), 0.0);
    }

    #[test]
    fn mixer_sees_the_effort_for_large_inputs() {
        let m = manual();
        let e = Effort::from_array([0.5, -0.25, 0.75, 0.1, -0.6, 0.3]);
        let back = effort_seen_by_mixer(&m.rc_channels(&e));
        for (a, b) in e.to_array().iter().zip(back.to_array()) {
            // Compensation shifts by at most the band (30.5/400 = 0.076).
            assert!(
                (a - b).abs() <= 0.077 && a.signum() == b.signum(),
                "{a} {b}"
            );
        }
    }

    #[test]
    fn manual_control_scaling() {
        let m = manual();
        let e = Effort::from_array([0.1, 0.0, -0.1, 0.0, 0.0, 0.0]);
        let mc = m.manual_control(&e);
        // 30.5 + 0.1 * 369.5 = 67.45 -> 67 us; ArduSub: 1500 + x * 0.2 truncated, so
        // x = 67.5 / 0.2 = 338 (1567.6 us). Throttle: 0.4 us per unit of z: 67.5 / 0.4.
        assert_eq!(mc[0], 338);
        assert_eq!(mc[2], 500 + 169);
        let full = m.manual_control(&Effort::from_array([1.0, -1.0, 1.0, 1.0, 1.0, 1.0]));
        assert_eq!(full, [1000, -1000, 0, 1000, 1000, 1000]);
        // What ArduSub makes of every small forward effort is the RC override's PWM.
        for k in 1..200 {
            let e = Effort::from_array([k as f64 * 1e-3, 0.0, 0.0, 0.0, 0.0, 0.0]);
            let x = f64::from(m.manual_control(&e)[0]);
            let rc = m.rc_channels(&e)[channel::FORWARD - 1];
            assert_eq!((1500.0 + x * 0.4 * 0.5).trunc() as u16, rc, "effort {k}e-3");
            let heave = Effort::from_array([0.0, 0.0, k as f64 * 1e-3, 0.0, 0.0, 0.0]);
            let z = f64::from(m.manual_control(&heave)[2]);
            let thr = m.rc_channels(&heave)[channel::THROTTLE - 1];
            assert_eq!(
                (1500.0 + (z - 500.0) * 0.8 * 0.5).trunc() as u16,
                thr,
                "heave {k}e-3"
            );
            let neg = Effort::from_array([-(k as f64) * 1e-3, 0.0, 0.0, 0.0, 0.0, 0.0]);
            let x = f64::from(m.manual_control(&neg)[0]);
            let rc = m.rc_channels(&neg)[channel::FORWARD - 1];
            assert_eq!(
                (1500.0 + x * 0.4 * 0.5).trunc() as u16,
                rc,
                "effort -{k}e-3"
            );
        }
    }
}
