//! Naive reference implementations: full sort, f64 throughout, fresh buffers every call.
//!
//! They define what the fast paths must compute and are the baselines the benchmarks
//! measure beside them. Not for the loop.

use crate::{ImageView, MetricParams, MetricValue, Response};

/// `M` and `dM/d(ln t)` by the textbook route: per-pixel f64 gradients, a full sort by
/// `G`, the weight formula evaluated per rank; equal `G` share the mean weight of their
/// ranks (the same tie rule as the histogram path).
pub fn metric_full_sort(
    view: ImageView<'_>,
    response: &Response,
    params: &MetricParams,
) -> Option<MetricValue> {
    let (w, h) = (view.width, view.height);
    if w < 3 || h < 3 {
        return None;
    }
    let px = |x: usize, y: usize| view.row(y)[x] as f64;
    let d = |x: usize, y: usize| {
        let p = view.row(y)[x];
        if p >= params.saturation_grey {
            0.0
        } else {
            response.di_dlnt(p)
        }
    };
    let sobel = |f: &dyn Fn(usize, usize) -> f64, x: usize, y: usize| {
        let gx = (f(x + 1, y - 1) - f(x - 1, y - 1))
            + 2.0 * (f(x + 1, y) - f(x - 1, y))
            + (f(x + 1, y + 1) - f(x - 1, y + 1));
        let gy = (f(x - 1, y + 1) + 2.0 * f(x, y + 1) + f(x + 1, y + 1))
            - (f(x - 1, y - 1) + 2.0 * f(x, y - 1) + f(x + 1, y - 1));
        (gx / 8.0, gy / 8.0)
    };
    let mut pixels: Vec<(f64, f64)> = Vec::new();
    let (mut sum_grey, mut n_sat) = (0.0, 0usize);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let (ix, iy) = sobel(&px, x, y);
            let (dx, dy) = sobel(&d, x, y);
            let g = ix * ix + iy * iy;
            let mut dg = 2.0 * (ix * dx + iy * dy);
            let p = view.row(y)[x];
            sum_grey += p as f64;
            if p >= params.saturation_grey {
                n_sat += 1;
                dg = -params.saturation_penalty * dg.abs().max(params.saturation_floor);
            }
            pixels.push((g, dg));
        }
    }
    pixels.sort_by(|a, b| a.0.total_cmp(&b.0));
    let s = pixels.len();
    let mut weights = Vec::new();
    crate::soft_percentile_weights(s, params.percentile, params.weight_power, &mut weights);
    let (mut m, mut dm) = (0.0, 0.0);
    let mut i = 0;
    while i < s {
        let mut j = i;
        while j < s && pixels[j].0 == pixels[i].0 {
            j += 1;
        }
        let wbar: f64 = weights[i..j].iter().sum::<f64>() / (j - i) as f64;
        for p in &pixels[i..j] {
            m += wbar * p.0;
            dm += wbar * p.1;
        }
        i = j;
    }
    Some(MetricValue {
        m,
        dm_dlnt: dm,
        pixels: s,
        mean_grey: sum_grey / s as f64,
        saturated_frac: n_sat as f64 / s as f64,
    })
}

/// Box downsampling by `factor` into a fresh buffer, in f64.
pub fn downsample(view: ImageView<'_>, factor: usize) -> (usize, usize, Vec<u8>) {
    let f = factor.max(1);
    let (w, h) = (view.width / f, view.height / f);
    let mut out = Vec::new();
    for oy in 0..h {
        for ox in 0..w {
            let mut sum = 0.0;
            for y in oy * f..oy * f + f {
                for x in ox * f..ox * f + f {
                    sum += view.row(y)[x] as f64;
                }
            }
            out.push((sum / (f * f) as f64).round() as u8);
        }
    }
    (w, h, out)
}

/// AEC's metric the naive way: fresh pyramid level, then [`metric_full_sort`].
pub fn aec_metric(
    view: ImageView<'_>,
    factor: usize,
    response: &Response,
    params: &MetricParams,
) -> Option<MetricValue> {
    let (w, h, data) = downsample(view, factor);
    let small = ImageView {
        width: w,
        height: h,
        stride: w,
        data: &data,
    };
    metric_full_sort(small, response, params)
}

/// GEC's anchor scores the naive way: each gamma image synthesized with `powf` into a
/// fresh buffer, f64 gradients, `ln` per pixel.
pub fn gec_scores(view: ImageView<'_>, cfg: &crate::GecConfig) -> Option<[f64; 7]> {
    let (w, h) = (view.width, view.height);
    if w < 3 || h < 3 {
        return None;
    }
    let norm = (cfg.lambda * (1.0 - cfg.delta) + 1.0).ln();
    let mut out = [0.0; 7];
    for (k, &g) in crate::GEC_GAMMAS.iter().enumerate() {
        let mut img = Vec::new();
        for y in 0..h {
            for &p in view.row(y) {
                img.push((255.0 * (p as f64 / 255.0).powf(g)).round());
            }
        }
        let at = |x: usize, y: usize| img[y * w + x];
        let mut score = 0.0;
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let sx = (at(x + 1, y - 1) - at(x - 1, y - 1))
                    + 2.0 * (at(x + 1, y) - at(x - 1, y))
                    + (at(x + 1, y + 1) - at(x - 1, y + 1));
                let sy = (at(x - 1, y + 1) + 2.0 * at(x, y + 1) + at(x + 1, y + 1))
                    - (at(x - 1, y - 1) + 2.0 * at(x, y - 1) + at(x + 1, y - 1));
                let m = ((sx * sx + sy * sy).sqrt() / 1020.0).min(1.0);
                if m >= cfg.delta {
                    score += (cfg.lambda * (m - cfg.delta) + 1.0).ln() / norm;
                }
            }
        }
        out[k] = score;
    }
    Some(out)
}
