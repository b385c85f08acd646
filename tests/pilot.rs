//! `markhold run` and `markhold hil --vehicle` beside a pilot: a pymavlink vehicle
//! (autopilot/tests/pymav_vehicle.py) plays ArduSub, with its pilot-input handling and
//! its pilot-input and GCS failsafes, and QGroundControl (system 255, component 190:
//! its heartbeat at 1 Hz, its joystick) beside it. The pilot engages by arming in the
//! site's mode, switches mode away (markhold must go quiet within 100 ms and stay quiet),
//! switches back (engaged again), moves a stick (markhold lets go), engages a third
//! time; markhold then stops at the end of its frames and hands back. markhold sends
//! everything as a component of the vehicle (its system id, component 191) but its pilot
//! input, which goes out as SYSID_MYGCS and stops when the pilot's station falls silent,
//! so the vehicle's GCS failsafe fires. Every exit, over UDP, TCP and a serial line and on
//! SIGTERM, leaves neutral input applied, 100 times out of 100. `markhold preflight`
//! against the same vehicle passes on a good parameter set and fails on
//! FS_PILOT_INPUT = 0 and on a SYSID_MYGCS mismatch.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{mpsc, OnceLock};
use std::time::{Duration, Instant};

use common::{
    frames_camera, markhold, pymav_texts, pymav_verdict, repo, rig_at, run_engaged, site_path,
    station_frames, tmp_path,
};
use markhold::field::engage::{EngagedLink, ExitPolicy};
use markhold_autopilot::{Effort, LinkConfig, LinkMode, NeutralShown, VehicleLink};
use serde_json::Value;

fn tmp(name: &str) -> PathBuf {
    tmp_path("pilot", name)
}

/// These tests run real-time vehicles and judge what markhold did by the clock (within
/// 1.5 s, 30 frames/s): one at a time, so that they do not starve each other of the
/// machine's cores.
fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|p| p.into_inner())
}

/// 8 s of frames on station (the pilot's plan takes about 4 s), made once.
fn frames_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| station_frames(tmp("frames"), 240))
}

use common::PymavVehicle as Vehicle;

/// Start the pymavlink vehicle with `args` (at most 40 s); its UDP port.
fn vehicle(args: &[&str]) -> (Vehicle, u16) {
    common::pymav_vehicle(&[&["--deadline", "40"], args].concat())
}

/// What markhold sent, as whom: every (system id, component id, message) the vehicle
/// saw. Pilot input as SYSID_MYGCS (255), everything else as the vehicle's system (1),
/// all from component 191; its HEARTBEAT and STATUSTEXT among them.
fn assert_identity(v: &Value) {
    let ids: Vec<(u64, u64, String)> = v["mh_ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            (
                t[0].as_u64().unwrap(),
                t[1].as_u64().unwrap(),
                t[2].as_str().unwrap().to_string(),
            )
        })
        .collect();
    for (sys, comp, ty) in &ids {
        assert_eq!(*comp, 191, "{ty} from component {comp}");
        let pilot = ty == "RC_CHANNELS_OVERRIDE" || ty == "MANUAL_CONTROL";
        assert_eq!(*sys, if pilot { 255 } else { 1 }, "{ty} from system {sys}");
    }
    for ty in ["HEARTBEAT", "STATUSTEXT"] {
        assert!(
            ids.iter().any(|(s, c, t)| (*s, *c) == (1, 191) && t == ty),
            "no {ty} from 1/191: {ids:?}"
        );
    }
}

/// Times (s from the vehicle's start) of every frame markhold sent as SYSID_MYGCS.
fn gcs_frames(v: &Value) -> Vec<f64> {
    v["gcs_frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect()
}

/// The fixture site with extra `[link]` keys, written next to the original (its paths
/// are relative to it).
fn site_with(name: &str, link_keys: &str) -> PathBuf {
    let text = std::fs::read_to_string(site_path()).unwrap();
    let text = text.replacen("[link]\n", &format!("[link]\n{link_keys}\n"), 1);
    let p = tmp(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn run(site: &Path, port: u16, summary: &Path) -> std::process::Output {
    markhold()
        .args(["run", "--site"])
        .arg(site)
        .arg("--camera")
        .arg(format!("frames:{}", frames_dir().display()))
        .arg("--link")
        .arg(format!("udpout:127.0.0.1:{port}"))
        .arg("--summary")
        .arg(summary)
        .output()
        .unwrap()
}

#[test]
fn the_pilot_engages_takes_over_and_gets_the_vehicle_back() {
    let _one = one_at_a_time();
    let summary = tmp("pilot.json");
    let (stderr, verdict) = run_against(&["--scenario", "pilot"], &site_path(), &summary);
    let said = pymav_texts(&verdict);
    assert_eq!(
        verdict["failures"],
        serde_json::json!([]),
        "{verdict}\n{stderr}"
    );
    assert_eq!(
        verdict["step"], 11,
        "the pilot's plan did not finish: {verdict}"
    );
    // Every engagement change said once, in order.
    let changes: Vec<&str> = said
        .iter()
        .map(String::as_str)
        .filter(|t| !t.starts_with("markhold: marker") && !t.starts_with("markhold: exposure"))
        .collect();
    assert_eq!(
        changes,
        [
            "markhold ready: arm, select MANUAL",
            "markhold on: holding station",
            "markhold off: mode changed",
            "markhold on: holding station",
            "markhold off: pilot input",
            "markhold on: holding station",
            "markhold off: stopped",
            "markhold stopped: take the controls",
            "markhold: pilot has control",
        ],
        "{verdict}"
    );
    // When markhold heard the mode change: one neutral, "markhold off: mode changed",
    // then only the release (by the order it sent them).
    let around = &verdict["around_off_text"];
    assert_eq!(around["before"], "neutral", "{verdict}");
    assert_eq!(around["after"], serde_json::json!(["release"]), "{verdict}");
    assert_eq!(verdict["release_seen"], true, "{verdict}");
    eprintln!(
        "pilot: last pilot input {} ms after the pilot's mode change (wall clock, loopback)",
        verdict["last_input_after_mode_change_ms"]
    );
    assert_eq!(verdict["inputs_while_off"], 0, "{verdict}");
    // Handed back: still armed, neither failsafe fired (the station was alive all along).
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["gcs_failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["armed_at_end"], true, "{verdict}");
    assert_identity(&verdict);
    // After the pilot took the controls at the end, nothing more as SYSID_MYGCS: the
    // release comes before "markhold: pilot has control", and nothing after it.
    let handed = verdict["texts"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t[2] == "markhold: pilot has control")
        .map(|t| t[0].as_f64().unwrap())
        .unwrap();
    let late: Vec<f64> = gcs_frames(&verdict)
        .into_iter()
        .filter(|t| *t > handed)
        .collect();
    assert!(late.is_empty(), "sent as 255 after the hand-back: {late:?}");
    assert_eq!(
        verdict["named"],
        serde_json::json!(["mh_err_m", "mh_yaw_deg"])
    );
    // The vehicle's own STATUSTEXT lands in markhold's log.
    assert!(stderr.contains("vehicle says: Leak Detected!"), "{stderr}");
    assert!(stderr.contains("vehicle reports a failsafe"), "{stderr}");
    // The preflight ran (parameter reads) before the loop.
    assert!(verdict["param_reads"].as_u64().unwrap() >= 5, "{verdict}");
    let s = read_summary(&summary);
    assert_eq!(s["engagements"], 3, "{s}");
    assert_eq!(s["hand_back"], "pilot_took_over", "{s}");
    assert!(s["withheld"].as_u64().unwrap() > 0, "{s}");
}

#[test]
fn with_nobody_at_the_joystick_the_hand_back_disarms_and_says_so() {
    let _one = one_at_a_time();
    let site = site_with("handback.toml", "hand_back_timeout_s = 1.0");
    let summary = tmp("handback.json");
    let (_, verdict) = run_against(
        &["--scenario", "pilot", "--no-pilot-after-exit"],
        &site,
        &summary,
    );
    let said = pymav_texts(&verdict);
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert!(
        said.iter()
            .any(|t| t == "markhold: no pilot input, disarming"),
        "{said:?}"
    );
    assert_eq!(verdict["armed_at_end"], false, "{verdict}");
    // markhold disarmed it; ArduSub's failsafes did not have to.
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["gcs_failsafe"], serde_json::json!([]), "{verdict}");
    let s = read_summary(&summary);
    assert_eq!(s["hand_back"]["disarmed"], "Accepted", "{s}");
}

fn preflight(extra: &[&str]) -> (std::process::Output, serde_json::Value) {
    preflight_with(&[], extra)
}

/// `markhold preflight` against the `params` vehicle started with `vehicle_args` and
/// the parameter overrides `extra`.
fn preflight_with(vehicle_args: &[&str], extra: &[&str]) -> (std::process::Output, Value) {
    let mut args = vec!["--scenario", "params"];
    args.extend_from_slice(vehicle_args);
    for p in extra {
        args.extend(["--param", p]);
    }
    let (mut v, port) = vehicle(&args);
    let o = markhold()
        .args(["preflight", "--site"])
        .arg(site_path())
        .arg("--link")
        .arg(format!("udpout:127.0.0.1:{port}"))
        .output()
        .unwrap();
    (o, pymav_verdict(&mut v))
}

#[test]
fn preflight_passes_a_good_vehicle_and_fails_a_bad_one_with_the_fix() {
    let _one = one_at_a_time();
    let (o, v) = preflight(&[]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(out.contains("0 fail"), "{out}");
    assert!(out.contains("[pass] gcs id"), "{out}");
    assert!(out.contains("[pass] ardusub version"), "{out}");
    assert!(out.contains("4.1.2"), "{out}");
    assert!(v["param_reads"].as_u64().unwrap() >= 5, "{v}");
    // FS_GCS_TIMEOUT read, and how long the pilot's station may be silent with it.
    assert!(out.contains("[pass] gcs timeout"), "{out}");
    assert!(out.contains("FS_GCS_TIMEOUT = 2.5 s"), "{out}");
    assert!(out.contains("stops 1.25 s after"), "{out}");
    assert!(out.contains("[pass] pilot station"), "{out}");
    assert!(out.contains("component 190"), "{out}");

    // No GCS failsafe, or no station: warned, with the fix.
    let (o, _) = preflight(&["FS_GCS_ENABLE=0"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("[WARN] gcs failsafe"), "{out}");
    assert!(out.contains("fix: set FS_GCS_ENABLE = 2"), "{out}");
    let (o, _) = preflight_with(&["--station", "none"], &[]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("[WARN] pilot station"), "{out}");
    // A short FS_GCS_TIMEOUT: markhold cannot tell a lost station within half of it.
    let (o, _) = preflight(&["FS_GCS_TIMEOUT=1.5"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("[WARN] gcs timeout"), "{out}");

    let (o, _) = preflight(&["FS_PILOT_INPUT=0"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(out.contains("[FAIL] pilot failsafe"), "{out}");
    assert!(out.contains("fix: set FS_PILOT_INPUT = 2"), "{out}");

    let (o, _) = preflight(&["SYSID_MYGCS=254"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(out.contains("[FAIL] gcs id"), "{out}");
    assert!(out.contains("set SYSID_MYGCS = 255"), "{out}");

    // The frame the site names must be the vehicle's.
    let (o, _) = preflight(&["FRAME_CONFIG=1"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(out.contains("[FAIL] frame"), "{out}");
}

#[test]
fn run_refuses_to_start_on_a_failed_preflight() {
    let _one = one_at_a_time();
    let (mut v, port) = vehicle(&["--scenario", "params", "--param", "FS_PILOT_INPUT=0"]);
    let o = run(&site_path(), port, &tmp("refused.json"));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("failed the preflight check"), "{stderr}");
    assert!(stderr.contains("--no-preflight"), "{stderr}");
    let verdict = pymav_verdict(&mut v);
    // Nothing but parameter traffic: no pilot input, no arming.
    assert_eq!(verdict["armed_at_end"], false, "{verdict}");
}

/// How far the test pilot nudges the vehicle off station before letting go, m.
const PILOT_NUDGE_M: f64 = 0.08;
/// The test pilot's sway stick while nudging.
const PILOT_SWAY: f64 = 0.3;

/// The pilot's QGroundControl on a second TCP connection to the external vehicle, as
/// system 255, component 190 (a `VehicleLink` with QGroundControl's ids): switches mode
/// away at `away_s`, pushes the vehicle sideways with its own overrides, centres and
/// releases them and switches back at `back_s` (wall seconds from the start). Returns how far the vehicle
/// moved from where it was at `away_s` (its LOCAL_POSITION_NED), metres.
fn pilot_on_tcp(
    addr: std::net::SocketAddr,
    away_s: f64,
    back_s: f64,
) -> std::thread::JoinHandle<f64> {
    use markhold_autopilot::{ArduSubMode, Effort, LinkConfig, VehicleLink};
    use std::time::{Duration, Instant};
    std::thread::spawn(move || {
        let cfg = LinkConfig {
            url: format!("tcp:{addr}"),
            component_id: 190,
            ..LinkConfig::default()
        };
        let mut qgc = VehicleLink::connect(&cfg).unwrap();
        qgc.set_pilot_keepalive(false);
        let t0 = Instant::now();
        let (mut step, mut at_away, mut moved) = (0, None::<[f64; 3]>, 0.0f64);
        let (mut centred_at, mut pushing_from) = (None::<f64>, None::<f64>);
        while step < 4 && t0.elapsed() < Duration::from_secs(30) {
            let t = t0.elapsed().as_secs_f64();
            qgc.tick(t).unwrap();
            let pos = qgc.state().local_position.map(|p| p.position);
            if let (Some(a), Some(p)) = (at_away, pos) {
                let d =
                    ((p[0] - a[0]).powi(2) + (p[1] - a[1]).powi(2) + (p[2] - a[2]).powi(2)).sqrt();
                moved = moved.max(d);
            }
            match step {
                0 if t >= away_s => {
                    qgc.request_mode(ArduSubMode::Stabilize, t).unwrap();
                    at_away = pos;
                    step = 1;
                }
                // The pilot nudges it, watching it move, and lets go 8 cm off station: it
                // coasts on to about 0.3 m (not so far that the marker leaves the view).
                // markhold lets go on the HEARTBEAT that reports the new mode: the pilot
                // waits for the same report before pushing, else the two fight.
                1 if pushing_from.is_none() && qgc.state().mode == Some(ArduSubMode::Stabilize) => {
                    pushing_from = Some(t + 0.3);
                }
                1 if pushing_from.is_none_or(|p| t < p) => {}
                1 if centred_at.is_none() && moved < PILOT_NUDGE_M && t < away_s + 3.0 => {
                    let push = Effort {
                        sway: PILOT_SWAY,
                        ..Effort::NEUTRAL
                    };
                    qgc.send_effort(&push, t).unwrap();
                }
                // The pilot lets go: centred sticks, then the overrides released. ArduSub
                // with no RC receiver keeps a released override's last value until the
                // pilot-input failsafe, so releasing mid-push would go on pushing.
                1 if t < *centred_at.get_or_insert(t) + 0.3 => {
                    qgc.send_effort(&Effort::NEUTRAL, t).unwrap();
                }
                1 => {
                    qgc.release_pilot().unwrap();
                    step = 2;
                }
                2 if t >= back_s => {
                    // The site's mode: markhold engages again.
                    qgc.request_mode(ArduSubMode::Manual, t).unwrap();
                    step = 3;
                }
                3 if t >= back_s + 1.0 => step = 4,
                _ => {}
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        moved
    })
}

#[test]
fn hil_on_an_external_vehicle_hands_over_to_the_pilot_and_regains_station() {
    let _one = one_at_a_time();
    use common::RealTimeVehicle;
    use markhold::params;
    use markhold_hil::{EndpointConfig, HilRig, HilSetup, VehicleMotion};
    let site = params::load(&site_path()).unwrap();
    let s = &site.site;
    let t_world_station = site.t_world_marker() * s.station.t_marker_vehicle();
    let rig = HilRig::new(HilSetup {
        // ArduSub itself (as SITL would be): the loop's delays are its own, real ones.
        vehicle: markhold_hil::VehicleConfig {
            delay: markhold_hil::DelayConfig::NONE,
            ..s.vehicle.clone()
        },
        endpoint: EndpointConfig {
            tcp_enabled: true,
            ..EndpointConfig::default()
        },
        water: s.water.clone(),
        lighting: s.lighting.clone(),
        camera: markhold::sim::hil::camera_model(&site, site.limits()),
        t_vehicle_cam: site.t_vehicle_cam(),
        marker: markhold::sim::hil::marker_spec(&site).unwrap(),
        t_world_marker: site.t_world_marker(),
        map: Vec::new(),
        // hil --vehicle places the marker for a vehicle starting this far off station.
        t_world_vehicle_start: t_world_station * markhold::sim::hil::start_offset(&s.vehicle),
        motion: VehicleMotion::Free,
        seed: 3,
        lock_step: false,
    })
    .unwrap();
    let tcp = rig.mavlink_tcp_addr().expect("tcp endpoint");
    let sim = RealTimeVehicle::start(rig);
    let pilot = pilot_on_tcp(tcp, 4.0, 7.5);
    let out = tmp("hil-pilot.json");
    // The pilot has left by the end: the exit hands back, hears nobody for 1 s, disarms.
    let site_file = site_with("hil-pilot.toml", "hand_back_timeout_s = 1.0");
    let o = common::hil_on_vehicle(&site_file, "16", &format!("tcp:{tcp}"))
        .arg("--summary")
        .arg(&out)
        .output()
        .unwrap();
    let moved = pilot.join().unwrap();
    let end = sim.finish();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    // The run's exit is `run`'s: neutral seen applied (the simulated vehicle streams
    // RC_CHANNELS), hand back, nobody there, disarmed by markhold; neither of the
    // vehicle's failsafes had to act.
    assert!(
        stderr.contains("neutral input at exit: RcChannels"),
        "{stderr}"
    );
    assert!(stderr.contains("Disarmed(Accepted)"), "{stderr}");
    assert!(!end.truth.armed, "{:?}", end.stats);
    assert_eq!(
        (end.stats.failsafe_pilot, end.stats.failsafe_gcs),
        (0, 0),
        "{:?}",
        end.stats
    );
    // Let go when the pilot switched away, engaged again when the pilot came back.
    assert!(stderr.contains("disengaged why=ModeChanged"), "{stderr}");
    assert!(stderr.contains("engaged 2 times"), "{stderr}");
    // The vehicle really left its station while markhold was off (the pilot's sideways
    // nudge and the coast after it, about 0.3 m, plus its positive buoyancy) ...
    assert!(
        moved > 0.15,
        "the vehicle moved {moved:.3} m while markhold was off"
    );
    // ... and markhold brought it back after the pilot engaged it again (the error at
    // the run's last frame, from the vehicle's telemetry: after it the exit hands back
    // and the vehicle, neutral, drifts on its buoyancy).
    let summary = common::read_json(&out);
    let err = summary["final_position_error_m"].as_f64().unwrap();
    assert!(err < 0.15, "{err:.3} m from station at the end\n{stderr}");
    eprintln!(
        "hil pilot: moved {moved:.2} m while markhold was off, {err:.3} m from station at the end"
    );
}

/// Drives the `--scenario thrust` vehicle with a `VehicleLink` configured like a site's
/// `[link]`: selects `mode`, sends `effort` for 0.6 s, releases; the vehicle's verdict.
fn thrust_run(
    link: markhold_autopilot::LinkConfig,
    effort: markhold_autopilot::Effort,
    volts: &str,
) -> serde_json::Value {
    use markhold_autopilot::VehicleLink;
    use std::time::{Duration, Instant};
    let (mut v, port) = vehicle(&["--scenario", "thrust", "--volts", volts]);
    let mode = link.mode.ardusub();
    let mut l = VehicleLink::connect(&markhold_autopilot::LinkConfig {
        url: format!("udpout:127.0.0.1:{port}"),
        ..link
    })
    .unwrap();
    let t0 = Instant::now();
    let mut asked = false;
    while t0.elapsed() < Duration::from_secs(10) {
        let t = t0.elapsed().as_secs_f64();
        l.tick(t).unwrap();
        if l.state().discovered && !asked {
            l.request_mode(mode, t).unwrap();
            asked = true;
        }
        if l.state().mode == Some(mode) {
            let start = Instant::now();
            while start.elapsed() < Duration::from_millis(600) {
                let t = t0.elapsed().as_secs_f64();
                l.tick(t).unwrap();
                l.send_effort(&effort, t).unwrap();
                std::thread::sleep(Duration::from_millis(30));
            }
            l.release_pilot().unwrap();
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(l);
    pymav_verdict(&mut v)
}

/// Against a vehicle that reads pilot input as ArduSub does and turns it into thrust
/// from Blue Robotics' T200 table: the smallest forward command the station keeper sends
/// (an effort just above `effort_epsilon`, in ALT_HOLD as every site runs, over RC
/// overrides and over MANUAL_CONTROL) produces the thrust the keeper intends within
/// 20 %. The keeper intends the T200 thrust at the PWM it aims for: 1500 + its ESC dead
/// band (`thruster_deadband_us`, here the table's own 28 us at 16 V) + the effort; with
/// an input dead zone added on forward (which ArduSub does not have) it would be several
/// times that.
#[test]
fn the_smallest_forward_command_makes_the_thrust_the_keeper_intends() {
    let _one = one_at_a_time();
    use markhold_autopilot::{Effort, LinkConfig, LinkMode, PilotInput, PilotMap};
    use markhold_hil::mixer::{Frame6Dof, Mixer};
    use markhold_hil::ThrusterConfig;
    let volts = 16.0;
    for pilot_input in [PilotInput::RcOverride, PilotInput::ManualControl] {
        let link = LinkConfig {
            mode: LinkMode::AltHold,
            pilot_input,
            thruster_deadband_us: 28.0,
            ..LinkConfig::default()
        };
        let e = Effort {
            surge: link.effort_epsilon * 1.01,
            ..Effort::NEUTRAL
        };
        // What the keeper aims for: the forward channel's PWM straight into the mixer.
        let rc = PilotMap::from_config(&link).rc_channels(&e);
        let fwd = f64::from(rc[4]) - 1500.0;
        let mixer = Mixer::new(Frame6Dof::Heavy);
        let pwm = mixer.mix_pwm(&[fwd / 400.0, 0.0, 0.0, 0.0, 0.0, 0.0], true);
        let t200 = ThrusterConfig::default();
        let thrust = pwm.map(|p| t200.steady_thrust_n(f64::from(p), volts));
        let intended = mixer.wrench(&thrust).0.x;
        assert!(
            intended > 0.0,
            "the keeper's smallest command makes no thrust: {pwm:?}"
        );

        let verdict = thrust_run(link, e, "16");
        assert_eq!(verdict["ok"], true, "{verdict}");
        let samples = verdict["samples"].as_array().unwrap();
        let cmd: Vec<_> = samples
            .iter()
            .filter(|s| s["rc"][4].as_u64() != Some(1500))
            .collect();
        assert!(
            !cmd.is_empty(),
            "no forward command reached the vehicle: {verdict}"
        );
        for s in cmd {
            let fx = s["fx_n"].as_f64().unwrap();
            assert!(
                (fx - intended).abs() <= 0.2 * intended,
                "{pilot_input:?}: the vehicle made {fx:.3} N forward, the keeper intended \
                 {intended:.3} N (motors {:?} from {:?}, keeper aimed at {pwm:?})",
                s["motors"],
                s["rc"]
            );
            // Nothing else moved: no setpoint left its dead zone.
            for (k, v) in s["setpoints"].as_object().unwrap() {
                assert_eq!(v.as_f64(), Some(0.0), "{k} in {s}");
            }
        }
        eprintln!("smallest forward command over {pilot_input:?}: {intended:.3} N intended");
    }
}

/// `markhold hil --vehicle` for `seconds` on the pymavlink vehicle at `port`.
fn hil_vehicle(site: &Path, port: u16, seconds: &str) -> std::process::Output {
    common::hil_on_vehicle(site, seconds, &format!("udpout:127.0.0.1:{port}"))
        .output()
        .unwrap()
}

/// `run` of `site` against a test vehicle started with `args`, its summary to `summary`:
/// it succeeds; its stderr and the vehicle's verdict.
fn run_against(args: &[&str], site: &Path, summary: &Path) -> (String, Value) {
    let (mut v, port) = vehicle(args);
    succeeded(run(site, port, summary), &mut v)
}

/// `hil --vehicle` for `seconds` against a test vehicle started with `args`: it
/// succeeds; its stderr and the vehicle's verdict.
fn hil_against(args: &[&str], site: &Path, seconds: &str) -> (String, Value) {
    let (mut v, port) = vehicle(args);
    succeeded(hil_vehicle(site, port, seconds), &mut v)
}

/// markhold's run `o` against `v` succeeded: its stderr and the vehicle's verdict.
fn succeeded(o: std::process::Output, v: &mut Vehicle) -> (String, Value) {
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "{stderr}");
    (stderr, pymav_verdict(v))
}

/// The run's `--summary` JSON.
fn read_summary(summary: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(summary).expect("the run wrote its summary"))
        .expect("the summary is JSON")
}

/// The pilot's station stops (tether cut topside, QGroundControl closed) a second after
/// markhold engaged. markhold must stop every SYSID_MYGCS frame within 0.7 s of the
/// station's last heartbeat, say why, and the vehicle's GCS failsafe (as ArduSub runs
/// it: markhold's own pilot input counts as contact) must fire FS_GCS_TIMEOUT after
/// markhold's last such frame. With markhold commanding, that is at most the relay
/// window (`STATION_RELAY_S`) and the vehicle's 0.3 s check period later than without
/// it.
fn assert_station_loss_lets_the_failsafe_fire(verdict: &Value, stderr: &str) {
    let said = pymav_texts(verdict);
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert!(
        said.iter()
            .any(|t| t == "markhold off: pilot station silent"),
        "{said:?}\n{stderr}"
    );
    assert_identity(verdict);
    let last_hb = verdict["station_last_hb"].as_f64().unwrap();
    let frames = gcs_frames(verdict);
    let last_gcs = frames.iter().cloned().fold(f64::MIN, f64::max);
    assert!(
        frames.iter().any(|t| *t < last_hb),
        "markhold never commanded: {verdict}"
    );
    // The link relays the station's contact for STATION_RELAY_S; a frame's and the
    // scheduler's slack.
    assert!(
        last_gcs <= last_hb + markhold_autopilot::link::STATION_RELAY_S + 0.1,
        "sent as 255 {:.3} s after the station's last heartbeat",
        last_gcs - last_hb
    );
    let timeout = verdict["fs_gcs_timeout_s"].as_f64().unwrap();
    let fired = verdict["gcs_failsafe"]
        .as_array()
        .unwrap()
        .first()
        .map(|t| t.as_f64().unwrap())
        .unwrap_or_else(|| panic!("the vehicle's GCS failsafe never fired: {verdict}"));
    let bound = markhold_autopilot::station_timeout_s(timeout);
    eprintln!(
        "station silent: last SYSID_MYGCS frame {:.3} s and GCS failsafe {:.3} s after the \
         station's last heartbeat (FS_GCS_TIMEOUT {timeout} s, station timeout {bound} s)",
        last_gcs - last_hb,
        fired - last_hb
    );
    // Not kept quiet: the failsafe fires within the vehicle's own timeout and check
    // period of markhold's last SYSID_MYGCS frame ...
    assert!(fired - last_gcs >= timeout - 1e-3, "{verdict}");
    assert!(fired - last_gcs <= timeout + 0.3 + 0.2, "{verdict}");
    // ... and so within FS_GCS_TIMEOUT + 1 s of the station's last heartbeat, as
    // without markhold but for the relay window.
    assert!(fired - last_hb <= timeout + 1.0, "{verdict}");
    assert_eq!(verdict["armed_at_end"], false, "FS_GCS_ENABLE = 2 disarms");
    // markhold heard the vehicle say so.
    assert!(
        stderr.contains("vehicle says: MYGCS: 255, heartbeat lost"),
        "{stderr}"
    );
}

#[test]
fn when_the_pilot_station_falls_silent_markhold_stops_as_the_gcs_and_the_failsafe_fires() {
    let _one = one_at_a_time();
    let summary = tmp("station.json");
    let (stderr, verdict) = run_against(
        &["--scenario", "station", "--station-silent-after", "1.0"],
        &site_path(),
        &summary,
    );
    assert_station_loss_lets_the_failsafe_fire(&verdict, &stderr);
    let s = read_summary(&summary);
    assert_eq!(s["hand_back"], "not_commanding", "{s}");
    assert!(s["engagement"].to_string().contains("station_lost"), "{s}");
}

/// On Blue Robotics' ArduSub V4.2.0dev (the SITL markhold flies), RC overrides are not
/// ground-station contact: with markhold's heartbeat no longer from SYSID_MYGCS, the
/// failsafe fires as without markhold, within FS_GCS_TIMEOUT and its 0.3 s check period
/// of the station's last heartbeat, while markhold still commands.
#[test]
fn on_ardusub_4_2_the_gcs_failsafe_fires_as_without_markhold() {
    let _one = one_at_a_time();
    let (mut v, port) = vehicle(&[
        "--scenario",
        "station",
        "--station-silent-after",
        "1.0",
        "--ardusub",
        "4.2dev",
    ]);
    let o = run(&site_path(), port, &tmp("station-42.json"));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let verdict = pymav_verdict(&mut v);
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert_identity(&verdict);
    let last_hb = verdict["station_last_hb"].as_f64().unwrap();
    let timeout = verdict["fs_gcs_timeout_s"].as_f64().unwrap();
    let fired = verdict["gcs_failsafe"][0]
        .as_f64()
        .unwrap_or_else(|| panic!("the GCS failsafe never fired: {verdict}"));
    eprintln!(
        "ArduSub 4.2dev rules: GCS failsafe {:.3} s after the station's last heartbeat",
        fired - last_hb
    );
    assert!(fired - last_hb >= timeout - 1e-3, "{verdict}");
    assert!(fired - last_hb <= timeout + 1.0, "{verdict}");
    let last_gcs = gcs_frames(&verdict).into_iter().fold(f64::MIN, f64::max);
    assert!(
        last_gcs <= last_hb + markhold_autopilot::link::STATION_RELAY_S + 0.1,
        "{verdict}"
    );
}

#[test]
fn hil_vehicle_stops_as_the_gcs_when_the_pilot_station_falls_silent() {
    let _one = one_at_a_time();
    let (stderr, verdict) = hil_against(
        &["--scenario", "station", "--station-silent-after", "1.0"],
        &site_path(),
        "8",
    );
    assert_station_loss_lets_the_failsafe_fire(&verdict, &stderr);
}

/// After the pilot's takeover: one neutral, the text, the release; then nothing to the
/// end of the run and its exit (the order markhold sent them in). The pilot flies on
/// (still armed), no failsafe fired, and markhold spoke as whom it should.
fn assert_released_after_takeover(verdict: &Value) {
    let around = &verdict["around_off_text"];
    assert_eq!(around["before"], "neutral", "{verdict}");
    assert_eq!(around["after"], serde_json::json!(["release"]), "{verdict}");
    assert!(
        pymav_texts(verdict).iter().any(|t| t == "markhold stopped"),
        "{verdict}"
    );
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["gcs_failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["armed_at_end"], true, "{verdict}");
    assert_identity(verdict);
}

/// After the pilot's takeover (a mode switch) `run` sends one neutral, says why, sends
/// the release, and then nothing as SYSID_MYGCS to the end of the run, its exit
/// included; the pilot flies on, no failsafe fires.
#[test]
fn after_a_takeover_run_sends_nothing_as_the_gcs_also_at_exit() {
    let _one = one_at_a_time();
    let summary = tmp("takeover.json");
    let (_, verdict) = run_against(
        &["--scenario", "takeover", "--takeover-after", "1.0"],
        &site_path(),
        &summary,
    );
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert_released_after_takeover(&verdict);
    let s = read_summary(&summary);
    assert_eq!(s["hand_back"], "not_commanding", "{s}");
    assert_eq!(s["exit"]["commanding"], false, "{s}");
}

/// `hil --vehicle` like `run`: after the pilot's takeover (a mode switch) markhold sends
/// what was in flight, one neutral and the release, then nothing as SYSID_MYGCS, also
/// at its exit; the pilot flies on, no failsafe fires.
#[test]
fn hil_vehicle_after_a_takeover_sends_nothing_as_the_gcs_also_at_exit() {
    let _one = one_at_a_time();
    let (stderr, verdict) = hil_against(
        &["--scenario", "takeover", "--takeover-after", "1.0"],
        &site_path(),
        "4",
    );
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert!(stderr.contains("disengaged why=ModeChanged"), "{stderr}");
    assert_released_after_takeover(&verdict);
}

/// `hil --vehicle` ends as `run` does: with nobody at the joystick the hand-back keeps
/// the sticks centred, then disarms and says so; neither failsafe fires.
#[test]
fn hil_vehicle_exit_without_a_pilot_hands_back_then_disarms_and_no_failsafe_fires() {
    let _one = one_at_a_time();
    let site = site_with("hil-noplan.toml", "hand_back_timeout_s = 1.0");
    let (stderr, verdict) = hil_against(&["--scenario", "noplan"], &site, "3");
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    let said = pymav_texts(&verdict);
    for t in [
        "markhold off: stopped",
        "markhold stopped: take the controls",
        "markhold: no pilot input, disarming",
    ] {
        assert!(said.iter().any(|s| s == t), "{t}: {said:?}");
    }
    assert!(
        stderr.contains("neutral input at exit: RcChannels"),
        "{stderr}"
    );
    assert_eq!(verdict["armed_at_end"], false, "{verdict}");
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["gcs_failsafe"], serde_json::json!([]), "{verdict}");
    let applied: Vec<u64> = verdict["applied_at_end"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_u64().unwrap())
        .collect();
    assert_eq!(applied[..6], [1500; 6], "{verdict}");
    assert_identity(&verdict);
}

/// The `--scenario exit` vehicle: its stdout lines on a channel, its stdin held open
/// (closing it ends the run and brings the verdict).
struct ExitVehicle {
    child: Child,
    lines: mpsc::Receiver<String>,
    cmds: u64,
}

impl Drop for ExitVehicle {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl ExitVehicle {
    /// Over `mode` (udp, tcp, pty); its address line ("UDP 1234", "TCP 1234", "PTY /dev/pts/3").
    fn start(mode: &str) -> (Self, String) {
        markhold_testkit::require_pymavlink();
        let mut child = Command::new("python3")
            .arg(repo("autopilot/tests/pymav_vehicle.py"))
            .args(["--scenario", "exit", "--mode", mode, "--deadline", "900"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn python3");
        let out = child.stdout.take().unwrap();
        let rx = markhold_testkit::lines_on_channel(out);
        let first = rx
            .recv_timeout(Duration::from_secs(20))
            .expect("the exit vehicle did not start");
        (
            Self {
                child,
                lines: rx,
                cmds: 0,
            },
            first,
        )
    }

    /// Sessions that applied an input off neutral so far (their "CMD ..." lines).
    fn commanded(&mut self) -> u64 {
        self.cmds += self
            .lines
            .try_iter()
            .filter(|l| l.starts_with("CMD "))
            .count() as u64;
        self.cmds
    }

    /// Every session's record, once stdin is closed.
    fn finish(mut self) -> Vec<Value> {
        drop(self.child.stdin.take());
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let l = self
                .lines
                .recv_timeout(deadline.saturating_duration_since(Instant::now()))
                .expect("no verdict from the exit vehicle");
            if l.starts_with('{') {
                let v: Value = serde_json::from_str(&l).unwrap();
                return v["sessions"].as_array().unwrap().clone();
            }
        }
    }
}

/// Each session commanded off neutral, and the vehicle was left with neutral applied.
fn assert_all_neutral(sessions: &[Value], n: usize, what: &str) {
    assert_eq!(sessions.len(), n, "{what}: {sessions:?}");
    let commanded = sessions
        .iter()
        .filter(|s| s["cmd_applied"].as_u64().unwrap() > 0)
        .count();
    let neutral = sessions.iter().filter(|s| s["neutral"] == true).count();
    eprintln!(
        "{what}: {neutral} of {n} exits left neutral applied ({commanded} commanded off neutral)"
    );
    let bad: Vec<&Value> = sessions.iter().filter(|s| s["neutral"] != true).collect();
    assert!(bad.is_empty(), "{what}: not neutral at the end: {bad:?}");
    assert_eq!(commanded, n, "{what}: {sessions:?}");
}

/// A pseudo-random effort off neutral (a fixed sequence: the run repeats).
fn effort_of(k: u64) -> Effort {
    let x = k
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let f = |s: u32| (((x >> s) & 0xff) as f64 / 255.0 - 0.5) * 1.2;
    let mut e = Effort::from_array([f(8), f(16), f(24), f(32), f(40), f(48)]);
    e.surge = 0.3 + 0.2 * f(56).abs();
    e
}

/// `n` runs in this process on one vehicle over `mode`, each ended by the real exit
/// (`EngagedLink::exit`, as `run` and `hil --vehicle` end) while commanding a random
/// effort, at a random moment after the vehicle applied its first command.
fn exits_in_process(mode: &str, n: u64) {
    let (mut v, first) = ExitVehicle::start(mode);
    let url = match mode {
        "udp" => format!("udpout:127.0.0.1:{}", first.trim_start_matches("UDP ")),
        "tcp" => format!("tcp:127.0.0.1:{}", first.trim_start_matches("TCP ")),
        _ => format!("serial:{}:115200", first.trim_start_matches("PTY ")),
    };
    let cfg = LinkConfig {
        url,
        mode: LinkMode::Manual,
        stream_hz: 50.0,
        pilot_input_hz: 50.0,
        ..LinkConfig::default()
    };
    for i in 0..n {
        let mut link = VehicleLink::connect(&cfg).unwrap();
        link.set_pilot_keepalive(false);
        let t0 = Instant::now();
        let now = || t0.elapsed().as_secs_f64();
        while !link.state().discovered {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "exit {i}: no vehicle"
            );
            link.tick(now()).unwrap();
            std::thread::sleep(Duration::from_millis(2));
        }
        // Which run this is, for a vehicle that sees one serial line.
        link.send_named_value("mh_sess", i as f32, now()).unwrap();
        let mut el = EngagedLink::new(link, true);
        let mut k = 0u64;
        let mut extra = None;
        loop {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "exit {i}: no command"
            );
            let t = now();
            markhold::pipeline::CommandLink::tick(&mut el, t).unwrap();
            markhold::pipeline::CommandLink::send_effort(&mut el, &effort_of(i * 1000 + k), t)
                .unwrap();
            k += 1;
            if extra.is_none() && v.commanded() > i {
                extra = Some(k + (i * 7919) % 5);
            }
            if extra.is_some_and(|e| k >= e) {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let policy = if i % 2 == 0 {
            ExitPolicy::HandBack
        } else {
            ExitPolicy::Disarm
        };
        let r = el.exit(policy, now());
        let shown = r.neutral.map(|s| s.shown);
        assert_eq!(shown, Some(NeutralShown::RcChannels), "exit {i}: {r:?}");
        if mode == "tcp" {
            assert!(r.close.flushed && r.close.peer_closed, "exit {i}: {r:?}");
        }
    }
    assert_all_neutral(&v.finish(), n as usize, mode);
}

#[test]
fn every_exit_over_udp_leaves_neutral_applied() {
    let _one = one_at_a_time();
    exits_in_process("udp", 100);
}

#[test]
fn every_exit_over_tcp_leaves_neutral_applied() {
    let _one = one_at_a_time();
    exits_in_process("tcp", 100);
}

#[test]
fn every_exit_over_a_serial_line_leaves_neutral_applied() {
    let _one = one_at_a_time();
    exits_in_process("pty", 100);
}

/// `markhold run` stopped by SIGTERM while commanding (off station, engaged at start),
/// 100 times: each time the vehicle is left with neutral input applied.
#[test]
fn every_sigterm_leaves_neutral_applied() {
    let _one = one_at_a_time();
    static FRAMES: OnceLock<PathBuf> = OnceLock::new();
    let frames = FRAMES.get_or_init(|| {
        // Off station: the keeper commands from the first frame.
        let site = markhold::params::load(&site_path()).unwrap();
        let start = site.t_world_marker()
            * site.site.station.t_marker_vehicle()
            * markhold::sim::hil::start_offset(&site.site.vehicle);
        let mut rig = rig_at(&site, start, 5, false);
        markhold_exposure::Camera::set_exposure_us(&mut rig, 3000.0).unwrap();
        let dir = tmp("frames-off-station");
        let mut rec = markhold_camera::FrameRecorder::create(&dir).unwrap();
        let mut f = markhold_exposure::Frame::default();
        for _ in 0..150 {
            markhold_exposure::Camera::grab(&mut rig, &mut f).unwrap();
            rec.write(&f).unwrap();
        }
        dir
    });
    let site = site_with("sigterm.toml", "stream_hz = 50.0\npilot_input_hz = 50.0");
    let (mut v, first) = ExitVehicle::start("udp");
    let port = first.trim_start_matches("UDP ").to_string();
    let n = 100;
    for i in 0..n {
        let mut child = common::spawn_quiet(
            run_engaged(&site, &frames_camera(frames))
                .arg("--link")
                .arg(format!("udpout:127.0.0.1:{port}")),
        );
        let t0 = Instant::now();
        while v.commanded() <= i {
            if let Some(status) = child.try_wait().unwrap() {
                let mut err = String::new();
                let _ = child.stderr.take().unwrap().read_to_string(&mut err);
                panic!("run {i} ended ({status}) before commanding: {err}");
            }
            assert!(
                t0.elapsed() < Duration::from_secs(20),
                "run {i}: no command applied"
            );
            std::thread::sleep(Duration::from_millis(2));
        }
        std::thread::sleep(Duration::from_millis((i * 37) % 100));
        assert!(common::sigterm(&child));
        let err = common::stderr_text(&mut child);
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(0), "run {i}: {err}");
        assert!(
            err.contains("neutral input at exit: RcChannels"),
            "run {i}: {err}"
        );
    }
    assert_all_neutral(&v.finish(), n as usize, "sigterm");
}
