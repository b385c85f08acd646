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
    let mut greys: Vec<u8> = Vec::new();
    let (mut sum_grey, mut n_sat) = (0.0, 0usize);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let (ix, iy) = sobel(&px, x, y);
            let (dx, dy) = sobel(&d, x, y);
            let g = ix * ix + iy * iy;
            let mut dg = 2.0 * (ix * dx + iy * dy);
            let p = view.row(y)[x];
            sum_grey += p as f64;
            greys.push(p);
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
        bright_grey: {
            greys.sort_unstable();
            let k = (crate::metric::BRIGHT_PERCENTILE * s as f64).ceil() as usize;
            greys[k.clamp(1, s) - 1]
        },
    })
}
