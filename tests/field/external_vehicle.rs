//! `markhold hil --vehicle URL`: camera-in-the-loop on an external MAVLink vehicle.
//! Here the external vehicle is hil's own rig, free-running in real time on its own
//! thread (as ArduSub SITL would be); markhold renders its camera from the vehicle's
//! LOCAL_POSITION_NED + ATTITUDE telemetry and holds station over loopback UDP.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use common::{rig_at, tmp_path, RealTimeVehicle};
use markhold::params;
use markhold::sim::hil::start_offset;

#[test]
fn holds_station_on_an_external_vehicle() {
    // The site's exit policy is the same as `run`'s: here `disarm`.
    let site_path = tmp_path("external", "site.toml");
    let text = std::fs::read_to_string(common::site_path())
        .unwrap()
        .replacen("[link]\n", "[link]\non_exit = \"disarm\"\n", 1);
    std::fs::write(&site_path, text).unwrap();
    let site = params::load(&site_path).unwrap();
    let s = &site.site;
    let t_world_station = site.t_world_marker() * s.station.t_marker_vehicle();
    let start = t_world_station * start_offset(&s.vehicle);
    // The external vehicle runs in real time, whatever markhold does.
    let sim = RealTimeVehicle::start(rig_at(&site, start, 3, false));
    let addr = sim.addr;

    let out = tmp_path("external", "summary.json");
    let plots = tmp_path("external", "plots");
    let o = common::hil_on_vehicle(&site_path, "12", &format!("udpout:{addr}"))
        .arg("--summary")
        .arg(&out)
        .arg("--plots")
        .arg(&plots)
        .output()
        .unwrap();
    let end = sim.finish();
    let truth = end.truth;
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let summary = common::read_json(&out);
    assert!(
        summary["detection_rate"].as_f64().unwrap() > 0.9,
        "{summary}"
    );
    // 12 s at 30 fps: frames the loop was too slow for are passed over, never made up
    // for after the 12 s of the vehicle's time.
    let frames = summary["frames"].as_u64().unwrap();
    eprintln!("external vehicle: {frames} of 360 camera frames handled");
    assert!((100..=360).contains(&frames), "{summary}");

    // The vehicle's own truth: it was moved from 0.3 m off to near its station.
    let err =
        (t_world_station.translation.vector - truth.t_world_vehicle.translation.vector).norm();
    assert!(
        err < 0.1,
        "external vehicle {err:.3} m from station; {summary}"
    );
    // markhold armed it, and at the end disarmed it as the site says, after its
    // neutral input was seen applied; neither of the vehicle's failsafes acted.
    assert!(
        stderr.contains("neutral input at exit: RcChannels"),
        "{stderr}"
    );
    assert!(
        stderr.contains("markhold: disarm on exit: Accepted"),
        "{stderr}"
    );
    assert!(!truth.armed, "markhold did not disarm the vehicle at exit");
    assert_eq!(
        (end.stats.failsafe_pilot, end.stats.failsafe_gcs),
        (0, 0),
        "{:?}",
        end.stats
    );
    // --plots works here too (the trajectory is the vehicle's telemetry).
    for stem in ["trajectory", "exposure_metric", "detection_latency"] {
        for ext in ["png", "svg"] {
            let p = plots.join(format!("{stem}.{ext}"));
            let len = std::fs::metadata(&p).map_or(0, |m| m.len());
            assert!(len > 1000, "{} has {len} bytes", p.display());
        }
    }
}
