//! The raw MAVLink tap: a HIL run recorded with the link tapped has a `/mavlink/raw`
//! channel holding every frame markhold wrote and read, in order, with loop-time stamps,
//! and each frame parses back to what the link counted.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common::{site_path, tmp_dir};

use markhold::params;
use markhold::pipeline::{Observer, Observers};
use markhold::record::{RecordConfig, Recorder, RunInfo, MAVLINK_RAW_ENCODING, TOPIC_MAVLINK_RAW};
use markhold::sim::hil::{HilOptions, HilRun};
use markhold_autopilot::mavlink::dialects::ardupilotmega::MavMessage;
use markhold_autopilot::mavlink::MavlinkReader;

#[test]
fn recorded_raw_mavlink_reads_back_as_the_links_traffic() {
    let dir = tmp_dir("tap", "lib");
    let path = dir.join("tap.mcap");

    let site_path = site_path();
    let site = params::load(&site_path).unwrap();
    let opts = HilOptions {
        seconds: 2.0,
        seed: 2,
        start_on_station: true,
        ..HilOptions::default()
    };
    let mut hil = HilRun::build(&site, &opts, Observers::new()).unwrap();
    let info = RunInfo::new(
        "hil",
        &site,
        hil.method,
        site.site.camera.initial_exposure_us,
        String::new(),
    )
    .unwrap();
    let mut rec = Recorder::create(
        &path,
        &info,
        RecordConfig {
            wait_when_full: true,
            ..Default::default()
        },
    )
    .unwrap();
    hil.pipeline.link_mut().set_raw_tap(Some(rec.mavlink_tap()));
    hil.arm(site.site.link.mode.ardusub()).unwrap();
    let frames = (opts.seconds * site.site.camera.fps) as usize;
    for _ in 0..frames {
        let (fr, _) = hil.step().unwrap();
        rec.frame(&hil.pipeline.view(&fr));
    }
    let sent = hil.pipeline.link().messages_sent();
    let received = hil.pipeline.link().messages_received();
    assert_eq!(hil.pipeline.link().raw_tap_dropped(), 0);
    hil.pipeline.link_mut().set_raw_tap(None);
    rec.finish().unwrap();

    let buf = std::fs::read(&path).unwrap();
    let (mut out, mut inc) = (0u64, 0u64);
    let (mut overrides, mut heartbeats_in) = (0u64, 0u64);
    let mut last_t = 0u64;
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic != TOPIC_MAVLINK_RAW {
            continue;
        }
        assert_eq!(m.channel.message_encoding, MAVLINK_RAW_ENCODING);
        assert!(m.log_time >= last_t, "out of order");
        last_t = m.log_time;
        let (dir, frame) = m.data.split_first().unwrap();
        let mut r = MavlinkReader::new(frame);
        let (h, msg) = r
            .read_any_message::<MavMessage>()
            .expect("a whole, CRC-valid frame");
        match dir {
            1 => {
                out += 1;
                // markhold is component 191 of the vehicle; only its pilot input goes
                // out as SYSID_MYGCS (255).
                let pilot = matches!(msg, MavMessage::RC_CHANNELS_OVERRIDE(_));
                assert_eq!(h.system_id, if pilot { 255 } else { 1 }, "{msg:?}");
                assert_eq!(h.component_id, 191);
                overrides += u64::from(pilot);
            }
            0 => {
                inc += 1;
                assert_eq!(h.system_id, 1);
                heartbeats_in += u64::from(matches!(msg, MavMessage::HEARTBEAT(_)));
            }
            d => panic!("direction byte {d}"),
        }
    }
    println!(
        "tap: {out} frames out ({overrides} RC overrides), {inc} in ({heartbeats_in} heartbeats); \
         link counted {sent} sent, {received} received"
    );
    assert_eq!(out, sent);
    assert_eq!(inc, received);
    assert!(overrides as usize >= frames - 2, "{overrides}");
    assert!(heartbeats_in >= 2, "{heartbeats_in}");
    // Stamps are loop time: within the run (2 s), not the wall clock.
    assert!(last_t <= 3_000_000_000, "{last_t}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The binary wires the tap: `markhold hil --record` writes `/mavlink/raw`, and the file
/// still replays with matching commands.
#[test]
fn hil_record_from_the_binary_holds_raw_mavlink_and_replays() {
    let dir = tmp_dir("tap", "bin");
    let path = dir.join("run.mcap");
    let site = site_path();
    let bin = env!("CARGO_BIN_EXE_markhold");
    crate::common::run_ok(
        std::process::Command::new(bin)
            .args(["hil", "--quiet", "--seconds", "2", "--site"])
            .arg(&site)
            .arg("--record")
            .arg(&path),
    );
    let buf = std::fs::read(&path).unwrap();
    let (mut out_frames, mut in_frames) = (0u64, 0u64);
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == TOPIC_MAVLINK_RAW {
            match m.data.first() {
                Some(1) => out_frames += 1,
                Some(0) => in_frames += 1,
                d => panic!("direction byte {d:?}"),
            }
        }
    }
    println!("binary recording: {out_frames} raw frames out, {in_frames} in");
    // 2 s at 30 fps: one RC override per frame at least, and the vehicle's heartbeats.
    assert!(out_frames >= 58, "{out_frames}");
    assert!(in_frames >= 2, "{in_frames}");
    let summary = dir.join("replay.json");
    crate::common::run_ok(
        std::process::Command::new(bin)
            .arg("replay")
            .arg(&path)
            .arg("--summary")
            .arg(&summary),
    );
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&summary).unwrap()).unwrap();
    assert_eq!(s["commands_match"], true, "{s}");
    std::fs::remove_dir_all(&dir).unwrap();
}
