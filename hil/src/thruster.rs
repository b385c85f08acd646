//! Blue Robotics T200 thruster from Blue Robotics' published bollard-pull table ("T200
//! Public Performance Data 10-20V (September 2019)", `hil/data/t200-*.csv`): thrust and
//! current drawn against PWM at 10, 12, 14, 16, 18 and 20 V, interpolated linearly in PWM
//! (the table's 4 us rows) and in supply voltage, with the table's own dead band (no
//! thrust inside it), the forward/reverse asymmetry of the propeller, and a first-order
//! spin-up lag.
//!
//! `dead_band_half_us` widens or narrows the table's dead band: the model's band at every
//! voltage is the table's band there plus `dead_band_half_us - 30` (30 us is the table as
//! published: its last zero-thrust rows are 32 us from 1500 at 14 V and 28 us at 16 V, so
//! about 30 us at a 4S pack's 14.8 V). Outside the band the table's curve is stretched
//! linearly from the band edge to full throttle, so full-throttle thrust is unchanged.

use std::sync::OnceLock;

use serde::{Deserialize, Serialize};

use markhold_config::{Checks, ConfigError};

/// `dead_band_half_us` that leaves the table's dead band as published, us.
pub const TABLE_DEAD_BAND_US: f64 = 30.0;
/// Newtons per kilogram-force.
const KGF_N: f64 = 9.80665;
/// Supply voltages of the published table, volts.
pub const TABLE_VOLTS: [f64; 6] = [10.0, 12.0, 14.0, 16.0, 18.0, 20.0];
const ROWS: usize = 201;
const CSV: [&str; 6] = [
    include_str!("../data/t200-10v.csv"),
    include_str!("../data/t200-12v.csv"),
    include_str!("../data/t200-14v.csv"),
    include_str!("../data/t200-16v.csv"),
    include_str!("../data/t200-18v.csv"),
    include_str!("../data/t200-20v.csv"),
];

/// One sheet of the table: rows at 1100, 1104, .. 1900 us.
#[derive(Debug, Clone, PartialEq)]
pub struct T200Sheet {
    /// Supply voltage, volts.
    pub volts: f64,
    /// Thrust, newtons (negative = reverse), per row.
    pub thrust_n: [f64; ROWS],
    /// Current drawn, amperes, per row.
    pub current_a: [f64; ROWS],
    /// Offset from 1500 us of the last zero-thrust row above (index 0) and below
    /// (index 1) neutral, us.
    pub band_us: [f64; 2],
}

/// The six sheets of the published table.
#[derive(Debug, Clone, PartialEq)]
pub struct T200Table {
    pub sheets: [T200Sheet; 6],
}

/// PWM of row `i`.
pub fn row_pwm(i: usize) -> f64 {
    1100.0 + 4.0 * i as f64
}

fn parse_sheet(text: &str, volts: f64) -> Result<T200Sheet, String> {
    let mut thrust_n = [0.0; ROWS];
    let mut current_a = [0.0; ROWS];
    let mut n = 0;
    for line in text.lines() {
        if line.starts_with('#') || line.starts_with("pwm_us") || line.trim().is_empty() {
            continue;
        }
        let f: Vec<f64> = line
            .split(',')
            .map(|s| {
                s.trim()
                    .parse::<f64>()
                    .map_err(|e| format!("{line:?}: {e}"))
            })
            .collect::<Result<_, _>>()?;
        if f.len() != 7 || n >= ROWS || f[0] != row_pwm(n) || f[3] != volts {
            return Err(format!("unexpected row {n} at {volts} V: {line:?}"));
        }
        current_a[n] = f[2];
        thrust_n[n] = f[5] * KGF_N;
        n += 1;
    }
    if n != ROWS {
        return Err(format!("{n} rows at {volts} V, expected {ROWS}"));
    }
    let mid = ROWS / 2;
    let last_zero = |step: isize| {
        let mut i = mid as isize;
        while (0..ROWS as isize).contains(&(i + step)) && thrust_n[(i + step) as usize] == 0.0 {
            i += step;
        }
        (row_pwm(i as usize) - 1500.0).abs()
    };
    Ok(T200Sheet {
        volts,
        thrust_n,
        current_a,
        band_us: [last_zero(1), last_zero(-1)],
    })
}

impl T200Table {
    /// Parse the compiled-in CSV files.
    pub fn parse() -> Result<Self, String> {
        let mut sheets = Vec::with_capacity(6);
        for (text, v) in CSV.iter().zip(TABLE_VOLTS) {
            sheets.push(parse_sheet(text, v)?);
        }
        let sheets: [T200Sheet; 6] = sheets
            .try_into()
            .map_err(|_| "six sheets expected".to_string())?;
        Ok(Self { sheets })
    }

    /// Sheets bracketing `volts` and the weight of the upper one (clamped to 10..20 V:
    /// the table is never extrapolated).
    fn bracket(&self, volts: f64) -> (usize, f64) {
        let v = if volts.is_finite() {
            volts.clamp(TABLE_VOLTS[0], TABLE_VOLTS[5])
        } else {
            TABLE_VOLTS[0]
        };
        let i = TABLE_VOLTS
            .iter()
            .rposition(|&t| t <= v)
            .unwrap_or(0)
            .min(4);
        (
            i,
            (v - TABLE_VOLTS[i]) / (TABLE_VOLTS[i + 1] - TABLE_VOLTS[i]),
        )
    }

    /// Table value at `pwm_us` (interpolated between rows) and `volts` (between sheets).
    fn lookup(&self, column: fn(&T200Sheet) -> &[f64; ROWS], pwm_us: f64, volts: f64) -> f64 {
        let x = ((pwm_us.clamp(1100.0, 1900.0) - 1100.0) / 4.0).min((ROWS - 1) as f64);
        let r = (x.floor() as usize).min(ROWS - 2);
        let fr = x - r as f64;
        let (s, fs) = self.bracket(volts);
        let at = |k: usize| {
            let c = column(&self.sheets[k]);
            c[r] + fr * (c[r + 1] - c[r])
        };
        at(s) + fs * (at(s + 1) - at(s))
    }

    /// The table's dead band at `volts` for forward (`true`) or reverse, us from 1500.
    pub fn band_us(&self, volts: f64, forward: bool) -> f64 {
        let k = usize::from(!forward);
        let (s, fs) = self.bracket(volts);
        let (a, b) = (self.sheets[s].band_us[k], self.sheets[s + 1].band_us[k]);
        a + fs * (b - a)
    }
}

/// The published table, parsed on first use.
pub fn t200() -> &'static T200Table {
    static TABLE: OnceLock<T200Table> = OnceLock::new();
    // The CSV files are compiled in and checked by this module's tests.
    TABLE.get_or_init(|| T200Table::parse().expect("the compiled-in T200 table parses"))
}

/// Static and dynamic parameters of one T200.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ThrusterConfig {
    /// Half width of the ESC dead band around 1500 us at a 4S pack's voltage: no thrust
    /// for |pwm - 1500| <= this. 30 (the default) is the published table's own band; the
    /// difference to 30 is added to the table's band at every voltage.
    pub dead_band_half_us: f64,
    /// Time constant of the first-order lag from commanded to delivered thrust, seconds
    /// (T200 spin-up takes about 0.15-0.2 s, i.e. 1.5-2 time constants).
    pub time_constant_s: f64,
}

impl Default for ThrusterConfig {
    fn default() -> Self {
        Self {
            dead_band_half_us: TABLE_DEAD_BAND_US,
            time_constant_s: 0.1,
        }
    }
}

impl ThrusterConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("vehicle.thruster")
            .range("dead_band_half_us", self.dead_band_half_us, 0.0..200.0, "0 <= value < 200")
            .non_negative("time_constant_s", self.time_constant_s, "a non-negative number of seconds")
            .done()
    }

    /// The PWM whose table row describes `pwm_us` once the dead band is moved by
    /// `dead_band_half_us - 30`; `None` inside the band.
    fn table_pwm(&self, pwm_us: f64, volts: f64) -> Option<f64> {
        if !pwm_us.is_finite() {
            return None;
        }
        let d = (pwm_us - 1500.0).clamp(-400.0, 400.0);
        let table = t200();
        let b_tab = table.band_us(volts, d > 0.0);
        let b = (b_tab + self.dead_band_half_us - TABLE_DEAD_BAND_US).clamp(0.0, 399.0);
        if d.abs() <= b {
            return None;
        }
        let dt = b_tab + (d.abs() - b) * (400.0 - b_tab) / (400.0 - b);
        Some(1500.0 + dt.min(400.0).copysign(d))
    }

    /// Steady-state thrust (N, signed: positive pushes along the thruster's direction)
    /// for a PWM pulse width at a supply voltage: the published table, interpolated.
    pub fn steady_thrust_n(&self, pwm_us: f64, volts: f64) -> f64 {
        self.table_pwm(pwm_us, volts)
            .map_or(0.0, |p| t200().lookup(|s| &s.thrust_n, p, volts))
    }

    /// Current the thruster's ESC draws at steady state, amperes (the table's column).
    pub fn current_a(&self, pwm_us: f64, volts: f64) -> f64 {
        self.table_pwm(pwm_us, volts)
            .map_or(0.0, |p| t200().lookup(|s| &s.current_a, p, volts))
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

    /// Advance by `dt_s` with the given PWM command at supply voltage `volts`; returns the
    /// delivered thrust. Exact discretisation of the first-order lag, so any step size is
    /// stable.
    pub fn step(&mut self, cfg: &ThrusterConfig, pwm_us: f64, volts: f64, dt_s: f64) -> f64 {
        let target = cfg.steady_thrust_n(pwm_us, volts);
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

    /// The published rows of one sheet as (pwm, thrust N, current A), read again from the
    /// CSV text independently of the parser's arrays.
    fn published(volts: f64) -> Vec<(f64, f64, f64)> {
        let k = TABLE_VOLTS.iter().position(|&v| v == volts).unwrap();
        CSV[k]
            .lines()
            .filter(|l| l.starts_with(|c: char| c.is_ascii_digit()))
            .map(|l| {
                let f: Vec<f64> = l.split(',').map(|s| s.parse().unwrap()).collect();
                (f[0], f[5] * KGF_N, f[2])
            })
            .collect()
    }

    #[test]
    fn the_table_parses_with_its_published_extremes() {
        let t = T200Table::parse().unwrap();
        // Full throttle forward / reverse per sheet, kgf, as published.
        let fwd = [2.93, 3.71, 4.53, 5.25, 6.02, 6.72];
        let rev = [-2.31, -2.92, -3.52, -4.07, -4.59, -5.04];
        for (k, s) in t.sheets.iter().enumerate() {
            let max = s.thrust_n.iter().cloned().fold(f64::MIN, f64::max) / KGF_N;
            let min = s.thrust_n.iter().cloned().fold(f64::MAX, f64::min) / KGF_N;
            assert!((max - fwd[k]).abs() < 0.006, "{} V: {max}", s.volts);
            assert!((min - rev[k]).abs() < 0.006, "{} V: {min}", s.volts);
        }
        // Dead bands (last zero rows): 1468..1532 at 14 V, 1472..1528 at 16 V.
        assert_eq!(t.sheets[2].band_us, [32.0, 32.0]);
        assert_eq!(t.sheets[3].band_us, [28.0, 28.0]);
    }

    #[test]
    fn the_t200_model_reproduces_the_published_table_within_5_percent_at_12_14_and_16_v() {
        for volts in [12.0, 14.0, 16.0] {
            // The table's own dead band at this voltage, in the model's terms.
            let c = ThrusterConfig::default();
            let mut checked = 0;
            for (pwm, thrust, current) in published(volts) {
                if thrust == 0.0 {
                    // Inside the dead band: no thrust, no current.
                    assert_eq!(c.steady_thrust_n(pwm, volts), 0.0, "{pwm} us at {volts} V");
                    continue;
                }
                let m = c.steady_thrust_n(pwm, volts);
                assert!(
                    (m - thrust).abs() <= 0.05 * thrust.abs(),
                    "{pwm} us at {volts} V: model {m:.3} N, table {thrust:.3} N"
                );
                let i = c.current_a(pwm, volts);
                assert!(
                    (i - current).abs() <= 0.05 * current.abs() + 1e-9,
                    "{pwm} us at {volts} V: model {i:.3} A, table {current:.3} A"
                );
                checked += 1;
            }
            // Both directions: every row outside the dead band (201 rows, 15-17 inside).
            assert!(checked >= 180, "{checked} rows at {volts} V");
        }
    }

    #[test]
    fn between_sheets_thrust_lies_between_the_neighbouring_voltages() {
        let c = ThrusterConfig::default();
        for pwm in [1150.0, 1300.0, 1420.0, 1580.0, 1700.0, 1900.0] {
            let (lo, hi) = (c.steady_thrust_n(pwm, 14.0), c.steady_thrust_n(pwm, 16.0));
            let mid = c.steady_thrust_n(pwm, 14.8);
            assert!(
                mid.abs() >= lo.abs() && mid.abs() <= hi.abs(),
                "{pwm}: {lo} {mid} {hi}"
            );
        }
        // Beyond the table: clamped, never extrapolated.
        assert_eq!(
            c.steady_thrust_n(1900.0, 25.0),
            c.steady_thrust_n(1900.0, 20.0)
        );
        assert_eq!(
            c.steady_thrust_n(1900.0, 6.0),
            c.steady_thrust_n(1900.0, 10.0)
        );
    }

    #[test]
    fn dead_band_half_us_moves_the_band_and_keeps_full_thrust() {
        let wide = ThrusterConfig {
            dead_band_half_us: 45.0,
            ..Default::default()
        };
        let narrow = ThrusterConfig {
            dead_band_half_us: 20.0,
            ..Default::default()
        };
        // At 16 V the table's band is 28 us: 43 us wide, 18 us narrow.
        assert_eq!(wide.steady_thrust_n(1543.0, 16.0), 0.0);
        assert!(wide.steady_thrust_n(1545.0, 16.0) > 0.0);
        assert_eq!(wide.steady_thrust_n(1457.0, 16.0), 0.0);
        assert_eq!(narrow.steady_thrust_n(1518.0, 16.0), 0.0);
        assert!(narrow.steady_thrust_n(1520.0, 16.0) > 0.0);
        assert!(narrow.steady_thrust_n(1480.0, 16.0) < 0.0);
        let d = ThrusterConfig::default();
        for c in [wide, narrow] {
            assert!(
                (c.steady_thrust_n(1900.0, 16.0) - d.steady_thrust_n(1900.0, 16.0)).abs() < 1e-9
            );
            assert!(
                (c.steady_thrust_n(1100.0, 16.0) - d.steady_thrust_n(1100.0, 16.0)).abs() < 1e-9
            );
        }
        assert_eq!(d.steady_thrust_n(f64::NAN, 16.0), 0.0);
    }

    #[test]
    fn lag_is_first_order() {
        let c = ThrusterConfig::default();
        let full = c.steady_thrust_n(1900.0, 16.0);
        let mut t = Thruster::default();
        let dt = 0.0025;
        let n = (c.time_constant_s / dt).round() as usize;
        for _ in 0..n {
            t.step(&c, 1900.0, 16.0, dt);
        }
        // After one time constant: 1 - 1/e of the target.
        let frac = t.thrust_n() / full;
        assert!((frac - (1.0 - (-1.0f64).exp())).abs() < 0.01, "{frac}");
        for _ in 0..10 * n {
            t.step(&c, 1900.0, 16.0, dt);
        }
        assert!((t.thrust_n() - full).abs() < 0.01);
    }

    mod laws {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            /// More pulse width never gives less thrust (the table is monotone to within
            /// its measurement noise of 0.02 kgf), and thrust stays within the table's
            /// forward / reverse extremes at that voltage.
            #[test]
            fn thrust_is_nearly_monotone_and_bounded(
                a in 900.0f64..2100.0, b in 900.0f64..2100.0, v in 10.0f64..20.0
            ) {
                let c = ThrusterConfig::default();
                let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
                prop_assert!(c.steady_thrust_n(lo, v) <= c.steady_thrust_n(hi, v) + 0.25);
                let t = c.steady_thrust_n(a, v);
                prop_assert!(t >= c.steady_thrust_n(1100.0, v) - 0.25);
                prop_assert!(t <= c.steady_thrust_n(1900.0, v) + 0.25);
            }

            /// The lag never overshoots: delivered thrust stays between the start and the
            /// target.
            #[test]
            fn lag_never_overshoots(pwm in 1100.0f64..1900.0, dt in 1e-4f64..0.5) {
                let c = ThrusterConfig::default();
                let mut t = Thruster::default();
                let target = c.steady_thrust_n(pwm, 14.8);
                for _ in 0..50 {
                    let v = t.step(&c, pwm, 14.8, dt);
                    prop_assert!(v.abs() <= target.abs() + 1e-12);
                    prop_assert!(v * target >= 0.0);
                }
            }
        }
    }
}
