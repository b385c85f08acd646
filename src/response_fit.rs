//! `markhold response fit`: the camera response from frames of one static scene taken at
//! several exposures.
//!
//! With `g = ln f^-1`, a pixel seen at grey `I_a` with exposure `t_a` and at `I_b` with
//! `t_b` satisfies `g(I_b) - g(I_a) = ln(t_b / t_a)` (same irradiance). Two fits:
//! - `regularised` (the default, [`regularised`]): a discrete `g` over the grey levels,
//!   monotone and smooth, its smoothness chosen by cross-validation; written as a `g'`
//!   table file with the range of levels it is valid on.
//! - `polynomial`: the paper's form `g'(I) = sum_j c_j I^j`, unregularised least squares.
//!   The left side is linear in the coefficients,
//!   `sum_j c_j (I_b^(j+1) - I_a^(j+1)) / (j + 1)`, so every pixel of every pair of frames
//!   adjacent in exposure gives one row (solved by SVD, in the grey level scaled to
//!   [0, 1] for conditioning). Pixels black or clipped in either frame carry no equation.

pub mod regularised;

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
    /// Fit the camera response from an exposure sweep and print the `[camera]` line for
    /// the site file. The sweep is rendered by the HIL camera of `--site`, or read from
    /// `--frames DIR` (a real camera's frames of one static scene at several exposures,
    /// with `frames.csv`). The default fit is regularised (monotone, smooth, its
    /// smoothness chosen by cross-validation) and writes a g' table file; `--method
    /// polynomial` fits the paper's polynomial form without regularisation.
    Fit(FitArgs),
}

/// Which fit `response fit` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FitMethod {
    /// A discrete g over the grey levels, monotone, with a smoothness penalty on ln g'
    /// chosen by k-fold cross-validation; writes a table file (`--out`).
    Regularised,
    /// The paper's polynomial g'(I) of `--degree`, unregularised least squares.
    Polynomial,
}

#[derive(Debug, Clone, clap::Args)]
pub struct FitArgs {
    /// Dive-site file (its camera, for the HIL sweep).
    #[arg(long, default_value = "params/pool.toml")]
    pub site: PathBuf,
    /// Fit these frames instead of a HIL sweep.
    #[arg(long, value_name = "DIR")]
    pub frames: Option<PathBuf>,
    /// The fit.
    #[arg(long, value_enum, default_value_t = FitMethod::Regularised)]
    pub method: FitMethod,
    /// Regularised: the g' table file to write (256 values, the valid range in its header).
    #[arg(long, value_name = "FILE", default_value = "response-table.txt")]
    pub out: PathBuf,
    /// Regularised: folds of the cross-validation (exposures dealt to folds), 2..=20.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    /// Regularised: this smoothness weight instead of the cross-validated one.
    #[arg(long)]
    pub lambda: Option<f64>,
    /// Polynomial: degree of g'(I), 0..=15 (the paper's camera: 14).
    #[arg(long, default_value_t = 4)]
    pub degree: usize,
    /// HIL sweep: exposures from the camera's minimum to its maximum, this many (the
    /// regularised fit compares frames at most 4x apart: 32 over the HIL camera's 1500x
    /// range are 1.27x apart).
    #[arg(long, default_value_t = 32)]
    pub steps: usize,
    /// HIL sweep, regularised: frames taken at each exposure (averaged: the sensor's noise
    /// would otherwise bias the fit where the scene's histogram bends).
    #[arg(long, default_value_t = 8)]
    pub repeats: usize,
    /// HIL sweep: seed of the simulated world.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

pub fn cli(cmd: ResponseCommand) -> anyhow::Result<()> {
    let ResponseCommand::Fit(args) = cmd;
    if args.method == FitMethod::Regularised {
        if !(2..=20).contains(&args.folds) {
            bail!("--folds {}: expected 2..=20", args.folds);
        }
        if let Some(l) = args.lambda {
            if !(l.is_finite() && l >= 0.0) {
                bail!("--lambda {l}: expected a finite weight >= 0");
            }
        }
    }
    match args.method {
        FitMethod::Polynomial => {
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
        }
        FitMethod::Regularised => {
            let means = match &args.frames {
                Some(dir) => {
                    let mut frames = frames_of_folder(dir)?;
                    frames.sort_by(|a, b| a.meta.exposure_us.total_cmp(&b.meta.exposure_us));
                    let mut avg = regularised::Averager::new();
                    for f in &frames {
                        avg.push(f)?;
                    }
                    avg.finish()
                }
                None => hil_means(&args)?,
            };
            let eq = regularised::equations(&means, args.folds)?;
            let fit = regularised::fit(&eq, args.lambda);
            write_table(&args.out, &fit)?;
            let (lo, hi) = fit.range;
            crate::outln!(
                "# {} exposures, {} pairs of them, {:.0} equations; valid on grey levels \
                 {lo}..={hi} (outside: coarse levels, or extrapolated beyond the data)",
                eq.exposures,
                eq.pairs,
                fit.equations,
            );
            for (l, e) in &fit.cv {
                if e.is_finite() {
                    crate::outln!("# lambda {l:.3e}: cross-validation rms {e:.5} in ln t");
                }
            }
            match args.lambda {
                Some(l) => crate::outln!("# lambda {l:e} (given), rms residual {:.5} in ln t", fit.rms_ln),
                None => crate::outln!(
                    "# chosen lambda {:.3e} ({}-fold cross-validation rms {:.5} in ln t), rms residual {:.5}",
                    fit.lambda,
                    args.folds,
                    fit.cv_rms(),
                    fit.rms_ln
                ),
            }
            crate::outln!("# g' table written to {}", args.out.display());
            crate::outln!("# under [camera] in {}:", args.site.display());
            let file = std::path::absolute(&args.out).unwrap_or_else(|_| args.out.clone());
            crate::outln!("{}", table_toml_line(&file));
        }
    }
    Ok(())
}

/// The site file's `response` line for a table file (TOML basic string).
pub fn table_toml_line(file: &std::path::Path) -> String {
    let quoted = toml::Value::String(file.display().to_string()).to_string();
    format!("response = {{ model = \"table\", file = {quoted} }}")
}

/// Write the fit as a `g'` table file that `[camera] response = { model = "table" }` reads.
pub fn write_table(
    path: &std::path::Path,
    fit: &regularised::RegularisedFit,
) -> anyhow::Result<()> {
    use std::fmt::Write;
    let (lo, hi) = fit.range;
    let mut text = format!(
        "# g'(I) = d ln f^-1 / dI for I = 0..=255 (markhold response fit, regularised)\n\
         # valid on grey levels {lo}..={hi}; outside, coarse levels (one level spans\n\
         # more than 0.25 in ln t) or ln g' extrapolated linearly beyond the data\n\
         # lambda {:e}, {}, {:.0} equations\n",
        fit.lambda,
        if fit.cv_rms().is_finite() {
            format!("cross-validation rms {:.5} in ln t", fit.cv_rms())
        } else {
            "given (no cross-validation)".to_string()
        },
        fit.equations
    );
    for (i, v) in fit.g_prime.iter().enumerate() {
        let _ = writeln!(text, "{v:e}  # {i}");
    }
    // The file must load as the site would load it.
    markhold_exposure::Response::parse_table(path, &text)
        .with_context(|| format!("the fitted table for {}", path.display()))?;
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

#[cfg(feature = "sim")]
fn hil_sweep(args: &FitArgs) -> anyhow::Result<Vec<Frame>> {
    let site = crate::params::load(&args.site)?;
    Ok(crate::sim::hil::exposure_sweep(
        &site, args.seed, args.steps,
    )?)
}

/// The regularised fit's HIL sweep: `--steps` exposures over the camera's range,
/// `--repeats` frames at each, averaged as they are rendered.
#[cfg(feature = "sim")]
fn hil_means(args: &FitArgs) -> anyhow::Result<Vec<regularised::MeanImage>> {
    if args.steps < 2 || !(1..=256).contains(&args.repeats) {
        bail!(
            "--steps {} --repeats {}: expected 2 or more exposures and 1..=256 frames at each",
            args.steps,
            args.repeats
        );
    }
    let site = crate::params::load(&args.site)?;
    let limits = site.limits();
    let (lo, hi) = (limits.min_us, limits.effective_max_us());
    let exposures: Vec<f64> = (0..args.steps)
        .flat_map(|k| {
            let t = lo * (hi / lo).powf(k as f64 / (args.steps - 1) as f64);
            std::iter::repeat_n(t, args.repeats)
        })
        .collect();
    let mut avg = regularised::Averager::new();
    crate::sim::hil::station_frames_each::<anyhow::Error>(
        &site,
        args.seed,
        &site.site.lighting,
        &exposures,
        |f| avg.push(f).map_err(anyhow::Error::from),
    )?;
    Ok(avg.finish())
}

#[cfg(not(feature = "sim"))]
fn hil_means(_: &FitArgs) -> anyhow::Result<Vec<regularised::MeanImage>> {
    bail!("this build has no HIL camera (built without the cargo feature `sim`): use --frames DIR")
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
        let (w, h) = (192u32, 144u32);
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

    fn means(frames: &[Frame]) -> Vec<regularised::MeanImage> {
        let mut avg = regularised::Averager::new();
        for f in frames {
            avg.push(f).unwrap();
        }
        avg.finish()
    }

    #[test]
    fn regularised_recovers_a_gamma_response_over_its_range() {
        let truth = Response::gamma(2.2).unwrap();
        let exposures: Vec<f64> = (0..16).map(|k| 100.0 * 1.3f64.powi(k)).collect();
        let eq = regularised::equations(&means(&sweep(&truth, &exposures)), 5).unwrap();
        let fit = regularised::fit(&eq, None);
        let (lo, hi) = fit.range;
        assert!(lo <= 10 && hi >= 250, "{lo}..={hi}");
        for i in lo.max(10)..=hi {
            let (a, b) = (truth.g_prime(i), fit.g_prime[i as usize]);
            assert!((b / a - 1.0).abs() < 0.05, "g'({i}): fit {b} truth {a}");
        }
        // g' > 0 everywhere, and the table loads as a response.
        assert!(fit.g_prime.iter().all(|v| *v > 0.0));
        Response::from_g_prime(fit.g_prime).unwrap();
        // Cross-validation tried a grid and chose from it.
        assert!(fit.cv.len() > 5 && fit.cv.iter().any(|c| c.0 == fit.lambda));
    }

    #[test]
    fn regularised_refuses_what_cannot_be_fitted() {
        let truth = Response::linear();
        let e = regularised::equations(&means(&sweep(&truth, &[500.0, 510.0])), 5)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("two or more exposures"), "{e}");
        // Exposures 10x apart: no pair close enough to share unclipped pixels.
        let e = regularised::equations(&means(&sweep(&truth, &[100.0, 1000.0, 10_000.0])), 5)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no two frames"), "{e}");
        // A flat scene: two grey levels only.
        let mut flat = sweep(&truth, &[500.0, 600.0]);
        for (k, f) in flat.iter_mut().enumerate() {
            f.data.fill(100 + 10 * k as u8);
        }
        let e = regularised::equations(&means(&flat), 5)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("grey level"), "{e}");
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
