//! HIL exposure against an independent optimum: markhold's AAEC, on station and still,
//! ends where its metric `M` on the marker's region is within a stated margin of the
//! best over a sweep of the same view (not merely where it stopped moving).
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::Path;

use markhold::sim::hil::{run_hil, station_corners, station_frames, HilOptions};
use markhold_exposure::{AaecConfig, ExposureMethod, GradientMetric, Roi};
use markhold_hil::scene::LightingScenario;
use markhold_hil::VehicleMotion;

const SITE: &str = "tests/fixtures/pool-640.toml";

#[test]
fn aaec_ends_near_the_argmax_of_m_over_a_sweep_of_the_same_view() {
    let site = markhold::params::load(Path::new(SITE)).unwrap();
    for lighting in [LightingScenario::Normal, LightingScenario::Adversarial] {
        let mut light = site.site.lighting.clone();
        light.scenario = lighting;
        // The independent optimum: M on the marker's padded corner box over a 5 % sweep.
        let corners = station_corners(&site).unwrap();
        let (w, h) = (site.calibration.width, site.calibration.height);
        let roi = Roi::from_corners_padded(&corners, 0.1, w, h).unwrap();
        let response = site.site.camera.response.load().unwrap();
        let mut metric = GradientMetric::new(&response, AaecConfig::default().metric_params());
        let exposures: Vec<f64> = (0..=80).map(|k| 100.0 * 1.05f64.powi(k)).collect();
        let frames = station_frames(&site, 1, &light, &exposures).unwrap();
        let ms: Vec<(f64, f64)> = frames
            .iter()
            .map(|f| {
                let v = metric.evaluate(f.view().crop(roi)).unwrap();
                (f.meta.exposure_us, v.m)
            })
            .collect();
        let &(best_t, best_m) = ms.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
        let m_at = |t: f64| {
            ms.iter()
                .min_by(|a, b| (a.0 / t).ln().abs().total_cmp(&(b.0 / t).ln().abs()))
                .unwrap()
                .1
        };
        // The run starts 4x short of the optimum, so a frozen controller fails (above
        // it M is a plateau: 4x long is still within 20 % of the best).
        let start = best_t / 4.0;
        assert!(m_at(start) < 0.8 * best_m, "{lighting}: start too good");
        let opts = HilOptions {
            seconds: 8.0,
            exposure: Some(ExposureMethod::Aaec),
            lighting: Some(lighting),
            initial_exposure_us: Some(start),
            motion: VehicleMotion::Fixed,
            start_on_station: true,
            ..HilOptions::default()
        };
        let s = run_hil(&site, &opts, Default::default()).unwrap();
        let end = s.final_exposure_us;
        eprintln!(
            "{lighting}: argmax of M {best_t:.0} us; AAEC from {start:.0} ends at {end:.0} us \
             ({:.2}x), M there {:.3} of the best",
            end / best_t,
            m_at(end) / best_m
        );
        // markhold's AAEC holds at the knee, not at the argmax: M there is stated as
        // 5-10 % below the best (measured 10.3 % in normal light here); 15 % allowed.
        assert!(
            m_at(end) >= 0.85 * best_m,
            "{lighting}: M at {end:.0} us is {:.3} of the best (at {best_t:.0} us)",
            m_at(end) / best_m
        );
        assert!(
            (end / best_t).ln().abs() < 1.5f64.ln(),
            "{lighting}: {end} vs {best_t}"
        );
    }
}
