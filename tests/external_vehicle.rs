//! `markhold hil --vehicle URL`: camera-in-the-loop on an external MAVLink vehicle.
//! Here the external vehicle is hil's own rig, free-running in real time on its own
//! thread (as ArduSub SITL would be); markhold renders its camera from the vehicle's
//! LOCAL_POSITION_NED + ATTITUDE telemetry and holds station over loopback UDP.
#![cfg(feature = "sim")]

use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use markhold::params;
use markhold::sim::hil::{camera_model, marker_spec, start_offset};
use markhold_exposure::{Camera, Frame};
use markhold_hil::{EndpointConfig, HilRig, HilSetup, VehicleMotion};

#[test]
fn holds_station_on_an_external_vehicle() {
    let site_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = params::load(&site_path).unwrap();
    let s = &site.site;
    let t_world_marker = site.t_world_marker();
    let t_world_station = t_world_marker * s.station.t_marker_vehicle();
    let start = t_world_station * start_offset(&s.vehicle);
    let setup = HilSetup {
        vehicle: s.vehicle.clone(),
        endpoint: EndpointConfig::default(),
        water: s.water.clone(),
        lighting: s.lighting.clone(),
        camera: camera_model(&site, site.limits()),
        t_vehicle_cam: site.t_vehicle_cam(),
        marker: marker_spec(&site).unwrap(),
        t_world_marker,
        t_world_vehicle_start: start,
        motion: VehicleMotion::Free,
        seed: 3,
        lock_step: false,
    };
    let mut rig = HilRig::new(setup).unwrap();
    let addr = rig.mavlink_udp_addr();
    let stop = Arc::new(AtomicBool::new(false));
    let stop2 = stop.clone();
    // The external vehicle runs in real time, whatever markhold does.
    let sim = std::thread::spawn(move || {
        let mut frame = Frame::default();
        let t0 = Instant::now();
        let period = Duration::from_secs_f64(1.0 / 30.0);
        let mut k = 0u32;
        while !stop2.load(Ordering::Relaxed) && t0.elapsed() < Duration::from_secs(60) {
            rig.grab(&mut frame).unwrap();
            k += 1;
            if let Some(w) = (t0 + period * k).checked_duration_since(Instant::now()) {
                std::thread::sleep(w);
            }
        }
        rig.truth()
    });

    let out = std::env::temp_dir().join(format!("markhold-external-{}.json", std::process::id()));
    let o = Command::new(env!("CARGO_BIN_EXE_markhold"))
        .args(["hil", "--quiet", "--seconds", "12", "--site"])
        .arg(&site_path)
        .arg("--vehicle")
        .arg(format!("udpout:{addr}"))
        .arg("--summary")
        .arg(&out)
        .output()
        .unwrap();
    stop.store(true, Ordering::Relaxed);
    let truth = sim.join().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
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
    assert!(truth.armed, "markhold armed the external vehicle");
}
