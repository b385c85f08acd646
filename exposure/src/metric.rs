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
    /// Grey level from which a pixel counts as saturated (official AEC: 252).
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
            saturation_grey: 252,
            saturation_penalty: 3.0,
            saturation_floor: 0.5,
        }
    }
}

impl MetricParams {
    /// The configured weights and saturation penalty, the default penalty floor.
    pub fn configured(
        percentile: f64,
        weight_power: u32,
        saturation_grey: u8,
        saturation_penalty: f64,
    ) -> Self {
        Self {
            percentile,
            weight_power,
            saturation_grey,
            saturation_penalty,
            ..Self::default()
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
}

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
    /// Per odd harmonic h = 1, 3, 5, 7, 9: Fourier coefficient of sin^k (signed) over
    /// sin(h c1 / 2), and of cos^k over sin(h c2 / 2); 0 for harmonics above k.
    head_coef: [f64; 5],
    tail_coef: [f64; 5],
    /// e^{-i c1/2} and e^{+i c2/2}: shift the base angle by half a step.
    head_shift: (f64, f64),
    tail_shift: (f64, f64),
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

#[inline(always)]
fn cmul(a: (f64, f64), b: (f64, f64)) -> (f64, f64) {
    (a.0 * b.0 - a.1 * b.1, a.0 * b.1 + a.1 * b.0)
}

/// `sum_i coef[i] im(z^(2i+1)) part(zp^(2i+1))` with `z = e^{i angle}`, `zp = z shift` and
/// `part` the imaginary part (`IM`, the head's sines) or the real part (the tail's
/// cosines): the closed form of both branches' partial sums.
#[inline(always)]
fn harmonic_sum<const IM: bool>(coef: &[f64; 5], angle: f64, shift: (f64, f64)) -> f64 {
    let z = unit(angle);
    let (a, b) = (odd_powers(z), odd_powers(cmul(z, shift)));
    let mut acc = 0.0;
    for i in 0..5 {
        acc += coef[i] * a[i].1 * if IM { b[i].1 } else { b[i].0 };
    }
    acc
}

/// z, z^3, z^5, z^7, z^9 as (re, im).
#[inline(always)]
fn odd_powers(z: (f64, f64)) -> [(f64, f64); 5] {
    let z2 = cmul(z, z);
    let z3 = cmul(z2, z);
    let z5 = cmul(z3, z2);
    let z7 = cmul(z5, z2);
    let z9 = cmul(z7, z2);
    [z, z3, z5, z7, z9]
}

fn unit(angle: f64) -> (f64, f64) {
    let (s, c) = angle.sin_cos();
    (c, s)
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
        let c1 = if n > 0 {
            std::f64::consts::FRAC_PI_2 / n as f64
        } else {
            0.0
        };
        let c2 = std::f64::consts::FRAC_PI_2 / (s - n).max(1) as f64;
        // sin^k x = 4^-m sum_j (-1)^(m-j) C(k, j) sin((k-2j) x),
        // cos^k x = 4^-m sum_j C(k, j) cos((k-2j) x), k = 2m + 1.
        let m = (k - 1) / 2;
        let scale = 1.0 / 4f64.powi(m as i32);
        let (mut head_coef, mut tail_coef) = ([0.0; 5], [0.0; 5]);
        for j in 0..=m {
            let h = k - 2 * j;
            let idx = ((h - 1) / 2) as usize;
            let c = scale * binomial(k, j);
            let sign = if (m - j).is_multiple_of(2) { 1.0 } else { -1.0 };
            if n > 0 {
                head_coef[idx] = sign * c / (0.5 * h as f64 * c1).sin();
            }
            tail_coef[idx] = c / (0.5 * h as f64 * c2).sin();
        }
        let mut w = Self {
            s,
            n,
            c1,
            c2,
            k,
            head_coef,
            tail_coef,
            head_shift: unit(-0.5 * c1),
            tail_shift: unit(0.5 * c2),
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

    /// `sum_{i=0}^{r-1} sin(c1 i)^k`, for r <= n + 1, with
    /// `sum_{i=0}^{r-1} sin(a i) = sin(a r/2) sin(a (r-1)/2) / sin(a/2)` per harmonic;
    /// one sin_cos, the harmonics by complex powers.
    fn head_sum(&self, r: usize) -> f64 {
        if r == 0 {
            return 0.0;
        }
        if self.n == 0 {
            return 1.0;
        }
        harmonic_sum::<true>(&self.head_coef, 0.5 * self.c1 * r as f64, self.head_shift)
    }

    /// `sum_{q=1}^{j} cos(c2 q)^k`, with
    /// `sum_{q=1}^{j} cos(a q) = sin(a j/2) cos(a (j+1)/2) / sin(a/2)` per harmonic.
    fn tail_sum(&self, j: usize) -> f64 {
        if j == 0 {
            return 0.0;
        }
        harmonic_sum::<false>(&self.tail_coef, 0.5 * self.c2 * j as f64, self.tail_shift)
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

/// Bins allocated: a power of two above `N_BINS`, so that a masked key needs no
/// bounds check.
const BIN_SLOTS: usize = 4096;
const _: () = assert!(N_BINS <= BIN_SLOTS);

/// Histogram key of an integer `g64 = 64 G` (given as an exact f32): monotone in
/// `g64`, 0 only for 0.
#[inline(always)]
fn key_f32(g64: f32) -> u32 {
    let bits = g64.to_bits() >> (23 - KEY_MANTISSA_BITS);
    // For g64 = 0 the bits are 0 and the subtraction wraps: select 0 instead.
    if g64 == 0.0 {
        0
    } else {
        bits.wrapping_sub((127 << KEY_MANTISSA_BITS) - 1)
    }
}

#[cfg(test)]
fn key(g64: u32) -> u32 {
    key_f32(g64 as f32)
}

/// One histogram bin: pixel count, sum of `64 G`, sum of fixed-point `dG/d(ln t)`.
#[derive(Debug, Clone, Copy, Default)]
struct Bin {
    cnt: u32,
    sum_g64: f64,
    sum_dg: f64,
}

/// Reusable evaluator of the metric: buffers are sized at the first use (or by
/// [`GradientMetric::reserve`]) and reused; evaluating allocates nothing after that
/// unless the image grows wider.
#[derive(Debug, Clone)]
pub struct GradientMetric {
    params: MetricParams,
    /// `D` per grey level (0 at saturation) in fixed point: `D * d_scale`, at most
    /// `D_Q_MAX`, so that a Sobel sum of `D` fits an i16.
    d_lut: [i16; 256],
    d_scale: f64,
    /// `Some(k)` when the table is `k * I` for 0 < I < saturation (a linear camera):
    /// rows are then filled by arithmetic, which vectorizes, instead of a lookup.
    linear_step: Option<i16>,
    /// `D` for three consecutive rows.
    d_rows: [Vec<i16>; 3],
    /// `64 G` per pixel of a row (an exact integer held in an f32).
    g64: Vec<f32>,
    /// `dG/d(ln t)` in units of `1 / (32 d_scale)`.
    dg: Vec<f32>,
    keys: Vec<u32>,
    bins: Box<[Bin; BIN_SLOTS]>,
}

/// Largest fixed-point `D`: 4 * 8160 = 32640 fits an i16.
const D_Q_MAX: f64 = 8160.0;

impl GradientMetric {
    pub fn new(response: &Response, params: MetricParams) -> Self {
        let d_of = |i: usize| {
            if i < params.saturation_grey as usize {
                response.di_dlnt(i as u8)
            } else {
                0.0
            }
        };
        let d_max = (0..256).map(d_of).fold(0.0, f64::max);
        // Finest power-of-two fixed point that keeps every Sobel sum of D inside an
        // i16 (a power of two keeps a linear camera's D = I exact).
        let d_scale = if d_max > 0.0 {
            2f64.powi((D_Q_MAX / d_max).log2().floor() as i32)
        } else {
            1.0
        };
        let mut d_lut = [0i16; 256];
        for (i, d) in d_lut.iter_mut().enumerate() {
            *d = (d_of(i) * d_scale).round().min(D_Q_MAX) as i16;
        }
        let k = d_lut[1];
        let linear_step = (1..256)
            .all(|i| {
                let want = if i < params.saturation_grey as usize {
                    i as i32 * k as i32
                } else {
                    0
                };
                d_lut[i] as i32 == want
            })
            .then_some(k);
        Self {
            params,
            d_lut,
            d_scale,
            linear_step,
            d_rows: [Vec::new(), Vec::new(), Vec::new()],
            g64: Vec::new(),
            dg: Vec::new(),
            keys: Vec::new(),
            bins: Box::new([Bin::default(); BIN_SLOTS]),
        }
    }

    pub fn params(&self) -> &MetricParams {
        &self.params
    }

    /// Size the row buffers for images up to `width` pixels wide.
    pub fn reserve(&mut self, width: usize) {
        if self.g64.len() < width {
            for r in &mut self.d_rows {
                r.resize(width, 0);
            }
            self.g64.resize(width, 0.0);
            self.dg.resize(width, 0.0);
            self.keys.resize(width, 0);
        }
    }

    /// `M` and `dM/d(ln t)` on `view` (its interior: the filter needs a one-pixel
    /// border). `None` when the view has no interior pixel.
    pub fn evaluate(&mut self, view: ImageView<'_>) -> Option<MetricValue> {
        // The same code compiled twice: with AVX2 the i16 Sobel lanes double (0.64-0.71x
        // the time, docs/design/exposure.md). No FMA: Rust never fuses on its own, so both builds give
        // bit-identical results and a HIL run does not depend on the CPU.
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { self.evaluate_avx2(view) };
        }
        self.evaluate_portable(view)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn evaluate_avx2(&mut self, view: ImageView<'_>) -> Option<MetricValue> {
        self.evaluate_portable(view)
    }

    /// [`Self::evaluate`] without CPU dispatch (public for the benchmark's baseline).
    #[inline(always)]
    pub fn evaluate_portable(&mut self, view: ImageView<'_>) -> Option<MetricValue> {
        let (w, h) = (view.width, view.height);
        if w < 3 || h < 3 {
            return None;
        }
        self.reserve(w);
        let sat = self.params.saturation_grey;
        // The clipped-pixel rule in the fixed point of dG: penalty in 1/256.
        let unit = 32.0 * self.d_scale;
        let pen = self.params.saturation_penalty as f32;
        let floor = (self.params.saturation_floor * unit) as f32;
        let (lut, linear) = (&self.d_lut, self.linear_step);
        // Per row of the ring: holds a pixel where D is not k * I (black or clipped).
        let mut special = [true; 3];
        for ((r, y), sp) in self.d_rows.iter_mut().zip(0..2).zip(special.iter_mut()) {
            *sp = fill_d_row(&mut r[..w], view.row(y), lut, linear, sat);
        }
        let m = w - 2;
        let (mut sum_grey, mut n_sat) = (0u64, 0u64);
        // Pixels with G = 0 (flat areas) all land in bin 0: count them in registers.
        let (mut zero_cnt, mut zero_dg) = (0u32, 0f64);
        for y in 1..h - 1 {
            let (r0, r1, r2) = (view.row(y - 1), view.row(y), view.row(y + 1));
            {
                let slot = &mut self.d_rows[(y + 1) % 3];
                special[(y + 1) % 3] = fill_d_row(&mut slot[..w], r2, lut, linear, sat);
            }
            match linear {
                // Linear table and no black or clipped pixel in the window: D = k I, so
                // the Sobel of D is k times the Sobel of I and dG = k * 64 G exactly.
                Some(k) if !special.iter().any(|&s| s) => sobel_row_linear(
                    [r0, r1, r2],
                    k as f32,
                    &mut self.g64[..m],
                    &mut self.dg[..m],
                    &mut self.keys[..m],
                ),
                _ => {
                    let d0 = &self.d_rows[(y - 1) % 3][..w];
                    let d1 = &self.d_rows[y % 3][..w];
                    let d2 = &self.d_rows[(y + 1) % 3][..w];
                    sobel_row(
                        [r0, r1, r2],
                        [d0, d1, d2],
                        &mut self.g64[..m],
                        &mut self.dg[..m],
                        &mut self.keys[..m],
                    );
                }
            }
            // Grey statistics: branch-free, vectorizes.
            let (g64, dg, keys) = (&self.g64[..m], &mut self.dg[..m], &self.keys[..m]);
            let centre = &r1[1..m + 1];
            // Sums in u16 lanes over chunks of 128 (128 * 255 < 2^16), so they vectorize.
            let (mut row_grey, mut row_sat) = (0u32, 0u32);
            for chunk in centre.chunks(128) {
                let (mut g, mut n) = (0u16, 0u16);
                for &p in chunk {
                    g += p as u16;
                    n += (p >= sat) as u16;
                }
                row_grey += g as u32;
                row_sat += n as u32;
            }
            if row_sat > 0 {
                // The clipped-pixel rule, only on rows that have clipped pixels.
                for x in 0..m {
                    if centre[x] >= sat {
                        dg[x] = -pen * dg[x].abs().max(floor);
                    }
                }
            }
            sum_grey += row_grey as u64;
            n_sat += row_sat as u64;
            let (zc, zd) = scatter(&mut self.bins, keys, g64, dg);
            zero_cnt += zc;
            zero_dg += zd;
        }
        self.bins[0].cnt += zero_cnt;
        self.bins[0].sum_dg += zero_dg;
        let s = m * (h - 2);
        let (mm, dm) = self.collect(s);
        Some(MetricValue {
            m: mm,
            dm_dlnt: dm,
            pixels: s,
            mean_grey: sum_grey as f64 / s as f64,
            saturated_frac: n_sat as f64 / s as f64,
        })
    }

    /// Walk the bins in ascending `G`, weight each by the mean weight of its ranks, and
    /// clear them for the next frame.
    fn collect(&mut self, s: usize) -> (f64, f64) {
        let rw = RankWeights::new(s, self.params.percentile, self.params.weight_power);
        let (mut rank, mut w_prev) = (0usize, 0.0f64);
        let (mut m, mut dm) = (0.0f64, 0.0f64);
        for b in self.bins.iter_mut() {
            if b.cnt == 0 {
                continue;
            }
            rank += b.cnt as usize;
            let w_now = rw.cumulative(rank);
            let wbar = (w_now - w_prev) / b.cnt as f64;
            w_prev = w_now;
            m += wbar * b.sum_g64;
            dm += wbar * b.sum_dg;
            *b = Bin::default();
        }
        let n = rw.total();
        (m / (64.0 * n), dm / (n * 32.0 * self.d_scale))
    }
}

/// `D` of one row in fixed point: by arithmetic for a linear table, else by lookup.
/// Returns whether the row holds a pixel where `D` is not `k * I` (always true for a
/// non-linear table).
#[inline(always)]
fn fill_d_row(out: &mut [i16], row: &[u8], lut: &[i16; 256], linear: Option<i16>, sat: u8) -> bool {
    match linear {
        Some(k) => {
            let d0 = lut[0];
            let mut special = 0u32;
            for chunk in row.chunks(128) {
                let mut n = 0u16;
                for &p in chunk {
                    n += (p == 0 || p >= sat) as u16;
                }
                special += n as u32;
            }
            for (d, &p) in out.iter_mut().zip(row) {
                // Used only below saturation, where it cannot overflow.
                let v = (p as i16).wrapping_mul(k);
                *d = if p == 0 {
                    d0
                } else if p >= sat {
                    0
                } else {
                    v
                };
            }
            special > 0
        }
        None => {
            for (d, &p) in out.iter_mut().zip(row) {
                *d = lut[p as usize];
            }
            true
        }
    }
}

/// [`sobel_row`] for a linear table away from black and clipped pixels: the Sobel of
/// `D = k I` is `k` times that of `I`, so `sx Dx + sy Dy = k g64`.
#[inline(always)]
fn sobel_row_linear(r: [&[u8]; 3], k: f32, g64: &mut [f32], dg: &mut [f32], keys: &mut [u32]) {
    let m = g64.len();
    let (keys, dg) = (&mut keys[..m], &mut dg[..m]);
    let (a0, b0, c0) = (&r[0][..m], &r[0][1..m + 1], &r[0][2..m + 2]);
    let (a1, c1) = (&r[1][..m], &r[1][2..m + 2]);
    let (a2, b2, c2) = (&r[2][..m], &r[2][1..m + 1], &r[2][2..m + 2]);
    for x in 0..m {
        let i = |v: u8| v as i16;
        let sx = (i(c0[x]) - i(a0[x])) + 2 * (i(c1[x]) - i(a1[x])) + (i(c2[x]) - i(a2[x]));
        let sy = (i(a2[x]) + 2 * i(b2[x]) + i(c2[x])) - (i(a0[x]) + 2 * i(b0[x]) + i(c0[x]));
        let (sx, sy) = (sx as f32, sy as f32);
        let g = sx * sx + sy * sy;
        g64[x] = g;
        keys[x] = key_f32(g);
        dg[x] = k * g;
    }
}

/// Add one row's pixels to the histogram; pixels with `G = 0` (flat areas, which
/// would all hit bin 0 one after the other) are summed in registers and returned.
#[inline(never)]
fn scatter(bins: &mut [Bin; BIN_SLOTS], keys: &[u32], g64: &[f32], dg: &[f32]) -> (u32, f64) {
    let m = keys.len();
    let (g64, dg) = (&g64[..m], &dg[..m]);
    let (mut zc, mut zd) = (0u32, 0f64);
    for x in 0..m {
        let k = keys[x] as usize;
        if k == 0 {
            zc += 1;
            zd += dg[x] as f64;
        } else {
            let b = &mut bins[k & (BIN_SLOTS - 1)];
            b.cnt += 1;
            b.sum_g64 += g64[x] as f64;
            b.sum_dg += dg[x] as f64;
        }
    }
    (zc, zd)
}

/// Sobel of one row: `g64 = sx^2 + sy^2` (integer Sobel on the grey rows) and
/// `sx Dx + sy Dy` on the fixed-point `D` rows (= `dG/d(ln t)` times `32 d_scale`).
/// i16 lanes throughout (|sx| <= 1020, |Dx| <= 32640); all slices are cut to the output
/// length so the loop runs without bounds checks and vectorizes.
#[inline(always)]
fn sobel_row(r: [&[u8]; 3], d: [&[i16]; 3], g64: &mut [f32], dg: &mut [f32], keys: &mut [u32]) {
    let m = g64.len();
    let keys = &mut keys[..m];
    let (a0, b0, c0) = (&r[0][..m], &r[0][1..m + 1], &r[0][2..m + 2]);
    let (a1, c1) = (&r[1][..m], &r[1][2..m + 2]);
    let (a2, b2, c2) = (&r[2][..m], &r[2][1..m + 1], &r[2][2..m + 2]);
    let (e0, f0, h0) = (&d[0][..m], &d[0][1..m + 1], &d[0][2..m + 2]);
    let (e1, h1) = (&d[1][..m], &d[1][2..m + 2]);
    let (e2, f2, h2) = (&d[2][..m], &d[2][1..m + 1], &d[2][2..m + 2]);
    let dg = &mut dg[..m];
    for x in 0..m {
        let i = |v: u8| v as i16;
        let sx = (i(c0[x]) - i(a0[x])) + 2 * (i(c1[x]) - i(a1[x])) + (i(c2[x]) - i(a2[x]));
        let sy = (i(a2[x]) + 2 * i(b2[x]) + i(c2[x])) - (i(a0[x]) + 2 * i(b0[x]) + i(c0[x]));
        // f32 products: exact for g64 (< 2^22), within 2^-24 for dG; SSE2 has no
        // 32-bit integer multiply, so this is the fast path on baseline x86-64.
        let (sx, sy) = (sx as f32, sy as f32);
        let g = sx * sx + sy * sy;
        g64[x] = g;
        keys[x] = key_f32(g);
        let dx = (h0[x] - e0[x]) + 2 * (h1[x] - e1[x]) + (h2[x] - e2[x]);
        let dy = (e2[x] + 2 * f2[x] + h2[x]) - (e0[x] + 2 * f0[x] + h0[x]);
        dg[x] = sx * dx as f32 + sy * dy as f32;
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
            let k = key(g) as usize;
            assert!(k >= prev && k < N_BINS);
            if g < 256 {
                assert!(k > prev, "{g}");
            }
            prev = k;
        }
    }
}
