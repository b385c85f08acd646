//! Efforts to ArduSub pilot input: RC channel map, dead-zone and dead-band compensation,
//! MANUAL_CONTROL scaling.

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
    /// Offset (us) added to any non-zero input per axis (surge, sway, heave, roll, pitch, yaw).
    pub offset_us: [f64; 6],
    /// Efforts smaller than this are exact neutral.
    pub epsilon: f64,
    /// MANUAL_CONTROL joystick gain to undo (ArduSub multiplies by it).
    pub joystick_gain: f64,
}

impl PilotMap {
    /// Dead zones for the configured mode: in MANUAL the channel is a straight mixer input,
    /// so only the T200 dead band matters; in STABILIZE / ALT_HOLD ArduSub first applies an
    /// input dead zone (yaw wider). In ALT_HOLD the throttle is a climb-rate demand and
    /// roll/pitch/yaw are attitude demands in both stabilized modes, which ArduSub's own
    /// loops push through the thrusters, so the thruster band is added only where the
    /// channel drives thrusters directly.
    pub fn from_config(cfg: &LinkConfig) -> Self {
        let db = cfg.thruster_deadband_us;
        let dz = cfg.input_deadzone_us;
        let dzy = cfg.yaw_deadzone_us;
        let offset_us = match cfg.mode {
            LinkMode::Manual | LinkMode::Guided => [db; 6],
            LinkMode::Stabilize => [dz + db, dz + db, dz + db, dz, dz, dzy],
            LinkMode::AltHold => [dz + db, dz + db, dz, dz, dz, dzy],
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
        let off = self.offset_us[axis].clamp(0.0, PWM_SPAN_US);
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
    /// 500 neutral. ArduSub maps them to 1500 +- 400 * gain * v / 1000, so the PWM offset is
    /// divided by the gain here (saturating at full stick).
    pub fn manual_control(&self, e: &Effort) -> [i16; 6] {
        let g = self.joystick_gain.max(1e-3);
        let v = |us: f64| -> f64 { (us / PWM_SPAN_US / g * 1000.0).clamp(-1000.0, 1000.0) };
        let x = v(self.offset(0, e.surge));
        let y = v(self.offset(1, e.sway));
        let z = (500.0 - v(self.offset(2, e.heave)) / 2.0).clamp(0.0, 1000.0);
        let r = v(self.offset(5, e.yaw));
        let s = v(self.offset(4, e.pitch));
        let t = v(self.offset(3, e.roll));
        [x, y, z, r, s, t].map(|f| f.round() as i16)
    }
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
        // 1500 + 28 (T200 band) + 0.01 * 372.
        assert_eq!(c[channel::FORWARD - 1], 1532);
        e.surge = -0.01;
        assert_eq!(m.rc_channels(&e)[channel::FORWARD - 1], 1468);
        // Below epsilon: exact neutral.
        e.surge = 1e-4;
        assert_eq!(m.rc_channels(&e)[channel::FORWARD - 1], 1500);
    }

    #[test]
    fn stabilized_modes_add_the_input_dead_zone() {
        let cfg = LinkConfig {
            mode: LinkMode::AltHold,
            ..Default::default()
        };
        let m = PilotMap::from_config(&cfg);
        let mut e = Effort::NEUTRAL;
        e.yaw = 0.001 + 1e-9;
        e.heave = -0.001 - 1e-9;
        let c = m.rc_channels(&e);
        assert_eq!(c[channel::YAW - 1], 1540);
        assert_eq!(c[channel::THROTTLE - 1], 1530);
    }

    #[test]
    fn mixer_sees_the_effort_for_large_inputs() {
        let m = manual();
        let e = Effort::from_array([0.5, -0.25, 0.75, 0.1, -0.6, 0.3]);
        let back = effort_seen_by_mixer(&m.rc_channels(&e));
        for (a, b) in e.to_array().iter().zip(back.to_array()) {
            // Compensation shifts by at most the band (28/400 = 0.07).
            assert!(
                (a - b).abs() <= 0.071 && a.signum() == b.signum(),
                "{a} {b}"
            );
        }
    }

    #[test]
    fn manual_control_scaling() {
        let m = manual();
        let e = Effort::from_array([0.1, 0.0, -0.1, 0.0, 0.0, 0.0]);
        let mc = m.manual_control(&e);
        // 28 + 0.1 * 372 = 65.2 us / 400 / 0.5 gain * 1000 = 326.
        assert_eq!(mc[0], 326);
        assert_eq!(mc[2], 500 + 163);
        let full = m.manual_control(&Effort::from_array([1.0, -1.0, 1.0, 1.0, 1.0, 1.0]));
        assert_eq!(full, [1000, -1000, 0, 1000, 1000, 1000]);
    }
}
