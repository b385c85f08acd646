//! Failsafe supervisor: a pure state machine on loop time. It is fed the vehicle's heartbeat
//! time, the camera's and the marker's last times and a shutdown flag, and says what the
//! loop may send. Every transition is logged and returned as an event for the recording.

use serde::Serialize;

use crate::config::{ControllerConfig, LinkConfig, MarkerLostAction};

/// What the loop should send this frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Directive {
    /// Send the station keeper's effort (it holds or goes neutral on a short marker loss).
    Command,
    /// Send neutral pilot input (vision stalled, marker lost for long, action taken).
    Neutral,
    /// Send no pilot input: the vehicle is not there (no heartbeat yet, or lost).
    Silent,
    /// Shutting down: send neutral, then disarm if `disarm` (once), then stop.
    Shutdown {
        /// Disarm after the neutral input.
        disarm: bool,
    },
}

/// A transition, with the loop time it happened.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum FailsafeEvent {
    /// First vehicle heartbeat.
    VehicleConnected {
        /// Loop time.
        at_s: f64,
    },
    /// Vehicle heartbeat older than the timeout: stop commanding.
    VehicleHeartbeatLost {
        /// Loop time.
        at_s: f64,
        /// Age of the last heartbeat.
        age_s: f64,
    },
    /// Vehicle heartbeat back.
    VehicleHeartbeatRestored {
        /// Loop time.
        at_s: f64,
        /// How long it was missing.
        lost_for_s: f64,
    },
    /// No camera frame for `vision_stall_s`: neutral.
    VisionStalled {
        /// Loop time.
        at_s: f64,
        /// Age of the last frame.
        age_s: f64,
    },
    /// Frames arrive again.
    VisionRestored {
        /// Loop time.
        at_s: f64,
    },
    /// The marker has been missing longer than the hold.
    MarkerLost {
        /// Loop time.
        at_s: f64,
        /// Loop time it was last seen.
        last_seen_s: f64,
    },
    /// The marker is seen again after a loss.
    MarkerReacquired {
        /// Loop time.
        at_s: f64,
        /// How long it was missing.
        lost_for_s: f64,
    },
    /// The configured action on a long marker loss is due (switch mode to it).
    MarkerLostActionDue {
        /// Loop time.
        at_s: f64,
        /// The action.
        action: MarkerLostAction,
    },
    /// Ctrl-C / SIGTERM.
    ShutdownRequested {
        /// Loop time.
        at_s: f64,
        /// A disarm follows the neutral input.
        disarm: bool,
    },
}

/// The supervisor's inputs for one frame (loop time).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct SupervisorInput {
    /// Loop time now.
    pub now_s: f64,
    /// Loop time of the last vehicle heartbeat (`VehicleState::last_heartbeat_s`).
    pub vehicle_heartbeat_s: Option<f64>,
    /// Loop time of the last camera frame.
    pub last_frame_s: Option<f64>,
    /// Loop time the marker was last seen.
    pub marker_seen_s: Option<f64>,
    /// Ctrl-C / SIGTERM received.
    pub shutdown: bool,
}

/// The failsafe state machine.
#[derive(Clone, Debug)]
pub struct Supervisor {
    heartbeat_timeout_s: f64,
    vision_stall_s: f64,
    hold_s: f64,
    action_after_s: f64,
    action: MarkerLostAction,
    disarm_on_exit: bool,
    vehicle_seen: bool,
    heartbeat_lost_at: Option<f64>,
    vision_stalled: bool,
    marker_lost: bool,
    marker_lost_last_seen_s: f64,
    action_taken: bool,
    shutting_down: bool,
}

impl Supervisor {
    /// Thresholds from `[controller]` (vision stall, marker hold and action) and `[link]`
    /// (vehicle heartbeat timeout, disarm on exit).
    pub fn new(ctl: &ControllerConfig, link: &LinkConfig) -> Self {
        Self {
            heartbeat_timeout_s: link.vehicle_heartbeat_timeout_s,
            vision_stall_s: ctl.vision_stall_s,
            hold_s: ctl.marker_lost_hold_s,
            action_after_s: ctl.marker_lost_action_after_s,
            action: ctl.marker_lost_action,
            disarm_on_exit: link.disarm_on_exit,
            vehicle_seen: false,
            heartbeat_lost_at: None,
            vision_stalled: false,
            marker_lost: false,
            marker_lost_last_seen_s: 0.0,
            action_taken: false,
            shutting_down: false,
        }
    }

    fn emit(events: &mut Vec<FailsafeEvent>, e: FailsafeEvent) {
        match e {
            FailsafeEvent::VehicleConnected { .. }
            | FailsafeEvent::VehicleHeartbeatRestored { .. }
            | FailsafeEvent::VisionRestored { .. }
            | FailsafeEvent::MarkerReacquired { .. } => tracing::info!(event = ?e, "failsafe"),
            _ => tracing::warn!(event = ?e, "failsafe"),
        }
        events.push(e);
    }

    /// One step. Transitions are appended to `events` (caller-owned, reuse it).
    pub fn update(&mut self, inp: &SupervisorInput, events: &mut Vec<FailsafeEvent>) -> Directive {
        let now = inp.now_s;
        if inp.shutdown {
            if !self.shutting_down {
                self.shutting_down = true;
                Self::emit(
                    events,
                    FailsafeEvent::ShutdownRequested {
                        at_s: now,
                        disarm: self.disarm_on_exit,
                    },
                );
            }
            return Directive::Shutdown {
                disarm: self.disarm_on_exit,
            };
        }

        // Vehicle heartbeat.
        let hb_ok = match inp.vehicle_heartbeat_s {
            Some(t) => {
                if !self.vehicle_seen {
                    self.vehicle_seen = true;
                    Self::emit(events, FailsafeEvent::VehicleConnected { at_s: now });
                }
                let age = now - t;
                let ok = age <= self.heartbeat_timeout_s;
                match (self.heartbeat_lost_at, ok) {
                    (None, false) => {
                        self.heartbeat_lost_at = Some(now);
                        Self::emit(
                            events,
                            FailsafeEvent::VehicleHeartbeatLost {
                                at_s: now,
                                age_s: age,
                            },
                        );
                    }
                    (Some(at), true) => {
                        self.heartbeat_lost_at = None;
                        Self::emit(
                            events,
                            FailsafeEvent::VehicleHeartbeatRestored {
                                at_s: now,
                                lost_for_s: now - at,
                            },
                        );
                    }
                    _ => {}
                }
                ok
            }
            None => false,
        };

        // Camera frames.
        let vision_ok = match inp.last_frame_s {
            Some(t) => now - t <= self.vision_stall_s,
            None => false,
        };
        match (self.vision_stalled, vision_ok) {
            (false, false) if inp.last_frame_s.is_some() || self.vehicle_seen => {
                self.vision_stalled = true;
                Self::emit(
                    events,
                    FailsafeEvent::VisionStalled {
                        at_s: now,
                        age_s: inp.last_frame_s.map_or(f64::INFINITY, |t| now - t),
                    },
                );
            }
            (true, true) => {
                self.vision_stalled = false;
                Self::emit(events, FailsafeEvent::VisionRestored { at_s: now });
            }
            _ => {}
        }

        // Marker.
        let marker_age = inp.marker_seen_s.map(|t| now - t);
        match marker_age {
            Some(a) if a <= self.hold_s && self.marker_lost => {
                self.marker_lost = false;
                self.action_taken = false;
                Self::emit(
                    events,
                    FailsafeEvent::MarkerReacquired {
                        at_s: now,
                        lost_for_s: (now - a) - self.marker_lost_last_seen_s,
                    },
                );
            }
            Some(a) if a > self.hold_s => {
                if !self.marker_lost {
                    self.marker_lost = true;
                    self.marker_lost_last_seen_s = now - a;
                    Self::emit(
                        events,
                        FailsafeEvent::MarkerLost {
                            at_s: now,
                            last_seen_s: now - a,
                        },
                    );
                }
                if a >= self.action_after_s
                    && !self.action_taken
                    && self.action != MarkerLostAction::None
                {
                    self.action_taken = true;
                    Self::emit(
                        events,
                        FailsafeEvent::MarkerLostActionDue {
                            at_s: now,
                            action: self.action,
                        },
                    );
                }
            }
            _ => {}
        }

        if !hb_ok {
            Directive::Silent
        } else if !vision_ok || self.action_taken {
            Directive::Neutral
        } else {
            Directive::Command
        }
    }

    /// True once the marker-lost action has fired for the current loss.
    pub fn marker_action_taken(&self) -> bool {
        self.action_taken
    }
}
