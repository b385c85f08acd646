//! The paper's published code as facts shared by `aaec-paper`, `aec-paper` and
//! `gec-paper` (Rennylex/adaptive_active_exposure_control; the file and commit of each fact
//! are in docs/design/exposure.md): its region rule, OpenCV's 3x3 Sobel with its border
//! rule, the soft-percentile metric with its derivative, and what it sends the camera.
//! Written from those facts; none of the code is carried over.

use crate::{Corners, ExposureLimits, ImageView, Response, Roi};
use markhold_config::{Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// Which camera response a paper method's derivative assumes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PaperResponse {
    /// The code's degree-14 polynomial whatever the camera, as the code ran
    /// ([`crate::PAPER_CODE_G_PRIME`]).
    Code,
    /// The site's `[camera] response`.
    Site,
}

impl PaperResponse {
    /// The response this choice means on a camera whose own is `site`.
    pub fn resolve(self, site: &Response) -> Response {
        match self {
            Self::Code => Response::paper_code(),
            Self::Site => site.clone(),
        }
    }
}

/// What a paper method does before its first detection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PreDetection {
    /// The camera's own auto exposure runs (the published node sends exposure 0, the
    /// driver's "auto", every frame until a region is set): markhold's mean-intensity AE
    /// with the `[exposure.default]` settings stands in for it.
    CameraAe,
    /// Nothing is commanded: the exposure stays where it is (the 2023 node, whose
    /// camera was launched at a fixed exposure).
    Hold,
}

/// Which frames a paper method learns from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PaperFrames {
    /// Every frame, taken to be exposed with the last command (the code reads back the
    /// camera driver's parameter, which holds the value it last sent).
    Every,
    /// Only frames exposed with the last command (markhold's rule for its own methods).
    ExposedAsCommanded,
}

/// Which gradient ranks and scores the pixels of the paper's metric.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PaperMetric {
    /// As published: `G = Ix^2 + Iy^2` ranks and scores.
    Published,
    /// As in the code: `|Ix|` ranks and scores (it computes `Ix^2 + Iy^2`, then
    /// overwrites it with `|Ix|`); the derivative is that of `Ix^2 + Iy^2` either way.
    AbsIx,
}

/// A law whose every step so far fell under its gate: the exposure has not moved from
/// where the law started. The step scales with the site's metric (image size, marker
/// size, contrast), so a learning rate tuned on one camera can freeze on another.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GateStall {
    /// Frames the law ran without moving.
    pub frames: u64,
    /// Largest step it computed, microseconds.
    pub largest_step_us: f64,
    /// The gate a step must exceed, microseconds.
    pub gate_us: f64,
    /// The learning rate it ran with.
    pub rate: f64,
    /// The learning rate at which that largest step would have passed the gate (none
    /// when the derivative itself was under its own gate, or zero).
    pub rate_to_pass: Option<f64>,
}

/// Used frames a law must run without moving before [`GateStall`] is reported (1 s at
/// 30 fps).
pub const STALL_FRAMES: u64 = 30;

/// Tracks whether a gated law ever moved.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct StallWatch {
    moved: bool,
    frames: u64,
    largest_step_us: f64,
    /// Frames where the derivative passed its own gate (aec-paper's |dM/dt| > 15000).
    derivative_passed: u64,
    warned: bool,
}

impl StallWatch {
    /// One law update: the step it computed and whether the exposure moved.
    pub(crate) fn record(&mut self, step_us: f64, derivative_passed: bool, moved: bool) {
        if self.moved {
            return;
        }
        if moved {
            self.moved = true;
            return;
        }
        self.frames += 1;
        if step_us.is_finite() {
            self.largest_step_us = self.largest_step_us.max(step_us.abs());
        }
        self.derivative_passed += u64::from(derivative_passed);
    }

    pub(crate) fn stall(&self, gate_us: f64, rate: f64) -> Option<GateStall> {
        (!self.moved && self.frames >= STALL_FRAMES).then(|| GateStall {
            frames: self.frames,
            largest_step_us: self.largest_step_us,
            gate_us,
            rate,
            rate_to_pass: (self.derivative_passed > 0 && self.largest_step_us > 0.0)
                .then(|| rate * gate_us / self.largest_step_us),
        })
    }

    /// Log the stall once (the first time it is seen).
    pub(crate) fn warn_once(&mut self, method: &str, gate_us: f64, rate: f64) {
        if self.warned {
            return;
        }
        if let Some(s) = self.stall(gate_us, rate) {
            self.warned = true;
            match s.rate_to_pass {
                Some(r) => tracing::warn!(
                    "{method}: for {} frames every step was under its {} us gate (largest \
                     {:.3} us with learning rate {:.2e}): the exposure cannot move at this \
                     site's metric scale; a rate of at least {:.2e} would move it",
                    s.frames,
                    s.gate_us,
                    s.largest_step_us,
                    s.rate,
                    r
                ),
                None => tracing::warn!(
                    "{method}: for {} frames the metric's derivative stayed under its gate: \
                     the exposure cannot move at this site's metric scale",
                    s.frames
                ),
            }
        }
    }

    pub(crate) fn reset(&mut self) {
        *self = Self {
            warned: self.warned,
            ..Self::default()
        };
    }
}

/// The code's region for a marker: the tracker's corner box in whole pixels (truncated),
/// padded by `pad_frac` of its width and height on each side in f32 and truncated again,
/// clamped to the `w` x `h` image. `None` for an empty box or non-finite corners.
pub fn code_region(corners: &Corners, pad_frac: f64, w: u32, h: u32) -> Option<Roi> {
    if corners.iter().flatten().any(|v| !v.is_finite()) {
        return None;
    }
    let xs = corners.map(|c| c[0]);
    let ys = corners.map(|c| c[1]);
    let lo = |v: [f32; 4]| v.iter().copied().fold(f32::MAX, f32::min) as i64;
    let hi = |v: [f32; 4]| v.iter().copied().fold(f32::MIN, f32::max) as i64;
    let (bx0, bx1, by0, by1) = (lo(xs), hi(xs), lo(ys), hi(ys));
    let px = ((bx1 - bx0) as f64 * pad_frac) as f32;
    let py = ((by1 - by0) as f64 * pad_frac) as f32;
    let x0 = ((bx0 as f32 - px) as i64).max(0);
    let y0 = ((by0 as f32 - py) as i64).max(0);
    let x1 = ((bx1 as f32 + px) as i64).min(w as i64);
    let y1 = ((by1 as f32 + py) as i64).min(h as i64);
    (x1 > x0 && y1 > y0).then(|| Roi {
        x: x0 as u32,
        y: y0 as u32,
        width: (x1 - x0) as u32,
        height: (y1 - y0) as u32,
    })
}

/// What the code sends the camera for a law's `t_us`: at or below `floor_us - 1`
/// becomes `floor_us` (12 -> 13 us in the code), above the camera's maximum the maximum,
/// then whole microseconds (it sends an integer parameter); the camera's own limits
/// last. A non-finite `t_us` keeps `current_us`.
pub fn code_command(t_us: f64, floor_us: f64, limits: &ExposureLimits, current_us: f64) -> f64 {
    if !t_us.is_finite() {
        return current_us;
    }
    let mut t = t_us;
    if t <= floor_us - 1.0 {
        t = floor_us;
    }
    t = t.min(limits.effective_max_us());
    limits.clamp(t.trunc())
}

/// Reflect-101 border index (OpenCV's `BORDER_DEFAULT`): -1 -> 1, n -> n - 2.
#[inline]
fn reflect(i: isize, n: usize) -> usize {
    if n == 1 {
        0
    } else if i < 0 {
        (-i) as usize
    } else if i as usize >= n {
        2 * n - 2 - i as usize
    } else {
        i as usize
    }
}

/// The neighbours' columns (left, right) of column `x` of `n`, reflect-101.
#[inline]
pub(crate) fn side_columns(x: usize, n: usize) -> (usize, usize) {
    (reflect(x as isize - 1, n), reflect(x as isize + 1, n))
}

/// The rows above and below row `y` of `n`, reflect-101.
#[inline]
pub(crate) fn side_rows(y: usize, n: usize) -> (usize, usize) {
    (reflect(y as isize - 1, n), reflect(y as isize + 1, n))
}

/// The paper's soft-percentile weights for `len` ranked pixels, percentile `p`, power
/// `k`, as the code computes them: `n = trunc(len p)`, `sin(pi i / 2n)^k` up to `n`,
/// then `sin(pi/2 - pi (i - n) / 2 (len - n))^k`. Unnormalized; `None` below 2 pixels.
pub fn code_weights(len: usize, p: f64, k: u32, out: &mut Vec<f64>) -> Option<f64> {
    out.clear();
    let n = (len as f64 * p) as usize;
    if len < 2 || n == 0 || n >= len {
        return None;
    }
    let half_pi = std::f64::consts::FRAC_PI_2;
    let mut sum = 0.0;
    for i in 0..len {
        let arg = if i <= n {
            half_pi * i as f64 / n as f64
        } else {
            half_pi - half_pi * (i - n) as f64 / (len - n) as f64
        };
        let w = arg.sin().powi(k as i32);
        sum += w;
        out.push(w);
    }
    (sum.is_finite() && sum > 0.0).then_some(sum)
}

/// `M` and its derivative.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PaperMetricValue {
    /// `sum w_i key_i / sum w` (what the code reports as its metric).
    pub m: f64,
    /// `sum w_i G_i / sum w` with the same ranking, `G = Ix^2 + Iy^2`: the function whose
    /// derivative `dm_dt` is (ranks held), so the one the law climbs. Equal to `m` for
    /// the published metric; with `|Ix|` ranking `m` is not it.
    pub climbed: f64,
    /// `d climbed / dt` with the ranks held, per second of exposure.
    pub dm_dt: f64,
    /// Pixels ranked (the whole region).
    pub pixels: usize,
}

/// Settings of one evaluation of the paper's metric.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PaperMetricParams {
    pub metric: PaperMetric,
    /// Percentile `p` of the weights' peak.
    pub percentile: f64,
    /// Power `k` of the sine weights.
    pub weight_power: u32,
}

/// Largest `|Ix|` of a 3x3 Sobel on 8-bit pixels (4 x 255).
const MAX_ABS_IX: usize = 1020;

/// The paper's metric as its code computes it, with reused buffers: on every pixel of
/// the region (`S` = its area), `Ix`, `Iy` by OpenCV's raw 3x3 Sobel on the whole image
/// (the region is a view into it, so its border pixels see their real neighbours;
/// reflect-101 at the image's edge), `D = 1 / (g'(I) t)` and its Sobel on the region
/// alone (a new matrix: reflect-101 at the region's edge), `dG/dt = 2 (Ix Dx + Iy Dy)`;
/// pixels ranked by their key ascending, ties by position (row-major), as its sort of
/// (value, (row, column)) pairs; `M = sum w_i key_i / sum w`,
/// `dM/dt = sum w_i (dG/dt)_i / sum w`. `|Ix|` keys are integers 0..=1020, so counting
/// the keys gives each pixel its rank in the code's order without a sort (pixels of one
/// key take consecutive ranks in row-major order); `Ix^2 + Iy^2` keys are sorted.
#[derive(Debug, Clone)]
pub struct PaperMetricEval {
    /// `1 / g'(I)` per grey level (`D` times the exposure in seconds).
    d_lut: [f64; 256],
    /// Sobel of the image per pixel of the region.
    ix: Vec<i16>,
    iy: Vec<i16>,
    /// Next free rank of each `|Ix|` key.
    slots: Vec<u32>,
    /// `Ix^2 + Iy^2` keys with positions, sorted (the published metric).
    packed: Vec<u64>,
    /// Rank of each pixel (the published metric).
    rank_of: Vec<u32>,
    weights: Vec<f64>,
    /// (len, percentile bits, power) the weights were computed for, and their sum.
    weights_for: Option<(usize, u64, u32, f64)>,
}

impl PaperMetricEval {
    pub fn new(response: &Response) -> Self {
        let mut d_lut = [0.0; 256];
        for (i, d) in d_lut.iter_mut().enumerate() {
            *d = response.di_dlnt(i as u8);
        }
        Self {
            d_lut,
            ix: Vec::new(),
            iy: Vec::new(),
            slots: Vec::new(),
            packed: Vec::new(),
            rank_of: Vec::new(),
            weights: Vec::new(),
            weights_for: None,
        }
    }

    /// `M` and `dM/dt` of the pixels of `roi` in `image` (the whole frame) exposed for
    /// `t_us`. `None` for an empty region, fewer than 2 pixels or a bad exposure.
    pub fn evaluate(
        &mut self,
        image: ImageView<'_>,
        roi: Roi,
        t_us: f64,
        params: &PaperMetricParams,
    ) -> Option<PaperMetricValue> {
        let roi = roi.clamp_to(image.width as u32, image.height as u32);
        if roi.is_empty() || t_us.is_nan() || t_us <= 0.0 {
            return None;
        }
        let (rw, rh) = (roi.width as usize, roi.height as usize);
        let s = rw * rh;
        let key = (s, params.percentile.to_bits(), params.weight_power);
        let wsum = match self.weights_for {
            Some((n, p, k, sum)) if (n, p, k) == key => sum,
            _ => {
                let sum =
                    code_weights(s, params.percentile, params.weight_power, &mut self.weights);
                self.weights_for = sum.map(|sum| (key.0, key.1, key.2, sum));
                sum?
            }
        };
        self.sobel_of_image(image, roi);
        self.rank(params.metric);
        let (x0, y0) = (roi.x as usize, roi.y as usize);
        let d_lut = &self.d_lut;
        let (mut m, mut g, mut dm) = (0.0, 0.0, 0.0);
        for y in 0..rh {
            let (lu, ld) = side_rows(y, rh);
            let row = |r: usize| &image.row(y0 + r)[x0..x0 + rw];
            let (d0, d1, d2) = (row(lu), row(y), row(ld));
            let d = |r: &[u8], i: usize| d_lut[r[i] as usize];
            for x in 0..rw {
                let pos = y * rw + x;
                let (dl, dr) = side_columns(x, rw);
                let dx = (d(d0, dr) - d(d0, dl))
                    + 2.0 * (d(d1, dr) - d(d1, dl))
                    + (d(d2, dr) - d(d2, dl));
                let dy = (d(d2, dl) + 2.0 * d(d2, x) + d(d2, dr))
                    - (d(d0, dl) + 2.0 * d(d0, x) + d(d0, dr));
                let (ix, iy) = (self.ix[pos] as f64, self.iy[pos] as f64);
                let (k, rank) = match params.metric {
                    PaperMetric::AbsIx => {
                        let k = self.ix[pos].unsigned_abs() as usize;
                        let slot = &mut self.slots[k];
                        let r = *slot;
                        *slot += 1;
                        (k as f64, r)
                    }
                    PaperMetric::Published => (ix * ix + iy * iy, self.rank_of[pos]),
                };
                let w = self.weights[rank as usize];
                m += w * k;
                g += w * (ix * ix + iy * iy);
                dm += w * 2.0 * (ix * dx + iy * dy);
            }
        }
        Some(PaperMetricValue {
            m: m / wsum,
            climbed: g / wsum,
            dm_dt: dm / wsum / (t_us * 1e-6),
            pixels: s,
        })
    }

    /// `ix`, `iy` of every pixel of `roi`, neighbours from the whole image.
    fn sobel_of_image(&mut self, image: ImageView<'_>, roi: Roi) {
        let (rw, rh) = (roi.width as usize, roi.height as usize);
        let (x0, y0) = (roi.x as usize, roi.y as usize);
        let (iw, ih) = (image.width, image.height);
        self.ix.clear();
        self.iy.clear();
        for y in 0..rh {
            let gy = y0 + y;
            let (gu, gd) = side_rows(gy, ih);
            let (r0, r1, r2) = (image.row(gu), image.row(gy), image.row(gd));
            for gx in x0..x0 + rw {
                let (xl, xr) = side_columns(gx, iw);
                let p = |r: &[u8], i: usize| r[i] as i16;
                self.ix.push(
                    (p(r0, xr) - p(r0, xl)) + 2 * (p(r1, xr) - p(r1, xl)) + (p(r2, xr) - p(r2, xl)),
                );
                self.iy.push(
                    (p(r2, xl) + 2 * p(r2, gx) + p(r2, xr))
                        - (p(r0, xl) + 2 * p(r0, gx) + p(r0, xr)),
                );
            }
        }
    }

    /// The first rank of each `|Ix|` key in `slots`, or each pixel's rank in `rank_of`.
    fn rank(&mut self, metric: PaperMetric) {
        match metric {
            PaperMetric::AbsIx => {
                self.slots.clear();
                self.slots.resize(MAX_ABS_IX + 2, 0);
                for &v in &self.ix {
                    self.slots[v.unsigned_abs() as usize + 1] += 1;
                }
                for i in 1..self.slots.len() {
                    self.slots[i] += self.slots[i - 1];
                }
            }
            PaperMetric::Published => {
                self.packed.clear();
                self.packed
                    .extend(
                        self.ix
                            .iter()
                            .zip(&self.iy)
                            .enumerate()
                            .map(|(pos, (&x, &y))| {
                                let (x, y) = (x as i64, y as i64);
                                ((x * x + y * y) as u64) << 32 | pos as u64
                            }),
                    );
                self.packed.sort_unstable();
                self.rank_of.clear();
                self.rank_of.resize(self.packed.len(), 0);
                for (r, &v) in self.packed.iter().enumerate() {
                    self.rank_of[v as u32 as usize] = r as u32;
                }
            }
        }
    }
}

/// How a paper method's learning rate follows the region's size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EtaScaling {
    /// The rate as configured (the code).
    None,
    /// The rate times `sqrt(S / reference_pixels)` for a region of `S` pixels: the rate
    /// grows with the region's side. The code's `dM/dt` (|Ix| ranking) shrinks about as
    /// the side grows: the same marker at 1440x1080 has 5.2x the pixels of 640x480 and a
    /// 2.7-2.9x smaller derivative on the pool (docs/design/exposure.md).
    RoiSide,
}

/// Check the shared keys of a paper method's section.
pub(crate) fn check_rate_scaling(
    section: &str,
    scaling: EtaScaling,
    reference_pixels: f64,
) -> Result<(), ConfigError> {
    let mut c = Checks::new(section);
    if scaling == EtaScaling::RoiSide {
        c = c.range(
            "eta_reference_pixels",
            reference_pixels,
            1.0..=1e8,
            "a pixel count in [1, 1e8] (the region size the learning rate is tuned for)",
        );
    }
    c.done()
}

/// The rate for a region of `pixels`.
pub(crate) fn scaled_rate(
    rate: f64,
    scaling: EtaScaling,
    reference_pixels: f64,
    pixels: usize,
) -> f64 {
    match scaling {
        EtaScaling::None => rate,
        EtaScaling::RoiSide => rate * (pixels.max(1) as f64 / reference_pixels).sqrt(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn region_truncates_like_the_code() {
        // Box x 100.7..200.2 -> 100..200, pad 10 px; y 50.9..80.5 -> 50..80, pad 3 px.
        let c = [[100.7, 50.9], [200.2, 50.9], [200.2, 80.5], [100.7, 80.5]];
        let r = code_region(&c, 0.1, 640, 480).unwrap();
        assert_eq!((r.x, r.y, r.width, r.height), (90, 47, 120, 36));
        // Clamped to the image; a negative start truncates toward zero, then 0.
        let c = [[2.0, 1.0], [40.0, 1.0], [40.0, 30.0], [2.0, 30.0]];
        let r = code_region(&c, 0.1, 41, 480).unwrap();
        assert_eq!((r.x, r.y, r.width, r.height), (0, 0, 41, 32));
        assert!(code_region(&[[f32::NAN; 2]; 4], 0.1, 640, 480).is_none());
    }

    #[test]
    fn command_clamps_and_truncates_like_the_code() {
        let l = ExposureLimits {
            min_us: 5.0,
            max_us: 20000.0,
            fps: 30.0,
        };
        assert_eq!(code_command(12.0, 13.0, &l, 100.0), 13.0);
        assert_eq!(code_command(12.5, 13.0, &l, 100.0), 12.0);
        assert_eq!(code_command(1005.8, 13.0, &l, 100.0), 1005.0);
        assert_eq!(code_command(1e9, 13.0, &l, 100.0), 20000.0);
        assert_eq!(code_command(f64::NAN, 13.0, &l, 100.0), 100.0);
    }

    #[test]
    fn reflect_101() {
        assert_eq!(side_columns(0, 5), (1, 1));
        assert_eq!(side_columns(4, 5), (3, 3));
        assert_eq!(side_columns(2, 5), (1, 3));
        assert_eq!(side_columns(0, 1), (0, 0));
    }

    /// The 3x3 Sobel derivatives (x, y) of `f` at (x, y).
    fn sobel(f: &impl Fn(isize, isize) -> f64, x: isize, y: isize) -> (f64, f64) {
        let dx =
            f(x + 1, y - 1) - f(x - 1, y - 1) + 2.0 * (f(x + 1, y) - f(x - 1, y)) + f(x + 1, y + 1)
                - f(x - 1, y + 1);
        let dy = f(x - 1, y + 1) + 2.0 * f(x, y + 1) + f(x + 1, y + 1)
            - f(x - 1, y - 1)
            - 2.0 * f(x, y - 1)
            - f(x + 1, y - 1);
        (dx, dy)
    }

    /// The metric by the naive route: every pixel's key, a full sort of (key, position).
    fn naive(
        img: &[u8],
        w: usize,
        h: usize,
        roi: Roi,
        t_us: f64,
        p: &PaperMetricParams,
        d_lut: &[f64; 256],
    ) -> (f64, f64) {
        let at = |x: isize, y: isize| -> f64 { img[reflect(y, h) * w + reflect(x, w)] as f64 };
        let (rw, rh) = (roi.width as isize, roi.height as isize);
        let dat = |x: isize, y: isize| -> f64 {
            let (x, y) = (reflect(x, rw as usize), reflect(y, rh as usize));
            d_lut[img[(roi.y as usize + y) * w + roi.x as usize + x] as usize] / (t_us * 1e-6)
        };
        let mut px = Vec::new();
        for y in 0..rh {
            for x in 0..rw {
                let (gx, gy) = (roi.x as isize + x, roi.y as isize + y);
                let (ix, iy) = sobel(&at, gx, gy);
                let (dx, dy) = sobel(&dat, x, y);
                let key = match p.metric {
                    PaperMetric::AbsIx => ix.abs(),
                    PaperMetric::Published => ix * ix + iy * iy,
                };
                px.push((key, (y * rw + x) as usize, 2.0 * (ix * dx + iy * dy)));
            }
        }
        px.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut w = Vec::new();
        let sum = code_weights(px.len(), p.percentile, p.weight_power, &mut w).unwrap();
        let m: f64 = px.iter().zip(&w).map(|(q, w)| w / sum * q.0).sum();
        let dm: f64 = px.iter().zip(&w).map(|(q, w)| w / sum * q.2).sum();
        (m, dm)
    }

    #[test]
    fn counting_sort_metric_equals_the_full_sort_with_the_codes_borders() {
        let (w, h) = (37usize, 29usize);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let img: Vec<u8> = (0..w * h)
            .map(|i| {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                // Blocks with noise: ties in |Ix| and real edges.
                let block = if (i % w) / 9 % 2 == (i / w) / 7 % 2 {
                    200
                } else {
                    40
                };
                (block + (seed % 7) as i32 - 3) as u8
            })
            .collect();
        let view = ImageView::new(w, h, &img).unwrap();
        let response = Response::paper_code();
        let mut e = PaperMetricEval::new(&response);
        let mut d_lut = [0.0; 256];
        for (i, d) in d_lut.iter_mut().enumerate() {
            *d = response.di_dlnt(i as u8);
        }
        // A region touching the image's edge and one inside it.
        for roi in [
            Roi {
                x: 0,
                y: 3,
                width: 20,
                height: 26,
            },
            Roi {
                x: 5,
                y: 4,
                width: 25,
                height: 20,
            },
        ] {
            for metric in [PaperMetric::AbsIx, PaperMetric::Published] {
                let p = PaperMetricParams {
                    metric,
                    percentile: 0.9,
                    weight_power: 5,
                };
                let v = e.evaluate(view, roi, 1500.0, &p).unwrap();
                let (m, dm) = naive(&img, w, h, roi, 1500.0, &p, &d_lut);
                assert_eq!(v.pixels, (roi.width * roi.height) as usize);
                assert!(
                    (v.m / m - 1.0).abs() < 1e-12,
                    "{metric:?} {roi:?}: {} vs {m}",
                    v.m
                );
                assert!(
                    (v.dm_dt / dm - 1.0).abs() < 1e-9,
                    "{metric:?} {roi:?}: {} vs {dm}",
                    v.dm_dt
                );
            }
        }
    }
}
