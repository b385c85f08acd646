//! The bundle adjustment of a marker map: every camera pose, every marker pose but the
//! origin's and, when asked, some of the camera's intrinsics, on the whitened corner
//! residuals; and the covariance that is reported with the map.

use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix2x3, Matrix3, Matrix6, Point3, SMatrix, SVector, Vector6,
};

use super::{
    apply, planes, IntrinsicsReport, MapBuilder, MapEstimate, MapSettings, MappedMarker, Obs,
};
use crate::calibration::solve::{intrinsic_jacobian, step_intrinsics, Param};
use crate::pose::{marker_object_points, refine_pose_joint, MarkerCorners};
use crate::CameraCalibration;
use markhold_geometry::skew;

type Blocks8x6 = SMatrix<f64, 8, 6>;

/// What a repeated error is tied to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Repeat {
    /// The place in the image (a cell of the `FIELD_X` x `FIELD_Y` grid).
    ImageCell,
    /// One corner of one marker.
    MarkerCorner,
}

/// The grid over the image on which the residuals' field is measured.
const FIELD_X: usize = 8;
const FIELD_Y: usize = 6;

/// A free marker's own block: (marker, Jm^T Jm, Jm^T r, Jm^T Ji).
type MarkerBlock = (usize, Matrix6<f64>, Vector6<f64>, DMatrix<f64>);

/// One observation linearised: whitened residual, whitened Jacobians w.r.t. the camera
/// pose, the marker pose and the free intrinsics, and the raw squared residual.
struct Linear {
    r: SVector<f64, 8>,
    /// Whitened displacement of the corners when the marker's size grows by 1
    /// (relative).
    size: SVector<f64, 8>,
    jc: Blocks8x6,
    jm: Blocks8x6,
    ji: DMatrix<f64>,
    raw: f64,
}

/// Residuals of one observation (`None`: a corner behind the camera).
fn observation(
    calib: &CameraCalibration,
    params: &[Param],
    obj: &[Point3<f64>; 4],
    o: &Obs,
    t_cam_site: &Isometry3<f64>,
    t_site_marker: &Isometry3<f64>,
) -> Option<Linear> {
    let mut r = SVector::<f64, 8>::zeros();
    let mut jc = Blocks8x6::zeros();
    let mut jm = Blocks8x6::zeros();
    let mut ji = DMatrix::zeros(8, params.len());
    let mut size = SVector::<f64, 8>::zeros();
    let r_cs: Matrix3<f64> = *t_cam_site.rotation.to_rotation_matrix().matrix();
    let r_sm = t_site_marker.rotation.to_rotation_matrix();
    for (i, x) in obj.iter().enumerate() {
        let rx = r_sm * x.coords;
        let q = rx + t_site_marker.translation.vector;
        let rq = r_cs * q;
        let p = rq + t_cam_site.translation.vector;
        if p.z <= 1e-9 {
            return None;
        }
        let iz = 1.0 / p.z;
        let (nx, ny) = (p.x * iz, p.y * iz);
        let (uv, dd) = calib.distort_with_jacobian(nx, ny);
        let d = dd * Matrix2x3::new(iz, 0.0, -nx * iz, 0.0, iz, -ny * iz);
        let e = o.img[i] - uv;
        r[2 * i] = e.x;
        r[2 * i + 1] = e.y;
        // The object point scaled by 1 + s moves the camera point by R_cs R_sm X s.
        let ds = d * (r_cs * rx);
        size[2 * i] = ds.x;
        size[2 * i + 1] = ds.y;
        // Camera: dp/d dt = I, dp/d dtheta = -[R_cs q]x.
        let dc_rot = d * (-skew(&rq));
        // Marker: dq/d dtau = I, dq/d dphi = -[R_sm X]x, dp/dq = R_cs.
        let dm_t = d * r_cs;
        let dm_rot = dm_t * (-skew(&rx));
        for c in 0..3 {
            for k in 0..2 {
                jc[(2 * i + k, c)] = d[(k, c)];
                jc[(2 * i + k, 3 + c)] = dc_rot[(k, c)];
                jm[(2 * i + k, c)] = dm_t[(k, c)];
                jm[(2 * i + k, 3 + c)] = dm_rot[(k, c)];
            }
        }
        if !params.is_empty() {
            let j = intrinsic_jacobian(calib, params, nx, ny);
            ji.rows_mut(2 * i, 2).copy_from(&j);
        }
    }
    let raw = r.norm_squared();
    let w = DMatrix::from_fn(8, 8, |a, b| o.white[(a, b)]);
    Some(Linear {
        r: o.white * r,
        size: o.white * size,
        jc: o.white * jc,
        jm: o.white * jm,
        ji: w * ji,
        raw,
    })
}

/// One frame's share of the normal equations.
struct FrameTerms {
    cost: f64,
    /// Camera block, its gradient, its coupling with each free marker it saw and with
    /// the intrinsics (6 x ni).
    hff: Matrix6<f64>,
    gf: Vector6<f64>,
    coupling: Vec<(usize, Matrix6<f64>)>,
    ci: DMatrix<f64>,
    /// The free markers' own blocks.
    own: Vec<MarkerBlock>,
    /// The intrinsics' own block and gradient.
    hii: DMatrix<f64>,
    gi: DVector<f64>,
}

/// The normal equations at one point.
struct Linearised {
    cost: f64,
    frames: Vec<FrameTerms>,
    markers: Vec<(Matrix6<f64>, Vector6<f64>)>,
    hmi: Vec<DMatrix<f64>>,
    hii: DMatrix<f64>,
    gi: DVector<f64>,
}

/// A step: per camera, the global unknowns (free markers stacked, then the intrinsics),
/// and the reduced matrix.
type Step = (Vec<Vector6<f64>>, DVector<f64>, DMatrix<f64>);

#[derive(Clone)]
pub(super) struct Adjustment<'a> {
    b: &'a MapBuilder,
    origin: usize,
    obj: Vec<[Point3<f64>; 4]>,
    /// Index of each marker among the free ones (`None`: the origin).
    free: Vec<Option<usize>>,
    n_free: usize,
    t_site: Vec<Isometry3<f64>>,
    t_cam: Vec<Isometry3<f64>>,
    /// Observations in use (false: left out as an outlier).
    used: Vec<bool>,
    /// Start of each frame's observations in `b.obs`.
    frame_start: Vec<usize>,
    calib: CameraCalibration,
    params: Vec<Param>,
}

impl<'a> Adjustment<'a> {
    pub(super) fn new(
        b: &'a MapBuilder,
        origin: usize,
        placed: Vec<Option<Isometry3<f64>>>,
        calib: CameraCalibration,
        params: Vec<Param>,
    ) -> Self {
        let t_site: Vec<Isometry3<f64>> = placed
            .into_iter()
            .map(|p| p.unwrap_or_else(Isometry3::identity))
            .collect();
        let obj: Vec<[Point3<f64>; 4]> = b
            .markers
            .iter()
            .map(|(_, s)| marker_object_points(*s))
            .collect();
        let mut free = vec![None; b.markers.len()];
        let mut n_free = 0;
        for (m, f) in free.iter_mut().enumerate() {
            if m != origin {
                *f = Some(n_free);
                n_free += 1;
            }
        }
        let mut frame_start = Vec::with_capacity(b.frames_kept + 1);
        for (i, o) in b.obs.iter().enumerate() {
            if frame_start.len() == o.frame {
                frame_start.push(i);
            }
        }
        frame_start.push(b.obs.len());
        // Each camera from the start map: every observation's marker proposes a pose,
        // refined on all the frame's markers; the lowest residual wins.
        let t_cam = frame_start
            .windows(2)
            .map(|w| {
                let frame = &b.obs[w[0]..w[1]];
                let corners: Vec<MarkerCorners> = frame
                    .iter()
                    .map(|o| MarkerCorners {
                        obj: obj[o.marker].map(|p| t_site[o.marker] * p),
                        img: o.img,
                        white: o.white,
                        ..MarkerCorners::default()
                    })
                    .collect();
                let used = vec![true; frame.len()];
                let mut best: Option<(f64, Isometry3<f64>)> = None;
                for o in frame {
                    let init = o.t_cam_marker * t_site[o.marker].inverse();
                    if let Some(p) = refine_pose_joint(&calib, &corners, &used, &init) {
                        if best.is_none_or(|(r, _)| p.reproj_rms_px < r) {
                            best = Some((p.reproj_rms_px, p.t_cam_marker));
                        }
                    }
                }
                best.map_or(
                    frame[0].t_cam_marker * t_site[frame[0].marker].inverse(),
                    |b| b.1,
                )
            })
            .collect();
        Self {
            b,
            origin,
            obj,
            free,
            n_free,
            t_site,
            t_cam,
            used: vec![true; b.obs.len()],
            frame_start,
            calib,
            params,
        }
    }

    /// This adjustment with `params` of the intrinsics free.
    pub(super) fn with_intrinsics(&self, params: Vec<Param>) -> Self {
        Self {
            params,
            ..self.clone()
        }
    }

    pub(super) fn calibration(&self) -> &CameraCalibration {
        &self.calib
    }

    fn n_global(&self) -> usize {
        6 * self.n_free + self.params.len()
    }

    /// Whitened cost and raw squared residual with corners counted (`None`: a corner
    /// behind a camera).
    fn cost_at(
        &self,
        t_cam: &[Isometry3<f64>],
        t_site: &[Isometry3<f64>],
        calib: &CameraCalibration,
    ) -> Option<(f64, f64, usize)> {
        let (mut cost, mut raw, mut n) = (0.0, 0.0, 0);
        for (o, _) in self.b.obs.iter().zip(&self.used).filter(|(_, u)| **u) {
            let l = observation(
                calib,
                &[],
                &self.obj[o.marker],
                o,
                &t_cam[o.frame],
                &t_site[o.marker],
            )?;
            cost += l.r.norm_squared();
            raw += l.raw;
            n += 4;
        }
        Some((cost, raw, n))
    }

    pub(super) fn rms_px(&self) -> f64 {
        self.cost_at(&self.t_cam, &self.t_site, &self.calib)
            .map_or(f64::NAN, |(_, raw, n)| (raw / n.max(1) as f64).sqrt())
    }

    /// Frame `f`'s terms at the current estimate.
    fn frame_terms(&self, f: usize) -> Option<FrameTerms> {
        let ni = self.params.len();
        let mut t = FrameTerms {
            cost: 0.0,
            hff: Matrix6::zeros(),
            gf: Vector6::zeros(),
            coupling: Vec::new(),
            ci: DMatrix::zeros(6, ni),
            own: Vec::new(),
            hii: DMatrix::zeros(ni, ni),
            gi: DVector::zeros(ni),
        };
        for i in self.frame_start[f]..self.frame_start[f + 1] {
            if !self.used[i] {
                continue;
            }
            let o = &self.b.obs[i];
            let l = observation(
                &self.calib,
                &self.params,
                &self.obj[o.marker],
                o,
                &self.t_cam[o.frame],
                &self.t_site[o.marker],
            )?;
            t.cost += l.r.norm_squared();
            t.hff += l.jc.transpose() * l.jc;
            t.gf += l.jc.transpose() * l.r;
            if ni > 0 {
                let jc = DMatrix::from_fn(8, 6, |a, b| l.jc[(a, b)]);
                let r = DVector::from_fn(8, |a, _| l.r[a]);
                t.ci += jc.transpose() * &l.ji;
                t.hii += l.ji.transpose() * &l.ji;
                t.gi += l.ji.transpose() * r;
            }
            if let Some(k) = self.free[o.marker] {
                t.coupling.push((k, l.jc.transpose() * l.jm));
                let jmi = if ni > 0 {
                    DMatrix::from_fn(8, 6, |a, b| l.jm[(a, b)]).transpose() * &l.ji
                } else {
                    DMatrix::zeros(6, 0)
                };
                t.own
                    .push((k, l.jm.transpose() * l.jm, l.jm.transpose() * l.r, jmi));
            }
        }
        Some(t)
    }

    fn linearise(&self) -> Option<Linearised> {
        let ni = self.params.len();
        let mut lin = Linearised {
            cost: 0.0,
            frames: Vec::with_capacity(self.t_cam.len()),
            markers: vec![(Matrix6::zeros(), Vector6::zeros()); self.n_free],
            hmi: vec![DMatrix::zeros(6, ni); self.n_free],
            hii: DMatrix::zeros(ni, ni),
            gi: DVector::zeros(ni),
        };
        for f in 0..self.t_cam.len() {
            let t = self.frame_terms(f)?;
            lin.cost += t.cost;
            for (k, h, g, hmi) in &t.own {
                lin.markers[*k].0 += h;
                lin.markers[*k].1 += g;
                if ni > 0 {
                    lin.hmi[*k] += hmi;
                }
            }
            lin.hii += &t.hii;
            lin.gi += &t.gi;
            lin.frames.push(t);
        }
        Some(lin)
    }

    /// The damped step by the Schur complement on the global unknowns (free markers,
    /// intrinsics); also the reduced matrix (for the covariance). `None`: singular.
    fn step(&self, lin: &Linearised, lambda: f64) -> Option<Step> {
        let damp = |h: &Matrix6<f64>| {
            let mut a = *h;
            for d in 0..6 {
                a[(d, d)] += lambda * h[(d, d)].max(1e-9);
            }
            a
        };
        let ni = self.params.len();
        let io = 6 * self.n_free;
        let dim = self.n_global();
        let mut s = DMatrix::<f64>::zeros(dim, dim);
        let mut rhs = DVector::<f64>::zeros(dim);
        for (k, (h, g)) in lin.markers.iter().enumerate() {
            s.fixed_view_mut::<6, 6>(6 * k, 6 * k).copy_from(&damp(h));
            rhs.fixed_rows_mut::<6>(6 * k).copy_from(g);
            if ni > 0 {
                s.view_mut((6 * k, io), (6, ni)).copy_from(&lin.hmi[k]);
                s.view_mut((io, 6 * k), (ni, 6))
                    .copy_from(&lin.hmi[k].transpose());
            }
        }
        if ni > 0 {
            let mut hii = lin.hii.clone();
            for d in 0..ni {
                hii[(d, d)] += lambda * lin.hii[(d, d)].max(1e-12);
            }
            s.view_mut((io, io), (ni, ni)).copy_from(&hii);
            rhs.rows_mut(io, ni).copy_from(&lin.gi);
        }
        let mut a_inv = Vec::with_capacity(lin.frames.len());
        for t in &lin.frames {
            if t.hff.iter().all(|v| *v == 0.0) {
                // Every observation of the frame left out: its camera stays.
                a_inv.push(Matrix6::zeros());
                continue;
            }
            let inv = damp(&t.hff).cholesky()?.inverse();
            reduce(&mut s, &mut rhs, t, &inv, io);
            a_inv.push(inv);
        }
        let dg = if dim == 0 {
            DVector::zeros(0)
        } else {
            s.clone().cholesky()?.solve(&rhs)
        };
        let di = dg.rows(io, ni).into_owned();
        let dc = lin
            .frames
            .iter()
            .zip(&a_inv)
            .map(|(t, inv)| {
                let mut g = t.gf;
                for (k, hfk) in &t.coupling {
                    g -= hfk * dg.fixed_rows::<6>(6 * k);
                }
                if ni > 0 {
                    let c = &t.ci * &di;
                    g -= Vector6::from_fn(|a, _| c[a]);
                }
                inv * g
            })
            .collect();
        Some((dc, dg, s))
    }

    fn moved(
        &self,
        dc: &[Vector6<f64>],
        dg: &DVector<f64>,
    ) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>, CameraCalibration) {
        let t_cam = self
            .t_cam
            .iter()
            .zip(dc)
            .map(|(t, d)| apply(t, d.as_slice()))
            .collect();
        let t_site = self
            .t_site
            .iter()
            .zip(&self.free)
            .map(|(t, f)| match f {
                Some(k) => apply(t, &dg.as_slice()[6 * k..6 * k + 6]),
                None => *t,
            })
            .collect();
        let mut calib = self.calib.clone();
        step_intrinsics(&mut calib, &self.params, &dg.as_slice()[6 * self.n_free..]);
        (t_cam, t_site, calib)
    }

    /// Levenberg-Marquardt to convergence; returns the iterations taken.
    pub(super) fn run(&mut self, max_iterations: usize) -> usize {
        let mut lambda = 1e-4;
        let mut it = 0;
        let Some(mut lin) = self.linearise() else {
            return 0;
        };
        while it < max_iterations {
            it += 1;
            let Some((dc, dg, _)) = self.step(&lin, lambda) else {
                lambda *= 10.0;
                if lambda > 1e8 {
                    break;
                }
                continue;
            };
            let (t_cam, t_site, calib) = self.moved(&dc, &dg);
            let sane = calib.fx > 0.0 && calib.fy > 0.0;
            match self.cost_at(&t_cam, &t_site, &calib) {
                Some((cost, _, _)) if sane && cost <= lin.cost => {
                    let small = dg.amax() < 1e-10 && dc.iter().all(|d| d.amax() < 1e-10);
                    let done = small || lin.cost - cost < 1e-10 * lin.cost.max(1e-30);
                    self.t_cam = t_cam;
                    self.t_site = t_site;
                    self.calib = calib;
                    lambda = (lambda * 0.1).max(1e-12);
                    match self.linearise() {
                        Some(l) => lin = l,
                        None => break,
                    }
                    if done {
                        break;
                    }
                }
                _ => {
                    lambda *= 10.0;
                    if lambda > 1e8 {
                        break;
                    }
                }
            }
        }
        it
    }

    /// RMS reprojection error of each observation, pixels (NaN: behind the camera).
    fn observation_rms(&self) -> Vec<f64> {
        self.b
            .obs
            .iter()
            .map(|o| {
                observation(
                    &self.calib,
                    &[],
                    &self.obj[o.marker],
                    o,
                    &self.t_cam[o.frame],
                    &self.t_site[o.marker],
                )
                .map_or(f64::NAN, |l| (l.raw / 4.0).sqrt())
            })
            .collect()
    }

    /// Leave out the observations far above the median residual (a wrong corner, a
    /// marker half hidden); a marker keeps at least 3 observations. Returns how many.
    pub(super) fn reject(&mut self, settings: &MapSettings) -> usize {
        let rms = self.observation_rms();
        let mut sorted: Vec<f64> = rms.iter().copied().filter(|r| r.is_finite()).collect();
        if sorted.is_empty() {
            return 0;
        }
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let gate = (settings.outlier_median_factor * median).max(settings.outlier_floor_px);
        let mut left = vec![0usize; self.b.markers.len()];
        for o in &self.b.obs {
            left[o.marker] += 1;
        }
        // Worst first, so a marker's 3 kept are its best.
        let mut order: Vec<usize> = (0..rms.len()).collect();
        order.sort_by(|a, b| rms[*b].total_cmp(&rms[*a]));
        let mut n = 0;
        for i in order {
            let bad = !rms[i].is_finite() || rms[i] > gate;
            let m = self.b.obs[i].marker;
            if bad && left[m] > 3 {
                self.used[i] = false;
                left[m] -= 1;
                n += 1;
            }
        }
        n
    }

    /// The frames grouped by viewpoint: greedily, a frame joins the first group whose
    /// first frame's camera is within `viewpoint_m` and `viewpoint_deg` of its own.
    pub(super) fn viewpoints(&self, settings: &MapSettings) -> Vec<Vec<usize>> {
        let mut groups: Vec<(Isometry3<f64>, Vec<usize>)> = Vec::new();
        let max_angle = settings.viewpoint_deg.to_radians();
        for (f, t) in self.t_cam.iter().enumerate() {
            let cam = t.inverse();
            match groups.iter_mut().find(|(rep, _)| {
                (rep.translation.vector - cam.translation.vector).norm() <= settings.viewpoint_m
                    && rep.rotation.angle_to(&cam.rotation) <= max_angle
            }) {
                Some((_, g)) => g.push(f),
                None => groups.push((cam, vec![f])),
            }
        }
        groups.into_iter().map(|(_, g)| g).collect()
    }

    /// The group of corner `k` of observation `o` for a kind of repeated error, and the
    /// number of groups.
    fn group(&self, kind: Repeat, o: &Obs, k: usize) -> usize {
        match kind {
            Repeat::ImageCell => self.cell(&o.img[k]),
            Repeat::MarkerCorner => 4 * o.marker + k,
        }
    }

    fn groups(&self, kind: Repeat) -> usize {
        match kind {
            Repeat::ImageCell => FIELD_X * FIELD_Y,
            Repeat::MarkerCorner => 4 * self.b.markers.len(),
        }
    }

    /// The image cell (of a `FIELD_X` x `FIELD_Y` grid) of a pixel.
    fn cell(&self, p: &nalgebra::Vector2<f64>) -> usize {
        let (w, h) = (self.calib.width as f64, self.calib.height as f64);
        let i = ((p.x / w * FIELD_X as f64).max(0.0) as usize).min(FIELD_X - 1);
        let j = ((p.y / h * FIELD_Y as f64).max(0.0) as usize).min(FIELD_Y - 1);
        j * FIELD_X + i
    }

    /// The part of the residuals repeated within each group of `kind` (the same
    /// displacement in every frame wherever a corner falls in one cell of the image, or
    /// for one corner of one marker), as a variance per coordinate, pixels^2, and the
    /// residuals' whole variance per coordinate.
    fn repeated_residual(&self, kind: Repeat) -> (f64, f64) {
        let n = self.groups(kind);
        let (mut sum, mut sq, mut cnt) = (vec![[0.0; 2]; n], vec![0.0; n], vec![0usize; n]);
        for (o, _) in self.b.obs.iter().zip(&self.used).filter(|(_, u)| **u) {
            let Some(l) = observation(
                &self.calib,
                &[],
                &self.obj[o.marker],
                o,
                &self.t_cam[o.frame],
                &self.t_site[o.marker],
            ) else {
                continue;
            };
            // The raw residual: undo the whitening.
            let Some(wi) = o.white.try_inverse() else {
                continue;
            };
            let r = wi * l.r;
            for k in 0..4 {
                let c = self.group(kind, o, k);
                let (x, y) = (r[2 * k], r[2 * k + 1]);
                sum[c][0] += x;
                sum[c][1] += y;
                sq[c] += x * x + y * y;
                cnt[c] += 1;
            }
        }
        let total: usize = cnt.iter().sum();
        if total == 0 {
            return (0.0, 0.0);
        }
        let v_tot = sq.iter().sum::<f64>() / (2 * total) as f64;
        let mut field = 0.0;
        for c in 0..n {
            if cnt[c] < 2 {
                continue;
            }
            let m = cnt[c] as f64;
            let (mx, my) = (sum[c][0] / m, sum[c][1] / m);
            let within = (sq[c] / m - mx * mx - my * my).max(0.0) / 2.0;
            // E[mean^2] = field^2 + within / m, per coordinate.
            field += m * ((mx * mx + my * my) / 2.0 - within / (m - 1.0)).max(0.0);
        }
        (field / total as f64, v_tot)
    }

    /// How displacements of the corners move the global unknowns, cameras eliminated:
    /// `pattern` gives, for an observation, each corner displacement pattern (whitened,
    /// 8 values) and the column it adds to; returns `B` (global x `columns`), column `c`
    /// the reduced gradient of a unit of pattern `c` in every frame. The solution moves
    /// by `S^-1 B` per unit.
    fn gradients(
        &self,
        columns: usize,
        pattern: impl Fn(&Obs, &Linear) -> Vec<(usize, SVector<f64, 8>)>,
    ) -> Option<DMatrix<f64>> {
        let g = self.n_global();
        let io = 6 * self.n_free;
        let ni = self.params.len();
        let mut b = DMatrix::<f64>::zeros(g, columns);
        for f in 0..self.t_cam.len() {
            let t = self.frame_terms(f)?;
            if t.hff.iter().all(|v| *v == 0.0) {
                continue;
            }
            let inv = t.hff.cholesky()?.inverse();
            // Per column: the camera's and the global gradients of this frame.
            let mut vc: Vec<Vector6<f64>> = vec![Vector6::zeros(); columns];
            let mut vg = DMatrix::<f64>::zeros(g, columns);
            for i in self.frame_start[f]..self.frame_start[f + 1] {
                if !self.used[i] {
                    continue;
                }
                let o = &self.b.obs[i];
                let Some(l) = observation(
                    &self.calib,
                    &self.params,
                    &self.obj[o.marker],
                    o,
                    &self.t_cam[o.frame],
                    &self.t_site[o.marker],
                ) else {
                    continue;
                };
                for (col, w) in pattern(o, &l) {
                    vc[col] += l.jc.transpose() * w;
                    if let Some(m) = self.free[o.marker] {
                        let gm = l.jm.transpose() * w;
                        for d in 0..6 {
                            vg[(6 * m + d, col)] += gm[d];
                        }
                    }
                    if ni > 0 {
                        let wd = DVector::from_fn(8, |x, _| w[x]);
                        let gi = l.ji.transpose() * wd;
                        for d in 0..ni {
                            vg[(io + d, col)] += gi[d];
                        }
                    }
                }
            }
            // Eliminate the camera: g - H_gf H_ff^-1 v.
            for (col, v) in vc.iter().enumerate() {
                if v.iter().all(|x| *x == 0.0) {
                    continue;
                }
                let y = inv * v;
                for (k, hfk) in &t.coupling {
                    let d = hfk.transpose() * y;
                    for r in 0..6 {
                        vg[(6 * k + r, col)] -= d[r];
                    }
                }
                if ni > 0 {
                    let yd = DVector::from_fn(6, |x, _| y[x]);
                    let d = t.ci.transpose() * yd;
                    for r in 0..ni {
                        vg[(io + r, col)] -= d[r];
                    }
                }
            }
            b += vg;
        }
        Some(b)
    }

    /// `B B^T` of a unit displacement repeated within each group of `kind`, per axis.
    fn repeated_gradients(&self, kind: Repeat) -> Option<DMatrix<f64>> {
        let b = self.gradients(2 * self.groups(kind), |o, _| {
            (0..8)
                .map(|j| {
                    let (k, a) = (j / 2, j % 2);
                    (
                        2 * self.group(kind, o, k) + a,
                        o.white.column(2 * k + a).into_owned(),
                    )
                })
                .collect()
        })?;
        Some(&b * b.transpose())
    }

    /// `B` of each marker's size (relative: its corners' object points scaled by 1 +
    /// unit), one column per marker.
    fn size_gradients(&self) -> Option<DMatrix<f64>> {
        self.gradients(self.b.markers.len(), |o, l| vec![(o.marker, l.size)])
    }

    /// Covariance of the global unknowns (free markers, then intrinsics), the
    /// a-posteriori variance factor, and the viewpoints counted.
    ///
    /// The part of the residuals that repeats from frame to frame is model error that
    /// no number of frames averages away: a displacement tied to the place in the image
    /// (an unmodelled lens or port: the mean residual of each cell of an 8 x 6 grid) or
    /// to a marker's corner (a print, an edge profile: the mean residual of each corner
    /// of each marker), each measured as the variance of the group means beyond what
    /// the scatter within a group explains. Each is propagated as a displacement common
    /// to every corner of its group, of that variance: `S^-1 (B B^T) S^-1 v`. The rest
    /// scales the corner-noise covariance `S^-1` as the a-posteriori variance factor
    /// does.
    pub(super) fn covariance(&self, settings: &MapSettings) -> Option<(DMatrix<f64>, f64, usize)> {
        let lin = self.linearise()?;
        let (_, _, s) = self.step(&lin, 0.0)?;
        let viewpoints = self.viewpoints(settings).len();
        if s.nrows() == 0 {
            return Some((s, 1.0, viewpoints));
        }
        let p = s.clone().cholesky()?.inverse();
        let n_res = 8 * self.used.iter().filter(|u| **u).count();
        let n_par = 6 * self.t_cam.len() + self.n_global();
        let s2 = if n_res > n_par {
            lin.cost / (n_res - n_par) as f64
        } else {
            1.0
        };
        let mut repeated = 0.0;
        let mut cov = DMatrix::zeros(s.nrows(), s.ncols());
        let mut v_all = 0.0;
        for kind in [Repeat::ImageCell, Repeat::MarkerCorner] {
            let (v, v_tot) = self.repeated_residual(kind);
            v_all = v_tot;
            if v > 0.0 {
                cov += &p * self.repeated_gradients(kind)? * &p * v;
                repeated += v;
            }
        }
        let alpha = if v_all > 0.0 {
            (repeated / v_all).min(1.0)
        } else {
            0.0
        };
        let noise = if s2 <= 1.0 {
            s2
        } else {
            (s2 * (1.0 - alpha)).max(1.0)
        };
        cov += &p * noise;
        // The printed sizes: each marker's own error, and one common to all (the scale).
        if settings.size_sigma > 0.0 || settings.scale_sigma > 0.0 {
            let b = self.size_gradients()?;
            let moved = &p * &b;
            cov += &moved * moved.transpose() * settings.size_sigma.powi(2);
            let common = moved.column_sum();
            cov += &common * common.transpose() * settings.scale_sigma.powi(2);
        }
        Some((cov, s2, viewpoints))
    }

    /// One standard deviation of each free intrinsic (`None`: singular).
    pub(super) fn intrinsic_sigmas(&self, settings: &MapSettings) -> Option<Vec<f64>> {
        let (cov, _, _) = self.covariance(settings)?;
        let io = 6 * self.n_free;
        Some(
            (0..self.params.len())
                .map(|i| cov[(io + i, io + i)].max(0.0).sqrt())
                .collect(),
        )
    }

    /// The farthest corner used from the optical axis, in normalised undistorted units.
    pub(super) fn max_normalised_radius(&self) -> f64 {
        self.b
            .obs
            .iter()
            .zip(&self.used)
            .filter(|(_, u)| **u)
            .flat_map(|(o, _)| o.img.iter())
            .map(|p| self.calib.undistort_pixel(p.x, p.y).norm())
            .fold(0.0, f64::max)
    }

    pub(super) fn estimate(
        &self,
        origin: u32,
        initial_rms_px: f64,
        iterations: usize,
        outliers: usize,
        intrinsics: IntrinsicsReport,
        settings: &MapSettings,
    ) -> MapEstimate {
        let rms = self.observation_rms();
        let nm = self.b.markers.len();
        let (mut frames, mut out, mut sq) = (vec![0usize; nm], vec![0usize; nm], vec![0.0; nm]);
        for ((o, u), r) in self.b.obs.iter().zip(&self.used).zip(&rms) {
            if *u {
                frames[o.marker] += 1;
                sq[o.marker] += r * r;
            } else {
                out[o.marker] += 1;
            }
        }
        let (cov, s2, viewpoints) = self.covariance(settings).unwrap_or_else(|| {
            (
                DMatrix::from_element(self.n_global(), self.n_global(), f64::NAN),
                f64::NAN,
                0,
            )
        });
        let block = |m: usize| -> Matrix6<f64> {
            match self.free[m] {
                Some(k) => Matrix6::from_fn(|a, b| cov[(6 * k + a, 6 * k + b)]),
                None => Matrix6::zeros(),
            }
        };
        let covs: Vec<Matrix6<f64>> = (0..nm).map(block).collect();
        let (planes, plane_factor) = planes::check(
            &self.b.planes,
            &self.b.markers,
            &self.t_site,
            &self.obj,
            &covs,
        );
        let scale = plane_factor.max(1.0);
        let order = std::iter::once(self.origin).chain((0..nm).filter(|m| *m != self.origin));
        let markers = order
            .map(|m| {
                let (id, size_m) = self.b.markers[m];
                let c = covs[m] * scale;
                let worst = |off: usize| {
                    (0..3)
                        .map(|d| c[(off + d, off + d)])
                        .fold(0.0, f64::max)
                        .sqrt()
                };
                MappedMarker {
                    id,
                    size_m,
                    t_site_marker: self.t_site[m],
                    frames: frames[m],
                    outliers: out[m],
                    rms_px: (sq[m] / frames[m].max(1) as f64).sqrt(),
                    sigma_position_m: worst(0),
                    sigma_angle_deg: worst(3).to_degrees(),
                    covariance: c,
                }
            })
            .collect();
        MapEstimate {
            origin,
            markers,
            frames_used: self.t_cam.len(),
            observations: self.used.iter().filter(|u| **u).count(),
            outliers,
            initial_rms_px,
            rms_px: self.rms_px(),
            iterations,
            intrinsics,
            viewpoints,
            variance_factor: s2,
            planes,
            plane_factor,
        }
    }
}

/// Eliminate one frame's camera (its block inverted, `inv`) from the reduced system
/// `s`, `rhs` (free markers at 6 k, intrinsics at `io`).
fn reduce(
    s: &mut DMatrix<f64>,
    rhs: &mut DVector<f64>,
    t: &FrameTerms,
    inv: &Matrix6<f64>,
    io: usize,
) {
    let ni = t.ci.ncols();
    let gf = DVector::from_fn(6, |a, _| t.gf[a]);
    let inv_d = DMatrix::from_fn(6, 6, |a, b| inv[(a, b)]);
    let yi = if ni > 0 {
        Some(t.ci.transpose() * &inv_d)
    } else {
        None
    };
    for (k, hfk) in &t.coupling {
        let y = hfk.transpose() * inv;
        let mut rk = rhs.fixed_rows_mut::<6>(6 * k);
        rk -= y * t.gf;
        for (l, hfl) in &t.coupling {
            let mut blk = s.fixed_view_mut::<6, 6>(6 * k, 6 * l);
            blk -= y * hfl;
        }
        if ni > 0 {
            let yd = DMatrix::from_fn(6, 6, |a, b| y[(a, b)]);
            let c = &yd * &t.ci;
            let mut blk = s.view_mut((6 * k, io), (6, ni));
            blk -= &c;
            let mut blk = s.view_mut((io, 6 * k), (ni, 6));
            blk -= c.transpose();
        }
    }
    if let Some(yi) = yi {
        let mut ri = rhs.rows_mut(io, ni);
        ri -= &yi * gf;
        let mut blk = s.view_mut((io, io), (ni, ni));
        blk -= &yi * &t.ci;
    }
}
