//! `markhold calibrate` through the built binary: OpenCV's ChArUco tutorial photographs
//! against their published calibration, the refusal of view sets that cannot fix the
//! focal length, the printed target as the detector reads it, and a HIL site with a
//! known lens calibrated, then mapped with that calibration.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::{look_at, repo, run_markhold as markhold, tmp_path};

use markhold_camera::FrameRecorder;
use markhold_exposure::Frame;
use markhold_vision::calibration::board::{read_image, BoardDetector, Target};
use markhold_vision::synth::{render_markers, SceneParams};
use markhold_vision::{marker_bitmap, CameraCalibration, MarkerFamily};
use nalgebra::{Isometry3, Vector3};
use opencv::{aruco, core, imgcodecs, prelude::*};

fn scratch(name: &str) -> PathBuf {
    tmp_path("calibrate", name)
}

fn ok(o: &Output) -> String {
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{out}\n{err}");
    out.into_owned()
}

fn json(path: &Path) -> serde_json::Value {
    crate::common::read_json(path)
}

const CHARUCO: &[&str] = &[
    "--target",
    "charuco",
    "--squares",
    "5x7",
    "--square-mm",
    "40",
    "--marker-mm",
    "20",
    "--family",
    "aruco_6x6_250",
];

/// OpenCV 4.6's own pipeline on the tutorial photographs, as its
/// `calibrate_camera_charuco` sample runs it: markers, a first calibration on their
/// corners, ChArUco corners interpolated through it, `calibrateCameraCharuco` (flags 0).
/// Returns (fx, fy, RMS).
fn opencv_reference() -> (f64, f64, f64) {
    let dict =
        aruco::get_predefined_dictionary(aruco::PREDEFINED_DICTIONARY_NAME::DICT_6X6_250).unwrap();
    let board = aruco::CharucoBoard::create(5, 7, 0.04, 0.02, &dict).unwrap();
    let markers_board = aruco::Board::create(&board.obj_points(), &dict, &board.ids()).unwrap();
    let mut params = aruco::DetectorParameters::create().unwrap();
    params.set_polygonal_approx_accuracy_rate(0.05);
    let (mut all_c, mut all_i, mut count) = (
        core::Vector::<core::Vector<core::Point2f>>::new(),
        core::Vector::<i32>::new(),
        core::Vector::<i32>::new(),
    );
    let mut per = Vec::new();
    for i in 0..4 {
        let path = repo(&format!("tests/fixtures/real/opencv-charuco/img_0{i}.jpg"));
        let img = imgcodecs::imread(&path, imgcodecs::IMREAD_COLOR).unwrap();
        let (mut c, mut ids, mut rej) = (
            core::Vector::<core::Vector<core::Point2f>>::new(),
            core::Vector::<i32>::new(),
            core::Vector::<core::Vector<core::Point2f>>::new(),
        );
        aruco::detect_markers(&img, &dict, &mut c, &mut ids, &params, &mut rej).unwrap();
        c.iter().for_each(|q| all_c.push(q));
        ids.iter().for_each(|q| all_i.push(q));
        count.push(ids.len() as i32);
        per.push((c, ids, img));
    }
    let size = core::Size::new(640, 480);
    let crit = core::TermCriteria::new(
        core::TermCriteria_COUNT + core::TermCriteria_EPS,
        30,
        f64::EPSILON,
    )
    .unwrap();
    let (mut k, mut d) = (core::Mat::default(), core::Mat::default());
    let (mut rv, mut tv) = (
        core::Vector::<core::Mat>::new(),
        core::Vector::<core::Mat>::new(),
    );
    aruco::calibrate_camera_aruco(
        &all_c,
        &all_i,
        &count,
        &markers_board,
        size,
        &mut k,
        &mut d,
        &mut rv,
        &mut tv,
        0,
        crit,
    )
    .unwrap();
    let (mut cc, mut ci) = (
        core::Vector::<core::Mat>::new(),
        core::Vector::<core::Mat>::new(),
    );
    for (c, ids, img) in &per {
        let (mut a, mut b) = (core::Mat::default(), core::Mat::default());
        aruco::interpolate_corners_charuco(c, ids, img, &board, &mut a, &mut b, &k, &d, 2).unwrap();
        cc.push(a);
        ci.push(b);
    }
    let (mut k2, mut d2) = (core::Mat::default(), core::Mat::default());
    let rms = aruco::calibrate_camera_charuco(
        &cc, &ci, &board, size, &mut k2, &mut d2, &mut rv, &mut tv, 0, crit,
    )
    .unwrap();
    let kk = k2.data_typed::<f64>().unwrap();
    (kk[0], kk[4], rms)
}

/// The four photographs of OpenCV's ChArUco tutorial (`tests/fixtures/real/
/// opencv-charuco/SOURCE`), calibrated as their published calibration was (plumb_bob,
/// fx and fy free). Four views of one board leave the focal length uncertain to about
/// 3 % (both here and for OpenCV): the published fx is checked against the stated
/// standard deviation, the whole pipeline against OpenCV's own on the same files to
/// 1 %, the reprojection RMS against the published one to 20 %.
#[test]
fn the_charuco_photographs_give_the_published_calibration() {
    let out = scratch("charuco.yaml");
    let sum = scratch("charuco.json");
    let dir = repo("tests/fixtures/real/opencv-charuco");
    let mut args = vec!["calibrate", "--frames", dir.to_str().unwrap()];
    args.extend_from_slice(CHARUCO);
    args.extend_from_slice(&[
        "--medium",
        "air",
        "--model",
        "plumb_bob",
        "--out",
        out.to_str().unwrap(),
        "--summary",
        sum.to_str().unwrap(),
    ]);
    let text = ok(&markhold(&args));
    let published = CameraCalibration::load(&dir.join("tutorial_camera_charuco.yml")).unwrap();
    let notes = CameraCalibration::load_notes(&dir.join("tutorial_camera_charuco.yml")).unwrap();
    let mine = CameraCalibration::load(&out).unwrap();
    let s = json(&sum);
    assert_eq!(s["views_used"], 4, "{text}");
    let rms = s["rms_px"].as_f64().unwrap();
    let published_rms = notes.reprojection_rms_px.unwrap();
    assert!(
        (rms / published_rms - 1.0).abs() < 0.2,
        "RMS {rms} px, published {published_rms} px\n{text}"
    );
    let sigma = |name: &str| {
        s["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p[0] == name)
            .unwrap()[2]
            .as_f64()
            .unwrap()
    };
    for (name, got, want) in [("fx", mine.fx, published.fx), ("fy", mine.fy, published.fy)] {
        assert!(
            (got - want).abs() < 2.0 * sigma(name),
            "{name} {got} +- {}, published {want}\n{text}",
            sigma(name)
        );
    }
    let (fx, fy, cv_rms) = opencv_reference();
    assert!(
        (mine.fx / fx - 1.0).abs() < 0.01,
        "fx {} vs OpenCV {fx}",
        mine.fx
    );
    assert!(
        (mine.fy / fy - 1.0).abs() < 0.01,
        "fy {} vs OpenCV {fy}",
        mine.fy
    );
    assert!(
        (rms / cv_rms - 1.0).abs() < 0.1,
        "RMS {rms} vs OpenCV {cv_rms}"
    );
    eprintln!(
        "fx {:.2} +- {:.2} (published {:.2}, OpenCV 4.6 on these files {fx:.2}); fy {:.2} \
         (published {:.2}, OpenCV {fy:.2}); RMS {rms:.4} px (published {published_rms:.4}, \
         OpenCV {cv_rms:.4})",
        mine.fx,
        sigma("fx"),
        published.fx,
        mine.fy,
        published.fy
    );
    // The coverage picture is written beside the file.
    let png = std::fs::read(out.with_extension("coverage.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG"));
}

/// A 4x3 AprilTag grid of 60 mm tags, 80 mm apart, rendered face-on from each camera
/// position (looking straight along -z) into a recorded-frames folder.
fn face_on_frames(dir: &Path, cams: &[Vector3<f64>]) {
    let calib = CameraCalibration {
        dist: vec![-0.1, 0.02, 0.0, 0.0, 0.0],
        ..CameraCalibration::pinhole(640, 480, 600.0, 600.0, 320.0, 240.0)
    };
    let grid = Target::aprilgrid(MarkerFamily::AprilTag36h11, 4, 3, 0.06, 1.0 / 3.0, 0);
    let Target::Markers { markers, .. } = &grid else {
        unreachable!()
    };
    let bitmaps: Vec<_> = markers
        .iter()
        .map(|m| marker_bitmap(MarkerFamily::AprilTag36h11, m.id).unwrap())
        .collect();
    let mut rec = FrameRecorder::create(dir).unwrap();
    let mut frame = Frame::new(640, 480);
    for (i, c) in cams.iter().enumerate() {
        let t_cam_site = look_at(*c, Vector3::new(c.x, c.y, 0.0));
        let drawn: Vec<_> = markers
            .iter()
            .zip(&bitmaps)
            .map(|(m, b)| {
                let at = Isometry3::translation(m.centre_m[0], m.centre_m[1], 0.0);
                (b, m.size_m, t_cam_site * at)
            })
            .collect();
        render_markers(&mut frame, &calib, &drawn, &SceneParams::default());
        frame.meta.seq = i as u64;
        frame.meta.stamp_s = i as f64;
        frame.meta.exposure_us = 1000.0;
        rec.write(&frame).unwrap();
    }
}

#[test]
fn one_view_and_face_on_views_are_refused_with_the_reason() {
    // One photograph.
    let one = scratch("one-view");
    std::fs::create_dir_all(&one).unwrap();
    std::fs::copy(
        repo("tests/fixtures/real/opencv-charuco/img_00.jpg"),
        one.join("img_00.jpg"),
    )
    .unwrap();
    let out = scratch("one.yaml");
    let mut args = vec!["calibrate", "--frames", one.to_str().unwrap()];
    args.extend_from_slice(CHARUCO);
    args.extend_from_slice(&["--medium", "air", "--out", out.to_str().unwrap()]);
    let o = markhold(&args);
    let err = crate::common::stderr_of_exit(&o, 2);
    assert!(
        err.contains("1 usable view") && err.contains("at least 3 views"),
        "{err}"
    );
    assert!(!out.exists());
    // Eight views of a grid, every one face-on (shifted and at several distances).
    let dir = scratch("face-on");
    let cams: Vec<Vector3<f64>> = (0..8)
        .map(|k| {
            let a = k as f64;
            Vector3::new(
                0.12 + 0.06 * a.sin(),
                -0.08 + 0.05 * a.cos(),
                0.35 + 0.03 * a,
            )
        })
        .collect();
    face_on_frames(&dir, &cams);
    let out = scratch("face-on.yaml");
    let o = markhold(&[
        "calibrate",
        "--frames",
        dir.to_str().unwrap(),
        "--target",
        "aprilgrid",
        "--tags",
        "4x3",
        "--tag-mm",
        "60",
        "--spacing",
        "0.3333333333",
        "--medium",
        "water",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(2), "{stdout}\n{err}");
    assert!(
        err.contains("face-on") && err.contains("tilt the target"),
        "{stdout}\n{err}"
    );
    assert!(!out.exists());
}

/// The printed ChArUco board, read back as a photograph of it face-on at 100 dpi:
/// every marker and every inner corner found where the layout puts it.
#[test]
fn the_printed_board_is_what_the_detector_expects() {
    let png = scratch("board.png");
    let mut args = vec!["calibrate", "--print-target", png.to_str().unwrap()];
    args.extend_from_slice(CHARUCO);
    args.extend_from_slice(&["--dpi", "100"]);
    let text = ok(&markhold(&args));
    assert!(text.contains("ChArUco 5x7"), "{text}");
    let frame = read_image(&png).unwrap();
    let target = Target::Charuco {
        squares_x: 5,
        squares_y: 7,
        square_m: 0.04,
        marker_m: 0.02,
        family: MarkerFamily::Aruco6x6_250,
    };
    let mut det = BoardDetector::new(&target).unwrap();
    let found = det.detect(&frame, None).unwrap();
    assert_eq!(found.markers, 17, "markers decoded");
    assert_eq!(found.points.len(), 24, "inner corners");
    // Pixel = (margin + board position) at 100 dpi (OpenCV's board coordinates run as
    // the page's: x right, y down), within a pixel: the printed edges sit on the nearest
    // pixel boundary (up to 0.5 px away) and cornerSubPix reads a binary saddle's
    // boundary up to half a pixel off. A layout wrong by a square is 157 px off.
    let ppm = 100.0 / 0.0254;
    let margin = markhold::tag::BOARD_MARGIN_MM / 1000.0;
    for (x, p) in &found.points {
        let u = (margin + x.x) * ppm;
        let v = (margin + x.y) * ppm;
        assert!(
            (p.x + 0.5 - u).abs() < 1.0 && (p.y + 0.5 - v).abs() < 1.0,
            "corner {x:?} at {p:?}, expected ({u}, {v})"
        );
    }
}

/// Needs the simulator (`markhold hil`).
#[cfg(feature = "sim")]
mod hil {
    use super::*;
    use crate::common::run_map;
    use markhold_vision::MarkerConfig;
    use nalgebra::Matrix3;

    /// The HIL site of the calibration test: `[camera]` of the pool fixture at 640x480 with
    /// a pincushion lens (as a flat port gives), the station and mount of one view, and
    /// `markers` as the map.
    fn hil_site(name: &str, view: [f64; 6], origin_size: f64, markers: &str) -> String {
        let base = std::fs::read_to_string(repo("tests/fixtures/pool-640-map4.toml")).unwrap();
        let head = &base[..base.find("# The station marker is the site frame").unwrap()];
        let [dist, lat, vert, yaw, pitch, roll] = view;
        head.replace("name = \"pool-640-map4\"", &format!("name = \"{name}\""))
            .replace(
                "size_m = 0.15             # edge",
                &format!("size_m = {origin_size} # edge"),
            )
            .replace(
                "cy_px = 240.0\n",
                &format!("cy_px = 240.0\ndistortion = {LENS}\n"),
            )
            .replace(
                "distance_m = 1.0          # hold 1 m in front of the marker, facing it",
                &format!(
                    "distance_m = {dist}\nlateral_m = {lat}\nvertical_m = {vert}\nyaw_deg = {yaw}"
                ),
            )
            .replace(
                "mount_rpy_deg = [0.0, 0.0, 0.0]      # looking straight ahead",
                &format!("mount_rpy_deg = [{roll}, {pitch}, 0.0]"),
            )
            + markers
    }

    /// The HIL camera's lens: pincushion (k1 k2 p1 p2 k3).
    const LENS: &str = "[0.12, 0.03, 0.0004, -0.0003, 0.0]";

    /// Run `markhold hil` on each site for `seconds` with snapshots every `every` frames,
    /// and gather the frames into one recorded-frames folder `dir`.
    fn hil_frames(dir: &Path, sites: &[String], seconds: f64, every: u64) {
        let mut rec = FrameRecorder::create(dir).unwrap();
        let mut n = 0u64;
        for (k, text) in sites.iter().enumerate() {
            let site = scratch(&format!(
                "{}-site-{k}.toml",
                dir.file_name().unwrap().to_string_lossy()
            ));
            std::fs::write(&site, text).unwrap();
            let snap = scratch(&format!(
                "{}-snap-{k}",
                dir.file_name().unwrap().to_string_lossy()
            ));
            ok(&markhold(&[
                "hil",
                "--quiet",
                "--seconds",
                &seconds.to_string(),
                "--seed",
                &k.to_string(),
                "--site",
                site.to_str().unwrap(),
                "--snapshot",
                snap.to_str().unwrap(),
                "--snapshot-every",
                &every.to_string(),
            ]));
            let mut cam = markhold_camera::RecordedCamera::open(&snap).unwrap();
            let mut frame = Frame::new(0, 0);
            while markhold_exposure::Camera::grab(&mut cam, &mut frame).is_ok() {
                frame.meta.seq = n;
                frame.meta.stamp_s = n as f64 / 30.0;
                rec.write(&frame).unwrap();
                n += 1;
            }
        }
    }

    /// A HIL site with a known pincushion lens: a 5x4 AprilTag grid filmed from eight
    /// stations and camera mounts is calibrated; a four-marker layout (three on one wall,
    /// one on a bracket) filmed from six is then mapped with that calibration, the site's
    /// poses zeroed. Every marker comes out within 3 mm, and the stated covariance covers
    /// the error: each marker within 3 sigma, the normalised squared error (NEES) of the
    /// markers near 1 (below 3).
    #[test]
    fn a_hil_site_calibrated_then_mapped_recovers_its_markers_with_honest_errors() {
        let calib = calibrate_the_hil_camera();
        map_with(&calib);
    }

    /// The HIL camera calibrated on a 5x4 AprilTag grid from eight views: the known lens
    /// recovered. Returns the calibration file.
    fn calibrate_the_hil_camera() -> PathBuf {
        // The grid: tag (i, j) at (0.11 i, -0.11 j) m from tag 0, the site's origin.
        let mut grid = String::new();
        for j in 0..4 {
            for i in 0..5 {
                if i + j > 0 {
                    grid += &format!(
                        "\n[[marker.map]]\nid = {}\nsize_m = 0.08\nposition_m = [{}, {}, 0.0]\n",
                        5 * j + i,
                        0.11 * i as f64,
                        -0.11 * j as f64
                    );
                }
            }
        }
        let views = [
            [0.7, 0.22, -0.165, 0.0, 0.0, 0.0],
            [0.6, 0.0, -0.1, 25.0, 0.0, 0.0],
            [0.6, 0.4, -0.1, -25.0, 0.0, 0.0],
            [0.55, 0.2, 0.1, 0.0, -20.0, 0.0],
            [0.55, 0.2, -0.35, 0.0, 20.0, 0.0],
            [0.8, 0.1, -0.2, 15.0, 10.0, 12.0],
            [0.9, 0.3, -0.1, -10.0, -8.0, -10.0],
            [0.5, 0.22, -0.165, 0.0, 0.0, 20.0],
        ];
        let sites: Vec<String> = views
            .iter()
            .enumerate()
            .map(|(k, v)| hil_site(&format!("grid-{k}"), *v, 0.08, &grid))
            .collect();
        let frames = scratch("grid-frames");
        hil_frames(&frames, &sites, 1.5, 9);
        let calib = scratch("hil-calib.yaml");
        let text = ok(&markhold(&[
            "calibrate",
            "--frames",
            frames.to_str().unwrap(),
            "--target",
            "aprilgrid",
            "--tags",
            "5x4",
            "--tag-mm",
            "80",
            "--spacing",
            "0.375",
            "--medium",
            "water",
            "--model",
            "plumb_bob",
            "--out",
            calib.to_str().unwrap(),
        ]));
        let c = CameraCalibration::load(&calib).unwrap();
        assert!((c.fx / 533.0 - 1.0).abs() < 0.002, "fx {}\n{text}", c.fx);
        assert!((c.dist[0] - 0.12).abs() < 0.005, "k1 {}\n{text}", c.dist[0]);
        calib
    }

    /// The pool fixture's four markers mapped with the calibration file `calib`, their
    /// poses zeroed: within 3 mm of the truth, each within 3 sigma, NEES below 3, the
    /// declared wall flat.
    fn map_with(calib: &Path) {
        // The layout of the pool fixture, the wall's three markers declared on one plane.
        let base = std::fs::read_to_string(repo("tests/fixtures/pool-640-map4.toml")).unwrap();
        let layout = &base[base.find("# The station marker is the site frame").unwrap()..];
        let map_views = [
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [0.9, -0.2, 0.1, 20.0, 0.0, 0.0],
            [0.9, 0.25, -0.1, -20.0, 0.0, 0.0],
            [1.2, 0.0, 0.2, 0.0, 12.0, 0.0],
            [1.1, 0.1, -0.2, 10.0, -10.0, 10.0],
            [1.3, -0.1, 0.0, -12.0, 5.0, -8.0],
        ];
        let sites: Vec<String> = map_views
            .iter()
            .enumerate()
            .map(|(k, v)| hil_site(&format!("map-{k}"), *v, 0.15, layout))
            .collect();
        let frames = scratch("map-frames");
        hil_frames(&frames, &sites, 2.0, 6);
        // The site `map` reads: the calibration file instead of the lens, poses zeroed.
        let zeroed: String = sites[0]
            .replace(
                &format!("distortion = {LENS}\n"),
                &format!(
                    "calibration_file = \"{}\"\ncalibration_source = \"in-water\"\n",
                    calib.display()
                ),
            )
            .lines()
            .map(|l| {
                if l.starts_with("position_m") {
                    "position_m = [0.0, 0.0, 0.0]\n".to_string()
                } else if l.starts_with("rpy_deg") {
                    "rpy_deg = [0.0, 0.0, 0.0]\n".to_string()
                } else if l.starts_with("id = 0")
                    || l.starts_with("id = 1")
                    || l.starts_with("id = 2")
                {
                    format!("{l}\nplane = \"wall\"\n")
                } else {
                    format!("{l}\n")
                }
            })
            .collect();
        let site = scratch("map-site.toml");
        std::fs::write(&site, zeroed).unwrap();
        let sum = scratch("map.json");
        let text = ok(&run_map(
            &site,
            "frames",
            &frames,
            &["--summary", sum.to_str().unwrap()],
        ));
        let s = json(&sum);
        let (errs, nees) = graded(&s, &base);
        for (id, e, sigma) in &errs {
            assert!(*e < 0.003, "marker {id}: {:.2} mm off\n{text}", e * 1e3);
            assert!(
                *e < 3.0 * sigma,
                "marker {id}: {:.3} mm off, 1-sigma {:.3} mm\n{text}",
                e * 1e3,
                sigma * 1e3
            );
            eprintln!(
                "marker {id}: error {:.3} mm, 1-sigma {:.3} mm (worst axis)",
                e * 1e3,
                sigma * 1e3
            );
        }
        eprintln!("NEES {nees:.2} over {} markers\n{text}", errs.len());
        assert!(nees < 3.0, "NEES {nees}\n{text}");
        let wall = &s["planes"][0];
        assert_eq!(wall["name"], "wall");
        assert!(wall["max_m"].as_f64().unwrap() < 0.001, "{wall}");
        focal_5_percent_long(calib, &site, &frames, &base);
    }

    /// The same frames mapped with the calibration's focal length 5 % too long: by
    /// default the map refines it back (within 0.5 %) and keeps every marker within 3 mm;
    /// with the intrinsics held, the wall's plane is reported and the stated 1-sigma never
    /// claims less than a third of the real error.
    fn focal_5_percent_long(calib: &Path, site: &Path, frames: &Path, base: &str) {
        let mut c = CameraCalibration::load(calib).unwrap();
        let truth_f = c.fx;
        c.fx *= 1.05;
        c.fy *= 1.05;
        let long = scratch("hil-calib-f105.yaml");
        let notes = CameraCalibration::load_notes(calib).unwrap();
        std::fs::write(&long, c.to_yaml(&notes, &[])).unwrap();
        let text = std::fs::read_to_string(site)
            .unwrap()
            .replace(&calib.display().to_string(), &long.display().to_string());
        let long_site = scratch("map-site-f105.toml");
        std::fs::write(&long_site, text).unwrap();
        for held in [false, true] {
            let sum = scratch(&format!("map-f105-{held}.json"));
            let mut args = vec!["--summary", sum.to_str().unwrap()];
            if held {
                args.extend(["--intrinsics", "fixed"]);
            }
            let out = ok(&run_map(&long_site, "frames", frames, &args));
            let s = json(&sum);
            let (errs, nees) = graded(&s, base);
            eprintln!("f 5 % long, intrinsics held {held}: {errs:?}, NEES {nees:.2}\n{out}");
            for (id, e, sigma) in &errs {
                assert!(
                    *e <= 3.0 * sigma,
                    "held {held}: marker {id}: {:.3} mm off, 1-sigma {:.3} mm\n{out}",
                    e * 1e3,
                    sigma * 1e3
                );
            }
            assert!(s["planes"][0]["max_m"].as_f64().is_some(), "{out}");
            assert!(out.contains("# plane \"wall\""), "{out}");
            if held {
                assert!(out.contains("held as given"), "{out}");
            } else {
                assert!(out.contains("# intrinsics: refined"), "{out}");
                let f = s["intrinsics_refined"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|r| r[0] == "f")
                    .unwrap_or_else(|| panic!("f not refined\n{out}"))[2]
                    .as_f64()
                    .unwrap();
                assert!(
                    (f / truth_f - 1.0).abs() < 0.005,
                    "f {f}, the calibration's {truth_f}\n{out}"
                );
                for (id, e, _) in &errs {
                    assert!(*e < 0.003, "marker {id}: {:.2} mm off\n{out}", e * 1e3);
                }
            }
        }
    }

    /// Each mapped marker's (id, position error, stated 1-sigma on its worst axis) against
    /// the pool fixture's layout (`base`: its text), and the markers' mean NEES (3 axes).
    fn graded(s: &serde_json::Value, base: &str) -> (Vec<(u32, f64, f64)>, f64) {
        let truth: MarkerConfig =
            markhold::params::parse(&repo("tests/fixtures/pool-640-map4.toml"), base)
                .unwrap()
                .site
                .marker;
        let mut nees = 0.0;
        let mut out = Vec::new();
        for m in s["markers"].as_array().unwrap().iter().skip(1) {
            let id = m["id"].as_u64().unwrap() as u32;
            let want = truth
                .markers()
                .find(|t| t.id == id)
                .unwrap()
                .t_site_marker
                .translation
                .vector;
            let p: Vec<f64> = m["position_m"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let e = Vector3::new(p[0], p[1], p[2]) - want;
            let cov = Matrix3::from_fn(|i, j| m["covariance"][i][j].as_f64().unwrap());
            nees += (e.transpose() * cov.try_inverse().unwrap() * e)[(0, 0)] / 3.0;
            out.push((id, e.norm(), m["sigma_position_m"].as_f64().unwrap()));
        }
        let n = out.len() as f64;
        (out, nees / n)
    }
}

/// `params check` says where a site's intrinsics come from: the stock site's are
/// placeholders, an in-air calibration is wrong under water, an in-water one (the
/// tutorial's file, made in air, declared in-water) contradicts its file.
#[test]
fn params_check_warns_about_placeholder_and_in_air_intrinsics() {
    let stock = ok(&markhold(&[
        "params",
        "check",
        repo("params/bluerov2-stock.toml").to_str().unwrap(),
    ]));
    assert!(
        stock.contains("# WARNING: the camera intrinsics are placeholders"),
        "{stock}"
    );
    let base = std::fs::read_to_string(repo("params/bluerov2-stock.toml")).unwrap();
    let in_air = scratch("in-air.toml");
    std::fs::write(
        &in_air,
        base.replace(
            "calibration_source = \"placeholder\"",
            "calibration_source = \"in-air\"",
        ),
    )
    .unwrap();
    let text = ok(&markhold(&["params", "check", in_air.to_str().unwrap()]));
    assert!(
        text.contains("# WARNING: the camera was calibrated in air"),
        "{text}"
    );
    // A calibration file written by `calibrate --medium air`, declared in-water.
    let cal = scratch("air.yaml");
    let mut args: Vec<String> = vec![
        "calibrate".into(),
        "--frames".into(),
        repo("tests/fixtures/real/opencv-charuco")
            .to_str()
            .unwrap()
            .to_owned(),
    ];
    args.extend(CHARUCO.iter().map(|s| (*s).to_owned()));
    args.extend(["--medium", "air", "--out", cal.to_str().unwrap()].map(str::to_owned));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&markhold(&args));
    let site = scratch("in-water.toml");
    std::fs::write(
        &site,
        base.replace(
            "calibration_source = \"placeholder\"",
            &format!(
                "calibration_source = \"in-water\"\ncalibration_file = \"{}\"",
                cal.display()
            ),
        )
        .replace("width_px = 1920", "width_px = 640")
        .replace("height_px = 1080", "height_px = 480"),
    )
    .unwrap();
    let o = markhold(&["params", "check", site.to_str().unwrap()]);
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        text.contains("says it was made in air, but camera.calibration_source says in-water"),
        "{text}"
    );
    assert!(!text.contains("placeholders"), "{text}");
}
