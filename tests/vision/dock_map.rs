//! The dock-map site end to end: the HIL world draws every marker of the map, the pose
//! comes from every marker in view, and occluding one marker (by id) does not lose the
//! station where occluding the only marker of a site does. Reduced runs (CI time); the
//! full figures (60 s, seeds 1-5) are docs/results.md's command.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::path::{Path, PathBuf};

use common::{markhold, repo, tmp_dir};

/// Simulated seconds of the reduced runs.
const SECONDS: &str = "20";

fn tmpdir(name: &str) -> PathBuf {
    tmp_dir("dock", name)
}

/// dock-map.toml, and the same site reduced to its central (origin) marker.
fn sites(d: &Path) -> (PathBuf, PathBuf) {
    let full = repo("params/dock-map.toml");
    let text = std::fs::read_to_string(&full).unwrap();
    let mut central = String::new();
    let mut in_map = false;
    for line in text.lines() {
        if line.starts_with('[') {
            in_map = line.trim() == "[[marker.map]]";
        }
        if !in_map {
            central.push_str(line);
            central.push('\n');
        }
    }
    assert!(!central.contains("marker.map") && central.contains("[camera]"));
    let reduced = d.join("dock-central.toml");
    std::fs::write(&reduced, central).unwrap();
    (full, reduced)
}

fn hil(site: &Path, extra: &[&str], out: &Path) -> serde_json::Value {
    let args = [&["--seconds", SECONDS, "--seed", "1"], extra].concat();
    common::hil_summary(site, &args, out)
}

fn num(s: &serde_json::Value, k: &str) -> f64 {
    s[k].as_f64()
        .unwrap_or_else(|| panic!("summary has no number {k}: {s}"))
}

/// The trace's `markers` column (markers of the map in each frame's pose).
fn markers_per_frame(trace: &Path) -> Vec<u32> {
    let text = std::fs::read_to_string(trace).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "markers").unwrap();
    lines
        .map(|l| l.split(',').nth(col).unwrap().parse().unwrap())
        .collect()
}

/// Every marker in view: the start shows part of the map (the left column is outside
/// the view), the pose takes in every marker once the vehicle turns toward the panel;
/// detection in 99 % of the frames and more than one marker in the pose on average; the
/// same run (same seed) on the central marker alone uses one. The map's pose puts the
/// vehicle at most half as far from its true position (RMS) as the central marker's; the
/// station error, set by the current and the gusts, is only printed.
#[test]
fn the_map_puts_every_marker_in_view_into_the_pose() {
    let d = tmpdir("view");
    let (full, central) = sites(&d);
    let trace = d.join("map.csv");
    let map = hil(
        &full,
        &["--trace", trace.to_str().unwrap()],
        &d.join("map.json"),
    );
    let one = hil(&central, &[], &d.join("one.json"));
    let markers = markers_per_frame(&trace);
    assert!((1..5).contains(&markers[0]), "start: {:?}", &markers[..10]);
    assert_eq!(markers.iter().max(), Some(&5), "{markers:?}");
    assert!(num(&map, "detection_rate") >= 0.99, "{map}");
    assert!(num(&map, "markers_in_view_mean") > 1.0, "{map}");
    assert!(num(&one, "markers_in_view_mean") <= 1.0, "{one}");
    assert!(num(&map, "final_position_error_m") < 0.05, "{map}");
    let (pose_map, pose_one) = (
        num(&map, "pose_position_rms_m"),
        num(&one, "pose_position_rms_m"),
    );
    eprintln!(
        "pose position RMS: map {:.4} mm, central {:.4} mm ({:.3}x); station position RMS: \
         map {:.2} mm, central {:.2} mm",
        pose_map * 1e3,
        pose_one * 1e3,
        pose_map / pose_one,
        num(&map, "position_rms_m") * 1e3,
        num(&one, "position_rms_m") * 1e3,
    );
    assert!(pose_map > 0.0, "{map}");
    // docs/results.md: the map makes the pose 7-70 times more accurate (seeds 1-5, 60 s);
    // held here at its weakest, 7x (seed 1 on 20 s: 0.043).
    assert!(
        pose_map <= pose_one / 7.0,
        "map {pose_map} central {pose_one}"
    );
}

/// Occluding the origin marker (by id) for 5 s: on the map the pose continues from the
/// others (not a frame without a detection); on the central marker alone the detection
/// is lost in that window.
#[test]
fn occluding_one_marker_of_the_map_keeps_the_station() {
    let d = tmpdir("occlude");
    let (full, central) = sites(&d);
    let fault = ["--fault", "occlude:0@6+5"];
    let map = hil(&full, &fault, &d.join("map.json"));
    let one = hil(&central, &fault, &d.join("one.json"));
    let (rm, ro) = (&map["faults"][0], &one["faults"][0]);
    assert_eq!(rm["marker"], 0, "{rm}");
    assert!(
        rm["marker_missed_at_s"].is_null(),
        "map lost the station: {rm}"
    );
    assert!(num(&map, "detection_rate") >= 0.99, "{map}");
    let missed = ro["marker_missed_at_s"]
        .as_f64()
        .unwrap_or_else(|| panic!("the single marker was never missed: {ro}"));
    assert!((6.0..6.2).contains(&missed), "{ro}");
    // Alone, the marker is not seen again before the window ends.
    let again = ro["marker_detected_again_at_s"]
        .as_f64()
        .unwrap_or(f64::INFINITY);
    assert!(again >= 11.0, "{ro}");
    // The other markers of the map keep the vehicle on station through the window.
    assert!(num(&map, "final_position_error_m") < 0.05, "{map}");
}

/// An id that is not in the site's map is refused, naming the flag and the map's ids.
#[test]
fn occluding_a_marker_that_is_not_in_the_map_is_refused() {
    let d = tmpdir("bad-id");
    let o = markhold()
        .args([
            "hil",
            "--site",
            repo("params/dock-map.toml").to_str().unwrap(),
        ])
        .args(["--seconds", "1", "--quiet", "--fault", "occlude:9@0.5"])
        .arg("--summary")
        .arg(d.join("s.json"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("occlude:9") && err.contains("0, 1, 2, 3, 4"),
        "{err}"
    );
}
