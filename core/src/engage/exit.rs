//! The end of a run on a real link, one code path for `run` and `hil --vehicle`
//! (signal, end of frames, error alike): neutral input seen applied by the vehicle, then
//! the site's exit policy, then a close of the link that loses nothing written.
//!
//! - markhold commanding (engaged): "markhold off: stopped", neutral input repeated
//!   until the vehicle shows it applied (RC_CHANNELS, or SERVO_OUTPUT_RAW in MANUAL;
//!   bounded by `exit_confirm_timeout_s`), then `disarm` (acknowledged) or `hand_back`
//!   (neutral kept until the pilot's own input is heard, a mode change or a disarm;
//!   nothing within `hand_back_timeout_s`: disarm and say so), then the override
//!   released.
//! - markhold not commanding (never engaged, or the pilot took over): nothing at all as
//!   SYSID_MYGCS, only "markhold stopped" (as a component of the vehicle).
//! - The pilot's station silent: no SYSID_MYGCS traffic can go out (the link refuses it);
//!   the vehicle's own GCS failsafe acts.
//!
//! Loop time here is the last loop time plus the time waited: no frames come any more.

use crate::CoreError;
use std::time::{Duration, Instant};

use markhold_autopilot::{
    CloseReport, CommandStatus, LinkConfig, NeutralShown, Settled, Severity, VehicleLink,
};
use serde::Serialize;

use super::{Disengage, EngagedLink};

/// The close waits at most this long for the vehicle to read what was sent and close
/// its side, s.
pub const CLOSE_TIMEOUT_S: f64 = 1.0;

/// What markhold leaves behind when it stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ExitPolicy {
    /// `on_exit = "hand_back"`: neutral until the pilot's input is heard.
    HandBack,
    /// `on_exit = "disarm"` (or `disarm_on_exit`): neutral, then disarm.
    Disarm,
}

impl ExitPolicy {
    /// The site's policy.
    pub fn of(cfg: &LinkConfig) -> Self {
        if cfg.disarms_on_exit() {
            Self::Disarm
        } else {
            Self::HandBack
        }
    }
}

/// How a hand-back at the end of a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum HandBack {
    /// markhold was not commanding (or the vehicle was disarmed): nothing to hand back.
    NotCommanding,
    /// The pilot's input (or a mode change / disarm) was heard: released.
    PilotTookOver,
    /// No pilot input within `hand_back_timeout_s`: disarmed.
    Disarmed(CommandStatus),
    /// The pilot's station fell silent: no SYSID_MYGCS traffic; the vehicle's GCS
    /// failsafe acts.
    StationLost,
    /// The vehicle was not heard: nothing could be handed back.
    VehicleLost,
}

/// How a run's exit went.
#[derive(Debug, Clone, Serialize)]
pub struct ExitReport {
    /// The policy that applied.
    pub policy: ExitPolicy,
    /// markhold was commanding when it stopped.
    pub commanding: bool,
    /// The neutral input and how the vehicle showed it (markhold commanding only).
    pub neutral: Option<Settled>,
    /// `hand_back`: how it ended.
    pub hand_back: Option<HandBack>,
    /// `disarm`, or a hand-back that found no pilot: how the disarm ended.
    pub disarm: Option<CommandStatus>,
    /// The link's close.
    pub close: CloseReport,
}

impl EngagedLink {
    /// End the run: see the module. `t0` is the loop time of the last frame. Never fails:
    /// every step is bounded and logged, the close always happens.
    pub fn exit(&mut self, policy: ExitPolicy, t0: f64) -> ExitReport {
        let started = Instant::now();
        let now = move || t0 + started.elapsed().as_secs_f64();
        let commanding = self.engager.commanding();
        let mut report = ExitReport {
            policy,
            commanding,
            neutral: None,
            hand_back: None,
            disarm: None,
            close: CloseReport {
                transport: "none",
                flushed: false,
                peer_closed: false,
            },
        };
        if !self.engager.engaged() {
            // A disengage in progress (its neutral is out): finish it with the release.
            // Otherwise the pilot has the vehicle: nothing as SYSID_MYGCS.
            if let Err(e) = self.release() {
                tracing::warn!(error = %e, "release on exit");
            }
            self.say_text(Severity::Info, "markhold stopped");
            if policy == ExitPolicy::HandBack {
                report.hand_back = Some(HandBack::NotCommanding);
            }
            report.close = self.link.close(CLOSE_TIMEOUT_S);
            return report;
        }
        if let Err(e) = self.disengage(Disengage::Stopped, now()) {
            tracing::warn!(error = %e, "disengage on exit");
        }
        let timeout = self.link.config().exit_confirm_timeout_s;
        let settled = match self.link.settle_neutral(now(), timeout) {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "neutral on exit");
                Settled {
                    shown: NeutralShown::NotShown,
                    waited_s: started.elapsed().as_secs_f64(),
                    neutrals: 0,
                }
            }
        };
        eprintln!(
            "markhold: neutral input at exit: {:?} after {:.2} s ({} sent)",
            settled.shown, settled.waited_s, settled.neutrals
        );
        report.neutral = Some(settled);
        let outcome = match settled.shown {
            NeutralShown::PilotInput => HandBack::PilotTookOver,
            NeutralShown::NotSent if self.link.station_lost() => HandBack::StationLost,
            NeutralShown::NotSent => HandBack::VehicleLost,
            _ => match policy {
                ExitPolicy::Disarm => {
                    let st = disarm_on_exit(&mut self.link, now());
                    report.disarm = Some(st);
                    HandBack::Disarmed(st)
                }
                ExitPolicy::HandBack => self.hand_back(t0, &started, &mut report),
            },
        };
        match outcome {
            HandBack::PilotTookOver => {
                if let Err(e) = self.release() {
                    tracing::warn!(error = %e, "release on exit");
                }
                self.say_text(Severity::Notice, "markhold: pilot has control");
                eprintln!("markhold: handed back: the pilot has control");
            }
            HandBack::StationLost => {
                self.say_text(Severity::Critical, "markhold stopped: pilot station silent");
            }
            HandBack::VehicleLost => {}
            HandBack::NotCommanding | HandBack::Disarmed(_) => {
                if let Err(e) = self.release() {
                    tracing::warn!(error = %e, "release on exit");
                }
            }
        }
        self.link.set_pilot_keepalive(false);
        self.engager.released();
        if policy == ExitPolicy::HandBack {
            report.hand_back = Some(outcome);
        }
        report.close = self.link.close(CLOSE_TIMEOUT_S);
        tracing::info!(?report, "exit");
        report
    }

    /// The exit of a lockstep runner (`sitl-loop`), whose vehicle's clock moves only
    /// when the runner steps it, so [`Self::exit`]'s wall-clock waits would starve it:
    /// the caller sends the neutral and steps the vehicle, then this disengages and
    /// releases the override.
    pub fn stop_lockstep(&mut self, now_s: f64) -> Result<(), CoreError> {
        self.disengage(Disengage::Stopped, now_s)?;
        self.release()
    }

    fn say_text(&mut self, sev: Severity, text: &'static str) {
        if let Err(e) = self.link.send_statustext(sev, text) {
            tracing::warn!(error = %e, "statustext");
        }
    }

    /// `hand_back` after the neutral was applied: if the vehicle is armed, keep its
    /// sticks centred and tell the pilot, until the pilot's own input is heard (or the
    /// pilot changes mode or disarms); nothing within `hand_back_timeout_s`: disarm and
    /// say so, so an armed vehicle is never left with nobody commanding it without a
    /// word. Stops at once when the pilot's station or the vehicle falls silent.
    fn hand_back(&mut self, t0: f64, started: &Instant, report: &mut ExitReport) -> HandBack {
        let now = || t0 + started.elapsed().as_secs_f64();
        if !self.link.state().armed {
            self.say_text(Severity::Info, "markhold stopped");
            return HandBack::NotCommanding;
        }
        let timeout = self.link.config().hand_back_timeout_s;
        self.say_text(Severity::Warning, "markhold stopped: take the controls");
        eprintln!(
            "markhold: handing back: neutral until the pilot's input is heard (at most {timeout} s)"
        );
        let link = &mut self.link;
        link.set_pilot_keepalive(true);
        let before = link.state().clone();
        let t_start = now();
        let outcome = loop {
            let t = now();
            if let Err(e) = link.tick(t) {
                tracing::warn!(error = %e, "hand back: link");
            }
            let st = link.state();
            let pilot = st.pilot.count > before.pilot.count;
            if pilot || st.mode_changes != before.mode_changes || !st.armed {
                break HandBack::PilotTookOver;
            }
            if link.station_lost() {
                break HandBack::StationLost;
            }
            if !st.heartbeat_ok {
                break HandBack::VehicleLost;
            }
            if t - t_start >= timeout {
                break HandBack::Disarmed(CommandStatus::TimedOut);
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        if let HandBack::Disarmed(_) = outcome {
            self.say_text(Severity::Critical, "markhold: no pilot input, disarming");
            let st = disarm_on_exit(&mut self.link, now());
            report.disarm = Some(st);
            return HandBack::Disarmed(st);
        }
        outcome
    }
}

/// Disarm, acknowledged and retried by the link, on loop time `t0` plus the time waited,
/// bounded by the link's own retries. Neutral input keeps going out (the link's
/// keep-alive) until it settles.
pub fn disarm_on_exit(link: &mut VehicleLink, t0: f64) -> CommandStatus {
    let cfg = link.config().clone();
    link.set_pilot_keepalive(true);
    let started = Instant::now();
    let limit = cfg.command_timeout_s * f64::from(cfg.command_retries + 1) + 0.5;
    let now = |started: Instant| t0 + started.elapsed().as_secs_f64();
    if let Err(e) = link.request_arm(false, now(started)) {
        tracing::warn!(error = %e, "disarm on exit: request not sent");
        return CommandStatus::TimedOut;
    }
    eprintln!("markhold: disarming ([link] on_exit)");
    let status = loop {
        let t = now(started);
        if let Err(e) = link.tick(t) {
            tracing::warn!(error = %e, "disarm on exit: link");
        }
        let st = link.state();
        match st.arm_command {
            CommandStatus::Pending { .. } | CommandStatus::Idle if st.armed => {}
            CommandStatus::Pending { .. } | CommandStatus::Idle => break CommandStatus::Accepted,
            other => break other,
        }
        if t - t0 > limit {
            break CommandStatus::TimedOut;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    tracing::info!(?status, armed = link.state().armed, "disarm on exit");
    eprintln!(
        "markhold: disarm on exit: {status:?} (vehicle armed: {})",
        link.state().armed
    );
    status
}
