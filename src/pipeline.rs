//! The per-frame loop, the same for live, HIL and replay: only the camera, the link and
//! where time comes from differ. Data flows one way per frame:
//! camera -> vision -> station keeper -> link, then exposure -> camera.

use std::time::Instant;

use markhold_autopilot::{
    Directive, Effort, FailsafeEvent, PoseMeasurement, StationKeeper, Supervisor, SupervisorInput,
    VehicleLink, VehicleState,
};
use markhold_exposure::{Camera, Corners, ExposureController, ExposureStep, Frame};
use markhold_vision::{MarkerObservation, MarkerTracker};
use nalgebra::{Isometry3, Matrix6};

/// What happened on one frame, for the summary, the recorder and tests.
#[derive(Debug, Clone, Copy)]
pub struct FrameRecord {
    pub seq: u64,
    pub stamp_s: f64,
    /// Exposure this frame was taken with.
    pub exposure_used_us: f64,
    /// Exposure commanded after this frame.
    pub exposure: ExposureStep,
    pub detected: bool,
    pub corners: Option<Corners>,
    pub t_cam_marker: Option<Isometry3<f64>>,
    /// Covariance of `t_cam_marker` (docs/frames.md order), for the recorder.
    pub cov_cam: Option<Matrix6<f64>>,
    pub reproj_rms_px: f64,
    /// The station keeper's effort.
    pub effort: Effort,
    /// What the failsafe supervisor let through (neutral and silent send no effort).
    pub directive: Directive,
    /// Wall time from the frame being available to the command written to the socket.
    pub latency_s: f64,
}

/// Where the loop's commands go: a real MAVLink link, or (replay) a sink that only
/// keeps them.
pub trait CommandLink {
    /// Drive the link at loop time `now_s` (heartbeats, incoming telemetry).
    fn tick(&mut self, now_s: f64) -> anyhow::Result<()>;
    /// Send this frame's effort.
    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> anyhow::Result<()>;
    /// Send neutral pilot input (on exit, on failsafe).
    fn send_neutral(&mut self, now_s: f64) -> anyhow::Result<()>;
    /// Loop time of the vehicle's last heartbeat, if one was heard.
    fn vehicle_heartbeat_s(&self) -> Option<f64>;
    /// The vehicle's state as the link knows it (for the recorder); none for a sink.
    fn vehicle_state(&self) -> Option<&VehicleState> {
        None
    }
}

impl CommandLink for VehicleLink {
    fn tick(&mut self, now_s: f64) -> anyhow::Result<()> {
        Ok(VehicleLink::tick(self, now_s)?)
    }
    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> anyhow::Result<()> {
        Ok(VehicleLink::send_effort(self, effort, now_s)?)
    }
    fn send_neutral(&mut self, now_s: f64) -> anyhow::Result<()> {
        Ok(VehicleLink::send_neutral(self, now_s)?)
    }
    fn vehicle_heartbeat_s(&self) -> Option<f64> {
        self.state().last_heartbeat_s
    }
    fn vehicle_state(&self) -> Option<&VehicleState> {
        Some(self.state())
    }
}

pub struct Pipeline<L: CommandLink = VehicleLink> {
    pub tracker: MarkerTracker,
    pub exposure: Box<dyn ExposureController>,
    pub keeper: StationKeeper,
    pub link: L,
    pub supervisor: Supervisor,
    pub frame: Frame,
    /// Failsafe transitions of the last frame (reused buffer).
    pub events: Vec<FailsafeEvent>,
    /// Loop time the marker was last seen.
    pub marker_seen_s: Option<f64>,
    /// Set by a signal handler: the next frame sends neutral and the loop ends.
    pub shutdown: bool,
    /// The vehicle's mode changes seen so far: a change resets the station keeper.
    pub mode_changes_seen: u64,
}

impl<L: CommandLink> Pipeline<L> {
    /// A loop over these parts, with empty per-frame state.
    pub fn new(
        tracker: MarkerTracker,
        exposure: Box<dyn ExposureController>,
        keeper: StationKeeper,
        supervisor: Supervisor,
        link: L,
        frame: Frame,
    ) -> Self {
        Self {
            tracker,
            exposure,
            keeper,
            link,
            supervisor,
            frame,
            events: Vec::with_capacity(8),
            marker_seen_s: None,
            shutdown: false,
            mode_changes_seen: 0,
        }
    }

    /// Run one frame through the loop.
    pub fn step(&mut self, camera: &mut dyn Camera) -> anyhow::Result<FrameRecord> {
        camera.grab(&mut self.frame)?;
        let t0 = Instant::now();
        let stamp = self.frame.meta.stamp_s;
        let obs: Option<MarkerObservation> = self.tracker.process(&self.frame)?;
        let meas = obs.as_ref().map(|o| PoseMeasurement {
            stamp_s: stamp,
            t_cam_marker: o.t_cam_marker,
            cov_cam: o.cov_cam,
        });
        self.link.tick(stamp)?;
        // A mode change (by the pilot, a failsafe or us) invalidates the integrators.
        if let Some(changes) = self.link.vehicle_state().map(|v| v.mode_changes) {
            if changes != self.mode_changes_seen {
                self.mode_changes_seen = changes;
                self.keeper.reset();
            }
        }
        let effort = self.keeper.update(stamp, meas.as_ref());
        if obs.is_some() {
            self.marker_seen_s = Some(stamp);
        }
        self.events.clear();
        let directive = self.supervisor.update(
            &SupervisorInput {
                now_s: stamp,
                vehicle_heartbeat_s: self.link.vehicle_heartbeat_s(),
                last_frame_s: Some(stamp),
                marker_seen_s: self.marker_seen_s,
                shutdown: self.shutdown,
            },
            &mut self.events,
        );
        match directive {
            Directive::Command => self.link.send_effort(&effort, stamp)?,
            Directive::Neutral | Directive::Shutdown { .. } => self.link.send_neutral(stamp)?,
            // No vehicle to talk to: pilot input to a vehicle we cannot hear is not sent.
            Directive::Silent => {}
        }
        let latency_s = t0.elapsed().as_secs_f64();

        // Exposure after the command: it does not gate the vehicle.
        let corners = obs.as_ref().map(|o| o.corners);
        let step = self.exposure.update(&self.frame, corners.as_ref());
        camera.set_exposure_us(step.exposure_us)?;
        Ok(FrameRecord {
            seq: self.frame.meta.seq,
            stamp_s: stamp,
            exposure_used_us: self.frame.meta.exposure_us,
            exposure: step,
            detected: obs.is_some(),
            corners,
            t_cam_marker: obs.as_ref().map(|o| o.t_cam_marker),
            cov_cam: obs.as_ref().map(|o| o.cov_cam),
            reproj_rms_px: obs.as_ref().map_or(f64::NAN, |o| o.reproj_rms_px),
            effort,
            directive,
            latency_s,
        })
    }
}
