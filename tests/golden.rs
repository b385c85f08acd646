//! Golden runs: a short HIL run of every shipped site (`params/*.toml`, 5 simulated
//! seconds, seed 1) whose summary, wall-clock fields aside, must equal the committed one in
//! `tests/golden/<site>.json` to the last bit. A HIL run is a function of its seed, so any
//! change that moves the vehicle, the picture, the detection, the exposure or the keeper
//! shows here. When a change is meant to move them, `MARKHOLD_BLESS=1 cargo test --release
//! --test golden` rewrites the files; commit them with the reason.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use std::path::Path;

use common::{differences, repo, same_as_file, tmp_path, without_wall_clock};
use markhold_autopilot::ControllerConfig;
use serde_json::Value;

const SECONDS: &str = "5";
const SEED: &str = "1";

/// The summary of `site`'s golden run, the fields above removed.
fn run(site: &Path, summary: &Path) -> Value {
    let args = ["--seconds", SECONDS, "--seed", SEED];
    without_wall_clock(common::hil_summary(site, &args, summary))
}

fn golden(site: &str) {
    let now = run(
        &repo(&format!("params/{site}.toml")),
        &tmp_path("golden", &format!("{site}.json")),
    );
    same_as_file(
        &repo(&format!("tests/golden/{site}.json")),
        &now,
        &format!("{site}: the {SECONDS} s run of seed {SEED}"),
        "cargo test --release --test golden",
    );
}

/// The golden run is fine enough to see a small change: pool with the surge axis's
/// proportional gain 1 % above the default is not pool's golden run.
#[test]
fn a_keeper_gain_one_percent_off_is_not_the_golden_run() {
    let text = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    assert!(
        !text.contains("[controller"),
        "pool.toml sets the keeper's gains itself"
    );
    let site = tmp_path("golden", "pool-surge-kp.toml");
    let kp = 1.01 * ControllerConfig::default().surge.kp;
    std::fs::write(&site, format!("{text}\n[controller.surge]\nkp = {kp}\n")).unwrap();
    let off = run(&site, &tmp_path("golden", "pool-surge-kp.json"));
    let file = repo("tests/golden/pool.json");
    let want: Value = common::read_json(file);
    assert!(off != want, "surge kp {kp} ran exactly as the default");
    eprintln!("surge kp {kp}:\n{}", differences(&off, &want));
}

/// The sites below, which must be every shipped site and every golden file.
const SITES: [&str; 7] = [
    "bluerov2-stock",
    "connecticut-river",
    "dock-map",
    "lamp-map",
    "night-harbor",
    "pool",
    "reef-caustics",
];

fn stems(dir: &str, ext: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(repo(dir))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn every_shipped_site_has_a_golden_run() {
    assert_eq!(stems("params", "toml"), SITES, "params/*.toml vs SITES");
    assert_eq!(
        stems("tests/golden", "json"),
        SITES,
        "tests/golden vs SITES"
    );
}

#[test]
fn golden_bluerov2_stock() {
    golden("bluerov2-stock");
}

#[test]
fn golden_connecticut_river() {
    golden("connecticut-river");
}

#[test]
fn golden_dock_map() {
    golden("dock-map");
}

#[test]
fn golden_lamp_map() {
    golden("lamp-map");
}

#[test]
fn golden_night_harbor() {
    golden("night-harbor");
}

#[test]
fn golden_pool() {
    golden("pool");
}

#[test]
fn golden_reef_caustics() {
    golden("reef-caustics");
}
