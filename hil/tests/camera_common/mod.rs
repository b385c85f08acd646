//! Shared set-up of the camera tests: a marker on station in front of the camera.
#![allow(dead_code)]

use markhold_exposure::{ExposureLimits, ResponseModel};
use markhold_hil::camera::{CameraModel, SensorConfig};
use markhold_hil::scene::{LightingConfig, LightingScenario, MarkerSpec, Scene, WaterConfig};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

pub const DEPTH_M: f64 = 4.0;

/// An 8x8 marker (black border, a 6x6 asymmetric pattern inside), 0.15 m.
pub fn marker() -> MarkerSpec {
    let cells = 8;
    let mut white = vec![false; cells * cells];
    for j in 1..cells - 1 {
        for i in 1..cells - 1 {
            white[j * cells + i] = (i * 7 + j * 3 + i * j) % 3 == 0;
        }
    }
    MarkerSpec {
        cells,
        white,
        size_m: 0.15,
        plate_margin_m: 0.04,
    }
}

fn rot(cols: [[f64; 3]; 3]) -> UnitQuaternion<f64> {
    let m = Matrix3::from_columns(&[
        Vector3::from(cols[0]),
        Vector3::from(cols[1]),
        Vector3::from(cols[2]),
    ]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
}

/// Marker at NED (0, 0, depth), face toward south (frames.md).
pub fn t_world_marker() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.0, 0.0, DEPTH_M),
        rot([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),
    )
}

/// A camera `dist_m` south of the marker looking north, turned by small angles.
pub fn t_world_cam(dist_m: f64, yaw_deg: f64, roll_deg: f64) -> Isometry3<f64> {
    let base = rot([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]);
    // Roll about the optical axis, yaw about the camera's y (down) axis.
    let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians())
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll_deg.to_radians());
    Isometry3::from_parts(
        Translation3::new(-dist_m, 0.03, DEPTH_M - 0.02),
        base * turn,
    )
}

pub fn model(width: u32, height: u32, response: ResponseModel) -> CameraModel {
    let f = 0.6 * width as f64;
    CameraModel {
        width,
        height,
        fx: f,
        fy: f * 1.01,
        cx: width as f64 / 2.0 - 0.5 + 3.0,
        cy: height as f64 / 2.0 - 0.5 - 2.0,
        dist: [0.0; 5],
        fps: 30.0,
        limits: ExposureLimits {
            min_us: 10.0,
            max_us: 30_000.0,
            fps: 30.0,
        },
        gain_db: 0.0,
        delay_frames: 1,
        response,
        sensor: SensorConfig {
            noise: false,
            ..SensorConfig::default()
        },
    }
}

pub fn scene(scenario: LightingScenario, seed: u64) -> Scene {
    let lighting = LightingConfig {
        scenario,
        ..LightingConfig::default()
    };
    Scene::new(
        &WaterConfig::default(),
        &lighting,
        marker(),
        t_world_marker(),
        seed,
    )
    .expect("valid scene")
}

/// Pixel of a marker-frame point seen from `t_world_cam`.
pub fn project_marker_point(
    m: &CameraModel,
    t_world_cam: &Isometry3<f64>,
    p_marker: [f64; 2],
) -> [f64; 2] {
    let p_w = t_world_marker() * Point3::new(p_marker[0], p_marker[1], 0.0);
    let p_c = t_world_cam.inverse_transform_point(&p_w);
    m.project(&p_c).expect("in front of the camera")
}

/// Bilinear grey at a sub-pixel position (pixel centres at integers).
pub fn sample(frame: &markhold_exposure::Frame, x: f64, y: f64) -> f64 {
    let w = frame.width as usize;
    let x0 = x.floor() as usize;
    let y0 = y.floor() as usize;
    let fx = x - x0 as f64;
    let fy = y - y0 as f64;
    let p = |i: usize, j: usize| frame.data[j * w + i] as f64;
    (p(x0, y0) * (1.0 - fx) + p(x0 + 1, y0) * fx) * (1.0 - fy)
        + (p(x0, y0 + 1) * (1.0 - fx) + p(x0 + 1, y0 + 1) * fx) * fy
}

/// Mean grey over the pixels of a marker-frame rectangle (centre, half sizes), shrunk
/// so only interior pixels count.
pub fn mean_over_marker_rect(
    frame: &markhold_exposure::Frame,
    m: &CameraModel,
    t_world_cam: &Isometry3<f64>,
    centre: [f64; 2],
    half: [f64; 2],
) -> f64 {
    let mut acc = 0.0;
    let mut n = 0.0;
    for i in 0..9 {
        for j in 0..9 {
            let u = centre[0] + half[0] * (i as f64 / 4.0 - 1.0);
            let v = centre[1] + half[1] * (j as f64 / 4.0 - 1.0);
            let p = project_marker_point(m, t_world_cam, [u, v]);
            acc += sample(frame, p[0], p[1]);
            n += 1.0;
        }
    }
    acc / n
}

/// A second 8x8 pattern (another id), 0.12 m.
pub fn marker_b() -> MarkerSpec {
    let cells = 8;
    let mut white = vec![false; cells * cells];
    for j in 1..cells - 1 {
        for i in 1..cells - 1 {
            white[j * cells + i] = (i * 5 + j * 11 + i * j * 3) % 4 < 2;
        }
    }
    MarkerSpec {
        cells,
        white,
        size_m: 0.12,
        plate_margin_m: 0.03,
    }
}

/// The map markers of `map_scene`: print and pose in the origin marker's frame (x right,
/// y up, z out of its face). One beside the origin marker on its wall, one turned
/// toward the camera, one standing out in front and hiding a corner of the origin plate.
pub fn map_markers() -> Vec<(MarkerSpec, Isometry3<f64>)> {
    let at = |x: f64, y: f64, z: f64, rpy: [f64; 3]| {
        let [r, p, yaw] = rpy.map(f64::to_radians);
        Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_euler_angles(r, p, yaw),
        )
    };
    vec![
        (marker_b(), at(0.30, 0.02, 0.0, [0.0, 0.0, 0.0])),
        (marker_b(), at(-0.30, -0.05, 0.03, [10.0, 25.0, 5.0])),
        (marker_b(), at(0.10, 0.12, 0.12, [0.0, -10.0, 0.0])),
    ]
}

/// `scene` with the markers of `map_markers` added.
pub fn map_scene(scenario: LightingScenario, seed: u64) -> Scene {
    let mut s = scene(scenario, seed);
    for (m, t) in map_markers() {
        s.add_map_marker(m, t).expect("valid map marker");
    }
    s
}

/// Pixel of a point of map marker `k` (its own frame) seen from `t_world_cam`.
pub fn project_map_point(
    m: &CameraModel,
    t_world_cam: &Isometry3<f64>,
    k: usize,
    p_marker: [f64; 2],
) -> Option<[f64; 2]> {
    let t = t_world_marker() * map_markers()[k].1;
    let p_w = t * Point3::new(p_marker[0], p_marker[1], 0.0);
    m.project(&t_world_cam.inverse_transform_point(&p_w))
}
