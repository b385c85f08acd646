//! A HIL run recorded to MCAP, read back with the mcap crate, and replayed: the same
//! build and frames give bit-identical commands. Plus the recorder's loss accounting
//! and its write-error path.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::collections::BTreeMap;
use std::io::{Cursor, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use markhold::params;
use markhold::pipeline::FrameRecord;
use markhold::pipeline::{Observer, Observers};
use markhold::record::replay::replay;
use markhold::record::{
    CommandMsg, LinkSnapshot, RecordConfig, Recorder, RunInfo, TOPICS, TOPIC_ANNOTATIONS,
    TOPIC_COMMAND, TOPIC_DETECTION, TOPIC_EXPOSURE, TOPIC_FAILSAFE, TOPIC_FRAME, TOPIC_IMAGE,
    TOPIC_POSE, TOPIC_VEHICLE,
};
use markhold::sim::hil::{HilOptions, HilRun};

const SITE: &str = "tests/fixtures/pool-640.toml";

fn temp_path(name: &str) -> PathBuf {
    common::tmp_path("record", name)
}

fn counts(path: &Path) -> BTreeMap<String, u64> {
    let buf = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&buf)
        .unwrap()
        .expect("finalized file has a summary");
    let mut out: BTreeMap<String, u64> = summary
        .channels
        .values()
        .map(|c| (c.topic.clone(), 0))
        .collect();
    for m in mcap::MessageStream::new(&buf).unwrap() {
        *out.entry(m.unwrap().channel.topic.clone()).or_default() += 1;
    }
    out
}

struct Recorded {
    frames: u64,
    detected: u64,
    events: u64,
    records: Vec<FrameRecord>,
}

/// Record `seconds` of HIL; `tamper` may change a frame's record before it is written.
fn record_hil(path: &Path, seconds: f64, tamper: &dyn Fn(&mut FrameRecord)) -> Recorded {
    let site = params::load(Path::new(SITE)).unwrap();
    let opts = HilOptions {
        seconds,
        ..HilOptions::default()
    };
    let mut rec = markhold::sim::hil::open_recorder(&site, &opts, path).unwrap();
    let mut run = HilRun::build(&site, &opts, Observers::new()).unwrap();
    run.arm(site.site.link.mode.ardusub()).unwrap();
    let n = (seconds * site.site.camera.fps).round() as u64;
    let mut out = Recorded {
        frames: n,
        detected: 0,
        events: 0,
        records: Vec::new(),
    };
    for _ in 0..n {
        let (mut fr, _) = run.step().unwrap();
        tamper(&mut fr);
        rec.frame(&run.pipeline.view(&fr));
        out.detected += fr.detected as u64;
        out.events += run.pipeline.events().len() as u64;
        out.records.push(fr);
    }
    let stats = rec.finish().unwrap();
    assert_eq!(stats.frames, n);
    assert_eq!(
        stats.images_dropped, 0,
        "hil recording waits, it never drops"
    );
    assert_eq!(stats.write_error, None);
    out
}

#[test]
fn hil_recording_has_every_channel_and_replays_bit_identical() {
    let path = temp_path("hil.mcap");
    let r = record_hil(&path, 1.5, &|_| {});
    assert!(r.detected > 0, "the marker is seen on station");
    assert!(
        r.events > 0,
        "the supervisor reports the vehicle connecting"
    );

    let c = counts(&path);
    for topic in TOPICS {
        assert!(c.contains_key(topic), "channel {topic} missing: {c:?}");
    }
    for topic in [
        TOPIC_IMAGE,
        TOPIC_ANNOTATIONS,
        TOPIC_FRAME,
        TOPIC_EXPOSURE,
        TOPIC_DETECTION,
        TOPIC_COMMAND,
        TOPIC_VEHICLE,
    ] {
        assert_eq!(c[topic], r.frames, "{topic}");
    }
    assert_eq!(c[TOPIC_POSE], r.detected);
    assert_eq!(c[TOPIC_FAILSAFE], r.events);

    // The recorded commands are the loop's, bit for bit.
    let buf = std::fs::read(&path).unwrap();
    let recorded: Vec<CommandMsg> = mcap::MessageStream::new(&buf)
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.channel.topic == TOPIC_COMMAND)
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    let expected: Vec<CommandMsg> = r.records.iter().map(CommandMsg::from_record).collect();
    // Bits, not the decimal numbers: serde_json's default float parsing may be one ulp
    // off, which is why the recording carries the bit patterns.
    let key = |c: &CommandMsg| (c.seq, c.directive.clone(), c.effort_bits);
    assert_eq!(recorded.len(), expected.len());
    for (a, b) in recorded.iter().zip(&expected) {
        assert!(
            key(a) == key(b),
            "frame {}: recorded {a:?} != loop {b:?}",
            b.seq
        );
    }

    let out = replay(&path).unwrap();
    assert_eq!(out.frames_recorded, r.frames);
    assert_eq!(out.frames_replayed, r.frames);
    assert_eq!(out.commands_compared, r.frames);
    assert_eq!(out.first_mismatch, None);
    assert!(out.commands_match);
    assert_eq!(out.recorded_by, "hil");
}

#[test]
fn replay_reports_the_first_differing_command() {
    let path = temp_path("tampered.mcap");
    // One frame's recorded surge differs by one ulp from what the loop computed.
    let r = record_hil(&path, 0.5, &|fr| {
        if fr.seq == 7 {
            fr.effort.surge = f64::from_bits(fr.effort.surge.to_bits() ^ 1);
        }
    });
    let out = replay(&path).unwrap();
    assert!(!out.commands_match);
    let m = out.first_mismatch.expect("a mismatch");
    assert_eq!(m.seq, 7);
    assert_eq!(m.field, "effort.surge");
    assert_eq!(out.frames_replayed, r.frames);
}

fn site_info() -> RunInfo {
    let site = params::load(Path::new(SITE)).unwrap();
    RunInfo::new(
        "test",
        &site,
        markhold_exposure::ExposureMethod::Aaec,
        2000.0,
        String::new(),
    )
    .unwrap()
}

fn dummy_record(seq: u64) -> FrameRecord {
    FrameRecord {
        seq,
        stamp_s: seq as f64 / 30.0,
        exposure_used_us: 2000.0,
        exposure: markhold_exposure::ExposureStep {
            exposure_us: 2000.0,
            metric: 0.5,
            used_frame: true,
            roi: None,
        },
        detected: false,
        corners: None,
        t_cam_marker: None,
        cov_cam: None,
        reproj_rms_px: f64::NAN,
        markers_used: 0,
        effort: Default::default(),
        directive: markhold_autopilot::Directive::Silent,
        latency_s: 0.0,
    }
}

fn noisy_frame(seq: u64) -> markhold_exposure::Frame {
    let mut f = markhold_exposure::Frame::new(640, 480);
    let mut x = seq.wrapping_mul(6364136223846793005).wrapping_add(1);
    for p in f.data.iter_mut() {
        x = x
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *p = (x >> 56) as u8;
    }
    f.meta.seq = seq;
    f.meta.stamp_s = seq as f64 / 30.0;
    f.meta.exposure_us = 2000.0;
    f
}

#[test]
fn a_slow_writer_drops_images_and_counts_them_without_blocking() {
    let path = temp_path("drops.mcap");
    let cfg = RecordConfig {
        image_queue_frames: 1,
        queue_frames: 4,
        png_level: 9,
        wait_when_full: false,
        ..RecordConfig::default()
    };
    let mut rec = Recorder::create(&path, &site_info(), cfg).unwrap();
    let frame = noisy_frame(0);
    let link = LinkSnapshot {
        heartbeat_s: None,
        vehicle: None,
    };
    let n = 60;
    for seq in 0..n {
        let mut f = frame.clone();
        f.meta.seq = seq;
        f.meta.stamp_s = seq as f64 / 30.0;
        rec.record(&dummy_record(seq), &f, &link, false, &[]);
    }
    let stats = rec.finish().unwrap();
    assert_eq!(stats.frames, n);
    // A 640x480 noise PNG at level 9 takes far longer than handing 60 frames over.
    assert!(stats.images_dropped > 0, "{stats:?}");
    let c = counts(&path);
    assert_eq!(c[TOPIC_IMAGE], n - stats.images_dropped);
    assert_eq!(c[TOPIC_FRAME], n - stats.frames_dropped);
    // Replay stops at the first frame without its image and says so.
    let out = replay(&path).unwrap();
    assert!(!out.commands_match);
    assert_eq!(out.first_mismatch.unwrap().field, "image");
}

/// Accepts `budget` bytes, then fails like a full disk.
struct FullDisk {
    inner: Cursor<Vec<u8>>,
    budget: usize,
}

impl Write for FullDisk {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if self.inner.get_ref().len() + buf.len() > self.budget {
            return Err(std::io::Error::from_raw_os_error(28)); // ENOSPC
        }
        self.inner.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for FullDisk {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.inner.seek(pos)
    }
}

#[test]
fn a_full_disk_is_reported_once_and_recording_goes_on() {
    let cfg = RecordConfig {
        wait_when_full: true,
        ..RecordConfig::default()
    };
    let disk = FullDisk {
        inner: Cursor::new(Vec::new()),
        budget: 200_000,
    };
    let mut rec = Recorder::to_writer(disk, &site_info(), cfg).unwrap();
    let link = LinkSnapshot {
        heartbeat_s: None,
        vehicle: None,
    };
    for seq in 0..20 {
        rec.record(&dummy_record(seq), &noisy_frame(seq), &link, false, &[]);
    }
    let stats = rec.finish().unwrap();
    assert_eq!(stats.frames, 20, "every frame was handed over");
    let err = stats.write_error.expect("the write error is reported");
    assert!(err.contains("No space left"), "{err}");
}

#[test]
fn an_existing_or_unwritable_record_path_is_refused_and_left_alone() {
    let path = temp_path("exists.mcap");
    std::fs::write(&path, b"keep me").unwrap();
    let e = Recorder::create(&path, &site_info(), RecordConfig::default())
        .err()
        .expect("refused");
    assert!(e.to_string().contains("exists"), "{e}");
    assert_eq!(std::fs::read(&path).unwrap(), b"keep me");

    let missing = temp_path("no-such-dir").join("x.mcap");
    let e = Recorder::create(&missing, &site_info(), RecordConfig::default())
        .err()
        .expect("refused");
    assert!(e.to_string().contains("x.mcap"), "{e}");
    assert!(!missing.exists());
}

#[test]
fn cli_hil_record_then_replay_summary() {
    let bin = env!("CARGO_BIN_EXE_markhold");
    let rec = temp_path("cli.mcap");
    let summary = temp_path("cli-replay.json");
    let hil_summary = temp_path("cli-hil.json");
    common::run_ok(
        std::process::Command::new(bin)
            .args([
                "hil",
                "--quiet",
                "--seconds",
                "1",
                "--site",
                SITE,
                "--record",
            ])
            .arg(&rec)
            .arg("--summary")
            .arg(&hil_summary),
    );
    // A recorded run is the same runner as any other: the world's own time is reported.
    let h = common::read_json(&hil_summary);
    assert!(h["world_wall_seconds"].as_f64().unwrap() > 0.0, "{h}");
    assert!(h["world_realtime_factor"].as_f64().unwrap() > 0.0, "{h}");
    assert_ne!(h["render_loops"], "", "{h}");
    common::run_ok(
        std::process::Command::new(bin)
            .arg("replay")
            .arg(&rec)
            .arg("--summary")
            .arg(&summary),
    );
    let s = common::read_json(&summary);
    assert_eq!(s["commands_match"], true, "{s}");
    assert_eq!(s["frames_replayed"], 30, "{s}");
    assert!(s["first_mismatch"].is_null());

    // Not a recording: a clear error, exit 2.
    let junk = temp_path("junk.mcap");
    std::fs::write(&junk, b"not an mcap file").unwrap();
    let o = std::process::Command::new(bin)
        .arg("replay")
        .arg(&junk)
        .output()
        .unwrap();
    let err = common::stderr_of_exit(&o, 2);
    assert!(err.contains("junk.mcap"), "{err}");
}

/// A recording cut short (a crash, a full disk, a copy interrupted) replays up to its
/// last complete chunk and says it ended early; one byte short loses nothing.
#[test]
fn a_truncated_recording_replays_up_to_its_last_complete_chunk() {
    let path = temp_path("whole.mcap");
    let r = record_hil(&path, 1.0, &|_| {});
    let bytes = std::fs::read(&path).unwrap();

    let short = temp_path("one-byte-short.mcap");
    std::fs::write(&short, &bytes[..bytes.len() - 1]).unwrap();
    let out = replay(&short).unwrap();
    assert_eq!(out.frames_replayed, r.frames, "{out:?}");
    assert!(out.commands_match, "{out:?}");
    assert!(out.recovered.is_some(), "the early end is reported");

    let half = temp_path("half.mcap");
    std::fs::write(&half, &bytes[..bytes.len() / 2]).unwrap();
    let out = replay(&half).unwrap();
    assert!(
        out.frames_replayed > 0 && out.frames_replayed < r.frames,
        "{out:?}"
    );
    assert_eq!(out.frames_replayed, out.commands_compared);
    assert!(out.first_mismatch.is_none(), "{out:?}");
    let rec = out.recovered.expect("the early end is reported");
    assert_eq!(rec.file_bytes, (bytes.len() / 2) as u64);

    // Only the header: nothing to replay is an error that names the file.
    let stub = temp_path("stub.mcap");
    std::fs::write(&stub, &bytes[..20]).unwrap();
    let e = replay(&stub).unwrap_err();
    assert!(format!("{e:#}").contains("stub.mcap"), "{e:#}");
}

/// Peak resident memory of a child process, read from /proc while it runs (bounded).
fn replay_peak_rss_kb(file: &Path) -> u64 {
    let mut child = common::markhold()
        .arg("replay")
        .arg(file)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let status = format!("/proc/{}/status", child.id());
    let mut peak = 0;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    loop {
        if let Ok(s) = std::fs::read_to_string(&status) {
            if let Some(kb) = s
                .lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            {
                peak = peak.max(kb);
            }
        }
        if child.try_wait().unwrap().is_some() {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "replay did not end");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    peak
}

/// Replay reads record by record: a recording ten times as long needs about the same
/// peak memory (loading it whole would add its size to the peak).
#[test]
fn replay_memory_does_not_grow_with_the_file() {
    let short = temp_path("mem-short.mcap");
    let long = temp_path("mem-long.mcap");
    record_hil(&short, 0.5, &|_| {});
    record_hil(&long, 5.0, &|_| {});
    let (s, l) = (
        std::fs::metadata(&short).unwrap().len() / 1024,
        std::fs::metadata(&long).unwrap().len() / 1024,
    );
    assert!(
        l > s + 15_000,
        "the long file is 15 MB larger: {s} kB vs {l} kB"
    );
    let (ps, pl) = (replay_peak_rss_kb(&short), replay_peak_rss_kb(&long));
    assert!(ps > 0 && pl > 0, "peak RSS read from /proc");
    assert!(
        pl < ps + (l - s) / 3,
        "peak RSS {ps} kB for {s} kB of file, {pl} kB for {l} kB"
    );
}

fn jpeg_site() -> PathBuf {
    let p = temp_path("jpeg-site.toml");
    let text = std::fs::read_to_string(SITE).unwrap().replace(
        "image_format = \"png\"",
        "image_format = \"jpeg\"\njpeg_quality = 90",
    );
    assert!(
        text.contains("\"jpeg\""),
        "the fixture names its image format"
    );
    std::fs::write(&p, text).unwrap();
    p
}

/// `[record] image_format = "jpeg"`: images are `jpeg` CompressedImages, the file is
/// smaller than PNG's, and replay says it is not bit-exact instead of failing.
#[test]
fn a_jpeg_recording_is_smaller_and_replay_says_it_is_not_exact() {
    let site = params::load(&jpeg_site()).unwrap();
    let opts = HilOptions {
        seconds: 0.5,
        ..HilOptions::default()
    };
    let jpeg = temp_path("jpeg.mcap");
    let png = temp_path("png.mcap");
    for (path, site) in [
        (&jpeg, site.clone()),
        (&png, params::load(Path::new(SITE)).unwrap()),
    ] {
        let mut rec = markhold::sim::hil::open_recorder(&site, &opts, path).unwrap();
        let mut run = HilRun::build(&site, &opts, Observers::new()).unwrap();
        run.arm(site.site.link.mode.ardusub()).unwrap();
        for _ in 0..15 {
            let (fr, _) = run.step().unwrap();
            rec.frame(&run.pipeline.view(&fr));
        }
        rec.finish().unwrap();
    }
    let buf = std::fs::read(&jpeg).unwrap();
    let mut formats = BTreeMap::<String, u64>::new();
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == TOPIC_IMAGE {
            use foxglove::Decode;
            let img = foxglove::schemas::CompressedImage::decode(&m.data[..]).unwrap();
            *formats.entry(img.format).or_default() += 1;
        }
    }
    assert_eq!(formats.get("jpeg"), Some(&15), "{formats:?}");
    let (j, p) = (
        std::fs::metadata(&jpeg).unwrap().len(),
        std::fs::metadata(&png).unwrap().len(),
    );
    assert!(j * 2 < p, "JPEG {j} bytes vs PNG {p} bytes");
    // docs/usage.md's rates at 640x480 and 30 fps, PNG about 265 and JPEG about 69 MB per
    // minute: these 15 frames (0.5 s of camera time) within 2x of them.
    let per_minute = |bytes: u64| bytes as f64 / 0.5 * 60.0 / 1e6;
    let (jr, pr) = (per_minute(j), per_minute(p));
    assert!(
        pr > 265.0 / 2.0 && pr < 265.0 * 2.0,
        "PNG {pr:.0} MB per minute"
    );
    assert!(
        jr > 69.0 / 2.0 && jr < 69.0 * 2.0,
        "JPEG {jr:.0} MB per minute"
    );
    let out = replay(&jpeg).unwrap();
    assert_eq!(out.lossy_images, 15, "{out:?}");
    assert_eq!(out.frames_replayed, 15, "{out:?}");
    let out = replay(&png).unwrap();
    assert_eq!(out.lossy_images, 0);
    assert!(out.commands_match);
}

/// SIGTERM during `hil --record`: the file is finalized, the exit status is 130 and the
/// recording replays.
#[test]
fn sigterm_during_a_recorded_hil_run_finalizes_the_file() {
    let rec = temp_path("sigterm.mcap");
    let mut child = common::spawn_quiet(
        common::markhold()
            .args([
                "hil",
                "--quiet",
                "--seconds",
                "600",
                "--site",
                SITE,
                "--record",
            ])
            .arg(&rec),
    );
    // Wait (bounded) until frames are being written.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while std::fs::metadata(&rec).map(|m| m.len()).unwrap_or(0) < 5_000_000 {
        assert!(std::time::Instant::now() < deadline, "no recording grew");
        assert!(child.try_wait().unwrap().is_none(), "hil ended early");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let kill = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(130),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = replay(&rec).unwrap();
    assert!(r.recovered.is_none(), "a finalized file: {r:?}");
    assert!(r.frames_replayed > 0 && r.commands_match, "{r:?}");
}

/// A recording whose run description is hostile (a site no site file could hold, an
/// initial exposure of NaN) is refused with an error naming it, never replayed.
#[test]
fn replay_validates_the_recorded_site_like_a_site_file() {
    let good = site_info();
    let cases: [(&str, RunInfo); 3] = [
        (
            "fps",
            RunInfo {
                site_toml: good.site_toml.replace("fps = 30.0", "fps = -1.0"),
                ..good.clone()
            },
        ),
        (
            "width",
            RunInfo {
                site_toml: good.site_toml.replace("width_px = 640", "width_px = 0"),
                ..good.clone()
            },
        ),
        (
            "initial",
            RunInfo {
                initial_exposure_us: f64::NAN,
                ..good.clone()
            },
        ),
    ];
    for (name, info) in cases {
        assert_ne!(info, good, "{name}: the case changes the description");
        let path = temp_path(&format!("hostile-{name}.mcap"));
        let mut rec = Recorder::create(&path, &info, RecordConfig::default()).unwrap();
        let link = LinkSnapshot {
            heartbeat_s: None,
            vehicle: None,
        };
        for seq in 0..3 {
            rec.record(&dummy_record(seq), &noisy_frame(seq), &link, false, &[]);
        }
        rec.finish().unwrap();
        let e = replay(&path).expect_err(name);
        let msg = format!("{e:#}");
        assert!(msg.contains(&format!("hostile-{name}.mcap")), "{msg}");
        assert!(msg.contains("recorded"), "{name}: {msg}");
    }
}

/// A grey PNG of `side` x `side` pixels, all zero, made by python3's zlib (about 1 MB
/// for 32768: deflate packs a run of zeros about a thousand to one).
fn zero_png(side: u32) -> Vec<u8> {
    let script = format!(
        "import struct,sys,zlib\n\
         w=h={side}\n\
         def chunk(t,d):\n\
         \x20   return struct.pack('>I',len(d))+t+d+struct.pack('>I',zlib.crc32(t+d)&0xffffffff)\n\
         c=zlib.compressobj(9)\n\
         row=bytes(w+1)\n\
         idat=b''.join(c.compress(row) for _ in range(h))+c.flush()\n\
         sys.stdout.buffer.write(b'\\x89PNG\\r\\n\\x1a\\n'+chunk(b'IHDR',struct.pack('>IIBBBBB',w,h,8,0,0,0,0))+chunk(b'IDAT',idat)+chunk(b'IEND',b''))\n"
    );
    let o = std::process::Command::new("python3")
        .args(["-c", &script])
        .output()
        .expect("python3");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o.stdout
}

/// A recording of one frame whose run description is `info` and whose image is `png`,
/// written with the mcap crate as a hostile tool would.
fn one_frame_recording(path: &Path, info: &RunInfo, png: &[u8]) {
    use foxglove::Encode;
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(path).unwrap(),
    ))
    .unwrap();
    w.write_metadata(&mcap::records::Metadata {
        name: markhold::record::METADATA_NAME.into(),
        metadata: info.to_metadata(),
    })
    .unwrap();
    let schema = w
        .add_schema("foxglove.CompressedImage", "protobuf", b"")
        .unwrap();
    let image = w
        .add_channel(schema, TOPIC_IMAGE, "protobuf", &BTreeMap::new())
        .unwrap();
    let frame = w
        .add_channel(0, TOPIC_FRAME, "json", &BTreeMap::new())
        .unwrap();
    let msg = foxglove::schemas::CompressedImage {
        timestamp: None,
        frame_id: "camera".into(),
        data: foxglove::bytes::Bytes::copy_from_slice(png),
        format: "png".into(),
    };
    let mut data = Vec::new();
    msg.encode(&mut data).unwrap();
    let header = |channel_id| mcap::records::MessageHeader {
        channel_id,
        sequence: 0,
        log_time: 1_000_000,
        publish_time: 1_000_000,
    };
    w.write_to_known_channel(&header(image), &data).unwrap();
    let f = serde_json::json!({
        "seq": 0, "stamp_s": 0.001, "exposure_us": null, "gain_db": 0.0,
        "width": 640, "height": 480, "image": true, "heartbeat_s": null, "shutdown": false,
        "bits": {"stamp": 0.001f64.to_bits(), "exposure": f64::NAN.to_bits(), "gain": 0, "heartbeat": null}
    });
    w.write_to_known_channel(&header(frame), f.to_string().as_bytes())
        .unwrap();
    w.finish().unwrap();
}

/// `markhold ARGS`: exit status, stderr and peak memory (kB), bounded in time.
fn markhold_peak(args: &[&std::ffi::OsStr]) -> (Option<i32>, String, u64) {
    let mut child = common::spawn_quiet(common::markhold().args(args));
    let reader = common::stderr_on_thread(&mut child);
    let mut peak = 0;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let code = loop {
        peak = peak.max(common::peak_rss_kb(child.id()).unwrap_or(0));
        if let Some(s) = child.try_wait().unwrap() {
            break s.code();
        }
        assert!(std::time::Instant::now() < deadline, "markhold did not end");
        std::thread::sleep(std::time::Duration::from_millis(5));
    };
    (code, reader.join().unwrap(), peak)
}

/// A recording holding a 32768 x 32768 PNG (1 GiB of pixels once decoded) and one whose
/// recorded site is 100 MB: both refused before anything of that size is made, by
/// `replay` and by `map`.
#[test]
fn hostile_recordings_are_refused_before_allocating() {
    let info = site_info();
    let huge = temp_path("huge-image.mcap");
    one_frame_recording(&huge, &info, &zero_png(32768));
    let site = std::path::Path::new(SITE);
    for args in [
        vec!["replay".as_ref(), huge.as_os_str()],
        vec![
            "map".as_ref(),
            "--site".as_ref(),
            site.as_os_str(),
            "--recording".as_ref(),
            huge.as_os_str(),
        ],
    ] {
        let (code, err, peak) = markhold_peak(&args);
        eprintln!("{:?}: exit {code:?}, peak RSS {} MB", args[0], peak / 1024);
        assert_eq!(code, Some(2), "{err}");
        assert!(
            err.contains("32768x32768") && err.contains("not decoded"),
            "{err}"
        );
        assert!(peak < 400 << 10, "peak RSS {peak} kB");
    }

    let big_site = temp_path("big-site.mcap");
    let padded = RunInfo {
        site_toml: format!("{}\n#{}\n", info.site_toml, "x".repeat(100 << 20)),
        ..info.clone()
    };
    one_frame_recording(&big_site, &padded, &zero_png(16));
    let (code, err, peak) = markhold_peak(&["replay".as_ref(), big_site.as_os_str()]);
    eprintln!("100 MB site: exit {code:?}, peak RSS {} MB", peak / 1024);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("site_toml") && err.contains("at most 4194304"),
        "{err}"
    );
}

/// Each camera kind a run reads, recorded and replayed: recorded frames (`frames:`), a
/// GStreamer stream (`gst:`, whose frames carry no known exposure while the camera is
/// the pilot's: NaN, written as null), and the stream's frames saved with
/// `--record-frames` and run again as `frames:`.
#[test]
fn a_run_of_each_camera_kind_records_and_replays() {
    let dir = temp_path("kinds");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // Station frames rendered by the simulator; the first frozen into a live stream.
    let rig_frames = common::station_frames(dir.join("rendered"), 30);
    let png = rig_frames.join("frame_000000.png");
    let gst = format!(
        "gst:filesrc location={} ! pngdec ! imagefreeze is-live=true num-buffers=45 ! video/x-raw,format=GRAY8,width=640,height=480,framerate=30/1 ! appsink",
        png.display()
    );
    let saved = dir.join("saved");
    let cameras = [
        ("frames", format!("frames:{}", rig_frames.display()), false),
        ("gst", gst, true),
        ("saved", format!("frames:{}", saved.display()), false),
    ];
    for (name, camera, save) in cameras {
        // Not engaged (the pymavlink vehicle never arms): the loop runs and records every
        // frame until its frames end or 1.5 s have passed.
        let rec = dir.join(format!("{name}.mcap"));
        let (_vehicle, port) = common::pymav_vehicle(&["--scenario", "hold", "--deadline", "30"]);
        let mut cmd = common::markhold();
        cmd.args(["run", "--no-preflight", "--site", SITE, "--camera"])
            .arg(&camera)
            .arg("--link")
            .arg(format!("udpout:127.0.0.1:{port}"))
            .args(["--seconds", "1.5", "--record"])
            .arg(&rec);
        if save {
            cmd.arg("--record-frames").arg(&saved);
        }
        let o = cmd.output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{name}: {err}");
        let out = replay(&rec).unwrap_or_else(|e| panic!("{name}: {e:#}"));
        eprintln!(
            "{name}: {} frames replayed, commands match: {}",
            out.frames_replayed, out.commands_match
        );
        // The recorder never blocks the loop: on a loaded host it may drop a frame, and
        // says so; replay then stops there, every command before it matched.
        let dropped = out
            .first_mismatch
            .as_ref()
            .is_some_and(|m| m.field == "image" && m.recorded == "dropped while recording");
        assert!(out.commands_match || dropped, "{name}: {out:?}");
        // Paced at 30 fps for 1.5 s: a loaded host acts on the newest frame and passes
        // the others over (at least 15 are acted on); a frame the recorder dropped ends
        // the replay there, so then only some must have replayed.
        let floor = if dropped { 5 } else { 15 };
        assert!(out.frames_replayed >= floor, "{name}: {out:?}");
        assert_eq!(
            out.commands_compared, out.frames_replayed,
            "{name}: {out:?}"
        );
    }
}
