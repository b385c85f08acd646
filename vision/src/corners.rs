//! Sub-pixel corners from the four outer edges of the black border.
//!
//! Each side is sampled away from its corners; along the outward normal, the edge
//! is the peak of the dark-to-bright gradient (parabola-interpolated). A line is fitted
//! to each side in undistorted pixel coordinates (so lens distortion does not bend it)
//! and the corners are the intersections of adjacent lines. Unlike cv::cornerSubPix
//! this is unbiased for any corner angle (oblique views) and averages the noise of
//! every edge pixel. The fit residuals give each line's covariance, propagated to an
//! 8x8 covariance of the corners (adjacent corners share a line, so they correlate).
//!
//! An edge whose white side clips (a pixel at the top grey level, as an exposure set
//! just above the white cells' clip onset gives) has lost the part of the step above
//! the clip level, and the gradient centroid moves towards the dark side by an amount
//! that depends on the edge's sub-pixel phase and on how far the white is over-exposed,
//! neither of which the frame shows. That shift is the same for every point of a side
//! whose phase does not change along it, so the residuals cannot see it: it is returned
//! as a separate covariance ([`EdgeCovariance::clip`]): a shift common to the four
//! sides (the marker looks smaller) and one of each side, each scaled by the fraction
//! of the side's points that clip ([`ClipModel`]).

use crate::CameraCalibration;
use markhold_camera::{Corners, ImageView};
use nalgebra::{Matrix2, SMatrix, Vector2};

/// 8x8 covariance of (u0, v0, u1, v1, ...), pixels^2.
pub type CornerCov = SMatrix<f64, 8, 8>;

/// Grey level at which a pixel counts as clipped (an 8-bit sensor's top level).
const CLIP_GREY: u8 = 255;
/// Darkest black border a contrast is measured against (below it the noise is a large
/// part of the grey).
const MIN_DARK_GREY: f64 = 4.0;
/// Width, in `1 - 1/r`, over which the sensor noise spreads the clip onset (fitted to
/// the shift of clipped edges on the HIL's frames, design/vision.md).
const CLIP_NOISE: f64 = 0.04;
/// Unclipped edge points a contrast is measured on, at least.
const MIN_CONTRAST_POINTS: f64 = 24.0;

/// Standard deviations, pixels, of the shift of a marker side whose white side clips
/// (all its points): `common_px` shared by the four sides (outward positive), `side_px`
/// of each side on its own.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ClipModel {
    pub common_px: f64,
    pub side_px: f64,
    /// White-to-black grey ratio of this marker's edges, last measured on its unclipped
    /// edge points (the tracker keeps it per marker; this frame's own, when it has
    /// enough of them, is used first). With it a side's shift is
    /// `gain_px (1 - 1/r)`, `r` the over-exposure of its white, `contrast` times its
    /// black border's grey over the clip level; the side's own part is
    /// `side_px / common_px` of that. Without it, `common_px` and `side_px`.
    pub contrast: Option<f64>,
    pub gain_px: f64,
}

/// The corners' covariance in two parts: the noise the fit residuals measure (the
/// pose is weighted by it), and the shift of edges whose white side clips.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EdgeCovariance {
    /// From the residuals of the four edge lines.
    pub fit: CornerCov,
    /// Clipped edges ([`ClipModel`]): each side's own shift, scaled by the fraction of
    /// its points that clip. Zero when no edge point clips.
    pub clip: CornerCov,
    /// Clipped edges: the corners' move when every side moves inward by its common
    /// shift's standard deviation (covariance `clip_common clip_common^T`). Every
    /// marker of a frame shares the sign (a clipped step always moves towards its dark
    /// side), so a map's markers add these before squaring.
    pub clip_common: SMatrix<f64, 8, 1>,
    /// Edge points whose white side clips, of all the points fitted.
    pub clipped_points: u32,
    pub points: u32,
    /// White-to-black grey ratio of the edge points that do not clip (`None` with too few
    /// of them, or a black too dark to divide by).
    pub contrast: Option<f64>,
}

#[derive(Debug, Clone, Copy, Default)]
struct Line {
    /// Centroid of the edge points (undistorted pixels).
    c: Vector2<f64>,
    /// Unit direction.
    d: Vector2<f64>,
    /// Variance of the offset along the normal at the centroid, px^2.
    var_rho: f64,
    /// Variance of the direction angle, rad^2.
    var_theta: f64,
    /// Fraction of the fitted points whose white side clips.
    clipped: f64,
    /// Mean grey of the black side of the clipped points, and of the unclipped ones; mean
    /// grey of the white side of the unclipped points (0 without any).
    dark_clipped: f64,
    dark_unclipped: f64,
    bright: f64,
    /// Length the fitted points span, pixels.
    len: f64,
    /// Points fitted.
    n: u32,
}

impl Line {
    fn normal(&self) -> Vector2<f64> {
        Vector2::new(-self.d.y, self.d.x)
    }

    fn intersect(&self, o: &Line) -> Option<Vector2<f64>> {
        // c1 + a d1 = c2 + b d2.
        let m = Matrix2::new(self.d.x, -o.d.x, self.d.y, -o.d.y);
        let ab = m.try_inverse()? * (o.c - self.c);
        Some(self.c + self.d * ab.x)
    }

    fn perturbed(&self, drho: f64, dtheta: f64) -> Line {
        let (s, c) = dtheta.sin_cos();
        let d = Vector2::new(c * self.d.x - s * self.d.y, s * self.d.x + c * self.d.y);
        Line {
            c: self.c + self.normal() * drho,
            d,
            ..*self
        }
    }
}

/// Reusable buffers of the edge fitter.
#[derive(Debug, Default)]
pub(crate) struct EdgeRefiner {
    pts: Vec<Vector2<f64>>,
    /// Per point: its white side clips.
    clip: Vec<bool>,
    /// Per point: grey of its black side (the lobe's foot) and of its white side
    /// ([`BRIGHT_PAST_TOP_PX`] past the lobe's top).
    grey: Vec<(f64, f64)>,
    resid: Vec<f64>,
    /// Distance between edge points along the side being fitted, pixels.
    spacing_px: f64,
}

/// Edge points per side at most (beyond this the line is already far more precise
/// than the model; the cost is linear in it).
const MAX_EDGE_POINTS: usize = 80;
/// Edge points per side of the wide first pass at most: it only brings the corners
/// within the narrow pass's band, which sets them.
const MAX_WIDE_EDGE_POINTS: usize = 40;
/// Where the white side's grey is read, pixels past the lobe's brightest sample: on the
/// plateau (docs/design/vision.md, "Clipped edges").
const BRIGHT_PAST_TOP_PX: f64 = 3.0;
/// Step of the intensity profile across the edge, pixels.
const PROFILE_STEP_PX: f64 = 0.5;

/// Whether any of the four pixels a bilinear sample at (x, y) reads is clipped.
fn clipped_at(img: &ImageView<'_>, x: f64, y: f64) -> bool {
    if !(x >= 0.0 && y >= 0.0) {
        return false;
    }
    // Truncation is the floor of a non-negative value (a call to libm's floor on the
    // baseline x86_64 target, which has no SSE4.1 rounding instruction).
    let (x0, y0) = (x as usize, y as usize);
    if x0 + 1 >= img.width || y0 + 1 >= img.height {
        return false;
    }
    let i = y0 * img.stride + x0;
    let d = img.data;
    [d[i], d[i + 1], d[i + img.stride], d[i + img.stride + 1]].contains(&CLIP_GREY)
}

/// Bilinear sample; `None` outside the image.
fn sample(img: &ImageView<'_>, x: f64, y: f64) -> Option<f64> {
    if !(x >= 0.0 && y >= 0.0) {
        return None;
    }
    // Truncation is the floor of a non-negative value, as in `clipped_at`.
    let (x0, y0) = (x as usize, y as usize);
    if x0 + 1 >= img.width || y0 + 1 >= img.height {
        return None;
    }
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let i = y0 * img.stride + x0;
    let d = img.data;
    let top = d[i] as f64 * (1.0 - fx) + d[i + 1] as f64 * fx;
    let bot = d[i + img.stride] as f64 * (1.0 - fx) + d[i + img.stride + 1] as f64 * fx;
    Some(top * (1.0 - fy) + bot * fy)
}

impl EdgeRefiner {
    pub(crate) fn new() -> Self {
        Self {
            pts: Vec::with_capacity(MAX_EDGE_POINTS),
            clip: Vec::with_capacity(MAX_EDGE_POINTS),
            grey: Vec::with_capacity(MAX_EDGE_POINTS),
            resid: Vec::with_capacity(MAX_EDGE_POINTS),
            spacing_px: 1.0,
        }
    }

    /// Refine `corners` (aruco order, pixels) in place and return their covariance
    /// (`clip`: the shift of sides whose white side clips).
    /// `module_px` is the border module width in pixels. `None` (corners untouched)
    /// when an edge cannot be measured.
    pub(crate) fn refine(
        &mut self,
        img: &ImageView<'_>,
        calib: &CameraCalibration,
        corners: &mut Corners,
        module_px: f64,
        clip: &ClipModel,
    ) -> Option<EdgeCovariance> {
        // Two passes: a wide search band absorbs the coarse corners' error, a
        // narrow one keeps away from neighbouring edges.
        let wide = (0.9 * module_px).clamp(1.5, 6.0);
        let narrow = (0.5 * module_px).clamp(1.0, 3.0);
        let mut cur = *corners;
        let mut lines = [Line::default(); 4];
        for (band, max_points) in [(wide, MAX_WIDE_EDGE_POINTS), (narrow, MAX_EDGE_POINTS)] {
            for (i, line) in lines.iter_mut().enumerate() {
                *line = self.fit_side(img, calib, &cur, i, band, max_points)?;
            }
            let mut next = cur;
            for i in 0..4 {
                let p = lines[(i + 3) % 4].intersect(&lines[i])?;
                let px = undistorted_to_pixel(calib, &p);
                let moved =
                    ((px.x - cur[i][0] as f64).powi(2) + (px.y - cur[i][1] as f64).powi(2)).sqrt();
                if moved.is_nan() || moved > 2.0 * band {
                    return None;
                }
                next[i] = [px.x as f32, px.y as f32];
            }
            cur = next;
        }
        *corners = cur;
        let fit = corner_covariance(calib, &lines, |_, l| (l.var_rho, l.var_theta));
        // Each side's shift when clipped (the common part), and its own part (standard
        // deviations, pixels). The noise's clipping at `r` about 1 moves the four sides
        // alike; their differences grow with the over-exposure itself.
        let (mut shift, mut own) = ([0.0; 4], [0.0; 4]);
        let side_ratio = if clip.common_px > 0.0 {
            clip.side_px / clip.common_px
        } else {
            0.0
        };
        let contrast = measured_contrast(&lines);
        // A gain of 0 keeps the fixed figures.
        let known = contrast.or(clip.contrast).filter(|_| clip.gain_px > 0.0);
        for ((s, o), l) in shift.iter_mut().zip(&mut own).zip(&lines) {
            (*s, *o) = match known {
                Some(c) if l.clipped > 0.0 => {
                    let r = c * l.dark_clipped / f64::from(CLIP_GREY);
                    let g = l.clipped * clip.gain_px;
                    (
                        g * clipped_height(r),
                        side_ratio * g * (1.0 - 1.0 / r).max(0.0),
                    )
                }
                Some(_) => (0.0, 0.0),
                None => (l.clipped * clip.common_px, l.clipped * clip.side_px),
            };
        }
        let clip_cov = corner_covariance(calib, &lines, |i, l| {
            let v = own[i].powi(2);
            // The side's offset, and as much again between its two ends.
            (v, 2.0 * v / (l.len * l.len).max(1e-12))
        });
        let clip_common = if shift.iter().any(|s| *s > 0.0) {
            common_shift_jacobian(calib, &lines, &shift)
        } else {
            SMatrix::zeros()
        };
        let points: u32 = lines.iter().map(|l| l.n).sum();
        let clipped_points = lines
            .iter()
            .map(|l| (l.clipped * l.n as f64).round() as u32)
            .sum();
        Some(EdgeCovariance {
            fit,
            clip: clip_cov,
            clip_common,
            clipped_points,
            points,
            contrast,
        })
    }

    /// Fit the line of side `i` (from corner i to corner i+1).
    fn fit_side(
        &mut self,
        img: &ImageView<'_>,
        calib: &CameraCalibration,
        c: &Corners,
        i: usize,
        band: f64,
        max_points: usize,
    ) -> Option<Line> {
        let a = Vector2::new(c[i][0] as f64, c[i][1] as f64);
        let b = Vector2::new(c[(i + 1) % 4][0] as f64, c[(i + 1) % 4][1] as f64);
        let centre = c.iter().fold(Vector2::zeros(), |s, p| {
            s + Vector2::new(p[0] as f64, p[1] as f64)
        }) / 4.0;
        let (na, nb) = (
            pixel_to_undistorted(calib, &a),
            pixel_to_undistorted(calib, &b),
        );
        let len = (b - a).norm();
        if len < 8.0 {
            return None;
        }
        // Stay clear of the corners, where the other edge enters the band.
        let t0 = ((band + 2.0) / len).max(0.1);
        if t0 >= 0.45 {
            return None;
        }
        // One edge point per pixel of edge, at most `max_points` per side.
        let usable = len * (1.0 - 2.0 * t0);
        let n_samples = usable.clamp(6.0, max_points as f64) as usize;
        self.spacing_px = usable / n_samples as f64;
        let step = PROFILE_STEP_PX;
        let n_steps = (band / step).ceil() as i32;
        self.pts.clear();
        self.clip.clear();
        self.grey.clear();
        for k in 0..n_samples {
            let t = t0 + (1.0 - 2.0 * t0) * (k as f64 + 0.5) / n_samples as f64;
            let q = na + (nb - na) * t;
            let p = undistorted_to_pixel(calib, &q);
            let dt = 0.5 / len;
            let tan = undistorted_to_pixel(calib, &(na + (nb - na) * (t + dt)))
                - undistorted_to_pixel(calib, &(na + (nb - na) * (t - dt)));
            let Some(tan) = tan.try_normalize(1e-12) else {
                continue;
            };
            let mut n = Vector2::new(-tan.y, tan.x);
            if n.dot(&(p - centre)) < 0.0 {
                n = -n;
            }
            // Gradient along the outward normal by central differences of samples.
            let at = |s: f64| sample(img, p.x + n.x * s, p.y + n.y * s);
            let mut best = (0.0, 0i32);
            let mut prev = at(-(n_steps as f64 + 1.0) * step);
            let mut here = at(-(n_steps as f64) * step);
            let mut grads = [0.0f64; 64];
            let m = (2 * n_steps + 1).min(64) as usize;
            let mut ok = true;
            for j in 0..m as i32 {
                let s = (j - n_steps) as f64 * step;
                let next = at(s + step);
                match (prev, next) {
                    (Some(p0), Some(p1)) => {
                        let g = (p1 - p0) / (2.0 * step);
                        grads[j as usize] = g;
                        if g > best.0 {
                            best = (g, j);
                        }
                    }
                    _ => {
                        ok = false;
                        break;
                    }
                }
                prev = here;
                here = next;
            }
            let (g, j) = best;
            // Needs a clear dark-to-bright step, with its peak inside the band.
            if !ok || g < 2.0 || j == 0 || j as usize >= m - 1 {
                continue;
            }
            // Centroid of the whole positive gradient lobe around the peak: for a
            // pixel-integrated step edge the centroid of the first difference is
            // exactly the edge (the sum telescopes); a parabola through the peak or
            // a thresholded centroid is biased by up to ~0.1 px.
            let (mut lo, mut hi) = (j as usize, j as usize);
            while lo > 0 && grads[lo - 1] > 0.0 {
                lo -= 1;
            }
            while hi + 1 < m && grads[hi + 1] > 0.0 {
                hi += 1;
            }
            let (mut sw, mut swx) = (0.0, 0.0);
            for (jj, gg) in grads.iter().enumerate().take(hi + 1).skip(lo) {
                sw += gg;
                swx += gg * jj as f64;
            }
            let s = (swx / sw - n_steps as f64) * step;
            let e = p + n * s;
            self.pts.push(pixel_to_undistorted(calib, &e));
            // The brightest sample of the lobe (the profile rises through it).
            let top = (hi as f64 + 1.0 - n_steps as f64) * step;
            let clipped = clipped_at(img, p.x + n.x * top, p.y + n.y * top);
            self.clip.push(clipped);
            let foot = (lo as f64 - 1.0 - n_steps as f64) * step;
            let dark = at(foot).unwrap_or(0.0);
            let bright = at(top + BRIGHT_PAST_TOP_PX).unwrap_or(0.0);
            self.grey.push((dark, bright));
        }
        self.fit_line()
    }

    /// Total least squares with one round of outlier rejection (3.5 robust sigma).
    fn fit_line(&mut self) -> Option<Line> {
        let fit = |pts: &[Vector2<f64>]| -> Option<(Vector2<f64>, Vector2<f64>)> {
            let n = pts.len() as f64;
            let c = pts.iter().fold(Vector2::zeros(), |s, p| s + p) / n;
            let mut m = Matrix2::zeros();
            for p in pts {
                let d = p - c;
                m += d * d.transpose();
            }
            let eig = m.symmetric_eigen();
            let k = if eig.eigenvalues[0] > eig.eigenvalues[1] {
                0
            } else {
                1
            };
            let d = eig
                .eigenvectors
                .column(k)
                .into_owned()
                .try_normalize(1e-12)?;
            Some((c, d))
        };
        if self.pts.len() < 6 {
            return None;
        }
        let (c, d) = fit(&self.pts)?;
        let nrm = Vector2::new(-d.y, d.x);
        self.resid.clear();
        self.resid
            .extend(self.pts.iter().map(|p| (p - c).dot(&nrm).abs()));
        self.resid.sort_by(|a, b| a.total_cmp(b));
        let mad = self.resid[self.resid.len() / 2];
        let limit = (3.5 * 1.4826 * mad).max(0.05);
        let pts = &self.pts;
        let keep = |k: usize| (pts[k] - c).dot(&nrm).abs() <= limit;
        let mut k = 0;
        self.clip.retain(|_| {
            k += 1;
            keep(k - 1)
        });
        let mut k = 0;
        self.grey.retain(|_| {
            k += 1;
            keep(k - 1)
        });
        self.pts.retain(|p| (p - c).dot(&nrm).abs() <= limit);
        if self.pts.len() < 6 {
            return None;
        }
        let (c, d) = fit(&self.pts)?;
        let nrm = Vector2::new(-d.y, d.x);
        let n = self.pts.len() as f64;
        let (mut ss, mut stt) = (0.0, 0.0);
        for p in &self.pts {
            let q = p - c;
            ss += q.dot(&nrm).powi(2);
            stt += q.dot(&d).powi(2);
        }
        // Each edge point reads a 2 px bilinear footprint along the edge, so points
        // closer than 2 px correlate: the autocorrelation of the triangle kernel at
        // lag d < 2 is (2 - d)^3 / 4 (1/4 at 1 px), and the line's variance is
        // (1 + 2 rho) times the independent value.
        let rho = (2.0 - self.spacing_px).max(0.0).powi(3) / 4.0;
        let var = (1.0 + 2.0 * rho) * ss / (n - 2.0);
        if stt <= 0.0 {
            return None;
        }
        let clipped = self.clip.iter().filter(|c| **c).count() as f64 / n;
        let (mut dc, mut nc, mut du, mut b, mut nb) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (&(dark, bright), &clipped) in self.grey.iter().zip(&self.clip) {
            if clipped {
                dc += dark;
                nc += 1.0;
            } else {
                du += dark;
                b += bright;
                nb += 1.0;
            }
        }
        Some(Line {
            dark_clipped: if nc > 0.0 { dc / nc } else { 0.0 },
            dark_unclipped: if nb > 0.0 { du / nb } else { 0.0 },
            bright: if nb > 0.0 { b / nb } else { 0.0 },
            c,
            d,
            var_rho: var / n,
            var_theta: var / stt,
            clipped,
            // n points spread evenly over len: stt = n len^2 / 12.
            len: (12.0 * stt / n).sqrt(),
            n: self.pts.len() as u32,
        })
    }
}

/// Undistorted pixel (pinhole image of the same ray) of a distorted pixel.
fn pixel_to_undistorted(calib: &CameraCalibration, p: &Vector2<f64>) -> Vector2<f64> {
    let n = calib.undistort_pixel(p.x, p.y);
    Vector2::new(n.x * calib.fx + calib.cx, n.y * calib.fy + calib.cy)
}

fn undistorted_to_pixel(calib: &CameraCalibration, q: &Vector2<f64>) -> Vector2<f64> {
    let (x, y) = ((q.x - calib.cx) / calib.fx, (q.y - calib.cy) / calib.fy);
    calib.distort_with_jacobian(x, y).0
}

/// Fraction of the white's height lost to the clip, `1 - 1/r` at over-exposure `r`,
/// smoothed over the sensor noise: at `r` about 1 the noise alone clips part of the
/// white (softplus of width [`CLIP_NOISE`]).
fn clipped_height(r: f64) -> f64 {
    let x = (1.0 - 1.0 / r.max(1e-3)) / CLIP_NOISE;
    CLIP_NOISE * if x > 30.0 { x } else { x.exp().ln_1p() }
}

/// White-to-black grey ratio of the edge points that do not clip (`None` with fewer
/// than [`MIN_CONTRAST_POINTS`] of them or a black too dark to divide by).
fn measured_contrast(lines: &[Line; 4]) -> Option<f64> {
    let (mut n, mut dark, mut bright) = (0.0, 0.0, 0.0);
    for l in lines {
        let m = (1.0 - l.clipped) * f64::from(l.n);
        n += m;
        dark += l.dark_unclipped * m;
        bright += l.bright * m;
    }
    (n >= MIN_CONTRAST_POINTS && dark >= MIN_DARK_GREY * n && bright > dark).then(|| bright / dark)
}

/// Corners (distorted pixels) where adjacent lines meet.
fn corners_of(calib: &CameraCalibration, lines: &[Line; 4]) -> Option<[Vector2<f64>; 4]> {
    let mut out = [Vector2::zeros(); 4];
    for (i, o) in out.iter_mut().enumerate() {
        *o = undistorted_to_pixel(calib, &lines[(i + 3) % 4].intersect(&lines[i])?);
    }
    Some(out)
}

/// d corners / d s when every side moves outward by `s` times its `shift` (a column
/// of 8, order u0 v0 u1 v1 ...).
fn common_shift_jacobian(
    calib: &CameraCalibration,
    lines: &[Line; 4],
    shift: &[f64; 4],
) -> SMatrix<f64, 8, 1> {
    let centre = lines.iter().fold(Vector2::zeros(), |s, l| s + l.c) / 4.0;
    let shifted = |h: f64| {
        let mut ls = *lines;
        for (l, w) in ls.iter_mut().zip(shift) {
            let out = if l.normal().dot(&(l.c - centre)) >= 0.0 {
                1.0
            } else {
                -1.0
            };
            *l = l.perturbed(out * h * w, 0.0);
        }
        corners_of(calib, &ls)
    };
    let h = 1e-4;
    let mut g = SMatrix::<f64, 8, 1>::zeros();
    if let (Some(p), Some(m)) = (shifted(h), shifted(-h)) {
        for i in 0..4 {
            let d = (p[i] - m[i]) / (2.0 * h);
            g[2 * i] = d.x;
            g[2 * i + 1] = d.y;
        }
    }
    g
}

/// Covariance of the four distorted-pixel corners from the four lines' covariances
/// `var(line) = (offset variance, angle variance)` (offset and angle about each
/// centroid are independent in a TLS fit).
fn corner_covariance(
    calib: &CameraCalibration,
    lines: &[Line; 4],
    var: impl Fn(usize, &Line) -> (f64, f64),
) -> CornerCov {
    let mut cov = CornerCov::zeros();
    // Jacobian of the distorted pixel w.r.t. the undistorted pixel, per corner.
    let mut dist_j = [Matrix2::identity(); 4];
    for i in 0..4 {
        let p = lines[(i + 3) % 4]
            .intersect(&lines[i])
            .unwrap_or_else(Vector2::zeros);
        let (x, y) = ((p.x - calib.cx) / calib.fx, (p.y - calib.cy) / calib.fy);
        let j = calib.distort_with_jacobian(x, y).1;
        dist_j[i] = j * Matrix2::new(1.0 / calib.fx, 0.0, 0.0, 1.0 / calib.fy);
    }
    for l in 0..4 {
        // Line l makes corner l (with line l-1) and corner l+1 (with line l+1).
        let mut jac = SMatrix::<f64, 8, 2>::zeros();
        for (ci, other) in [(l, (l + 3) % 4), ((l + 1) % 4, (l + 1) % 4)] {
            for (k, h) in [(0usize, 1e-4), (1usize, 1e-6)] {
                let (dr, dt) = if k == 0 { (h, 0.0) } else { (0.0, h) };
                let lp = lines[l].perturbed(dr, dt);
                let lm = lines[l].perturbed(-dr, -dt);
                let (pp, pm) = if ci == l {
                    (lines[other].intersect(&lp), lines[other].intersect(&lm))
                } else {
                    (lp.intersect(&lines[other]), lm.intersect(&lines[other]))
                };
                if let (Some(pp), Some(pm)) = (pp, pm) {
                    let du = dist_j[ci] * ((pp - pm) / (2.0 * h));
                    jac[(2 * ci, k)] = du.x;
                    jac[(2 * ci + 1, k)] = du.y;
                }
            }
        }
        let (vr, vt) = var(l, &lines[l]);
        let s = Matrix2::new(vr, 0.0, 0.0, vt);
        cov += jac * s * jac.transpose();
    }
    cov
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{render_marker, SceneParams};
    use crate::{marker_bitmap, MarkerFamily};
    use markhold_camera::Frame;
    use nalgebra::{Isometry3, Vector3};

    #[test]
    fn oblique_corners_are_recovered_to_hundredths_of_a_pixel() {
        let calib = CameraCalibration {
            dist: vec![-0.15, 0.04, 0.0, 0.0, 0.0],
            model: crate::DistortionModel::PlumbBob,
            ..CameraCalibration::pinhole(800, 600, 600.0, 600.0, 399.5, 299.5)
        };
        let bm = marker_bitmap(MarkerFamily::AprilTag36h11, 0).unwrap();
        let pose = Isometry3::new(Vector3::new(0.15, 0.05, 1.0), Vector3::new(2.6, 0.0, 0.9));
        let mut f = Frame::default();
        let truth = render_marker(&mut f, &calib, &bm, 0.2, &pose, &SceneParams::default());
        let truth = truth.map(|p| p.unwrap());
        // Start 1.2 px off in different directions.
        let mut c: Corners = [[0.0; 2]; 4];
        for (i, t) in truth.iter().enumerate() {
            let s = if i % 2 == 0 { 1.0 } else { -1.0 };
            c[i] = [(t[0] + 1.2 * s) as f32, (t[1] - 0.8 * s) as f32];
        }
        let module = 0.2 * 600.0 / 8.0 * 0.5;
        let cov = EdgeRefiner::new()
            .refine(&f.view(), &calib, &mut c, module, &ClipModel::default())
            .expect("refined")
            .fit;
        for (got, want) in c.iter().zip(&truth) {
            let e = ((got[0] as f64 - want[0]).powi(2) + (got[1] as f64 - want[1]).powi(2)).sqrt();
            assert!(e < 0.04, "corner error {e} px: {got:?} vs {want:?}");
        }
        assert!(cov.diagonal().iter().all(|v| *v > 0.0 && v.is_finite()));
    }

    #[test]
    fn clipped_white_shifts_the_sides_as_the_clip_covariance_states() {
        let calib = CameraCalibration::pinhole(640, 480, 533.0, 533.0, 320.0, 240.0);
        let bm = marker_bitmap(MarkerFamily::AprilTag36h11, 0).unwrap();
        let pose = Isometry3::new(
            Vector3::new(0.01, -0.02, 1.0),
            Vector3::new(0.05, 0.1, 0.02),
        );
        let mut f = Frame::default();
        let scene = SceneParams::default();
        let truth = render_marker(&mut f, &calib, &bm, 0.15, &pose, &scene);
        let truth = truth.map(|p| p.unwrap());
        let start: Corners = truth.map(|t| [t[0] as f32, t[1] as f32]);
        let centre = truth
            .iter()
            .fold(Vector2::zeros(), |s, t| s + Vector2::new(t[0], t[1]))
            / 4.0;
        let module = 0.15 * 533.0 / 10.0;
        let mut model = ClipModel {
            common_px: 0.06,
            side_px: 0.042,
            contrast: None,
            gain_px: 0.6,
        };
        let mut c = start;
        let plain = EdgeRefiner::new()
            .refine(&f.view(), &calib, &mut c, module, &model)
            .expect("refined");
        assert_eq!(plain.clipped_points, 0);
        assert_eq!(plain.clip, CornerCov::zeros());
        assert_eq!(plain.clip_common, SMatrix::<f64, 8, 1>::zeros());
        // Unclipped, the edges give the marker's white-to-black contrast.
        let contrast = plain.contrast.expect("contrast measured");
        let want = scene.white / scene.black;
        assert!((contrast / want - 1.0).abs() < 0.05, "{contrast} vs {want}");
        model.contrast = Some(contrast);
        // The same frame brighter: the white clips at 255 (over-exposed 1.18x, 1.5x,
        // 2x) and the sides move inward, by about what the common shift states.
        let mut last = 0.0;
        for gain in [1.5, 1.9, 2.55] {
            let mut bright = f.clone();
            for v in bright.data.iter_mut() {
                *v = (*v as f64 * gain).min(255.0) as u8;
            }
            let mut c = start;
            let clipped = EdgeRefiner::new()
                .refine(&bright.view(), &calib, &mut c, module, &model)
                .expect("refined");
            assert!(
                clipped.clipped_points as f64 > 0.9 * clipped.points as f64,
                "{clipped:?}"
            );
            // Outward move of each corner coordinate, and the model's.
            let (mut moved, mut stated) = (0.0, 0.0);
            for k in 0..4 {
                let out = Vector2::new(truth[k][0], truth[k][1]) - centre;
                for a in 0..2 {
                    let sign = out[a].signum();
                    moved += sign * (c[k][a] as f64 - truth[k][a]) / 8.0;
                    stated += sign * clipped.clip_common[2 * k + a] / 8.0;
                }
            }
            let r = gain * scene.white / 255.0;
            println!("r {r:.2}: sides moved {moved:.4} px, the model states {stated:.4} px");
            assert!(moved < -0.02, "{gain}x: moved {moved} px");
            assert!(
                (-moved / 1.5..-moved * 1.5).contains(&stated),
                "r {r:.2}: sides moved {moved:.3} px, the model states {stated:.3}"
            );
            assert!(-moved > last, "r {r:.2}: {moved} px");
            last = -moved;
            // The sides' own shifts are a fraction of it, each side apart.
            let own = (0..8).map(|k| clipped.clip[(k, k)].sqrt()).sum::<f64>() / 8.0;
            assert!(
                own > 0.1 * stated && own < stated,
                "own {own}, common {stated}"
            );
        }
    }
}
