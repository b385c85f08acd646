//! `markhold run` end to end: the recorded-frames camera, hil's vehicle endpoint as the
//! vehicle (free-running on its own thread, like ArduSub would be), a recording that
//! replays; SIGTERM stops it cleanly; start-up failures exit 2 and leave nothing behind.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStderr, Command, ExitStatus, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use common::{
    frames_camera, markhold, read_json, run_engaged, site_path, station_frames, station_rig,
    tmp_path, ws_read_frame, RealTimeVehicle,
};
use markhold::record::{CommandMsg, TOPIC_COMMAND};
use markhold_camera::FrameRecorder;
use markhold_exposure::{Camera, Frame};

fn tmp(name: &str) -> PathBuf {
    tmp_path("run", name)
}

/// 90 frames (3 s) rendered on station, as a recorded-frames folder; made once.
fn frames_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| station_frames(tmp("frames"), 90))
}

/// hil's vehicle on its own thread in real time.
fn vehicle() -> RealTimeVehicle {
    RealTimeVehicle::start(station_rig(false))
}

/// `markhold run --engage --no-preflight` on `site` with the recorded frames in `frames`
/// as its camera.
fn run_on_frames(site: &Path, frames: &Path) -> Command {
    run_engaged(site, &frames_camera(frames))
}

/// [`run_on_frames`] on the test site with `v` as the vehicle.
fn run_with_vehicle(frames: &Path, v: &RealTimeVehicle) -> Command {
    let mut c = run_on_frames(&site_path(), frames);
    c.args(["--link", &v.link()]);
    c
}

/// Waits for the run's "running" line on stderr (at most 20 s), lets it run 0.3 s, then
/// sends it SIGTERM: the rest of its stderr, and the deadline for its exit.
fn sigterm_once_running(child: &mut Child) -> (BufReader<ChildStderr>, Instant) {
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut err = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    while !line.contains("running") {
        line.clear();
        assert!(
            err.read_line(&mut line).unwrap() > 0,
            "exited before running"
        );
        assert!(Instant::now() < deadline);
    }
    std::thread::sleep(Duration::from_millis(300));
    assert!(common::sigterm(child));
    (err, deadline)
}

/// The child's exit status, waited for until `deadline`.
fn exit_by(child: &mut Child, deadline: Instant) -> ExitStatus {
    common::exit_status_by(child, deadline, "did not stop after SIGTERM")
}

/// `frames` run engaged (at their pace) against a fresh vehicle, recorded to
/// `NAME.mcap` with the summary `NAME.json`: (its output, the vehicle still running, the
/// recording, the summary).
fn run_recorded(frames: &Path, name: &str) -> (Output, RealTimeVehicle, PathBuf, PathBuf) {
    let v = vehicle();
    let (rec, summary) = (tmp(&format!("{name}.mcap")), tmp(&format!("{name}.json")));
    let o = run_with_vehicle(frames, &v)
        .arg("--record")
        .arg(&rec)
        .arg("--summary")
        .arg(&summary)
        .output()
        .unwrap();
    (o, v, rec, summary)
}

/// The messages on `topic` of the recording at `path`, decoded from JSON, in order.
fn messages<T: serde::de::DeserializeOwned>(path: &Path, topic: &str) -> Vec<T> {
    let buf = std::fs::read(path).unwrap();
    mcap::MessageStream::new(&buf)
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.channel.topic == topic)
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect()
}

fn commands(path: &Path) -> Vec<CommandMsg> {
    let buf = std::fs::read(path).unwrap();
    mcap::Summary::read(&buf)
        .unwrap()
        .expect("a finalized recording");
    messages(path, TOPIC_COMMAND)
}

#[test]
fn run_on_hil_vehicle_with_recorded_frames_end_to_end() {
    // At the recorded pace: the vehicle runs in real time, and markhold judges the link
    // on frame stamps (0.9 s without a message = silent). With --no-pace the stamps ran
    // ahead of the vehicle's messages and a stall of its thread read as a silent link
    // (9 of 90 frames silent).
    let (o, v, rec, summary) = run_recorded(frames_dir(), "e2e");
    // Let the vehicle take in the last inputs before stopping it.
    std::thread::sleep(Duration::from_millis(100));
    let stats = v.finish().stats;
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = read_json(&summary);
    // Played in real time, each frame is acted on or, when the loop was still busy with
    // an older one (a loaded host), passed over: never queued.
    let acted = report["frames"].as_u64().unwrap();
    assert_eq!(
        acted + report["frames_passed_over"].as_u64().unwrap(),
        90,
        "{report}"
    );
    assert!(acted >= 45, "{report}");
    assert_eq!(report["stopped_by"], "end_of_stream");
    assert!(
        report["detected"].as_u64().unwrap() + 5 >= acted,
        "{report}"
    );
    // The vehicle heard markhold's pilot input on (nearly) every frame, plus the final
    // neutral one.
    assert!(stats.pilot_inputs + 10 >= acted, "{stats:?}");
    assert_eq!(stats.pilot_inputs_dropped, 0, "{stats:?}");

    let cmds = commands(&rec);
    assert_eq!(cmds.len() as u64, acted);
    assert!(cmds.iter().filter(|c| c.directive == "command").count() as u64 + 5 >= acted);

    // The dive replays to the same commands (unless the recorder had to drop images).
    let out = markhold::record::replay::replay(&rec).unwrap();
    if report["record"]["images_dropped"] == 0 {
        assert!(out.commands_match, "{out:?}");
        assert_eq!(out.frames_replayed, acted);
    } else {
        assert_eq!(out.first_mismatch.unwrap().field, "image");
    }
}

#[test]
fn sigterm_sends_neutral_closes_the_recording_and_exits_0() {
    let frames = frames_dir();
    let v = vehicle();
    let rec = tmp("sigterm.mcap");
    let mut child = run_with_vehicle(frames, &v)
        .arg("--record")
        .arg(&rec)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Paced at 30 fps the 90 frames last 3 s: stop it once it runs.
    let (_err, deadline) = sigterm_once_running(&mut child);
    let status = exit_by(&mut child, deadline);
    let _ = v.finish();
    let mut out = String::new();
    std::io::Read::read_to_string(&mut child.stdout.take().unwrap(), &mut out).unwrap();
    assert_eq!(status.code(), Some(0), "{out}");
    assert!(out.contains("stopped by Signal"), "{out}");
    let cmds = commands(&rec);
    assert!(cmds.len() < 85, "stopped early: {} frames", cmds.len());
    let last = cmds.last().unwrap();
    assert!(last.directive.starts_with("shutdown"), "{last:?}");
}

fn assert_exit_2(o: &std::process::Output, needle: &str) {
    let err = crate::common::stderr_of_exit(o, 2);
    assert!(err.contains(needle), "expected '{needle}' in: {err}");
}

#[test]
fn missing_camera_unreachable_link_and_bad_record_path_exit_2_leaving_nothing() {
    let frames = frames_dir();
    let rec = tmp("never.mcap");

    let o = run_on_frames(&site_path(), Path::new("/no/such/folder"))
        .arg("--record")
        .arg(&rec)
        .output()
        .unwrap();
    assert_exit_2(&o, "camera frames:/no/such/folder");
    assert!(!rec.exists(), "half-written recording left behind");

    // Nobody listens on this port (bound, then released).
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let o = run_on_frames(&site_path(), frames)
        .args(["--heartbeat-timeout-s", "0.5"])
        .arg("--link")
        .arg(format!("udpout:127.0.0.1:{port}"))
        .arg("--record")
        .arg(&rec)
        .output()
        .unwrap();
    assert_exit_2(&o, "no vehicle heartbeat");
    assert!(!rec.exists(), "half-written recording left behind");

    let bad = tmp("no-such-dir").join("x.mcap");
    let o = run_on_frames(&site_path(), frames)
        .arg("--record")
        .arg(&bad)
        .output()
        .unwrap();
    assert_exit_2(&o, "x.mcap");
    assert!(!bad.exists());

    // 640x480 frames against a site calibrated for 1440x1080.
    let pool = common::repo("params/pool.toml");
    let o = run_on_frames(&pool, frames).output().unwrap();
    assert_exit_2(
        &o,
        "640x480 frames but the site's calibration is for 1440x1080",
    );
}

#[test]
fn live_view_advertises_every_channel_over_foxglove_websocket() {
    use std::io::Write;
    let mut rec =
        markhold::record::Recorder::live_only(markhold::record::RecordConfig::default()).unwrap();
    let port = rec.serve_live(0, &Default::default()).unwrap();
    assert_ne!(port, 0);
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    .unwrap();
    // The HTTP answer ends with an empty line.
    let mut head = Vec::new();
    let mut b = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        std::io::Read::read_exact(&mut s, &mut b).unwrap();
        head.push(b[0]);
    }
    let head = String::from_utf8_lossy(&head);
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    // serverInfo, then the channel advertisement.
    let mut advertised = String::new();
    for _ in 0..4 {
        let (op, data) = ws_read_frame(&mut s).unwrap();
        if op == 1 {
            let text = String::from_utf8(data).unwrap();
            if text.contains("\"op\":\"advertise\"") {
                advertised = text;
                break;
            }
        }
    }
    for topic in markhold::record::TOPICS {
        assert!(advertised.contains(topic), "{topic} not in {advertised}");
    }
    drop(s);
    rec.finish().unwrap();
}

/// 60 frames rendered on station with a 2 s hole in their stamps after frame 30: played
/// at the pace of its stamps, the camera stalls for 2 s.
fn stalling_frames_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tmp("frames-stall");
        let mut rig = station_rig(false);
        rig.set_exposure_us(3000.0).unwrap();
        let mut rec = FrameRecorder::create(&dir).unwrap();
        let mut f = Frame::default();
        for i in 0..60 {
            rig.grab(&mut f).unwrap();
            if i >= 30 {
                f.meta.stamp_s += 2.0;
            }
            rec.write(&f).unwrap();
        }
        dir
    })
}

/// The vehicle states the recording holds, per frame: (stamp, pilot inputs sent so far).
fn pilot_inputs_per_frame(path: &Path) -> Vec<(f64, u64)> {
    messages::<serde_json::Value>(path, markhold::record::TOPIC_VEHICLE)
        .iter()
        .map(|v| {
            (
                v["stamp_s"].as_f64().unwrap(),
                v["state"]["counters"]["pilot_inputs"].as_u64().unwrap(),
            )
        })
        .collect()
}

#[test]
fn camera_stall_goes_neutral_on_loop_time_then_resumes() {
    let (o, v, rec, summary) = run_recorded(stalling_frames_dir(), "stall");
    let _ = v.finish();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = read_json(&summary);
    // Each frame acted on or passed over (a loaded host), never queued.
    assert_eq!(
        report["frames"].as_u64().unwrap() + report["frames_passed_over"].as_u64().unwrap(),
        60,
        "{report}"
    );
    // One stall (2 s without frames > vision_stall_s = 0.5 s), noticed while it lasted.
    assert_eq!(report["vision_stalls"], 1, "{report}");
    // Between the last frame before the hole and the first after it, the loop kept
    // sending (neutral) pilot input on its ticks: a blocked grab would send none.
    let per = pilot_inputs_per_frame(&rec);
    let i = per
        .windows(2)
        .position(|w| w[1].0 - w[0].0 > 1.5)
        .expect("the hole is in the recording");
    let sent_in_hole = per[i + 1].1 - per[i].1;
    assert!(
        sent_in_hole >= 10,
        "only {sent_in_hole} pilot inputs during the 2 s stall"
    );
    // The commands around it: station keeping before, station keeping again after.
    let cmds = commands(&rec);
    assert_eq!(cmds[i].directive, "command", "{:?}", cmds[i]);
    let after = cmds.len() - i - 1;
    assert!(after >= 10, "{} frames acted on after the stall", after);
    assert!(
        cmds[i + 1..]
            .iter()
            .filter(|c| c.directive == "command")
            .count()
            + 5
            >= after,
        "{:?}",
        &cmds[i + 1..]
    );
}

#[test]
fn sigterm_with_disarm_on_exit_sends_neutral_then_disarms() {
    let frames = frames_dir();
    let v = vehicle();
    let rec = tmp("disarm.mcap");
    let summary = tmp("disarm.json");
    let site = tmp("disarm-site.toml");
    let text = std::fs::read_to_string(site_path()).unwrap().replace(
        "mode = \"manual\"",
        "mode = \"manual\"\ndisarm_on_exit = true",
    );
    std::fs::write(&site, text).unwrap();
    let mut child = run_on_frames(&site, frames)
        .args(["--arm", "--link", &v.link()])
        .arg("--record")
        .arg(&rec)
        .arg("--summary")
        .arg(&summary)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (mut err, deadline) = sigterm_once_running(&mut child);
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    let status = exit_by(&mut child, deadline);
    let end = v.finish();
    let (stats, armed) = (end.stats, end.truth.armed);
    assert_eq!(status.code(), Some(0), "{rest}");
    assert!(rest.contains("disarm on exit: Accepted"), "{rest}");
    // The vehicle is disarmed, by markhold (well before its own 3 s pilot failsafe: the
    // run lasted 0.3 s after start-up and input went out on every frame).
    assert!(!armed, "vehicle still armed; {stats:?}");
    let report = read_json(&summary);
    assert_eq!(report["stopped_by"], "signal", "{report}");
    assert_eq!(report["disarm"], "Accepted", "{report}");
    // Recording finalized; its last frame is the shutdown's neutral input.
    let cmds = commands(&rec);
    let last = cmds.last().unwrap();
    assert!(last.directive.starts_with("shutdown"), "{last:?}");
}

/// Per frame of a `--trace` CSV: (seq, detected).
fn detections(trace: &Path) -> Vec<(u64, bool)> {
    std::fs::read_to_string(trace)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0].parse().unwrap(), f[6] == "1")
        })
        .collect()
}

/// One recorded-frames format: `hil --snapshot` writes what `run --camera frames:` reads,
/// the run sees the same detections on it, and `run --record-frames` writes the same
/// folder again.
#[test]
fn a_snapshot_plays_back_as_a_camera_with_the_same_detections() {
    let snap = tmp("snap");
    let again = tmp("again");
    let (hil_trace, run_trace) = (tmp("hil.csv"), tmp("run.csv"));
    for d in [&snap, &again] {
        let _ = std::fs::remove_dir_all(d);
    }
    common::run_ok(
        markhold()
            .args(["hil", "--quiet", "--seconds", "2", "--site"])
            .arg(site_path())
            .args(["--snapshot-every", "1", "--snapshot"])
            .arg(&snap)
            .arg("--trace")
            .arg(&hil_trace),
    );

    let v = vehicle();
    let o = run_with_vehicle(&snap, &v)
        .arg("--no-pace")
        .arg("--trace")
        .arg(&run_trace)
        .arg("--record-frames")
        .arg(&again)
        .output()
        .unwrap();
    let _ = v.finish();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let (seen, replayed) = (detections(&hil_trace), detections(&run_trace));
    assert_eq!(seen.len(), 60, "two seconds at 30 fps");
    assert!(
        seen.iter().filter(|d| d.1).count() > 30,
        "the marker is seen"
    );
    assert_eq!(replayed, seen, "the same frames give the same detections");
    let csv = |d: &Path| std::fs::read_to_string(d.join("frames.csv")).unwrap();
    assert_eq!(
        csv(&again),
        csv(&snap),
        "stamps and exposures written again"
    );
    for name in ["frame_000000.png", "frame_000059.png"] {
        let a = std::fs::read(snap.join(name)).unwrap();
        let b = std::fs::read(again.join(name)).unwrap();
        assert!(a == b, "{name}: the pixels are written again as they were");
    }
}

/// 240 station frames (4 s) restamped 1/60 s apart: a 60 fps recording; made once.
fn frames_60fps() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = station_frames(tmp("frames60"), 240);
        let csv = dir.join("frames.csv");
        let text = std::fs::read_to_string(&csv).unwrap();
        let mut out = String::new();
        for (i, line) in text.lines().enumerate() {
            if i > 0 {
                let mut f: Vec<String> = line.split(',').map(String::from).collect();
                f[2] = format!("{:.9}", (i - 1) as f64 / 60.0);
                out.push_str(&f.join(","));
            } else {
                out.push_str(line);
            }
            out.push('\n');
        }
        std::fs::write(&csv, out).unwrap();
        dir
    })
}

#[test]
fn a_loop_slower_than_its_60_fps_frames_acts_on_the_newest_and_says_so() {
    let frames = frames_60fps();
    let v = vehicle();
    let summary = tmp("slow60.json");
    // The test-only delay: the loop sleeps 50 ms after each frame, so it cannot act on
    // more than 20 frames a second of a recording played at 60.
    let o = run_with_vehicle(frames, &v)
        .arg("--summary")
        .arg(&summary)
        .env("MARKHOLD_TEST_LOOP_DELAY_MS", "50")
        .output()
        .unwrap();
    v.finish();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let s = read_json(&summary);
    let num = |k: &str| {
        s[k].as_f64()
            .unwrap_or_else(|| panic!("summary has no {k}: {s}"))
    };
    assert_eq!(s["stopped_by"], "end_of_stream", "{s}");
    let acted = s["frames"].as_u64().unwrap();
    let passed = s["frames_passed_over"].as_u64().unwrap();
    eprintln!(
        "60 fps recording, 50 ms pause a frame: acted on {acted}, passed over {passed}, {:.1} fps effective, frame age at use {}",
        num("effective_fps"),
        s["frame_age"]
    );
    // Each recorded frame was acted on or passed over, never both. The frame handed out
    // is the newest due, and the loop comes back at least 50 ms later: consecutive
    // frames acted on are more than 50 ms less one frame period (2 frames) apart, so at
    // most 1 + 239 / 2 of the 240 were acted on (a queue would act on all 240).
    assert_eq!(acted + passed, 240, "{s}");
    assert!(acted <= 120, "{s}");
    // The last frame acted on is the recording's last: the loop ends in the present.
    assert!((num("loop_seconds") - 239.0 / 60.0).abs() < 1e-6, "{s}");
    // Rates from stamps: the camera's 60, the loop's own under the designed 30.
    assert!((num("camera_fps") - 60.0).abs() < 1e-6, "{s}");
    let effective = (acted - 1) as f64 / num("loop_seconds");
    assert!((num("effective_fps") - effective).abs() < 1e-9, "{s}");
    assert_eq!(num("designed_fps"), 30.0, "{s}");
    assert!(num("effective_fps") < 0.9 * 30.0, "{s}");
    assert!(s["rate_warnings"].as_u64().unwrap() >= 1, "{s}");
    assert!(
        err.contains("under the 30 fps the keeper is designed for"),
        "{err}"
    );
    // No growing latency: each frame acted on was at most a few frames old (in stamps)
    // when the loop came back for the next. A queue would have fallen 2.7 s behind by
    // the end (4 s of frames at 60 fps taken at 20 a second).
    let age = &s["frame_age"];
    assert_eq!(age["frames"].as_u64().unwrap(), acted - 1, "{s}");
    assert!(age["max_s"].as_f64().unwrap() <= 0.5, "{s}");
    assert!(age["max_frames"].as_u64().unwrap() <= 30, "{s}");
    assert!(age["mean_s"].as_f64().unwrap() >= 2.0 / 60.0, "{s}");
}
