//! The pictures look like the problem: in `adversarial` light a whole-image mean
//! auto exposure washes the marker out, an exposure metered on the marker reveals it;
//! in `normal` light both see it.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod camera_common;

use camera_common::*;
use markhold_exposure::{
    Corners, ExposureController, ExposureLimits, Frame, MeanAe, MeanAeConfig, ResponseModel,
};
use markhold_hil::camera::{CameraModel, UnderwaterCamera};
use markhold_hil::scene::LightingScenario;
use nalgebra::Isometry3;

fn corners(m: &CameraModel, t_wc: &Isometry3<f64>) -> Corners {
    let l = marker().size_m / 2.0;
    let mut c = [[0f32; 2]; 4];
    for (k, p) in [[-l, l], [l, l], [l, -l], [-l, -l]].iter().enumerate() {
        let q = project_marker_point(m, t_wc, *p);
        c[k] = [q[0] as f32, q[1] as f32];
    }
    c
}

/// Mean grey at the centres of the marker's white and black cells.
fn cell_levels(frame: &Frame, m: &CameraModel, t_wc: &Isometry3<f64>) -> (f64, f64) {
    let spec = marker();
    let n = spec.cells;
    let cell = spec.size_m / n as f64;
    let (mut w, mut nw, mut b, mut nb) = (0.0, 0.0, 0.0, 0.0);
    for j in 0..n {
        for i in 0..n {
            let u = -spec.size_m / 2.0 + (i as f64 + 0.5) * cell;
            let v = spec.size_m / 2.0 - (j as f64 + 0.5) * cell;
            let g = mean_over_marker_rect(frame, m, t_wc, [u, v], [0.25 * cell, 0.25 * cell]);
            if spec.white[j * n + i] {
                w += g;
                nw += 1.0;
            } else {
                b += g;
                nb += 1.0;
            }
        }
    }
    (w / nw, b / nb)
}

/// Run a mean-intensity AE in the loop with the camera; returns the last frame and the
/// exposure it converged to.
fn converge(
    scenario: LightingScenario,
    meter_marker: bool,
    model: &CameraModel,
    t_wc: &Isometry3<f64>,
) -> (Frame, f64) {
    let scene = scene(scenario, 11);
    let mut cam = UnderwaterCamera::new(model.clone(), 11).unwrap();
    let limits: ExposureLimits = model.limits;
    let cfg = MeanAeConfig {
        meter_roi: meter_marker,
        kappa: 0.5,
        ..MeanAeConfig::default()
    };
    let mut ae = MeanAe::new(cfg, limits, 2000.0).unwrap();
    cam.set_exposure_us(ae.commanded_us());
    let c = corners(model, t_wc);
    let mut frame = Frame::default();
    for k in 0..40 {
        cam.render(&scene, t_wc, t_wc, k as f64 / 30.0, &mut frame);
        let step = ae.update(&frame, Some(&c));
        cam.set_exposure_us(step.exposure_us);
    }
    let t = frame.meta.exposure_us;
    (frame, t)
}

fn test_model() -> CameraModel {
    let mut m = model(480, 360, ResponseModel::Gamma { gamma: 2.2 });
    m.sensor.noise = true;
    m
}

#[test]
fn adversarial_whole_image_ae_washes_the_marker_out_marker_ae_reveals_it() {
    let m = test_model();
    let t_wc = t_world_cam(1.0, 4.0, 3.0);

    let (global, t_global) = converge(LightingScenario::Adversarial, false, &m, &t_wc);
    let (w, b) = cell_levels(&global, &m, &t_wc);
    assert!(
        t_global > 10_000.0,
        "whole-image AE stayed short: {t_global} us"
    );
    assert!(
        w > 250.0 && b > 235.0,
        "marker not washed out at {t_global} us: white {w}, black {b}"
    );

    let (local, t_local) = converge(LightingScenario::Adversarial, true, &m, &t_wc);
    let (w, b) = cell_levels(&local, &m, &t_wc);
    assert!(
        t_local < 0.2 * t_global,
        "marker AE not shorter: {t_local} vs {t_global}"
    );
    assert!(
        w - b > 100.0,
        "marker contrast only {} at {t_local} us ({w} vs {b})",
        w - b
    );
}

#[test]
fn normal_light_any_ae_sees_the_marker() {
    let m = test_model();
    let t_wc = t_world_cam(1.0, -3.0, 0.0);
    for meter_marker in [false, true] {
        let (f, t) = converge(LightingScenario::Normal, meter_marker, &m, &t_wc);
        let (w, b) = cell_levels(&f, &m, &t_wc);
        assert!(
            w - b > 80.0,
            "meter_marker {meter_marker}: contrast {} at {t} us",
            w - b
        );
        assert!(
            w < 254.0,
            "meter_marker {meter_marker}: white clipped at {t} us"
        );
    }
}

#[test]
fn low_light_needs_long_exposure_and_shows_noise() {
    let m = test_model();
    let t_wc = t_world_cam(1.0, 0.0, 0.0);
    let (f, t) = converge(LightingScenario::Low, true, &m, &t_wc);
    assert!(
        t > 8_000.0,
        "low light converged to a short exposure: {t} us"
    );
    // Neighbouring pixels on the flat white margin differ by shot and read noise.
    let top = marker().size_m / 2.0 + marker().plate_margin_m / 2.0;
    let p = project_marker_point(&m, &t_wc, [0.0, top]);
    let (x0, y0) = (p[0] as usize, p[1] as usize);
    let w = f.width as usize;
    let vals: Vec<f64> = (0..20)
        .map(|k| f.data[y0 * w + x0 - 10 + k] as f64)
        .collect();
    let mean = vals.iter().sum::<f64>() / vals.len() as f64;
    let sd = (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / vals.len() as f64).sqrt();
    assert!(sd > 1.0, "no visible noise: sd {sd} at mean {mean}");
}

#[test]
fn caustics_move_over_time() {
    let m = model(240, 180, ResponseModel::Gamma { gamma: 2.2 });
    let t_wc = t_world_cam(1.0, 0.0, 0.0);
    let scene = scene(LightingScenario::Caustics, 2);
    let mut cam = UnderwaterCamera::new(m, 2).unwrap();
    cam.set_exposure_us(1500.0);
    let (mut a, mut b, mut c) = (Frame::default(), Frame::default(), Frame::default());
    cam.render(&scene, &t_wc, &t_wc, 1.0, &mut a);
    cam.render(&scene, &t_wc, &t_wc, 1.0, &mut b);
    cam.render(&scene, &t_wc, &t_wc, 1.5, &mut c);
    // Noise is off: the same instant renders the same, half a second later differs.
    assert_eq!(a.data, b.data);
    let moved = a
        .data
        .iter()
        .zip(&c.data)
        .filter(|(x, y)| x.abs_diff(**y) > 10)
        .count();
    assert!(moved > a.data.len() / 20, "only {moved} pixels changed");
    // Bright webs over darker gaps: a wide spread of levels.
    let mut levels = a.data.clone();
    levels.sort_unstable();
    let pct = |p: f64| levels[((levels.len() - 1) as f64 * p) as usize] as i32;
    assert!(
        pct(0.99) - pct(0.5) > 50,
        "p50 {} p99 {}",
        pct(0.5),
        pct(0.99)
    );
}
