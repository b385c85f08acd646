//! GEC: gamma-based exposure control (Shim, Lee, Kweon, IROS 2014; Shim et al., IEEE
//! TCSVT 2018), with the published constants.
//!
//! On a downsampled whole image: gradient magnitude `m` in [0, 1] (integer Sobel over
//! 4 * 255, so a full-contrast step edge is 1), information
//! `m_bar = ln(lambda (m - delta) + 1) / ln(lambda (1 - delta) + 1)` for `m >= delta`
//! (else 0), score = sum of `m_bar`. The score of the image mapped by each anchor gamma
//! `255 (I/255)^gamma` is fitted by a 5th-order polynomial in gamma; its argmax
//! `gamma_hat` in [1/1.9, 1.9] drives the nonlinear update
//! `R = 1 + d tan((1 - gamma_hat) atan(1/d))`, `t <- (1 + alpha Kp (R - 1)) t`,
//! `alpha = 0.5` if `gamma_hat >= 1` else 1.

use crate::pyramid::Downsampler;
use markhold_config::{open_closed, Checks, ConfigError};

use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, ImageView,
};
use serde::{Deserialize, Serialize};

/// The anchor gammas of the papers.
pub const GEC_GAMMAS: [f64; 7] = [1.0 / 1.9, 1.0 / 1.5, 1.0 / 1.2, 1.0, 1.2, 1.5, 1.9];

/// The `[exposure.gec]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GecConfig {
    /// Downsampling factor of the scored image, 1..=32.
    pub downsample: u32,
    /// Activation threshold delta of the gradient magnitude, [0, 1) (published: 0.06).
    pub delta: f64,
    /// Mapping sharpness lambda, (0, 1e6] (published: 1000).
    pub lambda: f64,
    /// Proportional gain Kp, (0, 2] (published: 0.2; the AAEC paper's baseline ran
    /// with 1e-8, which barely moves).
    pub kp: f64,
    /// Nonlinearity d of the update, (0, 10] (published: 0.1).
    pub d: f64,
    /// Not in the papers (ours, for a fair baseline): when no anchor scores anything
    /// (black or washed-out frame, where every gamma gives the same image), step the
    /// mean grey toward 127, by at most 2x per frame. Without it GEC never leaves a
    /// washed-out frame.
    pub no_information_fallback: bool,
}

impl Default for GecConfig {
    fn default() -> Self {
        Self {
            downsample: 4,
            delta: 0.06,
            lambda: 1000.0,
            kp: 0.2,
            d: 0.1,
            no_information_fallback: true,
        }
    }
}

impl GecConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.gec")
            .range("downsample", self.downsample, 1..=32, "a factor in 1..=32")
            .range("delta", self.delta, 0.0..1.0, "a threshold in [0, 1)")
            .range("lambda", self.lambda, open_closed(0.0, 1e6), "a value in (0, 1e6]")
            .range("kp", self.kp, open_closed(0.0, 2.0), "a gain in (0, 2]")
            .range("d", self.d, open_closed(0.0, 10.0), "a value in (0, 10]")
            .done()
    }
}

/// The GEC exposure ratio for an estimated best gamma (published update rule).
pub fn gec_ratio(gamma_hat: f64, kp: f64, d: f64) -> f64 {
    let r = 1.0 + d * ((1.0 - gamma_hat) * (1.0 / d).atan()).tan();
    let alpha = if gamma_hat >= 1.0 { 0.5 } else { 1.0 };
    1.0 + alpha * kp * (r - 1.0)
}

/// Least-squares polynomial of degree 5 through `(x, y)` (7 points), in powers of
/// `x - 1`; `None` if the system is singular.
pub fn fit_quintic(x: &[f64; 7], y: &[f64; 7]) -> Option<[f64; 6]> {
    fit_quintic_points(x, y)
}

/// [`fit_quintic`] through any number (>= 6) of points.
pub fn fit_quintic_points(x: &[f64], y: &[f64]) -> Option<[f64; 6]> {
    if x.len() < 6 || x.len() != y.len() {
        return None;
    }
    // Normal equations A^T A c = A^T y, 6x6, Gaussian elimination with partial pivoting.
    let mut a = [[0.0f64; 7]; 6];
    for (xi, yi) in x.iter().zip(y) {
        let u = xi - 1.0;
        let mut pw = [1.0f64; 6];
        for k in 1..6 {
            pw[k] = pw[k - 1] * u;
        }
        for r in 0..6 {
            for c in 0..6 {
                a[r][c] += pw[r] * pw[c];
            }
            a[r][6] += pw[r] * yi;
        }
    }
    for col in 0..6 {
        let piv = (col..6).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-300 {
            return None;
        }
        a.swap(col, piv);
        let pivot_row = a[col];
        for (r, row) in a.iter_mut().enumerate() {
            if r != col {
                let f = row[col] / pivot_row[col];
                for (v, p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                    *v -= f * p;
                }
            }
        }
    }
    let mut c = [0.0; 6];
    for k in 0..6 {
        c[k] = a[k][6] / a[k][k];
        if !c[k].is_finite() {
            return None;
        }
    }
    Some(c)
}

fn poly(c: &[f64; 6], x: f64) -> f64 {
    let u = x - 1.0;
    c.iter().rev().fold(0.0, |acc, &k| acc * u + k)
}

/// Argmax of the fitted polynomial on [1/1.9, 1.9] (dense grid, then a finer one).
pub fn best_gamma(c: &[f64; 6]) -> f64 {
    let (lo, hi) = (1.0 / 1.9, 1.9);
    let mut best = (1.0, poly(c, 1.0));
    let n = 400;
    for i in 0..=n {
        let g = lo + (hi - lo) * i as f64 / n as f64;
        let v = poly(c, g);
        if v > best.1 {
            best = (g, v);
        }
    }
    let step = (hi - lo) / n as f64;
    let (a, b) = ((best.0 - step).max(lo), (best.0 + step).min(hi));
    for i in 0..=100 {
        let g = a + (b - a) * i as f64 / 100.0;
        let v = poly(c, g);
        if v > best.1 {
            best = (g, v);
        }
    }
    best.0
}

/// Reusable GEC scorer: gamma tables, information table, buffers.
#[derive(Debug, Clone)]
pub struct GecScorer {
    /// Gamma-mapped grey for each anchor.
    maps: Vec<[u8; 256]>,
    /// `m_bar` in 1/65536 by a key of `sx^2 + sy^2` (its f32 bits: exact below 512,
    /// 1/256 relative above), so the inner loop has no sqrt, no log and an integer sum.
    info: Vec<u32>,
    rows: [Vec<u8>; 3],
}

const INFO_MANTISSA_BITS: u32 = 8;
/// Keys of `sx^2 + sy^2 <= 2 * 1020^2 < 2^21`.
const INFO_SLOTS: usize = 8192;
const _: () = assert!(21 * (1 << INFO_MANTISSA_BITS) < INFO_SLOTS);
const INFO_ONE: f64 = 65536.0;

#[inline(always)]
fn info_key(g: f32) -> usize {
    let bits = g.to_bits() >> (23 - INFO_MANTISSA_BITS);
    let k = if g == 0.0 {
        0
    } else {
        bits.wrapping_sub((127 << INFO_MANTISSA_BITS) - 1)
    };
    k as usize & (INFO_SLOTS - 1)
}

/// The squared Sobel magnitude a key stands for (the middle of its range).
fn info_key_value(k: usize) -> f64 {
    if k == 0 {
        return 0.0;
    }
    let base = |k: usize| {
        f32::from_bits(((k as u32 - 1) + (127 << INFO_MANTISSA_BITS)) << (23 - INFO_MANTISSA_BITS))
            as f64
    };
    let (lo, hi) = (base(k), base(k + 1));
    if hi - lo <= 1.0 {
        lo
    } else {
        0.5 * (lo + hi)
    }
}

impl GecScorer {
    pub fn new(cfg: &GecConfig) -> Self {
        Self::with_gammas(cfg, &GEC_GAMMAS)
    }

    /// A scorer with other anchor gammas than the published seven.
    pub fn with_gammas(cfg: &GecConfig, gammas: &[f64]) -> Self {
        let mut maps = vec![[0u8; 256]; gammas.len()];
        for (map, &g) in maps.iter_mut().zip(gammas.iter()) {
            for (i, v) in map.iter_mut().enumerate() {
                *v = (255.0 * (i as f64 / 255.0).powf(g)).round() as u8;
            }
        }
        let norm = (cfg.lambda * (1.0 - cfg.delta) + 1.0).ln();
        let info = (0..INFO_SLOTS)
            .map(|k| {
                let m = (info_key_value(k).sqrt() / 1020.0).min(1.0);
                if m < cfg.delta {
                    0
                } else {
                    ((cfg.lambda * (m - cfg.delta) + 1.0).ln() / norm * INFO_ONE).round() as u32
                }
            })
            .collect();
        Self {
            maps,
            info,
            rows: [Vec::new(), Vec::new(), Vec::new()],
        }
    }

    /// Information score of `view` mapped by each anchor gamma.
    pub fn scores(&mut self, view: ImageView<'_>) -> Option<[f64; 7]> {
        let mut out = [0.0f64; 7];
        (self.maps.len() == 7 && self.scores_into(view, &mut out)).then_some(out)
    }

    /// Information score of `view` mapped by each anchor gamma into `out` (one per
    /// anchor); false when the view is smaller than 3x3 or `out` has another length.
    pub fn scores_into(&mut self, view: ImageView<'_>, out: &mut [f64]) -> bool {
        let (w, h) = (view.width, view.height);
        if w < 3 || h < 3 || out.len() != self.maps.len() {
            return false;
        }
        for r in &mut self.rows {
            if r.len() < w {
                r.resize(w, 0);
            }
        }
        for (gi, map) in self.maps.iter().enumerate() {
            for k in 0..2 {
                for (d, &p) in self.rows[k][..w].iter_mut().zip(view.row(k)) {
                    *d = map[p as usize];
                }
            }
            let mut acc = 0u64;
            for y in 1..h - 1 {
                {
                    let slot = &mut self.rows[(y + 1) % 3];
                    for (d, &p) in slot[..w].iter_mut().zip(view.row(y + 1)) {
                        *d = map[p as usize];
                    }
                }
                let r0 = &self.rows[(y - 1) % 3][..w];
                let r1 = &self.rows[y % 3][..w];
                let r2 = &self.rows[(y + 1) % 3][..w];
                acc += info_row(r0, r1, r2, &self.info);
            }
            out[gi] = acc as f64 / INFO_ONE;
        }
        true
    }
}

/// Sum of the information table over one row's interior pixels (fixed point).
#[inline(always)]
fn info_row(r0: &[u8], r1: &[u8], r2: &[u8], info: &[u32]) -> u64 {
    let m = r0.len() - 2;
    let (a0, b0, c0) = (&r0[..m], &r0[1..m + 1], &r0[2..m + 2]);
    let (a1, c1) = (&r1[..m], &r1[2..m + 2]);
    let (a2, b2, c2) = (&r2[..m], &r2[1..m + 1], &r2[2..m + 2]);
    let mut acc = 0u64;
    for x in 0..m {
        let i = |v: u8| v as i16;
        let sx = (i(c0[x]) - i(a0[x])) + 2 * (i(c1[x]) - i(a1[x])) + (i(c2[x]) - i(a2[x]));
        let sy = (i(a2[x]) + 2 * i(b2[x]) + i(c2[x])) - (i(a0[x]) + 2 * i(b0[x]) + i(c0[x]));
        let (sx, sy) = (sx as f32, sy as f32);
        acc += info[info_key(sx * sx + sy * sy)] as u64;
    }
    acc
}

pub struct Gec {
    cfg: GecConfig,
    limits: ExposureLimits,
    scorer: GecScorer,
    down: Downsampler,
    commanded_us: f64,
}

impl Gec {
    pub fn new(
        cfg: GecConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            scorer: GecScorer::new(&cfg),
            down: Downsampler::new(),
            commanded_us: limits.clamp(initial_us),
            limits,
            cfg,
        })
    }
}

impl ExposureController for Gec {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::Gec
    }

    fn update(&mut self, frame: &Frame, _marker: Option<&Corners>) -> ExposureStep {
        let hold = ExposureStep::skipped(self.commanded_us);
        if !exposed_as_commanded(frame, self.commanded_us) || !frame.is_consistent() {
            return hold;
        }
        let small = self.down.run(frame.view(), self.cfg.downsample as usize);
        let Some(scores) = self.scorer.scores(small) else {
            return hold;
        };
        let ratio = if scores.iter().all(|&s| s == scores[0]) {
            // A featureless image scores the same for every gamma: no information.
            if self.cfg.no_information_fallback {
                let (mut sum, mut n) = (0u64, 0u64);
                for y in 0..small.height {
                    sum += small.row(y).iter().map(|&p| p as u64).sum::<u64>();
                    n += small.width as u64;
                }
                let mean = (sum as f64 / n.max(1) as f64).max(0.5);
                (127.0 / mean).clamp(0.5, 2.0)
            } else {
                1.0
            }
        } else {
            let gamma_hat = match fit_quintic(&GEC_GAMMAS, &scores) {
                Some(c) => best_gamma(&c),
                None => 1.0,
            };
            gec_ratio(gamma_hat, self.cfg.kp, self.cfg.d)
        };
        self.commanded_us = self.limits.clamp(self.commanded_us * ratio);
        ExposureStep::used(self.commanded_us, scores[3], None)
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.commanded_us = self.limits.clamp(exposure_us);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_computed_update() {
        // gamma_hat = 1: no change.
        assert!((gec_ratio(1.0, 0.2, 0.1) - 1.0).abs() < 1e-12);
        // gamma_hat = 0.5 (brighter wanted): R = 1 + 0.1 tan(0.5 atan 10)
        //   atan 10 = 1.4711277, half = 0.7355638, tan = 0.9049875, R = 1.0904988;
        //   alpha = 1: t *= 1 + 0.2 * 0.0904988 = 1.0180998.
        assert!((gec_ratio(0.5, 0.2, 0.1) - 1.018_099_8).abs() < 1e-6);
        // gamma_hat = 1.5 (darker wanted): tan(-0.5 atan 10) = -0.9049875,
        //   R = 0.9095012, alpha = 0.5: t *= 1 + 0.1 * (-0.0904988) = 0.9909501.
        assert!((gec_ratio(1.5, 0.2, 0.1) - 0.990_950_1).abs() < 1e-6);
    }

    #[test]
    fn quintic_fit_recovers_polynomial_and_argmax() {
        // y = -(g - 1.3)^2 + 5: the fit is exact and its argmax is 1.3.
        let y = GEC_GAMMAS.map(|g| -(g - 1.3f64).powi(2) + 5.0);
        let c = fit_quintic(&GEC_GAMMAS, &y).unwrap();
        for g in [0.6, 1.0, 1.7] {
            assert!((poly(&c, g) - (-(g - 1.3f64).powi(2) + 5.0)).abs() < 1e-8);
        }
        assert!((best_gamma(&c) - 1.3).abs() < 1e-3);
        // Monotone scores put the argmax at the end of the range.
        let y = GEC_GAMMAS.map(|g| g);
        let c = fit_quintic(&GEC_GAMMAS, &y).unwrap();
        assert!((best_gamma(&c) - 1.9).abs() < 1e-9);
    }

    #[test]
    fn information_of_a_step_edge() {
        // A vertical full-contrast edge: inner pixels next to it have m = 1 -> m_bar 1,
        // others 0. Columns 0..2 black, 3..5 white; interior x = 1..4.
        let cfg = GecConfig::default();
        let mut s = GecScorer::new(&cfg);
        let mut data = vec![0u8; 6 * 4];
        for y in 0..4 {
            for x in 3..6 {
                data[y * 6 + x] = 255;
            }
        }
        let v = ImageView::new(6, 4, &data).unwrap();
        let sc = s.scores(v).unwrap();
        // Interior rows 1..=2, columns 1..=4: x = 2 and x = 3 straddle the edge, each
        // with sx = 4 * 255 = 1020, m = 1, m_bar = 1: score = 2 rows * 2 = 4.
        assert!((sc[3] - 4.0).abs() < 1e-6, "{sc:?}");
    }
}
