//! `markhold params check`: every shipped site is valid; each kind of bad file exits 78
//! with a message that names the file, line, key and value. The messages are compared
//! with snapshots in tests/snapshots/params/ (refresh: UPDATE_SNAPSHOTS=1 cargo test).
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::Path;

use crate::common::{markhold, outcome, repo, tmp_dir, tmp_path};

fn check(path: &Path) -> (i32, String, String) {
    outcome(markhold().args(["params", "check"]).arg(path))
}

#[test]
fn every_shipped_site_is_valid() {
    let mut n = 0;
    for entry in std::fs::read_dir(repo("params")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let (code, out, err) = check(&path);
        assert_eq!(code, 0, "{}: {err}", path.display());
        // Defaults are filled in: sections the file leaves out are printed too.
        for section in ["[controller", "[vision]", "[exposure.aaec]", "[link]"] {
            assert!(
                out.contains(section),
                "{}: no {section} in\n{out}",
                path.display()
            );
        }
        n += 1;
    }
    assert!(n >= 4, "expected the four shipped sites, found {n}");
}

/// Apply `edit` to pool.toml, check it, and compare the message with its snapshot.
fn bad_case(name: &str, edit: impl Fn(&str) -> String) {
    let pool = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    let text = edit(&pool);
    assert_ne!(text, pool, "{name}: the edit changed nothing");
    let path = tmp_path("params", &format!("{name}.toml"));
    let dir = path.parent().unwrap();
    std::fs::write(&path, &text).unwrap();
    let (code, _, err) = check(&path);
    assert_eq!(code, 78, "{name}: {err}");
    assert!(!err.contains("panicked"), "{name}: {err}");
    // The temp dir differs per run: the snapshot holds the message after the file name.
    let msg = err.replace(&dir.display().to_string(), "<dir>");
    snapshot(name, &msg);
}

fn snapshot(name: &str, actual: &str) {
    let path = repo(&format!("tests/snapshots/params/{name}.txt"));
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        std::fs::write(&path, actual).unwrap();
        return;
    }
    let expected = std::fs::read_to_string(&path).unwrap_or_else(|_| {
        panic!(
            "no snapshot {}: run with UPDATE_SNAPSHOTS=1",
            path.display()
        )
    });
    assert_eq!(
        actual, expected,
        "message of {name} changed (UPDATE_SNAPSHOTS=1 to accept)"
    );
}

/// `bad_case` for the example site with the first `from` replaced by `to`.
fn bad_replacement(name: &str, from: &str, to: &str) {
    bad_case(name, |t| t.replacen(from, to, 1));
}

#[test]
fn unknown_key() {
    bad_replacement("unknown_key", "[marker]\n", "[marker]\ncolour = \"red\"\n");
}

#[test]
fn wrong_type() {
    bad_replacement("wrong_type", "fps = 30.0", "fps = \"thirty\"");
}

#[test]
fn out_of_range() {
    bad_replacement(
        "out_of_range",
        "exposure_max_us = 30000.0",
        "exposure_max_us = 5.0",
    );
}

#[test]
fn unknown_method() {
    bad_replacement("unknown_method", "method = \"aaec\"", "method = \"magic\"");
}

#[test]
fn unknown_marker_family() {
    bad_replacement("unknown_family", "apriltag_36h11", "qr_code");
}

#[test]
fn crate_section_out_of_range() {
    bad_replacement("station_distance", "distance_m = 1.0", "distance_m = -1.0");
}

#[test]
fn missing_section() {
    bad_case("missing_camera", |t| {
        let start = t.find("[camera]").unwrap();
        let end = t.find("[exposure]").unwrap();
        format!("{}{}", &t[..start], &t[end..])
    });
}

#[test]
fn missing_calibration_file() {
    bad_case("missing_calibration", |t| {
        t.replacen(
            "[camera]\n",
            "[camera]\ncalibration_file = \"no-such-calib.yaml\"\n",
            1,
        )
    });
}

#[test]
fn missing_file() {
    let (code, _, err) = check(Path::new("/nonexistent/dir/site.toml"));
    assert_eq!(code, 78, "{err}");
    assert!(err.contains("/nonexistent/dir/site.toml"), "{err}");
}

/// `params check` prints what a run uses: with a calibration file, its intrinsics and
/// distortion, not the inline ones or their defaults.
#[test]
fn effective_values_come_from_the_calibration_file() {
    let dir = tmp_dir("params", "cal");
    std::fs::write(
        dir.join("ost.yaml"),
        "image_width: 1440\nimage_height: 1080\ncamera_name: cam\ncamera_matrix:\n  rows: 3\n  \
         cols: 3\n  data: [1195.2, 0, 716.5, 0, 1197.9, 541.25, 0, 0, 1]\n\
         distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  \
         data: [-0.21, 0.07, 0.001, -0.002, 0.0]\n",
    )
    .unwrap();
    let pool = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    let site = dir.join("site.toml");
    std::fs::write(
        &site,
        pool.replacen(
            "[camera]\n",
            "[camera]\ncalibration_file = \"ost.yaml\"\n",
            1,
        ),
    )
    .unwrap();
    let (code, out, err) = check(&site);
    assert_eq!(code, 0, "{err}");
    for line in [
        "fx_px = 1195.2",
        "fy_px = 1197.9",
        "cx_px = 716.5",
        "cy_px = 541.25",
        "-0.21,",
        "ost.yaml (5 coefficients)",
    ] {
        assert!(out.contains(line), "no `{line}` in\n{out}");
    }
    assert!(!out.contains("fx_px = 1200.0"), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Errors point at the value's line and column, also inside an inline table.
#[test]
fn an_error_names_line_and_column_inside_an_inline_table() {
    let dir = tmp_dir("params", "col");
    let pool = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    let text = pool.replacen(
        "[camera]\n",
        "[camera]\nsensor = { full_well_e = 9000.0, read_noise_e = -1.0 }\n",
        1,
    );
    let line = text
        .lines()
        .position(|l| l.starts_with("sensor = {"))
        .unwrap()
        + 1;
    let column = "sensor = { full_well_e = 9000.0, read_noise_e = ".len() + 1;
    let path = dir.join("inline.toml");
    std::fs::write(&path, &text).unwrap();
    let (code, _, err) = check(&path);
    assert_eq!(code, 78, "{err}");
    let place = format!(
        "{}:{line}:{column}: camera.sensor.read_noise_e = -1",
        path.display()
    );
    assert!(err.contains(&place), "expected `{place}` in {err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn camera_response_polynomial_not_positive() {
    // g'(I) = 0.01 - 1e-4 I is negative above level 100.
    bad_case("response_polynomial", |t| {
        t.replacen(
            "[camera]\n",
            "[camera]\nresponse = { model = \"polynomial\", coefficients = [0.01, -1e-4] }\n",
            1,
        )
    });
}

#[test]
fn camera_response_under_exposure_is_named() {
    bad_case("response_under_exposure", |t| {
        t.replacen(
            "[exposure]\n",
            "[exposure]\nresponse = { model = \"gamma\", gamma = 2.2 }\n",
            1,
        )
    });
}

/// Pool with a marker map (two markers beside the origin) appended.
fn with_map(pool: &str, second_id: u32, second_rpy: &str) -> String {
    format!(
        "{pool}\n[[marker.map]]\nid = 1\nsize_m = 0.15\nposition_m = [0.4, 0.0, 0.0]\n\n\
         [[marker.map]]\nid = {second_id}\nsize_m = 0.1\nposition_m = [-0.4, 0.1, 0.0]\n\
         rpy_deg = {second_rpy}\n"
    )
}

#[test]
fn marker_map_with_a_repeated_id() {
    bad_case("map_duplicate_id", |t| with_map(t, 1, "[0.0, 0.0, 0.0]"));
}

#[test]
fn marker_map_with_a_bad_pose() {
    bad_case("map_bad_pose", |t| with_map(t, 2, "[0.0, 0.0, 270.0]"));
}

#[test]
fn params_check_lists_the_marker_map() {
    let dir = tmp_dir("params", "map");
    let pool = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    let path = dir.join("map.toml");
    std::fs::write(&path, with_map(&pool, 2, "[0.0, 30.0, 0.0]")).unwrap();
    let (code, out, err) = check(&path);
    assert_eq!(code, 0, "{err}");
    for line in [
        "# marker map: 3 markers of apriltag_36h11",
        "#   id    0  size 0.150 m  origin",
        "#   id    1  size 0.150 m  at (0.400, 0.000, 0.000) m  rpy (0.0, 0.0, 0.0) deg",
        "#   id    2  size 0.100 m  at (-0.400, 0.100, 0.000) m  rpy (0.0, 30.0, 0.0) deg",
    ] {
        assert!(out.contains(line), "no `{line}` in\n{out}");
    }
    assert_eq!(out.matches("[[marker.map]]").count(), 2, "{out}");
    // A map of one lists no map.
    let (_, out, _) = check(&repo("params/pool.toml"));
    assert!(
        !out.contains("marker map") && !out.contains("marker.map"),
        "{out}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
