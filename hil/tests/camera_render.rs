//! The HIL camera draws the marker where the intrinsics put it, its brightness is linear
//! in exposure until the sensor clips, and exposure requests land late, as configured.

mod camera_common;

use camera_common::*;
use markhold_exposure::{Frame, ResponseModel};
use markhold_hil::camera::UnderwaterCamera;
use markhold_hil::scene::LightingScenario;
use nalgebra::{Isometry3, Point3};

/// Largest distance (pixels) between a projected edge of the marker's black square and
/// the mid-grey crossing found in the rendered image, over 3 points on each edge
/// (infinite when the image shows no edge there).
fn worst_edge_error(
    frame: &Frame,
    model: &markhold_hil::camera::CameraModel,
    t_wc: &Isometry3<f64>,
) -> f64 {
    let l = marker().size_m / 2.0;
    let corners = [[-l, l], [l, l], [l, -l], [-l, -l]];
    let mut worst: f64 = 0.0;
    for k in 0..4 {
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        for f in [0.3, 0.5, 0.7] {
            let p = [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])];
            // Outward in the marker plane: away from the centre, 1 mm.
            let norm = (p[0].abs().max(p[1].abs())).max(1e-9);
            let out = if p[0].abs() > p[1].abs() {
                [p[0] / norm * 0.001, 0.0]
            } else {
                [0.0, p[1] / norm * 0.001]
            };
            let q0 = project_marker_point(model, t_wc, p);
            let q1 = project_marker_point(model, t_wc, [p[0] + out[0], p[1] + out[1]]);
            let (dx, dy) = (q1[0] - q0[0], q1[1] - q0[1]);
            let n = (dx * dx + dy * dy).sqrt();
            let (nx, ny) = (dx / n, dy / n);
            let at = |t: f64| sample(frame, q0[0] + nx * t, q0[1] + ny * t);
            let (black, white) = (at(-4.0), at(4.0));
            if white - black < 60.0 {
                // No black-to-white edge where the model says there is one.
                return f64::INFINITY;
            }
            let mid = 0.5 * (black + white);
            let mut t = -4.0;
            while t < 4.0 && at(t) < mid {
                t += 0.02;
            }
            worst = worst.max(t.abs());
        }
    }
    worst
}

fn render_once(
    model: markhold_hil::camera::CameraModel,
    t_wc: &Isometry3<f64>,
    exposure_us: f64,
) -> Frame {
    let scene = scene(LightingScenario::Normal, 3);
    let mut cam = UnderwaterCamera::new(model, 3).expect("camera");
    cam.set_exposure_us(exposure_us);
    let mut frame = Frame::default();
    cam.render(&scene, t_wc, t_wc, 0.0, &mut frame);
    frame
}

#[test]
fn marker_edges_are_where_the_intrinsics_project_them() {
    let model = model(800, 600, ResponseModel::Gamma { gamma: 2.2 });
    for (dist, yaw, roll) in [(1.0, 0.0, 0.0), (0.8, 12.0, 20.0), (1.4, -8.0, -35.0)] {
        let t_wc = t_world_cam(dist, yaw, roll);
        let frame = render_once(model.clone(), &t_wc, 2000.0);
        let err = worst_edge_error(&frame, &model, &t_wc);
        assert!(
            err < 1.0,
            "pose ({dist}, {yaw}, {roll}): edge off by {err} px"
        );
        // The check itself can tell: a principal point 2 px off is caught.
        let mut wrong = model.clone();
        wrong.cx += 2.0;
        let err = worst_edge_error(&frame, &wrong, &t_wc);
        assert!(err > 1.5, "a 2 px error went unnoticed ({err})");
    }
}

#[test]
fn marker_edges_follow_the_distortion_model() {
    let mut model = model(800, 600, ResponseModel::Gamma { gamma: 2.2 });
    model.dist = [-0.28, 0.09, 0.001, -0.0008, -0.01];
    // Put the marker off-centre where distortion moves it by many pixels.
    let t_wc = t_world_cam(0.9, 25.0, 10.0);
    let frame = render_once(model.clone(), &t_wc, 2000.0);
    let err = worst_edge_error(&frame, &model, &t_wc);
    assert!(err < 1.0, "edge off by {err} px");
    // And the undistorted projection would be clearly elsewhere.
    let mut pinhole = model.clone();
    pinhole.dist = [0.0; 5];
    let p = t_world_marker() * Point3::new(0.075, 0.075, 0.0);
    let pc = t_wc.inverse_transform_point(&p);
    let (a, b) = (model.project(&pc).unwrap(), pinhole.project(&pc).unwrap());
    assert!(
        (a[0] - b[0]).hypot(a[1] - b[1]) > 5.0,
        "test pose shows no distortion"
    );
}

#[test]
fn brightness_is_linear_in_exposure_until_the_sensor_clips() {
    let model = model(400, 300, ResponseModel::Linear);
    let t_wc = t_world_cam(1.0, 0.0, 0.0);
    // The white margin above the marker.
    let top = marker().size_m / 2.0 + marker().plate_margin_m / 2.0;
    let grey_at = |t_us: f64| {
        let f = render_once(model.clone(), &t_wc, t_us);
        assert_eq!(f.meta.exposure_us, t_us);
        mean_over_marker_rect(&f, &model, &t_wc, [0.0, top], [0.05, 0.008])
    };
    let g1 = grey_at(1000.0);
    let g2 = grey_at(2000.0);
    let g4 = grey_at(4000.0);
    assert!(
        g1 > 15.0 && g4 < 250.0,
        "test exposures not in the linear range: {g1} {g4}"
    );
    assert!((g2 / g1 - 2.0).abs() < 0.06, "{g1} -> {g2}");
    assert!((g4 / g1 - 4.0).abs() < 0.12, "{g1} -> {g4}");
    // Far past full well every white pixel is clipped at 255, not beyond, not wrapped.
    let gmax = grey_at(25_000.0);
    assert!(gmax > 254.5, "{gmax}");
}

#[test]
fn exposure_requests_land_delay_frames_late_and_frames_say_so() {
    let mut model = model(200, 150, ResponseModel::Linear);
    model.delay_frames = 2;
    let scene = scene(LightingScenario::Normal, 1);
    let t_wc = t_world_cam(1.0, 0.0, 0.0);
    let mut cam = UnderwaterCamera::new(model.clone(), 1).unwrap();
    assert_eq!(cam.set_exposure_us(1000.0), 1000.0);
    let mut f = Frame::default();
    let mut seen = Vec::new();
    let mut means = Vec::new();
    for k in 0..6u64 {
        if k == 1 {
            // Requested after frame 0: frames 1 and 2 still use 1000, frame 3 has 2000.
            assert_eq!(cam.set_exposure_us(2000.0), 2000.0);
        }
        cam.render(&scene, &t_wc, &t_wc, k as f64 / 30.0, &mut f);
        assert_eq!(f.meta.seq, k);
        assert_eq!(f.meta.stamp_s, k as f64 / 30.0);
        assert_eq!(f.meta.gain_db, 0.0);
        seen.push(f.meta.exposure_us);
        means.push(f.data.iter().map(|&v| v as f64).sum::<f64>() / f.data.len() as f64);
    }
    assert_eq!(seen, vec![1000.0, 1000.0, 1000.0, 2000.0, 2000.0, 2000.0]);
    // The pixels agree with the metadata: the image is twice as bright from frame 3.
    assert!((means[2] - means[0]).abs() < 0.5, "{means:?}");
    assert!((means[3] / means[2] - 2.0).abs() < 0.1, "{means:?}");
    // Out-of-range requests are clamped to what the camera can do (frame period bound).
    assert_eq!(cam.set_exposure_us(1e9), 30_000.0);
    assert_eq!(cam.set_exposure_us(0.0), 10.0);
    assert_eq!(cam.set_exposure_us(f64::NAN), 10.0);
}
