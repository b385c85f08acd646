//! Setpoint mode in HIL: the vehicle receives a vision estimate with its covariance every
//! frame and grades it against the true error (NEES of position and yaw). The shipped
//! covariance is consistent on the HIL's rendered frames (AAEC clips the marker's white,
//! and the covariance carries the clipped edges' shift: design/vision.md); the same run
//! with the covariance scaled by 1/100 is caught as inconsistent; on the full-size sites
//! the covariance follows the white's over-exposure; and while the station
//! marker of a map is occluded the estimates keep flowing from the other markers and the
//! station holds (the map's NEES is reported: design/autopilot.md, "NEES in HIL").
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use markhold::params::{self, LoadedSite};
use markhold::sim::hil::{run_hil, HilOptions, HilRun};
use markhold::sim::summary::VisionNeesSummary;
use markhold_autopilot::{CommandKind, LinkMode};
use markhold_geometry::stats::mean_bounds_95;
use markhold_hil::endpoint::VisionNees;

/// Frames per independent NEES draw. On station the error is mostly the clipped edges'
/// shift, which changes slowly with the vehicle's pose: the integrated autocorrelation
/// time of the per-frame NEES is 4-30 frames (pool-640, setpoint, 20 s, seeds 1-3:
/// 597 frames carry 20-170 independent draws), so a mean over `n` frames is held to the
/// 95 % bounds of `n / 30` independent chi-square draws.
const FRAMES_PER_DRAW: u64 = 30;

/// `site` in setpoint mode (GUIDED), its covariance sent times `scale`.
fn setpoint(mut site: LoadedSite, scale: f64) -> LoadedSite {
    site.site.link.command = CommandKind::Setpoint;
    site.site.link.mode = LinkMode::Guided;
    site.site.link.vision_covariance_scale = scale;
    site
}

/// The small test site in setpoint mode, its covariance sent times `scale`.
fn setpoint_run(scale: f64, seconds: f64, seed: u64) -> (u64, VisionNeesSummary) {
    setpoint_site_run(&common::site_path(), scale, seconds, seed)
}

/// Site `path` in setpoint mode, its covariance sent times `scale`.
fn setpoint_site_run(
    path: &std::path::Path,
    scale: f64,
    seconds: f64,
    seed: u64,
) -> (u64, VisionNeesSummary) {
    let site = setpoint(params::load(path).unwrap(), scale);
    let opts = HilOptions {
        seconds,
        seed,
        ..HilOptions::default()
    };
    let s = run_hil(&site, &opts, Default::default()).unwrap();
    let n = s.vision_nees.expect("setpoint mode reports vision_nees");
    println!(
        "{}, scale {scale}: {} of {} frames, position NEES mean {:.3} ({:.3} under 7.81), \
         yaw NEES mean {:.3} ({:.3} under 3.84), position RMS {:.4} m",
        path.display(),
        n.frames,
        s.frames,
        n.nees_pos_mean,
        n.nees_pos_inside_95,
        n.nees_yaw_mean,
        n.nees_yaw_inside_95,
        s.position_rms_m,
    );
    (s.frames, n)
}

/// Position (3 dof) and yaw (1 dof) NEES means of `frames` graded frames inside the 95 %
/// bounds of their means, frames correlated ([`FRAMES_PER_DRAW`]).
fn assert_consistent(what: &str, frames: u64, pos_mean: f64, yaw_mean: f64) {
    let draws = (frames / FRAMES_PER_DRAW).max(1);
    let (plo, phi) = mean_bounds_95(3.0, draws);
    let (ylo, yhi) = mean_bounds_95(1.0, draws);
    println!(
        "{what}: {frames} frames, position NEES mean {pos_mean:.3} (bounds {plo:.3}..{phi:.3}), \
         yaw {yaw_mean:.3} (bounds {ylo:.3}..{yhi:.3})"
    );
    assert!(
        (plo..=phi).contains(&pos_mean),
        "{what}: position NEES mean {pos_mean:.3} outside {plo:.3}..{phi:.3} ({frames} frames)"
    );
    assert!(
        (ylo..=yhi).contains(&yaw_mean),
        "{what}: yaw NEES mean {yaw_mean:.3} outside {ylo:.3}..{yhi:.3} ({frames} frames)"
    );
}

/// Not over-confident: each NEES mean of `frames` graded frames under the upper 95 %
/// bound of its mean (frames correlated, [`FRAMES_PER_DRAW`]). And not conservative by
/// more than [`CONSERVATIVE_LIMIT`] (each mean at least its dof over it); `yaw: false`
/// leaves the yaw's lower side out.
fn assert_not_overconfident(what: &str, frames: u64, pos_mean: f64, yaw_mean: f64, yaw: bool) {
    let draws = (frames / FRAMES_PER_DRAW).max(1);
    let (_, phi) = mean_bounds_95(3.0, draws);
    let (_, yhi) = mean_bounds_95(1.0, draws);
    println!(
        "{what}: {frames} frames, position NEES mean {pos_mean:.3} (upper bound {phi:.3}), \
         yaw {yaw_mean:.3} (upper bound {yhi:.3})"
    );
    assert!(
        pos_mean <= phi,
        "{what}: position NEES mean {pos_mean:.3} over {phi:.3}"
    );
    assert!(
        yaw_mean <= yhi,
        "{what}: yaw NEES mean {yaw_mean:.3} over {yhi:.3}"
    );
    assert!(
        pos_mean >= 3.0 / CONSERVATIVE_LIMIT,
        "{what}: position NEES mean {pos_mean:.3}: the covariance is far too large"
    );
    assert!(
        !yaw || yaw_mean >= 1.0 / CONSERVATIVE_LIMIT,
        "{what}: yaw NEES mean {yaw_mean:.3}: the covariance is far too large"
    );
}

/// How far under its dof a NEES mean may fall on the sites and maps where the
/// covariance is conservative (design/autopilot.md, "NEES in HIL").
const CONSERVATIVE_LIMIT: f64 = 8.0;

#[test]
fn setpoint_mode_vehicle_receives_a_consistent_covariance() {
    let (frames, n) = setpoint_run(1.0, 10.0, 3);
    // An estimate every frame the marker was seen, each compared with the truth.
    assert!(n.frames as f64 >= 0.95 * frames as f64, "{n:?}");
    assert_eq!((n.unmatched, n.without_covariance), (0, 0), "{n:?}");
    // The summary's bounds are the strict reading (independent frames).
    let (lo, hi) = (n.nees_pos_mean_bounds_95[0], n.nees_pos_mean_bounds_95[1]);
    assert!(lo < 3.0 && hi > 3.0 && hi - lo < 1.0, "{n:?}");
    assert_consistent("pool-640", n.frames, n.nees_pos_mean, n.nees_yaw_mean);

    // The same run told to trust vision 100x more: the vehicle sees the covariance it
    // was sent (every NEES 100x, to f32 rounding) and grades it inconsistent.
    let (_, tight) = setpoint_run(0.01, 10.0, 3);
    assert_eq!(tight.frames, n.frames);
    let ratio = tight.nees_pos_mean / n.nees_pos_mean;
    assert!((ratio - 100.0).abs() < 0.1, "position NEES ratio {ratio}");
    let ratio = tight.nees_yaw_mean / n.nees_yaw_mean;
    assert!((ratio - 100.0).abs() < 0.1, "yaw NEES ratio {ratio}");
    assert!(!tight.consistent(), "a 1/100 covariance passed: {tight:?}");
    let draws = tight.frames / FRAMES_PER_DRAW;
    assert!(
        tight.nees_pos_mean > mean_bounds_95(3.0, draws).1,
        "{tight:?}"
    );
}

/// The clipped edges' shift follows the white's over-exposure: at 1440x1080 in the pool
/// AAEC lands at the clip onset (the noise alone clips), in the river a lamp
/// over-exposes two of the marker's sides about 2x. A fixed shift was 13x too large in
/// the first (position NEES mean 0.08) and 10x too small in the second (32).
#[test]
fn the_covariance_follows_the_over_exposure_on_the_full_size_sites() {
    for site in ["params/pool.toml", "params/connecticut-river.toml"] {
        let (frames, n) = setpoint_site_run(&common::repo(site), 1.0, 10.0, 1);
        assert!(n.frames as f64 >= 0.95 * frames as f64, "{site}: {n:?}");
        assert_eq!((n.unmatched, n.without_covariance), (0, 0), "{site}: {n:?}");
        assert_not_overconfident(site, n.frames, n.nees_pos_mean, n.nees_yaw_mean, true);
    }
}

/// NEES means over the frames graded between two readings.
fn between(a: &VisionNees, b: &VisionNees) -> (u64, f64, f64) {
    let n = b.frames - a.frames;
    let m = n.max(1) as f64;
    (
        n,
        (b.pos_nees_sum - a.pos_nees_sum) / m,
        (b.yaw_nees_sum - a.yaw_nees_sum) / m,
    )
}

#[test]
fn occluding_the_station_marker_of_a_map_keeps_estimates_flowing_and_the_station() {
    // Four markers at 1 m; the station (origin) marker painted over from 6 s to 10 s:
    // the pose comes from the others meanwhile.
    let site = setpoint(
        params::load(&common::repo("tests/fixtures/pool-640-map4.toml")).unwrap(),
        1.0,
    );
    let (start_s, end_s, seconds) = (6.0, 10.0, 16.0);
    let opts = HilOptions {
        seconds,
        seed: 2,
        faults: vec![format!("occlude:0@{start_s}+{}", end_s - start_s)
            .parse()
            .unwrap()],
        ..HilOptions::default()
    };
    let station = site.t_world_marker() * site.site.station.t_marker_vehicle();
    let mut run = HilRun::build(&site, &opts, Default::default()).unwrap();
    run.arm(site.site.link.mode.ardusub()).unwrap();
    let fps = site.site.camera.fps;
    let frames = (seconds * fps).round() as u64;
    // Readings at 2 s (after the approach), at the occlusion's start and end, and last.
    let marks = [2.0, start_s, end_s, seconds];
    let mut readings = Vec::new();
    let (mut used_during, mut frames_during, mut last_error) = (0u64, 0u64, f64::NAN);
    for k in 0..frames {
        let t = k as f64 / fps;
        if marks.iter().any(|m| (m * fps).round() as u64 == k) {
            readings.push(run.vision_nees().unwrap());
        }
        let (rec, truth) = run.step().unwrap();
        if (start_s + 0.5..end_s).contains(&t) {
            frames_during += 1;
            used_during += u64::from(rec.markers_used);
            assert!(
                rec.markers_used <= 3,
                "the occluded marker was used at {t:.2} s"
            );
        }
        last_error = (truth.t_world_vehicle.translation.vector - station.translation.vector).norm();
    }
    let all = run.vision_nees().unwrap();
    readings.push(all);
    // Every estimate carries a covariance and is graded against the truth.
    assert_eq!((all.unmatched, all.without_covariance), (0, 0), "{all:?}");
    // Seen through the others meanwhile (two of the three are in view at the station),
    // an estimate on nearly every occluded frame.
    println!("{used_during} markers used over {frames_during} occluded frames");
    assert!(
        used_during as f64 >= 1.9 * frames_during as f64,
        "{used_during} markers used over {frames_during} occluded frames"
    );
    let phases = ["before", "during", "after"];
    for (i, what) in phases.iter().enumerate() {
        let (n, pos, yaw) = between(&readings[i], &readings[i + 1]);
        let want = if i == 1 { end_s - start_s } else { 3.5 };
        assert!(n as f64 >= 0.95 * want * fps, "{what}: {n} estimates");
        // Before, during (AAEC meters the two smaller markers left and clips harder)
        // and after: never over-confident. The yaw is conservative with a map (up to
        // 8x here: design/autopilot.md, "NEES in HIL"), so only its upper side is held.
        assert_not_overconfident(&format!("{what} the occlusion"), n, pos, yaw, false);
    }
    // The station holds: the vehicle ends within 5 cm of it (the bound tests/vision/dock_map.rs
    // holds an occluded map run to).
    println!("final position error {last_error:.4} m");
    assert!(last_error < 0.05, "final position error {last_error:.4} m");
}
