//! The end of a session: neutral input seen applied by the vehicle, then a close that
//! loses nothing already written. Both wait (bounded, wall clock): they run once, after
//! the loop.

use std::time::{Duration, Instant};

use serde::Serialize;

use super::VehicleLink;
use crate::error::AutopilotError;
use crate::types::ArduSubMode;

/// Consecutive vehicle reports at neutral, all received after the first neutral input
/// went out, that count as "applied": the vehicle made the first of them before or
/// after our input arrived, the second a report period later, after it.
const REPORTS_AT_NEUTRAL: u64 = 2;

/// How the vehicle showed (or did not show) markhold's neutral input applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NeutralShown {
    /// RC_CHANNELS reported channels 1..6 at 1500 us in two reports in a row.
    RcChannels,
    /// No RC_CHANNELS stream; in MANUAL, SERVO_OUTPUT_RAW had every thruster within the
    /// dead band in two reports in a row.
    ServoOutputs,
    /// Neither showed it within the wait (sent, but not confirmed).
    NotShown,
    /// Not sent: the pilot's station is silent (no SYSID_MYGCS traffic) or the vehicle
    /// is not heard.
    NotSent,
    /// The pilot's own stick input was heard during the wait: markhold stopped sending.
    PilotInput,
}

/// What [`VehicleLink::settle_neutral`] did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Settled {
    /// How the vehicle showed it.
    pub shown: NeutralShown,
    /// Wall time waited, s.
    pub waited_s: f64,
    /// Neutral inputs written.
    pub neutrals: u64,
}

/// What [`VehicleLink::close`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct CloseReport {
    /// "udp", "tcp" or "serial".
    pub transport: &'static str,
    /// Every byte written reached the socket or the device.
    pub flushed: bool,
    /// TCP: the vehicle closed its side after reading all of ours.
    pub peer_closed: bool,
}

impl VehicleLink {
    /// Neutral pilot input, repeated at `pilot_input_hz`, until the vehicle shows it
    /// applied or `timeout_s` (wall clock) passes; loop time is `t0` plus the time
    /// waited. Shown by RC_CHANNELS (what ArduSub applies as input, an override or
    /// MANUAL_CONTROL alike), or, from a vehicle that streams no RC_CHANNELS, by
    /// SERVO_OUTPUT_RAW in MANUAL (its thrusters follow the sticks only there). Stops at
    /// once when the pilot's stick is heard, when the pilot's station falls silent (no
    /// SYSID_MYGCS traffic), or when the vehicle is not heard.
    pub fn settle_neutral(&mut self, t0: f64, timeout_s: f64) -> Result<Settled, AutopilotError> {
        let started = Instant::now();
        let elapsed = |s: Instant| s.elapsed().as_secs_f64();
        let c0 = self.state.counters;
        let deflected0 = self.state.pilot.deflected_s;
        let period = 1.0 / self.cfg.pilot_input_hz;
        let mut last_sent: Option<f64> = None;
        let mut neutrals = 0u64;
        let shown = loop {
            let t = t0 + elapsed(started);
            self.tick(t)?;
            let st = &self.state;
            if st.pilot.deflected_s != deflected0 {
                break NeutralShown::PilotInput;
            }
            let c = st.counters;
            let rc_new = c.rc_reports - c0.rc_reports;
            if neutrals > 0
                && rc_new >= REPORTS_AT_NEUTRAL
                && c.rc_neutral_run >= REPORTS_AT_NEUTRAL
            {
                break NeutralShown::RcChannels;
            }
            let servo_new = c.servo_reports - c0.servo_reports;
            if neutrals > 0
                && c.rc_reports == 0
                && st.mode == Some(ArduSubMode::Manual)
                && servo_new >= REPORTS_AT_NEUTRAL
                && c.servo_neutral_run >= REPORTS_AT_NEUTRAL
            {
                break NeutralShown::ServoOutputs;
            }
            // Between two of a live station's heartbeats the link withholds pilot input
            // (the relay window): wait for the next; a lost station ends the wait.
            if !st.heartbeat_ok || st.station.lost {
                break if neutrals == 0 {
                    NeutralShown::NotSent
                } else {
                    NeutralShown::NotShown
                };
            }
            if elapsed(started) >= timeout_s {
                break NeutralShown::NotShown;
            }
            if last_sent.is_none_or(|s| t - s >= period) {
                let before = self.state.counters.pilot_inputs;
                self.send_neutral(t)?;
                if self.state.counters.pilot_inputs > before {
                    neutrals += 1;
                }
                last_sent = Some(t);
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        let waited_s = elapsed(started);
        match shown {
            NeutralShown::RcChannels | NeutralShown::ServoOutputs => {
                tracing::info!(
                    ?shown,
                    waited_s,
                    neutrals,
                    "neutral input applied by the vehicle"
                )
            }
            _ => tracing::warn!(?shown, waited_s, neutrals, "neutral input not seen applied"),
        }
        Ok(Settled {
            shown,
            waited_s,
            neutrals,
        })
    }

    /// Close the link (bounded by `timeout_s`) so that nothing written is lost: see
    /// `Transport::close`. Nothing goes out afterwards.
    pub fn close(&mut self, timeout_s: f64) -> CloseReport {
        let t = Duration::from_secs_f64(timeout_s.clamp(0.0, 60.0));
        let c = self.transport.close(t);
        self.closed = true;
        let report = CloseReport {
            transport: c.kind,
            flushed: c.flushed,
            peer_closed: c.peer_closed,
        };
        tracing::info!(?report, "vehicle link closed");
        report
    }
}
