//! End-to-end: the built binary holds station in HIL, deterministically, and rejects bad
//! site files with a message that names the file and the key.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::path::{Path, PathBuf};

use common::{markhold, repo, run_summary, tmp_dir};

fn tmpdir(name: &str) -> PathBuf {
    tmp_dir("e2e", name)
}

/// The pool row of the README's results table (`markhold hil --site params/pool.toml
/// --seconds 60 --seed 1`): the run equals its result file, and the summary carries what
/// the table and the speed figures read.
#[test]
fn pool_station_keeping_settles() {
    let s = readme_site_run("pool");
    let f = |k: &str| {
        s[k].as_f64()
            .unwrap_or_else(|| panic!("summary has no number {k}: {s}"))
    };
    assert!(f("final_yaw_error_deg") < 3.0, "{s}");
    assert!(f("detection_rate") > 0.999, "{s}");
    assert_eq!(s["frames"].as_u64(), Some(1800), "{s}");
    // The world's own time is part of the loop's: positive, and less than the whole.
    assert!(
        f("world_wall_seconds") > 0.0 && f("world_wall_seconds") < f("wall_seconds"),
        "{s}"
    );
    assert!(f("world_realtime_factor") > f("realtime_factor"), "{s}");
    for k in [
        "position_rms_m",
        "exposure_convergence_frames",
        "sim_seconds",
        "wall_seconds",
        "world_wall_seconds",
        "world_realtime_factor",
        "exposure_method",
        "lighting",
        "seed",
        "loop_latency_p99_ms",
        "render_loops",
    ] {
        assert!(s.get(k).is_some(), "summary lacks {k}: {s}");
    }
}

/// The summary of the README's results command for a shipped site
/// (`markhold hil --site params/SITE.toml --seconds 60 --seed 1`), which must equal, wall
/// clock aside, the result file the README's and docs/results.md's tables are generated
/// from (`docs/results/hil/SITE.json`; `tests/cli/cli_docs.rs` checks the tables).
fn readme_site_run(site: &str) -> serde_json::Value {
    let d = tmpdir(site);
    let path = repo(&format!("params/{site}.toml"));
    let s = run_summary(
        &[
            "hil",
            "--site",
            path.to_str().unwrap(),
            "--seconds",
            "60",
            "--seed",
            "1",
        ],
        &d.join("s.json"),
    );
    common::same_as_file(
        &repo(&format!("docs/results/hil/{site}.json")),
        &common::without_wall_clock(s.clone()),
        &format!("{site}: the 60 s run of seed 1"),
        "cargo test --release --test sim hil_e2e::",
    );
    s
}

#[test]
fn connecticut_river_as_the_readme_states() {
    readme_site_run("connecticut-river");
}

#[test]
fn night_harbor_as_the_readme_states() {
    readme_site_run("night-harbor");
}

#[test]
fn reef_caustics_as_the_readme_states() {
    readme_site_run("reef-caustics");
}

#[test]
fn same_seed_same_numbers() {
    let d = tmpdir("determinism");
    let pool = repo("params/pool.toml");
    let args = [
        "hil",
        "--site",
        pool.to_str().unwrap(),
        "--seconds",
        "4",
        "--seed",
        "7",
    ];
    let mut a = run_summary(&args, &d.join("a.json"));
    let mut b = run_summary(&args, &d.join("b.json"));
    // Wall-clock measurements are the only fields allowed to differ.
    for k in WALL_FIELDS {
        a.as_object_mut().unwrap().remove(k);
        b.as_object_mut().unwrap().remove(k);
    }
    assert_eq!(a, b);
}

fn bad_site(name: &str, text: &str) -> (i32, String) {
    let d = tmpdir("bad");
    let path = d.join(name);
    std::fs::write(&path, text).unwrap();
    let o = markhold()
        .args(["hil", "--quiet", "--seconds", "1", "--site"])
        .arg(&path)
        .output()
        .unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn pool_text() -> String {
    std::fs::read_to_string(repo("params/pool.toml")).unwrap()
}

#[test]
fn missing_site_file_is_named() {
    let o = markhold()
        .args(["hil", "--quiet", "--site", "/nonexistent/site.toml"])
        .output()
        .unwrap();
    let err = crate::common::stderr_of_exit(&o, 78);
    assert!(err.contains("/nonexistent/site.toml"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn unknown_key_is_named_with_file_and_line() {
    let text = pool_text().replacen("[marker]", "[marker]\ncolour = \"red\"", 1);
    let (code, err) = bad_site("unknown.toml", &text);
    assert_eq!(code, 78, "{err}");
    assert!(err.contains("unknown.toml"), "{err}");
    assert!(err.contains("colour"), "{err}");
    let line = text.lines().position(|l| l.starts_with("colour")).unwrap() + 1;
    assert!(
        err.contains(&format!(":{line}:")),
        "line {line} not in {err}"
    );
}

#[test]
fn wrong_type_is_named() {
    let text = pool_text().replacen("fps = 30.0", "fps = \"thirty\"", 1);
    assert_ne!(text, pool_text(), "pool.toml must set camera fps = 30.0");
    let (code, err) = bad_site("wrongtype.toml", &text);
    assert_eq!(code, 78, "{err}");
    assert!(
        err.contains("wrongtype.toml") && err.contains("fps"),
        "{err}"
    );
}

#[test]
fn out_of_range_value_is_named() {
    let text = pool_text().replacen("fps = 30.0", "fps = -5.0", 1);
    let (code, err) = bad_site("range.toml", &text);
    assert_eq!(code, 78, "{err}");
    assert!(err.contains("camera.fps") && err.contains("-5"), "{err}");
}

/// The summary fields the wall clock changes.
const WALL_FIELDS: [&str; 5] = [
    "wall_seconds",
    "realtime_factor",
    "world_wall_seconds",
    "world_realtime_factor",
    "loop_latency_p99_ms",
];

#[test]
fn render_loops_change_the_speed_not_the_run() {
    // `--render-loops portable` against the widest build this CPU runs: the same frames,
    // so the same run to the bit; the summary names the build that ran. (On a CPU
    // without AVX2 both are the portable loops and only the names are checked.)
    let d = tmpdir("render-loops");
    let pool = repo("params/pool.toml");
    let base = [
        "hil",
        "--site",
        pool.to_str().unwrap(),
        "--seconds",
        "3",
        "--seed",
        "5",
    ];
    let mut portable = base.to_vec();
    portable.extend(["--render-loops", "portable"]);
    let mut a = run_summary(&portable, &d.join("portable.json"));
    let mut b = run_summary(&base, &d.join("widest.json"));
    assert_eq!(a["render_loops"], "portable", "{a}");
    let widest = b["render_loops"].as_str().unwrap_or_default().to_string();
    assert!(
        ["portable", "avx2", "avx512"].contains(&widest.as_str()),
        "{b}"
    );
    for k in WALL_FIELDS.iter().chain(&["render_loops"]) {
        a.as_object_mut().unwrap().remove(*k);
        b.as_object_mut().unwrap().remove(*k);
    }
    assert_eq!(a, b, "portable vs {widest}");
}

#[test]
fn unknown_render_loops_are_named() {
    let pool = repo("params/pool.toml");
    let o = markhold()
        .args(["hil", "--site", pool.to_str().unwrap(), "--seconds", "0.1"])
        .args(["--render-loops", "neon"])
        .output()
        .expect("run markhold");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--render-loops") && err.contains("neon"),
        "{err}"
    );
    assert!(err.contains("portable, avx2, avx512"), "{err}");
}

/// A map whose other markers are never seen is the single marker of before: pool with
/// two more markers in its map, one behind the rock wall (inside the view, hidden by the
/// wall) and one far out of view, runs exactly as pool (the map's window for the hidden
/// marker is searched every frame and finds nothing, and the pose is the origin
/// marker's, bit for bit). Its exposure meters the origin marker only (`regions =
/// "single"`): by default it would also meter the wall where the map places the hidden
/// marker.
#[test]
fn a_map_whose_other_markers_are_not_seen_runs_as_its_origin_marker() {
    let d = tmpdir("map-of-one");
    let map = d.join("pool-map.toml");
    std::fs::write(
        &map,
        format!(
            "{}\n[[marker.map]]\nid = 5\nsize_m = 0.15\nposition_m = [0.3, 0.0, -0.5]\n\n\
             [[marker.map]]\nid = 6\nsize_m = 0.15\nposition_m = [40.0, 0.0, 0.0]\n\n\
             [exposure.aaec]\nregions = \"single\"\n",
            pool_text()
        ),
    )
    .unwrap();
    let run = |site: &Path, name: &str| {
        let args = [
            "hil",
            "--site",
            site.to_str().unwrap(),
            "--seconds",
            "3",
            "--seed",
            "2",
        ];
        let mut s = run_summary(&args, &d.join(name));
        for k in WALL_FIELDS {
            s.as_object_mut().unwrap().remove(k);
        }
        s
    };
    let a = run(&repo("params/pool.toml"), "pool.json");
    let b = run(&map, "map.json");
    assert!(a["detection_rate"].as_f64().unwrap() > 0.9, "{a}");
    assert_eq!(a, b);
}
