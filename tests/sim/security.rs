//! Security: MAVLink 2 signing end to end between markhold and the HIL vehicle,
//! and listening sockets bound only to the configured address (loopback by default).
//! Loopback only (127.0.0.1, and the 127.0.0.2 alias of the loopback interface), ports
//! from the OS, every wait bounded.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::net::{IpAddr, Ipv4Addr, SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::time::Duration;

use markhold::params::{self, LoadedSite};
use markhold::pipeline::Observers;
use markhold::sim::hil::{HilOptions, HilRun};
use markhold_autopilot::mavlink;
use markhold_autopilot::{LinkConfig, VehicleLink};
use mavlink::dialects::ardupilotmega::{MavMessage, RC_CHANNELS_OVERRIDE_DATA};
use mavlink::{MavHeader, SigningConfig, SigningData};

/// A scratch directory for key files, unique per test.
fn scratch(name: &str) -> PathBuf {
    common::tmp_dir("sec", name)
}

fn key_file(dir: &Path, name: &str, byte: u8) -> PathBuf {
    let p = dir.join(name);
    // The hex form (64 digits and a newline), as `openssl rand -hex 32` writes it.
    let hex: String = (0..32u8)
        .map(|i| format!("{:02x}", byte.wrapping_add(i)))
        .collect();
    std::fs::write(&p, format!("{hex}\n")).unwrap();
    p
}

/// The pool fixture at 320x240, STABILIZE, signing with `key` when given.
fn site(key: Option<&Path>) -> LoadedSite {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut out = String::new();
    for line in text.lines() {
        let k = line.split('=').next().unwrap_or("").trim();
        let v = match k {
            "width_px" => "width_px = 320".to_string(),
            "height_px" => "height_px = 240".to_string(),
            "fx_px" => "fx_px = 266.5".to_string(),
            "fy_px" => "fy_px = 266.5".to_string(),
            "cx_px" => "cx_px = 160.0".to_string(),
            "cy_px" => "cy_px = 120.0".to_string(),
            "mode" => match key {
                Some(p) => format!(
                    "mode = \"stabilize\"\nsigning_key_file = \"{}\"",
                    p.display()
                ),
                None => "mode = \"stabilize\"".to_string(),
            },
            _ => line.to_string(),
        };
        out.push_str(&v);
        out.push('\n');
    }
    params::parse(&path, &out).unwrap()
}

fn station_error(hil: &HilRun) -> f64 {
    let t = hil.rig.truth();
    (hil.t_marker_station.inverse() * hil.t_world_marker.inverse() * t.t_world_vehicle)
        .translation
        .vector
        .norm()
}

/// An RC override from the GCS system id that would drive the vehicle forward at full
/// stick, unsigned or signed with `key`.
fn rogue_override(seq: u8, key: Option<[u8; 32]>) -> Vec<u8> {
    let signing = key.map(|k| SigningData::from_config(SigningConfig::new(k, 7, true, false)));
    let msg = MavMessage::RC_CHANNELS_OVERRIDE(RC_CHANNELS_OVERRIDE_DATA {
        chan1_raw: 1500,
        chan2_raw: 1500,
        chan3_raw: 1500,
        chan4_raw: 1500,
        chan5_raw: 1900,
        chan6_raw: 1500,
        target_system: 1,
        target_component: 1,
        ..Default::default()
    });
    let h = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: seq,
    };
    let mut out = Vec::new();
    mavlink::write_v2_msg_signed(&mut out, h, &msg, signing.as_ref()).unwrap();
    out
}

/// Signed both ways: the vehicle requires signed input (unsigned frames dropped) and
/// `seconds` of HIL from station (seed 6), the vehicle keyed with `vehicle_key` if any.
fn on_station(seconds: f64, vehicle_key: Option<PathBuf>) -> HilOptions {
    HilOptions {
        seconds,
        seed: 6,
        start_on_station: true,
        vehicle_signing_key_file: vehicle_key,
        ..HilOptions::default()
    }
}

/// markhold drops unsigned frames; the run arms, holds station and nothing is rejected.
/// A sender without the key (unsigned, and signed with another key) on another port
/// sends full-forward RC overrides from the GCS system id every frame: all dropped, the
/// vehicle never answers it, station is held.
#[test]
fn signed_run_holds_station_and_unsigned_override_is_ignored() {
    let dir = scratch("signed");
    let key = key_file(&dir, "key.hex", 0x40);
    let site = site(Some(&key));
    let opts = on_station(6.0, None);
    let mut hil = common::armed_hil(&site, &opts);
    let vehicle = hil.rig.mavlink_udp_addr();
    let rogue = common::side_socket();
    let fps = site.site.camera.fps;
    let frames = (opts.seconds * fps) as usize;
    let mut sent_unsigned = 0u64;
    let mut sent_bad = 0u64;
    let mut detected = 0;
    let mut max_err: f64 = 0.0;
    let stats0 = hil.rig.endpoint_stats();
    for i in 0..frames {
        // From 2 s on: the attacker's overrides, one unsigned and one with a wrong key.
        if i as f64 >= 2.0 * fps {
            rogue
                .send_to(&rogue_override(i as u8, None), vehicle)
                .unwrap();
            sent_unsigned += 1;
            rogue
                .send_to(&rogue_override(i as u8, Some([0x55; 32])), vehicle)
                .unwrap();
            sent_bad += 1;
        }
        let (rec, _) = hil.step().unwrap();
        detected += usize::from(rec.detected);
        max_err = max_err.max(station_error(&hil));
    }
    let st = hil.rig.endpoint_stats();
    let link = hil.pipeline.link().state();
    println!(
        "signed: station error max {max_err:.4} m, final {:.4} m; vehicle: {} pilot inputs \
         accepted, rejected {} unsigned / {} bad signature / {} datagrams; link: received {}, \
         rejected {} unsigned / {} bad signature",
        station_error(&hil),
        st.pilot_inputs - stats0.pilot_inputs,
        st.rejected_unsigned,
        st.rejected_signature,
        st.rejected_datagrams,
        link.counters.received,
        link.counters.rejected_unsigned,
        link.counters.rejected_bad_signature
    );
    // Both ends signed and verified: markhold heard the vehicle, the vehicle obeyed.
    assert!(link.heartbeat_ok && link.armed, "{link:?}");
    assert_eq!(link.counters.rejected_unsigned, 0);
    assert_eq!(link.counters.rejected_bad_signature, 0);
    assert!(st.pilot_inputs - stats0.pilot_inputs >= frames as u64 - 2);
    // Every rogue frame was dropped by the vehicle, none became pilot input.
    assert_eq!(st.rejected_unsigned, sent_unsigned, "{st:?}");
    assert_eq!(st.rejected_signature, sent_bad, "{st:?}");
    assert_eq!(st.pilot_inputs_dropped, 0, "{st:?}");
    // The attacker's port never became the vehicle's peer.
    let mut buf = [0u8; 512];
    assert!(
        rogue.recv_from(&mut buf).is_err(),
        "telemetry went to the rogue sender"
    );
    assert!(hil.rig.truth().armed);
    assert!(detected as f64 >= 0.95 * frames as f64);
    // Full forward stick for 4 s would have carried the vehicle well over a metre.
    assert!(max_err < 0.1, "station error up to {max_err} m");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// markhold keyed differently from the vehicle: the vehicle drops every frame markhold
/// sends (arm, mode, pilot input), markhold drops every frame of the vehicle, and the
/// arming fails with an error that names the cause.
#[test]
fn wrongly_keyed_markhold_never_commands_the_vehicle_and_says_why() {
    let dir = scratch("wrongkey");
    let ours = key_file(&dir, "markhold.hex", 0x10);
    let theirs = key_file(&dir, "vehicle.hex", 0x90);
    let site = site(Some(&ours));
    let opts = on_station(1.0, Some(theirs));
    let mut hil = HilRun::build(&site, &opts, Observers::new()).unwrap();
    let err = hil
        .arm(site.site.link.mode.ardusub())
        .expect_err("armed with the wrong key")
        .to_string();
    println!("wrong key: {err}");
    // The vehicle answers no one it cannot authenticate, so markhold hears nothing: the
    // error says signing is the likely cause.
    assert!(
        err.contains("signing") && err.contains("another key"),
        "{err}"
    );
    let st = hil.rig.endpoint_stats();
    assert!(st.rejected_signature > 0, "{st:?}");
    assert_eq!(st.messages, 0, "{st:?}");
    assert!(!hil.rig.truth().armed);
    // Frames go on: the link stays silent to a vehicle it cannot hear.
    for _ in 0..(opts.seconds * site.site.camera.fps) as usize {
        hil.step().unwrap();
    }
    let st = hil.rig.endpoint_stats();
    assert_eq!((st.messages, st.pilot_inputs), (0, 0), "{st:?}");
    assert!(!hil.pipeline.link().state().discovered);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An unsigned markhold against a vehicle that requires signing: its commands are
/// dropped, the vehicle never arms.
#[test]
fn unsigned_markhold_is_refused_by_a_signing_vehicle() {
    let dir = scratch("unsigned");
    let theirs = key_file(&dir, "vehicle.hex", 0x90);
    let site = site(None);
    let opts = on_station(1.0, Some(theirs));
    let mut hil = HilRun::build(&site, &opts, Observers::new()).unwrap();
    assert!(hil.arm(site.site.link.mode.ardusub()).is_err());
    let st = hil.rig.endpoint_stats();
    assert!(st.rejected_unsigned > 0, "{st:?}");
    assert_eq!((st.messages, st.pilot_inputs), (0, 0), "{st:?}");
    assert!(!hil.rig.truth().armed);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// markhold's listening links at `urls` are bound to `ip`, as the kernel has them.
fn assert_links_bound(urls: [&str; 2], ip: Ipv4Addr) {
    for url in urls {
        let link = VehicleLink::connect(&LinkConfig {
            url: url.into(),
            ..Default::default()
        })
        .unwrap();
        let proto = if url.starts_with("udp") { "udp" } else { "tcp" };
        assert_bound(url, proto, link.local_addr().unwrap(), ip);
    }
}

/// The local address of the socket on `port` in /proc/net/{udp,tcp} (TCP: listening
/// sockets only), as the kernel has it.
fn proc_local(proto: &str, port: u16) -> Vec<Ipv4Addr> {
    let table = std::fs::read_to_string(format!("/proc/net/{proto}")).unwrap();
    let want = format!(":{port:04X}");
    table
        .lines()
        .skip(1)
        .filter_map(|l| {
            let cols: Vec<&str> = l.split_whitespace().collect();
            let local = cols.get(1)?;
            // TCP state 0A = LISTEN.
            if proto == "tcp" && cols.get(3) != Some(&"0A") {
                return None;
            }
            let (ip, p) = local.split_once(':')?;
            if format!(":{p}") != want {
                return None;
            }
            let v = u32::from_str_radix(ip, 16).ok()?;
            Some(Ipv4Addr::from(v.swap_bytes()))
        })
        .collect()
}

fn assert_bound(what: &str, proto: &str, addr: SocketAddr, ip: Ipv4Addr) {
    assert_eq!(addr.ip(), IpAddr::V4(ip), "{what}: {addr}");
    assert_eq!(
        proc_local(proto, addr.port()),
        vec![ip],
        "{what}: /proc/net/{proto} for port {}",
        addr.port()
    );
}

/// 127.0.0.2 is on the loopback interface (all of 127/8 is on Linux); a host where it
/// cannot be bound fails the configured-address half rather than passing without it.
fn alias() -> Ipv4Addr {
    let a = Ipv4Addr::new(127, 0, 0, 2);
    if let Err(e) = UdpSocket::bind((a, 0)) {
        panic!(
            "cannot bind {a} ({e}): the configured-address checks need a second loopback address"
        );
    }
    a
}

#[test]
fn every_listener_binds_loopback_by_default_and_the_configured_address_when_given() {
    let lo = Ipv4Addr::LOCALHOST;
    // HIL vehicle endpoint, UDP and TCP.
    let cfg = markhold_hil::EndpointConfig {
        tcp_enabled: true,
        ..Default::default()
    };
    let ep = markhold_hil::VehicleEndpoint::bind(&cfg).unwrap();
    assert_bound("endpoint udp", "udp", ep.udp_addr(), lo);
    assert_bound("endpoint tcp", "tcp", ep.tcp_addr().unwrap(), lo);
    // A wildcard address is refused, not silently exposed.
    let any = markhold_hil::EndpointConfig {
        bind_ip: Ipv4Addr::UNSPECIFIED.into(),
        ..Default::default()
    };
    let e = markhold_hil::VehicleEndpoint::bind(&any).err().unwrap();
    assert!(e.to_string().contains("endpoint.bind_ip"), "{e}");

    // The HIL rig a `markhold hil` run builds.
    let site = site(None);
    let hil = HilRun::build(
        &site,
        &HilOptions {
            seconds: 1.0,
            ..HilOptions::default()
        },
        Observers::new(),
    )
    .unwrap();
    assert_bound("hil rig", "udp", hil.rig.mavlink_udp_addr(), lo);
    // markhold's own udpout link to it: connected, so local address is the route's.
    assert_bound(
        "markhold link",
        "udp",
        hil.pipeline.link().local_addr().unwrap(),
        lo,
    );
    drop(hil);

    // SITL JSON server.
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    let sitl = markhold_hil::SitlServer::bind(
        &markhold_hil::SitlConfig::default(),
        &site.site.vehicle,
        &start,
        1,
    );
    let sitl = sitl.unwrap();
    let sitl_addr = sitl.local_addr().unwrap();
    assert_bound("sitl", "udp", sitl_addr, lo);
    drop(sitl);

    // Foxglove live view.
    let mut rec = markhold::record::Recorder::live_only(Default::default()).unwrap();
    let port = rec.serve_live(0, &Default::default()).unwrap();
    assert_bound("foxglove", "tcp", SocketAddr::from((lo, port)), lo);
    drop(rec);

    // markhold's listening links.
    assert_links_bound(["udpin:127.0.0.1:0", "tcpin:127.0.0.1:0"], lo);

    // The configured address, on a loopback alias.
    let a2 = alias();
    let cfg = markhold_hil::EndpointConfig {
        bind_ip: a2.into(),
        tcp_enabled: true,
        ..Default::default()
    };
    let ep = markhold_hil::VehicleEndpoint::bind(&cfg).unwrap();
    assert_bound("endpoint udp (configured)", "udp", ep.udp_addr(), a2);
    assert_bound(
        "endpoint tcp (configured)",
        "tcp",
        ep.tcp_addr().unwrap(),
        a2,
    );
    let sitl = markhold_hil::SitlServer::bind(
        &markhold_hil::SitlConfig {
            bind_ip: a2.into(),
            port: 0,
        },
        &site.site.vehicle,
        &start,
        1,
    )
    .unwrap();
    assert_bound("sitl (configured)", "udp", sitl.local_addr().unwrap(), a2);
    assert_links_bound(["udpin:127.0.0.2:0", "tcpin:127.0.0.2:0"], a2);
}

fn heartbeat_from(system_id: u8, component_id: u8, seq: u8) -> Vec<u8> {
    use mavlink::dialects::ardupilotmega::{
        MavAutopilot, MavModeFlag, MavState, MavType, HEARTBEAT_DATA,
    };
    let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 19,
        mavtype: MavType::MAV_TYPE_SUBMARINE,
        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        system_status: MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    });
    let h = MavHeader {
        system_id: system_id.into(),
        component_id,
        sequence: seq,
    };
    let mut out = Vec::new();
    mavlink::write_v2_msg(&mut out, h, &msg).unwrap();
    out
}

/// Datagrams waiting on `sock` (non-blocking drain).
fn drain(sock: &UdpSocket) -> u64 {
    let mut buf = [0u8; 2048];
    let mut n = 0;
    while sock.recv_from(&mut buf).is_ok() {
        n += 1;
    }
    n
}

/// A `udpin:` link follows only the vehicle: a local sender of junk bytes (and of valid
/// heartbeats from another system id) that speaks first and keeps speaking at 50 Hz
/// receives nothing, the vehicle receives the link's output.
#[test]
fn udpin_is_not_hijacked_by_a_junk_sender() {
    let mut link = VehicleLink::connect(&LinkConfig {
        url: "udpin:127.0.0.1:0".into(),
        ..Default::default()
    })
    .unwrap();
    let addr = link.local_addr().unwrap();
    let junk = UdpSocket::bind("127.0.0.1:0").unwrap();
    let vehicle = UdpSocket::bind("127.0.0.1:0").unwrap();
    junk.set_nonblocking(true).unwrap();
    vehicle.set_nonblocking(true).unwrap();
    let (mut to_junk, mut to_vehicle) = (0u64, 0u64);
    let mut now = 0.0;
    for i in 0..150u32 {
        // The junk sender first in every round, so it is always "the last that spoke"
        // before the link writes.
        junk.send_to(&[0xfd, 1, 2, 3, 4, 5, 6, 7], addr).unwrap();
        junk.send_to(&heartbeat_from(42, 1, i as u8), addr).unwrap();
        if i % 3 == 0 {
            vehicle
                .send_to(&heartbeat_from(1, 1, i as u8), addr)
                .unwrap();
        }
        junk.send_to(&[0x55; 8], addr).unwrap();
        link.tick(now).unwrap();
        now += 0.02;
        std::thread::sleep(Duration::from_millis(2));
        to_junk += drain(&junk);
        to_vehicle += drain(&vehicle);
    }
    std::thread::sleep(Duration::from_millis(20));
    to_junk += drain(&junk);
    to_vehicle += drain(&vehicle);
    assert!(link.state().heartbeat_ok, "{:?}", link.state());
    assert!(
        to_vehicle > 20,
        "the vehicle received {to_vehicle} datagrams"
    );
    assert_eq!(to_junk, 0, "the junk sender received {to_junk} datagrams");
}

/// Run the built binary with `args`, bounded to 60 s; (status code, stderr).
fn run_bounded(args: &[&str]) -> (Option<i32>, String) {
    let mut child = common::spawn_quiet(common::markhold().args(args));
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    common::exit_status_by(
        &mut child,
        deadline,
        &format!("markhold {args:?} did not end"),
    );
    let out = child.wait_with_output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A device or a FIFO as a site or calibration file is refused at once (exit 78), not
/// read without end or waited on.
#[test]
fn devices_and_fifos_are_refused_as_site_and_calibration_files() {
    let dir = scratch("special-files");
    let fifo = dir.join("site.fifo");
    let _ = std::fs::remove_file(&fifo);
    assert!(std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success());
    for file in ["/dev/zero", fifo.to_str().unwrap()] {
        let (code, err) = run_bounded(&["params", "check", file]);
        assert_eq!(code, Some(78), "{file}: {err}");
        assert!(err.contains("not a regular file"), "{file}: {err}");
    }
    // A calibration file that is /dev/zero.
    let site = dir.join("site.toml");
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml"),
    )
    .unwrap()
    .replace("[camera]", "[camera]\ncalibration_file = \"/dev/zero\"");
    std::fs::write(&site, text).unwrap();
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(78), "{err}");
    assert!(
        err.contains("calibration_file") && err.contains("not a regular file"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Out-of-range durations and overrides are errors, not aborts or silent clamps.
#[test]
fn hil_refuses_absurd_seconds_and_bad_initial_exposure() {
    let site = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = site.to_str().unwrap();
    let (code, err) = run_bounded(&["hil", "--quiet", "--site", site, "--seconds", "1e12"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--seconds"), "{err}");
    for v in ["nan", "inf", "0", "-5"] {
        let flag = format!("--initial-exposure-us={v}");
        let (code, err) =
            run_bounded(&["hil", "--quiet", "--site", site, "--seconds", "0.1", &flag]);
        assert_eq!(code, Some(78), "{v}: {err}");
        assert!(err.contains("--initial-exposure-us"), "{v}: {err}");
    }
}

/// `markhold params check FILE | head -1`: stdout closed before the report is written
/// ends the program quietly with status 0, no panic.
#[test]
fn a_closed_stdout_ends_quietly() {
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let site = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let out = common::markhold()
        .args(["params", "check"])
        .arg(&site)
        .stdout(writer)
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let err = crate::common::stderr_of_exit(&out, 0);
    assert!(!err.contains("panicked"), "{err}");
}

/// The signing key file is resolved against the site file and checked by `params
/// check`: missing, or 10 bytes long, is a config error (exit 78) naming the key.
#[test]
fn params_check_checks_the_signing_key() {
    let dir = scratch("key-check");
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(fixture).unwrap();
    let with_key = |key: &str| {
        let site = dir.join("site.toml");
        let t = text.replace("[link]", &format!("[link]\nsigning_key_file = \"{key}\""));
        std::fs::write(&site, t).unwrap();
        site
    };
    let site = with_key("missing.key");
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(78), "{err}");
    assert!(err.contains("link.signing_key_file"), "{err}");
    std::fs::write(dir.join("short.key"), [7u8; 10]).unwrap();
    let site = with_key("short.key");
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(78), "{err}");
    assert!(err.contains("10 bytes"), "{err}");
    // A good key next to the site file, named relative to it, from another directory.
    key_file(&dir, "good.key", 3);
    let site = with_key("good.key");
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    // A saved signing timestamp beside it that is not a number: refused, naming the file.
    std::fs::write(dir.join("good.key.timestamp"), "garbage\n").unwrap();
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(78), "{err}");
    assert!(
        err.contains("good.key.timestamp") && err.contains("garbage"),
        "{err}"
    );
    std::fs::write(dir.join("good.key.timestamp"), "123456789\n").unwrap();
    let (code, err) = run_bounded(&["params", "check", site.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A missing site file: exit 78, the OS error said once.
#[test]
fn a_missing_site_file_names_the_os_error_once() {
    let (code, err) = run_bounded(&["hil", "--site", "nope-does-not-exist.toml"]);
    assert_eq!(code, Some(78), "{err}");
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
}

/// A vehicle that cannot be reached is said at once, with the cause, not after a 15 s
/// wait for a pose.
#[test]
fn an_unreachable_vehicle_is_reported_with_its_cause() {
    // A port nobody listens on: bind one, note it, close it.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let site = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = site.to_str().unwrap();
    let tcp = format!("tcpout:127.0.0.1:{port}");
    for (url, cause) in [
        (tcp.as_str(), "Connection refused"),
        (
            "serial:/dev/nonexistent-markhold:115200",
            "No such file or directory",
        ),
    ] {
        let (code, err) = run_bounded(&[
            "hil",
            "--quiet",
            "--site",
            site,
            "--seconds",
            "1",
            "--vehicle",
            url,
        ]);
        assert_eq!(code, Some(2), "{url}: {err}");
        assert!(err.contains(cause), "{url}: {err}");
        assert!(!err.contains("no pose"), "{url}: {err}");
    }
}

/// Sizes that would allocate tens of gigabytes are refused with the flag and the limit,
/// at once: `compare --seconds`, `--seeds`, `robustness --seconds`.
#[test]
fn absurd_sweep_sizes_are_refused_before_allocating() {
    let site = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = site.to_str().unwrap();
    let out = scratch("absurd-out");
    let out = out.to_str().unwrap();
    for (args, needle) in [
        (
            vec!["compare", "--site", site, "--seconds", "1e7", "--out", out],
            "--seconds 10000000: expected a positive number of simulated seconds, at most 3600",
        ),
        (
            vec!["compare", "--site", site, "--seconds", "1e18", "--out", out],
            "at most 3600",
        ),
        (
            vec![
                "compare",
                "--site",
                site,
                "--seeds",
                "100000000",
                "--out",
                out,
            ],
            "--seeds 100000000: expected 1..1000",
        ),
        (
            vec![
                "robustness",
                "--site",
                site,
                "--seconds",
                "1e12",
                "--out",
                out,
            ],
            "at most 3600",
        ),
    ] {
        let (code, err) = run_bounded(&args);
        assert!(code.is_some_and(|c| c != 0), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(
            !err.contains("panicked") && !err.contains("memory allocation"),
            "{err}"
        );
    }
}

/// `params check` refuses what a run would misread or `hil` would refuse: a list of
/// numbers of the wrong length (the extra one was dropped), a marker of 1e300 m, a site
/// name with a newline and an escape (it reaches reports and terminals).
#[test]
fn params_check_refuses_wrong_array_lengths_and_sizes_hil_refuses() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(&fixture).unwrap();
    let dir = scratch("params");
    let cases = [
        (
            "map4",
            format!("{text}\n[[marker.map]]\nid = 3\nsize_m = 0.15\nposition_m = [0.5, 0.0, 0.0, 7.0]\n"),
            "marker.map.position_m = [0.5, 0.0, 0.0, 7.0]: 4 numbers: expected exactly 3",
        ),
        (
            "mount2",
            text.replace("mount_position_m = [0.2, 0.0, 0.0]", "mount_position_m = [0.2, 0.0]"),
            "2 numbers: expected exactly 3",
        ),
        (
            "huge",
            text.replace("size_m = 0.15 ", "size_m = 1e300 "),
            "expected a size in (0, 10] metres",
        ),
        (
            "name",
            text.replace("name = \"pool-640\"", "name = \"pool\\n# injected\\u001b[31m\""),
            "without control characters",
        ),
    ];
    for (name, body, needle) in cases {
        assert_ne!(body, text, "{name}: the case changes the fixture");
        let p = dir.join(format!("{name}.toml"));
        std::fs::write(&p, body).unwrap();
        let (code, err) = run_bounded(&["params", "check", p.to_str().unwrap()]);
        assert_eq!(code, Some(78), "{name}: {err}");
        assert!(err.contains(needle), "{name}: {err}");
    }
}
