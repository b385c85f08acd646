//! How well a run held its station, in the figures that compare two autopilots flying
//! the same keeper: position RMS and final error (as the HIL summary), the heading's
//! standard deviation, the spread of the yaw and heave commands, and how often the
//! thrusters reverse.

use markhold_hil::Truth;
use nalgebra::Isometry3;
use serde::Serialize;

use markhold_core::pipeline::FrameRecord;

/// A thruster PWM within this of 1500 us counts as stopped (the T200's dead band is
/// about +-25 us): a reversal is a change between the two sides of it.
const REVERSAL_BAND_US: i32 = 25;

/// The figures of one run (all over its last half, as the summary's position RMS).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HoldFigures {
    /// Position error RMS against the station, m.
    pub position_rms_m: f64,
    /// Position error at the last frame, m.
    pub final_error_m: f64,
    /// Standard deviation of the heading error, degrees.
    pub heading_std_deg: f64,
    /// Standard deviation of the yaw and heave efforts the keeper sent.
    pub yaw_effort_std: f64,
    pub heave_effort_std: f64,
    /// Thruster reversals (PWM crossing the dead band from one side to the other), per
    /// second, summed over the thrusters.
    pub thruster_reversals_per_s: f64,
    /// Frames in which the marker was detected, fraction.
    pub detection_rate: f64,
}

/// Per-frame series of a run.
pub struct HoldSeries {
    t_world_marker: Isometry3<f64>,
    t_marker_station: Isometry3<f64>,
    time_s: Vec<f64>,
    pos_err_m: Vec<f64>,
    yaw_err_deg: Vec<f64>,
    yaw_effort: Vec<f64>,
    heave_effort: Vec<f64>,
    pwm: Vec<[u16; 8]>,
    detected: Vec<bool>,
}

impl HoldSeries {
    pub fn new(
        frames: usize,
        t_world_marker: Isometry3<f64>,
        t_marker_station: Isometry3<f64>,
    ) -> Self {
        Self {
            t_world_marker,
            t_marker_station,
            time_s: Vec::with_capacity(frames),
            pos_err_m: Vec::with_capacity(frames),
            yaw_err_deg: Vec::with_capacity(frames),
            yaw_effort: Vec::with_capacity(frames),
            heave_effort: Vec::with_capacity(frames),
            pwm: Vec::with_capacity(frames),
            detected: Vec::with_capacity(frames),
        }
    }

    pub fn push(&mut self, rec: &FrameRecord, truth: &Truth) {
        let t_marker_vehicle = self.t_world_marker.inverse() * truth.t_world_vehicle;
        let err = self.t_marker_station.inverse() * t_marker_vehicle;
        self.time_s.push(truth.time_s);
        self.pos_err_m.push(err.translation.vector.norm());
        self.yaw_err_deg
            .push(err.rotation.euler_angles().2.to_degrees());
        self.yaw_effort.push(rec.effort.yaw);
        self.heave_effort.push(rec.effort.heave);
        self.pwm.push(truth.pwm);
        self.detected.push(rec.detected);
    }

    pub fn figures(&self) -> HoldFigures {
        let n = self.time_s.len();
        let h = n / 2;
        let span = match (self.time_s.get(h), self.time_s.last()) {
            (Some(a), Some(b)) if b > a => b - a,
            _ => f64::NAN,
        };
        HoldFigures {
            position_rms_m: super::summary::rms(&self.pos_err_m[h..]),
            final_error_m: self.pos_err_m.last().copied().unwrap_or(f64::NAN),
            heading_std_deg: std_dev(&self.yaw_err_deg[h..]),
            yaw_effort_std: std_dev(&self.yaw_effort[h..]),
            heave_effort_std: std_dev(&self.heave_effort[h..]),
            thruster_reversals_per_s: reversals(&self.pwm[h..]) as f64 / span,
            detection_rate: self.detected.iter().filter(|d| **d).count() as f64 / n.max(1) as f64,
        }
    }
}

/// Population standard deviation (NaN for none).
pub fn std_dev(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
}

/// Thruster reversals in a PWM series: per thruster, the changes of side (above or below
/// the dead band) between successive frames outside it.
pub fn reversals(pwm: &[[u16; 8]]) -> u64 {
    let mut count = 0;
    for m in 0..8 {
        let mut side = 0i32;
        for p in pwm {
            let d = i32::from(p[m]) - 1500;
            let s = if d > REVERSAL_BAND_US {
                1
            } else if d < -REVERSAL_BAND_US {
                -1
            } else {
                0
            };
            if s != 0 {
                if side != 0 && s != side {
                    count += 1;
                }
                side = s;
            }
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reversals_count_side_changes_across_the_band() {
        let mut a = [[1500u16; 8]; 6];
        // Thruster 0: +, stop, -, - , +, inside band: two reversals.
        for (i, p) in [1560, 1500, 1440, 1430, 1570, 1510].iter().enumerate() {
            a[i][0] = *p;
        }
        // Thruster 3: wobbling inside the band: none.
        for (i, p) in [1510, 1490, 1520, 1480, 1500, 1515].iter().enumerate() {
            a[i][3] = *p;
        }
        assert_eq!(reversals(&a), 2);
    }

    #[test]
    fn std_dev_of_a_known_series() {
        assert!((std_dev(&[1.0, 3.0, 1.0, 3.0]) - 1.0).abs() < 1e-12);
        assert!(std_dev(&[]).is_nan());
    }
}
