//! `markhold response fit` end to end: the line it prints, put under `[camera]`, makes a
//! site that `params check` accepts and that runs; the regularised fit of a HIL sweep
//! reproduces the rendering camera's g' (the paper's code's degree-14 polynomial, and a
//! linear camera's 1/I) over the range it reports, where the unregularised polynomial
//! invents a shoulder.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common::{markhold, repo, site_path, tmp_dir};
use markhold_exposure::{Response, ResponseModel};
use std::path::{Path, PathBuf};

/// `response fit ARGS --site SITE`: its stdout (the command must succeed).
fn fit(site: &Path, args: &[&str]) -> String {
    let o = markhold()
        .args(["response", "fit"])
        .args(args)
        .arg("--site")
        .arg(site)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

/// The regularised fit of `site`'s HIL sweep: the table it wrote and the valid range it
/// reported.
fn regularised(site: &Path, name: &str) -> (Response, (u8, u8), String) {
    let out_file: PathBuf = tmp_dir("response-fit", name).join("g-prime.txt");
    let out = fit(site, &["--out", out_file.to_str().unwrap()]);
    let range = out
        .lines()
        .find_map(|l| l.split("valid on grey levels ").nth(1))
        .and_then(|r| r.split_whitespace().next())
        .and_then(|r| r.split_once("..="))
        .map(|(a, b)| (a.parse::<u8>().unwrap(), b.parse::<u8>().unwrap()))
        .unwrap_or_else(|| panic!("no valid range in\n{out}"));
    assert!(out.contains("chosen lambda"), "{out}");
    assert!(out.contains("cross-validation rms"), "{out}");
    // The printed line names the written file.
    (printed_response(&out, "table"), range, out)
}

/// The response of `out`'s `response = { model = "MODEL", ... }` line.
fn printed_response(out: &str, model: &str) -> Response {
    let start = format!("response = {{ model = \"{model}\"");
    let line = out
        .lines()
        .find(|l| l.starts_with(&start))
        .unwrap_or_else(|| panic!("no response line in\n{out}"));
    let v: toml::Table = toml::from_str(line).expect("the response line is TOML");
    let model: ResponseModel = v["response"]
        .clone()
        .try_into()
        .expect("the response line is a response model");
    model.load().expect("the printed response loads")
}

/// The levels of `lo..=hi` where the fit is more than 10 % off `truth`.
fn off_by_more_than_10_percent(
    fit: &Response,
    truth: impl Fn(u8) -> f64,
    lo: u8,
    hi: u8,
) -> Vec<String> {
    (lo..=hi)
        .filter_map(|i| {
            let (got, want) = (fit.g_prime(i), truth(i));
            ((got / want - 1.0).abs() > 0.10).then(|| format!("g'({i}) = {got:.5} vs {want:.5}"))
        })
        .collect()
}

/// The regularised fit on the paper camera of tests/fixtures/`fixture`: valid from level
/// 10 or lower to `hi_min` or higher, and within 10 % of the code's response from 10 to
/// `check_to(top of the valid range)`.
fn fits_the_paper_code(fixture: &str, name: &str, hi_min: u8, check_to: impl Fn(u8) -> u8) {
    let site = repo(&format!("tests/fixtures/{fixture}"));
    let (r, (lo, hi), out) = regularised(&site, name);
    assert!(lo <= 10 && hi >= hi_min, "valid range {lo}..={hi}\n{out}");
    let code = Response::paper_code();
    let bad = off_by_more_than_10_percent(&r, |i| code.g_prime(i), 10, check_to(hi));
    assert!(bad.is_empty(), "{}\n{out}", bad.join("\n"));
}

#[test]
fn regularised_fit_reproduces_the_paper_codes_response() {
    // At the camera's longest exposure (30 ms) the pool's brightest parts reach grey 239
    // through the code's response: the fit is valid, and checked, up to there.
    fits_the_paper_code("pool-paper-camera.toml", "paper", 235, |hi| hi.min(250));
}

#[test]
fn regularised_fit_reproduces_the_paper_codes_shoulder_with_long_exposures() {
    // The same camera and scene swept up to 0.4 s: the fit covers the shoulder.
    fits_the_paper_code("pool-paper-camera-long.toml", "paper-long", 250, |_| 250);
}

#[test]
fn regularised_fit_reproduces_a_linear_camera_without_the_polynomials_shoulder() {
    let site = site_path();
    let (r, (lo, hi), out) = regularised(&site, "linear");
    // The range reported covers nearly every level: it cannot pass by shrinking. Above
    // it, where the sensor's noise clips a share of the pixels, the table is extrapolated;
    // it must hold there too (the shoulder's levels 239..=255 are all checked).
    assert!(lo <= 5 && hi >= 240, "valid range {lo}..={hi}\n{out}");
    let linear = |i: u8| 1.0 / i as f64;
    let bad = off_by_more_than_10_percent(&r, linear, lo, 255);
    assert!(bad.is_empty(), "{}\n{out}", bad.join("\n"));
    // The unregularised degree-4 polynomial of the same camera overshoots near clipping.
    let poly = fit(&site, &["--method", "polynomial", "--degree", "4"]);
    let p = printed_response(&poly, "polynomial");
    let shoulder = (239u8..=255)
        .map(|i| p.g_prime(i) * i as f64)
        .fold(0.0, f64::max);
    assert!(
        shoulder > 1.3,
        "polynomial g' x I up to {shoulder} at 239..=255"
    );
}

#[test]
fn fitted_line_makes_a_valid_site() {
    let fixture = site_path();
    let out = fit(
        &fixture,
        &["--method", "polynomial", "--degree", "4", "--steps", "8"],
    );
    let line = out
        .lines()
        .find(|l| l.starts_with("response = { model = \"polynomial\""))
        .unwrap_or_else(|| panic!("no response line in\n{out}"));
    let dir = tmp_dir("response-fit", "site");
    let site = dir.join("pool-640-fitted.toml");
    let text = std::fs::read_to_string(&fixture).unwrap();
    std::fs::write(
        &site,
        text.replacen("[camera]\n", &format!("[camera]\n{line}\n"), 1),
    )
    .unwrap();
    let o = crate::common::run_ok(markhold().args(["params", "check"]).arg(&site));
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(printed.contains("polynomial"), "{printed}");
    crate::common::run_ok(
        markhold()
            .args(["hil", "--quiet", "--seconds", "1", "--site"])
            .arg(&site),
    );
}

#[test]
fn too_few_exposures_are_refused_by_name() {
    let o = markhold()
        .args(["response", "fit", "--steps", "2", "--site"])
        .arg(site_path())
        .arg("--out")
        .arg(tmp_dir("response-fit", "refused").join("t.txt"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    // 2 steps over 20..30000 us are 1500x apart: no pair to compare.
    assert!(err.contains("no two frames"), "{err}");
}
