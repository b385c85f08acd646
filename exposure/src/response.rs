//! Camera response models.
//!
//! A camera maps the linear sensor signal `x = E * t / full_well` (in [0, 1]) to a grey
//! level `I = f(x)`. The controllers need `g'(I)` with `g = ln f^-1`, because
//! `dI/d(ln t) = 1 / g'(I)`; the HIL camera needs the forward map `f` to render. Both live
//! in one [`Response`] so that the simulated camera and the controllers' model agree.

use crate::ExposureError;
use markhold_config::{Checks, ConfigError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The `response` key of the site file's `[camera]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "model", rename_all = "lowercase", deny_unknown_fields)]
pub enum ResponseModel {
    /// `I = 255 x`.
    #[default]
    Linear,
    /// `I = 255 x^(1/gamma)` (gamma 2.2 is the usual display encoding; 1 is linear).
    Gamma { gamma: f64 },
    /// The paper's calibrated form: `g'(I) = sum_j coefficients[j] * I^j` (lowest order
    /// first, `I` the grey level 0..=255), positive at every level. `markhold response
    /// fit` computes the coefficients from an exposure sweep.
    Polynomial { coefficients: Vec<f64> },
    /// A calibrated curve: a text file of 256 values of `g'(I) = d ln f^-1 / dI` for
    /// I = 0..=255, whitespace or comma separated, `#` starts a comment.
    Table { file: PathBuf },
}

impl ResponseModel {
    /// Check the ranges that can be checked without reading files.
    pub fn validate(&self) -> Result<(), ConfigError> {
        match self {
            ResponseModel::Gamma { gamma } => check_gamma(*gamma),
            ResponseModel::Polynomial { coefficients } => {
                polynomial_table(coefficients).map(|_| ())
            }
            ResponseModel::Linear | ResponseModel::Table { .. } => Ok(()),
        }
    }

    /// The same model with a relative table path taken relative to `base` (the folder
    /// of the site file that named it); other models are returned unchanged.
    pub fn relative_to(&self, base: &Path) -> ResponseModel {
        match self {
            ResponseModel::Table { file } if file.is_relative() => ResponseModel::Table {
                file: base.join(file),
            },
            other => other.clone(),
        }
    }

    /// Build the response (reads the table file for `model = "table"`).
    pub fn load(&self) -> Result<Response, ExposureError> {
        self.validate()?;
        match self {
            ResponseModel::Linear => Ok(Response::linear()),
            ResponseModel::Gamma { gamma } => Response::gamma(*gamma),
            ResponseModel::Polynomial { coefficients } => {
                Ok(Response::integrate(polynomial_table(coefficients)?))
            }
            ResponseModel::Table { file } => Response::from_table_file(file),
        }
    }
}

/// `g'(I)` of the paper's code, lowest order first (`I` the grey level 0..=255): the
/// degree-14 polynomial its AAEC and its AEC evaluate for every camera
/// (Rennylex/adaptive_active_exposure_control, `src/changeParam.cpp` in every commit from
/// a49651a to 402f5c2, and `src/aaec_exposure_node.cpp` from 309420f; there highest order
/// first). Calibrated for the paper's FLIR Blackfly S.
pub const PAPER_CODE_G_PRIME: [f64; 15] = [
    1.30761122e+00,
    -3.08446340e-01,
    3.21098127e-02,
    -1.84372346e-03,
    6.54831886e-05,
    -1.54014489e-06,
    2.50378889e-08,
    -2.88855261e-10,
    2.39781444e-12,
    -1.43597629e-14,
    6.14568309e-17,
    -1.83243015e-19,
    3.61455838e-22,
    -4.23843983e-25,
    2.23648003e-28,
];

/// Most coefficients of a polynomial response (degree 15).
pub const MAX_POLYNOMIAL_COEFFICIENTS: usize = 16;

/// `g'(I) = sum_j c_j I^j` at one grey level (Horner).
pub fn polynomial_g_prime(coefficients: &[f64], grey: f64) -> f64 {
    coefficients
        .iter()
        .rev()
        .fold(0.0, |acc, &c| acc * grey + c)
}

/// The 256-entry `g'` table of a polynomial response; the error names the key, and the
/// first grey level where `g'` is not finite and positive.
fn polynomial_table(coefficients: &[f64]) -> Result<[f64; 256], ConfigError> {
    let key = "coefficients";
    let n = coefficients.len();
    Checks::new("camera.response")
        .check(
            key,
            format!("{n} values"),
            (1..=MAX_POLYNOMIAL_COEFFICIENTS).contains(&n),
            "1 to 16 coefficients, lowest order first",
        )
        .done()?;
    if let Some(j) = coefficients.iter().position(|c| !c.is_finite()) {
        return Checks::new("camera.response")
            .check(
                &format!("{key}[{j}]"),
                coefficients[j],
                false,
                "a finite number",
            )
            .done()
            .map(|_| [0.0; 256]);
    }
    let mut table = [0.0; 256];
    for (i, v) in table.iter_mut().enumerate() {
        *v = polynomial_g_prime(coefficients, i as f64);
        if !(v.is_finite() && *v > 0.0) {
            let value = format!("g'({i}) = {v:e}");
            return Checks::new("camera.response")
                .check(
                    key,
                    value,
                    false,
                    "coefficients whose g'(I) is positive at every grey level 0..=255",
                )
                .done()
                .map(|_| [0.0; 256]);
        }
    }
    Ok(table)
}

fn check_gamma(gamma: f64) -> Result<(), ConfigError> {
    Checks::new("camera.response")
        .range("gamma", gamma, 0.2..=5.0, "a gamma in [0.2, 5]")
        .done()
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Forward {
    Linear,
    Gamma(f64),
    /// Interpolated from the integrated table.
    Table,
}

/// A camera response: the 256-entry `g'` table and the forward curve `grey(x)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    forward: Forward,
    g_prime: [f64; 256],
    /// `ln f^-1(I)` for each level, with `f^-1(255) = 1` (full well).
    ln_x: [f64; 256],
}

/// Grey level below which `1/I` is taken at half a level, so `g'(0)` stays finite.
const HALF_LEVEL: f64 = 0.5;

impl Response {
    /// A linear sensor: `g'(I) = 1/I` (at I = 0, taken at half a level).
    pub fn linear() -> Self {
        Self::gamma_unchecked(1.0, Forward::Linear)
    }

    /// The response the paper's code assumes whatever the camera ([`PAPER_CODE_G_PRIME`]).
    pub fn paper_code() -> Self {
        let table = polynomial_table(&PAPER_CODE_G_PRIME)
            .expect("the paper's polynomial is positive at every grey level (tested)");
        Self::integrate(table)
    }

    /// `I = 255 x^(1/gamma)`, so `g'(I) = gamma / I`.
    pub fn gamma(gamma: f64) -> Result<Self, ExposureError> {
        check_gamma(gamma)?;
        Ok(Self::gamma_unchecked(gamma, Forward::Gamma(gamma)))
    }

    fn gamma_unchecked(gamma: f64, forward: Forward) -> Self {
        let mut g_prime = [0.0; 256];
        let mut ln_x = [0.0; 256];
        for i in 0..256 {
            let level = (i as f64).max(HALF_LEVEL);
            g_prime[i] = gamma / level;
            ln_x[i] = gamma * (level / 255.0).ln();
        }
        Self {
            forward,
            g_prime,
            ln_x,
        }
    }

    /// A response from a `g'` table (every entry finite and > 0). The forward curve is
    /// its integral: `ln f^-1(I) = -int_I^255 g'`, trapezoid rule between levels.
    pub fn from_g_prime(g_prime: [f64; 256]) -> Result<Self, ExposureError> {
        let bad = g_prime.iter().position(|v| !(v.is_finite() && *v > 0.0));
        if let Some(i) = bad {
            Checks::new("camera.response")
                .positive(&format!("table[{i}]"), g_prime[i], "a finite g' > 0")
                .done()?;
        }
        Ok(Self::integrate(g_prime))
    }

    fn integrate(g_prime: [f64; 256]) -> Self {
        let mut ln_x = [0.0; 256];
        for i in (0..255).rev() {
            ln_x[i] = ln_x[i + 1] - 0.5 * (g_prime[i] + g_prime[i + 1]);
        }
        Self {
            forward: Forward::Table,
            g_prime,
            ln_x,
        }
    }

    /// Read a table file; the error names the file, the line and the bad value.
    pub fn from_table_file(path: &Path) -> Result<Self, ExposureError> {
        let text = std::fs::read_to_string(path).map_err(|source| ExposureError::ResponseIo {
            file: path.to_path_buf(),
            source,
        })?;
        Self::parse_table(path, &text)
    }

    /// Parse the text of a table file (`path` only names it in errors).
    pub fn parse_table(path: &Path, text: &str) -> Result<Self, ExposureError> {
        let mut g_prime = [0.0; 256];
        let mut count = 0usize;
        for (line_no, line) in text.lines().enumerate() {
            let content = line.split('#').next().unwrap_or("");
            for token in content
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|t| !t.is_empty())
            {
                let bad = |expected: &str| ExposureError::ResponseTable {
                    file: path.to_path_buf(),
                    line: line_no + 1,
                    value: token.to_string(),
                    expected: expected.to_string(),
                };
                let v: f64 = token.parse().map_err(|_| bad("a number"))?;
                if !(v.is_finite() && v > 0.0) {
                    return Err(bad("a finite g' > 0"));
                }
                if count == 256 {
                    return Err(bad("no more than 256 values"));
                }
                g_prime[count] = v;
                count += 1;
            }
        }
        if count != 256 {
            return Err(ExposureError::ResponseTableLength {
                file: path.to_path_buf(),
                count,
            });
        }
        Ok(Self::integrate(g_prime))
    }

    /// `g'(I) = d ln f^-1 / dI` for each grey level.
    pub fn g_prime_table(&self) -> &[f64; 256] {
        &self.g_prime
    }

    pub fn g_prime(&self, grey: u8) -> f64 {
        self.g_prime[grey as usize]
    }

    /// `dI / d(ln t) = 1 / g'(I)`: how fast a pixel at this level brightens per unit of
    /// log exposure.
    pub fn di_dlnt(&self, grey: u8) -> f64 {
        1.0 / self.g_prime[grey as usize]
    }

    /// Grey level (in [0, 255], not quantized) for the normalized linear signal `x`
    /// (1 = full well). NaN and negative signals give 0.
    pub fn grey(&self, x: f64) -> f64 {
        if x.is_nan() || x <= 0.0 {
            return 0.0;
        }
        if x >= 1.0 {
            return 255.0;
        }
        match self.forward {
            Forward::Linear => 255.0 * x,
            Forward::Gamma(g) => 255.0 * x.powf(1.0 / g),
            Forward::Table => {
                let lx = x.ln();
                if lx <= self.ln_x[0] {
                    return 0.0;
                }
                // ln_x is strictly increasing: first level above lx.
                let hi = self.ln_x.partition_point(|&v| v <= lx).min(255);
                let lo = hi - 1;
                let span = self.ln_x[hi] - self.ln_x[lo];
                lo as f64 + (lx - self.ln_x[lo]) / span
            }
        }
    }

    /// The normalized linear signal that yields `grey` (inverse of [`Response::grey`]).
    pub fn signal(&self, grey: f64) -> f64 {
        let g = grey.clamp(0.0, 255.0);
        match self.forward {
            Forward::Linear => g / 255.0,
            Forward::Gamma(gm) => (g / 255.0).powf(gm),
            Forward::Table => {
                let lo = (g.floor() as usize).min(254);
                let frac = g - lo as f64;
                (self.ln_x[lo] + frac * (self.ln_x[lo + 1] - self.ln_x[lo])).exp()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_and_gamma_derivatives() {
        let l = Response::linear();
        assert_eq!(l.di_dlnt(100), 100.0);
        assert_eq!(l.di_dlnt(0), 0.5);
        assert!((l.grey(0.5) - 127.5).abs() < 1e-12);
        let g = Response::gamma(2.0).unwrap();
        // I = 255 sqrt(x): dI/dln t = I/2.
        assert!((g.di_dlnt(100) - 50.0).abs() < 1e-12);
        assert!((g.grey(0.25) - 127.5).abs() < 1e-12);
        assert!((g.signal(127.5) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn table_integrates_to_forward_curve() {
        // A gamma-2 table written out: the integrated curve must match the closed form.
        let exact = Response::gamma(2.0).unwrap();
        let mut text = String::new();
        for v in exact.g_prime_table() {
            text.push_str(&format!("{v}\n"));
        }
        let t = Response::parse_table(Path::new("g2.txt"), &text).unwrap();
        for x in [0.05, 0.1, 0.3, 0.6, 0.9] {
            let (a, b) = (exact.grey(x), t.grey(x));
            assert!((a - b).abs() < 0.6, "x {x}: {a} vs {b}");
        }
        // grey and signal are inverse.
        for g in [10.0, 77.3, 200.0, 254.5] {
            assert!((t.grey(t.signal(g)) - g).abs() < 1e-9, "{g}");
        }
    }

    #[test]
    fn malformed_table_names_file_line_value() {
        let mut text = "# header\n".to_string();
        for i in 0..256 {
            if i == 40 {
                text.push_str("0.01, -3\n");
            } else {
                text.push_str("0.01\n");
            }
        }
        let e = Response::parse_table(Path::new("crf.txt"), &text)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("crf.txt") && e.contains("line 42") && e.contains("-3"),
            "{e}"
        );
        let e = Response::parse_table(Path::new("crf.txt"), "1 2 x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 1") && e.contains("'x'"), "{e}");
        let e = Response::parse_table(Path::new("crf.txt"), "1 2 3")
            .unwrap_err()
            .to_string();
        assert!(e.contains("3 values"), "{e}");
        let e = ResponseModel::Table {
            file: "/nonexistent/crf.txt".into(),
        }
        .load()
        .unwrap_err()
        .to_string();
        assert!(e.contains("/nonexistent/crf.txt"), "{e}");
    }

    #[test]
    fn relative_table_paths_resolve_against_the_site_folder() {
        let dir = std::env::temp_dir().join(format!("markhold-crf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let text: String = Response::gamma(2.0)
            .unwrap()
            .g_prime_table()
            .iter()
            .map(|v| format!("{v}\n"))
            .collect();
        std::fs::write(dir.join("crf.txt"), text).unwrap();
        let m = ResponseModel::Table {
            file: "crf.txt".into(),
        };
        let r = m.relative_to(&dir).load().unwrap();
        assert!((r.grey(0.25) - 127.5).abs() < 0.6, "{}", r.grey(0.25));
        let abs = ResponseModel::Table {
            file: "/abs/crf.txt".into(),
        };
        assert_eq!(abs.relative_to(&dir), abs);
        assert_eq!(
            ResponseModel::Linear.relative_to(&dir),
            ResponseModel::Linear
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_papers_code_response_has_its_shoulder() {
        let r = Response::paper_code();
        // Positive at every level, and D = 1/g' falls near clipping (dM/dt can turn down).
        assert!(r.g_prime_table().iter().all(|v| v.is_finite() && *v > 0.0));
        assert!(
            r.di_dlnt(150) > 10.0 * r.di_dlnt(255),
            "{} {}",
            r.di_dlnt(150),
            r.di_dlnt(255)
        );
        let p = ResponseModel::Polynomial {
            coefficients: PAPER_CODE_G_PRIME.to_vec(),
        }
        .load()
        .unwrap();
        assert_eq!(&p, &r);
    }

    #[test]
    fn serde_tagged() {
        #[derive(Deserialize)]
        struct W {
            response: ResponseModel,
        }
        let w: W = toml_like(r#"{"response": {"model": "gamma", "gamma": 2.2}}"#);
        assert_eq!(w.response, ResponseModel::Gamma { gamma: 2.2 });
        let w: W = toml_like(r#"{"response": {"model": "linear"}}"#);
        assert_eq!(w.response, ResponseModel::Linear);
        assert!(ResponseModel::Gamma { gamma: 0.0 }.load().is_err());
    }

    fn toml_like<T: serde::de::DeserializeOwned>(s: &str) -> T {
        serde_json::from_str(s).unwrap()
    }
}
