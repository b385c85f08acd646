//! Frames and pose covariances.
//!
//! Poses are `Isometry3<f64>` named `t_a_b` (frame b in frame a, docs/frames.md). A pose
//! error is a translation added in the frame named and a small rotation vector acting on
//! the left, `R = exp([dtheta]x) R_hat`, so both are on that frame's axes; a covariance
//! of a pose is 6x6 in the order (tx, ty, tz, rx, ry, rz).

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6,
};

/// Skew-symmetric matrix of `v`: `skew(v) * w == v.cross(&w)`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// `pose` moved by the error `delta` = (dt, dtheta) of the convention above: `dt` added
/// to the translation, `dtheta` a rotation vector applied on the left.
pub fn perturb(pose: &Isometry3<f64>, delta: &Vector6<f64>) -> Isometry3<f64> {
    let dt = Vector3::new(delta[0], delta[1], delta[2]);
    let dth = Vector3::new(delta[3], delta[4], delta[5]);
    let rot = UnitQuaternion::from_scaled_axis(dth) * pose.rotation;
    Isometry3::from_parts(Translation3::from(pose.translation.vector + dt), rot)
}

/// Covariance of `t_cam_marker * t_marker_frame` (a frame fixed to the marker, e.g. the
/// site frame seen through one of its markers) from that of `t_cam_marker` (same
/// parameterisation: the rotation error is shared, the frame's origin moves with it by
/// the lever arm `R t_marker_frame`).
pub fn cov_through(
    t_cam_marker: &Isometry3<f64>,
    t_marker_frame: &Isometry3<f64>,
    cov_cam: &Matrix6<f64>,
) -> Matrix6<f64> {
    let arm = t_cam_marker.rotation * t_marker_frame.translation.vector;
    let mut b = Matrix6::identity();
    b.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&arm)));
    b * cov_cam * b.transpose()
}

/// A pose covariance in the camera frame, rotated into frame `f`: the pose itself is
/// unchanged, only the axes its errors are expressed on (`t_frame_cam` is taken as
/// exact). Order (tx, ty, tz, rx, ry, rz).
pub fn cov_in_frame(cov_cam: &Matrix6<f64>, t_frame_cam: &Isometry3<f64>) -> Matrix6<f64> {
    let r: Matrix3<f64> = *t_frame_cam.rotation.to_rotation_matrix().matrix();
    let mut b = Matrix6::zeros();
    b.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    b.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    b * cov_cam * b.transpose()
}

/// Covariance of the inverse pose `t_marker_cam` (camera position and orientation in
/// the marker frame, errors on the marker frame's axes) from the covariance of
/// `t_cam_marker` in the camera frame. The lever arm couples rotation error into
/// the camera's position: `dp = -R^T dt - R^T [t]x dtheta`, `dphi = -R^T dtheta`.
pub fn cov_of_inverse(t_cam_marker: &Isometry3<f64>, cov_cam: &Matrix6<f64>) -> Matrix6<f64> {
    let rt: Matrix3<f64> = Rotation3::from(t_cam_marker.rotation).matrix().transpose();
    let t = t_cam_marker.translation.vector;
    let mut jac = Matrix6::zeros();
    jac.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-rt));
    jac.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-rt * skew(&t)));
    jac.fixed_view_mut::<3, 3>(3, 3).copy_from(&(-rt));
    jac * cov_cam * jac.transpose()
}

/// The inverse pose `t_b_a` of `t_a_b` with its covariance on b's axes
/// ([`cov_of_inverse`]).
pub fn inverse_with_cov(
    t_a_b: &Isometry3<f64>,
    cov_a: &Matrix6<f64>,
) -> (Isometry3<f64>, Matrix6<f64>) {
    (t_a_b.inverse(), cov_of_inverse(t_a_b, cov_a))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_skew_matrix_is_the_cross_product() {
        let (v, w) = (Vector3::new(0.3, -1.2, 2.0), Vector3::new(-0.7, 0.4, 1.1));
        assert_eq!(skew(&v) * w, v.cross(&w));
        assert_eq!(skew(&v).transpose(), -skew(&v));
    }

    #[test]
    fn cov_in_frame_rotates_blocks_and_inverse_matches_sampling() {
        // Rotating by the identity changes nothing; a 90 degree yaw swaps x and y.
        let mut cov = Matrix6::zeros();
        for (i, v) in [1.0, 4.0, 9.0, 0.01, 0.04, 0.09].iter().enumerate() {
            cov[(i, i)] = *v;
        }
        assert_eq!(cov_in_frame(&cov, &Isometry3::identity()), cov);
        let yaw = Isometry3::new(
            Vector3::new(5.0, 0.0, 0.0),
            Vector3::z() * std::f64::consts::FRAC_PI_2,
        );
        let r = cov_in_frame(&cov, &yaw);
        assert!((r[(0, 0)] - 4.0).abs() < 1e-12 && (r[(1, 1)] - 1.0).abs() < 1e-12);
        assert!((r[(3, 3)] - 0.04).abs() < 1e-12 && (r[(4, 4)] - 0.01).abs() < 1e-12);

        // Inverse: the linear map against a finite-difference of the inverse.
        let t = Isometry3::new(Vector3::new(0.1, -0.2, 1.5), Vector3::new(0.2, -0.3, 0.1));
        let h = 1e-6;
        let mut num = Matrix6::zeros();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let tp = perturb(&t, &d).inverse();
            let ti = t.inverse();
            let dp = (tp.translation.vector - ti.translation.vector) / h;
            let dphi = (tp.rotation * ti.rotation.inverse()).scaled_axis() / h;
            for i in 0..3 {
                num[(i, k)] = dp[i];
                num[(3 + i, k)] = dphi[i];
            }
        }
        let analytic = cov_of_inverse(&t, &Matrix6::identity());
        let sampled = num * num.transpose();
        assert!(
            (analytic - sampled).norm() < 1e-4 * analytic.norm(),
            "{analytic}\n{sampled}"
        );
        let (inv, cov_inv) = inverse_with_cov(&t, &Matrix6::identity());
        assert_eq!((inv, cov_inv), (t.inverse(), analytic));
    }
}
