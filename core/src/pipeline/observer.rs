//! Per-frame observers: what every runner can attach to the loop (recording, live view,
//! trace, snapshots, progress). The loop hands each of them the frame it just stepped;
//! an observer never stops the loop: it keeps its first error and reports it when the
//! run finishes.

use crate::CoreError;
use std::sync::mpsc::SyncSender;

use markhold_autopilot::{FailsafeEvent, RawFrame, VehicleState};
use markhold_exposure::Frame;

use super::{FrameRecord, ModeTransition};

/// One frame as the loop decided it, with what the link knew at the time.
pub struct FrameView<'a> {
    pub rec: &'a FrameRecord,
    /// The pixels the decision was made on.
    pub frame: &'a Frame,
    /// Loop time of the vehicle heartbeat the supervisor saw.
    pub heartbeat_s: Option<f64>,
    /// The vehicle's state, when the link is a real one.
    pub vehicle: Option<&'a VehicleState>,
    /// Supervisor transitions of this frame.
    pub events: &'a [FailsafeEvent],
    /// Ids of the markers of the map the frame's pose used, in map order.
    pub markers_in_view: &'a [u32],
    /// Mode changes the loop made on its own this frame.
    pub transitions: &'a [ModeTransition],
    /// The loop was asked to stop on this frame.
    pub shutdown: bool,
}

/// Something that sees every frame the loop steps.
pub trait Observer: Send {
    /// Short name, for logs and for describing the loop.
    fn name(&self) -> &'static str;
    /// This frame; must not block the loop for long and must not fail it.
    fn frame(&mut self, view: &FrameView<'_>);
    /// Flush and close; the first error met during the run is reported here.
    fn finish(self: Box<Self>) -> Result<(), CoreError>;
    /// The run never started: remove what was created (a half-made recording).
    fn abort(self: Box<Self>) {
        if let Err(e) = self.finish() {
            tracing::warn!(error = %e, "closing an observer of a run that did not start");
        }
    }
    /// A channel for every raw MAVLink frame on the link, if this observer keeps them.
    fn mavlink_tap(&self) -> Option<SyncSender<RawFrame>> {
        None
    }
}

/// The observers a runner attached, called in the order they were added.
#[derive(Default)]
pub struct Observers {
    list: Vec<Box<dyn Observer>>,
}

impl Observers {
    pub fn new() -> Self {
        Self::default()
    }

    /// Add `o`; returns `self` for chaining.
    pub fn with(mut self, o: impl Observer + 'static) -> Self {
        self.push(o);
        self
    }

    pub fn push(&mut self, o: impl Observer + 'static) {
        self.list.push(Box::new(o));
    }

    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Names, in call order.
    pub fn names(&self) -> Vec<&'static str> {
        self.list.iter().map(|o| o.name()).collect()
    }

    /// The first raw MAVLink tap an observer asks for (the link feeds one).
    pub fn mavlink_tap(&self) -> Option<SyncSender<RawFrame>> {
        self.list.iter().find_map(|o| o.mavlink_tap())
    }

    pub fn frame(&mut self, view: &FrameView<'_>) {
        for o in &mut self.list {
            o.frame(view);
        }
    }

    /// Finish every observer (all of them, also after one failed); the first error.
    pub fn finish(&mut self) -> Result<(), CoreError> {
        let mut first = Ok(());
        for o in self.list.drain(..) {
            let name = o.name();
            if let Err(e) = o.finish() {
                tracing::error!(observer = name, error = %e, "finishing");
                if first.is_ok() {
                    first = Err(e);
                }
            }
        }
        first
    }

    /// The run did not start: abort every observer.
    pub fn abort(&mut self) {
        for o in self.list.drain(..) {
            o.abort();
        }
    }
}
