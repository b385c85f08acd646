//! Blue Robotics T200 thruster: PWM to thrust with the ESC dead band, the forward/reverse
//! asymmetry of the propeller, and a first-order spin-up lag.

use serde::{Deserialize, Serialize};

use markhold_config::{Checks, ConfigError};

/// Static and dynamic parameters of one T200 (published figures at 16 V).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ThrusterConfig {
    /// Thrust at 1900 us (full forward), newtons.
    pub forward_max_n: f64,
    /// Thrust magnitude at 1100 us (full reverse), newtons.
    pub reverse_max_n: f64,
    /// Half width of the ESC dead band around 1500 us: no thrust for |pwm - 1500| <= this.
    pub dead_band_half_us: f64,
    /// Time constant of the first-order lag from commanded to delivered thrust, seconds
    /// (T200 spin-up takes about 0.15-0.2 s, i.e. 1.5-2 time constants).
    pub time_constant_s: f64,
}

impl Default for ThrusterConfig {
    fn default() -> Self {
        Self {
            forward_max_n: 51.4,
            reverse_max_n: 39.9,
            dead_band_half_us: 28.0,
            time_constant_s: 0.1,
        }
    }
}

impl ThrusterConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let newtons = "a positive number of newtons";
        Checks::new("vehicle.thruster")
            .positive("forward_max_n", self.forward_max_n, newtons)
            .positive("reverse_max_n", self.reverse_max_n, newtons)
            .range("dead_band_half_us", self.dead_band_half_us, 0.0..400.0, "0 <= value < 400")
            .non_negative("time_constant_s", self.time_constant_s, "a non-negative number of seconds")
            .done()
    }

    /// Steady-state thrust (N, signed: positive pushes along the thruster's direction)
    /// for a PWM pulse width. Zero inside the dead band, quadratic in (pwm - 1500) / 400
    /// outside it, saturating at 1100 / 1900.
    pub fn steady_thrust_n(&self, pwm_us: f64) -> f64 {
        if !pwm_us.is_finite() {
            return 0.0;
        }
        let d = (pwm_us - 1500.0).clamp(-400.0, 400.0);
        if d.abs() <= self.dead_band_half_us {
            return 0.0;
        }
        let u = d / 400.0;
        if u > 0.0 {
            self.forward_max_n * u * u
        } else {
            -self.reverse_max_n * u * u
        }
    }
}

/// One thruster's state: the thrust it delivers now.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Thruster {
    thrust_n: f64,
}

impl Thruster {
    /// Thrust delivered now, newtons (signed).
    pub fn thrust_n(&self) -> f64 {
        self.thrust_n
    }

    /// Advance by `dt_s` with the given PWM command; returns the delivered thrust.
    /// Exact discretisation of the first-order lag, so any step size is stable.
    pub fn step(&mut self, cfg: &ThrusterConfig, pwm_us: f64, dt_s: f64) -> f64 {
        let target = cfg.steady_thrust_n(pwm_us);
        if cfg.time_constant_s <= 0.0 {
            self.thrust_n = target;
        } else {
            let a = 1.0 - (-dt_s.max(0.0) / cfg.time_constant_s).exp();
            self.thrust_n += a * (target - self.thrust_n);
        }
        self.thrust_n
    }

    pub fn reset(&mut self) {
        self.thrust_n = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dead_band_gives_no_thrust() {
        let c = ThrusterConfig::default();
        for pwm in [1472.0, 1480.0, 1500.0, 1520.0, 1528.0] {
            assert_eq!(c.steady_thrust_n(pwm), 0.0, "pwm {pwm}");
        }
        assert!(c.steady_thrust_n(1530.0) > 0.0);
        assert!(c.steady_thrust_n(1470.0) < 0.0);
    }

    #[test]
    fn forward_stronger_than_reverse_and_saturates() {
        let c = ThrusterConfig::default();
        assert!((c.steady_thrust_n(1900.0) - 51.4).abs() < 1e-9);
        assert!((c.steady_thrust_n(1100.0) + 39.9).abs() < 1e-9);
        assert_eq!(c.steady_thrust_n(2100.0), c.steady_thrust_n(1900.0));
        assert!(c.steady_thrust_n(1700.0) > -c.steady_thrust_n(1300.0));
        // Quadratic: half stick gives a quarter of full thrust.
        assert!((c.steady_thrust_n(1700.0) - 51.4 / 4.0).abs() < 1e-9);
        assert_eq!(c.steady_thrust_n(f64::NAN), 0.0);
    }

    #[test]
    fn lag_is_first_order() {
        let c = ThrusterConfig::default();
        let mut t = Thruster::default();
        let dt = 0.0025;
        let n = (c.time_constant_s / dt).round() as usize;
        for _ in 0..n {
            t.step(&c, 1900.0, dt);
        }
        // After one time constant: 1 - 1/e of the target.
        let frac = t.thrust_n() / 51.4;
        assert!((frac - (1.0 - (-1.0f64).exp())).abs() < 0.01, "{frac}");
        for _ in 0..10 * n {
            t.step(&c, 1900.0, dt);
        }
        assert!((t.thrust_n() - 51.4).abs() < 0.01);
    }

    mod laws {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            /// More pulse width never gives less thrust, and thrust stays within the
            /// published forward / reverse limits.
            #[test]
            fn thrust_is_monotone_and_bounded(a in 900.0f64..2100.0, b in 900.0f64..2100.0) {
                let c = ThrusterConfig::default();
                let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
                prop_assert!(c.steady_thrust_n(lo) <= c.steady_thrust_n(hi));
                let t = c.steady_thrust_n(a);
                prop_assert!((-c.reverse_max_n..=c.forward_max_n).contains(&t));
            }

            /// The lag never overshoots: delivered thrust stays between the start and the
            /// target.
            #[test]
            fn lag_never_overshoots(pwm in 1100.0f64..1900.0, dt in 1e-4f64..0.5) {
                let c = ThrusterConfig::default();
                let mut t = Thruster::default();
                let target = c.steady_thrust_n(pwm);
                for _ in 0..50 {
                    let v = t.step(&c, pwm, dt);
                    prop_assert!(v.abs() <= target.abs() + 1e-12);
                    prop_assert!(v * target >= 0.0);
                }
            }
        }
    }
}
