#![allow(clippy::unwrap_used)]

use super::*;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::{calib3d, core, prelude::*};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn truth(model: DistortionModel) -> CameraCalibration {
    let dist = match model {
        DistortionModel::PlumbBob => vec![-0.21, 0.08, 0.0007, -0.0004, -0.012],
        DistortionModel::Rational => vec![0.4, 0.1, 0.0005, -0.0003, 0.002, 0.55, 0.05, 0.001],
        DistortionModel::Equidistant => vec![0.03, -0.01, 0.002, -0.0005],
    };
    CameraCalibration {
        width: 1280,
        height: 960,
        fx: 1010.0,
        fy: 1013.0,
        cx: 652.0,
        cy: 471.0,
        dist,
        model,
    }
}

/// A 9x7 grid of 40 mm.
fn board() -> Vec<Point3<f64>> {
    let mut v = Vec::new();
    for j in 0..7 {
        for i in 0..9 {
            v.push(Point3::new(i as f64 * 0.04, j as f64 * 0.04, 0.0));
        }
    }
    v
}

/// The board seen at `d` metres, turned by `(rx, ry, rz)` radians, shifted by
/// `(sx, sy)` metres, with Gaussian noise of `sigma` px; corners outside the image dropped.
fn view(
    c: &CameraCalibration,
    rot: (f64, f64, f64),
    shift: (f64, f64),
    d: f64,
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> (View, Isometry3<f64>) {
    let centre = Vector3::new(0.16, 0.12, 0.0);
    let r = UnitQuaternion::from_euler_angles(rot.0, rot.1, rot.2);
    let t = Vector3::new(shift.0, shift.1, d) - r * centre;
    let pose = Isometry3::from_parts(Translation3::from(t), r);
    let mut pts = Vec::new();
    for x in board() {
        let Some(uv) = c.project(&(pose * x)) else {
            continue;
        };
        if uv.x < 0.0 || uv.y < 0.0 || uv.x >= c.width as f64 || uv.y >= c.height as f64 {
            continue;
        }
        let n = Vector2::new(gauss(rng) * sigma, gauss(rng) * sigma);
        pts.push((x, uv + n));
    }
    (View::new(format!("{rot:?}"), pts), pose)
}

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    // Box-Muller.
    let u: f64 = rng.random_range(1e-12..1.0);
    let v: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
}

/// 16 views over the image, tilted up to 35 degrees, 0.45 to 0.8 m away.
fn views(c: &CameraCalibration, sigma: f64, seed: u64) -> Vec<View> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::new();
    for k in 0..16 {
        let a = k as f64 * 0.39;
        let rot = (0.6 * a.sin(), 0.6 * a.cos(), 0.2 * (2.0 * a).sin());
        let shift = (0.12 * (1.7 * a).cos(), 0.09 * (1.3 * a).sin());
        let d = 0.45 + 0.35 * (k % 4) as f64 / 3.0;
        out.push(view(c, rot, shift, d, sigma, &mut rng).0);
    }
    out
}

fn settings(model: DistortionModel) -> CalibrationSettings {
    CalibrationSettings {
        model,
        ..CalibrationSettings::default()
    }
}

#[test]
fn recovers_each_model_from_noisy_views() {
    for model in DistortionModel::all() {
        let t = truth(model);
        let cal = calibrate(views(&t, 0.1, 7), t.width, t.height, &settings(model)).unwrap();
        let c = &cal.calib;
        assert!(
            (c.fx - t.fx).abs() < 1.5 && (c.fy - t.fy).abs() < 1.5,
            "{model}: {c:?}"
        );
        assert!(
            (c.cx - t.cx).abs() < 1.5 && (c.cy - t.cy).abs() < 1.5,
            "{model}: {c:?}"
        );
        // Every free parameter within 4 of its stated standard deviations of the truth.
        for (name, value, sigma) in &cal.parameters {
            let truth_value = match name.as_str() {
                "fx" => t.fx,
                "fy" => t.fy,
                "cx" => t.cx,
                "cy" => t.cy,
                k => {
                    let i = model
                        .coefficient_names()
                        .iter()
                        .position(|n| n == &k)
                        .unwrap();
                    t.dist[i]
                }
            };
            assert!(
                (value - truth_value).abs() < 4.0 * sigma,
                "{model} {name}: {value} +- {sigma}, truth {truth_value}"
            );
        }
        assert!(
            cal.coverage.radius_fraction > 0.7,
            "{model}: {:?}",
            cal.coverage
        );
        // 0.1 px per axis: 0.141 px per corner.
        assert!(
            (cal.rms_px - 0.141).abs() < 0.01,
            "{model}: rms {}",
            cal.rms_px
        );
        assert_eq!(cal.views_used, 16);
    }
}

#[test]
fn agrees_with_opencv_calibrate_camera() {
    let t = truth(DistortionModel::PlumbBob);
    let vs = views(&t, 0.2, 11);
    let cal = calibrate(
        vs.clone(),
        t.width,
        t.height,
        &settings(DistortionModel::PlumbBob),
    )
    .unwrap();
    let mut obj = core::Vector::<core::Vector<core::Point3f>>::new();
    let mut img = core::Vector::<core::Vector<core::Point2f>>::new();
    for v in &vs {
        obj.push(
            v.points
                .iter()
                .map(|(x, _)| core::Point3f::new(x.x as f32, x.y as f32, 0.0))
                .collect(),
        );
        img.push(
            v.points
                .iter()
                .map(|(_, m)| core::Point2f::new(m.x as f32, m.y as f32))
                .collect(),
        );
    }
    let mut k = core::Mat::default();
    let mut d = core::Mat::default();
    let (mut rv, mut tv) = (
        core::Vector::<core::Mat>::new(),
        core::Vector::<core::Mat>::new(),
    );
    let rms = calib3d::calibrate_camera(
        &obj,
        &img,
        core::Size::new(t.width as i32, t.height as i32),
        &mut k,
        &mut d,
        &mut rv,
        &mut tv,
        0,
        core::TermCriteria::new(
            core::TermCriteria_COUNT + core::TermCriteria_EPS,
            100,
            1e-12,
        )
        .unwrap(),
    )
    .unwrap();
    let fx = *k.at_2d::<f64>(0, 0).unwrap();
    let fy = *k.at_2d::<f64>(1, 1).unwrap();
    let cx = *k.at_2d::<f64>(0, 2).unwrap();
    assert!(
        (cal.calib.fx - fx).abs() < 0.05,
        "{} vs OpenCV {fx}",
        cal.calib.fx
    );
    assert!(
        (cal.calib.fy - fy).abs() < 0.05,
        "{} vs OpenCV {fy}",
        cal.calib.fy
    );
    assert!(
        (cal.calib.cx - cx).abs() < 0.05,
        "{} vs OpenCV {cx}",
        cal.calib.cx
    );
    // Image points are f32 for OpenCV: the RMS agrees to its rounding.
    assert!(
        (cal.rms_px - rms).abs() < 1e-3,
        "{} vs OpenCV {rms}",
        cal.rms_px
    );
}

/// The plumb-bob calibration refuses `vs` with a message that holds every one of `words`.
fn assert_refused_saying(vs: Vec<View>, t: &CameraCalibration, words: [&str; 2]) {
    let e = calibrate(vs, t.width, t.height, &settings(DistortionModel::PlumbBob))
        .unwrap_err()
        .to_string();
    assert!(words.iter().all(|w| e.contains(w)), "{e}");
}

#[test]
fn one_view_is_refused_with_the_reason() {
    let t = truth(DistortionModel::PlumbBob);
    let mut vs = views(&t, 0.1, 3);
    vs.truncate(1);
    assert_refused_saying(vs, &t, ["1 usable view", "at least 3 views"]);
}

#[test]
fn face_on_views_are_refused_with_the_reason() {
    let t = truth(DistortionModel::PlumbBob);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let vs: Vec<View> = (0..8)
        .map(|k| {
            let a = k as f64;
            // Turned only about the optical axis, shifted and at several distances.
            view(
                &t,
                (0.0, 0.0, 0.3 * a),
                (0.1 * a.sin(), 0.08 * a.cos()),
                0.5 + 0.05 * a,
                0.1,
                &mut rng,
            )
            .0
        })
        .collect();
    assert_refused_saying(vs, &t, ["face-on", "tilt the target"]);
}

#[test]
fn a_bad_view_and_a_bad_corner_are_left_out() {
    let t = truth(DistortionModel::PlumbBob);
    let mut vs = views(&t, 0.1, 9);
    // View 3: every corner 2 px off at random (a blurred, mis-found view).
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for p in &mut vs[3].points {
        p.1 += Vector2::new(gauss(&mut rng) * 2.0, gauss(&mut rng) * 2.0);
    }
    // View 5: one corner 6 px off.
    vs[5].points[10].1.x += 6.0;
    let cal = calibrate(vs, t.width, t.height, &settings(DistortionModel::PlumbBob)).unwrap();
    assert!(cal.views[3].rejected.is_some(), "{:?}", cal.views[3]);
    assert!(cal.views[5].rejected.is_none());
    assert_eq!(cal.views[5].points_used, cal.views[5].points - 1);
    assert!((cal.calib.fx - t.fx).abs() < 1.5, "{}", cal.calib.fx);
    assert!(cal.rms_px < 0.15, "{}", cal.rms_px);
}

#[test]
fn coverage_counts_the_cells_reached() {
    let c = Coverage::of(
        800,
        600,
        [
            Vector2::new(10.0, 10.0),
            Vector2::new(790.0, 590.0),
            Vector2::new(-5.0, 3.0),
        ],
    );
    assert_eq!(c.counts.iter().sum::<u32>(), 2);
    assert!((c.cells_fraction - 2.0 / 48.0).abs() < 1e-12);
    assert!(c.radius_fraction > 0.97);
    assert_eq!(c.empty_cells().len(), 46);
    let png = coverage::picture(&c, &[(true, vec![Vector2::new(10.0, 10.0)])], "x").unwrap();
    assert!(png.starts_with(b"\x89PNG"));
}

/// A camera behind a flat port: an ideal pinhole in air (`f_air` px, 1280x960) whose
/// centre of projection is `gap` metres behind a thin flat port into water (n = 1.333).
/// The pixel of a point in water, camera frame (`None`: past the critical angle).
fn flat_port(f_air: f64, gap: f64, p: &Vector3<f64>) -> Option<Vector2<f64>> {
    const N: f64 = 1.333;
    let rho = p.x.hypot(p.y);
    if p.z <= gap {
        return None;
    }
    // rho = gap tan(a) + (z - gap) tan(w), sin(a) = n sin(w): solve for w by bisection.
    let reach = |w: f64| {
        let a = (N * w.sin()).asin();
        gap * a.tan() + (p.z - gap) * w.tan()
    };
    let (mut lo, mut hi) = (0.0, (1.0 / N).asin() - 1e-9);
    if reach(hi) < rho {
        return None;
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if reach(mid) < rho {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let r_air = (N * (0.5 * (lo + hi)).sin()).asin().tan();
    let s = if rho > 0.0 { r_air / rho } else { 0.0 };
    Some(Vector2::new(
        640.0 + f_air * s * p.x,
        480.0 + f_air * s * p.y,
    ))
}

/// Views of a 9x7 board of 0.1 m squares through the port, `d` metres away, tilted up
/// to 35 degrees, with `sigma` px of noise; and their poses. The board and the shifts
/// are scaled by `d / 0.9` so that every distance sees the same part of the image.
fn port_views(f_air: f64, gap: f64, d: [f64; 2], sigma: f64) -> (Vec<View>, Vec<Isometry3<f64>>) {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (mut out, mut poses) = (Vec::new(), Vec::new());
    for k in 0..16 {
        let a = k as f64 * 0.39;
        let r = UnitQuaternion::from_euler_angles(0.6 * a.sin(), 0.6 * a.cos(), 0.2 * a.sin());
        let dist = d[0] + (d[1] - d[0]) * (k % 4) as f64 / 3.0;
        let s = dist / 0.9;
        let shift = Vector3::new(0.3 * s * (1.7 * a).cos(), 0.22 * s * (1.3 * a).sin(), dist);
        let pose = Isometry3::from_parts(
            Translation3::from(shift - r * Vector3::new(0.4 * s, 0.3 * s, 0.0)),
            r,
        );
        let mut pts = Vec::new();
        for j in 0..7 {
            for i in 0..9 {
                let x = Point3::new(i as f64 * 0.1 * s, j as f64 * 0.1 * s, 0.0);
                let Some(uv) = flat_port(f_air, gap, &(pose * x).coords) else {
                    continue;
                };
                if uv.x < 0.0 || uv.y < 0.0 || uv.x >= 1280.0 || uv.y >= 960.0 {
                    continue;
                }
                pts.push((
                    x,
                    uv + Vector2::new(gauss(&mut rng), gauss(&mut rng)) * sigma,
                ));
            }
        }
        out.push(View::new(format!("port {k}"), pts));
        poses.push(pose);
    }
    (out, poses)
}

/// How well the calibration `c` serves a pose at `d` metres: the RMS error of the
/// board's corners (noiseless) after each view's pose is fitted with `c` held, pixels.
fn port_pose_rms(c: &CameraCalibration, f_air: f64, gap: f64, d: f64) -> f64 {
    let (vs, poses) = port_views(f_air, gap, [d, d], 0.0);
    let (vs, poses): (Vec<View>, Vec<_>) = vs
        .into_iter()
        .zip(poses)
        .filter(|(v, _)| v.points.len() >= 8)
        .unzip();
    solve::solve(c.clone(), poses, &vs, &[], 50).map_or(f64::NAN, |s| s.rms_px)
}

/// Behind a flat port (an 80 degree field of view in water, as the BlueROV2's camera),
/// the rational model follows the refraction where plumb_bob leaves a residual; with an
/// air gap the fit holds near the calibrated distances only. The figures are printed
/// (`cargo test --release -p markhold-vision --lib flat_port -- --nocapture`).
#[test]
fn a_flat_port_is_followed_by_the_rational_model_near_the_calibrated_distance() {
    let f_air = 384.6;
    let mut rows = Vec::new();
    for (gap, model) in [
        (0.0, DistortionModel::PlumbBob),
        (0.0, DistortionModel::Rational),
        (0.02, DistortionModel::PlumbBob),
    ] {
        let (vs, _) = port_views(f_air, gap, [0.7, 1.1], 0.1);
        let cal = calibrate(vs, 1280, 960, &settings(model)).unwrap();
        let near = port_pose_rms(&cal.calib, f_air, gap, 0.9);
        let far = port_pose_rms(&cal.calib, f_air, gap, 3.0);
        eprintln!(
            "gap {:.0} mm, {model}: f {:.1} px (in air {f_air}), RMS {:.3} px; a pose with \
             it: {near:.3} px at 0.9 m, {far:.3} px at 3 m",
            gap * 1e3,
            cal.calib.fx,
            cal.rms_px
        );
        rows.push((cal.rms_px, near, far, cal.calib.fx));
    }
    let [(pb, pb_near, _, f_pb), (ra, ra_near, ra_far, _), (_, gap_near, gap_far, _)] = rows[..]
    else {
        unreachable!()
    };
    // The focal length in water is n times the one in air.
    assert!((f_pb / (1.333 * f_air) - 1.0).abs() < 0.02, "f {f_pb}");
    // No gap: a central camera; the rational model fits to the noise (0.141 px) and
    // serves a pose at any distance; plumb_bob leaves a residual.
    assert!(ra < 0.15 && ra_near < 0.05 && ra_far < 0.05, "{rows:?}");
    assert!(pb > ra + 0.02 && pb_near > 5.0 * ra_near, "{rows:?}");
    // A 20 mm gap: not central; the fit holds near the calibrated distance, not at 3 m.
    assert!(gap_far > 3.0 * gap_near, "{rows:?}");
}
