//! GEC as the AAEC paper's code ran it (its `active_gec` branch,
//! Rennylex/adaptive_active_exposure_control `src/changeParam.cpp`), beside Shim's
//! published GEC (`gec.rs`). The paper states none of these; the code does:
//!
//! - Region: the tracker's corner box padded by 10 % (truncated, as for its AAEC), then
//!   grown by 25 px on each side on every frame until the next detection resets it (the
//!   bounds are kept between frames); before the first detection they start from zero,
//!   so the region grows from the image's top-left corner (`region = "marker-grown"`,
//!   the code until 2023-09-28; from d8a72df, 2023-10-13, the crop is commented out and
//!   the whole frame is metered: `region = "whole-frame"`).
//! - The crop min-max normalised to [0, 1] (OpenCV's `normalize`: `v scale + shift`, a
//!   fused multiply-add); for gamma 1 and each of the 11 anchors {1/1.9, 1/1.5, 1/1.3,
//!   1/1.2, 1/1.1, 1, 1.1, 1.2, 1.3, 1.5, 1.9}: `v^gamma` (OpenCV's `pow`: NaN for the
//!   darkest level's negative rounding residue, which blanks its 3x3 neighbourhood),
//!   raw 3x3 Sobel in x and y (reflect-101 borders), each made an
//!   8-bit integer (`convertScaleAbs`: through f32, rounded half to even, saturated),
//!   squared and summed in 8 bits (saturating at 255); the score is
//!   `sum over pixels with q >= delta of ln(lambda (q - delta) + 1) / ln(lambda (1 - delta) + 1)`
//!   in row-major order, delta 0.04, lambda 1000.
//! - The discrete argmax: gamma 1's score first, then the anchors in order, replacing the
//!   best only when strictly greater (gamma 1 is kept on ties).
//! - Shim's nonlinear update, `R = d tan((2 - gamma) atan2(1, d) - atan2(1, d)) + 1`,
//!   `t <- t (1 + alpha Kp (R - 1))`, alpha 0.5 when gamma >= 1 else 1, d 0.1, Kp 1e-8
//!   (the launch file's value from 2023-07-20 on; earlier 0.4 in the source, then 0.1);
//!   at or below 12 us becomes 13 us, whole microseconds. Every frame is used.

use crate::paper_code::{code_command, code_region, side_columns, side_rows, PaperFrames};
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, ImageView, Roi,
};
use markhold_config::{open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// The code's anchor gammas, in its order.
pub const GEC_PAPER_ANCHORS: [f64; 11] = [
    1.0 / 1.9,
    1.0 / 1.5,
    1.0 / 1.3,
    1.0 / 1.2,
    1.0 / 1.1,
    1.0,
    1.1,
    1.2,
    1.3,
    1.5,
    1.9,
];

/// What the paper's GEC meters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GecRegion {
    /// The marker's padded box grown by `grow_px` a frame (the code until 2023-09-28).
    MarkerGrown,
    /// The whole frame (the code from 2023-10-13).
    WholeFrame,
}

/// The `[exposure.gec_paper]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GecPaperConfig {
    /// `marker-grown` (default) or `whole-frame`.
    pub region: GecRegion,
    /// Padding of the marker's corner box on each side, fraction of its size, [0, 1]
    /// (code: 0.1).
    pub roi_pad_frac: f64,
    /// Pixels the region grows on each side every frame, 0..=1000 (code: 25).
    pub grow_px: u32,
    /// Activation threshold delta, [0, 1) (code: 0.04).
    pub delta: f64,
    /// Mapping sharpness lambda, (0, 1e6] (code: 1000).
    pub lambda: f64,
    /// Proportional gain Kp, (0, 2] (code: 1e-8; 0.4 and 0.1 before 2023-07-20).
    pub kp: f64,
    /// Nonlinearity d of the update, (0, 10] (code: 0.1).
    pub d: f64,
    /// Commands at or below `floor_us - 1` become `floor_us`, microseconds, [0, 1000]
    /// (code: 13).
    pub floor_us: f64,
    /// `every` (code) or `exposed-as-commanded`.
    pub frames: PaperFrames,
}

impl Default for GecPaperConfig {
    fn default() -> Self {
        Self {
            region: GecRegion::MarkerGrown,
            roi_pad_frac: 0.1,
            grow_px: 25,
            delta: 0.04,
            lambda: 1000.0,
            kp: 1e-8,
            d: 0.1,
            floor_us: 13.0,
            frames: PaperFrames::Every,
        }
    }
}

impl GecPaperConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.gec_paper")
            .range("roi_pad_frac", self.roi_pad_frac, 0.0..=1.0, "a fraction in [0, 1]")
            .range("grow_px", self.grow_px, 0..=1000, "pixels in 0..=1000")
            .range("delta", self.delta, 0.0..1.0, "a threshold in [0, 1)")
            .range("lambda", self.lambda, open_closed(0.0, 1e6), "a value in (0, 1e6]")
            .range("kp", self.kp, open_closed(0.0, 2.0), "a gain in (0, 2]")
            .range("d", self.d, open_closed(0.0, 10.0), "a value in (0, 10]")
            .range("floor_us", self.floor_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .done()
    }
}

/// The code's GEC score of an 8-bit image for each gamma, with reused buffers.
#[derive(Debug, Clone)]
pub struct GecPaperScorer {
    delta: f64,
    lambda: f64,
    /// Score term per 8-bit squared magnitude.
    term: [f64; 256],
    /// Horizontal difference and smoothing (the separable Sobel's first pass) of three
    /// rows, a ring.
    h: Vec<f64>,
    s: Vec<f64>,
    /// One row's levels and 8-bit magnitudes.
    v: Vec<f64>,
    q: Vec<u8>,
}

/// OpenCV's `convertScaleAbs` of a double: through f32, absolute, rounded half to even,
/// saturated to 8 bits.
#[inline(always)]
pub fn quantize_abs(v: f64) -> u8 {
    // Adding 2^23 leaves no fraction bits: the sum is rounded half to even, as the vector
    // conversion does (`round_ties_even` is a libm call on baseline x86-64). NaN (a NaN
    // level spread by the filter) stays NaN and casts to 0, as OpenCV's conversion gives.
    const SHIFT: f32 = 8_388_608.0;
    let f = (v as f32).abs();
    let r = (f + SHIFT) - SHIFT;
    if r >= 255.0 {
        255
    } else {
        r as u8
    }
}

/// [`quantize_abs`] as an integer-valued f32 (0..=255), for lanes of floats.
#[inline(always)]
fn quantize_abs_f32(v: f64) -> f32 {
    const SHIFT: f32 = 8_388_608.0;
    let r = ((v as f32).abs() + SHIFT) - SHIFT;
    // NaN fails both tests: 0.
    if r >= 255.0 {
        255.0
    } else if r >= 0.0 {
        r
    } else {
        0.0
    }
}

/// The 8-bit squared magnitude of one pixel: `sat(sat(ax^2) + sat(ay^2))` (exact in f32:
/// integers up to 510).
#[inline(always)]
fn magnitude(ix: f64, iy: f64) -> u8 {
    let (ax, ay) = (quantize_abs_f32(ix), quantize_abs_f32(iy));
    let m = ((ax * ax).min(255.0) + (ay * ay).min(255.0)).min(255.0);
    // SAFETY: `m` is finite and in [0, 255] (both terms are integers in [0, 255]), so
    // the conversion is exact (the checked cast keeps the lanes scalar).
    unsafe { m.to_int_unchecked::<i32>() as u8 }
}

/// The row pass of OpenCV's separable 3x3 Sobel on f64 (reflect-101 at the ends):
/// `h = (-a + 0 b) + c` and `s = (a + 2 b) + c` of each pixel's left, centre and right.
#[inline(always)]
fn row_pass(row: &[u8], levels: &[f64; 256], v: &mut [f64], h: &mut [f64], s: &mut [f64]) {
    let w = row.len();
    for (o, &p) in v.iter_mut().zip(row) {
        *o = levels[p as usize];
    }
    let one = |x: usize, h: &mut [f64], s: &mut [f64]| {
        let (xl, xr) = side_columns(x, w);
        let (a, b, c) = (v[xl], v[x], v[xr]);
        h[x] = (-a + 0.0 * b) + c;
        s[x] = (a + 2.0 * b) + c;
    };
    if w < 3 {
        for x in 0..w {
            one(x, h, s);
        }
        return;
    }
    one(0, h, s);
    for (((hx, sx), (a, b)), c) in h[1..w - 1]
        .iter_mut()
        .zip(&mut s[1..w - 1])
        .zip(v[..w - 2].iter().zip(&v[1..w - 1]))
        .zip(&v[2..])
    {
        *hx = (-a + 0.0 * b) + c;
        *sx = (a + 2.0 * b) + c;
    }
    one(w - 1, h, s);
}

impl GecPaperScorer {
    pub fn new(delta: f64, lambda: f64) -> Self {
        let n = (lambda * (1.0 - delta) + 1.0).ln();
        let n_inv = 1.0 / n;
        let mut term = [0.0; 256];
        for (q, t) in term.iter_mut().enumerate() {
            let val = q as f64;
            if val >= delta {
                *t = n_inv * (lambda * (val - delta) + 1.0).ln();
            }
        }
        Self {
            delta,
            lambda,
            term,
            h: Vec::new(),
            s: Vec::new(),
            v: Vec::new(),
            q: Vec::new(),
        }
    }

    /// The min-max normalised value of each grey level of `view` (OpenCV's
    /// `normalize(NORM_MINMAX)` to [0, 1]: scale `1 / (max - min)`, shift `-min scale`,
    /// applied as one fused multiply-add as its vector code does).
    pub fn normalised_levels(view: ImageView<'_>) -> [f64; 256] {
        let (mut lo, mut hi) = (u8::MAX, 0u8);
        for y in 0..view.height {
            for &p in view.row(y) {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        let (smin, smax) = (lo as f64, hi as f64);
        let scale = if smax - smin > f64::EPSILON {
            1.0 / (smax - smin)
        } else {
            0.0
        };
        let shift = 0.0 - smin * scale;
        let mut out = [0.0; 256];
        for (v, o) in out.iter_mut().enumerate() {
            *o = (v as f64).mul_add(scale, shift);
        }
        out
    }

    /// `v^gamma` of each normalised level (gamma 1: the levels themselves). As OpenCV's
    /// `pow` does in the code's build (its documentation says absolute values; the
    /// implementation takes logs): a negative level, the normalisation's rounding residue
    /// at the crop's darkest grey (`fma(min, scale, -min scale)`), gives NaN for a
    /// non-integer gamma, the Sobel spreads it to the 3x3 neighbourhood and those pixels
    /// quantise to 0.
    pub fn gamma_levels(norm: &[f64; 256], gamma: f64) -> [f64; 256] {
        if gamma == 1.0 {
            return *norm;
        }
        norm.map(|v| v.powf(gamma))
    }

    /// The score of `view` with its grey levels mapped through `levels`; with `out`, the
    /// 8-bit squared magnitudes too (row-major).
    pub fn score(
        &mut self,
        view: ImageView<'_>,
        levels: &[f64; 256],
        out: Option<&mut Vec<u8>>,
    ) -> f64 {
        // The same code compiled twice: with AVX2 the f64 lanes double. No FMA (Rust never
        // fuses on its own) and the same operations in the same order, so both builds
        // give bit-identical scores.
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { self.score_avx2(view, levels, out) };
        }
        self.score_portable(view, levels, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn score_avx2(
        &mut self,
        view: ImageView<'_>,
        levels: &[f64; 256],
        out: Option<&mut Vec<u8>>,
    ) -> f64 {
        self.score_portable(view, levels, out)
    }

    /// [`Self::score`] without CPU dispatch. Rows are filtered as OpenCV's separable
    /// Sobel does for f64 (row pass, then column pass), three rows at a time.
    #[inline(always)]
    fn score_portable(
        &mut self,
        view: ImageView<'_>,
        levels: &[f64; 256],
        mut out: Option<&mut Vec<u8>>,
    ) -> f64 {
        let (w, h) = (view.width, view.height);
        if let Some(o) = out.as_deref_mut() {
            o.clear();
        }
        if w == 0 || h == 0 {
            return 0.0;
        }
        // A ring of three rows of the row pass: `h` the x kernel [-1, 0, 1] (the centre's
        // 0 weight applied, as OpenCV's row filter does: a NaN there spreads to Ix), `s`
        // the y kernel's [1, 2, 1].
        self.h.resize(3 * w, 0.0);
        self.s.resize(3 * w, 0.0);
        self.v.resize(w, 0.0);
        self.q.resize(w, 0);
        let mut ready = 0usize;
        let mut score = 0.0;
        for y in 0..h {
            let (ya, yb) = side_rows(y, h);
            while ready <= yb.max(y) {
                let slot = ready % 3;
                row_pass(
                    view.row(ready),
                    levels,
                    &mut self.v,
                    &mut self.h[slot * w..(slot + 1) * w],
                    &mut self.s[slot * w..(slot + 1) * w],
                );
                ready += 1;
            }
            fn row(buf: &[f64], r: usize, w: usize) -> &[f64] {
                &buf[(r % 3) * w..(r % 3 + 1) * w]
            }
            let (ha, hc, hb) = (row(&self.h, ya, w), row(&self.h, y, w), row(&self.h, yb, w));
            let (sa, sb) = (row(&self.s, ya, w), row(&self.s, yb, w));
            // Column pass, [1, 2, 1] for Ix (centre first), [-1, 0, 1] for Iy.
            for (x, q) in self.q.iter_mut().enumerate() {
                let ix = 2.0 * hc[x] + (hb[x] + ha[x]);
                let iy = sb[x] - sa[x];
                *q = magnitude(ix, iy);
            }
            // In row-major order, as the code sums; a zero term leaves the sum as it is
            // (eight pixels at a time past the flat ones).
            let mut chunks = self.q.chunks_exact(8);
            for c in &mut chunks {
                if u64::from_ne_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) != 0 {
                    for &q in c {
                        if q != 0 {
                            score += self.term[q as usize];
                        }
                    }
                }
            }
            for &q in chunks.remainder() {
                if q != 0 {
                    score += self.term[q as usize];
                }
            }
            if let Some(o) = out.as_deref_mut() {
                o.extend_from_slice(&self.q);
            }
        }
        score
    }

    /// Gamma 1's score and each anchor's (anchor 1 is gamma 1's).
    pub fn scores(&mut self, view: ImageView<'_>) -> (f64, [f64; 11]) {
        let norm = Self::normalised_levels(view);
        let first = self.score(view, &norm, None);
        let mut out = [0.0; 11];
        for (o, &g) in out.iter_mut().zip(&GEC_PAPER_ANCHORS) {
            *o = if g == 1.0 {
                first
            } else {
                self.score(view, &Self::gamma_levels(&norm, g), None)
            };
        }
        (first, out)
    }

    pub fn delta(&self) -> f64 {
        self.delta
    }

    pub fn lambda(&self) -> f64 {
        self.lambda
    }
}

/// The code's choice of gamma from gamma 1's score and the anchors' (strictly greater
/// replaces, in the anchors' order).
pub fn gec_paper_gamma(first: f64, scores: &[f64; 11]) -> f64 {
    let (mut best, mut gamma) = (first, 1.0);
    for (&s, &g) in scores.iter().zip(&GEC_PAPER_ANCHORS) {
        if s > best {
            best = s;
            gamma = g;
        }
    }
    gamma
}

/// Shim's nonlinear update as the code writes it: the next exposure, microseconds.
pub fn gec_paper_update(t_us: f64, gamma: f64, kp: f64, d: f64) -> f64 {
    let alpha = if gamma >= 1.0 { 0.5 } else { 1.0 };
    let a = 1.0f64.atan2(d);
    let r = d * ((2.0 - gamma) * a - a).tan() + 1.0;
    let t = t_us / 1_000_000.0;
    t * (1.0 + alpha * kp * (r - 1.0)) * 1_000_000.0
}

/// GEC as the paper's code ran it. See the module documentation.
pub struct GecPaper {
    cfg: GecPaperConfig,
    limits: ExposureLimits,
    scorer: GecPaperScorer,
    /// The code's region bounds, kept between frames: x0, y0, x1, y1.
    bounds: [i64; 4],
    commanded_us: f64,
}

impl GecPaper {
    pub fn new(
        cfg: GecPaperConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            scorer: GecPaperScorer::new(cfg.delta, cfg.lambda),
            bounds: [0; 4],
            commanded_us: limits.clamp(initial_us),
            limits,
            cfg,
        })
    }

    /// This frame's region: reset to the marker's padded box on a detection, then grown.
    fn region(&mut self, marker: Option<&Corners>, w: u32, h: u32) -> Roi {
        if let Some(r) = marker.and_then(|c| code_region(c, self.cfg.roi_pad_frac, w, h)) {
            self.bounds = [
                r.x as i64,
                r.y as i64,
                (r.x + r.width) as i64,
                (r.y + r.height) as i64,
            ];
        }
        let g = self.cfg.grow_px as i64;
        let [x0, y0, x1, y1] = self.bounds;
        self.bounds = [
            (x0 - g).max(0),
            (y0 - g).max(0),
            (x1 + g).min(w as i64),
            (y1 + g).min(h as i64),
        ];
        let [x0, y0, x1, y1] = self.bounds;
        match self.cfg.region {
            GecRegion::WholeFrame => Roi {
                x: 0,
                y: 0,
                width: w,
                height: h,
            },
            GecRegion::MarkerGrown => Roi {
                x: x0.max(0) as u32,
                y: y0.max(0) as u32,
                width: (x1 - x0).max(0) as u32,
                height: (y1 - y0).max(0) as u32,
            },
        }
    }
}

impl ExposureController for GecPaper {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::GecPaper
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        let hold = ExposureStep::skipped(self.commanded_us);
        if !frame.is_consistent() {
            return hold;
        }
        let roi = self.region(marker, frame.width, frame.height);
        if roi.is_empty()
            || (self.cfg.frames == PaperFrames::ExposedAsCommanded
                && !exposed_as_commanded(frame, self.commanded_us))
        {
            return hold;
        }
        let (first, scores) = self.scorer.scores(frame.view().crop(roi));
        let gamma = gec_paper_gamma(first, &scores);
        let next = gec_paper_update(self.commanded_us, gamma, self.cfg.kp, self.cfg.d);
        self.commanded_us = code_command(next, self.cfg.floor_us, &self.limits, self.commanded_us);
        ExposureStep::used(self.commanded_us, first, Some(roi))
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.bounds = [0; 4];
        self.commanded_us = self.limits.clamp(exposure_us);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchors_are_the_codes_list() {
        assert_eq!(GEC_PAPER_ANCHORS[5], 1.0);
        assert!(GEC_PAPER_ANCHORS.windows(2).all(|p| p[1] > p[0]));
        assert_eq!(GEC_PAPER_ANCHORS[0], 1.0 / 1.9);
        assert_eq!(GEC_PAPER_ANCHORS[10], 1.9);
    }

    #[test]
    fn gamma_1_is_kept_on_ties_and_the_first_strict_maximum_wins() {
        let first = 5.0;
        let mut s = [5.0; 11];
        assert_eq!(gec_paper_gamma(first, &s), 1.0);
        s[2] = 6.0;
        s[8] = 6.0;
        assert_eq!(gec_paper_gamma(first, &s), 1.0 / 1.3);
        s[9] = 6.5;
        assert_eq!(gec_paper_gamma(first, &s), 1.5);
    }

    #[test]
    fn the_update_barely_moves_with_the_codes_gain() {
        // Kp 1e-8: even the largest correction changes the exposure by < 1e-7.
        let t = gec_paper_update(1000.0, 1.0 / 1.9, 1e-8, 0.1);
        assert!(t > 1000.0 && t - 1000.0 < 1e-4, "{t}");
        // With Kp 0.1 gamma 1/1.9 lengthens, 1.9 shortens; gamma 1 keeps.
        assert!(gec_paper_update(1000.0, 1.0 / 1.9, 0.1, 0.1) > 1000.0);
        assert!(gec_paper_update(1000.0, 1.9, 0.1, 0.1) < 1000.0);
        assert!((gec_paper_update(1000.0, 1.0, 0.1, 0.1) - 1000.0).abs() < 1e-9);
    }

    #[test]
    fn quantize_rounds_half_to_even_through_f32() {
        assert_eq!(quantize_abs(2.5), 2);
        assert_eq!(quantize_abs(-3.5), 4);
        assert_eq!(quantize_abs(0.49999999999999994), 0);
        // 2.4999999999 is 2.5 in f32, then 2; 3.4999999999 is 3.5, then 4.
        assert_eq!(quantize_abs(3.4999999999), 4);
        assert_eq!(quantize_abs(300.0), 255);
        assert_eq!(magnitude(16.0, 16.0), 255);
        assert_eq!(magnitude(3.0, 4.0), 25);
        assert_eq!(magnitude(f64::NAN, 2.0), 4);
        for v in [
            0.0,
            0.5,
            1.5,
            2.4999999999,
            3.5,
            254.5,
            300.0,
            f64::NAN,
            f64::INFINITY,
        ] {
            assert_eq!(quantize_abs_f32(v) as u8, quantize_abs(v), "{v}");
        }
    }

    #[test]
    fn the_region_is_box_plus_10_percent_then_grows_25_px_a_frame() {
        let limits = ExposureLimits {
            min_us: 10.0,
            max_us: 20_000.0,
            fps: 30.0,
        };
        let mut g = GecPaper::new(GecPaperConfig::default(), limits, 1000.0).unwrap();
        // Before a detection: from the top-left corner, 25 px more each frame.
        assert_eq!(
            g.region(None, 160, 120),
            Roi {
                x: 0,
                y: 0,
                width: 25,
                height: 25
            }
        );
        assert_eq!(
            g.region(None, 160, 120),
            Roi {
                x: 0,
                y: 0,
                width: 50,
                height: 50
            }
        );
        // Detection: box 40..80 x 30..70, +4 px, then +25.
        let c = [[40.0, 30.0], [80.0, 30.0], [80.0, 70.0], [40.0, 70.0]];
        assert_eq!(
            g.region(Some(&c), 160, 120),
            Roi {
                x: 11,
                y: 1,
                width: 98,
                height: 98
            }
        );
        // Lost: it keeps growing, clamped to the image.
        assert_eq!(
            g.region(None, 160, 120),
            Roi {
                x: 0,
                y: 0,
                width: 134,
                height: 120
            }
        );
    }

    #[test]
    fn a_flat_crop_scores_zero_at_every_gamma() {
        let data = vec![77u8; 30 * 20];
        let view = ImageView::new(30, 20, &data).unwrap();
        let mut s = GecPaperScorer::new(0.04, 1000.0);
        let (first, scores) = s.scores(view);
        assert_eq!(first, 0.0);
        assert!(scores.iter().all(|&v| v == 0.0));
    }
}
