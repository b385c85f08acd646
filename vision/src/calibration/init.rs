//! Starting values of a calibration: each view's homography from the target plane to
//! the image, the focal lengths from the homographies with the principal point at the
//! image centre (the method of OpenCV's `initIntrinsicParams2D`, from Zhang 2000's
//! constraints on the image of the absolute conic), and each view's pose from its
//! homography.

use nalgebra::{DMatrix, Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::View;

/// The homography `H` with `img ~ H (x, y, 1)` for the target points (all at z = 0) of
/// `view`: the normalised direct linear transform (Hartley & Zisserman 2003, alg. 4.2).
/// `None` with fewer than 4 points or a degenerate layout.
pub fn homography(view: &View) -> Option<Matrix3<f64>> {
    let n = view.points.len();
    if n < 4 {
        return None;
    }
    let norm = |pts: &mut dyn Iterator<Item = (f64, f64)>| -> Matrix3<f64> {
        let v: Vec<(f64, f64)> = pts.collect();
        let (mx, my) = v.iter().fold((0.0, 0.0), |a, p| (a.0 + p.0, a.1 + p.1));
        let (mx, my) = (mx / v.len() as f64, my / v.len() as f64);
        let d = v.iter().map(|p| (p.0 - mx).hypot(p.1 - my)).sum::<f64>() / v.len() as f64;
        let s = if d > 0.0 {
            std::f64::consts::SQRT_2 / d
        } else {
            1.0
        };
        Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
    };
    let tobj = norm(&mut view.points.iter().map(|p| (p.0.x, p.0.y)));
    let timg = norm(&mut view.points.iter().map(|p| (p.1.x, p.1.y)));
    let mut a = DMatrix::<f64>::zeros(2 * n, 9);
    for (i, (o, m)) in view.points.iter().enumerate() {
        let p = tobj * Vector3::new(o.x, o.y, 1.0);
        let q = timg * Vector3::new(m.x, m.y, 1.0);
        let (x, y) = (p.x / p.z, p.y / p.z);
        let (u, v) = (q.x / q.z, q.y / q.z);
        let r0 = [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u];
        let r1 = [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v];
        for c in 0..9 {
            a[(2 * i, c)] = r0[c];
            a[(2 * i + 1, c)] = r1[c];
        }
    }
    // The right singular vector of the smallest singular value, through A^T A (9x9).
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hh = timg.try_inverse()? * hn * tobj;
    let s = hh[(2, 2)];
    (s.abs() > 1e-15 && hh.iter().all(|v| v.is_finite())).then(|| hh / s)
}

/// Focal lengths `(fx, fy)` from the views' homographies with the principal point at
/// `(cx, cy)` (zero skew): each homography gives two linear equations in `1/fx^2` and
/// `1/fy^2` (its first two columns are orthogonal and of equal length in the metric of
/// the image of the absolute conic). `same` solves for one focal length. `None` when
/// the equations do not fix them (every view face-on, or too few views).
pub fn focal_lengths(
    homographies: &[Matrix3<f64>],
    cx: f64,
    cy: f64,
    same: bool,
) -> Option<(f64, f64)> {
    let shift = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let mut rows: Vec<([f64; 2], f64)> = Vec::new();
    for h in homographies {
        let hc = shift * h;
        let mut c1: Vector3<f64> = hc.column(0).into();
        let mut c2: Vector3<f64> = hc.column(1).into();
        // Scale for conditioning: the equations are homogeneous in each column.
        c1 /= c1.norm();
        c2 /= c2.norm();
        let d1 = (c1 + c2) * 0.5;
        let d2 = (c1 - c2) * 0.5;
        rows.push(([c1.x * c2.x, c1.y * c2.y], -c1.z * c2.z));
        rows.push(([d1.x * d2.x, d1.y * d2.y], -d1.z * d2.z));
    }
    if same {
        let (mut aa, mut ab) = (0.0, 0.0);
        for (a, b) in &rows {
            let s = a[0] + a[1];
            aa += s * s;
            ab += s * b;
        }
        let w = ab / aa;
        if !(aa > 1e-12 && w > 0.0) {
            return None;
        }
        let f = 1.0 / w.sqrt();
        return Some((f, f));
    }
    let (mut m, mut r) = (
        nalgebra::Matrix2::<f64>::zeros(),
        nalgebra::Vector2::<f64>::zeros(),
    );
    for (a, b) in &rows {
        let av = nalgebra::Vector2::new(a[0], a[1]);
        m += av * av.transpose();
        r += av * *b;
    }
    // A near-singular system: the views do not tell fx from fy (or from the distance).
    let eig = m.symmetric_eigen();
    let (lo, hi) = (eig.eigenvalues.min(), eig.eigenvalues.max());
    if !(hi > 0.0 && lo > 1e-9 * hi) {
        return None;
    }
    let w = m.try_inverse()? * r;
    if !(w.x > 0.0 && w.y > 0.0) {
        return None;
    }
    Some((1.0 / w.x.sqrt(), 1.0 / w.y.sqrt()))
}

/// The target's pose in the camera frame from its homography and the camera matrix
/// `k` (Zhang 2000, sec. 3.1; the rotation made orthonormal by the nearest rotation).
pub fn pose_from_homography(h: &Matrix3<f64>, k: &Matrix3<f64>) -> Option<Isometry3<f64>> {
    let m = k.try_inverse()? * h;
    let (a, b, c) = (m.column(0), m.column(1), m.column(2));
    let lambda = 2.0 / (a.norm() + b.norm());
    // The target in front of the camera: its origin at positive depth.
    let sign = if c.z * lambda < 0.0 { -1.0 } else { 1.0 };
    let l = lambda * sign;
    let r1: Vector3<f64> = a * l;
    let r2: Vector3<f64> = b * l;
    let r3 = r1.cross(&r2);
    let t: Vector3<f64> = c * l;
    let r = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = r.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut rot = u * vt;
    if rot.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).neg_mut();
        rot = u2 * vt;
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rot));
    Some(Isometry3::from_parts(Translation3::from(t), q))
}
