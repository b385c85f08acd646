use super::*;
use crate::config::{MapMarker, MarkerFamily};
use crate::pose::marker_object_points;
use crate::pose::{isotropic_corner_cov, refine_pose, whitening};
use nalgebra::{Matrix3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SIGMA_PX: f64 = 0.3;

fn calib() -> CameraCalibration {
    crate::pose::tests::calib(vec![-0.12, 0.04, 0.0005, -0.0003, 0.0])
}

fn entry(id: u32, size_m: f64, position_m: [f64; 3], rpy_deg: [f64; 3]) -> MapMarker {
    MapMarker {
        id,
        size_m,
        position_m,
        rpy_deg,
        plane: None,
    }
}

/// Four markers: the origin, one beside it, one above it tilted, one in front of it
/// and turned (about all three axes).
fn layout() -> MarkerConfig {
    MarkerConfig {
        family: MarkerFamily::AprilTag36h11,
        id: 0,
        size_m: 0.15,
        map: vec![
            entry(1, 0.15, [0.5, 0.0, 0.0], [0.0, 0.0, 0.0]),
            entry(2, 0.2, [0.05, 0.45, -0.1], [12.0, 0.0, 0.0]),
            entry(3, 0.1, [-0.5, -0.15, 0.2], [-5.0, 25.0, 15.0]),
        ],
        ..MarkerConfig::single(MarkerFamily::AprilTag36h11, 0, 0.15)
    }
}

/// A camera at `c` (site frame) looking at `target`, image x along the site's x: the
/// pose of the site frame in the camera frame.
fn look_at(c: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    let z = (target - c).normalize();
    let x = z.cross(&Vector3::y()).normalize();
    let y = z.cross(&x);
    let r = nalgebra::Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    let t_site_cam = Isometry3::from_parts(Translation3::from(c), UnitQuaternion::from(r));
    t_site_cam.inverse()
}

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    // Box-Muller.
    let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// What a camera at `t_cam_site` sees of `map`: every marker wholly in the image and
/// facing the camera, its corners with Gaussian noise and its own pose refined from
/// them (as the tracker's per-marker PnP gives it).
fn observe(
    map: &MarkerConfig,
    t_cam_site: &Isometry3<f64>,
    rng: &mut ChaCha8Rng,
) -> Vec<SeenMarker> {
    let c = calib();
    let cov = isotropic_corner_cov(SIGMA_PX);
    let white = whitening(&cov).unwrap();
    let mut out = Vec::new();
    for m in map.markers() {
        let t_cam_marker = t_cam_site * m.t_site_marker;
        // Facing: the marker's z axis points toward the camera.
        let normal = t_cam_marker.rotation * Vector3::z();
        if normal.dot(&t_cam_marker.translation.vector) >= 0.0 {
            continue;
        }
        let obj = marker_object_points(m.size_m);
        let mut img = [Vector2::zeros(); 4];
        let mut inside = true;
        for (p, o) in img.iter_mut().zip(&obj) {
            match c.project(&(t_cam_marker * o)) {
                Some(uv) if uv.x > 5.0 && uv.y > 5.0 && uv.x < 1435.0 && uv.y < 1075.0 => {
                    *p = uv + Vector2::new(gauss(rng), gauss(rng)) * SIGMA_PX;
                }
                _ => inside = false,
            }
        }
        if !inside {
            continue;
        }
        let start = apply(&t_cam_marker, &[0.01, -0.01, 0.03, 0.02, -0.02, 0.01]);
        let single = refine_pose(&c, &obj, &img, &start, &cov).unwrap();
        out.push(SeenMarker {
            id: m.id,
            img,
            white,
            t_cam_marker: single.t_cam_marker,
        });
    }
    out
}

/// Camera poses in front of the layout: three distances, a grid of positions, each
/// looking at a jittered point near the layout's centre.
fn cameras(rng: &mut ChaCha8Rng) -> Vec<Isometry3<f64>> {
    let mut out = Vec::new();
    for z in [1.3, 1.8, 2.4] {
        for x in [-0.6, -0.2, 0.2, 0.6] {
            for y in [-0.3, 0.1, 0.5] {
                let target = Vector3::new(
                    0.1 * (rng.random::<f64>() - 0.5),
                    0.1 + 0.1 * (rng.random::<f64>() - 0.5),
                    0.0,
                );
                out.push(look_at(Vector3::new(x, y, z), target));
            }
        }
    }
    out
}

fn check_recovered(map: &MarkerConfig, est: &MapEstimate) {
    assert_eq!(est.markers.len(), map.len());
    assert_eq!(est.markers[0].id, map.id);
    for truth in map.markers() {
        let m = est.markers.iter().find(|m| m.id == truth.id).unwrap();
        let dp =
            (m.t_site_marker.translation.vector - truth.t_site_marker.translation.vector).norm();
        let da = m
            .t_site_marker
            .rotation
            .angle_to(&truth.t_site_marker.rotation)
            .to_degrees();
        assert!(
            dp < 0.005,
            "marker {}: position off by {:.2} mm: {est:#?}",
            m.id,
            dp * 1e3
        );
        assert!(
            da < 0.5,
            "marker {}: orientation off by {da:.3} deg: {est:#?}",
            m.id
        );
        assert!(m.frames > 0 && m.rms_px < 3.0 * SIGMA_PX, "{m:?}");
        if m.id != map.id {
            // The stated uncertainty is consistent with the error (and not zero).
            let (sp, sa) = (m.sigma_position_m, m.sigma_angle_deg);
            assert!(sp > 0.0 && dp < 5.0 * sp + 5e-4, "{m:?}: {dp} m");
            assert!(sa > 0.0 && da < 5.0 * sa + 0.01, "{m:?}: {da} deg");
        }
    }
    assert!(est.rms_px < 2.0 * SIGMA_PX, "{est:#?}");
}

/// A builder for `map` under `calib`, fed one frame from each of the survey's cameras
/// (jittered from `seed`).
fn survey(map: &MarkerConfig, calib: CameraCalibration, seed: u64) -> MapBuilder {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut b = MapBuilder::new(map, calib);
    for cam in cameras(&mut rng) {
        b.add_frame(observe(map, &cam, &mut rng));
    }
    b
}

/// The settings that hold the intrinsics as given.
fn fixed_intrinsics() -> MapSettings {
    MapSettings {
        intrinsics: IntrinsicsMode::Fixed,
        ..MapSettings::default()
    }
}

/// Every marker's stated 1-sigma is at least a third of its real position error.
fn assert_sigma_at_least_a_third_of_the_error(errs: &[(u32, f64, f64)]) {
    for (id, e, s) in errs {
        assert!(
            *e <= 3.0 * s,
            "marker {id}: {:.2} mm off, 1-sigma {:.2} mm",
            e * 1e3,
            s * 1e3
        );
    }
}

#[test]
fn recovers_a_four_marker_layout_from_noisy_corners() {
    let map = layout();
    let b = survey(&map, calib(), 7);
    assert!(b.frames_kept() >= 20, "{}", b.frames_kept());
    let est = b.solve(0, &MapSettings::default()).unwrap();
    check_recovered(&map, &est);
    assert_eq!(est.outliers, 0, "{est:#?}");
    // The stated covariance matches the error (normalised squared error near 1).
    let (errs, nees) = normalised_errors(&map, &est);
    assert!(nees > 0.2 && nees < 3.0, "NEES {nees}: {errs:?}");
    // The adjustment improves on the chained start.
    assert!(est.rms_px < est.initial_rms_px, "{est:#?}");
}

#[test]
fn chains_through_markers_never_seen_with_the_origin_and_drops_bad_corners() {
    let map = layout();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut b = MapBuilder::new(&map, calib());
    let pairs = [(0, 1), (1, 2), (2, 3)];
    // Three passes over the poses (new jitter each): each pair seen in 36 frames.
    let cams: Vec<Isometry3<f64>> = (0..3).flat_map(|_| cameras(&mut rng)).collect();
    for (i, cam) in cams.iter().enumerate() {
        let (p, q) = pairs[i % 3];
        let mut seen: Vec<SeenMarker> = observe(&map, cam, &mut rng)
            .into_iter()
            .filter(|s| s.id == p || s.id == q)
            .collect();
        // Every seventh frame: a corner 15 px off (a wrong edge).
        if i % 7 == 3 {
            if let Some(s) = seen.last_mut() {
                s.img[2].x += 15.0;
            }
        }
        b.add_frame(seen);
    }
    let est = b.solve(0, &MapSettings::default()).unwrap();
    check_recovered(&map, &est);
    assert!(est.outliers >= 3, "{est:#?}");
}

#[test]
fn another_origin_gives_the_same_layout_seen_from_it() {
    let map = layout();
    let b = survey(&map, calib(), 3);
    let est = b.solve(2, &MapSettings::default()).unwrap();
    assert_eq!(est.markers[0].id, 2);
    assert_eq!(est.markers[0].t_site_marker, Isometry3::identity());
    let t_2_site = map.map[1].t_site_marker().inverse();
    for truth in map.markers() {
        let m = est.markers.iter().find(|m| m.id == truth.id).unwrap();
        let want = t_2_site * truth.t_site_marker;
        let dp = (m.t_site_marker.translation.vector - want.translation.vector).norm();
        assert!(dp < 0.005, "marker {}: {:.2} mm", m.id, dp * 1e3);
        assert!(
            m.t_site_marker
                .rotation
                .angle_to(&want.rotation)
                .to_degrees()
                < 0.5
        );
    }
}

#[test]
fn a_disconnected_marker_is_named_by_id() {
    let mut map = layout();
    map.map
        .push(entry(9, 0.1, [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]));
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut b = MapBuilder::new(&map, calib());
    // Markers 0 and 1 together, 2 and 3 together, never across; 9 never.
    for (i, cam) in cameras(&mut rng).iter().enumerate() {
        let group: [u32; 2] = if i % 2 == 0 { [0, 1] } else { [2, 3] };
        let seen: Vec<SeenMarker> = observe(&map, cam, &mut rng)
            .into_iter()
            .filter(|s| group.contains(&s.id))
            .collect();
        b.add_frame(seen);
    }
    let err = b.solve(0, &MapSettings::default()).unwrap_err();
    let text = err.to_string();
    assert!(
        matches!(&err, VisionError::MapDisconnected { origin: 0, ids, .. } if ids == "2, 3, 9"),
        "{text}"
    );
    assert!(text.contains("9 (never seen)"), "{text}");
    assert!(text.contains("2 (seen in "), "{text}");
    // From marker 2, it is 0 and 1 that are cut off.
    let err = b.solve(2, &MapSettings::default()).unwrap_err();
    assert!(
        matches!(&err, VisionError::MapDisconnected { origin: 2, ids, .. } if ids == "0, 1, 9"),
        "{err}"
    );
}

#[test]
fn frames_with_one_marker_each_make_no_map() {
    let map = layout();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut b = MapBuilder::new(&map, calib());
    for cam in cameras(&mut rng) {
        let seen = observe(&map, &cam, &mut rng);
        assert!(b.add_frame(seen.into_iter().take(1)) <= 1);
    }
    let err = b.solve(0, &MapSettings::default()).unwrap_err();
    assert!(
        matches!(err, VisionError::MapNoFrames { frames: 36 }),
        "{err}"
    );
    let err = b.solve(42, &MapSettings::default()).unwrap_err();
    assert!(
        matches!(&err, VisionError::MapOrigin { origin: 42, ids } if ids == "0, 1, 2, 3"),
        "{err}"
    );
}

/// Six markers on one wall (declared `plane = "wall"`), up to 0.5 m apart.
fn wall() -> MarkerConfig {
    let on_wall = |id, p: [f64; 2]| MapMarker {
        plane: Some("wall".into()),
        ..entry(id, 0.15, [p[0], p[1], 0.0], [0.0; 3])
    };
    MarkerConfig {
        family: MarkerFamily::AprilTag36h11,
        id: 0,
        size_m: 0.15,
        map: vec![
            on_wall(1, [0.5, 0.0]),
            on_wall(2, [-0.5, 0.05]),
            on_wall(3, [0.0, 0.45]),
            on_wall(4, [0.45, 0.4]),
            on_wall(5, [-0.45, -0.3]),
        ],
        plane: Some("wall".into()),
        ..MarkerConfig::single(MarkerFamily::AprilTag36h11, 0, 0.15)
    }
}

/// The calibration with its focal length 5 % too long.
fn long_focal() -> CameraCalibration {
    let c = calib();
    CameraCalibration {
        fx: 1.05 * c.fx,
        fy: 1.05 * c.fy,
        ..c
    }
}

/// Each marker's position error against `map` over its stated 1-sigma (worst axis),
/// and the mean normalised squared error (NEES over 3 axes) of the free markers.
fn normalised_errors(map: &MarkerConfig, est: &MapEstimate) -> (Vec<(u32, f64, f64)>, f64) {
    let mut out = Vec::new();
    let mut nees = 0.0;
    for truth in map.markers().skip(1) {
        let m = est.markers.iter().find(|m| m.id == truth.id).unwrap();
        let e = m.t_site_marker.translation.vector - truth.t_site_marker.translation.vector;
        let p = m.covariance.fixed_view::<3, 3>(0, 0).into_owned();
        nees += (e.transpose() * p.try_inverse().unwrap() * e)[(0, 0)] / 3.0;
        out.push((m.id, e.norm(), m.sigma_position_m));
    }
    let n = out.len() as f64;
    (out, nees / n)
}

#[test]
fn a_survey_of_a_flat_wall_refines_a_focal_length_5_percent_off() {
    let map = wall();
    let b = survey(&map, long_focal(), 21);
    let est = b.solve(0, &MapSettings::default()).unwrap();
    let i = &est.intrinsics;
    assert!(!i.refined.is_empty(), "{}", i.reason);
    let fx = i.calibration.fx;
    assert!((fx / calib().fx - 1.0).abs() < 0.003, "fx {fx}: {i:?}");
    let (errs, nees) = normalised_errors(&map, &est);
    for (id, e, s) in &errs {
        assert!(*e < 0.003, "marker {id}: {:.2} mm off", e * 1e3);
        assert!(
            *e < 4.0 * s,
            "marker {id}: {:.2} mm off, 1-sigma {:.2} mm",
            e * 1e3,
            s * 1e3
        );
    }
    assert!(nees < 3.0, "NEES {nees}: {errs:?}");
    let wall = &est.planes[0];
    assert_eq!(wall.ids.len(), 6);
    assert!(wall.max_m < 0.002, "{wall:?}");
}

#[test]
fn held_intrinsics_5_percent_off_keep_the_covariance_above_a_third_of_the_error() {
    let map = wall();
    let b = survey(&map, long_focal(), 21);
    let est = b.solve(0, &fixed_intrinsics()).unwrap();
    assert!(est.intrinsics.refined.is_empty());
    assert!(est.variance_factor > 1.0, "{}", est.variance_factor);
    let (errs, _) = normalised_errors(&map, &est);
    // The 1-sigma never claims less than a third of the real error.
    assert_sigma_at_least_a_third_of_the_error(&errs);
    // The surveyed wall stays flat: the cameras absorb a focal length error.
    assert!(est.planes[0].max_m < 0.003, "{:?}", est.planes);
}

#[test]
fn a_lens_model_gone_wrong_bends_the_wall_and_the_planes_say_so() {
    let map = wall();
    // The radial distortion of another medium (k1 0.15 too high), held.
    let mut wrong = calib();
    wrong.dist[0] += 0.15;
    let b = survey(&map, wrong, 23);
    let est = b.solve(0, &fixed_intrinsics()).unwrap();
    let (errs, _) = normalised_errors(&map, &est);
    // The wall comes out bent by millimetres and tilted by degrees, and the report says
    // by how much.
    let wall = &est.planes[0];
    assert!(wall.max_m > 0.004 && wall.max_tilt_deg > 2.0, "{wall:?}");
    // The residuals show the model error: the 1-sigma stays above a third of the error.
    assert!(est.variance_factor > 3.0, "{}", est.variance_factor);
    assert_sigma_at_least_a_third_of_the_error(&errs);
}

#[test]
fn frames_from_one_viewpoint_hold_the_intrinsics_and_say_why() {
    let map = wall();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut b = MapBuilder::new(&map, calib());
    let cam = look_at(Vector3::new(0.0, 0.1, 1.8), Vector3::new(0.0, 0.1, 0.0));
    for _ in 0..30 {
        b.add_frame(observe(&map, &cam, &mut rng));
    }
    let est = b.solve(0, &MapSettings::default()).unwrap();
    assert!(est.intrinsics.refined.is_empty());
    assert_eq!(est.viewpoints, 1);
    assert!(
        est.intrinsics.reason.contains("1 viewpoint"),
        "{}",
        est.intrinsics.reason
    );
}
