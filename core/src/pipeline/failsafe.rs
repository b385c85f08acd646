//! What the loop does about failsafes beyond the supervisor's directive: the
//! marker-loss action (a mode change), the way back to the site's mode, and the climb
//! that stands in for SURFACE when the vehicle refuses it.

use crate::CoreError;
use markhold_autopilot::{
    ArduSubMode, CommandStatus, FailsafeEvent, MarkerLostAction, StationKeeper,
};
use serde::Serialize;

use super::CommandLink;

/// Heave effort (+ down) of the climb when `surface` falls back to ALT_HOLD: half stick
/// up, which ArduSub 4.5's ALT_HOLD reads as a climb rate, a fraction of PILOT_SPEED_UP
/// (500 cm/s) past THR_DZ x the joystick gain (`Sub::get_pilot_desired_climb_rate`).
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
    pub(super) fn update<L: CommandLink>(
        &mut self,
        link: &mut L,
        keeper: &mut StationKeeper,
        events: &[FailsafeEvent],
        now_s: f64,
    ) -> Result<(), CoreError> {
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
