//! AprilTag 3's own detector as the site's marker detector (`[marker] detector =
//! "apriltag3"`): it decodes the ids OpenCV's dictionaries draw, in OpenCV's corner order;
//! a site asking for it with a family it cannot decode is refused by name; and the HIL
//! pool holds station with it, through the same tracker, edge fit and loop as OpenCV's.
#![cfg(feature = "apriltag3")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use markhold_camera::Frame;
use markhold_vision::apriltag3::AprilTag3;
use markhold_vision::synth::{render_marker, SceneParams};
use markhold_vision::{marker_bitmap, CameraCalibration, MarkerFamily};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core;

/// For each AprilTag family both libraries know, markers drawn from OpenCV's dictionary
/// (first, second, a middle and the last id) are decoded by AprilTag 3 as the same id,
/// with its corners in OpenCV's order and pixel convention: within 0.5 px of the
/// renderer's exact corners (its coarse corners; the tracker refines them).
#[test]
fn apriltag3_decodes_opencvs_ids_in_opencvs_corner_order() {
    let calib = CameraCalibration::pinhole(640, 480, 600.0, 600.0, 319.5, 239.5);
    // Tilted, so a corner order mirrored or turned would not match.
    let pose = Isometry3::from_parts(
        Translation3::new(0.03, -0.02, 0.8),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_euler_angles(0.25, -0.3, 0.4),
    );
    let mut frame = Frame::new(640, 480);
    for family in [
        MarkerFamily::AprilTag36h11,
        MarkerFamily::AprilTag36h10,
        MarkerFamily::AprilTag25h9,
        MarkerFamily::AprilTag16h5,
    ] {
        let mut at = AprilTag3::new(family).unwrap();
        let n = family.id_count();
        for id in [0, 1, n / 2, n - 1] {
            let bm = marker_bitmap(family, id).unwrap();
            let truth = render_marker(
                &mut frame,
                &calib,
                &bm,
                0.15,
                &pose,
                &SceneParams::default(),
            )
            .map(|c| c.unwrap());
            let image =
                core::Mat::new_rows_cols_with_data::<u8>(480, 640, &frame.data[..640 * 480])
                    .unwrap();
            let mut found = Vec::new();
            at.detect(&image, |i, c| found.push((i, c))).unwrap();
            assert_eq!(found.len(), 1, "{family} id {id}: {found:?}");
            let (got, c) = found[0];
            assert_eq!(got, id, "{family}");
            for k in 0..4 {
                let d = (f64::from(c[k][0]) - truth[k][0]).hypot(f64::from(c[k][1]) - truth[k][1]);
                assert!(
                    d < 0.5,
                    "{family} id {id} corner {k}: {c:?} against {truth:?}"
                );
            }
        }
    }
}

/// A site asking for AprilTag 3 with a dictionary it does not decode exits 78 naming the
/// file, the line, the key, the value and what to use instead; an AprilTag family loads.
#[test]
fn apriltag3_for_an_aruco_dictionary_is_refused_by_name() {
    let text = std::fs::read_to_string(common::site_path()).unwrap();
    let with = |family: &str| {
        text.replace(
            "family = \"apriltag_36h11\" # AprilTag 36h11, or aruco_4x4_50 .. aruco_7x7_1000\n",
            &format!("family = \"{family}\"\ndetector = \"apriltag3\"\n"),
        )
    };
    let bad = common::tmp_path("apriltag3", "aruco.toml");
    std::fs::write(&bad, with("aruco_4x4_50")).unwrap();
    let o = common::run_markhold(&["params", "check", bad.to_str().unwrap()]);
    let err = crate::common::stderr_of_exit(&o, 78);
    let line = with("aruco_4x4_50")
        .lines()
        .position(|l| l.starts_with("detector"))
        .unwrap()
        + 1;
    assert!(
        err.contains(&format!("aruco.toml:{line}:"))
            && err.contains("marker.detector = \"apriltag3\"")
            && err.contains("\"opencv\" for aruco_4x4_50"),
        "{err}"
    );
    let good = common::tmp_path("apriltag3", "tag36h11.toml");
    std::fs::write(&good, with("apriltag_36h11")).unwrap();
    let o = common::run_markhold(&["params", "check", good.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// The pool site (1440x1080, AAEC) with AprilTag 3 finding the marker: the vehicle
/// settles on station and holds it as with OpenCV's detector (the same seed, the same
/// world; the figures are printed).
#[cfg(feature = "sim")]
#[test]
fn pool_holds_station_with_the_apriltag3_detector() {
    use markhold::params;
    use markhold::sim::hil::{run_hil, HilOptions};
    use markhold_vision::MarkerDetector;

    let opts = HilOptions {
        seconds: 20.0,
        seed: 1,
        ..HilOptions::default()
    };
    let run = |detector| {
        let mut site = params::load(&common::repo("params/pool.toml")).unwrap();
        site.site.marker.detector = detector;
        run_hil(&site, &opts, Default::default()).unwrap()
    };
    let april = run(MarkerDetector::AprilTag3);
    let cv = run(MarkerDetector::OpenCv);
    for (name, s) in [("apriltag3", &april), ("opencv", &cv)] {
        eprintln!(
            "{name}: detection rate {:.4}, position RMS {:.4} m, pose error RMS {:.5} m, \
             final error {:.4} m / {:.2} deg, loop latency p99 {:.2} ms",
            s.detection_rate,
            s.position_rms_m,
            s.pose_position_rms_m,
            s.final_position_error_m,
            s.final_yaw_error_deg,
            s.loop_latency_p99_ms,
        );
    }
    assert_eq!(april.frames, 600);
    assert!(april.detection_rate > 0.999, "{april:?}");
    assert!(april.final_position_error_m < 0.02, "{april:?}");
    assert!(april.final_yaw_error_deg < 3.0, "{april:?}");
    // Held as well as with OpenCV's detector: the corners are the same edge fit.
    assert!(
        april.position_rms_m < 1.25 * cv.position_rms_m + 0.002,
        "apriltag3 {} m, opencv {} m",
        april.position_rms_m,
        cv.position_rms_m
    );
    assert!(
        april.pose_position_rms_m < 2.0 * cv.pose_position_rms_m + 0.0005,
        "apriltag3 {} m, opencv {} m",
        april.pose_position_rms_m,
        cv.pose_position_rms_m
    );
}
