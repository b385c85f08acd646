//! The soft-percentile gradient metric `M` and its derivative `dM/d(ln t)`.
//!
//! Per pixel: Sobel gradients `Ix, Iy` (normalized, grey levels per pixel),
//! `G = Ix^2 + Iy^2`; `D = dI/d(ln t) = 1/g'(I)` from the response table, `Dx, Dy` with the
//! same filter, `dG/d(ln t) = 2 (Ix Dx + Iy Dy)`. The same `G` is used for ranking,
//! scoring and the derivative. Pixels at or above the saturation level have `D = 0` (a
//! clipped pixel does not change) and their own `dG` replaced by
//! `-penalty * max(|dG|, floor)`, so that an over-exposed region pushes the exposure down.
//!
//! Ranks come from a histogram of `G` (O(S)), not a sort: pixels in one bin are tied and
//! share the mean weight of the ranks the bin covers; the sum of the weights over a range
//! of ranks has a closed form, so the per-bin work is O(1). Bins are exact for integer
//! `64 G < 256` and 1/128 wide (relative) above.

use crate::{ImageView, Response};

/// Parameters of the metric.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricParams {
    /// Percentile `p` where the weights peak, in (0, 1).
    pub percentile: f64,
    /// Exponent `k` of the sine weights: an odd integer (1..=9); published value 5.
    pub weight_power: u32,
    /// Grey level from which a pixel counts as saturated (official AEC: 250).
    pub saturation_grey: u8,
    /// `dG` of a saturated pixel becomes `-penalty * max(|dG|, floor)`.
    pub saturation_penalty: f64,
    /// Floor of that penalty, grey levels squared per unit of ln t.
    pub saturation_floor: f64,
}

impl Default for MetricParams {
    fn default() -> Self {
        Self {
            percentile: 0.7,
            weight_power: 5,
            saturation_grey: 250,
            saturation_penalty: 3.0,
            saturation_floor: 0.5,
        }
    }
}

/// The metric on one image or RoI.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MetricValue {
    /// `M`, grey levels squared.
    pub m: f64,
    /// `dM / d(ln t)`, grey levels squared. `dM/dt = dm_dlnt / t`.
    pub dm_dlnt: f64,
    /// Number of pixels `S` scored (the interior of the region).
    pub pixels: usize,
    /// Mean grey of the scored pixels.
    pub mean_grey: f64,
    /// Fraction of scored pixels at or above the saturation level.
    pub saturated_frac: f64,
    /// Grey level at the 99th percentile of the scored pixels (the bright end that a
    /// longer exposure would saturate first).
    pub bright_grey: u8,
}

/// Percentile of the grey histogram reported as [`MetricValue::bright_grey`].
pub const BRIGHT_PERCENTILE: f64 = 0.99;

/// Closed-form partial sums of the soft-percentile weights
/// `w_i = sin(pi/2 * i/n)^k` (i <= n), `sin(pi/2 - pi/2 (i-n)/(S-n))^k` (i > n), with
/// `n = floor(p S)` (and `w_0 = 1` when `n = 0`).
#[derive(Debug, Clone, Copy)]
pub struct RankWeights {
    s: usize,
    n: usize,
    /// Angle steps of the two branches.
    c1: f64,
    c2: f64,
    k: u32,
    /// Fourier coefficients of sin^k / cos^k: harmonic (k - 2j) has coefficient coef[j].
    coef: [f64; 5],
    /// Sum of the first branch, i = 0..=n.
    head: f64,
    total: f64,
}

fn binomial(n: u32, k: u32) -> f64 {
    let mut r = 1.0;
    for i in 0..k {
        r = r * (n - i) as f64 / (i + 1) as f64;
    }
    r
}

impl RankWeights {
    /// Weights over `s` ranks. `k` must be odd in 1..=9 and `p` in (0, 1); callers
    /// validate both (other values are clamped here so nothing panics).
    pub fn new(s: usize, p: f64, k: u32) -> Self {
        let k = if k.is_multiple_of(2) { k + 1 } else { k }.clamp(1, 9);
        let p = if p.is_finite() {
            p.clamp(1e-9, 1.0 - 1e-9)
        } else {
            0.7
        };
        let n = ((p * s as f64).floor() as usize).min(s.saturating_sub(1));
        let m = (k - 1) / 2;
        let mut coef = [0.0; 5];
        let scale = 1.0 / 4f64.powi(m as i32);
        for (j, c) in coef.iter_mut().enumerate().take(m as usize + 1) {
            *c = scale * binomial(k, j as u32);
        }
        let c1 = if n > 0 {
            std::f64::consts::FRAC_PI_2 / n as f64
        } else {
            0.0
        };
        let c2 = std::f64::consts::FRAC_PI_2 / (s - n).max(1) as f64;
        let mut w = Self {
            s,
            n,
            c1,
            c2,
            k,
            coef,
            head: 0.0,
            total: 0.0,
        };
        w.head = w.head_sum(n + 1);
        w.total = w.cumulative(s);
        w
    }

    pub fn ranks(&self) -> usize {
        self.s
    }

    /// Sum of all weights (the normalizer `N`).
    pub fn total(&self) -> f64 {
        self.total
    }

    /// Weight of rank `i`, unnormalized (direct formula).
    pub fn weight(&self, i: usize) -> f64 {
        if i <= self.n {
            if self.n == 0 {
                return 1.0;
            }
            (self.c1 * i as f64).sin().powi(self.k as i32)
        } else {
            (self.c2 * (i - self.n) as f64).cos().powi(self.k as i32)
        }
    }

    /// `sum_{i=0}^{r-1} sin(c1 i)^k`, for r <= n + 1.
    fn head_sum(&self, r: usize) -> f64 {
        if r == 0 {
            return 0.0;
        }
        if self.n == 0 {
            return 1.0;
        }
        let m = (self.k - 1) / 2;
        let mut acc = 0.0;
        for j in 0..=m {
            let h = (self.k - 2 * j) as f64;
            let a = h * self.c1;
            // sum_{i=0}^{r-1} sin(a i) = sin(a r/2) sin(a (r-1)/2) / sin(a/2)
            let r = r as f64;
            let s = (0.5 * a * r).sin() * (0.5 * a * (r - 1.0)).sin() / (0.5 * a).sin();
            let sign = if (m - j).is_multiple_of(2) { 1.0 } else { -1.0 };
            acc += sign * self.coef[j as usize] * s;
        }
        acc
    }

    /// `sum_{q=1}^{j} cos(c2 q)^k`.
    fn tail_sum(&self, j: usize) -> f64 {
        if j == 0 {
            return 0.0;
        }
        let m = (self.k - 1) / 2;
        let jf = j as f64;
        let mut acc = 0.0;
        for jj in 0..=m {
            let h = (self.k - 2 * jj) as f64;
            let a = h * self.c2;
            // sum_{q=1}^{j} cos(a q) = sin(a j/2) cos(a (j+1)/2) / sin(a/2)
            let s = (0.5 * a * jf).sin() * (0.5 * a * (jf + 1.0)).cos() / (0.5 * a).sin();
            acc += self.coef[jj as usize] * s;
        }
        acc
    }

    /// `W(r) = sum_{i=0}^{r-1} w_i`, unnormalized, for r in 0..=S.
    pub fn cumulative(&self, r: usize) -> f64 {
        let r = r.min(self.s);
        if r <= self.n + 1 {
            self.head_sum(r)
        } else {
            self.head + self.tail_sum(r - self.n - 1)
        }
    }
}

/// Normalized weights of ranks 0..S by the direct formula (for tests and references).
pub fn soft_percentile_weights(s: usize, p: f64, k: u32, out: &mut Vec<f64>) {
    let w = RankWeights::new(s, p, k);
    out.clear();
    out.extend((0..s).map(|i| w.weight(i)));
    let sum: f64 = out.iter().sum();
    if sum > 0.0 {
        out.iter_mut().for_each(|v| *v /= sum);
    }
}

/// Mantissa bits kept in a histogram key.
const KEY_MANTISSA_BITS: u32 = 7;
/// Largest `64 G` with integer Sobel on 8-bit images: 2 * 1020^2 < 2^21.
const KEY_EXPONENTS: usize = 21;
const N_BINS: usize = KEY_EXPONENTS * (1 << KEY_MANTISSA_BITS) + 1;

/// Histogram key of an integer `g64 = 64 G`: monotone in `g64`, 0 only for 0.
#[inline(always)]
fn key(g64: u32) -> usize {
    if g64 == 0 {
        return 0;
    }
    let bits = (g64 as f32).to_bits() >> (23 - KEY_MANTISSA_BITS);
    (bits - (127 << KEY_MANTISSA_BITS) + 1) as usize
}

/// Reusable evaluator of the metric: buffers are sized at the first use (or by
/// [`GradientMetric::reserve`]) and reused; evaluating allocates nothing after that
/// unless the image grows wider.
#[derive(Debug, Clone)]
pub struct GradientMetric {
    params: MetricParams,
    /// `D` per grey level (0 at saturation), f32 for speed.
    d_lut: [f32; 256],
    /// `D` for three consecutive rows.
    d_rows: [Vec<f32>; 3],
    gx: Vec<i32>,
    gy: Vec<i32>,
    g64: Vec<u32>,
    dg: Vec<f32>,
    cnt: Vec<u32>,
    sum_g64: Vec<u64>,
    sum_dg: Vec<f64>,
    grey_hist: [u32; 256],
}

impl GradientMetric {
    pub fn new(response: &Response, params: MetricParams) -> Self {
        let mut d_lut = [0f32; 256];
        for (i, d) in d_lut.iter_mut().enumerate() {
            if i < params.saturation_grey as usize {
                *d = response.di_dlnt(i as u8) as f32;
            }
        }
        Self {
            params,
            d_lut,
            d_rows: [Vec::new(), Vec::new(), Vec::new()],
            gx: Vec::new(),
            gy: Vec::new(),
            g64: Vec::new(),
            dg: Vec::new(),
            cnt: vec![0; N_BINS],
            sum_g64: vec![0; N_BINS],
            sum_dg: vec![0.0; N_BINS],
            grey_hist: [0; 256],
        }
    }

    pub fn params(&self) -> &MetricParams {
        &self.params
    }

    /// Size the row buffers for images up to `width` pixels wide.
    pub fn reserve(&mut self, width: usize) {
        if self.gx.len() < width {
            for r in &mut self.d_rows {
                r.resize(width, 0.0);
            }
            self.gx.resize(width, 0);
            self.gy.resize(width, 0);
            self.g64.resize(width, 0);
            self.dg.resize(width, 0.0);
        }
    }

    /// `M` and `dM/d(ln t)` on `view` (its interior: the filter needs a one-pixel
    /// border). `None` when the view has no interior pixel.
    pub fn evaluate(&mut self, view: ImageView<'_>) -> Option<MetricValue> {
        let (w, h) = (view.width, view.height);
        if w < 3 || h < 3 {
            return None;
        }
        self.reserve(w);
        let sat = self.params.saturation_grey;
        let pen = self.params.saturation_penalty as f32;
        let floor = self.params.saturation_floor as f32;
        let lut = &self.d_lut;
        for (r, y) in self.d_rows.iter_mut().zip(0..2) {
            for (d, &p) in r[..w].iter_mut().zip(view.row(y)) {
                *d = lut[p as usize];
            }
        }
        let (mut sum_grey, mut n_sat) = (0u64, 0u64);
        for y in 1..h - 1 {
            let (r0, r1, r2) = (view.row(y - 1), view.row(y), view.row(y + 1));
            // Ring of D rows: slot (y+1) % 3 receives row y+1.
            {
                let slot = &mut self.d_rows[(y + 1) % 3];
                for (d, &p) in slot[..w].iter_mut().zip(r2) {
                    *d = lut[p as usize];
                }
            }
            let d0 = &self.d_rows[(y - 1) % 3][..w];
            let d1 = &self.d_rows[y % 3][..w];
            let d2 = &self.d_rows[(y + 1) % 3][..w];
            let m = w - 2;
            let (gx, gy) = (&mut self.gx[..m], &mut self.gy[..m]);
            let (g64, dg) = (&mut self.g64[..m], &mut self.dg[..m]);
            for x in 0..m {
                let a = |r: &[u8], i: usize| r[i] as i32;
                let sx = (a(r0, x + 2) - a(r0, x))
                    + 2 * (a(r1, x + 2) - a(r1, x))
                    + (a(r2, x + 2) - a(r2, x));
                let sy = (a(r2, x) + 2 * a(r2, x + 1) + a(r2, x + 2))
                    - (a(r0, x) + 2 * a(r0, x + 1) + a(r0, x + 2));
                gx[x] = sx;
                gy[x] = sy;
                g64[x] = (sx * sx + sy * sy) as u32;
                let dx = (d0[x + 2] - d0[x]) + 2.0 * (d1[x + 2] - d1[x]) + (d2[x + 2] - d2[x]);
                let dy =
                    (d2[x] + 2.0 * d2[x + 1] + d2[x + 2]) - (d0[x] + 2.0 * d0[x + 1] + d0[x + 2]);
                // 2 (Ix Dx + Iy Dy) with Ix = sx/8, Dx = dx/8.
                dg[x] = (sx as f32 * dx + sy as f32 * dy) * (1.0 / 32.0);
            }
            for x in 0..m {
                let p = r1[x + 1];
                sum_grey += p as u64;
                self.grey_hist[p as usize] += 1;
                let mut d = dg[x];
                if p >= sat {
                    n_sat += 1;
                    d = -pen * d.abs().max(floor);
                }
                let k = key(g64[x]);
                self.cnt[k] += 1;
                self.sum_g64[k] += g64[x] as u64;
                self.sum_dg[k] += d as f64;
            }
        }
        let s = (w - 2) * (h - 2);
        let (m, dm) = self.collect(s);
        let bright_grey = self.bright_grey(s);
        Some(MetricValue {
            m,
            dm_dlnt: dm,
            pixels: s,
            mean_grey: sum_grey as f64 / s as f64,
            saturated_frac: n_sat as f64 / s as f64,
            bright_grey,
        })
    }

    /// The grey at [`BRIGHT_PERCENTILE`] of the histogram, which it clears.
    fn bright_grey(&mut self, s: usize) -> u8 {
        let target = (BRIGHT_PERCENTILE * s as f64).ceil() as u64;
        let (mut acc, mut found) = (0u64, None);
        for (g, c) in self.grey_hist.iter_mut().enumerate() {
            acc += *c as u64;
            if found.is_none() && acc >= target {
                found = Some(g as u8);
            }
            *c = 0;
        }
        found.unwrap_or(255)
    }

    /// Walk the bins in ascending `G`, weight each by the mean weight of its ranks, and
    /// clear them for the next frame.
    fn collect(&mut self, s: usize) -> (f64, f64) {
        let rw = RankWeights::new(s, self.params.percentile, self.params.weight_power);
        let (mut rank, mut w_prev) = (0usize, 0.0f64);
        let (mut m, mut dm) = (0.0f64, 0.0f64);
        for b in 0..N_BINS {
            let c = self.cnt[b];
            if c == 0 {
                continue;
            }
            rank += c as usize;
            let w_now = rw.cumulative(rank);
            let wbar = (w_now - w_prev) / c as f64;
            w_prev = w_now;
            m += wbar * self.sum_g64[b] as f64;
            dm += wbar * self.sum_dg[b];
            self.cnt[b] = 0;
            self.sum_g64[b] = 0;
            self.sum_dg[b] = 0.0;
        }
        let n = rw.total();
        (m / (64.0 * n), dm / n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_computed_weights() {
        // S = 4, p = 0.5: n = 2; raw weights 0, sin(pi/4)^5, 1, sin(pi/4)^5.
        let mut w = Vec::new();
        soft_percentile_weights(4, 0.5, 5, &mut w);
        let a = (0.5f64).sqrt().powi(5); // 0.1767767
        let sum = 1.0 + 2.0 * a;
        let expect = [0.0, a / sum, 1.0 / sum, a / sum];
        for (g, e) in w.iter().zip(expect) {
            assert!((g - e).abs() < 1e-12, "{w:?}");
        }
        assert!((w[2] - 0.738796).abs() < 1e-6, "{w:?}");
        // S = 1: the only rank is the peak.
        soft_percentile_weights(1, 0.7, 5, &mut w);
        assert_eq!(w, vec![1.0]);
    }

    #[test]
    fn closed_form_cumulative_matches_direct_sum() {
        for &(s, p, k) in &[
            (1usize, 0.7, 5u32),
            (2, 0.7, 5),
            (7, 0.5, 3),
            (100, 0.7, 5),
            (1000, 0.9, 5),
            (12345, 0.6, 7),
            (90000, 0.7, 5),
        ] {
            let rw = RankWeights::new(s, p, k);
            let mut acc = 0.0;
            for r in 0..=s {
                let c = rw.cumulative(r);
                assert!(
                    (c - acc).abs() <= 1e-9 * (1.0 + acc),
                    "s {s} p {p} k {k} r {r}: {c} vs {acc}"
                );
                if r < s {
                    acc += rw.weight(r);
                }
            }
        }
    }

    #[test]
    fn keys_are_monotone_and_exact_below_256() {
        let mut prev = 0;
        for g in 1..(1u32 << 21) {
            let k = key(g);
            assert!(k >= prev && k < N_BINS);
            if g < 256 {
                assert!(k > prev, "{g}");
            }
            prev = k;
        }
    }
}
