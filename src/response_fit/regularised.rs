//! The regularised response fit: a discrete `g = ln f^-1` over the grey levels (Debevec and
//! Malik 1997), monotone by construction and smooth by a penalty whose weight is chosen by
//! k-fold cross-validation over the exposures.
//!
//! Unknowns are the steps `h_k = g(k+1) - g(k) = exp(u_k)` between adjacent levels of the
//! fitted range, so `g` increases (`g' > 0`) whatever the data. A pixel seen unclipped at
//! exposures `t_a < t_b` gives `g(I_b) - g(I_a) = ln(t_b / t_a)`: over all pairs of
//! exposures this is Debevec-Malik's objective with each pixel's `ln E` eliminated. The
//! frames of each exposure are averaged in two independent halves; pixels are grouped by
//! the second half's levels (an instrument) and each group's mean first-half greys give one
//! equation, so the noise of the grey a pixel is binned by does not bias `g` where the
//! scene's histogram bends. `g` between levels is interpolated linearly. Each fold's data
//! are a quadratic form in `h`; the penalty is `lambda * sum (second difference of u)^2`,
//! the smoothness of `ln g'`, which does not depend on the scale of `g'`. Each `lambda` of
//! a grid is solved by Levenberg-Marquardt on `u`, warm-started from the previous one.

use nalgebra::{DMatrix, DVector};

/// Grey levels a pixel may have to enter an equation: not black, not clipped.
pub const USABLE: std::ops::RangeInclusive<u8> = 1..=254;
/// Pairs of frames whose exposures differ by at least this ratio...
pub const MIN_RATIO: f64 = 1.05;
/// ... and at most this one (further apart, few pixels are unclipped in both).
pub const MAX_RATIO: f64 = 4.0;
/// A level belongs to the fitted range when this many equations have an end on it.
pub const MIN_LEVEL_SAMPLES: f64 = 200.0;
/// A level is fitted only while fewer than this share of its pixels were black or
/// clipped in one of their frames.
pub const MAX_CENSORED: f64 = 0.01;
/// Fewest levels a fit may span.
pub const MIN_LEVELS: usize = 16;
/// The valid range ends where one grey level spans more than this in ln exposure
/// (ln 1.28: a linear camera's levels below 4).
pub const MAX_STEP_LN: f64 = 0.25;
/// The regulariser's grid: `lambda = 10^(k / 2)` for k in this range.
const LAMBDA_EXP_HALF: std::ops::RangeInclusive<i32> = -14..=2;

/// The normal equations of one fold in `g` over all 256 levels:
/// `sum (g(I_b) - g(I_a) - ln r)^2 = g^T Q g - 2 c^T g + s` over `n` equations.
#[derive(Clone)]
struct FoldSums {
    q: Vec<f64>,
    c: Vec<f64>,
    s: f64,
    n: f64,
}

impl FoldSums {
    fn new() -> Self {
        Self {
            q: vec![0.0; 256 * 256],
            c: vec![0.0; 256],
            s: 0.0,
            n: 0.0,
        }
    }
}

/// The frames of one exposure averaged, in two independent halves: each sampled pixel's
/// mean grey over the odd frames (`grey`) and over the even frames (`instrument`), NaN
/// where any frame was black or clipped there. With one frame only, both are that frame.
pub struct MeanImage {
    pub exposure_us: f64,
    pub grey: Vec<f32>,
    pub instrument: Vec<f32>,
    /// The mean over every frame, black and clipped ones included.
    pub all: Vec<f32>,
}

/// Averages consecutive frames of one exposure, on every `stride`-th pixel of every
/// `stride`-th row (at most [`MAX_PIXELS`] pixels).
pub struct Averager {
    width: usize,
    height: usize,
    stride: usize,
    exposure_us: f64,
    count: u32,
    sum: [Vec<u32>; 2],
    bad: Vec<bool>,
    out: Vec<MeanImage>,
}

/// Most pixels sampled from each frame.
pub const MAX_PIXELS: usize = 400_000;

impl Averager {
    pub fn new() -> Self {
        Self {
            width: 0,
            height: 0,
            stride: 1,
            exposure_us: f64::NAN,
            count: 0,
            sum: [Vec::new(), Vec::new()],
            bad: Vec::new(),
            out: Vec::new(),
        }
    }

    /// Add a frame; a frame at a new exposure closes the previous exposure's mean.
    pub fn push(&mut self, f: &markhold_exposure::Frame) -> Result<(), FitRefusal> {
        let (w, h) = (f.width as usize, f.height as usize);
        if !f.is_consistent() || f.data.len() != w * h || w == 0 || h == 0 {
            return Err(FitRefusal::SizeMismatch);
        }
        if self.width == 0 {
            self.width = w;
            self.height = h;
            while (w / self.stride) * (h / self.stride) > MAX_PIXELS {
                self.stride += 1;
            }
        } else if (w, h) != (self.width, self.height) {
            return Err(FitRefusal::SizeMismatch);
        }
        let t = f.meta.exposure_us;
        if self.count == 0 || (t / self.exposure_us - 1.0).abs() > 1e-3 {
            self.close();
            self.exposure_us = t;
            let n = self.height.div_ceil(self.stride) * self.width.div_ceil(self.stride);
            self.sum = [vec![0; n], vec![0; n]];
            self.bad = vec![false; n];
        }
        let half = (self.count % 2) as usize;
        self.count += 1;
        let mut k = 0;
        for row in f.data.chunks_exact(w).step_by(self.stride) {
            for &v in row.iter().step_by(self.stride) {
                self.sum[half][k] += v as u32;
                self.bad[k] |= !USABLE.contains(&v);
                k += 1;
            }
        }
        Ok(())
    }

    fn close(&mut self) {
        if self.count == 0 {
            return;
        }
        // Frames 1, 3, ... in the first sum, 2, 4, ... in the second.
        let n = [self.count.div_ceil(2), self.count / 2];
        let mean = |h: usize| -> Vec<f32> {
            let (sum, n) = if n[h] == 0 {
                (&self.sum[0], n[0])
            } else {
                (&self.sum[h], n[h])
            };
            sum.iter()
                .zip(&self.bad)
                .map(|(&s, &b)| if b { f32::NAN } else { s as f32 / n as f32 })
                .collect()
        };
        let all = self.sum[0]
            .iter()
            .zip(&self.sum[1])
            .map(|(&a, &b)| (a + b) as f32 / self.count as f32)
            .collect();
        self.out.push(MeanImage {
            exposure_us: self.exposure_us,
            grey: mean(0),
            instrument: mean(1),
            all,
        });
        self.count = 0;
    }

    /// The means, one per exposure.
    pub fn finish(mut self) -> Vec<MeanImage> {
        self.close();
        self.out
    }
}

impl Default for Averager {
    fn default() -> Self {
        Self::new()
    }
}

/// The equations of a sweep, dealt into folds.
pub struct SweepEquations {
    folds: Vec<FoldSums>,
    /// The levels with enough samples to be fitted (both ends included).
    range: (usize, usize),
    /// Pairs of exposures that gave equations.
    pub pairs: usize,
    /// Exposures (means of frames) in the sweep.
    pub exposures: usize,
}

/// Why a sweep cannot support a fit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitRefusal {
    #[error("no frames to fit")]
    NoFrames,
    #[error("the frames differ in size: a sweep must show one scene from one camera")]
    SizeMismatch,
    #[error(
        "need frames at two or more exposures at least 5 % apart (found {distinct} distinct \
         exposure value(s))"
    )]
    TooFewExposures { distinct: usize },
    #[error(
        "no two frames are between {min}x and {max}x apart in exposure: pixels are compared \
         only between such frames; take exposures at most {max}x apart",
        min = MIN_RATIO,
        max = MAX_RATIO
    )]
    NoOverlappingPair,
    #[error(
        "the frames support a fit over {levels} grey level(s) only (levels {lo}..={hi}, each \
         with {samples} or more pixel comparisons, {need} levels needed): the exposures do \
         not overlap enough or the scene lacks varied brightness; take a denser sweep of a \
         scene with dark, mid and bright parts",
        samples = MIN_LEVEL_SAMPLES,
        need = MIN_LEVELS
    )]
    NarrowRange { levels: usize, lo: u8, hi: u8 },
}

/// The folds' equations of a sweep's means (any order).
pub fn equations(means: &[MeanImage], folds: usize) -> Result<SweepEquations, FitRefusal> {
    let mut order: Vec<&MeanImage> = means.iter().collect();
    order.sort_by(|a, b| a.exposure_us.total_cmp(&b.exposure_us));
    if order.is_empty() {
        return Err(FitRefusal::NoFrames);
    }
    let mut distinct = 1usize;
    for p in order.windows(2) {
        if p[1].exposure_us >= p[0].exposure_us * MIN_RATIO {
            distinct += 1;
        }
    }
    if distinct < 2 {
        return Err(FitRefusal::TooFewExposures { distinct });
    }
    // Each pair with its fold: the lower exposure's index, so a fold holds out whole
    // exposures' comparisons (the scene's histogram at an exposure biases them alike).
    let pairs: Vec<(&MeanImage, &MeanImage, usize)> = (0..order.len())
        .flat_map(|i| (i + 1..order.len()).map(move |j| (i, j)))
        .map(|(i, j)| (order[i], order[j], i % folds))
        .filter(|(a, b, _)| (MIN_RATIO..=MAX_RATIO).contains(&(b.exposure_us / a.exposure_us)))
        .collect();
    if pairs.is_empty() {
        return Err(FitRefusal::NoOverlappingPair);
    }
    // Pass 1: samples per level (each end of each comparison), for the range.
    let mut samples = [0.0f64; 256];
    for (a, b, _) in &pairs {
        for (&va, &vb) in a.grey.iter().zip(&b.grey) {
            if va.is_finite() && vb.is_finite() {
                samples[va.round() as usize] += 1.0;
                samples[vb.round() as usize] += 1.0;
            }
        }
    }
    let censored = censored_ends(&order);
    let ok: Vec<bool> = samples
        .iter()
        .enumerate()
        .map(|(l, &c)| c >= MIN_LEVEL_SAMPLES && censored.contains(&l))
        .collect();
    let (lo, hi) = longest_run(&ok);
    if hi < lo + MIN_LEVELS - 1 || hi < lo {
        let levels = if hi < lo { 0 } else { hi + 1 - lo };
        return Err(FitRefusal::NarrowRange {
            levels,
            lo: lo.min(255) as u8,
            hi: hi as u8,
        });
    }
    let mut sums = vec![FoldSums::new(); folds];
    let mut cover = [0.0f64; 257];
    let inside = |v: f32| v.is_finite() && (lo as f32..=hi as f32).contains(&v);
    // A grey between levels: g there is interpolated linearly between the two.
    let ends = |v: f64| -> (usize, f64) {
        let i = (v.floor().max(0.0) as usize).clamp(lo, hi - 1);
        (i, (v - i as f64).clamp(0.0, 1.0))
    };
    // Per cell of the instruments' levels: count, sum of grey a, sum of grey b.
    let mut cells = vec![(0u32, 0.0f64, 0.0f64); 65_536];
    for &(a, b, fold) in &pairs {
        let lr = (b.exposure_us / a.exposure_us).ln();
        cells.fill((0, 0.0, 0.0));
        let pixels = a
            .grey
            .iter()
            .zip(&b.grey)
            .zip(a.instrument.iter().zip(&b.instrument));
        for ((&va, &vb), (&za, &zb)) in pixels {
            if !(inside(va) && inside(vb) && inside(za) && inside(zb)) {
                continue;
            }
            let cell = za.round() as usize * 256 + zb.round() as usize;
            let c = &mut cells[cell];
            c.0 += 1;
            c.1 += va as f64;
            c.2 += vb as f64;
        }
        for &(count, sa, sb) in &cells {
            if count == 0 {
                continue;
            }
            let n = count as f64;
            let (xa, xb) = (sa / n, sb / n);
            let ((ia, fa), (ib, fb)) = (ends(xa), ends(xb));
            let row = [
                (ia, -(1.0 - fa)),
                (ia + 1, -fa),
                (ib, 1.0 - fb),
                (ib + 1, fb),
            ];
            let s = &mut sums[fold];
            for (x, cx) in row {
                s.c[x] += n * cx * lr;
                for (y, cy) in row {
                    s.q[x * 256 + y] += n * cx * cy;
                }
            }
            s.s += n * lr * lr;
            s.n += n;
            let (l, r) = (xa.min(xb).floor() as usize, xa.max(xb).ceil() as usize);
            cover[l] += n;
            cover[r.min(256)] -= n;
        }
    }
    // Every step of the range must be spanned by some comparison.
    let mut acc = 0.0;
    for (k, d) in cover.iter().enumerate().take(hi).skip(lo) {
        acc += d;
        if acc < 0.5 {
            return Err(FitRefusal::NarrowRange {
                levels: k + 1 - lo,
                lo: lo as u8,
                hi: k as u8,
            });
        }
    }
    Ok(SweepEquations {
        folds: sums,
        range: (lo, hi),
        pairs: pairs.len(),
        exposures: distinct,
    })
}

/// A regularised fit and how it was chosen.
#[derive(Debug, Clone)]
pub struct RegularisedFit {
    /// `g'(I)` for I = 0..=255: fitted where there are data, extrapolated beyond.
    pub g_prime: [f64; 256],
    /// The grey levels the fit is valid on (both ends included).
    pub range: (u8, u8),
    /// The chosen regulariser.
    pub lambda: f64,
    /// Cross-validation rms error (ln t) of each lambda tried.
    pub cv: Vec<(f64, f64)>,
    /// Rms residual (ln t) of the final fit on all the equations in the range.
    pub rms_ln: f64,
    /// Equations in the range.
    pub equations: f64,
}

impl RegularisedFit {
    /// The chosen lambda's cross-validation rms (ln t).
    pub fn cv_rms(&self) -> f64 {
        self.cv
            .iter()
            .find(|(l, _)| *l == self.lambda)
            .map_or(f64::NAN, |(_, e)| *e)
    }
}

/// The data of one fold in the step unknowns `h` over levels `lo..=hi`:
/// `sum w (g_b - g_a - ln r)^2 = h^T A h - 2 b^T h + s`, with `n` equations.
#[derive(Clone)]
struct Quadratic {
    a: DMatrix<f64>,
    b: DVector<f64>,
    s: f64,
    n: f64,
}

impl Quadratic {
    fn zeros(m: usize) -> Self {
        Self {
            a: DMatrix::zeros(m, m),
            b: DVector::zeros(m),
            s: 0.0,
            n: 0.0,
        }
    }

    fn add(&mut self, o: &Quadratic) {
        self.a += &o.a;
        self.b += &o.b;
        self.s += o.s;
        self.n += o.n;
    }

    fn value(&self, h: &DVector<f64>) -> f64 {
        (h.dot(&(&self.a * h)) - 2.0 * self.b.dot(h) + self.s).max(0.0)
    }
}

/// A fold's equations in the steps `h_k` over `lo..=hi` (k = 0 for `lo -> lo + 1`).
fn quadratic(s: &FoldSums, lo: usize, hi: usize) -> Quadratic {
    let levels = hi - lo + 1;
    // g_i = sum_{k < i} h_k (g_lo = 0): A = C^T Q C by suffix sums.
    let m = levels - 1;
    let mut suffix = DMatrix::<f64>::zeros(levels + 1, levels + 1);
    for i in (0..levels).rev() {
        for j in (0..levels).rev() {
            suffix[(i, j)] = s.q[(i + lo) * 256 + j + lo] + suffix[(i + 1, j)] + suffix[(i, j + 1)]
                - suffix[(i + 1, j + 1)];
        }
    }
    let a = DMatrix::from_fn(m, m, |k, l| suffix[(k + 1, l + 1)]);
    let mut b = DVector::<f64>::zeros(m);
    let mut acc = 0.0;
    for k in (0..m).rev() {
        acc += s.c[k + 1 + lo];
        b[k] = acc;
    }
    Quadratic {
        a,
        b,
        s: s.s,
        n: s.n,
    }
}

fn longest_run(ok: &[bool]) -> (usize, usize) {
    let (mut best, mut start) = ((1usize, 0usize), None);
    for i in 0..=ok.len() {
        match (ok.get(i).copied().unwrap_or(false), start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                if i - s > best.1 + 1 - best.0.min(best.1 + 1) {
                    best = (s, i - 1);
                }
                start = None;
            }
            _ => {}
        }
    }
    best
}

/// The penalty's matrix `D^T D` for second differences over `m` unknowns.
fn second_difference_gram(m: usize) -> DMatrix<f64> {
    let mut p = DMatrix::<f64>::zeros(m, m);
    for k in 1..m.saturating_sub(1) {
        let row = [(k - 1, 1.0), (k, -2.0), (k + 1, 1.0)];
        for (x, cx) in row {
            for (y, cy) in row {
                p[(x, y)] += cx * cy;
            }
        }
    }
    p
}

/// `J(u) = data(exp u) / n + lambda |D u|^2`.
fn objective(q: &Quadratic, p: &DMatrix<f64>, lambda: f64, u: &DVector<f64>) -> f64 {
    let h = u.map(f64::exp);
    q.value(&h) / q.n + lambda * u.dot(&(p * u))
}

/// Levenberg-Marquardt on `u = ln h` from `u0`.
fn solve(q: &Quadratic, p: &DMatrix<f64>, lambda: f64, u0: &DVector<f64>) -> DVector<f64> {
    let m = u0.len();
    let mut u = u0.clone();
    let mut j = objective(q, p, lambda, &u);
    let mut mu = 1e-3;
    for _ in 0..200 {
        let h = u.map(f64::exp);
        let ah = &q.a * &h;
        let grad = DVector::from_fn(m, |k, _| 2.0 * h[k] * (ah[k] - q.b[k]) / q.n)
            + 2.0 * lambda * (p * &u);
        let mut hess =
            DMatrix::from_fn(m, m, |k, l| 2.0 * h[k] * q.a[(k, l)] * h[l] / q.n) + 2.0 * lambda * p;
        let diag: Vec<f64> = (0..m).map(|k| hess[(k, k)].max(1e-300)).collect();
        let mut improved = false;
        for _ in 0..30 {
            for k in 0..m {
                hess[(k, k)] = diag[k] * (1.0 + mu);
            }
            let Some(ch) = hess.clone().cholesky() else {
                mu *= 10.0;
                continue;
            };
            let step = ch.solve(&(-&grad));
            let trial = &u + &step;
            let jt = objective(q, p, lambda, &trial);
            if jt.is_finite() && jt <= j {
                let gain = j - jt;
                u = trial;
                j = jt;
                mu = (mu / 3.0).max(1e-12);
                improved = true;
                if gain <= 1e-13 * j.max(1e-300) || step.amax() < 1e-9 {
                    return u;
                }
                break;
            }
            mu *= 10.0;
        }
        if !improved {
            break;
        }
    }
    u
}

/// Fit `g'` to `eq` by regularised least squares, lambda chosen by cross-validation over
/// the folds (or `lambda` when given).
pub fn fit(eq: &SweepEquations, lambda: Option<f64>) -> RegularisedFit {
    let (lo, hi) = eq.range;
    let m = hi - lo;
    let per_fold: Vec<Quadratic> = eq.folds.iter().map(|s| quadratic(s, lo, hi)).collect();
    let mut all = Quadratic::zeros(m);
    for q in &per_fold {
        all.add(q);
    }
    let p = second_difference_gram(m);
    // Start: the mean step of the equations (ln r per level), the most regularised fit
    // first.
    let u_start = {
        // The steps' mean from the unregularised normal equations, kept positive.
        let mut reg = all.a.clone();
        let scale = reg.trace() / m as f64 * 1e-6;
        for k in 0..m {
            reg[(k, k)] += scale;
        }
        let h0 = reg
            .cholesky()
            .map(|c| c.solve(&all.b))
            .map_or(0.01, |h| (h.sum() / m as f64).abs().max(1e-6));
        DVector::from_element(m, h0.ln())
    };
    let grid: Vec<f64> = match lambda {
        Some(l) => vec![l],
        None => LAMBDA_EXP_HALF
            .rev()
            .map(|k| 10f64.powf(k as f64 / 2.0))
            .collect(),
    };
    let mut cv = Vec::with_capacity(grid.len());
    // Standard error of each lambda's held-out mean squared error over the folds.
    let mut se = Vec::with_capacity(grid.len());
    if grid.len() > 1 {
        let trains: Vec<Quadratic> = (0..per_fold.len())
            .map(|f| {
                let mut t = Quadratic::zeros(m);
                for (g, q) in per_fold.iter().enumerate() {
                    if g != f {
                        t.add(q);
                    }
                }
                t
            })
            .collect();
        let mut warm: Vec<DVector<f64>> = vec![u_start.clone(); per_fold.len()];
        for &l in &grid {
            let (mut err, mut n) = (0.0, 0.0);
            let mut fold_mse = Vec::with_capacity(trains.len());
            for (f, train) in trains.iter().enumerate() {
                if train.n == 0.0 || per_fold[f].n == 0.0 {
                    continue;
                }
                warm[f] = solve(train, &p, l, &warm[f]);
                let h = warm[f].map(f64::exp);
                let e = per_fold[f].value(&h);
                fold_mse.push(e / per_fold[f].n);
                err += e;
                n += per_fold[f].n;
            }
            let k = fold_mse.len().max(2) as f64;
            let mean = fold_mse.iter().sum::<f64>() / k;
            let var = fold_mse.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (k - 1.0);
            cv.push((l, (err / n.max(1.0)).sqrt()));
            se.push((var / k).sqrt());
        }
    }
    let chosen = match lambda {
        Some(l) => l,
        None => one_standard_error(&cv, &se).unwrap_or(grid[0]),
    };
    // The final fit on all folds, warm-started along the grid down to the chosen lambda.
    let mut u = u_start;
    for &l in grid.iter().filter(|&&l| l >= chosen) {
        u = solve(&all, &p, l, &u);
    }
    let h = u.map(f64::exp);
    let rms_ln = (all.value(&h) / all.n).sqrt();
    if lambda.is_some() {
        cv.push((chosen, f64::NAN));
    }
    // Where one level is a coarser bin than MAX_STEP_LN of exposure, g' at a level is an
    // average over too wide a span to mean much: the valid range starts and ends inside.
    let first = (0..m).find(|&k| h[k] < MAX_STEP_LN).unwrap_or(0);
    let last = (0..m).rev().find(|&k| h[k] < MAX_STEP_LN).unwrap_or(m - 1);
    let (vlo, vhi) = if first <= last {
        (lo + first, lo + last + 1)
    } else {
        (lo, hi)
    };
    RegularisedFit {
        g_prime: g_prime_table(&h, lo, hi),
        range: (vlo as u8, vhi as u8),
        lambda: chosen,
        cv,
        rms_ln,
        equations: all.n,
    }
}

/// The levels, outward from mid grey, at which fewer than [`MAX_CENSORED`] of the pixels
/// (by their mean over all frames) were black or clipped in one of their frames: beyond,
/// keeping only the pixels never clipped keeps those whose noise was low, and their means
/// fall short.
fn censored_ends(means: &[&MeanImage]) -> std::ops::RangeInclusive<usize> {
    let (mut total, mut cut) = ([0.0f64; 256], [0.0f64; 256]);
    for m in means {
        for (&all, &g) in m.all.iter().zip(&m.grey) {
            let l = (all.round() as usize).min(255);
            total[l] += 1.0;
            if g.is_nan() {
                cut[l] += 1.0;
            }
        }
    }
    let fine = |l: usize| total[l] == 0.0 || cut[l] / total[l] < MAX_CENSORED;
    let hi = (128..256).find(|&l| !fine(l)).map_or(255, |l| l - 1);
    let lo = (0..=128).rev().find(|&l| !fine(l)).map_or(0, |l| l + 1);
    lo..=hi
}

/// The one-standard-error rule (Hastie, Tibshirani and Friedman, The Elements of
/// Statistical Learning, 2nd ed., section 7.10): the smoothest lambda whose held-out mean
/// squared error is within one standard error of the smallest.
fn one_standard_error(cv: &[(f64, f64)], se: &[f64]) -> Option<f64> {
    let (best, _) = cv
        .iter()
        .enumerate()
        .min_by(|a, b| a.1 .1.total_cmp(&b.1 .1))?;
    let limit = cv[best].1.powi(2) + se[best];
    cv.iter()
        .filter(|(_, e)| e.powi(2) <= limit)
        .map(|(l, _)| *l)
        .max_by(f64::total_cmp)
}

/// `g'` at each level from the steps: the mean of the two steps around a level inside the
/// range, the end step at the range's ends, and `ln g'` extrapolated linearly outside
/// (the slope of its last 8 steps, at most 0.5 a level).
fn g_prime_table(h: &DVector<f64>, lo: usize, hi: usize) -> [f64; 256] {
    let m = h.len();
    let mut t = [0.0; 256];
    for (k, v) in t[lo..=hi].iter_mut().enumerate() {
        *v = match (k, k == m) {
            (0, _) => h[0],
            (_, true) => h[m - 1],
            _ => 0.5 * (h[k - 1] + h[k]),
        };
    }
    let span = 8.min(m.saturating_sub(1)).max(1);
    let slope = |a: f64, b: f64| ((b.ln() - a.ln()) / span as f64).clamp(-0.5, 0.5);
    let (low, high) = (t[lo], t[hi]);
    let low_slope = slope(low, t[lo + span.min(hi - lo)]);
    for (i, v) in t.iter_mut().enumerate().take(lo) {
        *v = (low.ln() - low_slope * (lo - i) as f64).exp();
    }
    let high_slope = slope(t[hi - span.min(hi - lo)], high);
    for (i, v) in t.iter_mut().enumerate().skip(hi + 1) {
        *v = (high.ln() + high_slope * (i - hi) as f64).exp();
    }
    for v in &mut t {
        *v = v.clamp(1e-12, 1e12);
    }
    t
}
