//! `markhold response fit` end to end: the line it prints, put under `[camera]`, makes a
//! site that `params check` accepts and that runs.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common::{markhold, site_path, tmp_dir};

#[test]
fn fitted_line_makes_a_valid_site() {
    let fixture = site_path();
    let o = markhold()
        .args(["response", "fit", "--degree", "4", "--steps", "8", "--site"])
        .arg(&fixture)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
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
    let o = markhold()
        .args(["params", "check"])
        .arg(&site)
        .output()
        .unwrap();
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(printed.contains("polynomial"), "{printed}");
    let o = markhold()
        .args(["hil", "--quiet", "--seconds", "1", "--site"])
        .arg(&site)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}
