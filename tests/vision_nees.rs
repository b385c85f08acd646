//! Setpoint mode in HIL: the vehicle receives a vision estimate with its covariance every
//! frame and grades it against the true error (NEES of position and yaw against the
//! chi-square bounds of their means); the same run with the covariance scaled by 1/100
//! is caught as inconsistent. (With the shipped vision covariance the HIL's rendered
//! corners are not consistent either: design/autopilot.md, "NEES in HIL".)
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use markhold::params;
use markhold::sim::hil::{run_hil, HilOptions};
use markhold::sim::summary::VisionNeesSummary;
use markhold_autopilot::{CommandKind, LinkMode};

/// The small test site in setpoint mode (GUIDED), its covariance sent times `scale`.
fn setpoint_run(scale: f64, seconds: f64, seed: u64) -> (u64, VisionNeesSummary) {
    let mut site = params::load(&common::site_path()).unwrap();
    site.site.link.command = CommandKind::Setpoint;
    site.site.link.mode = LinkMode::Guided;
    site.site.link.vision_covariance_scale = scale;
    let opts = HilOptions {
        seconds,
        seed,
        ..HilOptions::default()
    };
    let s = run_hil(&site, &opts, Default::default()).unwrap();
    let n = s.vision_nees.expect("setpoint mode reports vision_nees");
    println!(
        "scale {scale}: {} of {} frames, position NEES mean {:.3} (bounds {:.3}..{:.3}, \
         {:.3} under 7.81), yaw NEES mean {:.3} (bounds {:.3}..{:.3}, {:.3} under 3.84), \
         position RMS {:.4} m",
        n.frames,
        s.frames,
        n.nees_pos_mean,
        n.nees_pos_mean_bounds_95[0],
        n.nees_pos_mean_bounds_95[1],
        n.nees_pos_inside_95,
        n.nees_yaw_mean,
        n.nees_yaw_mean_bounds_95[0],
        n.nees_yaw_mean_bounds_95[1],
        n.nees_yaw_inside_95,
        s.position_rms_m,
    );
    (s.frames, n)
}

#[test]
fn setpoint_mode_vehicle_receives_the_covariance_and_grades_it_against_the_truth() {
    let (frames, n) = setpoint_run(1.0, 10.0, 3);
    // An estimate every frame the marker was seen, each compared with the truth.
    assert!(n.frames as f64 >= 0.95 * frames as f64, "{n:?}");
    assert_eq!((n.unmatched, n.without_covariance), (0, 0), "{n:?}");
    // The bounds are the two-sided 95 % interval of the mean of n chi-square draws.
    let (lo, hi) = (n.nees_pos_mean_bounds_95[0], n.nees_pos_mean_bounds_95[1]);
    assert!(lo < 3.0 && hi > 3.0 && hi - lo < 1.0, "{n:?}");

    // The same run told to trust vision 100x more: the vehicle sees the covariance it
    // was sent (every NEES 100x, to f32 rounding) and grades it inconsistent.
    let (_, tight) = setpoint_run(0.01, 10.0, 3);
    assert_eq!(tight.frames, n.frames);
    let ratio = tight.nees_pos_mean / n.nees_pos_mean;
    assert!((ratio - 100.0).abs() < 0.1, "position NEES ratio {ratio}");
    let ratio = tight.nees_yaw_mean / n.nees_yaw_mean;
    assert!((ratio - 100.0).abs() < 0.1, "yaw NEES ratio {ratio}");
    assert!(!tight.consistent(), "a 1/100 covariance passed: {tight:?}");
    assert!(
        tight.nees_pos_mean > tight.nees_pos_mean_bounds_95[1],
        "{tight:?}"
    );
}
