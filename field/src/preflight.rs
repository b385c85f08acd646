//! `markhold preflight`: is the vehicle set up for markhold? Reads its parameters over
//! the MAVLink parameter protocol (PARAM_REQUEST_READ by name, PARAM_REQUEST_LIST for
//! what a read did not bring), its heartbeat and AUTOPILOT_VERSION, and prints a
//! checklist: pass / warn / fail, each with the fix. `markhold run` runs it before arming.
//!
//! The wall clock bounds the waits here (start-up, before the loop); loop time for the
//! link is the first frame's stamp plus the time waited.

use crate::error::{FieldError, StartupError};
use std::fmt::Write as _;
use std::time::{Duration, Instant};

use markhold_autopilot::{CommandKind, Frame6Dof, VehicleLink};
use serde::Serialize;

use markhold_core::params::LoadedSite;
use markhold_core::signal::ShutdownFlag;

/// Wait for parameter answers at most this long, wall seconds.
pub const PARAM_WAIT_S: f64 = 3.0;
/// Re-send the reads that have no answer after this, wall seconds.
const PARAM_RETRY_S: f64 = 0.5;
/// MAV_TYPE_SUBMARINE.
const MAV_TYPE_SUBMARINE: u8 = 12;

/// One item's verdict.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Pass,
    Warn,
    Fail,
}

/// One line of the checklist.
#[derive(Clone, Debug, Serialize)]
pub struct Item {
    pub name: &'static str,
    pub verdict: Verdict,
    /// What was found.
    pub found: String,
    /// What to do about it (empty on a pass).
    pub fix: String,
}

/// The checklist.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Checklist {
    pub items: Vec<Item>,
    /// Round trip of the first parameter read, milliseconds (wall clock).
    pub param_round_trip_ms: Option<f64>,
}

impl Checklist {
    fn add(&mut self, name: &'static str, verdict: Verdict, found: String, fix: &str) {
        self.items.push(Item {
            name,
            verdict,
            found,
            fix: if verdict == Verdict::Pass {
                String::new()
            } else {
                fix.to_string()
            },
        });
    }

    pub fn failed(&self) -> usize {
        self.count(Verdict::Fail)
    }

    pub fn count(&self, v: Verdict) -> usize {
        self.items.iter().filter(|i| i.verdict == v).count()
    }

    /// The failed items' names, comma-separated.
    pub fn failed_names(&self) -> String {
        let names: Vec<&str> = self
            .items
            .iter()
            .filter(|i| i.verdict == Verdict::Fail)
            .map(|i| i.name)
            .collect();
        names.join(", ")
    }

    pub fn item(&self, name: &str) -> Option<&Item> {
        self.items.iter().find(|i| i.name == name)
    }

    /// The checklist as text, one line per item and the fix under it.
    pub fn render(&self) -> String {
        let mut out = String::from("preflight:\n");
        for i in &self.items {
            let v = match i.verdict {
                Verdict::Pass => "pass",
                Verdict::Warn => "WARN",
                Verdict::Fail => "FAIL",
            };
            let _ = writeln!(out, "  [{v}] {:<18} {}", i.name, i.found);
            if !i.fix.is_empty() {
                let _ = writeln!(out, "         fix: {}", i.fix);
            }
        }
        let _ = writeln!(
            out,
            "preflight: {} pass, {} warn, {} fail",
            self.count(Verdict::Pass),
            self.count(Verdict::Warn),
            self.count(Verdict::Fail)
        );
        out
    }
}

/// The parameters read: the GCS id (under its old and new name), failsafes, frame, and
/// for setpoint mode the EKF sources and visual odometry.
fn wanted(setpoint: bool) -> Vec<&'static str> {
    let mut v = vec![
        "SYSID_MYGCS",
        "FS_PILOT_INPUT",
        "FS_PILOT_TIMEOUT",
        "FS_GCS_ENABLE",
        "FRAME_CONFIG",
    ];
    // ArduSub after 4.5; up to 4.5 the GCS failsafe waits a fixed 2.5 s. Not
    // waited for: an older vehicle never answers it.
    v.push("FS_GCS_TIMEOUT");
    if setpoint {
        v.extend([
            "EK3_SRC1_POSXY",
            "EK3_SRC1_VELXY",
            "EK3_SRC1_YAW",
            "VISO_TYPE",
        ]);
    }
    v
}

/// Read the parameters (by name, re-sent, then the whole list for any still missing),
/// bounded by `PARAM_WAIT_S`. Returns the first read's round trip.
fn read_params(
    link: &mut VehicleLink,
    names: &[&str],
    t0: f64,
    stop: &ShutdownFlag,
) -> Option<f64> {
    let started = Instant::now();
    let now = |s: Instant| t0 + s.elapsed().as_secs_f64();
    let mut rtt = None;
    let mut last_send = Instant::now();
    let mut listed = false;
    let send_missing = |link: &mut VehicleLink| {
        for n in names {
            if link.param(n).is_none() {
                if let Err(e) = link.request_param(n) {
                    tracing::warn!(error = %e, param = n, "param read");
                }
            }
        }
    };
    let _ = link.request_autopilot_version();
    send_missing(link);
    loop {
        if let Err(e) = link.tick(now(started)) {
            tracing::warn!(error = %e, "preflight: link");
        }
        if rtt.is_none() && names.first().is_some_and(|n| link.param(n).is_some()) {
            rtt = Some(started.elapsed().as_secs_f64() * 1e3);
        }
        // The GCS id has a newer name (MAV_GCS_SYSID): either answers. FS_GCS_TIMEOUT
        // exists only after ArduSub 4.5.
        let missing = names
            .iter()
            .filter(|n| link.param(n).is_none())
            .filter(|n| !(**n == "SYSID_MYGCS" && link.param("MAV_GCS_SYSID").is_some()))
            .filter(|n| **n != "FS_GCS_TIMEOUT")
            .count();
        let elapsed = started.elapsed().as_secs_f64();
        if missing == 0 || elapsed >= PARAM_WAIT_S || stop.is_set() {
            return rtt;
        }
        if last_send.elapsed().as_secs_f64() >= PARAM_RETRY_S {
            last_send = Instant::now();
            if elapsed >= 2.0 * PARAM_RETRY_S && !listed {
                listed = true;
                let _ = link.request_param("MAV_GCS_SYSID");
                if let Err(e) = link.request_param_list() {
                    tracing::warn!(error = %e, "param list");
                }
            } else {
                send_missing(link);
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A station heartbeats once a second: give it one period (and its jitter) to be heard,
/// if it was not during the parameter reads.
fn wait_for_station(link: &mut VehicleLink, t0: f64, stop: &ShutdownFlag) {
    let started = Instant::now();
    while link.state().station.last_s.is_none()
        && started.elapsed().as_secs_f64() < markhold_autopilot::config::STATION_TIMEOUT_MIN_S
        && !stop.is_set()
    {
        if let Err(e) = link.tick(t0 + started.elapsed().as_secs_f64()) {
            tracing::warn!(error = %e, "preflight: link");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The site's `[vehicle] frame` (`None`: the site names none, or, in a build without the
/// simulator, whose `[vehicle]` is not checked, one markhold does not know).
fn site_frame(site: &LoadedSite) -> Option<Frame6Dof> {
    let v = toml::Value::try_from(&site.site.vehicle).ok()?;
    v.get("frame")?.as_str()?.parse().ok()
}

/// Check the vehicle behind `link` (already heard) against the site. `t0`: loop time now.
pub fn check(link: &mut VehicleLink, site: &LoadedSite, t0: f64, stop: &ShutdownFlag) -> Checklist {
    let cfg = link.config().clone();
    let setpoint = cfg.command == CommandKind::Setpoint;
    let names = wanted(setpoint);
    let mut list = Checklist {
        param_round_trip_ms: read_params(link, &names, t0, stop),
        ..Checklist::default()
    };
    wait_for_station(link, t0, stop);
    let p = |n: &str| link.param(n).map(|(v, _)| v);

    check_ids_and_failsafes(&mut list, &p, &cfg, site);
    check_station(&mut list, link);
    check_frame(&mut list, p("FRAME_CONFIG"), site_frame(site));
    check_vehicle(&mut list, link, site);
    if setpoint {
        check_setpoint(&mut list, &p);
    }
    match list.param_round_trip_ms {
        Some(ms) if ms <= 100.0 => list.add(
            "link latency",
            Verdict::Pass,
            format!("{ms:.1} ms (param read round trip)"),
            "",
        ),
        Some(ms) => list.add(
            "link latency",
            Verdict::Warn,
            format!("{ms:.1} ms (param read round trip)"),
            "over 100 ms: check the tether and that markhold runs beside the vehicle (BlueOS)",
        ),
        None => list.add(
            "link latency",
            Verdict::Warn,
            "no parameter read answered".into(),
            "check the link",
        ),
    }
    list
}

/// The GCS id and the failsafe parameters.
fn check_ids_and_failsafes(
    list: &mut Checklist,
    p: &dyn Fn(&str) -> Option<f32>,
    cfg: &markhold_autopilot::LinkConfig,
    site: &LoadedSite,
) {
    let not_read = |n: &str| format!("{n} not reported by the vehicle");
    // Pilot input is dropped unless it comes from the GCS id.
    let gcs = p("SYSID_MYGCS").or_else(|| p("MAV_GCS_SYSID"));
    match gcs {
        Some(v) if v.round() as i64 == i64::from(cfg.gcs_system_id) => list.add(
            "gcs id",
            Verdict::Pass,
            format!("SYSID_MYGCS = {v} = link.gcs_system_id"),
            "",
        ),
        Some(v) => list.add(
            "gcs id",
            Verdict::Fail,
            format!(
                "SYSID_MYGCS = {v}, markhold sends as system {}",
                cfg.gcs_system_id
            ),
            &format!(
                "ArduSub drops pilot input from any other system id: set SYSID_MYGCS = {} \
                 in QGroundControl, or link.gcs_system_id = {v} in the site file",
                cfg.gcs_system_id
            ),
        ),
        None => list.add(
            "gcs id",
            Verdict::Fail,
            not_read("SYSID_MYGCS"),
            "check the link (a vehicle that answers no PARAM_REQUEST_READ is not ArduSub)",
        ),
    }
    match p("FS_PILOT_INPUT") {
        Some(v) if v.round() as i64 != 0 => list.add(
            "pilot failsafe",
            Verdict::Pass,
            format!("FS_PILOT_INPUT = {v}"),
            "",
        ),
        Some(v) => list.add(
            "pilot failsafe",
            Verdict::Fail,
            format!("FS_PILOT_INPUT = {v} (disabled)"),
            "set FS_PILOT_INPUT = 2 (disarm): with it off, nothing stops the thrusters \
             if markhold and the pilot's joystick both go quiet",
        ),
        None => list.add(
            "pilot failsafe",
            Verdict::Fail,
            not_read("FS_PILOT_INPUT"),
            "check the ArduSub version",
        ),
    }
    let frame_period = 1.0 / site.site.camera.fps;
    match p("FS_PILOT_TIMEOUT") {
        Some(v) if f64::from(v) >= 3.0 * frame_period.max(1.0 / cfg.pilot_input_hz) && v <= 5.0 => {
            list.add(
                "pilot timeout",
                Verdict::Pass,
                format!("FS_PILOT_TIMEOUT = {v} s"),
                "",
            )
        }
        Some(v) => list.add(
            "pilot timeout",
            Verdict::Warn,
            format!("FS_PILOT_TIMEOUT = {v} s"),
            "use 1..5 s (default 3): shorter trips on a camera hiccup, longer leaves \
             the vehicle running on a dead link",
        ),
        None => list.add(
            "pilot timeout",
            Verdict::Warn,
            not_read("FS_PILOT_TIMEOUT"),
            "set FS_PILOT_TIMEOUT = 3",
        ),
    }
    match p("FS_GCS_ENABLE") {
        Some(v) if v.round() as i64 != 0 => list.add(
            "gcs failsafe",
            Verdict::Pass,
            format!("FS_GCS_ENABLE = {v}"),
            "",
        ),
        Some(v) => list.add(
            "gcs failsafe",
            Verdict::Warn,
            format!("FS_GCS_ENABLE = {v} (disabled)"),
            "set FS_GCS_ENABLE = 2 (disarm) or 4 (surface) so a lost tether is handled: \
             markhold stops when the pilot's station falls silent and leaves the rest to it",
        ),
        None => list.add(
            "gcs failsafe",
            Verdict::Warn,
            not_read("FS_GCS_ENABLE"),
            "set FS_GCS_ENABLE = 2",
        ),
    }
}

/// The pilot's station and the GCS failsafe's timeout: how long markhold may keep
/// commanding after the station falls silent (`markhold_autopilot::station_timeout_s`).
fn check_station(list: &mut Checklist, link: &VehicleLink) {
    let (t, read) = link.fs_gcs_timeout_s();
    let bound = link.station_timeout_s();
    let source = if read {
        format!("FS_GCS_TIMEOUT = {t} s")
    } else {
        format!("FS_GCS_TIMEOUT not reported (ArduSub 4.5 and older: a fixed {t} s)")
    };
    let found = format!(
        "{source}; markhold's pilot input stops {bound:.2} s after the pilot's station \
         falls silent, so the GCS failsafe fires at most that much later than without it"
    );
    let verdict = if bound > 0.5 * t + 1e-9 {
        Verdict::Warn
    } else {
        Verdict::Pass
    };
    list.add(
        "gcs timeout",
        verdict,
        found,
        "FS_GCS_TIMEOUT under 2.4 s: markhold delays the failsafe by more than half of it \
         (a station heartbeats at 1 Hz: markhold cannot tell it lost sooner); 5 s is \
         ArduSub's default",
    );
    let st = link.state().station;
    match (st.last_s, st.component_id) {
        (Some(_), Some(comp)) if !st.lost => list.add(
            "pilot station",
            Verdict::Pass,
            format!(
                "heard: system {} component {comp} ({} heartbeats)",
                link.config().gcs_system_id,
                st.heartbeats
            ),
            "",
        ),
        _ => list.add(
            "pilot station",
            Verdict::Warn,
            format!(
                "no HEARTBEAT from SYSID_MYGCS ({}) heard",
                link.config().gcs_system_id
            ),
            "start QGroundControl and check that the router forwards its heartbeat to \
             markhold: markhold engages only while it hears the pilot's station (to let \
             ArduSub's GCS failsafe fire when it falls silent)",
        ),
    }
}

/// FRAME_CONFIG against the site's `[vehicle] frame`: 1 = vectored (BlueROV2, 6
/// thrusters), 2 = vectored 6-DOF (BlueROV2 Heavy, 8 thrusters).
fn check_frame(list: &mut Checklist, frame_config: Option<f32>, site: Option<Frame6Dof>) {
    let expect = site.map(Frame6Dof::frame_config);
    match (frame_config, expect) {
        (Some(v), Some(e)) if v.round() as i64 == e => list.add(
            "frame",
            Verdict::Pass,
            format!("FRAME_CONFIG = {v} matches [vehicle] frame"),
            "",
        ),
        (Some(v), Some(e)) => list.add(
            "frame",
            Verdict::Fail,
            format!("FRAME_CONFIG = {v}, the site's [vehicle] frame wants {e}"),
            "set FRAME_CONFIG (1 = BlueROV2, 2 = Heavy) or fix [vehicle] frame: the gains \
             were tuned for the site's frame",
        ),
        (Some(v), None) => list.add(
            "frame",
            Verdict::Warn,
            format!("FRAME_CONFIG = {v}, no [vehicle] frame in the site"),
            "name the frame in the site file ([vehicle] frame = \"heavy\" | \"standard\")",
        ),
        (None, _) => list.add(
            "frame",
            Verdict::Warn,
            "FRAME_CONFIG not reported".into(),
            "check the ArduSub version",
        ),
    }
}

/// The vehicle itself: a submarine, its ArduSub version, and whether the site's mode exists.
fn check_vehicle(list: &mut Checklist, link: &VehicleLink, site: &LoadedSite) {
    let st = link.state();
    let mode = site.site.link.mode.ardusub();
    if st.vehicle_type == MAV_TYPE_SUBMARINE {
        list.add(
            "mode",
            Verdict::Pass,
            format!(
                "{mode:?} ({}) on an ArduSub vehicle (MAV_TYPE_SUBMARINE)",
                mode.number()
            ),
            "",
        );
    } else {
        list.add(
            "mode",
            Verdict::Fail,
            format!(
                "the vehicle's heartbeat says MAV_TYPE {}, not a submarine (12)",
                st.vehicle_type
            ),
            "connect to the ArduSub autopilot (is this the right link?)",
        );
    }
    match st.flight_sw_version {
        Some(v) => {
            let (major, minor, patch) = (v >> 24, (v >> 16) & 0xff, (v >> 8) & 0xff);
            let verdict = if major >= 4 {
                Verdict::Pass
            } else {
                Verdict::Warn
            };
            list.add(
                "ardusub version",
                verdict,
                format!("{major}.{minor}.{patch}"),
                "markhold is checked against ArduSub 4.x: update the autopilot firmware",
            );
        }
        None => list.add(
            "ardusub version",
            Verdict::Warn,
            "no AUTOPILOT_VERSION answer".into(),
            "the version is unknown: check it in QGroundControl",
        ),
    }
}

/// Setpoint mode needs the EKF on external navigation and MAVLink visual odometry.
fn check_setpoint(list: &mut Checklist, p: &dyn Fn(&str) -> Option<f32>) {
    let items: [(&'static str, &str, &[i64], &str); 4] = [
        (
            "ekf xy source",
            "EK3_SRC1_POSXY",
            &[6],
            "set EK3_SRC1_POSXY = 6 (ExternalNav)",
        ),
        (
            "ekf velocity src",
            "EK3_SRC1_VELXY",
            &[6, 0],
            "set EK3_SRC1_VELXY = 6 (ExternalNav) or 0",
        ),
        (
            "ekf yaw source",
            "EK3_SRC1_YAW",
            &[6, 1],
            "set EK3_SRC1_YAW = 6 (ExternalNav) or 1 (compass)",
        ),
        (
            "visual odometry",
            "VISO_TYPE",
            &[1],
            "set VISO_TYPE = 1 (MAVLink) and reboot",
        ),
    ];
    for (name, param, ok, fix) in items {
        match p(param) {
            Some(v) if ok.contains(&(v.round() as i64)) => {
                list.add(name, Verdict::Pass, format!("{param} = {v}"), "");
            }
            Some(v) => list.add(name, Verdict::Fail, format!("{param} = {v}"), fix),
            None => list.add(name, Verdict::Fail, format!("{param} not reported"), fix),
        }
    }
}

/// `markhold preflight`: open the link, wait for the vehicle (wall clock, bounded), check.
pub fn preflight(
    site: &LoadedSite,
    url: Option<&str>,
    heartbeat_timeout_s: f64,
    stop: &ShutdownFlag,
) -> Result<Checklist, FieldError> {
    let mut cfg = site.site.link.clone();
    if let Some(u) = url {
        cfg.url = u.to_string();
    }
    let mut link = VehicleLink::connect(&cfg).map_err(|e| StartupError::Link {
        url: cfg.url.clone(),
        reason: e.to_string(),
    })?;
    // Only parameter traffic: no pilot input at all.
    link.set_pilot_keepalive(false);
    let started = Instant::now();
    let timeout = Duration::from_secs_f64(heartbeat_timeout_s.clamp(0.0, 600.0));
    loop {
        link.tick(started.elapsed().as_secs_f64())?;
        if link.state().last_heartbeat_s.is_some() {
            break;
        }
        if started.elapsed() >= timeout || stop.is_set() {
            return Err(StartupError::NoHeartbeat {
                url: cfg.url,
                timeout_s: heartbeat_timeout_s,
            }
            .into());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(check(
        &mut link,
        site,
        started.elapsed().as_secs_f64(),
        stop,
    ))
}
