//! A marker map from frames in which several markers are seen together: each marker's
//! pose in the site frame (the origin marker's frame), by chaining single-marker poses
//! through co-visible frames and then a bundle adjustment of every camera pose and every
//! marker pose on the corners' reprojection error.
//!
//! The bundle adjustment is Levenberg-Marquardt on the whitened corner residuals (the
//! same weighting as the tracker's pose: each marker's four corners with their 8x8
//! covariance). Its normal equations are solved through the Schur complement on the
//! marker poses: the camera poses of the frames are eliminated frame by frame (6x6
//! blocks), leaving a dense system of 6 per marker besides the origin (at most 186
//! unknowns), so thousands of frames cost little. The origin marker is held at the
//! identity: that fixes the gauge (the map's position and orientation); the scale comes
//! from the printed marker sizes.

use std::collections::HashMap;

use crate::config::MarkerConfig;
use crate::pose::{marker_object_points, refine_pose_joint, skew, MarkerCorners};
use crate::{CameraCalibration, MarkerTracker, VisionError};
use markhold_exposure::Frame;
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix2x3, Matrix3, Matrix6, Point3, SMatrix, SVector,
    Translation3, UnitQuaternion, Vector2, Vector3, Vector6,
};

/// One marker found in one frame, with its own pose (from its four corners alone).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeenMarker {
    pub id: u32,
    /// Sub-pixel corners in aruco order, pixels.
    pub img: [Vector2<f64>; 4],
    /// `C^-1` for the corners' covariance `C C^T` (order u0 v0 u1 v1 ...).
    pub white: SMatrix<f64, 8, 8>,
    /// The marker's pose in the camera frame from its corners alone.
    pub t_cam_marker: Isometry3<f64>,
}

/// Settings of [`MapBuilder::solve`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapSettings {
    /// Levenberg-Marquardt iterations at most, per pass (two passes: all observations,
    /// then without the outliers).
    pub max_iterations: usize,
    /// An observation (one marker in one frame) is an outlier when its corners' RMS
    /// reprojection error after the first pass exceeds this many times the median one...
    pub outlier_median_factor: f64,
    /// ... and this many pixels.
    pub outlier_floor_px: f64,
}

impl Default for MapSettings {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            outlier_median_factor: 5.0,
            outlier_floor_px: 1.0,
        }
    }
}

/// One marker of an estimated map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MappedMarker {
    pub id: u32,
    pub size_m: f64,
    /// Pose in the site frame (the identity for the origin marker).
    pub t_site_marker: Isometry3<f64>,
    /// Frames of the adjustment (two or more markers in view) it was used in.
    pub frames: usize,
    /// Observations of it left out as outliers.
    pub outliers: usize,
    /// RMS reprojection error of its corners over those frames, pixels.
    pub rms_px: f64,
    /// One standard deviation of its position, largest axis, metres, and of its
    /// orientation, largest axis, degrees: from the adjustment's covariance scaled by the
    /// a-posteriori variance factor (0 for the origin marker, which is fixed).
    pub sigma_position_m: f64,
    pub sigma_angle_deg: f64,
}

/// A marker map estimated by [`MapBuilder::solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct MapEstimate {
    pub origin: u32,
    /// Every marker, the origin first.
    pub markers: Vec<MappedMarker>,
    /// Frames of the adjustment (two or more markers in view).
    pub frames_used: usize,
    /// Observations (a marker in a frame) used, and left out as outliers.
    pub observations: usize,
    pub outliers: usize,
    /// RMS reprojection error over every corner used: from the chained start, and at the
    /// solution, pixels.
    pub initial_rms_px: f64,
    pub rms_px: f64,
    /// Levenberg-Marquardt iterations over both passes.
    pub iterations: usize,
}

#[derive(Debug, Clone, Copy)]
struct Obs {
    frame: usize,
    /// Index of the marker in the builder's list.
    marker: usize,
    img: [Vector2<f64>; 4],
    white: SMatrix<f64, 8, 8>,
    t_cam_marker: Isometry3<f64>,
}

/// Collects the markers seen per frame and solves for the map.
#[derive(Debug, Clone)]
pub struct MapBuilder {
    calib: CameraCalibration,
    /// (id, size) of each marker to map.
    markers: Vec<(u32, f64)>,
    index_of_id: HashMap<u32, usize>,
    /// Observations of the frames kept (two or more markers), by frame.
    obs: Vec<Obs>,
    frames_read: usize,
    frames_kept: usize,
    /// Frames each marker was seen in, alone or not.
    seen: Vec<usize>,
}

type Blocks8x6 = SMatrix<f64, 8, 6>;

impl MapBuilder {
    /// A builder for the markers of `marker` (the site's `[marker]` section: the origin
    /// marker and `[[marker.map]]`; their ids and sizes, not their poses) seen by a
    /// camera of calibration `calib`.
    pub fn new(marker: &MarkerConfig, calib: CameraCalibration) -> Self {
        let markers: Vec<(u32, f64)> = marker.markers().map(|m| (m.id, m.size_m)).collect();
        let index_of_id = markers
            .iter()
            .enumerate()
            .map(|(i, (id, _))| (*id, i))
            .collect();
        Self {
            calib,
            seen: vec![0; markers.len()],
            markers,
            index_of_id,
            obs: Vec::new(),
            frames_read: 0,
            frames_kept: 0,
        }
    }

    /// Frames given so far, and those kept (two or more of the map's markers seen).
    pub fn frames_read(&self) -> usize {
        self.frames_read
    }

    pub fn frames_kept(&self) -> usize {
        self.frames_kept
    }

    /// Frames each marker (by id) was seen in, alone or with others.
    pub fn seen_counts(&self) -> impl Iterator<Item = (u32, usize)> + '_ {
        self.markers
            .iter()
            .zip(&self.seen)
            .map(|((id, _), n)| (*id, *n))
    }

    /// The markers seen in one frame (ids not in the map are ignored). Returns how many
    /// of the map's markers it showed; frames with fewer than two add nothing to the map.
    pub fn add_frame(&mut self, seen: impl IntoIterator<Item = SeenMarker>) -> usize {
        let start = self.obs.len();
        for s in seen {
            let Some(&m) = self.index_of_id.get(&s.id) else {
                continue;
            };
            if self.obs[start..].iter().any(|o| o.marker == m) {
                continue;
            }
            self.seen[m] += 1;
            self.obs.push(Obs {
                frame: self.frames_kept,
                marker: m,
                img: s.img,
                white: s.white,
                t_cam_marker: s.t_cam_marker,
            });
        }
        self.frames_read += 1;
        let n = self.obs.len() - start;
        if n >= 2 {
            self.frames_kept += 1;
        } else {
            self.obs.truncate(start);
        }
        n
    }

    /// Detect the map's markers in `frame` with `tracker` (a full-frame search, no
    /// tracking: each frame stands alone) and add them.
    pub fn detect(
        &mut self,
        tracker: &mut MarkerTracker,
        frame: &Frame,
    ) -> Result<usize, VisionError> {
        tracker.reset();
        tracker.process_full(frame)?;
        Ok(self.add_frame(tracker.seen_markers()))
    }

    /// The map with marker `origin` as the site frame.
    pub fn solve(&self, origin: u32, settings: &MapSettings) -> Result<MapEstimate, VisionError> {
        let Some(&o) = self.index_of_id.get(&origin) else {
            let ids: Vec<String> = self.markers.iter().map(|(id, _)| id.to_string()).collect();
            return Err(VisionError::MapOrigin {
                origin,
                ids: ids.join(", "),
            });
        };
        if self.frames_kept == 0 {
            return Err(VisionError::MapNoFrames {
                frames: self.frames_read,
            });
        }
        let t_site = self.chain(o)?;
        let mut ba = Adjustment::new(self, o, t_site);
        let initial_rms_px = ba.rms_px();
        let mut iterations = ba.run(settings.max_iterations);
        let outliers = ba.reject(settings);
        if outliers > 0 {
            iterations += ba.run(settings.max_iterations);
        }
        Ok(ba.estimate(origin, initial_rms_px, iterations, outliers))
    }

    /// Start poses of the markers: from the origin, each next marker is the one seen in
    /// the most frames together with a marker already placed, placed through the medoid
    /// of those frames' relative poses (robust to a single-marker pose that took the
    /// wrong one of its two IPPE solutions). Errors list the markers not reached.
    fn chain(&self, origin: usize) -> Result<Vec<Option<Isometry3<f64>>>, VisionError> {
        let n = self.markers.len();
        // Relative poses t_a_b per ordered pair, over the frames that show both.
        let mut rel: HashMap<(usize, usize), Vec<Isometry3<f64>>> = HashMap::new();
        for frame in self.frames() {
            for a in frame {
                for b in frame {
                    if a.marker != b.marker {
                        rel.entry((a.marker, b.marker))
                            .or_default()
                            .push(a.t_cam_marker.inverse() * b.t_cam_marker);
                    }
                }
            }
        }
        let mut placed: Vec<Option<Isometry3<f64>>> = vec![None; n];
        placed[origin] = Some(Isometry3::identity());
        loop {
            let mut best: Option<(usize, usize, usize)> = None;
            for (&(a, b), v) in &rel {
                if placed[a].is_some() && placed[b].is_none() && best.is_none_or(|x| v.len() > x.2)
                {
                    best = Some((a, b, v.len()));
                }
            }
            let Some((a, b, _)) = best else {
                break;
            };
            let (Some(t_site_a), Some(v)) = (placed[a], rel.get(&(a, b))) else {
                break;
            };
            placed[b] = Some(t_site_a * medoid(v));
        }
        let missing: Vec<usize> = (0..n).filter(|m| placed[*m].is_none()).collect();
        if missing.is_empty() {
            return Ok(placed);
        }
        let describe = |m: usize| {
            let (id, _) = self.markers[m];
            match self.seen[m] {
                0 => format!("{id} (never seen)"),
                k => format!(
                    "{id} (seen in {k} frames, never together with a marker linked to the origin)"
                ),
            }
        };
        Err(VisionError::MapDisconnected {
            origin: self.markers[origin].0,
            ids: missing
                .iter()
                .map(|m| self.markers[*m].0.to_string())
                .collect::<Vec<_>>()
                .join(", "),
            detail: missing
                .iter()
                .map(|m| describe(*m))
                .collect::<Vec<_>>()
                .join("; "),
        })
    }

    /// The observations of each kept frame.
    fn frames(&self) -> impl Iterator<Item = &[Obs]> {
        self.obs.chunk_by(|a, b| a.frame == b.frame)
    }
}

/// The pose among `v` with the least summed distance to the others (translation in
/// metres plus rotation angle in radians times 0.1 m), over at most 101 evenly spaced
/// samples.
fn medoid(v: &[Isometry3<f64>]) -> Isometry3<f64> {
    let step = v.len().div_ceil(101).max(1);
    let s: Vec<&Isometry3<f64>> = v.iter().step_by(step).collect();
    let dist = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
        (a.translation.vector - b.translation.vector).norm()
            + 0.1 * a.rotation.angle_to(&b.rotation)
    };
    let mut best = (f64::MAX, *s[0]);
    for a in &s {
        let d: f64 = s.iter().map(|b| dist(a, b)).sum();
        if d < best.0 {
            best = (d, **a);
        }
    }
    best.1
}

/// `R = exp([dtheta]x) R`, `t = t + dt`: the perturbation of every pose here (as in
/// the pose refinement).
fn apply(pose: &Isometry3<f64>, delta: &[f64]) -> Isometry3<f64> {
    let dt = Vector3::new(delta[0], delta[1], delta[2]);
    let dth = Vector3::new(delta[3], delta[4], delta[5]);
    let rot = UnitQuaternion::from_scaled_axis(dth) * pose.rotation;
    Isometry3::from_parts(Translation3::from(pose.translation.vector + dt), rot)
}

/// Whitened residuals (observed - projected) of one observation, the Jacobians of the
/// projection w.r.t. the camera pose and the marker pose (whitened), and the raw
/// squared residual. `None`: a corner behind the camera.
fn observation(
    calib: &CameraCalibration,
    obj: &[Point3<f64>; 4],
    o: &Obs,
    t_cam_site: &Isometry3<f64>,
    t_site_marker: &Isometry3<f64>,
) -> Option<(SVector<f64, 8>, Blocks8x6, Blocks8x6, f64)> {
    let mut r = SVector::<f64, 8>::zeros();
    let mut jc = Blocks8x6::zeros();
    let mut jm = Blocks8x6::zeros();
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
    }
    let raw = r.norm_squared();
    Some((o.white * r, o.white * jc, o.white * jm, raw))
}

/// One frame's share of the normal equations: its camera block, gradient, and the
/// coupling `Jc^T Jm` with each free marker it saw.
type FrameBlocks = (Matrix6<f64>, Vector6<f64>, Vec<(usize, Matrix6<f64>)>);

/// A step: per camera, the free markers' (stacked), and the reduced matrix.
type Step = (Vec<Vector6<f64>>, DVector<f64>, DMatrix<f64>);

/// The normal equations at one point: per frame (camera block, its gradient, and the
/// coupling with each free marker it saw), per free marker (its block and gradient).
struct Linearised {
    cost: f64,
    frames: Vec<FrameBlocks>,
    markers: Vec<(Matrix6<f64>, Vector6<f64>)>,
}

struct Adjustment<'a> {
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
}

impl<'a> Adjustment<'a> {
    fn new(b: &'a MapBuilder, origin: usize, placed: Vec<Option<Isometry3<f64>>>) -> Self {
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
                    if let Some(p) = refine_pose_joint(&b.calib, &corners, &used, &init) {
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
        }
    }

    /// Whitened cost and raw squared residual with corners counted, at the current
    /// poses (`None`: a corner behind a camera).
    fn cost_at(
        &self,
        t_cam: &[Isometry3<f64>],
        t_site: &[Isometry3<f64>],
    ) -> Option<(f64, f64, usize)> {
        let (mut cost, mut raw, mut n) = (0.0, 0.0, 0);
        for (o, _) in self.b.obs.iter().zip(&self.used).filter(|(_, u)| **u) {
            let (r, _, _, sq) = observation(
                &self.b.calib,
                &self.obj[o.marker],
                o,
                &t_cam[o.frame],
                &t_site[o.marker],
            )?;
            cost += r.norm_squared();
            raw += sq;
            n += 4;
        }
        Some((cost, raw, n))
    }

    fn rms_px(&self) -> f64 {
        self.cost_at(&self.t_cam, &self.t_site)
            .map_or(f64::NAN, |(_, raw, n)| (raw / n.max(1) as f64).sqrt())
    }

    fn linearise(&self) -> Option<Linearised> {
        let mut lin = Linearised {
            cost: 0.0,
            frames: Vec::with_capacity(self.t_cam.len()),
            markers: vec![(Matrix6::zeros(), Vector6::zeros()); self.n_free],
        };
        for w in self.frame_start.windows(2) {
            let (mut hff, mut gf, mut coupling) = (Matrix6::zeros(), Vector6::zeros(), Vec::new());
            for i in w[0]..w[1] {
                if !self.used[i] {
                    continue;
                }
                let o = &self.b.obs[i];
                let (r, jc, jm, _) = observation(
                    &self.b.calib,
                    &self.obj[o.marker],
                    o,
                    &self.t_cam[o.frame],
                    &self.t_site[o.marker],
                )?;
                lin.cost += r.norm_squared();
                hff += jc.transpose() * jc;
                gf += jc.transpose() * r;
                if let Some(k) = self.free[o.marker] {
                    coupling.push((k, jc.transpose() * jm));
                    lin.markers[k].0 += jm.transpose() * jm;
                    lin.markers[k].1 += jm.transpose() * r;
                }
            }
            lin.frames.push((hff, gf, coupling));
        }
        Some(lin)
    }

    /// The damped step (cameras, free markers) by the Schur complement on the markers;
    /// also the reduced matrix (for the covariance). `None`: singular.
    fn step(&self, lin: &Linearised, lambda: f64) -> Option<Step> {
        let damp = |h: &Matrix6<f64>| {
            let mut a = *h;
            for d in 0..6 {
                a[(d, d)] += lambda * h[(d, d)].max(1e-9);
            }
            a
        };
        let dim = 6 * self.n_free;
        let mut s = DMatrix::<f64>::zeros(dim, dim);
        let mut rhs = DVector::<f64>::zeros(dim);
        for (k, (h, g)) in lin.markers.iter().enumerate() {
            s.fixed_view_mut::<6, 6>(6 * k, 6 * k).copy_from(&damp(h));
            rhs.fixed_rows_mut::<6>(6 * k).copy_from(g);
        }
        let mut a_inv = Vec::with_capacity(lin.frames.len());
        for (hff, gf, coupling) in &lin.frames {
            if hff.iter().all(|v| *v == 0.0) {
                // Every observation of the frame left out: its camera stays.
                a_inv.push(Matrix6::zeros());
                continue;
            }
            let inv = damp(hff).cholesky()?.inverse();
            for (k, hfk) in coupling {
                let y = hfk.transpose() * inv;
                let mut rk = rhs.fixed_rows_mut::<6>(6 * k);
                rk -= y * gf;
                for (l, hfl) in coupling {
                    let mut blk = s.fixed_view_mut::<6, 6>(6 * k, 6 * l);
                    blk -= y * hfl;
                }
            }
            a_inv.push(inv);
        }
        let dm = s.clone().cholesky()?.solve(&rhs);
        let dc = lin
            .frames
            .iter()
            .zip(&a_inv)
            .map(|((_, gf, coupling), inv)| {
                let mut g = *gf;
                for (k, hfk) in coupling {
                    g -= hfk * dm.fixed_rows::<6>(6 * k);
                }
                inv * g
            })
            .collect();
        Some((dc, dm, s))
    }

    fn moved(
        &self,
        dc: &[Vector6<f64>],
        dm: &DVector<f64>,
    ) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
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
                Some(k) => apply(t, &dm.as_slice()[6 * k..6 * k + 6]),
                None => *t,
            })
            .collect();
        (t_cam, t_site)
    }

    /// Levenberg-Marquardt to convergence; returns the iterations taken.
    fn run(&mut self, max_iterations: usize) -> usize {
        let mut lambda = 1e-4;
        let mut it = 0;
        let Some(mut lin) = self.linearise() else {
            return 0;
        };
        while it < max_iterations {
            it += 1;
            let Some((dc, dm, _)) = self.step(&lin, lambda) else {
                lambda *= 10.0;
                if lambda > 1e8 {
                    break;
                }
                continue;
            };
            let (t_cam, t_site) = self.moved(&dc, &dm);
            match self.cost_at(&t_cam, &t_site) {
                Some((cost, _, _)) if cost <= lin.cost => {
                    let small = dm.amax() < 1e-10 && dc.iter().all(|d| d.amax() < 1e-10);
                    let done = small || lin.cost - cost < 1e-10 * lin.cost.max(1e-30);
                    self.t_cam = t_cam;
                    self.t_site = t_site;
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
                    &self.b.calib,
                    &self.obj[o.marker],
                    o,
                    &self.t_cam[o.frame],
                    &self.t_site[o.marker],
                )
                .map_or(f64::NAN, |(_, _, _, raw)| (raw / 4.0).sqrt())
            })
            .collect()
    }

    /// Leave out the observations far above the median residual (a wrong corner, a
    /// marker half hidden); a marker keeps at least 3 observations. Returns how many.
    fn reject(&mut self, settings: &MapSettings) -> usize {
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

    fn estimate(
        &self,
        origin: u32,
        initial_rms_px: f64,
        iterations: usize,
        outliers: usize,
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
        // Covariance of the free markers: the inverse of the reduced (Schur) matrix,
        // scaled by the a-posteriori variance factor cost / redundancy.
        let mut cov: Option<DMatrix<f64>> = None;
        let mut factor = 1.0;
        if let Some(lin) = self.linearise() {
            let n_res = 8 * self.used.iter().filter(|u| **u).count();
            let n_par = 6 * (self.t_cam.len() + self.n_free);
            if n_res > n_par {
                factor = lin.cost / (n_res - n_par) as f64;
            }
            cov = self
                .step(&lin, 0.0)
                .and_then(|(_, _, s)| s.cholesky())
                .map(|c| c.inverse());
        }
        let sigma = |k: usize, off: usize| -> f64 {
            cov.as_ref().map_or(f64::NAN, |c| {
                (0..3)
                    .map(|d| c[(6 * k + off + d, 6 * k + off + d)] * factor)
                    .fold(0.0, f64::max)
                    .sqrt()
            })
        };
        let order = std::iter::once(self.origin).chain((0..nm).filter(|m| *m != self.origin));
        let markers = order
            .map(|m| {
                let (id, size_m) = self.b.markers[m];
                let (sp, sa) = match self.free[m] {
                    Some(k) => (sigma(k, 0), sigma(k, 3).to_degrees()),
                    None => (0.0, 0.0),
                };
                MappedMarker {
                    id,
                    size_m,
                    t_site_marker: self.t_site[m],
                    frames: frames[m],
                    outliers: out[m],
                    rms_px: (sq[m] / frames[m].max(1) as f64).sqrt(),
                    sigma_position_m: sp,
                    sigma_angle_deg: sa,
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
        }
    }
}

#[cfg(test)]
mod tests;
