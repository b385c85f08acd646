//! The per-frame loop, the same for every runner (`hil`, `hil --vehicle`, `run`,
//! `replay`): only the camera, the link and the observers differ. Data flows one way per
//! frame: camera -> vision -> station keeper -> link, then exposure -> camera, then the
//! observers. [`Pipeline::new`] is the one place the loop is built.

mod failsafe;
mod observer;

use crate::CoreError;
use std::sync::mpsc::SyncSender;
use std::time::Instant;

use markhold_autopilot::{
    ArduSubMode, CommandKind, Directive, Effort, FailsafeEvent, PoseMeasurement, RawFrame,
    StationKeeper, Supervisor, SupervisorInput, VehicleLink, VehicleState, VisionPose,
};
use markhold_exposure::{
    build_controller, Camera, Corners, ExposureController, ExposureMethod, ExposureStep, Frame,
};
use markhold_vision::{MarkerObservation, MarkerTracker, Tracked};
use nalgebra::{Isometry3, Matrix6};

pub use failsafe::{FailsafeActions, ModeTransition, SURFACE_CLIMB_EFFORT};
pub use observer::{FrameView, Observer, Observers};

use crate::params::LoadedSite;

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
    /// Markers of the map the pose was computed from (0 without a pose).
    pub markers_used: u32,
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
    fn tick(&mut self, now_s: f64) -> Result<(), CoreError>;
    /// Send this frame's effort.
    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> Result<(), CoreError>;
    /// Send neutral pilot input (on exit, on failsafe).
    fn send_neutral(&mut self, now_s: f64) -> Result<(), CoreError>;
    /// Setpoint mode: this frame's vehicle pose with its covariance (none when the
    /// marker was not seen) and the goal, both in the marker frame. A link without a
    /// vehicle (replay's sink) keeps nothing.
    fn send_setpoint(
        &mut self,
        _meas: Option<&VisionPose>,
        _goal: &Isometry3<f64>,
        _now_s: f64,
    ) -> Result<(), CoreError> {
        Ok(())
    }
    /// ALT_HOLD's depth target (metres down in the vehicle's local frame), sent after
    /// this frame's effort; a link without a vehicle keeps nothing.
    fn send_depth_target(&mut self, _down_m: f64, _now_s: f64) -> Result<(), CoreError> {
        Ok(())
    }
    /// Loop time of the vehicle's last heartbeat, if one was heard.
    fn vehicle_heartbeat_s(&self) -> Option<f64>;
    /// The vehicle's state as the link knows it (for the recorder); none for a sink.
    fn vehicle_state(&self) -> Option<&VehicleState> {
        None
    }
    /// Ask the vehicle for a flight mode (acknowledged and retried by a real link; a sink
    /// has no vehicle and ignores it).
    fn request_mode(&mut self, _mode: ArduSubMode, _now_s: f64) -> Result<(), CoreError> {
        Ok(())
    }
    /// Ask the vehicle to arm or disarm (acknowledged and retried by a real link).
    fn request_arm(&mut self, _arm: bool, _now_s: f64) -> Result<(), CoreError> {
        Ok(())
    }
    /// Copy every MAVLink frame sent and received to `tap` (a recorder); a link without
    /// MAVLink has nothing to copy.
    fn set_raw_tap(&mut self, _tap: Option<SyncSender<RawFrame>>) {}
}

impl CommandLink for VehicleLink {
    fn tick(&mut self, now_s: f64) -> Result<(), CoreError> {
        Ok(VehicleLink::tick(self, now_s)?)
    }
    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> Result<(), CoreError> {
        Ok(VehicleLink::send_effort(self, effort, now_s)?)
    }
    fn send_neutral(&mut self, now_s: f64) -> Result<(), CoreError> {
        Ok(VehicleLink::send_neutral(self, now_s)?)
    }
    fn send_depth_target(&mut self, down_m: f64, now_s: f64) -> Result<(), CoreError> {
        VehicleLink::send_depth_target(self, down_m, now_s)?;
        Ok(())
    }
    fn send_setpoint(
        &mut self,
        meas: Option<&VisionPose>,
        goal: &Isometry3<f64>,
        now_s: f64,
    ) -> Result<(), CoreError> {
        Ok(VehicleLink::send_setpoint(self, meas, goal, now_s)?)
    }
    fn vehicle_heartbeat_s(&self) -> Option<f64> {
        self.state().last_heartbeat_s
    }
    fn vehicle_state(&self) -> Option<&VehicleState> {
        Some(self.state())
    }
    fn request_mode(&mut self, mode: ArduSubMode, now_s: f64) -> Result<(), CoreError> {
        Ok(VehicleLink::request_mode(self, mode, now_s)?)
    }
    fn request_arm(&mut self, arm: bool, now_s: f64) -> Result<(), CoreError> {
        Ok(VehicleLink::request_arm(self, arm, now_s)?)
    }
    fn set_raw_tap(&mut self, tap: Option<SyncSender<RawFrame>>) {
        VehicleLink::set_raw_tap(self, tap);
    }
}

/// How a loop starts: the exposure method, where the exposure starts, and the flight
/// mode the failsafe actions return to (none: replay, which asks the vehicle nothing).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopStart {
    pub method: ExposureMethod,
    /// Clamped to the camera's limits by [`Pipeline::new`].
    pub initial_exposure_us: f64,
    pub site_mode: Option<ArduSubMode>,
}

impl LoopStart {
    /// The site's own start: its exposure method and initial exposure, its flight mode.
    pub fn of_site(site: &LoadedSite) -> Self {
        let s = &site.site;
        Self {
            method: s.exposure.method,
            initial_exposure_us: site.limits().clamp(s.camera.initial_exposure_us),
            site_mode: Some(s.link.mode.ardusub()),
        }
    }
}

/// What a loop is made of, for tests and logs: two runners given the same site and
/// start build the same loop.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopDescription {
    pub site: String,
    pub start: LoopStart,
    pub frame_width: u32,
    pub frame_height: u32,
    pub observers: Vec<&'static str>,
}

/// The loop: vision, exposure, station keeper, failsafe supervisor, a link, and the
/// observers that see every frame.
pub struct Pipeline<L: CommandLink = VehicleLink> {
    tracker: MarkerTracker,
    exposure: Box<dyn ExposureController>,
    keeper: StationKeeper,
    link: L,
    supervisor: Supervisor,
    frame: Frame,
    /// Failsafe transitions of the last frame (reused buffer).
    events: Vec<FailsafeEvent>,
    /// The markers the last frame's pose used (ids), and the corners of every marker
    /// of the map in view, decoded or placed by the pose (sized for the map).
    in_view_ids: Vec<u32>,
    in_view: Vec<Corners>,
    /// Loop time the marker was last seen.
    marker_seen_s: Option<f64>,
    /// Set by a signal handler: the next frame sends neutral and the loop ends.
    shutdown: bool,
    /// Loop time of the last frame stepped.
    last_frame_s: Option<f64>,
    /// The vehicle's mode changes seen so far: a change resets the station keeper.
    mode_changes_seen: u64,
    /// Marker-loss action and the way back to the site's mode.
    failsafe: FailsafeActions,
    observers: Observers,
    site_name: String,
    start: LoopStart,
    /// `command = "setpoint"`: GUIDED targets and vision poses instead of efforts.
    setpoint: bool,
    /// Camera mount, for the vision pose of setpoint mode.
    t_vehicle_cam: Isometry3<f64>,
}

impl<L: CommandLink> Pipeline<L> {
    /// The loop of `site`, started as `start`, commanding through `link`, with
    /// `observers` attached (one of them may tap the link's raw MAVLink).
    pub fn new(
        site: &LoadedSite,
        start: LoopStart,
        mut link: L,
        observers: Observers,
    ) -> Result<Self, CoreError> {
        let s = &site.site;
        let calib = &site.calibration;
        let limits = site.limits();
        let start = LoopStart {
            initial_exposure_us: limits.clamp(start.initial_exposure_us),
            ..start
        };
        let tracker = MarkerTracker::new(&s.marker, &s.vision, calib.clone())?;
        let exposure_cfg = markhold_exposure::ExposureConfig {
            response: s.camera.response.clone(),
            ..s.exposure.clone()
        };
        let mut exposure = build_controller(
            &exposure_cfg,
            start.method,
            limits,
            start.initial_exposure_us,
        )?;
        let map_len = tracker.map_len();
        exposure.reserve_markers(map_len);
        let mut keeper = StationKeeper::new(&s.station, &s.controller, site.t_vehicle_cam())?;
        keeper.set_view(crate::feasibility::view_limits(calib, s.marker.size_m));
        if let Some(tap) = observers.mavlink_tap() {
            link.set_raw_tap(Some(tap));
        }
        Ok(Self {
            tracker,
            exposure,
            keeper,
            supervisor: Supervisor::new(&s.controller, &s.link),
            link,
            frame: Frame::new(calib.width, calib.height),
            events: Vec::with_capacity(8),
            in_view_ids: Vec::with_capacity(map_len),
            in_view: Vec::with_capacity(map_len),
            marker_seen_s: None,
            shutdown: false,
            last_frame_s: None,
            mode_changes_seen: 0,
            failsafe: FailsafeActions::new(start.site_mode),
            observers,
            site_name: s.site.name.clone(),
            start,
            setpoint: s.link.command == CommandKind::Setpoint,
            t_vehicle_cam: site.t_vehicle_cam(),
        })
    }

    /// What this loop is made of.
    pub fn describe(&self) -> LoopDescription {
        LoopDescription {
            site: self.site_name.clone(),
            start: self.start,
            frame_width: self.frame.width,
            frame_height: self.frame.height,
            observers: self.observers.names(),
        }
    }

    pub fn start(&self) -> LoopStart {
        self.start
    }

    pub fn link(&self) -> &L {
        &self.link
    }

    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// The last frame stepped (its pixels and metadata).
    pub fn frame(&self) -> &Frame {
        &self.frame
    }

    /// The exposure controller (its diagnostics, e.g. a gated law that never moved).
    pub fn exposure_controller(&self) -> &dyn ExposureController {
        self.exposure.as_ref()
    }

    /// The station keeper's state after the last frame.
    pub fn keeper_status(&self) -> markhold_autopilot::KeeperStatus {
        self.keeper.status()
    }

    /// The station keeper's integral terms after the last frame (surge, sway, heave,
    /// roll, pitch, yaw; effort).
    pub fn keeper_integrals(&self) -> [f64; 6] {
        self.keeper.integrals()
    }

    /// Ids of the markers the last frame's pose used, in map order.
    pub fn markers_in_view(&self) -> &[u32] {
        &self.in_view_ids
    }

    /// Supervisor transitions of the last frame or tick.
    pub fn events(&self) -> &[FailsafeEvent] {
        &self.events
    }

    pub fn failsafe(&self) -> &FailsafeActions {
        &self.failsafe
    }

    /// From the next frame on, send neutral and end (a signal, or a recorded shutdown).
    pub fn set_shutdown(&mut self, shutdown: bool) {
        self.shutdown = shutdown;
    }

    /// Finish every observer (recording closed, trace flushed): the first error.
    pub fn finish_observers(&mut self) -> Result<(), CoreError> {
        self.observers.finish()
    }

    /// Send what the supervisor allows. While the surface fallback climbs in ALT_HOLD,
    /// its neutral becomes the climb (sent as a command, and recorded as one). In setpoint
    /// mode a command is the GUIDED target with this frame's vision pose (`vision`).
    fn send(
        &mut self,
        directive: Directive,
        effort: Effort,
        vision: Option<&VisionPose>,
        now_s: f64,
    ) -> Result<(Directive, Effort), CoreError> {
        Ok(match directive {
            Directive::Command if self.setpoint => {
                let goal = self.keeper.t_marker_vehicle_goal();
                self.link.send_setpoint(vision, &goal, now_s)?;
                (directive, effort)
            }
            Directive::Neutral if self.failsafe.climbing() => {
                let climb = Effort {
                    heave: SURFACE_CLIMB_EFFORT,
                    ..Effort::NEUTRAL
                };
                self.link.send_effort(&climb, now_s)?;
                (Directive::Command, climb)
            }
            Directive::Command => {
                self.link.send_effort(&effort, now_s)?;
                if let Some(down) = self.keeper.depth_target_m() {
                    self.link.send_depth_target(down, now_s)?;
                }
                (directive, effort)
            }
            Directive::Neutral | Directive::Shutdown { .. } => {
                self.link.send_neutral(now_s)?;
                (directive, effort)
            }
            // No vehicle to talk to: pilot input to a vehicle we cannot hear is not sent.
            Directive::Silent => (directive, effort),
        })
    }

    /// No frame came (the camera stalled): drive the link and the supervisor on loop time
    /// `now_s` (the last frame's stamp plus the time waited) so the vision-stall failsafe
    /// can act, and send what it allows. Returns the directive; the frame-dependent parts
    /// (keeper, exposure) do not run.
    pub fn tick_without_frame(&mut self, now_s: f64) -> Result<Directive, CoreError> {
        self.link.tick(now_s)?;
        self.events.clear();
        let directive = self.supervisor.update(
            &SupervisorInput {
                now_s,
                vehicle_heartbeat_s: self.link.vehicle_heartbeat_s(),
                last_frame_s: self.last_frame_s,
                marker_seen_s: self.marker_seen_s,
                shutdown: self.shutdown,
            },
            &mut self.events,
        );
        self.failsafe
            .update(&mut self.link, &mut self.keeper, &self.events, now_s)?;
        // Without a frame there is no fresh effort: only neutral (or nothing) goes out.
        match directive {
            Directive::Silent => {}
            Directive::Command => {
                // Within the stall time: the link's keep-alive repeats neutral if needed.
            }
            Directive::Neutral | Directive::Shutdown { .. } => {
                if self.failsafe.climbing() {
                    self.send(Directive::Neutral, Effort::NEUTRAL, None, now_s)?;
                } else {
                    self.link.send_neutral(now_s)?;
                }
            }
        }
        Ok(directive)
    }

    /// Run one frame through the loop.
    pub fn step(&mut self, camera: &mut dyn Camera) -> Result<FrameRecord, CoreError> {
        camera.grab(&mut self.frame)?;
        let t0 = Instant::now();
        let stamp = self.frame.meta.stamp_s;
        let (obs, full_search_after_send): (Option<MarkerObservation>, bool) =
            match self.tracker.process_tracked(&self.frame)? {
                Tracked::Done(obs) => (obs, false),
                // Deferred before the first fix too: the command (neutral until then) keeps
                // its latency while the marker is being acquired, which can take seconds
                // under caustics; the first fix then serves from the next frame on.
                Tracked::NeedsFullSearch if self.tracker.detector_config().defer_full_search => {
                    (None, true)
                }
                Tracked::NeedsFullSearch => (self.tracker.process_full(&self.frame)?, false),
            };
        // The keeper's measurement noise is the edge fit's (its filter and gate were
        // tuned on it); the vehicle's EKF gets the full covariance below.
        let meas = obs.as_ref().map(|o| PoseMeasurement {
            stamp_s: stamp,
            t_cam_marker: o.t_cam_marker,
            cov_cam: o.cov_cam_fit,
        });
        self.link.tick(stamp)?;
        // A mode change (by the pilot, a failsafe or us) invalidates the integrators.
        if let Some(changes) = self.link.vehicle_state().map(|v| v.mode_changes) {
            if changes != self.mode_changes_seen {
                self.mode_changes_seen = changes;
                self.keeper.reset();
            }
        }
        // Heading, position and depth for the way back when the marker slips out of view
        // (telemetry no older than a second).
        if let Some(v) = self.link.vehicle_state() {
            // What the vehicle's mode holds by itself, the keeper leaves alone.
            self.keeper.set_autopilot_mode(v.mode);
            let fresh = |t: f64| (0.0..=1.0).contains(&(stamp - t));
            if let Some(a) = v.attitude.filter(|a| fresh(a.stamp_s)) {
                self.keeper.set_heading(a.yaw);
            }
            let lp = v.local_position.filter(|p| fresh(p.stamp_s));
            self.keeper
                .set_position_ne(lp.map(|p| [p.position[0], p.position[1]]));
            self.keeper.set_depth(lp.map(|p| p.position[2]));
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
        self.failsafe
            .update(&mut self.link, &mut self.keeper, &self.events, stamp)?;
        // Setpoint mode: the vehicle's pose for the EKF, from the same measurement.
        let vision = obs.as_ref().filter(|_| self.setpoint).map(|o| {
            VisionPose::from_camera(stamp, &o.t_cam_marker, &o.cov_cam, &self.t_vehicle_cam)
        });
        let (directive, effort) = self.send(directive, effort, vision.as_ref(), stamp)?;
        let latency_s = t0.elapsed().as_secs_f64();
        self.last_frame_s = Some(stamp);
        // The full-frame search after the command: what it finds re-seeds tracking, the
        // exposure RoI and the record; the keeper gets the marker from the next frame.
        let obs = if full_search_after_send {
            let found = self.tracker.process_full(&self.frame)?;
            if found.is_some() {
                self.marker_seen_s = Some(stamp);
            }
            found
        } else {
            obs
        };

        // Exposure after the command: it does not gate the vehicle. It meters every
        // marker of the map in view, those the detector missed where the pose places
        // them (or the one the pose names, as the site says).
        let corners = obs.as_ref().map(|o| o.corners);
        self.in_view_ids.clear();
        self.in_view.clear();
        if obs.is_some() {
            let (ids, in_view) = (&mut self.in_view_ids, &mut self.in_view);
            self.tracker.for_each_marker_in_view(|id, c, decoded| {
                if decoded {
                    ids.push(id);
                }
                in_view.push(*c);
            });
        }
        let step = self
            .exposure
            .update_in_view(&self.frame, corners.as_ref(), &self.in_view);
        camera.set_exposure_us(step.exposure_us)?;
        let rec = FrameRecord {
            seq: self.frame.meta.seq,
            stamp_s: stamp,
            exposure_used_us: self.frame.meta.exposure_us,
            exposure: step,
            detected: obs.is_some(),
            corners,
            t_cam_marker: obs.as_ref().map(|o| o.t_cam_marker),
            cov_cam: obs.as_ref().map(|o| o.cov_cam),
            reproj_rms_px: obs.as_ref().map_or(f64::NAN, |o| o.reproj_rms_px),
            markers_used: obs.as_ref().map_or(0, |o| o.markers_used),
            effort,
            directive,
            latency_s,
        };
        self.observe(&rec);
        Ok(rec)
    }

    /// The frame `rec` (the last one stepped) as observers see it.
    pub fn view<'a>(&'a self, rec: &'a FrameRecord) -> FrameView<'a> {
        FrameView {
            rec,
            frame: &self.frame,
            heartbeat_s: self.link.vehicle_heartbeat_s(),
            vehicle: self.link.vehicle_state(),
            events: &self.events,
            markers_in_view: &self.in_view_ids,
            transitions: &self.failsafe.transitions,
            shutdown: self.shutdown,
        }
    }

    fn observe(&mut self, rec: &FrameRecord) {
        if self.observers.is_empty() {
            return;
        }
        // The list is taken out for the call so the view can borrow the rest.
        let mut observers = std::mem::take(&mut self.observers);
        observers.frame(&self.view(rec));
        self.observers = observers;
    }
}
