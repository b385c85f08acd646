//! Lens models: where a normalised image point `(x, y) = (X/Z, Y/Z)` lands after the
//! lens (and, under water, the port), with Jacobians for the pose and calibration
//! solvers, and the inverse.
//!
//! - `plumb_bob` (OpenCV's default, ROS's name): `k1 k2 p1 p2 [k3]`, radial polynomial
//!   `1 + k1 r^2 + k2 r^4 + k3 r^6` plus tangential terms.
//! - `rational_polynomial` (OpenCV `CALIB_RATIONAL_MODEL`): `k1 k2 p1 p2 k3 k4 k5 k6`,
//!   radial factor `(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`.
//!   Behind a flat port it fits the refraction's radial stretch, which grows like
//!   `1 / sqrt(1 - (n^2 - 1) r^2)`, better than a polynomial (docs/design/calibration.md).
//! - `equidistant` (OpenCV's `cv::fisheye`, ROS's and Kalibr's name): `k1 k2 k3 k4`,
//!   `theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)` with
//!   `theta = atan(r)`; the distorted point is `theta_d / r * (x, y)`.
//!
//! The formulas are OpenCV 4.6's (`modules/calib3d/src/calibration.cpp`,
//! `cvProjectPoints2Internal`; `modules/calib3d/src/fisheye.cpp`, `projectPoints`);
//! the code is ours.

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

/// Which lens model the coefficients of a calibration belong to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub enum DistortionModel {
    /// `k1 k2 p1 p2 [k3]` (0, 4 or 5 coefficients).
    #[default]
    #[serde(rename = "plumb_bob")]
    PlumbBob,
    /// `k1 k2 p1 p2 k3 k4 k5 k6` (8 coefficients).
    #[serde(rename = "rational_polynomial")]
    Rational,
    /// `k1 k2 k3 k4` of the equidistant fisheye model (4 coefficients).
    #[serde(rename = "equidistant")]
    Equidistant,
}

impl DistortionModel {
    /// The name in calibration files (ROS camera_info's `distortion_model`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::PlumbBob => "plumb_bob",
            Self::Rational => "rational_polynomial",
            Self::Equidistant => "equidistant",
        }
    }

    /// Every model, for messages and command-line choices.
    pub fn all() -> [DistortionModel; 3] {
        [Self::PlumbBob, Self::Rational, Self::Equidistant]
    }

    /// Coefficient counts a calibration of this model may hold.
    pub fn allowed_lengths(self) -> &'static [usize] {
        match self {
            Self::PlumbBob => &[0, 4, 5],
            Self::Rational => &[8],
            Self::Equidistant => &[4],
        }
    }

    /// The number of coefficients a calibration solver estimates.
    pub fn full_len(self) -> usize {
        match self {
            Self::PlumbBob => 5,
            Self::Rational => 8,
            Self::Equidistant => 4,
        }
    }

    /// The coefficients' names, in file order.
    pub fn coefficient_names(self) -> &'static [&'static str] {
        match self {
            Self::PlumbBob => &["k1", "k2", "p1", "p2", "k3"],
            Self::Rational => &["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"],
            Self::Equidistant => &["k1", "k2", "k3", "k4"],
        }
    }
}

impl std::fmt::Display for DistortionModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for DistortionModel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "plumb_bob" | "radtan" | "radial-tangential" => Ok(Self::PlumbBob),
            "rational_polynomial" | "rational" => Ok(Self::Rational),
            "equidistant" | "fisheye" => Ok(Self::Equidistant),
            other => Err(format!(
                "'{other}': expected plumb_bob (radtan), rational_polynomial (rational) or \
                 equidistant (fisheye)"
            )),
        }
    }
}

/// Coefficient `i` of `d`, 0 past its end.
fn at(d: &[f64], i: usize) -> f64 {
    d.get(i).copied().unwrap_or(0.0)
}

/// The distorted normalised point of `(x, y)` and its 2x2 Jacobian `d(xd, yd)/d(x, y)`.
pub fn distort(model: DistortionModel, d: &[f64], x: f64, y: f64) -> (Vector2<f64>, Matrix2<f64>) {
    match model {
        DistortionModel::PlumbBob | DistortionModel::Rational => {
            let (p, j, _) = radtan(model, d, x, y, false);
            (p, j)
        }
        DistortionModel::Equidistant => {
            let (p, j, _) = equidistant(d, x, y, false);
            (p, j)
        }
    }
}

/// The distorted normalised point, and its Jacobian with respect to the coefficients
/// (2 x `d.len()`, column `i` for coefficient `i`).
pub fn distort_coefficient_jacobian(
    model: DistortionModel,
    d: &[f64],
    x: f64,
    y: f64,
) -> (Vector2<f64>, Vec<[f64; 2]>) {
    let (p, _, mut jd) = match model {
        DistortionModel::PlumbBob | DistortionModel::Rational => radtan(model, d, x, y, true),
        DistortionModel::Equidistant => equidistant(d, x, y, true),
    };
    jd.truncate(d.len());
    (p, jd)
}

/// Radial-tangential (plumb_bob) and rational models.
fn radtan(
    model: DistortionModel,
    d: &[f64],
    x: f64,
    y: f64,
    coefficients: bool,
) -> (Vector2<f64>, Matrix2<f64>, Vec<[f64; 2]>) {
    let (k1, k2, p1, p2, k3) = (at(d, 0), at(d, 1), at(d, 2), at(d, 3), at(d, 4));
    let rational = model == DistortionModel::Rational;
    let (k4, k5, k6) = if rational {
        (at(d, 5), at(d, 6), at(d, 7))
    } else {
        (0.0, 0.0, 0.0)
    };
    let r2 = x * x + y * y;
    let num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    let den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
    let radial = num / den;
    // d radial / d r2 by the quotient rule.
    let dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
    let dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2);
    let drad_dr2 = (dnum * den - num * dden) / (den * den);
    let (drad_dx, drad_dy) = (drad_dr2 * 2.0 * x, drad_dr2 * 2.0 * y);
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let j = Matrix2::new(
        radial + x * drad_dx + 2.0 * p1 * y + 6.0 * p2 * x,
        x * drad_dy + 2.0 * p1 * x + 2.0 * p2 * y,
        y * drad_dx + 2.0 * p1 * x + 2.0 * p2 * y,
        radial + y * drad_dy + 6.0 * p1 * y + 2.0 * p2 * x,
    );
    let mut jd = Vec::new();
    if coefficients {
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        // d radial / d k_i for the numerator terms and the denominator terms.
        let up = |rp: f64| [x * rp / den, y * rp / den];
        let down = |rp: f64| [-x * num * rp / (den * den), -y * num * rp / (den * den)];
        jd.push(up(r2));
        jd.push(up(r4));
        jd.push([2.0 * x * y, r2 + 2.0 * y * y]);
        jd.push([r2 + 2.0 * x * x, 2.0 * x * y]);
        jd.push(up(r6));
        if rational {
            jd.push(down(r2));
            jd.push(down(r4));
            jd.push(down(r6));
        }
    }
    (Vector2::new(xd, yd), j, jd)
}

/// The equidistant fisheye model.
fn equidistant(
    d: &[f64],
    x: f64,
    y: f64,
    coefficients: bool,
) -> (Vector2<f64>, Matrix2<f64>, Vec<[f64; 2]>) {
    let k = [at(d, 0), at(d, 1), at(d, 2), at(d, 3)];
    let r = x.hypot(y);
    let mut jd = Vec::new();
    if r < 1e-12 {
        // theta_d / r -> 1 at the centre, and every coefficient's effect vanishes.
        if coefficients {
            jd = vec![[0.0, 0.0]; 4];
        }
        return (Vector2::new(x, y), Matrix2::identity(), jd);
    }
    let th = r.atan();
    let t2 = th * th;
    let poly = 1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])));
    let thd = th * poly;
    // d theta_d / d theta, d theta / d r.
    let dthd = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + 9.0 * t2 * k[3])));
    let dth_dr = 1.0 / (1.0 + r * r);
    let s = thd / r;
    let ds_dr = (dthd * dth_dr * r - thd) / (r * r);
    let (ux, uy) = (x / r, y / r);
    let j = Matrix2::new(
        s + x * ds_dr * ux,
        x * ds_dr * uy,
        y * ds_dr * ux,
        s + y * ds_dr * uy,
    );
    if coefficients {
        let mut tp = th * t2;
        for _ in 0..4 {
            jd.push([tp / r * x, tp / r * y]);
            tp *= t2;
        }
    }
    (Vector2::new(s * x, s * y), j, jd)
}

/// The normalised undistorted point whose distortion is `(xd, yd)`: Newton's method on
/// the analytic Jacobian from the distorted point (to 1e-14 in normalised units, about
/// 1e-11 px), `None` where it does not converge (outside the region where the model is
/// one-to-one).
pub fn undistort(model: DistortionModel, d: &[f64], xd: f64, yd: f64) -> Option<Vector2<f64>> {
    if d.iter().all(|k| *k == 0.0) {
        return Some(Vector2::new(xd, yd));
    }
    if model == DistortionModel::Equidistant {
        return undistort_equidistant(d, xd, yd);
    }
    let target = Vector2::new(xd, yd);
    let mut p = target;
    for _ in 0..50 {
        let (q, j) = distort(model, d, p.x, p.y);
        let e = q - target;
        if e.norm() < 1e-14 {
            return Some(p);
        }
        let step = j.try_inverse()? * e;
        // Halve a step that would leave the region the model is good in.
        let mut t = 1.0;
        let mut next = p - step * t;
        while t > 1e-3 && (distort(model, d, next.x, next.y).0 - target).norm() > e.norm() {
            t *= 0.5;
            next = p - step * t;
        }
        p = next;
    }
    let (q, _) = distort(model, d, p.x, p.y);
    ((q - target).norm() < 1e-9).then_some(p)
}

fn undistort_equidistant(d: &[f64], xd: f64, yd: f64) -> Option<Vector2<f64>> {
    let k = [at(d, 0), at(d, 1), at(d, 2), at(d, 3)];
    let thd = xd.hypot(yd);
    if thd < 1e-12 {
        return Some(Vector2::new(xd, yd));
    }
    // Solve theta (1 + k1 theta^2 + ...) = theta_d for theta in [0, pi/2).
    let mut th = thd.min(1.5);
    for _ in 0..50 {
        let t2 = th * th;
        let f = th * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - thd;
        let df = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + 9.0 * t2 * k[3])));
        if df <= 0.0 {
            return None;
        }
        let step = f / df;
        th = (th - step).clamp(0.0, 1.57);
        if step.abs() < 1e-15 {
            break;
        }
    }
    if !(0.0..std::f64::consts::FRAC_PI_2).contains(&th) {
        return None;
    }
    let scale = th.tan() / thd;
    Some(Vector2::new(xd * scale, yd * scale))
}

#[cfg(test)]
mod tests {
    use super::*;

    const CASES: [(DistortionModel, &[f64]); 4] = [
        (
            DistortionModel::PlumbBob,
            &[-0.21, 0.09, 0.001, -0.002, -0.01],
        ),
        (
            DistortionModel::Rational,
            &[0.9, 0.3, 0.001, -0.002, 0.01, 0.75, 0.2, 0.02],
        ),
        (DistortionModel::Equidistant, &[0.05, -0.02, 0.004, -0.001]),
        (DistortionModel::PlumbBob, &[]),
    ];

    const POINTS: [(f64, f64); 5] = [
        (0.1, -0.2),
        (-0.4, 0.3),
        (0.0, 0.0),
        (0.5, 0.45),
        (1e-7, 0.0),
    ];

    #[test]
    fn point_jacobians_match_finite_differences() {
        for (model, d) in CASES {
            for (x, y) in POINTS {
                let (_, j) = distort(model, d, x, y);
                let h = 1e-6;
                let dx =
                    (distort(model, d, x + h, y).0 - distort(model, d, x - h, y).0) / (2.0 * h);
                let dy =
                    (distort(model, d, x, y + h).0 - distort(model, d, x, y - h).0) / (2.0 * h);
                assert!(
                    (j.column(0) - dx).norm() < 1e-6,
                    "{model} {x} {y}: {j} vs {dx}"
                );
                assert!(
                    (j.column(1) - dy).norm() < 1e-6,
                    "{model} {x} {y}: {j} vs {dy}"
                );
            }
        }
    }

    #[test]
    fn coefficient_jacobians_match_finite_differences() {
        for (model, d) in CASES {
            for (x, y) in POINTS {
                let (_, jd) = distort_coefficient_jacobian(model, d, x, y);
                assert_eq!(jd.len(), d.len());
                for i in 0..d.len() {
                    let h = 1e-7;
                    let (mut a, mut b) = (d.to_vec(), d.to_vec());
                    a[i] += h;
                    b[i] -= h;
                    let num = (distort(model, &a, x, y).0 - distort(model, &b, x, y).0) / (2.0 * h);
                    let an = Vector2::new(jd[i][0], jd[i][1]);
                    assert!(
                        (num - an).norm() < 1e-6,
                        "{model} k{i} at {x},{y}: {num} vs {an}"
                    );
                }
            }
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        for (model, d) in CASES {
            for (x, y) in POINTS {
                let (q, _) = distort(model, d, x, y);
                let p = undistort(model, d, q.x, q.y).expect("converges");
                assert!(
                    (p - Vector2::new(x, y)).norm() < 1e-10,
                    "{model}: {p} vs {x},{y}"
                );
            }
        }
    }

    #[test]
    fn equidistant_matches_the_published_formula() {
        // theta = atan(r); theta_d = theta (1 + k1 theta^2 + ...); scaled by theta_d / r.
        let d = [0.1, 0.0, 0.0, 0.0];
        let (x, y) = (0.3, 0.4);
        let r: f64 = 0.5;
        let th = r.atan();
        let thd = th * (1.0 + 0.1 * th * th);
        let (q, _) = distort(DistortionModel::Equidistant, &d, x, y);
        assert!((q - Vector2::new(x, y) * (thd / r)).norm() < 1e-15);
    }

    #[test]
    fn names_round_trip() {
        for m in DistortionModel::all() {
            assert_eq!(m.as_str().parse::<DistortionModel>(), Ok(m));
            assert_eq!(m.coefficient_names().len(), m.full_len());
        }
        assert!("division".parse::<DistortionModel>().is_err());
    }
}
