//! Pose of a square marker from its four corners: Gauss-Newton refinement of the
//! reprojection error and its covariance.
//!
//! Parameterisation (used by the refinement and every covariance of this crate):
//! `t` is the marker origin in the camera frame, and a rotation error `dtheta` acts on
//! the left, `R = exp([dtheta]x) R_hat`, so it is a small rotation vector expressed in
//! the camera frame. The covariance order is (tx, ty, tz, rx, ry, rz) (docs/frames.md);
//! the step, changes of frame and inversion of such a covariance are markhold-geometry's.

use crate::{distortion, CameraCalibration};
use markhold_geometry::{perturb, skew};
use nalgebra::{Isometry3, Matrix2, Matrix2x3, Matrix6, Point3, SMatrix, Vector2, Vector6};

/// Object points for IPPE_SQUARE in aruco corner order (top-left, top-right,
/// bottom-right, bottom-left; marker y up), for a marker of side `size_m`.
pub fn marker_object_points(size_m: f64) -> [Point3<f64>; 4] {
    let h = size_m / 2.0;
    [
        Point3::new(-h, h, 0.0),
        Point3::new(h, h, 0.0),
        Point3::new(h, -h, 0.0),
        Point3::new(-h, -h, 0.0),
    ]
}

impl CameraCalibration {
    /// Distorted pixel of a normalised image point (x, y) = (X/Z, Y/Z), and the 2x2
    /// Jacobian d(u, v)/d(x, y), in the calibration's lens model ([`crate::distortion`]).
    pub fn distort_with_jacobian(&self, x: f64, y: f64) -> (Vector2<f64>, Matrix2<f64>) {
        let (q, j) = distortion::distort(self.model, &self.dist, x, y);
        let uv = Vector2::new(self.fx * q.x + self.cx, self.fy * q.y + self.cy);
        let j = Matrix2::new(
            self.fx * j[(0, 0)],
            self.fx * j[(0, 1)],
            self.fy * j[(1, 0)],
            self.fy * j[(1, 1)],
        );
        (uv, j)
    }

    /// Pixel of a point in the camera frame (`None` behind the camera).
    pub fn project(&self, p_cam: &Point3<f64>) -> Option<Vector2<f64>> {
        if p_cam.z <= 1e-9 {
            return None;
        }
        Some(
            self.distort_with_jacobian(p_cam.x / p_cam.z, p_cam.y / p_cam.z)
                .0,
        )
    }

    /// Normalised undistorted image point of a pixel (the inverse of the lens model by
    /// Newton's method), `None` where the model cannot be inverted (outside the region
    /// it was calibrated in).
    pub fn try_undistort_pixel(&self, u: f64, v: f64) -> Option<Vector2<f64>> {
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        distortion::undistort(self.model, &self.dist, xd, yd)
    }

    /// [`Self::try_undistort_pixel`], or the pixel's distorted normalised point where the
    /// model cannot be inverted.
    pub fn undistort_pixel(&self, u: f64, v: f64) -> Vector2<f64> {
        self.try_undistort_pixel(u, v)
            .unwrap_or_else(|| Vector2::new((u - self.cx) / self.fx, (v - self.cy) / self.fy))
    }
}

/// Result of refining a pose against observed corners.
#[derive(Debug, Clone, Copy)]
pub struct RefinedPose {
    pub t_cam_marker: Isometry3<f64>,
    /// sqrt(mean over the four corners of |observed - projected|^2), pixels.
    pub reproj_rms_px: f64,
    /// Fisher information J^T Sigma^-1 J of (t, dtheta) at the solution.
    pub info: Matrix6<f64>,
}

impl RefinedPose {
    /// Covariance of (t, dtheta) in the camera frame: the inverse of the information
    /// (first-order propagation of the corner covariance). `None` when degenerate.
    pub fn covariance(&self) -> Option<Matrix6<f64>> {
        let cov = self.info.try_inverse()?;
        // Symmetrise against round-off.
        let cov = (cov + cov.transpose()) * 0.5;
        (cov.iter().all(|v| v.is_finite()) && (0..6).all(|i| cov[(i, i)] > 0.0)).then_some(cov)
    }
}

/// Covariance of four corners with independent noise of `sigma_px` per axis.
pub fn isotropic_corner_cov(sigma_px: f64) -> SMatrix<f64, 8, 8> {
    SMatrix::<f64, 8, 8>::identity() * (sigma_px * sigma_px)
}

/// Residuals (observed - projected) and their Jacobian w.r.t. (dt, dtheta).
fn residuals(
    calib: &CameraCalibration,
    obj: &[Point3<f64>; 4],
    img: &[Vector2<f64>; 4],
    pose: &Isometry3<f64>,
) -> Option<(SMatrix<f64, 8, 1>, SMatrix<f64, 8, 6>)> {
    let mut r = SMatrix::<f64, 8, 1>::zeros();
    let mut j = SMatrix::<f64, 8, 6>::zeros();
    let rot = pose.rotation.to_rotation_matrix();
    for i in 0..4 {
        let rx = rot * obj[i].coords;
        let pc = rx + pose.translation.vector;
        if pc.z <= 1e-9 {
            return None;
        }
        let iz = 1.0 / pc.z;
        let (x, y) = (pc.x * iz, pc.y * iz);
        let (uv, dd) = calib.distort_with_jacobian(x, y);
        let dn_dp = Matrix2x3::new(iz, 0.0, -x * iz, 0.0, iz, -y * iz);
        let duv_dp = dd * dn_dp;
        // d pc / d dt = I, d pc / d dtheta = -[R X]x.
        let duv_dth = duv_dp * (-skew(&rx));
        let e = img[i] - uv;
        r[2 * i] = e.x;
        r[2 * i + 1] = e.y;
        for c in 0..3 {
            j[(2 * i, c)] = duv_dp[(0, c)];
            j[(2 * i + 1, c)] = duv_dp[(1, c)];
            j[(2 * i, 3 + c)] = duv_dth[(0, c)];
            j[(2 * i + 1, 3 + c)] = duv_dth[(1, c)];
        }
    }
    Some((r, j))
}

/// Levenberg-Marquardt on the reprojection error of the four corners weighted by
/// the inverse of `corner_cov` (8x8, order u0 v0 u1 v1 ...), from `init`.
/// Returns `None` when a point falls behind the camera or the system is degenerate.
pub fn refine_pose(
    calib: &CameraCalibration,
    obj: &[Point3<f64>; 4],
    img: &[Vector2<f64>; 4],
    init: &Isometry3<f64>,
    corner_cov: &SMatrix<f64, 8, 8>,
) -> Option<RefinedPose> {
    // Whitening: with Sigma = C C^T, C^-1 r has identity covariance.
    let chol = corner_cov.cholesky()?;
    let white = chol.l().try_inverse()?;
    let residuals = |pose: &Isometry3<f64>| {
        residuals(calib, obj, img, pose).map(|(r, j)| (white * r, white * j, r))
    };
    let mut pose = *init;
    let (mut r, mut j, mut raw) = residuals(&pose)?;
    let mut cost = r.norm_squared();
    let mut lambda = 1e-6;
    for _ in 0..30 {
        let jtj = j.transpose() * j;
        let g = j.transpose() * r;
        let mut a = jtj;
        for d in 0..6 {
            a[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
        }
        // r = observed - f(p): the step solves (J^T J) delta = J^T r.
        let Some(delta) = a.cholesky().map(|c| c.solve(&g)) else {
            lambda *= 10.0;
            continue;
        };
        let cand = perturb(&pose, &delta);
        match residuals(&cand) {
            Some((r2, j2, raw2)) if r2.norm_squared() <= cost => {
                let done =
                    delta.norm() < 1e-12 || cost - r2.norm_squared() < 1e-14 * cost.max(1e-30);
                pose = cand;
                r = r2;
                j = j2;
                raw = raw2;
                cost = r.norm_squared();
                lambda = (lambda * 0.1).max(1e-12);
                if done {
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e6 {
                    break;
                }
            }
        }
    }
    Some(RefinedPose {
        t_cam_marker: pose,
        reproj_rms_px: (raw.norm_squared() / 4.0).sqrt(),
        info: j.transpose() * j,
    })
}

/// One marker's share of a joint pose: its corners as points of the common (site) frame,
/// where they were seen, and the whitening of their covariance (`C^-1` for
/// `Sigma = C C^T`, see [`whitening`]).
#[derive(Debug, Clone, Copy)]
pub struct MarkerCorners {
    pub obj: [Point3<f64>; 4],
    pub img: [Vector2<f64>; 4],
    pub white: SMatrix<f64, 8, 8>,
    /// Corner covariance the weights leave out (clipped edges,
    /// [`crate::corners::EdgeCovariance::clip`]): added to the pose covariance by
    /// [`unweighted_gain`].
    pub clip: SMatrix<f64, 8, 8>,
    /// The clipped edges' common shift
    /// ([`crate::corners::EdgeCovariance::clip_common`]), shared in sign by every marker.
    pub clip_common: SMatrix<f64, 8, 1>,
}

impl Default for MarkerCorners {
    fn default() -> Self {
        Self {
            obj: [Point3::origin(); 4],
            img: [Vector2::zeros(); 4],
            white: SMatrix::identity(),
            clip: SMatrix::zeros(),
            clip_common: SMatrix::zeros(),
        }
    }
}

/// `C^-1` for `corner_cov = C C^T` (Cholesky): whitened residuals have identity
/// covariance. `None` when the covariance is not positive definite.
pub fn whitening(corner_cov: &SMatrix<f64, 8, 8>) -> Option<SMatrix<f64, 8, 8>> {
    corner_cov.cholesky()?.l().try_inverse()
}

/// RMS reprojection error of one marker's four corners under the common-frame pose
/// `t_cam_frame`, pixels (`None`: a corner behind the camera).
pub fn marker_rms_px(
    calib: &CameraCalibration,
    m: &MarkerCorners,
    t_cam_frame: &Isometry3<f64>,
) -> Option<f64> {
    residuals(calib, &m.obj, &m.img, t_cam_frame).map(|(r, _)| (r.norm_squared() / 4.0).sqrt())
}

/// Whitened normal equations of the markers selected by `used`: (J^T J, J^T r, whitened
/// cost, raw squared residual, corners used).
type JointSystem = (Matrix6<f64>, Vector6<f64>, f64, f64, usize);

fn joint_system(
    calib: &CameraCalibration,
    markers: &[MarkerCorners],
    used: &[bool],
    pose: &Isometry3<f64>,
) -> Option<JointSystem> {
    let mut jtj = Matrix6::zeros();
    let mut g = Vector6::zeros();
    let (mut cost, mut raw, mut n) = (0.0, 0.0, 0);
    for (m, _) in markers.iter().zip(used).filter(|(_, u)| **u) {
        let (r, j) = residuals(calib, &m.obj, &m.img, pose)?;
        let (rw, jw) = (m.white * r, m.white * j);
        jtj += jw.transpose() * jw;
        g += jw.transpose() * rw;
        cost += rw.norm_squared();
        raw += r.norm_squared();
        n += 4;
    }
    (n > 0).then_some((jtj, g, cost, raw, n))
}

/// Levenberg-Marquardt on the corners of every marker selected by `used` at once (the
/// same weighted reprojection error as [`refine_pose`], summed over the markers), from
/// `init`: the pose of the common frame in the camera frame, with its information for
/// the covariance. `reproj_rms_px` is over all corners used.
pub fn refine_pose_joint(
    calib: &CameraCalibration,
    markers: &[MarkerCorners],
    used: &[bool],
    init: &Isometry3<f64>,
) -> Option<RefinedPose> {
    let mut pose = *init;
    let (mut jtj, mut g, mut cost, mut raw, n) = joint_system(calib, markers, used, &pose)?;
    let mut lambda = 1e-6;
    for _ in 0..30 {
        let mut a = jtj;
        for d in 0..6 {
            a[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
        }
        let Some(delta) = a.cholesky().map(|c| c.solve(&g)) else {
            lambda *= 10.0;
            continue;
        };
        let cand = perturb(&pose, &delta);
        match joint_system(calib, markers, used, &cand) {
            Some((jtj2, g2, cost2, raw2, _)) if cost2 <= cost => {
                let done = delta.norm() < 1e-12 || cost - cost2 < 1e-14 * cost.max(1e-30);
                (pose, jtj, g, cost, raw) = (cand, jtj2, g2, cost2, raw2);
                lambda = (lambda * 0.1).max(1e-12);
                if done {
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e6 {
                    break;
                }
            }
        }
    }
    Some(RefinedPose {
        t_cam_marker: pose,
        reproj_rms_px: (raw / n as f64).sqrt(),
        info: jtj,
    })
}

/// How the weighted solution moves with the corners, for corner noise the weights did
/// not include: the weighted LM's step is `delta = P J^T W r` (`P` = `cov`, the inverse
/// of the information, `W` = `white^T white`), so a corner error `e` moves the pose by
/// `K e` and extra corner covariance `extra` adds `K extra K^T`, with `K = P J^T W`
/// (6x8, pose order (tx, ty, tz, rx, ry, rz)) and `J` at the solution `t_cam_frame`.
/// `None`: a corner behind the camera.
pub fn unweighted_gain(
    calib: &CameraCalibration,
    obj: &[Point3<f64>; 4],
    img: &[Vector2<f64>; 4],
    white: &SMatrix<f64, 8, 8>,
    t_cam_frame: &Isometry3<f64>,
    cov: &Matrix6<f64>,
) -> Option<SMatrix<f64, 6, 8>> {
    let (_, j) = residuals(calib, obj, img, t_cam_frame)?;
    let jw = white * j;
    Some(cov * jw.transpose() * white)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// The 1440x1080 camera of the unit tests with plumb-bob distortion `dist`.
    pub(crate) fn calib(dist: Vec<f64>) -> CameraCalibration {
        CameraCalibration {
            width: 1440,
            height: 1080,
            fx: 1100.0,
            fy: 1105.0,
            cx: 722.0,
            cy: 538.0,
            dist,
            model: crate::DistortionModel::PlumbBob,
        }
    }

    #[test]
    fn distortion_jacobian_matches_finite_differences() {
        let c = calib(vec![-0.21, 0.09, 0.001, -0.002, -0.01]);
        for &(x, y) in &[(0.1, -0.2), (-0.4, 0.3), (0.0, 0.0), (0.5, 0.45)] {
            let (_, j) = c.distort_with_jacobian(x, y);
            let h = 1e-6;
            let dx = (c.distort_with_jacobian(x + h, y).0 - c.distort_with_jacobian(x - h, y).0)
                / (2.0 * h);
            let dy = (c.distort_with_jacobian(x, y + h).0 - c.distort_with_jacobian(x, y - h).0)
                / (2.0 * h);
            assert!((j.column(0) - dx).norm() < 1e-4 * j.norm(), "{j} vs {dx}");
            assert!((j.column(1) - dy).norm() < 1e-4 * j.norm(), "{j} vs {dy}");
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let c = calib(vec![-0.21, 0.09, 0.001, -0.002, -0.01]);
        for &(x, y) in &[(0.1, -0.2), (-0.4, 0.3), (0.3, 0.3)] {
            let (uv, _) = c.distort_with_jacobian(x, y);
            let n = c.undistort_pixel(uv.x, uv.y);
            assert!((n - Vector2::new(x, y)).norm() < 1e-7, "{n}");
        }
    }

    #[test]
    fn residual_jacobian_matches_finite_differences() {
        let c = calib(vec![-0.1, 0.02, 0.0, 0.0, 0.0]);
        let obj = marker_object_points(0.2);
        let pose = Isometry3::new(Vector3::new(0.1, -0.05, 1.5), Vector3::new(0.3, -0.4, 0.1));
        let img = [Vector2::new(700.0, 500.0); 4];
        let (r0, j) = residuals(&c, &obj, &img, &pose).unwrap();
        let h = 1e-7;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let (rp, _) = residuals(&c, &obj, &img, &perturb(&pose, &d)).unwrap();
            d[k] = -h;
            let (rm, _) = residuals(&c, &obj, &img, &perturb(&pose, &d)).unwrap();
            // r = obs - f, so dr/dp = -J.
            let num = -(rp - rm) / (2.0 * h);
            assert!(
                (num - j.column(k)).norm() < 1e-3 * j.column(k).norm().max(1.0),
                "param {k}: {num} vs {}",
                j.column(k)
            );
        }
        assert!(r0.norm() > 0.0);
    }

    #[test]
    fn refinement_recovers_exact_pose_from_perturbed_start() {
        let c = calib(vec![-0.2, 0.05, 0.001, 0.0, 0.0]);
        let obj = marker_object_points(0.15);
        let truth = Isometry3::new(Vector3::new(-0.2, 0.1, 2.0), Vector3::new(0.2, 0.7, -0.3));
        let img = obj.map(|p| c.project(&(truth * p)).unwrap());
        let init = perturb(&truth, &Vector6::new(0.03, -0.02, 0.1, 0.05, -0.04, 0.03));
        let sol = refine_pose(&c, &obj, &img, &init, &isotropic_corner_cov(0.1)).unwrap();
        assert!(sol.reproj_rms_px < 1e-6, "{}", sol.reproj_rms_px);
        assert!((sol.t_cam_marker.translation.vector - truth.translation.vector).norm() < 1e-7);
        assert!(sol.t_cam_marker.rotation.angle_to(&truth.rotation) < 1e-7);
        assert!(sol.covariance().is_some());
    }

    #[test]
    fn unweighted_gain_gives_the_sandwich_of_the_weighted_fit() {
        let c = calib(vec![-0.2, 0.05, 0.001, 0.0, 0.0]);
        let obj = marker_object_points(0.15);
        let truth = Isometry3::new(Vector3::new(-0.2, 0.1, 2.0), Vector3::new(0.2, 0.7, -0.3));
        let img = obj.map(|p| c.project(&(truth * p)).unwrap());
        let weights = isotropic_corner_cov(0.1);
        let sol = refine_pose(&c, &obj, &img, &truth, &weights).unwrap();
        let cov = sol.covariance().unwrap();
        let white = whitening(&weights).unwrap();
        let k = unweighted_gain(&c, &obj, &img, &white, &truth, &cov).unwrap();
        let sandwich = |extra: &SMatrix<f64, 8, 8>| k * extra * k.transpose();
        // Extra noise equal to the weights' covariance: the propagated covariance again.
        let add = sandwich(&weights);
        let rel = (add - cov).norm() / cov.norm();
        assert!(rel < 1e-9, "{rel}");
        // Noise the weights left out (corner 0 alone, 0.3 px in u): the pose moves by
        // K e for a corner error e, so the added covariance is K e e^T K^T.
        let mut extra = SMatrix::<f64, 8, 8>::zeros();
        extra[(0, 0)] = 0.09;
        let add = sandwich(&extra);
        let mut shifted = img;
        shifted[0].x += 0.3;
        let moved = refine_pose(&c, &obj, &shifted, &truth, &weights).unwrap();
        let d = moved.t_cam_marker.translation.vector - truth.translation.vector;
        for k in 0..3 {
            let sd = add[(k, k)].sqrt();
            assert!(
                (d[k].abs() - sd).abs() < 0.02 * sd + 1e-9,
                "axis {k}: {} vs {sd}",
                d[k]
            );
        }
    }
}
