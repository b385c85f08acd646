//! `genicam:` cameras against Aravis's simulated cameras, without hardware:
//! `arv-fake-gv-camera-0.8` on 127.0.0.1 (GigE Vision over loopback) and Aravis's
//! in-process "Fake" interface. Every test holds one lock: the GigE fake listens on the
//! fixed GVCP port 3956 and Aravis's interface switches are process-wide.
//!
//! The simulated camera draws a diagonal ramp `((x + y + frame_id) % 255) * s` with
//! `s = 1 + gain + log10(exposure_us / 10000)` (clamped to 0..255), so an image's mean
//! tells the exposure it was really taken with.
#![cfg(all(feature = "sim", feature = "genicam"))]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::io::{BufRead, BufReader};
use std::net::UdpSocket;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use common::{
    exit_status_by, read_json, run_engaged, site_path, station_rig, tmp_path, RealTimeVehicle,
};
use markhold::params;
use markhold::record::{FrameMsg, TOPIC_COMMAND, TOPIC_FRAME};
use markhold_camera::genicam::{
    use_fake_interface, ExposureSource, GenicamCamera, GenicamConfig, GenicamError,
};
use markhold_camera::{Camera, ExposureLimits, Frame};

const FAKE_GV: &str = "arv-fake-gv-camera-0.8";
const GVCP: (&str, u16) = ("127.0.0.1", 3956);

static LOCK: Mutex<()> = Mutex::new(());

fn lock() -> MutexGuard<'static, ()> {
    LOCK.lock().unwrap_or_else(|p| p.into_inner())
}

fn tmp(name: &str) -> PathBuf {
    tmp_path("genicam", name)
}

/// Whether something answers a GVCP read of register 0 on 127.0.0.1:3956 within `wait`.
fn gvcp_answers(wait: Duration) -> bool {
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    // key 0x42, ack wanted, READREG_CMD 0x0080, 4 payload bytes, request 1, address 0.
    let cmd = [0x42, 0x01, 0x00, 0x80, 0x00, 0x04, 0x00, 0x01, 0, 0, 0, 0];
    let deadline = Instant::now() + wait;
    let mut buf = [0u8; 64];
    loop {
        let _ = sock.send_to(&cmd, GVCP);
        if let Ok(n) = sock.recv(&mut buf) {
            if n >= 8 && buf[2..4] == [0x00, 0x81] {
                return true;
            }
        }
        if Instant::now() >= deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `arv-fake-gv-camera-0.8 -i 127.0.0.1`, killed when dropped.
struct FakeGv {
    child: Child,
}

impl FakeGv {
    fn start() -> Self {
        assert!(
            !gvcp_answers(Duration::from_millis(200)),
            "something already answers GVCP on 127.0.0.1:3956 (a stray {FAKE_GV}?)"
        );
        let child = Command::new(FAKE_GV)
            .args(["-i", "127.0.0.1"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!("cannot start {FAKE_GV} ({e}): install aravis-tools (scripts/install-deps)")
            });
        let mut me = Self { child };
        if !gvcp_answers(Duration::from_secs(5)) {
            let status = me.child.try_wait().ok().flatten();
            panic!("{FAKE_GV} -i 127.0.0.1 does not answer on port 3956 (exited: {status:?})");
        }
        me
    }
}

impl Drop for FakeGv {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn config(width: u32, height: u32, initial_us: f64) -> GenicamConfig {
    GenicamConfig {
        width,
        height,
        fps: 30.0,
        limits: ExposureLimits {
            min_us: 100.0,
            max_us: 30_000.0,
            fps: 30.0,
        },
        initial_us,
        gain_db: 0.0,
        buffers: 4,
        frame_timeout_s: 2.0,
    }
}

/// Mean of the simulated camera's ramp for `exposure_us` (gain 0), `w` x `h`.
fn predicted_mean(exposure_us: f64, w: u32, h: u32) -> f64 {
    let s = 1.0 + (exposure_us / 10_000.0).log10();
    let mut sum = 0.0;
    for y in 0..h {
        for x in 0..w {
            sum += ((((x + y) % 255) as f64) * s).clamp(0.0, 255.0).trunc();
        }
    }
    sum / (w as f64 * h as f64)
}

fn mean(f: &Frame) -> f64 {
    f.data.iter().map(|&p| p as f64).sum::<f64>() / f.data.len() as f64
}

/// The simulated GigE camera on loopback, opened at `width` x `height` and `initial_us`.
/// Dropped in reverse order: the camera closes before the fake stops and the lock goes.
fn fake_gige_camera(
    width: u32,
    height: u32,
    initial_us: f64,
) -> (MutexGuard<'static, ()>, FakeGv, GenicamCamera) {
    let l = lock();
    use_fake_interface(false);
    let fake = FakeGv::start();
    let cam = GenicamCamera::open("127.0.0.1", &config(width, height, initial_us)).unwrap();
    (l, fake, cam)
}

/// Set each exposure in turn and grab `per` frames at it; returns (read back by
/// `set_exposure_us`, frames' meta exposure, frame mean) per frame.
fn sweep(cam: &mut GenicamCamera, exposures: &[f64], per: usize) -> Vec<(f64, f64, f64)> {
    let mut f = Frame::default();
    let mut out = Vec::new();
    for &e in exposures {
        let back = cam.set_exposure_us(e).unwrap();
        for _ in 0..per {
            cam.grab(&mut f).unwrap();
            out.push((back, f.meta.exposure_us, mean(&f)));
        }
    }
    out
}

#[test]
fn fake_gige_camera_exposure_is_set_per_frame_and_read_back() {
    let (_l, _fake, mut cam) = fake_gige_camera(640, 480, 3000.0);
    assert_eq!(cam.name(), "genicam:127.0.0.1");
    // The simulated camera sends no chunk data: the feature is read after each frame.
    assert_eq!(cam.exposure_source(), ExposureSource::FeatureAfterFrame);
    let lim = cam.exposure_limits();
    assert_eq!((lim.min_us, lim.max_us), (100.0, 30_000.0));
    // The simulated camera keeps a whole-microsecond frame period (33333 us).
    assert!((lim.fps - 30.0).abs() < 0.01, "frame rate {}", lim.fps);
    // Out-of-range requests are clamped to the limits, and the camera says so.
    let clamped = cam.set_exposure_us(1e9).unwrap();
    assert_eq!(clamped, 30_000.0);

    let (lo, hi) = (3000.0, 8000.0);
    let (m_lo, m_hi) = (predicted_mean(lo, 640, 480), predicted_mean(hi, 640, 480));
    assert!(m_hi > 1.5 * m_lo, "{m_lo} {m_hi}");
    // Each exposure's predicted mean, computed once (a full-frame pass each).
    let m_clamped = predicted_mean(clamped, 640, 480);
    let mean_at = |t: f64| {
        if t == lo {
            m_lo
        } else if t == hi {
            m_hi
        } else {
            m_clamped
        }
    };
    let per = 8;
    let steps = [lo, hi, lo, hi];
    let rows = sweep(&mut cam, &steps, per);
    // Figures (printed, not asserted): one exposure change is a GVCP
    // write and a read-back; the per-frame read-after-frame is one GVCP read.
    let t = Instant::now();
    for k in 0..50 {
        cam.set_exposure_us(if k % 2 == 0 { 4000.0 } else { 5000.0 })
            .unwrap();
    }
    let per_set_ms = t.elapsed().as_secs_f64() * 1e3 / 50.0;
    eprintln!("genicam fake: set_exposure_us (write + read back) {per_set_ms:.2} ms per change");
    cam.set_exposure_us(lo).unwrap();
    let mut f = Frame::default();
    cam.grab(&mut f).unwrap();
    assert_eq!((f.width, f.height), (640, 480));
    assert_eq!(f.meta.seq, rows.len() as u64);

    let mut mislabelled = 0;
    for (i, &(back, meta, m)) in rows.iter().enumerate() {
        let step = i / per;
        let asked = steps[step];
        // A frame already in flight when the step began was exposed with the step
        // before's exposure; for the first step that is the clamped request above.
        let before = if step == 0 { clamped } else { steps[step - 1] };
        assert_eq!(
            back, asked,
            "frame {i}: camera read back {back} for {asked}"
        );
        assert!(meta == lo || meta == hi, "frame {i}: exposure {meta}");
        // The frame's brightness says which exposure it was really taken with.
        let (m_asked, m_before) = (mean_at(asked), mean_at(before));
        let (really, m_really) = if (m - m_asked).abs() <= (m - m_before).abs() {
            (asked, m_asked)
        } else {
            (before, m_before)
        };
        assert!(
            (m - m_really).abs() < 4.0,
            "frame {i}: mean {m:.1}, expected {m_asked:.1} ({asked} us) or {m_before:.1} \
             ({before} us, in flight)"
        );
        if meta != really {
            mislabelled += 1;
        }
        // Settled frames (the last half of each step) carry the asked exposure, and the
        // image is exposed with it.
        if i % per >= per / 2 {
            assert_eq!(meta, asked, "frame {i}");
            assert_eq!(really, asked, "frame {i}: mean {m:.1}");
        }
    }
    // Read-after-frame lags a change by the frames already in flight: at most the
    // pool's 4 buffers per change (4 changes, counting the clamp before the first step).
    eprintln!(
        "genicam fake: {mislabelled} of {} frames labelled with the wrong exposure",
        rows.len()
    );
    assert!(mislabelled <= 4 * 4, "{mislabelled} mislabelled");
}

#[test]
fn fake_gige_camera_stamps_come_from_the_camera_clock() {
    let (_l, _fake, mut cam) = fake_gige_camera(320, 240, 2000.0);
    let mut f = Frame::default();
    let mut stamps = Vec::new();
    for k in 0..20u64 {
        cam.grab(&mut f).unwrap();
        assert_eq!(f.meta.seq, k);
        stamps.push(f.meta.stamp_s);
    }
    // Half the first exposure after the first frame's timestamp.
    assert!((stamps[0] - 0.001).abs() < 1e-9, "{}", stamps[0]);
    let mut dt: Vec<f64> = stamps.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(dt.iter().all(|&d| d > 0.0), "{dt:?}");
    dt.sort_by(f64::total_cmp);
    let median = dt[dt.len() / 2];
    // 30 fps asked through AcquisitionFrameRate.
    assert!(
        (median - 1.0 / 30.0).abs() < 0.005,
        "median frame interval {median} s"
    );
}

#[test]
fn after_a_stall_the_next_frame_is_the_newest_not_a_queued_one() {
    let (_l, _fake, mut cam) = fake_gige_camera(320, 240, 2000.0);
    let mut f = Frame::default();
    for _ in 0..3 {
        cam.grab(&mut f).unwrap();
    }
    let before = f.meta.stamp_s;
    // The loop is busy for 10 frame periods; the pool's 4 buffers fill meanwhile.
    std::thread::sleep(Duration::from_millis(330));
    cam.grab(&mut f).unwrap();
    let gap = f.meta.stamp_s - before;
    eprintln!("genicam fake: after a 330 ms stall the next frame is {gap:.3} s newer");
    // Taking the queued buffers in order would give the frame after `before` (33 ms).
    assert!(gap > 0.25, "the frame after the stall is {gap:.3} s newer");
    assert!(
        cam.frames_passed_over() >= 2,
        "{} stale frames passed over",
        cam.frames_passed_over()
    );
    // Keeping up again, a grab passes over the frames that arrived since the last one but
    // the newest: none when the loop keeps pace, and never more than arrived. A frame
    // that arrived incomplete (lost packets) is skipped and counted there instead. The
    // gap between stamps can also come from the camera itself (the fake camera runs late
    // on a loaded host, with no frame between), so the count is bounded by the gap, not
    // equal to it. Checked while fewer than the pool's 4 buffers filled.
    let period = 1.0 / cam.exposure_limits().fps;
    let mut last = f.meta.stamp_s;
    for _ in 0..5 {
        let (stale, skipped) = (cam.frames_passed_over(), cam.skipped);
        cam.grab(&mut f).unwrap();
        let dt = f.meta.stamp_s - last;
        let arrived = (dt / period).round() as u64;
        assert!(arrived >= 1, "frame interval {dt:.3} s");
        if arrived < 4 {
            let (passed, incomplete) = (cam.frames_passed_over() - stale, cam.skipped - skipped);
            let what =
                format!("frame interval {dt:.3} s: {passed} passed over, {incomplete} incomplete");
            // At pace (one period) this is exactly none.
            assert!(passed + incomplete < arrived, "{what}");
        }
        last = f.meta.stamp_s;
    }
}

#[test]
fn start_up_checks_name_the_device_and_the_problem() {
    let _l = lock();
    use_fake_interface(false);
    // Nobody on 127.0.0.1:3956 (an IP address: Aravis asks it directly, no broadcast).
    assert!(!gvcp_answers(Duration::from_millis(200)));
    let e = GenicamCamera::open("127.0.0.1", &config(640, 480, 3000.0))
        .err()
        .expect("no camera there");
    assert!(matches!(e, GenicamError::NotFound { .. }), "{e}");
    let s = e.to_string();
    assert!(
        s.contains("genicam:127.0.0.1") && s.contains("no such camera"),
        "{s}"
    );

    let _fake = FakeGv::start();
    // The simulated sensor is at most 2048x2048.
    let e = GenicamCamera::open("127.0.0.1", &config(4000, 3000, 3000.0))
        .err()
        .expect("too big");
    let s = e.to_string();
    assert!(matches!(e, GenicamError::Resolution { .. }), "{s}");
    assert!(
        s.contains("4000x3000") && s.contains("genicam:127.0.0.1"),
        "{s}"
    );
    // The site's exposure range outside the camera's (10 us .. 10 s).
    let mut cfg = config(640, 480, 3000.0);
    cfg.limits = ExposureLimits {
        min_us: 2e7,
        max_us: 3e7,
        fps: 30.0,
    };
    let e = GenicamCamera::open("127.0.0.1", &cfg).err().expect("range");
    let s = e.to_string();
    assert!(
        matches!(
            e,
            GenicamError::Rejected {
                feature: "ExposureTime",
                ..
            }
        ),
        "{s}"
    );
}

#[test]
fn fake_interface_first_camera_without_network() {
    let _l = lock();
    // Only Aravis's in-process simulated camera: nothing touches USB or the network.
    use_fake_interface(true);
    let opened = GenicamCamera::open("", &config(256, 128, 2000.0));
    use_fake_interface(false);
    let mut cam = opened.unwrap();
    assert_eq!(cam.name(), "genicam:");
    let rows = sweep(&mut cam, &[2000.0, 20_000.0], 6);
    let (m_lo, m_hi) = (rows[5].2, rows[11].2);
    assert_eq!((rows[5].1, rows[11].1), (2000.0, 20_000.0));
    assert!(
        (m_lo - predicted_mean(2000.0, 256, 128)).abs() < 4.0,
        "mean {m_lo:.1} at 2 ms"
    );
    assert!(
        (m_hi - predicted_mean(20_000.0, 256, 128)).abs() < 4.0,
        "mean {m_hi:.1} at 20 ms"
    );
}

// ---- markhold run end to end ----

#[test]
fn run_with_fake_genicam_camera_on_hil_vehicle() {
    let _l = lock();
    let _fake = FakeGv::start();
    let v = RealTimeVehicle::start(station_rig(false));
    let rec = tmp("run.mcap");
    let summary = tmp("run.json");
    let mut child = common::spawn_quiet(
        run_engaged(&site_path(), "genicam:127.0.0.1")
            .args(["--seconds", "2", "--link", &v.link()])
            .arg("--record")
            .arg(&rec)
            .arg("--summary")
            .arg(&summary),
    );
    let err = BufReader::new(child.stderr.take().unwrap());
    let log = std::thread::spawn(move || err.lines().map_while(Result::ok).collect::<Vec<_>>());
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = exit_status_by(
        &mut child,
        deadline,
        "markhold run did not stop after --seconds 2",
    );
    let log = log.join().unwrap().join("\n");
    std::thread::sleep(Duration::from_millis(100));
    let stats = v.finish().stats;
    assert!(status.success(), "{log}");
    let report = read_json(&summary);
    eprintln!("genicam run: {report}");
    assert_eq!(report["stopped_by"], "max_seconds", "{report}");
    // 2 s of camera time at 30 fps; when the loop is slower (2 shared cores) each grab
    // takes the newest frame and passes over the rest.
    let frames = report["frames"].as_u64().unwrap();
    assert!((10..=64).contains(&frames), "{report}");
    // A ramp, no marker.
    assert_eq!(report["detected"], 0, "{report}");
    // The vehicle heard markhold's pilot input on (nearly) every frame.
    assert!(stats.pilot_inputs + 5 >= frames, "{stats:?}");
    assert_eq!(stats.pilot_inputs_dropped, 0, "{stats:?}");

    // Every recorded frame carries the exposure read back from the camera, within the
    // site's limits, and the loop's clock is the camera's.
    let buf = std::fs::read(&rec).unwrap();
    let mut exposures = Vec::new();
    let mut stamps = Vec::new();
    let mut commands = 0;
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == TOPIC_FRAME {
            let v: FrameMsg = serde_json::from_slice(&m.data).unwrap();
            exposures.push(v.exposure_us);
            stamps.push(v.stamp_s);
        } else if m.channel.topic == TOPIC_COMMAND {
            commands += 1;
        }
    }
    let dropped = report["record"]["frames_dropped"].as_u64().unwrap();
    assert_eq!(exposures.len() as u64 + dropped, frames, "{report}");
    assert_eq!(commands, exposures.len());
    // The run stops at the first frame 2 s after the first: within one frame gap of it.
    let gap = stamps.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
    assert!(gap > 0.0, "stamps {stamps:?}");
    let loop_s = report["loop_seconds"].as_f64().unwrap();
    assert!(
        loop_s >= 2.0 && loop_s <= 2.0 + gap + 1e-6,
        "gap {gap}: {report}"
    );
    // Frames handled and frames passed over for a newer one are frames the camera took
    // in that time, each counted once.
    let passed = report["frames_passed_over"].as_u64().unwrap();
    eprintln!("genicam run: {frames} frames handled, {passed} passed over");
    assert!(
        frames + passed <= (loop_s * 30.0).round() as u64 + 2,
        "{report}"
    );
    let site = params::load(&site_path()).unwrap();
    let lim = site.limits();
    for e in &exposures {
        assert!(*e >= lim.min_us && *e <= lim.max_us, "{e}");
        assert_eq!(
            e.fract(),
            0.0,
            "the simulated camera keeps whole microseconds: {e}"
        );
    }
}

#[test]
fn run_with_a_missing_genicam_camera_exits_2_naming_it() {
    let _l = lock();
    assert!(!gvcp_answers(Duration::from_millis(200)));
    let rec = tmp("never.mcap");
    let o = run_engaged(&site_path(), "genicam:127.0.0.1")
        .arg("--record")
        .arg(&rec)
        .output()
        .unwrap();
    let err = crate::common::stderr_of_exit(&o, 2);
    assert!(
        err.contains("camera genicam:127.0.0.1") && err.contains("no such camera"),
        "{err}"
    );
    assert!(!rec.exists(), "half-written recording left behind");
}
