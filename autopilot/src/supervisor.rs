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
    /// Loop time the vehicle was last heard (`VehicleState::last_heartbeat_s`: any message
    /// from its autopilot, not only heartbeats).
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
    /// (`vehicle_timeout_s`: the vehicle unheard this long is lost; disarm on exit).
    pub fn new(ctl: &ControllerConfig, link: &LinkConfig) -> Self {
        Self {
            heartbeat_timeout_s: link.vehicle_timeout_s,
            vision_stall_s: ctl.vision_stall_s,
            hold_s: ctl.marker_lost_hold_s,
            action_after_s: ctl.marker_lost_action_after_s,
            action: ctl.marker_lost_action,
            disarm_on_exit: link.disarms_on_exit(),
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

#[cfg(test)]
mod tests {
    use super::*;

    fn sup(action: MarkerLostAction) -> Supervisor {
        let ctl = ControllerConfig {
            marker_lost_hold_s: 0.5,
            marker_lost_action_after_s: 3.0,
            marker_lost_action: action,
            vision_stall_s: 0.5,
            ..Default::default()
        };
        let link = LinkConfig {
            vehicle_timeout_s: 2.0,
            disarm_on_exit: true,
            ..Default::default()
        };
        Supervisor::new(&ctl, &link)
    }

    fn input(
        now: f64,
        hb: Option<f64>,
        frame: Option<f64>,
        marker: Option<f64>,
    ) -> SupervisorInput {
        SupervisorInput {
            now_s: now,
            vehicle_heartbeat_s: hb,
            last_frame_s: frame,
            marker_seen_s: marker,
            shutdown: false,
        }
    }

    #[test]
    fn silent_until_vehicle_then_command() {
        let mut s = sup(MarkerLostAction::None);
        let mut ev = Vec::new();
        assert_eq!(
            s.update(&input(0.0, None, Some(0.0), Some(0.0)), &mut ev),
            Directive::Silent
        );
        assert!(ev.is_empty());
        assert_eq!(
            s.update(&input(0.1, Some(0.1), Some(0.1), Some(0.1)), &mut ev),
            Directive::Command
        );
        assert!(matches!(ev[..], [FailsafeEvent::VehicleConnected { .. }]));
    }

    #[test]
    fn vision_stall_goes_neutral_and_recovers() {
        let mut s = sup(MarkerLostAction::None);
        let mut ev = Vec::new();
        s.update(&input(0.0, Some(0.0), Some(0.0), Some(0.0)), &mut ev);
        ev.clear();
        let d = s.update(&input(0.6, Some(0.6), Some(0.0), Some(0.0)), &mut ev);
        assert_eq!(d, Directive::Neutral);
        assert!(ev
            .iter()
            .any(|e| matches!(e, FailsafeEvent::VisionStalled { .. })));
        ev.clear();
        let d = s.update(&input(0.7, Some(0.7), Some(0.7), Some(0.7)), &mut ev);
        assert_eq!(d, Directive::Command);
        assert!(ev
            .iter()
            .any(|e| matches!(e, FailsafeEvent::VisionRestored { .. })));
    }

    #[test]
    fn marker_loss_events_and_action_once() {
        let mut s = sup(MarkerLostAction::AltHold);
        let mut ev = Vec::new();
        s.update(&input(0.0, Some(0.0), Some(0.0), Some(0.0)), &mut ev);
        ev.clear();
        // Within the hold: nothing.
        assert_eq!(
            s.update(&input(0.4, Some(0.4), Some(0.4), Some(0.0)), &mut ev),
            Directive::Command
        );
        assert!(ev.is_empty());
        // Past the hold: MarkerLost; the keeper itself goes neutral, the loop still commands.
        assert_eq!(
            s.update(&input(1.0, Some(1.0), Some(1.0), Some(0.0)), &mut ev),
            Directive::Command
        );
        assert!(
            matches!(ev[..], [FailsafeEvent::MarkerLost { last_seen_s, .. }] if last_seen_s == 0.0)
        );
        ev.clear();
        // Past the action time: action due once, then neutral.
        assert_eq!(
            s.update(&input(3.1, Some(3.1), Some(3.1), Some(0.0)), &mut ev),
            Directive::Neutral
        );
        assert!(matches!(
            ev[..],
            [FailsafeEvent::MarkerLostActionDue {
                action: MarkerLostAction::AltHold,
                ..
            }]
        ));
        ev.clear();
        s.update(&input(4.0, Some(4.0), Some(4.0), Some(0.0)), &mut ev);
        assert!(ev.is_empty());
        // Re-acquired.
        assert_eq!(
            s.update(&input(5.0, Some(5.0), Some(5.0), Some(5.0)), &mut ev),
            Directive::Command
        );
        assert!(
            matches!(ev[..], [FailsafeEvent::MarkerReacquired { lost_for_s, .. }] if (lost_for_s - 5.0).abs() < 1e-12)
        );
    }

    #[test]
    fn shutdown_wins_and_reports_disarm() {
        let mut s = sup(MarkerLostAction::None);
        let mut ev = Vec::new();
        let mut i = input(1.0, Some(1.0), Some(1.0), Some(1.0));
        i.shutdown = true;
        assert_eq!(s.update(&i, &mut ev), Directive::Shutdown { disarm: true });
        assert_eq!(s.update(&i, &mut ev), Directive::Shutdown { disarm: true });
        assert_eq!(ev.len(), 1, "{ev:?}");
    }

    mod props {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            /// Random heartbeat arrival gaps: the directive is Silent exactly when the last
            /// heartbeat is older than the timeout, and Lost/Restored events alternate.
            #[test]
            fn heartbeat_loss_transitions(gaps in prop::collection::vec(0.01..4.0f64, 1..60)) {
                let mut s = sup(MarkerLostAction::None);
                let mut ev = Vec::new();
                let mut t_hb = 0.0;
                let mut now = 0.0;
                for g in gaps {
                    // Tick every 0.1 s until the next heartbeat arrives.
                    let next = t_hb + g;
                    while now + 0.1 < next {
                        now += 0.1;
                        let d = s.update(&input(now, Some(t_hb), Some(now), Some(now)), &mut ev);
                        let lost = now - t_hb > 2.0;
                        prop_assert_eq!(d == Directive::Silent, lost);
                    }
                    now = next;
                    t_hb = next;
                    let d = s.update(&input(now, Some(t_hb), Some(now), Some(now)), &mut ev);
                    prop_assert_eq!(d, Directive::Command);
                }
                let hb: Vec<_> = ev
                    .iter()
                    .filter(|e| matches!(e, FailsafeEvent::VehicleHeartbeatLost { .. } | FailsafeEvent::VehicleHeartbeatRestored { .. }))
                    .collect();
                for (i, e) in hb.iter().enumerate() {
                    let lost = matches!(e, FailsafeEvent::VehicleHeartbeatLost { .. });
                    prop_assert_eq!(lost, i % 2 == 0, "events out of order: {:?}", hb);
                }
            }
        }
    }
}
