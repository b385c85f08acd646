//! End to end: faults injected into a HIL run (the library's `HilRun`, the same loop the
//! binary runs), each checked for what the loop must do about it. 640x480 pool fixture.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::path::Path;

use markhold::params::{self, LoadedSite};
use markhold::sim::faults::{FaultKind, FaultReport, FaultSpec, STATION_TOL_M};
use markhold::sim::hil::HilOptions;
use markhold_autopilot::{ArduSubMode, Directive};
use markhold_hil::Truth;

fn site(mode: &str) -> LoadedSite {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let text = text.replace("mode = \"manual\"", &format!("mode = \"{mode}\""));
    params::parse(&path, &text).unwrap()
}

struct Outcome {
    reports: Vec<FaultReport>,
    truth: Vec<Truth>,
    exposure_used_us: Vec<f64>,
    directives: Vec<Directive>,
    detected: Vec<bool>,
    stats: markhold::sim::faults::CameraFaultStats,
    relay: Option<markhold::sim::faults::RelayStats>,
}

fn run(
    site: &LoadedSite,
    seconds: f64,
    faults: &[&str],
    initial_exposure_us: Option<f64>,
) -> Outcome {
    run_seed(site, seconds, faults, initial_exposure_us, 3)
}

fn run_seed(
    site: &LoadedSite,
    seconds: f64,
    faults: &[&str],
    initial_exposure_us: Option<f64>,
    seed: u64,
) -> Outcome {
    run_hooked(site, seconds, faults, initial_exposure_us, seed, |_| {})
}

/// `run_seed` with `before` called on the run before its first frame.
fn run_hooked(
    site: &LoadedSite,
    seconds: f64,
    faults: &[&str],
    initial_exposure_us: Option<f64>,
    seed: u64,
    before: impl FnOnce(&mut markhold::sim::hil::HilRun),
) -> Outcome {
    let opts = HilOptions {
        seconds,
        seed,
        start_on_station: true,
        initial_exposure_us,
        faults: faults
            .iter()
            .map(|f| f.parse::<FaultSpec>().unwrap())
            .collect(),
        ..HilOptions::default()
    };
    let mut hil = crate::common::armed_hil(site, &opts);
    before(&mut hil);
    let frames = (seconds * site.site.camera.fps).round() as usize;
    let mut out = Outcome {
        reports: Vec::new(),
        truth: Vec::with_capacity(frames),
        exposure_used_us: Vec::with_capacity(frames),
        directives: Vec::with_capacity(frames),
        detected: Vec::with_capacity(frames),
        stats: Default::default(),
        relay: None,
    };
    for _ in 0..frames {
        let (rec, truth) = hil.step().unwrap();
        out.truth.push(truth);
        out.exposure_used_us.push(rec.exposure_used_us);
        out.directives.push(rec.directive);
        out.detected.push(rec.detected);
    }
    let f = hil.faults.take().expect("faults were given");
    out.stats = f.camera.stats;
    out.relay = f.relay.as_ref().map(|r| r.stats);
    out.reports = f.monitor.into_reports();
    out
}

/// Station regained is reported only after the vehicle left the tolerance: then within
/// `within_s` of the end; else never (and the error stayed within it).
fn station_regained_or_never_lost(r: &FaultReport, end: f64, within_s: f64) {
    if r.max_position_error_m > STATION_TOL_M {
        let regained = r.station_regained_at_s.expect("station not regained");
        assert!(regained - end < within_s, "{r:?}");
    } else {
        assert_eq!(
            r.station_regained_at_s, None,
            "nothing lost, nothing regained: {r:?}"
        );
    }
}

fn station_error(site: &LoadedSite, t: &Truth) -> f64 {
    let t_marker_station = site.site.station.t_marker_vehicle();
    (t_marker_station.inverse() * site.t_world_marker().inverse() * t.t_world_vehicle)
        .translation
        .vector
        .norm()
}

#[test]
fn link_cut_goes_silent_reconnects_and_regains_station() {
    let s = site("stabilize");
    let o = run(&s, 14.0, &["link_cut@6+2"], None);
    let r = &o.reports[0];
    println!("link_cut@6+2: {r:?}");
    assert_eq!(r.kind, FaultKind::LinkCut);
    // Link loss is measured from any message of the vehicle's autopilot (ATTITUDE and the
    // other streams at 10 Hz), not from its 1 Hz heartbeat: the default timeout is 1 s.
    assert!(s.site.link.vehicle_timeout_s <= 1.0);
    let silent = r.silent_at_s.expect("never went silent");
    let lost = r.heartbeat_lost_at_s.expect("link loss not reported");
    // No pilot input to the vehicle within 1 s of the cut, and never before it.
    assert!((6.0..=7.0).contains(&silent), "{r:?}");
    assert!((6.0..=7.0).contains(&lost), "{r:?}");
    assert_eq!(r.commands_while_unheard, 0, "{r:?}");
    let back = r.heartbeat_restored_at_s.expect("never reconnected");
    assert!((8.0..=9.05).contains(&back), "{r:?}");
    station_regained_or_never_lost(r, 8.0, 4.0);
    assert!(r.vehicle_disarmed_at_s.is_none(), "{r:?}");
    let relay = o.relay.unwrap();
    assert!(
        relay.dropped > 0 && relay.to_vehicle > 0 && relay.to_markhold > 0,
        "{relay:?}"
    );
    // Silent frames exist, and only inside the window.
    let fps = s.site.camera.fps;
    for (i, d) in o.directives.iter().enumerate() {
        if *d == Directive::Silent {
            let t = (i + 1) as f64 / fps;
            assert!((6.0..=back + 0.05).contains(&t), "silent at {t}");
        }
    }
    assert!(station_error(&s, o.truth.last().unwrap()) < STATION_TOL_M);
}

#[test]
fn vehicle_disarmed_by_its_own_failsafe_is_reported_not_fought() {
    // Longer than ArduSub's pilot-input failsafe (3 s in the HIL endpoint): it disarms.
    let s = site("stabilize");
    let o = run(&s, 12.0, &["link_cut@4+5"], None);
    let r = &o.reports[0];
    let disarmed = r.vehicle_disarmed_at_s.expect("disarm not noticed");
    assert!(disarmed >= 9.0, "{r:?}");
    // markhold never re-arms the vehicle.
    let last = o.truth.last().unwrap();
    assert!(!last.armed, "vehicle re-armed");
    assert!(o.truth.iter().skip_while(|t| t.armed).all(|t| !t.armed));
}

/// How far from its pre-fault value the exposure may be 1 s after the marker is back.
/// AAEC's optimum on this scene is flat and where it stops depends on the path: from
/// above (the start) it lands on the knee at 3.8 ms; after the loss the reacquisition
/// brings it back from below and 1 s after the return it is at 5.0-7.9 ms. Over seeds 1-6
/// the ratio was 1.84-2.06 (`out_of_view@3+1.5`), 1.33-2.07 (`occlude@4+0.5`) and
/// 1.33-1.75 (`occlude@4+3`), STABILIZE (`markhold hil --site F --fault SPEC --seed N
/// --trace T.csv`, F = pool-640 in STABILIZE). A runaway goes to a limit (20 us or 30 ms,
/// 8x away) and is caught here and by the limit check.
const BACK_FACTOR: f64 = 2.5;

/// No runaway: the exposure commanded during the window never goes near the camera's
/// limits, and at `back_s` it is within `factor` of where it was before the start.
fn exposure_bounded(s: &LoadedSite, o: &Outcome, start_s: f64, back_s: f64, factor: f64) {
    let fps = s.site.camera.fps;
    let before = o.exposure_used_us[(start_s * fps) as usize - 1];
    let at_end = o.exposure_used_us[(back_s * fps) as usize - 1];
    let r = o.reports.iter().find(|r| r.start_s == start_s).unwrap();
    let lim = s.limits();
    assert!(
        r.exposure_max_us < 0.5 * lim.max_us && r.exposure_min_us > 2.0 * lim.min_us,
        "exposure ran to a limit: {r:?}"
    );
    assert!(
        at_end <= before * factor && at_end >= before / factor,
        "exposure {at_end} us at {back_s} s, {before} us before: {r:?}"
    );
}

fn occlusion(seconds_occluded: f64) {
    // STABILIZE: with the marker gone nothing holds position, and in MANUAL the attitude
    // drifts too (see docs/design/reliability.md).
    let s = site("stabilize");
    let start = 4.0;
    let end = start + seconds_occluded;
    let spec = format!("occlude@{start}+{seconds_occluded}");
    let o = run(&s, end + 4.0, &[&spec], None);
    let fps = s.site.camera.fps;
    let r = &o.reports[0];
    assert!(o.stats.frames_occluded > 0);
    let missed = r.marker_missed_at_s.expect("marker still detected");
    assert!(missed - start < 2.0 / fps, "{r:?}");
    // Nothing detected inside the window: the painted marker is really gone.
    let inside = ((start * fps).ceil() as usize + 1)..((end * fps) as usize - 1);
    assert!(o.detected[inside].iter().all(|d| !d));
    let again = r
        .marker_detected_again_at_s
        .expect("marker never detected again");
    assert!(again - end < 0.5, "{r:?}");
    // Back within 1 s of the marker's return (the detection steers it again).
    exposure_bounded(&s, &o, start, end + 1.0, BACK_FACTOR);
    if seconds_occluded > s.site.controller.marker_lost_hold_s {
        assert!(
            r.marker_lost_at_s.is_some(),
            "marker-loss policy did not act: {r:?}"
        );
    }
    station_regained_or_never_lost(r, end, 3.0);
}

#[test]
fn marker_occluded_half_a_second() {
    occlusion(0.5);
}

#[test]
fn marker_occluded_three_seconds() {
    occlusion(3.0);
}

#[test]
fn marker_occluded_long_policy_acts_exposure_holds() {
    // Without the marker nothing holds position: the vehicle drifts off in the gusts and
    // station is not regained by itself (no search behaviour). What must hold: the
    // loss policy acts, the keeper stays neutral, the exposure does not run away.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("mode = \"manual\"", "mode = \"stabilize\"")
        + "\n[controller]\nmarker_lost_action = \"alt_hold\"\n";
    let s = params::parse(&path, &text).unwrap();
    // 12 s covers the action (10 s); the 30 s case is quoted in docs/design/reliability.md.
    let o = run(&s, 14.5, &["occlude@2+12"], None);
    let r = &o.reports[0];
    let hold = s.site.controller.marker_lost_hold_s;
    let after = s.site.controller.marker_lost_action_after_s;
    let lost = r.marker_lost_at_s.expect("marker-loss policy did not act");
    assert!((lost - 2.0 - hold).abs() < 0.1, "{r:?}");
    let action = r.marker_lost_action_at_s.expect("loss action not due");
    assert!((action - 2.0 - after).abs() < 0.6, "{r:?}");
    // The vehicle drifts, so the view changes: only no runaway to a limit is asserted,
    // and a neutral loop.
    exposure_bounded(&s, &o, 2.0, 14.0, 4.0);
    let fps = s.site.camera.fps;
    assert!(
        o.directives[(action * fps) as usize + 1..(14.0 * fps) as usize]
            .iter()
            .all(|d| *d == Directive::Neutral)
    );
}

#[test]
fn marker_out_of_view_then_back() {
    let s = site("stabilize");
    let o = run(&s, 8.0, &["out_of_view@3+1.5"], None);
    let r = &o.reports[0];
    assert!(o.stats.frames_out_of_view > 0);
    assert!(r.marker_detected_again_at_s.unwrap() - 4.5 < 0.5, "{r:?}");
    exposure_bounded(&s, &o, 3.0, 5.5, BACK_FACTOR);
    station_regained_or_never_lost(r, 4.5, 8.0);
}

#[test]
fn exposure_ignored_then_obeyed() {
    let s = site("manual");
    // Start far too bright: the controller must move, the camera ignores it for 2 s.
    let o = run(&s, 8.0, &["exposure_ignored@0+2"], Some(25_000.0));
    let fps = s.site.camera.fps;
    assert!(o.stats.exposure_ignored > 50, "{:?}", o.stats);
    // Ignored: every frame in the window was taken with the start exposure.
    for &e in &o.exposure_used_us[1..(2.0 * fps) as usize] {
        assert!((e - 25_000.0).abs() < 1.0, "{e}");
    }
    // Obeyed afterwards: converged away from it, and detection back.
    let last = *o.exposure_used_us.last().unwrap();
    assert!(last < 15_000.0, "{last}");
    assert!(o.detected[o.detected.len() - 30..].iter().all(|d| *d));
    // The summary: "detected again" only after a miss, "regained" only after a loss.
    let r = &o.reports[0];
    assert_eq!(
        r.marker_detected_again_at_s.is_some(),
        r.marker_missed_at_s.is_some(),
        "{r:?}"
    );
    station_regained_or_never_lost(r, 2.0, 6.0);
}

/// A fault that changes nothing the loop sees (exposure applied late for a second,
/// on station): no miss, no loss, so nothing "detected again" or "regained" in the summary.
#[test]
fn a_fault_without_effect_reports_no_recovery() {
    let s = site("manual");
    let o = run(&s, 3.0, &["exposure_late@1+1"], None);
    let r = &o.reports[0];
    assert!(o.detected.iter().all(|d| *d), "{r:?}");
    assert_eq!(r.marker_missed_at_s, None, "{r:?}");
    assert_eq!(r.marker_detected_again_at_s, None, "{r:?}");
    assert_eq!(r.neutral_at_s, None, "{r:?}");
    assert!(r.max_position_error_m <= STATION_TOL_M, "{r:?}");
    assert_eq!(r.station_regained_at_s, None, "{r:?}");
}

#[test]
fn exposure_applied_three_frames_late_does_not_oscillate() {
    let s = site("manual");
    let o = run(&s, 10.0, &["exposure_late@0"], Some(300.0));
    assert!(o.stats.exposure_delayed > 200);
    let e = &o.exposure_used_us;
    let n = e.len();
    // Settled: the last 3 s stay within 10 % of their mean, with few reversals.
    let tail = &e[n - 90..];
    let mean = tail.iter().sum::<f64>() / tail.len() as f64;
    assert!(
        tail.iter().all(|v| (v - mean).abs() < 0.1 * mean),
        "{tail:?}"
    );
    assert!(mean > 1_000.0, "never brightened from 300 us: {mean}");
    assert!(o.detected[n - 60..].iter().all(|d| *d));
}

#[test]
fn dropped_and_late_frames_keep_station() {
    let s = site("manual");
    let o = run(&s, 10.0, &["drop_frames@2+3", "late_frames@6+2"], None);
    assert!(o.stats.frames_dropped > 20, "{:?}", o.stats);
    assert!(o.stats.frames_late > 30, "{:?}", o.stats);
    for r in &o.reports {
        assert!(r.max_position_error_m < 0.15, "{r:?}");
        assert!(r.silent_at_s.is_none() && r.neutral_at_s.is_none(), "{r:?}");
    }
    assert!(station_error(&s, o.truth.last().unwrap()) < STATION_TOL_M);
}

#[test]
fn fault_flags_end_to_end_in_the_summary() {
    let pool = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let out = common::tmp_path("faults", "summary.json");
    let o = common::run_ok(
        common::markhold()
            .args(["hil", "--quiet", "--seconds", "4", "--site"])
            .arg(&pool)
            .args(["--fault", "occlude@1+0.5", "--fault", "drop_frames@2"])
            .arg("--summary")
            .arg(&out),
    );
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("fault occlude 1.00 s .. 1.50 s"),
        "{stdout}"
    );
    let v = common::read_json(&out);
    let faults = v["faults"].as_array().unwrap();
    assert_eq!(faults.len(), 2);
    assert_eq!(faults[0]["kind"], "occlude");
    assert_eq!(faults[0]["end_s"], 1.5);
    assert!(faults[1]["end_s"].is_null());
    let bad = common::markhold()
        .args(["hil", "--quiet", "--seconds", "1", "--fault", "lamp@1"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("unknown kind"));
    let _ = std::fs::remove_file(out);
}

/// The pool fixture in `mode`, with extra `[controller]` keys (marker-loss policy).
fn site_with_controller(mode: &str, controller: &str) -> LoadedSite {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("mode = \"manual\"", &format!("mode = \"{mode}\""))
        + "\n[controller]\n"
        + controller;
    params::parse(&path, &text).unwrap()
}

/// Depth of the vehicle (world NED z), metres.
fn depth(t: &Truth) -> f64 {
    t.t_world_vehicle.translation.vector.z
}

#[test]
fn marker_occluded_30_s_alt_hold_holds_depth_then_station_comes_back() {
    // Site conditions where coming back is physically possible without a search: the
    // calm pool (no current, no gusts), STABILIZE as the site's mode (attitude and heading
    // held with neutral sticks). What moves the vehicle is its own buoyancy (it rises in
    // STABILIZE with neutral throttle), which ALT_HOLD cancels: the loss action is what
    // keeps the marker in view.
    let s = site_with_controller(
        "stabilize",
        "marker_lost_action = \"alt_hold\"\nmarker_lost_action_after_s = 3.0\n",
    );
    let (start, dur) = (2.0, 30.0);
    let end = start + dur;
    let o = run(&s, end + 6.0, &[&format!("occlude@{start}+{dur}")], None);
    let fps = s.site.camera.fps;
    let r = &o.reports[0];
    // Due 3 s after the marker was last seen (the frame before the window), on sim stamps.
    let action = r.loss_action_requested_at_s.expect("no loss action");
    assert!(
        (action - (start + 3.0)).abs() <= 1.5 / fps,
        "action at {action}: {r:?}"
    );
    assert_eq!(r.marker_lost_action_at_s, Some(action), "{r:?}");
    assert_eq!(r.loss_action_mode, Some(ArduSubMode::AltHold), "{r:?}");
    assert!(r.surface_fallback_at_s.is_none(), "{r:?}");
    let in_mode = r
        .loss_action_in_mode_at_s
        .expect("vehicle never in ALT_HOLD");
    // Seen in the next 1 Hz heartbeat.
    assert!(in_mode - action <= 1.05, "{r:?}");
    // The vehicle obeys (truth): ALT_HOLD from then to the end of the occlusion, depth
    // held within 10 cm while neutral input is sent.
    let i0 = (in_mode * fps).round() as usize;
    let i1 = (end * fps) as usize - 2;
    // ALT_HOLD holds the stopping point of the climb it caught (ArduSub does the same):
    // the held depth is the one 2 s after the switch.
    let z_switch = depth(&o.truth[i0]);
    let z0 = depth(&o.truth[i0 + (2.0 * fps) as usize]);
    assert!((z0 - z_switch).abs() < 0.15, "{z_switch} -> {z0}");
    for (i, t) in o.truth[i0..i1].iter().enumerate() {
        assert_eq!(t.mode, 2, "not in ALT_HOLD at frame {}", i0 + i);
        if t.time_s < in_mode + 2.0 {
            continue;
        }
        assert!(
            (depth(t) - z0).abs() < 0.10,
            "depth {} vs {z0} at {:.2} s",
            depth(t),
            t.time_s
        );
    }
    assert!(o.directives[i0..i1]
        .iter()
        .all(|d| *d == Directive::Neutral));
    let held = o.truth[i0 + (2.0 * fps) as usize..i1].iter().map(depth);
    let (lo, hi) = held.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), z| {
        (a.min(z), b.max(z))
    });
    eprintln!("ALT_HOLD depth over the occlusion: {lo:.3} .. {hi:.3} m");
    // Before the action (neutral in STABILIZE) the buoyant vehicle rose: the action is
    // what held it.
    let before = depth(&o.truth[(start * fps) as usize]);
    assert!(
        before - z_switch > 0.02,
        "did not rise before the action: {before} -> {z_switch}"
    );
    eprintln!(
        "depth {before:.3} m at the occlusion, {z_switch:.3} m at the switch, held at {z0:.3} m"
    );
    // Marker back: detected, site mode (STABILIZE) requested and restored, station back.
    let again = r
        .marker_detected_again_at_s
        .expect("marker not detected again");
    assert!(again - end < 0.5, "{r:?}");
    let req = r.site_mode_requested_at_s.expect("site mode not requested");
    assert!(req >= again && req - again < 0.2, "{r:?}");
    let restored = r.site_mode_restored_at_s.expect("site mode not restored");
    // The mode is read from the vehicle's 1 Hz heartbeat.
    assert!(restored - req <= 1.05, "{r:?}");
    assert_eq!(o.truth.last().unwrap().mode, 0);
    // The report's `station_regained_at_s` counts only a station that was lost (error
    // past STATION_TOL_M); ALT_HOLD, holding heading and depth as ArduSub 4.5 does, can
    // keep the vehicle within it through the whole occlusion.
    match r.station_regained_at_s {
        Some(regained) => assert!(regained - end < 4.0, "{r:?}"),
        None => assert!(
            r.max_position_error_m <= STATION_TOL_M,
            "station not regained: {r:?}"
        ),
    }
    // Within the tolerance (truth) from 4 s after the marker came back to the end.
    let back = ((end + 4.0) * fps).round() as usize;
    for t in &o.truth[back..] {
        let e = station_error(&s, t);
        assert!(e < STATION_TOL_M, "{e:.3} m off at {:.2} s", t.time_s);
    }
}

#[test]
fn marker_lost_surface_action_climbs_to_the_surface() {
    // ArduSub with a depth sensor accepts SURFACE (mode_surface.cpp `init` checks only
    // the depth sensor): the vehicle climbs on its own, no fallback.
    let s = site_with_controller(
        "stabilize",
        "marker_lost_action = \"surface\"\nmarker_lost_action_after_s = 2.0\n",
    );
    let o = run(&s, 22.0, &["occlude@2"], None);
    let fps = s.site.camera.fps;
    let r = &o.reports[0];
    let action = r.loss_action_requested_at_s.expect("no loss action");
    assert!((action - 4.0).abs() <= 1.5 / fps, "{r:?}");
    assert_eq!(r.surface_fallback_at_s, None, "SURFACE was refused: {r:?}");
    assert_eq!(r.loss_action_mode, Some(ArduSubMode::Surface), "{r:?}");
    let in_mode = r
        .loss_action_in_mode_at_s
        .expect("vehicle never in SURFACE");
    // The mode is read from the vehicle's 1 Hz heartbeat.
    assert!(in_mode - action <= 1.05, "{r:?}");
    let i0 = (action * fps).round() as usize;
    let z0 = depth(&o.truth[i0]);
    let last = o.truth.last().unwrap();
    eprintln!(
        "surface: depth {z0:.3} m at the request ({action:.2} s), in SURFACE at {in_mode:.2} s, \
         {:.3} m in mode {} at {:.2} s: {r:?}",
        depth(last),
        last.mode,
        last.time_s
    );

    // Climbed from about 3 m to the surface (truth), where SURFACE hands over to ALT_HOLD
    // (mode_surface.cpp: at the surface, ALT_HOLD).
    assert!(z0 > 2.0, "{z0}");
    assert!(depth(last) < 0.3, "still at {} m", depth(last));
    // Climbing the whole way up in SURFACE: no sample deeper than 5 cm below an earlier
    // one; then ALT_HOLD holds it near the surface (it settles about 10 cm down from the
    // top of its climb, SURFACE_DEPTH).
    let up = o.truth[i0..]
        .iter()
        .position(|t| t.mode == 2)
        .expect("SURFACE never reached the surface")
        + i0;
    let mut shallowest = z0;
    for t in &o.truth[i0..up] {
        assert!(depth(t) < shallowest + 0.05, "sank at {:.2} s", t.time_s);
        shallowest = shallowest.min(depth(t));
    }
    assert!(shallowest < 0.3, "{shallowest}");
    assert!(
        o.truth[up..].iter().all(|t| depth(t) < 0.3),
        "sank after the surface"
    );
    // SURFACE climbs by itself: markhold's input stays neutral, and nothing goes to an
    // unheard vehicle.
    let i1 = (in_mode * fps).round() as usize;
    assert!(o.directives[i1 + 2..]
        .iter()
        .all(|d| *d == Directive::Neutral));
    assert_eq!(r.commands_while_unheard, 0);
}

#[test]
fn marker_lost_surface_action_with_a_failed_depth_sensor_falls_back_and_climbs() {
    // With its depth sensor failed ArduSub refuses SURFACE and ALT_HOLD
    // (`control_check_barometer`): markhold falls back as docs/design/loop.md says,
    // requesting ALT_HOLD with the throttle stick up; that is refused as well, so the
    // vehicle stays in the site's STABILIZE, where the stick up is a direct throttle.
    let s = site_with_controller(
        "stabilize",
        "marker_lost_action = \"surface\"\nmarker_lost_action_after_s = 2.0\n",
    );
    let o = run_hooked(&s, 16.0, &["occlude@2"], None, 3, |hil| {
        hil.rig.set_depth_sensor_healthy(false)
    });
    let fps = s.site.camera.fps;
    let r = &o.reports[0];
    let action = r.loss_action_requested_at_s.expect("no loss action");
    assert!((action - 4.0).abs() <= 1.5 / fps, "{r:?}");
    let fallback = r.surface_fallback_at_s.expect("SURFACE was not refused");
    assert!(fallback - action < 0.5, "{r:?}");
    assert_eq!(r.loss_action_mode, Some(ArduSubMode::AltHold), "{r:?}");
    assert_eq!(r.loss_action_in_mode_at_s, None, "ALT_HOLD accepted: {r:?}");
    // Never left STABILIZE.
    assert!(
        o.truth.iter().all(|t| t.mode == 0),
        "a depth mode was entered"
    );
    let i0 = (fallback * fps).round() as usize;
    let z0 = depth(&o.truth[i0]);
    let last = o.truth.last().unwrap();
    eprintln!(
        "surface, depth sensor failed: fallback at {fallback:.2} s from {z0:.3} m, {:.3} m at {:.2} s: {r:?}",
        depth(last),
        last.time_s
    );
    // The climb is sent as pilot input, never to an unheard vehicle, and it climbs.
    assert!(o.directives[i0 + 2..]
        .iter()
        .all(|d| *d == Directive::Command));
    assert_eq!(r.commands_while_unheard, 0);
    assert!(z0 > 2.0, "{z0}");
    assert!(depth(last) < 0.3, "still at {} m", depth(last));
}

/// Frames after `from` until the exposure the frames were taken with stays within `tol`
/// (relative) of its settled value (the median of the last second before `to`), and
/// that value.
fn frames_to_settle(e: &[f64], from: usize, to: usize, fps: f64, tol: f64) -> (usize, f64) {
    let mut tail = e[to - fps as usize..to].to_vec();
    tail.sort_by(|a, b| a.total_cmp(b));
    let settled = tail[tail.len() / 2];
    let within = |v: f64| (v - settled).abs() <= tol * settled;
    let mut j = to;
    while j > from && within(e[j - 1]) {
        j -= 1;
    }
    (j - from, settled)
}

/// What the tests hold the exposure to after a light change, in HIL: within 15 % of the
/// value it settles at within one second (30 frames), then no oscillation: every
/// frame-to-frame change below 15 % and nothing outside 25 % of the settled value.
const RECOVER_FRAMES: usize = 30;
const RECOVER_TOL: f64 = 0.15;
/// The light-change goal, asserted on every seed of `LIGHT_SEEDS`: within 5 % of the settled
/// value at most 8 frames after the change (one frame of actuation delay, so 4 used
/// frames). Met since AAEC's knee landing (docs/design/exposure.md); before it,
/// 6 of these 20 cases were.
const SETTLE_FRAMES: usize = 8;
/// The light-change tests run over these seeds of the simulated world: the frames to
/// settle varied from 2 to 71 over them before the knee landing, so one seed says little.
const LIGHT_SEEDS: [u64; 5] = [1, 2, 3, 4, 5];

/// One light change at `at_s`, checked up to `to_s`: exposure follows it in the expected
/// direction, recovers and does not oscillate, the marker is detected on every frame
/// after recovery, and is within 5 % of its settled value after at most `SETTLE_FRAMES`.
/// Returns the frames to within 5 % of the settled value.
fn light_change(o: &Outcome, fps: f64, at_s: f64, to_s: f64, brighter: bool, what: &str) -> usize {
    let e = &o.exposure_used_us;
    let k = (at_s * fps).round() as usize;
    let to = (to_s * fps).round() as usize;
    let before = e[k - 1];
    let (n5, settled) = frames_to_settle(e, k, to, fps, 0.05);
    let (n, _) = frames_to_settle(e, k, to, fps, RECOVER_TOL);
    let series: Vec<i64> = e[k - 2..to].iter().map(|v| v.round() as i64).collect();
    eprintln!(
        "{what}: {before:.0} us -> {settled:.0} us; within 15 % after {n} frames, within 5 % after {n5} frames; exposures from 2 frames before: {series:?}"
    );
    if brighter {
        assert!(settled < 0.6 * before, "{what}: {before} -> {settled}");
    } else {
        assert!(settled > 1.6 * before, "{what}: {before} -> {settled}");
    }
    assert!(n <= RECOVER_FRAMES, "{what}: {n} frames to within 15 %");
    let after = k + RECOVER_FRAMES;
    for w in e[after..to].windows(2) {
        let rel = (w[1] / w[0] - 1.0).abs();
        assert!(rel < 0.15, "{what}: step {rel:.3} after recovery");
    }
    assert!(
        e[after..to]
            .iter()
            .all(|v| (v - settled).abs() <= 0.25 * settled),
        "{what}: wandered off after recovery"
    );
    assert!(
        o.detected[after..to].iter().all(|d| *d),
        "{what}: marker not detected after recovery"
    );
    assert!(
        n5 <= SETTLE_FRAMES,
        "{what}: {n5} frames to within 5 % of {settled:.0} us"
    );
    n5
}

#[test]
fn lamp_switched_off_and_on_exposure_follows_without_oscillation() {
    // A dim day lit by the vehicle's own lamps (40 W/sr each, daylight 150 W/m2 at the
    // surface): the lamps give most of the light on the marker.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let mut text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("mode = \"manual\"", "mode = \"stabilize\"")
        .replace(
            "scenario = \"normal\"",
            "scenario = \"normal\"\nambient_surface_w_m2 = 150.0",
        );
    for y in [-0.12, 0.12] {
        text += &format!(
            "\n[[lighting.vehicle_lamps]]\nposition_m = [0.22, {y}, -0.05]\ndirection = [1.0, 0.0, 0.0]\n\
             intensity_w_sr = 40.0\ninner_half_angle_deg = 35.0\nouter_half_angle_deg = 65.0\n"
        );
    }
    let s = params::parse(&path, &text).unwrap();
    for seed in LIGHT_SEEDS {
        let o = run_seed(&s, 12.0, &["lamp_off@4+4"], None, seed);
        let fps = s.site.camera.fps;
        let r = &o.reports[0];
        assert_eq!(r.kind, FaultKind::LampOff);
        light_change(&o, fps, 4.0, 8.0, false, &format!("seed {seed}, lamp off"));
        light_change(&o, fps, 8.0, 12.0, true, &format!("seed {seed}, lamp on"));
        // The loop never lost the vehicle over it.
        assert!(r.silent_at_s.is_none(), "{r:?}");
    }
}

/// For each light seed, `seconds` of the stabilize site with the ambient step `fault`:
/// the exposure follows the change between `from_to` s (`brighter`) without oscillating.
fn ambient_step_settles(
    fault: &str,
    seconds: f64,
    from_to: (f64, f64),
    brighter: bool,
    what: &str,
) {
    let s = site("stabilize");
    for seed in LIGHT_SEEDS {
        let o = run_seed(&s, seconds, &[fault], None, seed);
        let fps = s.site.camera.fps;
        assert_eq!(o.reports[0].kind, FaultKind::AmbientStep);
        let what = format!("seed {seed}, {what}");
        light_change(&o, fps, from_to.0, from_to.1, brighter, &what);
    }
}

#[test]
fn ambient_light_back_from_10x_exposure_recovers_without_oscillation() {
    // 10x daylight from the start (the loop settles in it), back to the site's at 5 s.
    ambient_step_settles(
        "ambient_step@0+5",
        9.0,
        (5.0, 9.0),
        false,
        "ambient 10x -> 1x",
    );
}

/// A 10x step up in daylight (without AAEC's restart policy this wandered for 2.5 s;
/// see docs/design/exposure.md).
#[test]
fn ambient_light_10x_step_up_exposure_recovers_without_oscillation() {
    ambient_step_settles("ambient_step@4", 8.0, (4.0, 8.0), true, "ambient 1x -> 10x");
}
