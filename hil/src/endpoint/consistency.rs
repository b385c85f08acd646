//! Is the covariance the vehicle receives with each vision estimate consistent with the
//! estimate's true error? The normalised estimation error squared (NEES) of each
//! VISION_POSITION_ESTIMATE against the simulated vehicle's true pose in the same frame:
//! position (3 degrees of freedom) and yaw (1). A consistent covariance gives NEES
//! distributed chi-square with that many degrees of freedom: mean 3 (position) and 1
//! (yaw), 95 % of frames under the 95 % quantile.

use markhold_geometry::stats::{CHI2_95_DOF1, CHI2_95_DOF3};
use nalgebra::{Isometry3, Matrix3, Vector3};
use serde::Serialize;

/// A truth stamp within this of the estimate's stamp is the pose the estimate was
/// measured at (the HIL renders a frame at a physics step; the stamp is in microseconds).
const STAMP_MATCH_S: f64 = 1e-3;

/// NEES of the vision estimates received so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct VisionNees {
    /// Estimates with a covariance compared with the truth.
    pub frames: u64,
    /// Estimates without a covariance (NaN first element) or with one that is not
    /// positive definite.
    pub without_covariance: u64,
    /// Estimates whose stamp matched no truth sample (not compared).
    pub unmatched: u64,
    pub pos_nees_sum: f64,
    pub pos_inside_95: u64,
    pub yaw_nees_sum: f64,
    pub yaw_inside_95: u64,
}

impl VisionNees {
    /// Mean position NEES (3 dof; 3 when consistent).
    pub fn pos_mean(&self) -> f64 {
        self.pos_nees_sum / self.frames.max(1) as f64
    }
    /// Mean yaw NEES (1 dof; 1 when consistent).
    pub fn yaw_mean(&self) -> f64 {
        self.yaw_nees_sum / self.frames.max(1) as f64
    }
    /// Fraction of frames whose position NEES is under chi-square(3)'s 95 % quantile.
    pub fn pos_inside_fraction(&self) -> f64 {
        self.pos_inside_95 as f64 / self.frames.max(1) as f64
    }
    /// Fraction of frames whose yaw NEES is under chi-square(1)'s 95 % quantile.
    pub fn yaw_inside_fraction(&self) -> f64 {
        self.yaw_inside_95 as f64 / self.frames.max(1) as f64
    }
}

/// The check as the endpoint runs it: the vision frame in the world, the latest truth.
#[derive(Debug, Clone, Default)]
pub(crate) struct Consistency {
    /// `t_world_vision`: where the estimates' frame lies in the simulated world (none:
    /// the check is off).
    t_world_vision: Option<Isometry3<f64>>,
    /// The vehicle's true pose at the last physics step (time, `t_world_vehicle`).
    truth: Option<(f64, Isometry3<f64>)>,
    nees: VisionNees,
}

impl Consistency {
    pub(crate) fn set_frame(&mut self, t_world_vision: Isometry3<f64>) {
        self.t_world_vision = Some(t_world_vision);
    }

    pub(crate) fn set_truth(&mut self, time_s: f64, t_world_vehicle: &Isometry3<f64>) {
        self.truth = Some((time_s, *t_world_vehicle));
    }

    pub(crate) fn nees(&self) -> Option<VisionNees> {
        self.t_world_vision.map(|_| self.nees)
    }

    /// One estimate: stamp, (x, y, z, roll, pitch, yaw) in the vision frame and MAVLink's
    /// 21-element covariance (upper triangle, row-major).
    pub(crate) fn observe(&mut self, stamp_s: f64, x: [f64; 6], cov: &[f32; 21]) {
        let Some(t_world_vision) = self.t_world_vision else {
            return;
        };
        // Diagonal entries of the position block at 0, 6, 11; yaw at 20.
        let p = Matrix3::new(
            f64::from(cov[0]),
            f64::from(cov[1]),
            f64::from(cov[2]),
            f64::from(cov[1]),
            f64::from(cov[6]),
            f64::from(cov[7]),
            f64::from(cov[2]),
            f64::from(cov[7]),
            f64::from(cov[11]),
        );
        let var_yaw = f64::from(cov[20]);
        let Some(chol) = p.cholesky().filter(|_| var_yaw > 0.0) else {
            self.nees.without_covariance += 1;
            return;
        };
        let Some((_, truth)) = self
            .truth
            .filter(|(t, _)| (t - stamp_s).abs() <= STAMP_MATCH_S)
        else {
            self.nees.unmatched += 1;
            return;
        };
        let true_pose = t_world_vision.inverse() * truth;
        let e = Vector3::new(x[0], x[1], x[2]) - true_pose.translation.vector;
        let pos = e.dot(&chol.solve(&e));
        let (_, _, true_yaw) = true_pose.rotation.euler_angles();
        let dyaw = (x[5] - true_yaw + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        let yaw = dyaw * dyaw / var_yaw;
        tracing::debug!(
            stamp_s,
            ex = e.x,
            ey = e.y,
            ez = e.z,
            sx = p[(0, 0)].sqrt(),
            sy = p[(1, 1)].sqrt(),
            sz = p[(2, 2)].sqrt(),
            dyaw,
            syaw = var_yaw.sqrt(),
            pos,
            "vision nees"
        );
        let n = &mut self.nees;
        n.frames += 1;
        n.pos_nees_sum += pos;
        n.yaw_nees_sum += yaw;
        n.pos_inside_95 += u64::from(pos <= CHI2_95_DOF3);
        n.yaw_inside_95 += u64::from(yaw <= CHI2_95_DOF1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nees_of_known_errors() {
        let mut c = Consistency::default();
        // Off until the frame is known.
        c.observe(0.0, [0.0; 6], &[0.0; 21]);
        assert!(c.nees().is_none());
        // Vision frame 5 m north of the world origin; truth at the world origin, yaw 0.
        c.set_frame(Isometry3::translation(5.0, 0.0, 0.0));
        c.set_truth(1.0, &Isometry3::identity());
        // Variances 0.01 m^2 on each axis and 0.04 rad^2 in yaw; error (0.1, 0.2, 0)
        // and yaw 0.2 rad: position NEES 1 + 4 = 5, yaw NEES 1.
        let mut cov = [0.0f32; 21];
        for (i, v) in [
            (0, 0.01),
            (6, 0.01),
            (11, 0.01),
            (15, 1.0),
            (18, 1.0),
            (20, 0.04),
        ] {
            cov[i] = v;
        }
        c.observe(1.0, [-5.0 + 0.1, 0.2, 0.0, 0.0, 0.0, 0.2], &cov);
        let n = c.nees().unwrap();
        assert_eq!((n.frames, n.unmatched, n.without_covariance), (1, 0, 0));
        assert!((n.pos_mean() - 5.0).abs() < 1e-4, "{n:?}");
        assert!((n.yaw_mean() - 1.0).abs() < 1e-4, "{n:?}");
        assert_eq!((n.pos_inside_95, n.yaw_inside_95), (1, 1));
        // A stamp from another time is not compared; NaN means no covariance.
        c.observe(1.5, [0.0; 6], &cov);
        cov[0] = f32::NAN;
        c.observe(1.0, [0.0; 6], &cov);
        let n = c.nees().unwrap();
        assert_eq!((n.frames, n.unmatched, n.without_covariance), (1, 1, 1));
    }
}
