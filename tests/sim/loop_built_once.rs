//! Every runner builds its loop through the one constructor, `Pipeline::new`: given the
//! same site and start, `hil`, `hil --vehicle`, `run` and `replay` make the same loop,
//! differing only in the link and the observers they attach.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::UdpSocket;
use std::path::{Path, PathBuf};

use markhold::observe::TraceWriter;
use markhold::params::{self, LoadedSite};
use markhold::pipeline::{LoopDescription, LoopStart, Observers};
use markhold::record::replay;
use markhold::sim::hil::{open_recorder, run_hil, HilOptions, HilRun};
use markhold_autopilot::VehicleLink;

const SITE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/pool-640.toml");

fn temp(name: &str) -> PathBuf {
    crate::common::tmp_path("loop", name)
}

fn traced(name: &str) -> Observers {
    Observers::new().with(TraceWriter::create(&temp(name)).expect("trace file"))
}

/// A MAVLink link to a loopback socket that never answers (building a loop sends
/// nothing; the socket is only somewhere for the link to point).
fn quiet_link(site: &LoadedSite) -> (VehicleLink, UdpSocket) {
    let sink = UdpSocket::bind("127.0.0.1:0").expect("loopback socket");
    let mut cfg = site.site.link.clone();
    cfg.url = format!("udpout:{}", sink.local_addr().expect("bound"));
    (VehicleLink::connect(&cfg).expect("udpout link"), sink)
}

fn recorded(site: &LoadedSite, opts: &HilOptions) -> PathBuf {
    let path = temp("rec.mcap");
    let rec = open_recorder(site, opts, &path).expect("recorder");
    run_hil(site, opts, Observers::new().with(rec)).expect("a short recorded run");
    path
}

#[test]
fn every_runner_builds_the_same_loop_through_the_one_constructor() {
    let site = params::load(Path::new(SITE)).expect("fixture site");
    let opts = HilOptions {
        seconds: 0.2,
        ..HilOptions::default()
    };
    let site_start = LoopStart::of_site(&site);
    let expect = |start: LoopStart, observers: &[&'static str]| LoopDescription {
        site: site.site.site.name.clone(),
        start,
        frame_width: site.calibration.width,
        frame_height: site.calibration.height,
        observers: observers.to_vec(),
    };

    let hil = HilRun::build(&site, &opts, traced("hil.csv")).expect("hil loop");
    assert_eq!(hil.pipeline.describe(), expect(site_start, &["trace"]));

    let (link, _sink) = quiet_link(&site);
    let external = markhold::sim::external::build_loop(&site, &opts, link, traced("ext.csv"))
        .expect("external-vehicle loop");
    assert_eq!(external.describe(), expect(site_start, &["trace"]));

    let (link, _sink) = quiet_link(&site);
    let live = markhold::field::run::build_loop(&site, link, traced("run.csv")).expect("run loop");
    assert_eq!(live.describe(), expect(site_start, &["trace"]));

    // Replay rebuilds the recorded loop from the file alone: same start, but it asks no
    // vehicle for modes.
    let path = recorded(&site, &opts);
    let buf = std::fs::read(&path).expect("recording");
    let (info, recorded_site) = replay::read_run_info(&path, &buf).expect("run info");
    let method = info.exposure_method.parse().expect("method");
    let replayed = replay::build_loop(&recorded_site, method, &info).expect("replay loop");
    let no_modes = LoopStart {
        site_mode: None,
        ..site_start
    };
    assert_eq!(replayed.describe(), expect(no_modes, &[]));
    let _ = std::fs::remove_file(path);
}

#[test]
fn a_hil_start_from_the_command_line_reaches_the_loop() {
    let site = params::load(Path::new(SITE)).expect("fixture site");
    let limits = site.limits();
    let opts = HilOptions {
        seconds: 0.2,
        exposure: Some(markhold_exposure::ExposureMethod::Gec),
        // Beyond the camera's limit: the loop starts at the limit.
        initial_exposure_us: Some(limits.max_us * 10.0),
        ..HilOptions::default()
    };
    let hil = HilRun::build(&site, &opts, Observers::new()).expect("hil loop");
    let start = hil.pipeline.start();
    assert_eq!(start.method, markhold_exposure::ExposureMethod::Gec);
    assert_eq!(start.initial_exposure_us, limits.max_us);
    assert!(hil.pipeline.describe().observers.is_empty());
}
