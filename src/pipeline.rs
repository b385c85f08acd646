//! The per-frame loop, the same for live, HIL and replay: only the camera, the link and
//! where time comes from differ. Data flows one way per frame:
//! camera -> vision -> station keeper -> link, then exposure -> camera.

use std::time::Instant;

use markhold_autopilot::{
    ArduSubMode, CommandStatus, Directive, Effort, FailsafeEvent, MarkerLostAction,
    PoseMeasurement, StationKeeper, Supervisor, SupervisorInput, VehicleLink, VehicleState,
};
use markhold_exposure::{Camera, Corners, ExposureController, ExposureStep, Frame};
use markhold_vision::{MarkerObservation, MarkerTracker, Tracked};
use nalgebra::{Isometry3, Matrix6};
use serde::Serialize;

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
    /// Ask the vehicle for a flight mode (acknowledged and retried by a real link; a sink
    /// has no vehicle and ignores it).
    fn request_mode(&mut self, _mode: ArduSubMode, _now_s: f64) -> anyhow::Result<()> {
        Ok(())
    }
    /// Ask the vehicle to arm or disarm (acknowledged and retried by a real link).
    fn request_arm(&mut self, _arm: bool, _now_s: f64) -> anyhow::Result<()> {
        Ok(())
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
    fn request_mode(&mut self, mode: ArduSubMode, now_s: f64) -> anyhow::Result<()> {
        Ok(VehicleLink::request_mode(self, mode, now_s)?)
    }
    fn request_arm(&mut self, arm: bool, now_s: f64) -> anyhow::Result<()> {
        Ok(VehicleLink::request_arm(self, arm, now_s)?)
    }
}

/// Heave effort (+ down) of the climb when `surface` falls back to ALT_HOLD: half stick
/// up, i.e. half of ArduSub's pilot climb rate (PILOT_SPEED_UP, 0.5 m/s in the HIL
/// endpoint), so about 0.25 m/s.
pub const SURFACE_CLIMB_EFFORT: f64 = -0.5;

/// A mode transition the loop made on its own (marker-loss action and the way back),
/// logged and kept for the fault reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "transition", rename_all = "snake_case")]
pub enum ModeTransition {
    /// The marker-loss action was requested from the vehicle.
    LossActionRequested {
        at_s: f64,
        action: MarkerLostAction,
        mode: ArduSubMode,
    },
    /// The vehicle refused (or never answered) SURFACE: ALT_HOLD with a climb instead.
    SurfaceFallback { at_s: f64, refused: CommandStatus },
    /// The vehicle reports the action's mode in its heartbeat.
    LossActionInMode { at_s: f64, mode: ArduSubMode },
    /// Marker back: the site's mode requested again, the keeper reset.
    SiteModeRequested { at_s: f64, mode: ArduSubMode },
    /// The vehicle reports the site's mode again.
    SiteModeRestored { at_s: f64, mode: ArduSubMode },
    /// A mode request of ours ended without the mode (rejected or no answer).
    ModeRequestFailed {
        at_s: f64,
        mode: ArduSubMode,
        status: CommandStatus,
    },
}

/// The marker-loss action in progress, if any.
#[derive(Debug, Clone, Copy, PartialEq)]
struct LossAction {
    action: MarkerLostAction,
    /// The mode asked for now (SURFACE, or ALT_HOLD).
    mode: ArduSubMode,
    /// ALT_HOLD with a climb (surface fallback).
    climb: bool,
    in_mode: bool,
}

/// What the loop does about failsafes beyond the supervisor's directive: the marker-loss
/// action (a mode change) and the way back to the site's mode.
#[derive(Debug, Clone, Default)]
pub struct FailsafeActions {
    /// The site's mode: restored when the marker comes back. `None` (replay): no mode is
    /// ever requested.
    pub site_mode: Option<ArduSubMode>,
    loss: Option<LossAction>,
    /// Site mode requested, not yet seen in the heartbeat.
    restoring: Option<ArduSubMode>,
    /// Transitions of the last frame (reused buffer).
    pub transitions: Vec<ModeTransition>,
}

impl FailsafeActions {
    /// For a loop that runs in `site_mode` (requested back after a marker-loss action).
    pub fn new(site_mode: Option<ArduSubMode>) -> Self {
        Self {
            site_mode,
            loss: None,
            restoring: None,
            transitions: Vec::with_capacity(4),
        }
    }

    /// True while a marker-loss action is in force.
    pub fn loss_action_active(&self) -> bool {
        self.loss.is_some()
    }

    /// The mode the loss action has asked for (SURFACE or ALT_HOLD), if one is in force.
    pub fn loss_action_mode(&self) -> Option<ArduSubMode> {
        self.loss.map(|l| l.mode)
    }

    /// True while the loss action climbs in ALT_HOLD (SURFACE refused).
    pub fn climbing(&self) -> bool {
        self.loss.is_some_and(|l| l.climb)
    }

    fn log(&mut self, t: ModeTransition) {
        match t {
            ModeTransition::SurfaceFallback { .. } | ModeTransition::ModeRequestFailed { .. } => {
                tracing::warn!(transition = ?t, "failsafe mode")
            }
            _ => tracing::info!(transition = ?t, "failsafe mode"),
        }
        self.transitions.push(t);
    }

    /// Act on this frame's supervisor events and on the vehicle's answers.
    fn update<L: CommandLink>(
        &mut self,
        link: &mut L,
        keeper: &mut StationKeeper,
        events: &[FailsafeEvent],
        now_s: f64,
    ) -> anyhow::Result<()> {
        self.transitions.clear();
        let Some(site_mode) = self.site_mode else {
            return Ok(());
        };
        for e in events {
            match *e {
                FailsafeEvent::MarkerLostActionDue { action, .. } => {
                    let mode = match action {
                        MarkerLostAction::None => continue,
                        MarkerLostAction::AltHold => ArduSubMode::AltHold,
                        MarkerLostAction::Surface => ArduSubMode::Surface,
                    };
                    link.request_mode(mode, now_s)?;
                    self.restoring = None;
                    self.loss = Some(LossAction {
                        action,
                        mode,
                        climb: false,
                        in_mode: false,
                    });
                    self.log(ModeTransition::LossActionRequested {
                        at_s: now_s,
                        action,
                        mode,
                    });
                }
                FailsafeEvent::MarkerReacquired { .. } if self.loss.is_some() => {
                    self.loss = None;
                    link.request_mode(site_mode, now_s)?;
                    self.restoring = Some(site_mode);
                    keeper.reset();
                    self.log(ModeTransition::SiteModeRequested {
                        at_s: now_s,
                        mode: site_mode,
                    });
                }
                _ => {}
            }
        }
        let Some(v) = link.vehicle_state() else {
            return Ok(());
        };
        let (mode_now, status) = (v.mode, v.mode_command);
        let failed = matches!(
            status,
            CommandStatus::Rejected { .. } | CommandStatus::TimedOut
        );
        if let Some(mut l) = self.loss {
            if !l.in_mode && mode_now == Some(l.mode) {
                l.in_mode = true;
                self.log(ModeTransition::LossActionInMode {
                    at_s: now_s,
                    mode: l.mode,
                });
            } else if !l.in_mode && failed {
                if l.mode == ArduSubMode::Surface {
                    // ArduSub's SURFACE needs a depth sensor; a vehicle without the mode
                    // (or one that does not answer) still holds depth and climbs in
                    // ALT_HOLD with the throttle stick up.
                    l.mode = ArduSubMode::AltHold;
                    l.climb = true;
                    link.request_mode(ArduSubMode::AltHold, now_s)?;
                    self.log(ModeTransition::SurfaceFallback {
                        at_s: now_s,
                        refused: status,
                    });
                } else {
                    self.log(ModeTransition::ModeRequestFailed {
                        at_s: now_s,
                        mode: l.mode,
                        status,
                    });
                    // Neutral input goes on; the supervisor keeps the loop neutral.
                    l.in_mode = true;
                }
            }
            self.loss = Some(l);
        }
        if let Some(m) = self.restoring {
            if mode_now == Some(m) {
                self.restoring = None;
                self.log(ModeTransition::SiteModeRestored {
                    at_s: now_s,
                    mode: m,
                });
            } else if failed {
                self.restoring = None;
                self.log(ModeTransition::ModeRequestFailed {
                    at_s: now_s,
                    mode: m,
                    status,
                });
            }
        }
        Ok(())
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
    /// Loop time of the last frame stepped.
    pub last_frame_s: Option<f64>,
    /// The vehicle's mode changes seen so far: a change resets the station keeper.
    pub mode_changes_seen: u64,
    /// Marker-loss action and the way back to the site's mode.
    pub failsafe: FailsafeActions,
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
            last_frame_s: None,
            mode_changes_seen: 0,
            failsafe: FailsafeActions::default(),
        }
    }

    /// Send what the supervisor allows. While the surface fallback climbs in ALT_HOLD,
    /// its neutral becomes the climb (sent as a command, and recorded as one).
    fn send(
        &mut self,
        directive: Directive,
        effort: Effort,
        now_s: f64,
    ) -> anyhow::Result<(Directive, Effort)> {
        Ok(match directive {
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
    pub fn tick_without_frame(&mut self, now_s: f64) -> anyhow::Result<Directive> {
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
                    self.send(Directive::Neutral, Effort::NEUTRAL, now_s)?;
                } else {
                    self.link.send_neutral(now_s)?;
                }
            }
        }
        Ok(directive)
    }

    /// Run one frame through the loop.
    pub fn step(&mut self, camera: &mut dyn Camera) -> anyhow::Result<FrameRecord> {
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
        self.failsafe
            .update(&mut self.link, &mut self.keeper, &self.events, stamp)?;
        let (directive, effort) = self.send(directive, effort, stamp)?;
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
