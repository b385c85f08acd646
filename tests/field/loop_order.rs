//! The loop's order when tracking cannot answer: the frame's command goes out before the
//! full-frame search (`[vision] defer_full_search`, default on), so the search's cost never
//! delays the vehicle. Checked through call order: a link that notes every command and a
//! tracing layer that notes every `marker_full_search` span, in one log.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::Path;
use std::sync::{Arc, Mutex};

use markhold::error::CoreError;
use markhold::params;
use markhold::pipeline::{CommandLink, LoopStart, Observers, Pipeline};
use markhold_autopilot::Effort;
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use tracing_subscriber::layer::{Context, SubscriberExt};
use tracing_subscriber::Layer;

const SITE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/pool-640.toml");
const FRAMES: u64 = 5;

type Log = Arc<Mutex<Vec<&'static str>>>;

/// Notes each command (effort or neutral); a vehicle always heard.
struct OrderLink {
    log: Log,
    now_s: f64,
}

impl CommandLink for OrderLink {
    fn tick(&mut self, now_s: f64) -> Result<(), CoreError> {
        self.now_s = now_s;
        Ok(())
    }
    fn send_effort(&mut self, _effort: &Effort, _now_s: f64) -> Result<(), CoreError> {
        self.log.lock().unwrap().push("command");
        Ok(())
    }
    fn send_neutral(&mut self, _now_s: f64) -> Result<(), CoreError> {
        self.log.lock().unwrap().push("command");
        Ok(())
    }
    fn vehicle_heartbeat_s(&self) -> Option<f64> {
        Some(self.now_s)
    }
}

/// Notes each full-frame search (the tracker's `marker_full_search` span).
struct SearchLayer(Log);

impl<S: tracing::Subscriber> Layer<S> for SearchLayer {
    fn on_new_span(
        &self,
        attrs: &tracing::span::Attributes<'_>,
        _id: &tracing::span::Id,
        _ctx: Context<'_, S>,
    ) {
        if attrs.metadata().name() == "marker_full_search" {
            self.0.lock().unwrap().push("full_search");
        }
    }
}

/// Flat grey frames: no marker, so tracking never answers and every frame needs a full
/// search.
struct GreyCamera {
    seq: u64,
    width: u32,
    height: u32,
    limits: ExposureLimits,
    exposure_us: f64,
}

impl Camera for GreyCamera {
    fn name(&self) -> &str {
        "grey"
    }
    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        self.exposure_us = exposure_us;
        Ok(exposure_us)
    }
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        frame.width = self.width;
        frame.height = self.height;
        frame.data.clear();
        frame.data.resize((self.width * self.height) as usize, 120);
        frame.meta.seq = self.seq;
        frame.meta.stamp_s = self.seq as f64 / 30.0;
        frame.meta.exposure_us = self.exposure_us;
        frame.meta.gain_db = 0.0;
        self.seq += 1;
        Ok(())
    }
}

/// The log of `FRAMES` frames through the loop, one `frame` entry before each.
fn order(defer_full_search: bool) -> Vec<&'static str> {
    let mut site = params::load(Path::new(SITE)).unwrap();
    site.site.vision.defer_full_search = defer_full_search;
    let log: Log = Arc::default();
    let link = OrderLink {
        log: log.clone(),
        now_s: 0.0,
    };
    let mut camera = GreyCamera {
        seq: 0,
        width: site.calibration.width,
        height: site.calibration.height,
        limits: site.limits(),
        exposure_us: site.site.camera.initial_exposure_us,
    };
    let subscriber = tracing_subscriber::registry().with(SearchLayer(log.clone()));
    tracing::subscriber::with_default(subscriber, || {
        let mut pipeline =
            Pipeline::new(&site, LoopStart::of_site(&site), link, Observers::new()).unwrap();
        for _ in 0..FRAMES {
            log.lock().unwrap().push("frame");
            pipeline.step(&mut camera).unwrap();
        }
    });
    let log = log.lock().unwrap().clone();
    log
}

/// `per_frame` once for each of the `FRAMES` frames.
fn every_frame(per_frame: [&'static str; 3]) -> Vec<&'static str> {
    (0..FRAMES).flat_map(|_| per_frame).collect()
}

#[test]
fn the_command_goes_out_before_the_full_search() {
    assert_eq!(
        order(true),
        every_frame(["frame", "command", "full_search"])
    );
}

/// The check tells the orders apart: searching first puts the search before the command.
#[test]
fn without_deferral_the_search_comes_first() {
    assert_eq!(
        order(false),
        every_frame(["frame", "full_search", "command"])
    );
}
