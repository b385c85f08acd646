//! `markhold response fit`: the camera response in the paper's polynomial form, from
//! frames of one static scene taken at several exposures.
//!
//! With `g = ln f^-1`, a pixel seen at grey `I_a` with exposure `t_a` and at `I_b` with
//! `t_b` satisfies `g(I_b) - g(I_a) = ln(t_b / t_a)` (same irradiance). For
//! `g'(I) = sum_j c_j I^j` the left side is linear in the coefficients,
//! `sum_j c_j (I_b^(j+1) - I_a^(j+1)) / (j + 1)`, so every pixel of every pair of frames
//! adjacent in exposure gives one row of a linear least-squares problem (solved by SVD,
//! in the grey level scaled to [0, 1] for conditioning). Pixels black or clipped in either
//! frame carry no equation.

use anyhow::{bail, Context};
use markhold_exposure::{Frame, ResponseModel};
use nalgebra::{DMatrix, DVector};
use std::path::PathBuf;

/// Grey levels a pixel must lie within in both frames of a pair to give an equation.
const USABLE_GREY: std::ops::RangeInclusive<u8> = 20..=250;
/// Most equations: pixels are subsampled evenly down to this many.
const MAX_ROWS: usize = 60_000;

/// A fitted response and how well it fits.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseFit {
    /// `g'(I) = sum_j coefficients[j] I^j`, lowest order first, I in grey levels.
    pub coefficients: Vec<f64>,
    /// Root mean square residual of the equations, in ln t.
    pub rms_ln: f64,
    /// Equations used.
    pub rows: usize,
    /// Lowest and highest grey level seen in an equation.
    pub levels: (u8, u8),
}

impl ResponseFit {
    /// The site file's `[camera] response` value.
    pub fn model(&self) -> ResponseModel {
        ResponseModel::Polynomial {
            coefficients: self.coefficients.clone(),
        }
    }

    /// The TOML line for the site file's `[camera]` section.
    pub fn toml_line(&self) -> String {
        let c: Vec<String> = self.coefficients.iter().map(|v| format!("{v:e}")).collect();
        format!(
            "response = {{ model = \"polynomial\", coefficients = [{}] }}",
            c.join(", ")
        )
    }
}

/// Fit a polynomial `g'` of `degree` (0..=15) to frames of one static scene at
/// different exposures (each frame's `meta.exposure_us`).
pub fn fit_polynomial(frames: &[Frame], degree: usize) -> anyhow::Result<ResponseFit> {
    if degree > 15 {
        bail!("--degree {degree}: expected 0..=15 (at most 16 coefficients)");
    }
    let mut order: Vec<&Frame> = frames.iter().collect();
    order.sort_by(|a, b| a.meta.exposure_us.total_cmp(&b.meta.exposure_us));
    let first = order.first().context("no frames to fit")?;
    if order
        .iter()
        .any(|f| f.width != first.width || f.height != first.height || !f.is_consistent())
    {
        bail!("the frames differ in size: a sweep must show one scene from one camera");
    }
    let pairs: Vec<(&Frame, &Frame)> = order
        .windows(2)
        .filter(|w| w[1].meta.exposure_us > w[0].meta.exposure_us * 1.05)
        .map(|w| (w[0], w[1]))
        .collect();
    if pairs.is_empty() {
        bail!("need frames at two or more exposures at least 5 % apart");
    }
    let usable = |a: u8, b: u8| USABLE_GREY.contains(&a) && USABLE_GREY.contains(&b);
    let total: usize = pairs
        .iter()
        .map(|(a, b)| {
            a.data
                .iter()
                .zip(&b.data)
                .filter(|(&x, &y)| usable(x, y))
                .count()
        })
        .sum();
    let stride = total.div_ceil(MAX_ROWS).max(1);
    let n = degree + 1;
    let mut rows: Vec<f64> = Vec::with_capacity(MAX_ROWS * n + n);
    let mut rhs: Vec<f64> = Vec::with_capacity(MAX_ROWS + 1);
    let (mut lo, mut hi) = (u8::MAX, 0u8);
    let mut k = 0usize;
    for (a, b) in &pairs {
        let ln_ratio = (b.meta.exposure_us / a.meta.exposure_us).ln();
        for (&ia, &ib) in a.data.iter().zip(&b.data) {
            if !usable(ia, ib) {
                continue;
            }
            k += 1;
            if !k.is_multiple_of(stride) {
                continue;
            }
            lo = lo.min(ia.min(ib));
            hi = hi.max(ia.max(ib));
            let (ua, ub) = (ia as f64 / 255.0, ib as f64 / 255.0);
            let (mut pa, mut pb) = (ua, ub);
            for j in 0..n {
                rows.push((pb - pa) / (j + 1) as f64);
                pa *= ua;
                pb *= ub;
            }
            rhs.push(ln_ratio);
        }
    }
    let m = rhs.len();
    if m < 4 * n {
        bail!(
            "only {m} usable pixel pairs (neither black nor clipped in both frames of a pair) \
             for {n} coefficients: sweep a scene with more mid-grey content"
        );
    }
    let a = DMatrix::from_row_slice(m, n, &rows);
    let b = DVector::from_vec(rhs);
    let svd = a.clone().svd(true, true);
    let scaled = svd
        .solve(&b, 1e-12)
        .map_err(|e| anyhow::anyhow!("least squares failed: {e}"))?;
    let residual = &a * &scaled - &b;
    let rms_ln = (residual.norm_squared() / m as f64).sqrt();
    // g'(I) in grey levels: c_j = a_j / 255^(j+1) for u = I / 255.
    let coefficients: Vec<f64> = scaled
        .iter()
        .enumerate()
        .map(|(j, v)| v / 255f64.powi(j as i32 + 1))
        .collect();
    let fit = ResponseFit {
        coefficients,
        rms_ln,
        rows: m,
        levels: (lo, hi),
    };
    fit.model().validate().with_context(|| {
        format!(
            "the fitted degree-{degree} polynomial is not a valid response (g' must be \
             positive at every grey level; levels {lo}..={hi} were observed): try a lower \
             --degree or a sweep that covers more grey levels"
        )
    })?;
    Ok(fit)
}

/// Frames of a `frames:` folder (PNG files and `frames.csv` with each frame's exposure).
pub fn frames_of_folder(dir: &std::path::Path) -> anyhow::Result<Vec<Frame>> {
    use markhold_exposure::Camera;
    let mut cam = markhold_camera::RecordedCamera::open(dir)
        .with_context(|| format!("reading frames folder {}", dir.display()))?;
    let mut out = Vec::with_capacity(cam.len());
    for _ in 0..cam.len() {
        let mut f = Frame::new(1, 1);
        cam.grab(&mut f)
            .with_context(|| format!("reading frames folder {}", dir.display()))?;
        out.push(f);
    }
    Ok(out)
}

/// `markhold response ...`.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum ResponseCommand {
    /// Fit the camera response (the paper's polynomial form) from an exposure sweep and
    /// print the `[camera]` line for the site file. The sweep is rendered by the HIL
    /// camera of `--site`, or read from `--frames DIR` (a real camera's frames of one
    /// static scene at several exposures, with `frames.csv`).
    Fit(FitArgs),
}

#[derive(Debug, Clone, clap::Args)]
pub struct FitArgs {
    /// Dive-site file (its camera, for the HIL sweep).
    #[arg(long, default_value = "params/pool.toml")]
    pub site: PathBuf,
    /// Fit these frames instead of a HIL sweep.
    #[arg(long, value_name = "DIR")]
    pub frames: Option<PathBuf>,
    /// Degree of the polynomial g'(I), 0..=15 (the paper's camera: 14).
    #[arg(long, default_value_t = 4)]
    pub degree: usize,
    /// HIL sweep: exposures from the camera's minimum to its maximum, this many.
    #[arg(long, default_value_t = 12)]
    pub steps: usize,
    /// HIL sweep: seed of the simulated world.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

pub fn cli(cmd: ResponseCommand) -> anyhow::Result<()> {
    let ResponseCommand::Fit(args) = cmd;
    let frames = match &args.frames {
        Some(dir) => frames_of_folder(dir)?,
        None => hil_sweep(&args)?,
    };
    let fit = fit_polynomial(&frames, args.degree)?;
    crate::outln!(
        "# {} frames, {} equations over grey levels {}..={}, rms residual {:.4} in ln t",
        frames.len(),
        fit.rows,
        fit.levels.0,
        fit.levels.1,
        fit.rms_ln
    );
    crate::outln!("# under [camera] in {}:", args.site.display());
    crate::outln!("{}", fit.toml_line());
    Ok(())
}

#[cfg(feature = "sim")]
fn hil_sweep(args: &FitArgs) -> anyhow::Result<Vec<Frame>> {
    let site = crate::params::load(&args.site)?;
    crate::sim::hil::exposure_sweep(&site, args.seed, args.steps)
}

#[cfg(not(feature = "sim"))]
fn hil_sweep(_: &FitArgs) -> anyhow::Result<Vec<Frame>> {
    bail!("this build has no HIL camera (built without the cargo feature `sim`): use --frames DIR")
}

#[cfg(test)]
mod tests {
    use super::*;
    use markhold_exposure::Response;

    /// A static scene of varied irradiance seen by `response` at each exposure.
    fn sweep(response: &Response, exposures: &[f64]) -> Vec<Frame> {
        let (w, h) = (64u32, 48u32);
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let irradiance: Vec<f64> = (0..w * h)
            .map(|_| {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                // Log-uniform over 3 decades, so every exposure has mid-grey pixels.
                10f64.powf(-3.0 + 3.0 * (seed % 10_000) as f64 / 10_000.0)
            })
            .collect();
        exposures
            .iter()
            .map(|&t| {
                let mut f = Frame::new(w, h);
                f.meta.exposure_us = t;
                for (p, e) in f.data.iter_mut().zip(&irradiance) {
                    *p = response.grey(e * t / 1000.0).round() as u8;
                }
                f
            })
            .collect()
    }

    #[test]
    fn recovers_a_gamma_response() {
        let truth = Response::gamma(2.2).unwrap();
        let exposures: Vec<f64> = (0..10).map(|k| 100.0 * 1.6f64.powi(k)).collect();
        let fit = fit_polynomial(&sweep(&truth, &exposures), 6).unwrap();
        let r = fit.model().load().unwrap();
        // Over the mid levels g' (= 2.2 / I) is matched within 5 %.
        for i in [30u8, 60, 100, 150, 200] {
            let (a, b) = (truth.g_prime(i), r.g_prime(i));
            assert!((b / a - 1.0).abs() < 0.05, "g'({i}): fit {b} truth {a}");
        }
        assert!(fit.rms_ln < 0.05, "{}", fit.rms_ln);
    }

    #[cfg(feature = "sim")]
    #[test]
    fn hil_sweep_fit_recovers_the_linear_hil_camera() {
        // The HIL camera of the fixture is linear (g' = 1 / I) with shot and read noise.
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
        let site = crate::params::load(&path).unwrap();
        let frames = crate::sim::hil::exposure_sweep(&site, 1, 12).unwrap();
        assert_eq!(frames.len(), 12);
        let fit = fit_polynomial(&frames, 4).unwrap();
        let r = fit.model().load().unwrap();
        for i in [40u8, 70, 100, 150] {
            let (truth, got) = (1.0 / i as f64, r.g_prime(i));
            assert!(
                (got / truth - 1.0).abs() < 0.15,
                "g'({i}): fit {got} truth {truth}"
            );
        }
        assert!(fit.rms_ln < 0.05, "{}", fit.rms_ln);
    }

    #[test]
    fn a_single_exposure_is_refused() {
        let truth = Response::linear();
        let e = fit_polynomial(&sweep(&truth, &[500.0, 500.0]), 3)
            .unwrap_err()
            .to_string();
        assert!(e.contains("two or more exposures"), "{e}");
    }
}
