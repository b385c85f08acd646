//! ArduSub's 6-DOF motor mixer for the BlueROV2 frames, on the factor tables and
//! thruster geometry of autopilot's vehicle description (`markhold_autopilot::vehicle`).
//!
//! Efforts follow docs/frames.md: `[surge, sway, heave (+down), roll, pitch, yaw]`, each
//! in -1..1, FRD. ArduSub's throttle is positive up, so throttle = -heave.

use nalgebra::Vector3;

/// The vehicle description is autopilot's: the frames, their factor tables and thruster
/// layout.
pub use markhold_autopilot::vehicle::{Frame6Dof, ThrusterMount, MAX_MOTORS};

/// The mixer and geometry of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Mixer {
    frame: Frame6Dof,
    factors: [[f64; 6]; MAX_MOTORS],
    mounts: [ThrusterMount; MAX_MOTORS],
    n: usize,
    /// MOT_FV_CPLNG_K (the 6-thruster frame only).
    fv_coupling: f64,
}

impl Mixer {
    pub fn new(frame: Frame6Dof) -> Self {
        Self {
            frame,
            factors: frame.motor_factors(),
            mounts: frame.thruster_mounts(),
            n: frame.motor_count(),
            fv_coupling: 1.0,
        }
    }

    /// The same mixer with MOT_FV_CPLNG_K = `k` (ArduSub's default 1.0; 0 disables).
    pub fn with_fv_coupling(mut self, k: f64) -> Self {
        self.fv_coupling = if k.is_finite() { k.max(0.0) } else { 1.0 };
        self
    }

    pub fn frame(&self) -> Frame6Dof {
        self.frame
    }

    pub fn motor_count(&self) -> usize {
        self.n
    }

    /// Mount of motor `i` (0-based); motors past `motor_count()` have zero direction.
    pub fn mounts(&self) -> &[ThrusterMount; MAX_MOTORS] {
        &self.mounts
    }

    /// Normalised motor outputs (-1..1) for efforts `[surge, sway, heave(+down), roll,
    /// pitch, yaw]`. Non-finite efforts count as zero; each is clamped to -1..1 first.
    /// Motors past `motor_count()` output 0.
    pub fn mix_outputs(&self, efforts: &[f64; 6]) -> [f64; MAX_MOTORS] {
        let e = efforts.map(|v| {
            if v.is_finite() {
                v.clamp(-1.0, 1.0)
            } else {
                0.0
            }
        });
        let (forward, lateral, throttle) = (e[0], e[1], -e[2]);
        let (roll, pitch, yaw) = (e[3], e[4], e[5]);
        let mut vert = [0.0; MAX_MOTORS];
        let mut horz = [0.0; MAX_MOTORS];
        // AP_Motors6DOF::output_armed_stabilizing_vectored (the 6-thruster frame): under
        // throttle the forward part of the "rear" horizontal thrusters for the direction
        // of travel (motors 3 and 4 going forward, 1 and 2 going back) is limited to
        // 1 - MOT_FV_CPLNG_K x |throttle|.
        let coupling_limit = (1.0 - self.fv_coupling * throttle.abs()).max(0.0);
        for i in 0..self.n {
            let f = &self.factors[i];
            let mut fwd = forward;
            if self.frame == Frame6Dof::Standard && forward != 0.0 && i < 4 {
                let rear = if forward > 0.0 { i >= 2 } else { i < 2 };
                if rear {
                    fwd = forward.clamp(-coupling_limit, coupling_limit);
                }
            }
            vert[i] = roll * f[0] + pitch * f[1] + throttle * f[3];
            horz[i] = yaw * f[2] + fwd * f[4] + lateral * f[5];
        }
        let mut out = [0.0; MAX_MOTORS];
        match self.frame {
            Frame6Dof::Heavy => {
                // Each group is scaled down together so that it keeps its direction when
                // one motor would saturate.
                let vmax = vert.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                let hmax = horz.iter().fold(1.0f64, |m, v| m.max(v.abs()));
                for i in 0..self.n {
                    out[i] = (vert[i] / vmax + horz[i] / hmax).clamp(-1.0, 1.0);
                }
            }
            Frame6Dof::Standard => {
                // Roll, pitch and yaw plus the linear part, clamped (ArduSub's vectored
                // mixer normalizes nothing).
                for i in 0..self.n {
                    out[i] = (vert[i] + horz[i]).clamp(-1.0, 1.0);
                }
            }
        }
        out
    }

    /// Servo PWM for each motor: `1500 + 400 * out`, and 1500 for every motor when
    /// disarmed. Motors past `motor_count()` read 0 (no output), like SERVO_OUTPUT_RAW.
    pub fn mix_pwm(&self, efforts: &[f64; 6], armed: bool) -> [u16; MAX_MOTORS] {
        let mut pwm = [0u16; MAX_MOTORS];
        if !armed {
            pwm[..self.n].fill(1500);
            return pwm;
        }
        let out = self.mix_outputs(efforts);
        for i in 0..self.n {
            pwm[i] = (1500.0 + 400.0 * out[i]).round() as u16;
        }
        pwm
    }

    /// Body force (N) and moment about the centre of gravity (N m) produced by the given
    /// per-motor thrusts (N, signed along each mount's direction).
    pub fn wrench(&self, thrust_n: &[f64; MAX_MOTORS]) -> (Vector3<f64>, Vector3<f64>) {
        let mut f = Vector3::zeros();
        let mut m = Vector3::zeros();
        for (mount, &t) in self.mounts.iter().zip(thrust_n).take(self.n) {
            let fi = mount.direction * t;
            f += fi;
            m += mount.position_m.cross(&fi);
        }
        (f, m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::thruster::ThrusterConfig;

    fn wrench_of(frame: Frame6Dof, efforts: [f64; 6]) -> (Vector3<f64>, Vector3<f64>) {
        let mixer = Mixer::new(frame);
        let t = ThrusterConfig::default();
        let pwm = mixer.mix_pwm(&efforts, true);
        let thrust = pwm.map(|p| t.steady_thrust_n(p as f64, 16.0));
        mixer.wrench(&thrust)
    }

    #[test]
    fn each_effort_pushes_its_own_axis_positive() {
        for frame in [Frame6Dof::Heavy, Frame6Dof::Standard] {
            for axis in 0..6 {
                if frame == Frame6Dof::Standard && axis == 4 {
                    continue; // no pitch authority
                }
                let mut e = [0.0; 6];
                e[axis] = 0.8;
                let (f, m) = wrench_of(frame, e);
                let w = [f.x, f.y, f.z, m.x, m.y, m.z];
                assert!(w[axis] > 0.0, "{frame} axis {axis}: wrench {w:?}");
                // Reverse effort reverses it.
                e[axis] = -0.8;
                let (f, m) = wrench_of(frame, e);
                let w2 = [f.x, f.y, f.z, m.x, m.y, m.z];
                assert!(w2[axis] < 0.0, "{frame} axis {axis} reversed: {w2:?}");
            }
        }
    }

    /// AP_Motors6DOF::output_armed_stabilizing_vectored: under throttle the rear pair for
    /// the direction of travel gets at most 1 - MOT_FV_CPLNG_K x |throttle| of forward;
    /// the Heavy has no such limit.
    #[test]
    fn fv_cplng_k_limits_the_rear_thrusters_of_the_6_thruster_frame_under_throttle() {
        let std = Mixer::new(Frame6Dof::Standard);
        // Forward 0.8, throttle up 0.5 (heave -0.5): limit 0.5 on motors 3 and 4.
        let out = std.mix_outputs(&[0.8, 0.0, -0.5, 0.0, 0.0, 0.0]);
        assert_eq!([out[0], out[1]], [-0.8, -0.8]);
        assert_eq!([out[2], out[3]], [0.5, 0.5]);
        // Going back, motors 1 and 2 are the rear ones.
        let out = std.mix_outputs(&[-0.8, 0.0, -0.5, 0.0, 0.0, 0.0]);
        assert_eq!([out[0], out[1], out[2], out[3]], [0.5, 0.5, -0.8, -0.8]);
        // K = 0 disables it; no throttle, no limit.
        let off = Mixer::new(Frame6Dof::Standard).with_fv_coupling(0.0);
        assert_eq!(off.mix_outputs(&[0.8, 0.0, -0.5, 0.0, 0.0, 0.0])[2], 0.8);
        assert_eq!(std.mix_outputs(&[0.8, 0.0, 0.0, 0.0, 0.0, 0.0])[2], 0.8);
        let heavy = Mixer::new(Frame6Dof::Heavy);
        let out = heavy.mix_outputs(&[0.8, 0.0, -0.5, 0.0, 0.0, 0.0]);
        assert_eq!(out[2], out[3]);
        assert!((out[2] - 0.8).abs() < 1e-12, "{out:?}");
    }

    #[test]
    fn forward_effort_makes_no_side_force_or_yaw() {
        let (f, m) = wrench_of(Frame6Dof::Heavy, [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        // Two thrusters forward, two in reverse, all at 45 degrees (the T200 table at 16 V).
        let t = ThrusterConfig::default();
        let (fwd, rev) = (
            t.steady_thrust_n(1900.0, 16.0),
            -t.steady_thrust_n(1100.0, 16.0),
        );
        let expect = (2.0 * fwd + 2.0 * rev) * std::f64::consts::FRAC_1_SQRT_2;
        assert!((f.x - expect).abs() < 1e-6, "{f:?}");
        assert!(f.y.abs() < 1e-9 && f.z.abs() < 1e-9);
        assert!(m.z.abs() < 0.5, "yaw {m:?}");
    }

    #[test]
    fn surge_pitches_the_nose_up_because_the_thrusters_sit_below_the_cg() {
        for (frame, arm) in [(Frame6Dof::Heavy, 0.085), (Frame6Dof::Standard, 0.065)] {
            let (f, m) = wrench_of(frame, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0]);
            assert!(f.x > 0.0);
            // Pitch moment (FRD: + nose up) = arm below the CG x forward force.
            assert!((m.y - arm * f.x).abs() < 1e-9, "{frame}: {m:?} {f:?}");
        }
    }

    #[test]
    fn standard_frame_has_no_pitch_authority() {
        let (_, m) = wrench_of(Frame6Dof::Standard, [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        assert_eq!(m.norm(), 0.0);
    }

    #[test]
    fn disarmed_is_1500_and_outputs_clamped() {
        let mixer = Mixer::new(Frame6Dof::Heavy);
        assert_eq!(mixer.mix_pwm(&[1.0; 6], false), [1500; 8]);
        let std = Mixer::new(Frame6Dof::Standard);
        assert_eq!(
            std.mix_pwm(&[0.0; 6], false),
            [1500, 1500, 1500, 1500, 1500, 1500, 0, 0]
        );
        for p in mixer.mix_pwm(&[1.0, 1.0, -1.0, 1.0, 1.0, 1.0], true) {
            assert!((1100..=1900).contains(&p));
        }
        assert_eq!(mixer.mix_pwm(&[f64::NAN; 6], true), [1500; 8]);
    }

    #[test]
    fn heavy_group_normalisation_keeps_direction() {
        let mixer = Mixer::new(Frame6Dof::Heavy);
        // Surge + yaw saturate the horizontal group; the ratio between motors is kept.
        let out = mixer.mix_outputs(&[1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        // Raw horizontal: m1 = 1 - 1 = 0, m2 = -1 - 1 = -2, m3 = -1 + 1 = 0, m4 = 2.
        assert_eq!(&out[..4], &[0.0, -1.0, 0.0, 1.0]);
        let out = mixer.mix_outputs(&[0.0, 0.0, -1.0, 1.0, 0.0, 0.0]);
        // Raw vertical (throttle 1, roll 1): m5 = 1 - 1 = 0, m6 = -2, m7 = 0, m8 = -2.
        assert_eq!(&out[4..], &[0.0, -1.0, 0.0, -1.0]);
    }

    mod laws {
        use super::*;
        use nalgebra::{DMatrix, DVector};
        use proptest::prelude::*;

        proptest! {
            #[test]
            fn outputs_and_pwm_stay_in_range(e in proptest::array::uniform6(-3.0f64..3.0)) {
                for frame in [Frame6Dof::Heavy, Frame6Dof::Standard] {
                    let m = Mixer::new(frame);
                    for o in m.mix_outputs(&e) {
                        prop_assert!((-1.0..=1.0).contains(&o));
                    }
                    for (i, p) in m.mix_pwm(&e, true).into_iter().enumerate() {
                        if i < m.motor_count() {
                            prop_assert!((1100..=1900).contains(&p));
                        } else {
                            prop_assert_eq!(p, 0);
                        }
                    }
                }
            }

            /// Below saturation the mixer is linear: the pseudo-inverse of its factor
            /// matrix recovers the efforts (all six on the Heavy, all but pitch on the
            /// standard frame).
            #[test]
            fn mixer_inverse_round_trips(e in proptest::array::uniform6(-0.15f64..0.15)) {
                for frame in [Frame6Dof::Heavy, Frame6Dof::Standard] {
                    let m = Mixer::new(frame);
                    let n = m.motor_count();
                    // Column j = outputs for a unit effort on axis j (linear part).
                    let mut a = DMatrix::<f64>::zeros(n, 6);
                    for j in 0..6 {
                        let mut u = [0.0; 6];
                        u[j] = 0.1;
                        let out = m.mix_outputs(&u);
                        for i in 0..n {
                            a[(i, j)] = out[i] / 0.1;
                        }
                    }
                    let out = m.mix_outputs(&e);
                    let y = DVector::from_iterator(n, out[..n].iter().copied());
                    let pinv = a.clone().pseudo_inverse(1e-9).unwrap();
                    let back = pinv * y;
                    for j in 0..6 {
                        if frame == Frame6Dof::Standard && j == 4 {
                            prop_assert!(back[j].abs() < 1e-9);
                            continue;
                        }
                        prop_assert!((back[j] - e[j]).abs() < 1e-9, "{frame} axis {j}: {} vs {}", back[j], e[j]);
                    }
                }
            }
        }
    }
}
