//! The calibration's least squares: Levenberg-Marquardt over the intrinsics (the free
//! ones) and every view's pose of the target, on the corners' reprojection error in
//! pixels (unit weights, as OpenCV's calibrateCamera). The normal equations are solved
//! through the Schur complement on the intrinsics: each view's 6x6 pose block is
//! eliminated on its own, leaving a system of at most 11 unknowns, so views cost little.

use nalgebra::{DMatrix, DVector, Isometry3, Matrix2x3, Matrix6, Point3, Vector2, Vector6};

use crate::distortion::{self, DistortionModel};
use crate::CameraCalibration;
use markhold_geometry::{perturb, skew};

use super::View;

/// One free intrinsic parameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Param {
    Fx,
    Fy,
    /// One focal length for both axes, `fy = ratio fx` kept (`ratio` from the start).
    Focal {
        ratio: f64,
    },
    Cx,
    Cy,
    /// Distortion coefficient `i` of the model.
    Dist(usize),
}

impl Param {
    pub fn name(self, model: DistortionModel) -> String {
        match self {
            Param::Fx => "fx".into(),
            Param::Fy => "fy".into(),
            Param::Focal { .. } => "f".into(),
            Param::Cx => "cx".into(),
            Param::Cy => "cy".into(),
            Param::Dist(i) => model
                .coefficient_names()
                .get(i)
                .map_or(format!("d{i}"), |n| n.to_string()),
        }
    }

    fn get(self, c: &CameraCalibration) -> f64 {
        match self {
            Param::Fx | Param::Focal { .. } => c.fx,
            Param::Fy => c.fy,
            Param::Cx => c.cx,
            Param::Cy => c.cy,
            Param::Dist(i) => c.dist[i],
        }
    }

    fn add(self, c: &mut CameraCalibration, d: f64) {
        match self {
            Param::Fx => c.fx += d,
            Param::Fy => c.fy += d,
            Param::Focal { ratio } => {
                c.fx += d;
                c.fy = ratio * c.fx;
            }
            Param::Cx => c.cx += d,
            Param::Cy => c.cy += d,
            Param::Dist(i) => c.dist[i] += d,
        }
    }
}

/// A solution of the least squares.
#[derive(Debug, Clone)]
pub struct Solution {
    pub calib: CameraCalibration,
    /// Each view's target pose in the camera frame.
    pub poses: Vec<Isometry3<f64>>,
    /// The free parameters and their covariance (scaled by the a-posteriori variance
    /// factor), in the order of `params`.
    pub params: Vec<Param>,
    pub covariance: Option<DMatrix<f64>>,
    /// RMS reprojection error over every point used, and per view, pixels.
    pub rms_px: f64,
    pub view_rms_px: Vec<f64>,
    pub iterations: usize,
    /// Points used.
    pub points: usize,
}

impl Solution {
    /// One standard deviation of parameter `p` (NaN when it is not free or the
    /// covariance is singular).
    pub fn sigma(&self, p: impl Fn(Param) -> bool) -> f64 {
        let Some(cov) = &self.covariance else {
            return f64::NAN;
        };
        self.params
            .iter()
            .position(|q| p(*q))
            .map_or(f64::NAN, |i| cov[(i, i)].max(0.0).sqrt())
    }
}

/// A pixel, and its Jacobians w.r.t. the pose and the free intrinsics when asked.
type Projection = (
    Vector2<f64>,
    Option<(nalgebra::Matrix2x6<f64>, DMatrix<f64>)>,
);

/// The damped step: the intrinsics' part, each view's pose part, the reduced matrix.
type Step = (DVector<f64>, Vec<Vector6<f64>>, DMatrix<f64>);

/// Pixel of a target point, with the Jacobians w.r.t. the view's pose (left
/// perturbation, as `pose::refine_pose`) and w.r.t. the free intrinsics (`None`: behind
/// the camera).
fn project(
    c: &CameraCalibration,
    params: &[Param],
    pose: &Isometry3<f64>,
    x: &Point3<f64>,
    jac: bool,
) -> Option<Projection> {
    let rx = pose.rotation * x.coords;
    let p = rx + pose.translation.vector;
    if p.z <= 1e-9 {
        return None;
    }
    let iz = 1.0 / p.z;
    let (nx, ny) = (p.x * iz, p.y * iz);
    if !jac {
        let (q, _) = distortion::distort(c.model, &c.dist, nx, ny);
        return Some((Vector2::new(c.fx * q.x + c.cx, c.fy * q.y + c.cy), None));
    }
    let (q, jq) = distortion::distort(c.model, &c.dist, nx, ny);
    let (_, jd) = distortion::distort_coefficient_jacobian(c.model, &c.dist, nx, ny);
    let uv = Vector2::new(c.fx * q.x + c.cx, c.fy * q.y + c.cy);
    let mut juv = jq;
    juv.row_mut(0).scale_mut(c.fx);
    juv.row_mut(1).scale_mut(c.fy);
    let dn_dp = Matrix2x3::new(iz, 0.0, -nx * iz, 0.0, iz, -ny * iz);
    let d = juv * dn_dp;
    let drot = d * (-skew(&rx));
    let mut jp = nalgebra::Matrix2x6::zeros();
    jp.fixed_view_mut::<2, 3>(0, 0).copy_from(&d);
    jp.fixed_view_mut::<2, 3>(0, 3).copy_from(&drot);
    let ji = columns(c, params, &q, &jd);
    Some((uv, Some((jp, ji))))
}

/// The Jacobian of a pixel w.r.t. the free intrinsics `params` (2 x n), for the
/// distorted normalised point `q` and its coefficient Jacobian `jd`.
fn columns(
    c: &CameraCalibration,
    params: &[Param],
    q: &Vector2<f64>,
    jd: &[[f64; 2]],
) -> DMatrix<f64> {
    let mut ji = DMatrix::zeros(2, params.len());
    for (k, prm) in params.iter().enumerate() {
        let (a, b) = match *prm {
            Param::Fx => (q.x, 0.0),
            Param::Fy => (0.0, q.y),
            Param::Focal { ratio } => (q.x, ratio * q.y),
            Param::Cx => (1.0, 0.0),
            Param::Cy => (0.0, 1.0),
            Param::Dist(i) => (c.fx * jd[i][0], c.fy * jd[i][1]),
        };
        ji[(0, k)] = a;
        ji[(1, k)] = b;
    }
    ji
}

/// The Jacobian of the pixel of the normalised point `(x, y)` w.r.t. the free
/// intrinsics `params` (2 x `params.len()`).
pub fn intrinsic_jacobian(c: &CameraCalibration, params: &[Param], x: f64, y: f64) -> DMatrix<f64> {
    let (q, jd) = distortion::distort_coefficient_jacobian(c.model, &c.dist, x, y);
    columns(c, params, &q, &jd)
}

/// Apply a step `delta` (in the order of `params`) to `c`.
pub fn step_intrinsics(c: &mut CameraCalibration, params: &[Param], delta: &[f64]) {
    for (p, d) in params.iter().zip(delta) {
        p.add(c, *d);
    }
}

/// Sum of squared residuals and points counted (`None`: a point behind a camera).
pub fn cost(
    c: &CameraCalibration,
    views: &[View],
    poses: &[Isometry3<f64>],
) -> Option<(f64, usize)> {
    let (mut s, mut n) = (0.0, 0);
    for (v, pose) in views.iter().zip(poses) {
        for (i, (x, m)) in v.points.iter().enumerate() {
            if !v.used[i] {
                continue;
            }
            let (uv, _) = project(c, &[], pose, x, false)?;
            s += (m - uv).norm_squared();
            n += 1;
        }
    }
    Some((s, n))
}

/// RMS error of each view's points used, pixels (NaN: behind the camera).
pub fn view_rms(c: &CameraCalibration, views: &[View], poses: &[Isometry3<f64>]) -> Vec<f64> {
    views
        .iter()
        .zip(poses)
        .map(|(v, pose)| {
            cost(c, std::slice::from_ref(v), std::slice::from_ref(pose))
                .map_or(f64::NAN, |(s, n)| (s / n.max(1) as f64).sqrt())
        })
        .collect()
}

/// Each point's reprojection error, pixels (NaN: behind the camera), per view.
pub fn point_errors(
    c: &CameraCalibration,
    views: &[View],
    poses: &[Isometry3<f64>],
) -> Vec<Vec<f64>> {
    views
        .iter()
        .zip(poses)
        .map(|(v, pose)| {
            v.points
                .iter()
                .map(|(x, m)| {
                    project(c, &[], pose, x, false).map_or(f64::NAN, |(uv, _)| (m - uv).norm())
                })
                .collect()
        })
        .collect()
}

struct Normal {
    cost: f64,
    u: DMatrix<f64>,
    gi: DVector<f64>,
    views: Vec<(Matrix6<f64>, Vector6<f64>, DMatrix<f64>)>,
}

fn linearise(
    c: &CameraCalibration,
    params: &[Param],
    views: &[View],
    poses: &[Isometry3<f64>],
) -> Option<Normal> {
    let n = params.len();
    let mut out = Normal {
        cost: 0.0,
        u: DMatrix::zeros(n, n),
        gi: DVector::zeros(n),
        views: Vec::with_capacity(views.len()),
    };
    for (v, pose) in views.iter().zip(poses) {
        let (mut vv, mut gv, mut w) = (Matrix6::zeros(), Vector6::zeros(), DMatrix::zeros(n, 6));
        for (i, (x, m)) in v.points.iter().enumerate() {
            if !v.used[i] {
                continue;
            }
            let (uv, Some((jp, ji))) = project(c, params, pose, x, true)? else {
                return None;
            };
            let r = m - uv;
            out.cost += r.norm_squared();
            vv += jp.transpose() * jp;
            gv += jp.transpose() * r;
            out.u += ji.transpose() * &ji;
            out.gi += ji.transpose() * r;
            w += ji.transpose() * jp;
        }
        out.views.push((vv, gv, w));
    }
    Some(out)
}

/// The damped step (intrinsics, per-view poses) and the reduced matrix.
fn step(lin: &Normal, lambda: f64) -> Option<Step> {
    let n = lin.u.nrows();
    let mut s = lin.u.clone();
    for d in 0..n {
        s[(d, d)] += lambda * lin.u[(d, d)].max(1e-12);
    }
    let mut rhs = lin.gi.clone();
    let mut inv = Vec::with_capacity(lin.views.len());
    for (vv, gv, w) in &lin.views {
        let mut a = *vv;
        for d in 0..6 {
            a[(d, d)] += lambda * vv[(d, d)].max(1e-12);
        }
        let ai = a.cholesky()?.inverse();
        let y = w * ai;
        s -= &y * w.transpose();
        rhs -= &y * gv;
        inv.push(ai);
    }
    let di = if n == 0 {
        DVector::zeros(0)
    } else {
        s.clone().cholesky()?.solve(&rhs)
    };
    let dv = lin
        .views
        .iter()
        .zip(&inv)
        .map(|((_, gv, w), ai)| {
            let g = gv - w.transpose() * &di;
            ai * g
        })
        .collect();
    Some((di, dv, s))
}

/// Levenberg-Marquardt from `calib` and `poses` with `params` free.
pub fn solve(
    mut calib: CameraCalibration,
    mut poses: Vec<Isometry3<f64>>,
    views: &[View],
    params: &[Param],
    max_iterations: usize,
) -> Option<Solution> {
    let mut lin = linearise(&calib, params, views, &poses)?;
    let mut lambda = 1e-3;
    let mut it = 0;
    while it < max_iterations {
        it += 1;
        let Some((di, dv, _)) = step(&lin, lambda) else {
            lambda *= 10.0;
            if lambda > 1e10 {
                break;
            }
            continue;
        };
        let mut cand = calib.clone();
        for (p, d) in params.iter().zip(di.iter()) {
            p.add(&mut cand, *d);
        }
        let cand_poses: Vec<Isometry3<f64>> =
            poses.iter().zip(&dv).map(|(p, d)| perturb(p, d)).collect();
        let ok = cand.fx > 0.0 && cand.fy > 0.0;
        match cost(&cand, views, &cand_poses) {
            Some((c2, _)) if ok && c2 <= lin.cost => {
                let small = di.amax() < 1e-12 && dv.iter().all(|d| d.amax() < 1e-12);
                let done = small || lin.cost - c2 < 1e-12 * lin.cost.max(1e-30);
                calib = cand;
                poses = cand_poses;
                lambda = (lambda * 0.1).max(1e-12);
                lin = linearise(&calib, params, views, &poses)?;
                if done {
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e10 {
                    break;
                }
            }
        }
    }
    let (sq, points) = cost(&calib, views, &poses)?;
    let dof = (2 * points).saturating_sub(params.len() + 6 * views.len());
    let factor = if dof > 0 { sq / dof as f64 } else { f64::NAN };
    let covariance = step(&lin, 0.0)
        .and_then(|(_, _, s)| if s.nrows() == 0 { None } else { s.cholesky() })
        .map(|ch| ch.inverse() * factor);
    Some(Solution {
        view_rms_px: view_rms(&calib, views, &poses),
        calib,
        poses,
        params: params.to_vec(),
        covariance,
        rms_px: (sq / points.max(1) as f64).sqrt(),
        iterations: it,
        points,
    })
}

/// Parameter value, for reports.
pub fn value(p: Param, c: &CameraCalibration) -> f64 {
    p.get(c)
}
