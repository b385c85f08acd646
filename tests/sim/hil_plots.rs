//! `markhold hil --plots DIR`: every file written and non-trivial, and the trajectory
//! plot's data where the run's summary says the vehicle ended.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)]

use crate::common;

use std::path::Path;

use common::{markhold, site_path, tmp_path};
use opencv::core::{Mat, Scalar};
use opencv::prelude::*;

/// The polylines of an SVG with this stroke colour, as pixel points, in document order.
fn polylines(svg: &str, stroke: &str) -> Vec<Vec<(f64, f64)>> {
    let needle = format!("stroke=\"{stroke}\"");
    svg.split("<polyline")
        .skip(1)
        .filter_map(|el| {
            let el = &el[..el.find("/>").unwrap()];
            if !el.contains(&needle) {
                return None;
            }
            let pts = attr(el, "points")?;
            Some(
                pts.split_whitespace()
                    .map(|p| {
                        let (x, y) = p.split_once(',').unwrap();
                        (x.parse().unwrap(), y.parse().unwrap())
                    })
                    .collect(),
            )
        })
        .collect()
}

/// The centres of the SVG circles filled with this colour.
fn circles(svg: &str, fill: &str) -> Vec<(f64, f64)> {
    let needle = format!("fill=\"{fill}\"");
    svg.split("<circle")
        .skip(1)
        .filter_map(|el| {
            let el = &el[..el.find("/>").unwrap()];
            el.contains(&needle).then(|| {
                (
                    attr(el, "cx").unwrap().parse().unwrap(),
                    attr(el, "cy").unwrap().parse().unwrap(),
                )
            })
        })
        .collect()
}

fn attr<'a>(el: &'a str, name: &str) -> Option<&'a str> {
    let start = el.find(&format!(" {name}=\""))? + name.len() + 3;
    let len = el[start..].find('"')?;
    Some(&el[start..start + len])
}

fn check_png(path: &Path, size: (i32, i32)) {
    let img =
        opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_GRAYSCALE)
            .unwrap();
    assert_eq!(
        (img.cols(), img.rows()),
        size,
        "{} has the wrong size",
        path.display()
    );
    let mut not_white = Mat::default();
    opencv::core::compare(
        &img,
        &Scalar::all(250.0),
        &mut not_white,
        opencv::core::CMP_LT,
    )
    .unwrap();
    let drawn = opencv::core::count_non_zero(&not_white).unwrap();
    let total = size.0 * size.1;
    assert!(
        drawn > total / 100 && drawn < total * 19 / 20,
        "{}: {drawn} of {total} pixels drawn",
        path.display()
    );
}

#[test]
fn plots_of_a_run_are_written_and_match_the_summary() {
    let dir = tmp_path("hil-plots", "plots");
    let _ = std::fs::remove_dir_all(&dir);
    let summary = tmp_path("hil-plots", "summary.json");
    common::run_ok(
        markhold()
            .args(["hil", "--quiet", "--seconds", "3", "--seed", "1", "--site"])
            .arg(site_path())
            .arg("--plots")
            .arg(&dir)
            .arg("--summary")
            .arg(&summary),
    );
    let s = common::read_json(&summary);
    let frames = s["frames"].as_u64().unwrap() as usize;

    for (stem, size) in [
        ("trajectory", (1200, 600)),
        ("exposure_metric", (900, 640)),
        ("detection_latency", (900, 640)),
    ] {
        check_png(&dir.join(format!("{stem}.png")), size);
        let svg = std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap();
        let lines = polylines(&svg, "#D62728");
        let long = lines.iter().filter(|l| l.len() >= frames / 2).count();
        assert!(
            long >= 2,
            "{stem}.svg: {long} series paths of at least {} points",
            frames / 2
        );
    }

    // The trajectory's last point against the station, through each view's own scale
    // (the marker plate's length and the station's distance from it).
    let site = markhold::params::load(&site_path()).unwrap();
    let st = &site.site.station;
    let half = 0.5 * site.site.marker.size_m;
    let svg = std::fs::read_to_string(dir.join("trajectory.svg")).unwrap();
    let plates = polylines(&svg, "#1F77B4");
    let stations = circles(&svg, "#2CA02C");
    let paths = polylines(&svg, "#D62728");
    assert_eq!((plates.len(), stations.len(), paths.len()), (2, 2, 2));
    let end = |i: usize| *paths[i].last().unwrap();

    // Top view: x right, range z up the page; the plate lies along x at z = 0.
    let (p0, p1) = (plates[0][0], plates[0][1]);
    assert_eq!(p0.1, p1.1, "the plate is horizontal in the top view");
    let sx = (p1.0 - p0.0) / (2.0 * half);
    let plate_x0 = 0.5 * (p0.0 + p1.0);
    let sz_top = (p0.1 - stations[0].1) / st.distance_m;
    assert!(
        ((stations[0].0 - plate_x0) / sx - st.lateral_m).abs() < 3.0 / sx,
        "station's x in the top view"
    );
    let (ex, ez) = end(0);
    let dx = (ex - stations[0].0) / sx;
    let dz = -(ez - stations[0].1) / sz_top;

    // Side view: range z to the right, height y up; the plate lies along y at z = 0.
    let (q0, q1) = (plates[1][0], plates[1][1]);
    assert_eq!(q0.0, q1.0, "the plate is vertical in the side view");
    let sy = (q0.1 - q1.1).abs() / (2.0 * half);
    let sz_side = (stations[1].0 - q0.0) / st.distance_m;
    let (fz, fy) = end(1);
    let dy = -(fy - stations[1].1) / sy;
    let dz_side = (fz - stations[1].0) / sz_side;

    let px = 3.0 / sx.min(sy).min(sz_top).min(sz_side);
    assert!(
        (dz - dz_side).abs() < px,
        "range error {dz} m (top) vs {dz_side} m (side)"
    );
    let err = (dx * dx + dy * dy + dz * dz).sqrt();
    let want = s["final_position_error_m"].as_f64().unwrap();
    assert!(
        (err - want).abs() < px,
        "trajectory ends {err:.4} m from the station, summary says {want:.4} m (tolerance {px:.4} m)"
    );
    assert!(want > px, "a run that ends off station makes this a test");
}

#[test]
fn plots_folder_that_cannot_be_made_is_named() {
    let file = tmp_path("hil-plots-bad", "a-file");
    std::fs::write(&file, "x").unwrap();
    let out = markhold()
        .args(["hil", "--quiet", "--seconds", "0.1", "--site"])
        .arg(site_path())
        .arg("--plots")
        .arg(file.join("sub"))
        .output()
        .unwrap();
    let err = common::stderr_of_exit(&out, 2);
    assert!(err.contains("--plots"), "{err}");
}
