//! Clipped marker edges on the HIL's rendered frames: the shift of the corners against
//! the renderer's truth at exposures below and above the white's clip onset, beside
//! the clip covariance's fixed figures (design/vision.md, "Clipped edges").
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use markhold::params;
use markhold::sim::hil::{camera_model, marker_spec};
use markhold_exposure::{Camera, Frame};
use markhold_hil::{EndpointConfig, HilRig, HilSetup, VehicleMotion};
use markhold_vision::pose::marker_object_points;
use markhold_vision::MarkerTracker;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// Outward sign of each corner coordinate (u0 v0 u1 v1 ..., aruco order, image y down).
const OUTWARD: [f64; 8] = [-1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0];

/// (sides' common outward shift, RMS per-corner deviation from it, fraction of edge
/// points clipped), pixels, over `poses` still poses near the station at `exposure_us`.
fn shift_at(exposure_us: f64, poses: u64) -> (f64, f64, f64) {
    let site = params::load(&common::site_path()).unwrap();
    let s = &site.site;
    let station = site.t_world_marker() * s.station.t_marker_vehicle();
    let mut state = 999u64;
    let mut rnd = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % 10_000) as f64 / 10_000.0 - 0.5
    };
    let obj = marker_object_points(s.marker.size_m);
    let (mut common, mut dev2, mut n) = (0.0, 0.0, 0.0);
    let (mut points, mut clipped) = (0u64, 0u64);
    for k in 0..poses {
        let off = Isometry3::from_parts(
            Translation3::new(0.05 * rnd(), 0.05 * rnd(), 0.05 * rnd()),
            UnitQuaternion::from_euler_angles(0.03 * rnd(), 0.03 * rnd(), 0.05 * rnd()),
        );
        let mut rig = HilRig::new(HilSetup {
            vehicle: s.vehicle.clone(),
            endpoint: EndpointConfig::default(),
            water: s.water.clone(),
            lighting: s.lighting.clone(),
            camera: camera_model(&site, site.limits()),
            t_vehicle_cam: site.t_vehicle_cam(),
            marker: marker_spec(&site).unwrap(),
            t_world_marker: site.t_world_marker(),
            map: Vec::new(),
            t_world_vehicle_start: station * off,
            motion: VehicleMotion::Fixed,
            seed: 100 + k,
            lock_step: false,
        })
        .unwrap();
        rig.set_exposure_us(exposure_us).unwrap();
        let mut tracker =
            MarkerTracker::new(&s.marker, &s.vision, site.calibration.clone()).unwrap();
        let mut f = Frame::default();
        // The exposure lands a frame late; the first frames also seed the tracker.
        for i in 0..5 {
            rig.grab(&mut f).unwrap();
            let before = tracker.stats();
            let obs = tracker.process(&f).unwrap().expect("marker seen");
            if i < 2 {
                continue;
            }
            let after = tracker.stats();
            points += after.edge_points - before.edge_points;
            clipped += after.clipped_edge_points - before.clipped_edge_points;
            let truth = rig.truth();
            let mut out = [0.0; 8];
            for c in 0..4 {
                let p = site
                    .calibration
                    .project(&(truth.t_cam_marker * obj[c]))
                    .unwrap();
                out[2 * c] = OUTWARD[2 * c] * (obs.corners[c][0] as f64 - p.x);
                out[2 * c + 1] = OUTWARD[2 * c + 1] * (obs.corners[c][1] as f64 - p.y);
            }
            let m = out.iter().sum::<f64>() / 8.0;
            common += m;
            dev2 += out.iter().map(|x| (x - m).powi(2)).sum::<f64>() / 8.0;
            n += 1.0;
        }
    }
    (
        common / n,
        (dev2 / n).sqrt(),
        clipped as f64 / points.max(1) as f64,
    )
}

#[test]
fn clipped_edges_shift_inward_as_the_clip_covariance_states() {
    let site = params::load(&common::site_path()).unwrap();
    let v = &site.site.vision;
    let mut rows = Vec::new();
    for exposure in [3000.0, 3791.0, 5840.0] {
        let (shift, dev, frac) = shift_at(exposure, 10);
        println!(
            "{exposure} us: common outward shift {shift:+.4} px, per-corner deviation \
             {dev:.4} px, {:.0} % of edge points clipped",
            100.0 * frac
        );
        rows.push((shift, dev, frac));
    }
    // Unclipped: no edge point clips and the corners are where the renderer put them.
    assert_eq!(rows[0].2, 0.0, "{rows:?}");
    assert!(rows[0].0.abs() < 0.01 && rows[0].1 < 0.01, "{rows:?}");
    // At AAEC's landing in the loop (3791 us) every edge clips and the sides move inward
    // by about what the fixed clip figures state (within a factor of 1.5): the ones used
    // until the marker was seen unclipped.
    assert!(rows[1].2 > 0.95, "{rows:?}");
    let (c, s) = (v.corner_clip_common_px, v.corner_clip_side_px);
    assert!(
        (c / 1.5..c * 1.5).contains(&-rows[1].0),
        "common shift {} px, stated {c} px",
        rows[1].0
    );
    assert!(
        (s / 1.5..s * 1.5 * std::f64::consts::SQRT_2).contains(&rows[1].1),
        "per-corner deviation {} px, stated side {s} px",
        rows[1].1
    );
    // Clipping harder moves them further: the fixed figures hold for this landing only;
    // once a contrast is measured the shift follows the over-exposure (corners.rs's unit
    // test, tests/vision/vision_nees.rs; design/vision.md, "Clipped edges").
    assert!(-rows[2].0 > 2.0 * c, "{rows:?}");
}
