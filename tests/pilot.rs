//! `markhold run` beside a pilot: a pymavlink vehicle (autopilot/tests/pymav_vehicle.py,
//! `--scenario pilot`) plays ArduSub with QGroundControl (system 255, component 190)
//! beside it. The pilot engages by arming in the site's mode, switches mode away (markhold
//! must go quiet within 100 ms and stay quiet), switches back (engaged again), moves a
//! stick (markhold lets go), engages a third time; markhold then stops at the end of its
//! frames and hands back. `markhold preflight` against the same vehicle passes on a good
//! parameter set and fails on FS_PILOT_INPUT = 0 and on a SYSID_MYGCS mismatch.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;

use common::{markhold, repo, site_path, station_frames, tmp_path};

fn tmp(name: &str) -> PathBuf {
    tmp_path("pilot", name)
}

/// 8 s of frames on station (the pilot's plan takes about 4 s), made once.
fn frames_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| station_frames(tmp("frames"), 240))
}

/// The pymavlink vehicle; killed on drop if still running.
struct Vehicle(Child);

impl Drop for Vehicle {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start the vehicle with `args`; its UDP port.
fn vehicle(args: &[&str]) -> (Vehicle, u16) {
    markhold_testkit::require_pymavlink();
    let mut child = Command::new("python3")
        .arg(repo("autopilot/tests/pymav_vehicle.py"))
        .args(["--deadline", "40"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn python3");
    let mut line = String::new();
    BufReader::new(child.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .unwrap();
    let port = line
        .trim()
        .strip_prefix("UDP ")
        .unwrap_or_else(|| panic!("vehicle said {line:?}"))
        .parse()
        .unwrap();
    (Vehicle(child), port)
}

/// The vehicle's verdict (it ends 1.5 s after markhold falls silent).
fn verdict(v: &mut Vehicle) -> serde_json::Value {
    let mut out = String::new();
    v.0.stdout
        .as_mut()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    let _ = v.0.wait();
    let last = out.lines().last().unwrap_or_default();
    serde_json::from_str(last).unwrap_or_else(|e| panic!("verdict {out:?}: {e}"))
}

fn texts(v: &serde_json::Value) -> Vec<String> {
    v["texts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t[2].as_str().unwrap().to_string())
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
    let (mut v, port) = vehicle(&["--scenario", "pilot"]);
    let summary = tmp("pilot.json");
    let o = run(&site_path(), port, &summary);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let verdict = verdict(&mut v);
    let said = texts(&verdict);
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
    // After the mode change: what was in flight and one neutral, then only the release.
    let after = verdict["inputs_after_mode_change"].as_array().unwrap();
    let pilot_inputs = after.iter().filter(|k| *k != "release").count();
    assert!(pilot_inputs <= 2, "{after:?}");
    assert_eq!(verdict["release_seen"], true, "{verdict}");
    eprintln!(
        "pilot: last pilot input {} ms after the pilot's mode change (wall clock, loopback)",
        verdict["last_input_after_mode_change_ms"]
    );
    assert_eq!(verdict["inputs_while_off"], 0, "{verdict}");
    // Handed back: still armed, the failsafe never fired.
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    assert_eq!(verdict["armed_at_end"], true, "{verdict}");
    assert_eq!(
        verdict["named"],
        serde_json::json!(["mh_err_m", "mh_yaw_deg"])
    );
    // The vehicle's own STATUSTEXT lands in markhold's log.
    assert!(stderr.contains("vehicle says: Leak Detected!"), "{stderr}");
    assert!(stderr.contains("vehicle reports a failsafe"), "{stderr}");
    // The preflight ran (parameter reads) before the loop.
    assert!(verdict["param_reads"].as_u64().unwrap() >= 5, "{verdict}");
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&summary).unwrap()).unwrap();
    assert_eq!(s["engagements"], 3, "{s}");
    assert_eq!(s["hand_back"], "pilot_took_over", "{s}");
    assert!(s["withheld"].as_u64().unwrap() > 0, "{s}");
}

#[test]
fn with_nobody_at_the_joystick_the_hand_back_disarms_and_says_so() {
    let site = site_with("handback.toml", "hand_back_timeout_s = 1.0");
    let (mut v, port) = vehicle(&["--scenario", "pilot", "--no-pilot-after-exit"]);
    let summary = tmp("handback.json");
    let o = run(&site, port, &summary);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let verdict = verdict(&mut v);
    let said = texts(&verdict);
    assert_eq!(verdict["failures"], serde_json::json!([]), "{verdict}");
    assert!(
        said.iter()
            .any(|t| t == "markhold: no pilot input, disarming"),
        "{said:?}"
    );
    assert_eq!(verdict["armed_at_end"], false, "{verdict}");
    // markhold disarmed it; ArduSub's failsafe did not have to.
    assert_eq!(verdict["failsafe"], serde_json::json!([]), "{verdict}");
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&summary).unwrap()).unwrap();
    assert_eq!(s["hand_back"]["disarmed"], "Accepted", "{s}");
}

fn preflight(extra: &[&str]) -> (std::process::Output, serde_json::Value) {
    let mut args = vec!["--scenario", "params"];
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
    (o, verdict(&mut v))
}

#[test]
fn preflight_passes_a_good_vehicle_and_fails_a_bad_one_with_the_fix() {
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
    let (mut v, port) = vehicle(&["--scenario", "params", "--param", "FS_PILOT_INPUT=0"]);
    let o = run(&site_path(), port, &tmp("refused.json"));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("failed the preflight check"), "{stderr}");
    assert!(stderr.contains("--no-preflight"), "{stderr}");
    let verdict = verdict(&mut v);
    // Nothing but parameter traffic: no pilot input, no arming.
    assert_eq!(verdict["armed_at_end"], false, "{verdict}");
}

/// The pilot's QGroundControl on a second TCP connection to the external vehicle, as
/// system 255, component 190 (a `VehicleLink` with QGroundControl's ids): switches mode
/// away at `away_s`, pushes the vehicle sideways with its own overrides, releases them and
/// switches back at `back_s` (wall seconds from the start). Returns how far the vehicle
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
                // The pilot nudges it off station (not so far that the marker leaves the view).
                1 if t < away_s + 1.2 => {
                    let push = Effort {
                        sway: 0.6,
                        ..Effort::NEUTRAL
                    };
                    qgc.send_effort(&push, t).unwrap();
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
    use common::RealTimeVehicle;
    use markhold::params;
    use markhold_hil::{EndpointConfig, HilRig, HilSetup, VehicleMotion};
    let site = params::load(&site_path()).unwrap();
    let s = &site.site;
    let t_world_station = site.t_world_marker() * s.station.t_marker_vehicle();
    let rig = HilRig::new(HilSetup {
        vehicle: s.vehicle.clone(),
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
    let o = markhold()
        .args(["hil", "--quiet", "--seconds", "16", "--site"])
        .arg(&site_file)
        .arg("--vehicle")
        .arg(format!("tcp:{tcp}"))
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
    assert!(stderr.contains("neutral input at exit: RcChannels"), "{stderr}");
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
    // push, about 0.2 m, plus its positive buoyancy) ...
    assert!(
        moved > 0.15,
        "the vehicle moved {moved:.3} m while markhold was off"
    );
    // ... and markhold brought it back after the pilot engaged it again (the error at
    // the run's last frame, from the vehicle's telemetry: after it the exit hands back
    // and the vehicle, neutral, drifts on its buoyancy).
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
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
    verdict(&mut v)
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
