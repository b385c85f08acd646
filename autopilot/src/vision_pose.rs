//! The vehicle pose that goes to ArduSub's EKF in setpoint mode, with its covariance
//! carried from the camera through the mount and the marker into the vision frame `L`.
//!
//! Parameterisation (docs/frames.md): a pose error is a translation added in the frame
//! named and a small rotation vector acting on the left (`R = exp([dphi]x) R_hat`), on the
//! same frame's axes; order (tx, ty, tz, rx, ry, rz). VISION_POSITION_ESTIMATE wants the
//! rotation part as (roll, pitch, yaw) instead: the last step maps the rotation vector
//! through the Euler-rate Jacobian of `R = Rz(yaw) Ry(pitch) Rx(roll)`.

use markhold_geometry::{cov_in_frame, inverse_with_cov};
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3};

use crate::config::r_marker_body_facing;

/// `t_L_marker`: the vision frame `L` is the marker (site) frame turned so that a vehicle
/// on station facing the marker is level with yaw 0 (x_L = -z_m, y_L = x_m, z_L = -y_m).
pub fn t_vision_marker() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_rotation_matrix(&r_marker_body_facing().inverse()),
    )
}

/// One camera measurement turned into the vehicle's pose in the marker (site) frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VisionPose {
    /// Frame stamp, loop seconds.
    pub stamp_s: f64,
    /// The vehicle (centre of gravity, body FRD axes) in the marker frame.
    pub t_marker_vehicle: Isometry3<f64>,
    /// Covariance of `t_marker_vehicle`: position and left rotation vector on marker axes.
    pub cov_marker: Matrix6<f64>,
}

impl VisionPose {
    /// From the marker's pose in the camera (`t_cam_marker`, its covariance `cov_cam` on
    /// camera axes, rotation error on the left) and the camera mount `t_vehicle_cam`
    /// (taken as exact). The mount rotates both blocks onto body axes
    /// ([`cov_in_frame`]); the inverse then moves the vehicle's position by the rotation
    /// error times the lever arm from the marker to the vehicle ([`inverse_with_cov`]:
    /// `dp = -R^T dt - R^T [t]x dtheta`, `dphi = -R^T dtheta`, with
    /// `(R, t) = t_vehicle_marker`).
    pub fn from_camera(
        stamp_s: f64,
        t_cam_marker: &Isometry3<f64>,
        cov_cam: &Matrix6<f64>,
        t_vehicle_cam: &Isometry3<f64>,
    ) -> Self {
        let cov_vehicle = cov_in_frame(cov_cam, t_vehicle_cam);
        let t_vehicle_marker = t_vehicle_cam * t_cam_marker;
        let (t_marker_vehicle, cov_marker) = inverse_with_cov(&t_vehicle_marker, &cov_vehicle);
        Self {
            stamp_s,
            t_marker_vehicle,
            cov_marker,
        }
    }

    /// The pose in the vision frame `L` and its covariance on L's axes (same
    /// parameterisation: a rotation of frame only turns both blocks).
    pub fn in_vision_frame(&self) -> (Isometry3<f64>, Matrix6<f64>) {
        let t_l_m = t_vision_marker();
        (
            t_l_m * self.t_marker_vehicle,
            cov_in_frame(&self.cov_marker, &t_l_m),
        )
    }

    /// The pose in `L` as (x, y, z, roll, pitch, yaw) and its 6x6 covariance over those
    /// six numbers. `None` when it cannot be stated: a covariance that is not finite or
    /// has a non-positive variance, or pitch within 0.1 degree of +-90 (Euler angles
    /// degenerate there).
    pub fn euler_with_covariance(&self) -> Option<([f64; 6], Matrix6<f64>)> {
        let (pose, cov_l) = self.in_vision_frame();
        let (roll, pitch, yaw) = pose.rotation.euler_angles();
        if pitch.cos() < 0.1f64.to_radians().sin() {
            return None;
        }
        // World-frame rotation vector from Euler rates: dphi = E d(roll, pitch, yaw).
        let (sy, cy) = yaw.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        let e = Matrix3::from_columns(&[
            Vector3::new(cy * cp, sy * cp, -sp),
            Vector3::new(-sy, cy, 0.0),
            Vector3::z(),
        ]);
        let e_inv = e.try_inverse()?;
        let mut g = Matrix6::identity();
        g.fixed_view_mut::<3, 3>(3, 3).copy_from(&e_inv);
        let cov = g * cov_l * g.transpose();
        let cov = (cov + cov.transpose()) * 0.5;
        let usable = cov.iter().all(|v| v.is_finite()) && (0..6).all(|i| cov[(i, i)] > 0.0);
        let t = pose.translation.vector;
        usable.then_some(([t.x, t.y, t.z, roll, pitch, yaw], cov))
    }
}

/// The upper triangle of a symmetric 6x6, row-major (MAVLink's 21-element covariance:
/// indices 0..5 are row 0, 6..10 row 1 from the diagonal, ..., 20 the last diagonal),
/// scaled by `scale`.
pub fn upper_triangle(cov: &Matrix6<f64>, scale: f64) -> [f32; 21] {
    let mut out = [0.0f32; 21];
    let mut k = 0;
    for i in 0..6 {
        for j in i..6 {
            out[k] = (cov[(i, j)] * scale) as f32;
            k += 1;
        }
    }
    out
}

/// The symmetric 6x6 from MAVLink's 21-element upper triangle.
pub fn from_upper_triangle(c: &[f32; 21]) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    let mut k = 0;
    for i in 0..6 {
        for j in i..6 {
            m[(i, j)] = f64::from(c[k]);
            m[(j, i)] = f64::from(c[k]);
            k += 1;
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector6;

    /// SplitMix64 and Box-Muller: a deterministic normal stream without a dependency.
    struct Normal(u64);
    impl Normal {
        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
        fn next(&mut self) -> f64 {
            let (u, v) = (self.uniform(), self.uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    fn mount() -> Isometry3<f64> {
        // Forward camera 0.2 m ahead and 0.1 m below the centre of gravity, pitched 15
        // degrees down and yawed 10 degrees right (docs/frames.md mount convention).
        let forward = nalgebra::Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
            Vector3::new(0.0, 1.0, 0.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(1.0, 0.0, 0.0),
        ]));
        let turn = UnitQuaternion::from_euler_angles(0.0, (-15.0f64).to_radians(), 0.17);
        Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.1),
            turn * UnitQuaternion::from_rotation_matrix(&forward),
        )
    }

    fn camera_cov() -> Matrix6<f64> {
        // A PnP-like covariance: depth worst, rotation about the optical axis best,
        // translation and rotation correlated.
        let a = Matrix6::from_row_slice(&[
            2e-3, 0.0, 0.0, 0.0, 3e-3, 0.0, //
            0.0, 2e-3, 0.0, -3e-3, 0.0, 0.0, //
            0.0, 0.0, 6e-3, 0.0, 0.0, 0.0, //
            0.0, 0.0, 0.0, 2e-3, 0.0, 0.0, //
            0.0, 0.0, 0.0, 0.0, 2e-3, 0.0, //
            1e-4, 0.0, 1e-3, 0.0, 0.0, 1e-3,
        ]);
        a * a.transpose()
    }

    fn sample(rng: &mut Normal, l: &Matrix6<f64>) -> Vector6<f64> {
        let z = Vector6::from_fn(|_, _| rng.next());
        l * z
    }

    #[test]
    fn propagation_matches_monte_carlo_in_euler_coordinates() {
        // The marker 1.2 m ahead of the camera, a little left and turned: the lever arm
        // couples rotation error into the vehicle's position.
        let t_cam_marker =
            Isometry3::new(Vector3::new(-0.15, 0.05, 1.2), Vector3::new(0.1, 2.9, 0.05));
        let cov_cam = camera_cov();
        let est = VisionPose::from_camera(1.0, &t_cam_marker, &cov_cam, &mount());
        let (mean, analytic) = est.euler_with_covariance().expect("covariance");
        let l = cov_cam.cholesky().expect("positive definite").l();
        let mut rng = Normal(7);
        let n = 40_000;
        let mut acc = Matrix6::zeros();
        for _ in 0..n {
            let d = sample(&mut rng, &l);
            let noisy = Isometry3::from_parts(
                Translation3::from(t_cam_marker.translation.vector + d.fixed_rows::<3>(0)),
                UnitQuaternion::from_scaled_axis(d.fixed_rows::<3>(3).into_owned())
                    * t_cam_marker.rotation,
            );
            let t_l_b = t_vision_marker() * (mount() * noisy).inverse();
            let (r, p, y) = t_l_b.rotation.euler_angles();
            let t = t_l_b.translation.vector;
            let x = [t.x, t.y, t.z, r, p, y];
            let e = Vector6::from_fn(|i, _| {
                let v = x[i] - mean[i];
                if i >= 3 {
                    crate::types::wrap_pi(v)
                } else {
                    v
                }
            });
            acc += e * e.transpose();
        }
        let sampled = acc / n as f64;
        // Each element against the scale of its row and column: sampling error of a
        // covariance from 40 000 draws is about 1 % of sqrt(c_ii c_jj).
        for i in 0..6 {
            for j in 0..6 {
                let scale = (analytic[(i, i)] * analytic[(j, j)]).sqrt();
                let d = (sampled[(i, j)] - analytic[(i, j)]).abs() / scale;
                assert!(
                    d < 0.04,
                    "({i},{j}): analytic {analytic}\nsampled {sampled}"
                );
            }
        }
        // Not a trivial case: the lever arm makes position depend on rotation error.
        assert!(analytic[(1, 5)].abs() > 0.1 * (analytic[(1, 1)] * analytic[(5, 5)]).sqrt());
    }

    #[test]
    fn hand_computed_case_camera_ahead_of_a_level_vehicle() {
        // Camera looking straight ahead from the centre of gravity, the marker 2 m in
        // front, facing the vehicle: L coincides with body axes. A rotation error of the
        // marker about the camera's y (image down) axis of 0.01 rad moves the vehicle
        // sideways by 2 m x 0.01 on the marker's x axis = L's y; with only that variance
        // (1e-4 rad^2) the vehicle's y variance is 4e-4 m^2 and its yaw variance 1e-4.
        let mount = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(
                Matrix3::from_columns(&[Vector3::y(), Vector3::z(), Vector3::x()]),
            )),
        );
        // Marker facing the camera: its z toward the camera, x to the image right.
        let r_cm = nalgebra::Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
            Vector3::x(),
            -Vector3::y(),
            -Vector3::z(),
        ]));
        let t_cam_marker = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 2.0),
            UnitQuaternion::from_rotation_matrix(&r_cm),
        );
        let mut cov = Matrix6::zeros();
        cov[(4, 4)] = 1e-4;
        let est = VisionPose::from_camera(0.0, &t_cam_marker, &cov, &mount);
        let (pose, cl) = est.in_vision_frame();
        assert!((pose.translation.vector - Vector3::new(-2.0, 0.0, 0.0)).norm() < 1e-12);
        assert!((cl[(1, 1)] - 4e-4).abs() < 1e-15, "{cl}");
        assert!((cl[(5, 5)] - 1e-4).abs() < 1e-15, "{cl}");
        // The y position and yaw errors are fully correlated (|rho| = 1).
        assert!((cl[(1, 5)].abs() - 2e-4).abs() < 1e-15, "{cl}");
        assert!(cl[(0, 0)].abs() < 1e-18 && cl[(2, 2)].abs() < 1e-18);
        // Zero variances elsewhere: nothing the EKF could be given.
        assert!(est.euler_with_covariance().is_none());
    }

    #[test]
    fn upper_triangle_round_trips_and_orders_rows() {
        let m = Matrix6::from_fn(|i, j| (i.min(j) * 10 + i.max(j)) as f64);
        let u = upper_triangle(&m, 1.0);
        assert_eq!(u[0], 0.0);
        assert_eq!(u[5], 5.0);
        assert_eq!(u[6], 11.0);
        assert_eq!(u[11], 22.0);
        assert_eq!(u[15], 33.0);
        assert_eq!(u[18], 44.0);
        assert_eq!(u[20], 55.0);
        assert_eq!(from_upper_triangle(&u), m);
        assert_eq!(upper_triangle(&m, 0.5)[20], 27.5);
    }
}
