//! Standing disturbances and model errors of the simulated vehicle: tether drag, a
//! constant external force and moment, and the deliberate model errors of the robustness
//! sweep (thrust scale, buoyancy offset).
//!
//! Tether model (quasi-static, no tether dynamics): the tether runs straight from a fixed
//! point at the surface to the attachment point on the vehicle, and only the flow across
//! it (horizontal, world frame) loads it, as on a cylinder in cross flow:
//! `q(s) = 1/2 rho C_d d |u(s)| u(s)` per metre, with `u(s) = water - s * vehicle` the
//! relative velocity at fraction `s` of the way from the surface (the surface end is
//! still, the vehicle end moves with the vehicle). A line pinned at both ends carries the
//! share `integral of s q(s) ds` of that load at the vehicle end (moment balance about
//! the surface end), times the tether length. Drag coefficient: about 1.2 for a smooth
//! circular cylinder at sub-critical Reynolds numbers (Hoerner, *Fluid-Dynamic Drag*,
//! 1965, ch. 3; 1.0-1.2 at the Re 760-7600 of a 7.6 mm tether at 0.1-1 m/s). Diameter:
//! Blue Robotics' Fathom ROV Tether, 7.6 mm (docs.bluerobotics.com/fathom-r2,
//! specification table). The attachment point defaults to the BlueROV2's tether thimble
//! at the rear of the frame, above the centre of gravity.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use markhold_config::{Checks, ConfigError};

/// Points of the midpoint rule along the tether (exact to 0.3 % for the quadratic load).
const TETHER_POINTS: usize = 16;

/// `[vehicle.tether]`: present = the vehicle drags a tether.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TetherConfig {
    /// Tether in the water, from the surface to the vehicle, metres.
    pub length_m: f64,
    /// Outer diameter, metres (Fathom ROV Tether: 7.6 mm).
    pub diameter_m: f64,
    /// Cross-flow drag coefficient of the tether (smooth cylinder: about 1.2).
    pub drag_coefficient: f64,
    /// Where the tether is attached, body FRD from the centre of gravity, metres.
    pub attachment_m: [f64; 3],
}

impl Default for TetherConfig {
    fn default() -> Self {
        Self {
            length_m: 25.0,
            diameter_m: 0.0076,
            drag_coefficient: 1.2,
            attachment_m: [-0.22, 0.0, -0.1],
        }
    }
}

impl TetherConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("vehicle.tether")
            .finite_range("length_m", self.length_m, 0.0..=10_000.0, "0..=10000 m")
            .finite_range("diameter_m", self.diameter_m, 0.0..=0.1, "0..=0.1 m (a 7.6 mm tether is 0.0076)")
            .finite_range("drag_coefficient", self.drag_coefficient, 0.0..=5.0, "0..=5 (a smooth cylinder: about 1.2)")
            .each_finite("attachment_m", &self.attachment_m, "finite numbers")
            .each("attachment_m", &self.attachment_m, -2.0..=2.0, "within 2 m of the centre of gravity")
            .done()
    }

    /// Force the tether pulls on the vehicle with, world NED, newtons, given the water
    /// velocity and the vehicle's velocity (world NED, m/s) and the site's water density.
    pub fn force_world_n(
        &self,
        water_mps: &Vector3<f64>,
        vehicle_mps: &Vector3<f64>,
        density_kg_m3: f64,
    ) -> Vector3<f64> {
        let k = 0.5 * density_kg_m3 * self.drag_coefficient * self.diameter_m;
        let mut f = Vector3::zeros();
        for i in 0..TETHER_POINTS {
            let s = (i as f64 + 0.5) / TETHER_POINTS as f64;
            let mut u = water_mps - s * vehicle_mps;
            u.z = 0.0;
            f += s * k * u.norm() * u;
        }
        f * (self.length_m / TETHER_POINTS as f64)
    }
}

/// `[vehicle.model_error]`: how the simulated vehicle differs from its published model
/// (what the robustness sweep varies).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelError {
    /// Factor on every thruster's delivered thrust (1 = the thruster model).
    pub thrust_scale: f64,
    /// Added to the buoyancy, newtons (+ more buoyant).
    pub buoyancy_offset_n: f64,
}

impl Default for ModelError {
    fn default() -> Self {
        Self {
            thrust_scale: 1.0,
            buoyancy_offset_n: 0.0,
        }
    }
}

impl ModelError {
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("vehicle.model_error")
            .finite_range("thrust_scale", self.thrust_scale, 0.0..=2.0, "0..=2")
            .finite_range(
                "buoyancy_offset_n",
                self.buoyancy_offset_n,
                -100.0..=100.0,
                "-100..=100 N",
            )
            .done()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn still_vehicle_carries_half_the_tether_drag() {
        let t = TetherConfig::default();
        let w = Vector3::new(0.1, 0.0, 0.05);
        let f = t.force_world_n(&w, &Vector3::zeros(), 1000.0);
        // Uniform load q L, half of it at each end; vertical flow does not load it.
        let q = 0.5 * 1000.0 * 1.2 * 0.0076 * 0.1 * 0.1;
        let expect = 0.5 * q * t.length_m;
        assert!((f.x - expect).abs() < 1e-9 * expect, "{f:?} vs {expect}");
        assert_eq!(f.y, 0.0);
        assert_eq!(f.z, 0.0);
    }

    #[test]
    fn moving_vehicle_in_still_water_is_held_back() {
        let t = TetherConfig::default();
        let v = Vector3::new(0.0, 0.3, 0.0);
        let f = t.force_world_n(&Vector3::zeros(), &v, 1000.0);
        // Exact: 1/2 rho Cd d L v^2 integral of s^3 ds = ... / 4.
        let expect = -0.5 * 1000.0 * 1.2 * 0.0076 * t.length_m * 0.09 / 4.0;
        assert!(
            (f.y - expect).abs() < 0.01 * expect.abs(),
            "{f:?} vs {expect}"
        );
    }

    #[test]
    fn bad_values_name_the_key() {
        let t = TetherConfig {
            diameter_m: -0.1,
            ..TetherConfig::default()
        };
        let e = t.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.tether.diameter_m"), "{e}");
        let m = ModelError {
            thrust_scale: f64::NAN,
            ..ModelError::default()
        };
        let e = m.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.model_error.thrust_scale"), "{e}");
    }
}
