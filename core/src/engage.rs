//! Engagement: on a real vehicle markhold commands only while the pilot has engaged it,
//! and lets go at once when the pilot acts. The pilot engages from QGroundControl by
//! selecting the site's `[link] mode` while the vehicle is armed, after markhold said it
//! is ready, with the pilot's station heard; `run --engage` and `hil --vehicle` engage at
//! start (tests, bench runs, a simulator without a station). markhold disengages when
//! the mode changes, the vehicle disarms, the pilot moves a stick, the link is lost, the
//! pilot's station falls silent, the supervisor gives up on a lost marker, or markhold
//! stops: neutral input first, then the override released and no pilot input at all. It
//! never engages again by itself: that takes a new pilot action (a mode switch away and
//! back, or arming in the mode).
//!
//! [`EngagedLink`] wraps the vehicle link as the loop's [`CommandLink`] for every runner
//! on a real link (`run`, `hil --vehicle`): the loop is the same as everywhere else, pilot
//! input simply does not pass while disengaged, and [`EngagedLink::exit`] is the one way
//! a run ends (`exit`). [`Announcer`] tells the pilot what happens (STATUSTEXT, one
//! message per state change, flapping states rate limited) and sends the station error
//! as NAMED_VALUE_FLOAT.

mod exit;
pub use exit::{ExitPolicy, ExitReport, HandBack, CLOSE_TIMEOUT_S};

use crate::CoreError;
use std::sync::mpsc::SyncSender;

use markhold_autopilot::{
    ArduSubMode, Effort, FailsafeEvent, RawFrame, Severity, VehicleLink, VehicleState,
};
use serde::Serialize;

use crate::pipeline::CommandLink;

/// After a disengage one neutral input goes out and holds (ArduSub keeps an override
/// until it is released or RC_OVERRIDE_TIME passes) this long before the release, s
/// (loop time: the first tick at or after it releases, so at 30 frames/s 2 frames later).
pub const NEUTRAL_BEFORE_RELEASE_S: f64 = 0.05;
/// The same marker / camera / exposure message is not repeated within this, s.
pub const FLAP_INTERVAL_S: f64 = 5.0;
/// NAMED_VALUE_FLOAT rate while engaged, Hz.
pub const NAMED_VALUE_HZ: f64 = 4.0;

/// Why markhold let go.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Disengage {
    /// The vehicle's mode changed (the pilot chose another mode).
    ModeChanged,
    /// The vehicle disarmed.
    Disarmed,
    /// The pilot moved a stick (MANUAL_CONTROL / RC override from another sender).
    PilotInput,
    /// The vehicle is not heard.
    LinkLost,
    /// The pilot's station (its heartbeat from SYSID_MYGCS) fell silent.
    StationLost,
    /// The supervisor gave up on a lost marker.
    MarkerLost,
    /// markhold stops.
    Stopped,
}

impl Disengage {
    /// The STATUSTEXT (under 50 characters).
    pub fn text(self) -> &'static str {
        match self {
            Self::ModeChanged => "markhold off: mode changed",
            Self::Disarmed => "markhold off: disarmed",
            Self::PilotInput => "markhold off: pilot input",
            Self::LinkLost => "markhold off: link lost",
            Self::StationLost => "markhold off: pilot station silent",
            Self::MarkerLost => "markhold off: marker lost, gave up",
            Self::Stopped => "markhold off: stopped",
        }
    }
}

/// Where engagement stands.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EngageState {
    /// The vehicle not heard yet: nothing said, nothing sent.
    Waiting,
    /// Ready: waits for the pilot (arm + the site's mode); no pilot input goes out.
    Ready,
    /// Commanding.
    Engaged,
    /// Just disengaged: neutral until `release_at_s`, then released.
    Releasing { release_at_s: f64 },
    /// The pilot asked (armed in the mode) before the pilot's station was heard: engage
    /// once it is, within [`STATION_WAIT_S`] of `since_s`; no pilot input goes out.
    Pending { since_s: f64 },
}

/// A pilot's engage waits this long for the station's heartbeat (one 1 Hz period and
/// its jitter), s.
pub const STATION_WAIT_S: f64 = markhold_autopilot::config::STATION_TIMEOUT_MIN_S;

/// A change of engagement, for the announcer and the summary.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum Transition {
    Ready,
    Engaged,
    Disengaged(Disengage),
    /// The pilot asked (armed in the mode) but no pilot station is heard: markhold
    /// cannot tell when it falls silent, so it does not engage.
    NoStation,
}

/// The engagement state machine: pure, on loop time, fed the link's view of the vehicle.
#[derive(Clone, Debug)]
pub struct Engager {
    mode: ArduSubMode,
    engage_at_start: bool,
    /// Engage with no pilot station ever heard (`--engage`, a simulator): there is no
    /// ground-station failsafe to keep quiet. A station heard once is watched anyway.
    allow_without_station: bool,
    state: EngageState,
    /// Armed in the site's mode, as last observed: engaging takes a rising edge.
    armed_in_mode: bool,
    mode_changes: u64,
    armed: bool,
    /// The pilot's deflected input already accounted for.
    pilot_deflected_s: Option<f64>,
    /// markhold itself asked for the site's mode until this loop time: that edge is not
    /// a pilot action.
    own_request_until_s: Option<f64>,
    own_request_window_s: f64,
    engagements: u64,
    last_disengage: Option<Disengage>,
}

impl Engager {
    /// Engage in `mode`; `engage_at_start`: as soon as the vehicle is heard (`--engage`),
    /// also with no pilot station heard. `own_request_window_s`: how long a mode request
    /// of markhold's own may take to show.
    pub fn new(mode: ArduSubMode, engage_at_start: bool, own_request_window_s: f64) -> Self {
        Self {
            mode,
            engage_at_start,
            allow_without_station: engage_at_start,
            state: EngageState::Waiting,
            armed_in_mode: false,
            mode_changes: 0,
            armed: false,
            pilot_deflected_s: None,
            own_request_until_s: None,
            own_request_window_s,
            engagements: 0,
            last_disengage: None,
        }
    }

    pub fn state(&self) -> EngageState {
        self.state
    }

    pub fn engaged(&self) -> bool {
        self.state == EngageState::Engaged
    }

    /// Times markhold engaged.
    pub fn engagements(&self) -> u64 {
        self.engagements
    }

    pub fn last_disengage(&self) -> Option<Disengage> {
        self.last_disengage
    }

    /// markhold asked the vehicle for `mode` at `now_s` (a failsafe action or its way
    /// back): if that is the engage mode, the edge it makes does not engage.
    pub fn own_mode_request(&mut self, mode: ArduSubMode, now_s: f64) {
        if mode == self.mode {
            self.own_request_until_s = Some(now_s + self.own_request_window_s);
        }
    }

    /// Disengage for `why` (no-op unless engaged).
    pub fn disengage(&mut self, why: Disengage, now_s: f64) -> Option<Transition> {
        if self.state != EngageState::Engaged {
            return None;
        }
        self.state = EngageState::Releasing {
            release_at_s: now_s + NEUTRAL_BEFORE_RELEASE_S,
        };
        self.last_disengage = Some(why);
        tracing::warn!(?why, "disengaged");
        Some(Transition::Disengaged(why))
    }

    fn engage(&mut self) -> Option<Transition> {
        self.state = EngageState::Engaged;
        self.engagements += 1;
        tracing::info!(engagements = self.engagements, "engaged");
        Some(Transition::Engaged)
    }

    /// The pilot's station allows engaging: heard and not silent, or never heard where
    /// engaging without one is allowed.
    fn station_ok(&self, v: &VehicleState) -> bool {
        !v.station.lost && (v.station.last_s.is_some() || self.allow_without_station)
    }

    /// The pilot asked, but no pilot station is heard: not engaged, and said.
    fn refuse(&self, v: &VehicleState) -> Option<Transition> {
        tracing::warn!(
            lost = v.station.lost,
            "not engaging: no pilot station heard (a HEARTBEAT from SYSID_MYGCS)"
        );
        Some(Transition::NoStation)
    }

    /// Markhold commands (engaged) or has just let go and not yet released.
    pub fn commanding(&self) -> bool {
        matches!(
            self.state,
            EngageState::Engaged | EngageState::Releasing { .. }
        )
    }

    /// Back to Ready without a release (the caller released, or there is nothing to).
    fn released(&mut self) {
        if self.commanding() {
            self.state = EngageState::Ready;
        }
    }

    /// The release is due: the caller releases the override and this goes to Ready.
    pub fn release_due(&mut self, now_s: f64) -> bool {
        match self.state {
            EngageState::Releasing { release_at_s } if now_s >= release_at_s => {
                self.state = EngageState::Ready;
                true
            }
            _ => false,
        }
    }

    /// One observation of the vehicle at loop time `now_s`.
    pub fn observe(&mut self, v: &VehicleState, now_s: f64) -> Option<Transition> {
        let mode_changed = v.mode_changes != self.mode_changes;
        let disarmed = self.armed && !v.armed;
        let deflected =
            v.pilot.deflected_s.is_some() && v.pilot.deflected_s != self.pilot_deflected_s;
        let cond = v.armed && v.mode == Some(self.mode);
        let rising = cond && !self.armed_in_mode;
        self.mode_changes = v.mode_changes;
        self.armed = v.armed;
        self.pilot_deflected_s = v.pilot.deflected_s;
        self.armed_in_mode = cond;
        let own = self.own_request_until_s.is_some_and(|u| now_s <= u);
        if !own {
            self.own_request_until_s = None;
        }
        match self.state {
            EngageState::Waiting if v.heartbeat_ok => {
                if self.engage_at_start && self.station_ok(v) {
                    self.engage()
                } else {
                    self.state = EngageState::Ready;
                    Some(Transition::Ready)
                }
            }
            EngageState::Waiting => None,
            EngageState::Engaged if !v.heartbeat_ok => self.disengage(Disengage::LinkLost, now_s),
            EngageState::Engaged if v.station.lost => self.disengage(Disengage::StationLost, now_s),
            EngageState::Engaged if disarmed => self.disengage(Disengage::Disarmed, now_s),
            EngageState::Engaged if mode_changed => self.disengage(Disengage::ModeChanged, now_s),
            EngageState::Engaged if deflected => self.disengage(Disengage::PilotInput, now_s),
            EngageState::Engaged | EngageState::Releasing { .. } => None,
            EngageState::Ready if rising && v.heartbeat_ok && !own => {
                if self.station_ok(v) {
                    self.engage()
                } else if v.station.lost {
                    self.refuse(v)
                } else {
                    self.state = EngageState::Pending { since_s: now_s };
                    None
                }
            }
            EngageState::Ready => None,
            EngageState::Pending { .. } if !(cond && v.heartbeat_ok) => {
                self.state = EngageState::Ready;
                None
            }
            EngageState::Pending { .. } if self.station_ok(v) => self.engage(),
            EngageState::Pending { since_s } if now_s - since_s > STATION_WAIT_S => {
                self.state = EngageState::Ready;
                self.refuse(v)
            }
            EngageState::Pending { .. } => None,
        }
    }
}

/// A message kind that can flap, rate limited on its own.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Flap {
    Marker,
    Camera,
    Exposure,
}

/// One flapping state: the last one sent, when, and one waiting for the window to open.
#[derive(Clone, Copy, Debug, Default)]
struct Limited {
    sent: Option<(bool, f64)>,
    pending: Option<bool>,
}

/// A STATUSTEXT to send.
pub type Text = (Severity, &'static str);

/// Tells the pilot what markhold does: engagement changes at once, flapping states (marker
/// lost / regained, camera stalled / back, exposure at a limit) at most once per
/// `FLAP_INTERVAL_S` per kind, the latest state sent when the window opens if it differs
/// from the last one sent.
#[derive(Clone, Debug, Default)]
pub struct Announcer {
    marker: Limited,
    camera: Limited,
    exposure: Limited,
    last_named_s: Option<f64>,
    /// The keeper's way back is running, and when it was last announced.
    searching: bool,
    search_said_s: Option<f64>,
    /// Messages sent.
    pub sent: u64,
    /// Flapping state changes not sent (coalesced).
    pub suppressed: u64,
}

impl Announcer {
    fn slot(&mut self, f: Flap) -> &mut Limited {
        match f {
            Flap::Marker => &mut self.marker,
            Flap::Camera => &mut self.camera,
            Flap::Exposure => &mut self.exposure,
        }
    }

    fn text(f: Flap, on: bool) -> Text {
        match (f, on) {
            (Flap::Marker, true) => (Severity::Warning, "markhold: marker lost"),
            (Flap::Marker, false) => (Severity::Info, "markhold: marker regained"),
            (Flap::Camera, true) => (Severity::Warning, "markhold: camera stalled, neutral"),
            (Flap::Camera, false) => (Severity::Info, "markhold: camera back"),
            (Flap::Exposure, true) => (Severity::Warning, "markhold: exposure at its limit"),
            (Flap::Exposure, false) => (Severity::Info, "markhold: exposure within limits"),
        }
    }

    /// A flapping state became `on` at `now_s`; the text to send now, if any.
    fn flap(&mut self, f: Flap, on: bool, now_s: f64) -> Option<Text> {
        let s = self.slot(f);
        match s.sent {
            Some((last, _)) if last == on => {
                s.pending = None;
                None
            }
            Some((_, t)) if now_s - t < FLAP_INTERVAL_S => {
                s.pending = Some(on);
                self.suppressed += 1;
                None
            }
            None if !on => None,
            _ => {
                s.sent = Some((on, now_s));
                s.pending = None;
                self.sent += 1;
                Some(Self::text(f, on))
            }
        }
    }

    /// Pending flapping states whose window has opened: at most one text per kind.
    pub fn due(&mut self, now_s: f64, out: &mut Vec<Text>) {
        for f in [Flap::Marker, Flap::Camera, Flap::Exposure] {
            let s = self.slot(f);
            if let (Some(on), Some((_, t))) = (s.pending, s.sent) {
                if now_s - t >= FLAP_INTERVAL_S {
                    s.pending = None;
                    if let Some(text) = self.flap(f, on, now_s) {
                        out.push(text);
                    }
                }
            }
        }
    }

    /// An engagement change: always said, at once.
    pub fn transition(&mut self, t: Transition, mode: ArduSubMode) -> Text {
        self.sent += 1;
        match t {
            Transition::Ready => (Severity::Notice, ready_text(mode)),
            Transition::Engaged => (Severity::Notice, "markhold on: holding station"),
            Transition::Disengaged(why) => (Severity::Warning, why.text()),
            Transition::NoStation => (
                Severity::Warning,
                "markhold: pilot station not heard, not engaging",
            ),
        }
    }

    /// The supervisor's transitions of one frame.
    pub fn events(&mut self, events: &[FailsafeEvent], out: &mut Vec<Text>) {
        for e in events {
            let t = match *e {
                FailsafeEvent::MarkerLost { at_s, .. } => self.flap(Flap::Marker, true, at_s),
                FailsafeEvent::MarkerReacquired { at_s, .. } => {
                    self.flap(Flap::Marker, false, at_s)
                }
                FailsafeEvent::VisionStalled { at_s, .. } => self.flap(Flap::Camera, true, at_s),
                FailsafeEvent::VisionRestored { at_s } => self.flap(Flap::Camera, false, at_s),
                _ => None,
            };
            out.extend(t);
        }
    }

    /// The exposure controller is (or is no longer) pinned at a camera limit.
    pub fn exposure_at_limit(&mut self, at_limit: bool, now_s: f64) -> Option<Text> {
        self.flap(Flap::Exposure, at_limit, now_s)
    }

    /// The keeper's way back runs (or no longer does): said when it starts, at most once
    /// per `FLAP_INTERVAL_S`; its end is told by "marker regained" or "marker lost".
    pub fn searching(&mut self, on: bool, now_s: f64) -> Option<Text> {
        let start = on && !self.searching;
        self.searching = on;
        if !start {
            return None;
        }
        if self
            .search_said_s
            .is_some_and(|t| now_s - t < FLAP_INTERVAL_S && now_s >= t)
        {
            self.suppressed += 1;
            return None;
        }
        self.search_said_s = Some(now_s);
        self.sent += 1;
        Some((
            Severity::Warning,
            "markhold: marker out of view, turning back",
        ))
    }

    /// NAMED_VALUE_FLOAT is due at `now_s` (`NAMED_VALUE_HZ`).
    pub fn named_value_due(&mut self, now_s: f64) -> bool {
        if self
            .last_named_s
            .is_some_and(|t| now_s - t < 1.0 / NAMED_VALUE_HZ && now_s >= t)
        {
            return false;
        }
        self.last_named_s = Some(now_s);
        true
    }
}

/// "markhold ready: arm + ALT_HOLD to engage" for the site's mode.
pub fn ready_text(mode: ArduSubMode) -> &'static str {
    match mode {
        ArduSubMode::Manual => "markhold ready: arm, select MANUAL",
        ArduSubMode::Stabilize => "markhold ready: arm, select STABILIZE",
        ArduSubMode::AltHold => "markhold ready: arm, select ALT_HOLD",
        ArduSubMode::Guided => "markhold ready: arm, select GUIDED",
        ArduSubMode::PosHold => "markhold ready: arm, select POSHOLD",
        _ => "markhold ready: arm, select the site mode",
    }
}

/// The vehicle link as the run loop's [`CommandLink`]: pilot input passes only while
/// engaged; engagement changes are announced on the link itself.
pub struct EngagedLink {
    link: VehicleLink,
    engager: Engager,
    announcer: Announcer,
    mode: ArduSubMode,
    /// Pilot input the loop asked for while disengaged (not sent).
    pub withheld: u64,
    texts: Vec<Text>,
    /// Every engagement change, with its loop time.
    pub transitions: Vec<(f64, Transition)>,
}

impl EngagedLink {
    pub fn new(mut link: VehicleLink, engage_at_start: bool) -> Self {
        let cfg = link.config();
        let mode = cfg.mode.ardusub();
        let window = cfg.command_timeout_s * f64::from(cfg.command_retries + 1) + 1.0;
        // Nothing goes out by itself until engaged.
        link.set_pilot_keepalive(false);
        Self {
            link,
            engager: Engager::new(mode, engage_at_start, window),
            announcer: Announcer::default(),
            mode,
            withheld: 0,
            texts: Vec::with_capacity(8),
            transitions: Vec::with_capacity(16),
        }
    }

    pub fn inner(&self) -> &VehicleLink {
        &self.link
    }

    pub fn inner_mut(&mut self) -> &mut VehicleLink {
        &mut self.link
    }

    pub fn engager(&self) -> &Engager {
        &self.engager
    }

    pub fn announcer(&self) -> &Announcer {
        &self.announcer
    }

    fn say(&mut self, (sev, text): Text) -> Result<(), CoreError> {
        Ok(self.link.send_statustext(sev, text)?)
    }

    fn apply(&mut self, t: Option<Transition>, now_s: f64) -> Result<(), CoreError> {
        let Some(t) = t else { return Ok(()) };
        self.transitions.push((now_s, t));
        let text = self.announcer.transition(t, self.mode);
        match t {
            Transition::Engaged => self.link.set_pilot_keepalive(true),
            // Centre the sticks at once (an override holds until released, and ArduSub
            // with no RC receiver keeps the last value after a release); nothing more
            // until the release follows.
            Transition::Disengaged(why) => {
                self.link.send_neutral(now_s)?;
                self.link.set_pilot_keepalive(false);
                if matches!(why, Disengage::StationLost | Disengage::LinkLost) {
                    // Nobody to hand over to, or nobody hears us: let go in the same
                    // tick, inside the station's grace (no SYSID_MYGCS traffic after).
                    self.link.release_pilot()?;
                    self.engager.released();
                }
            }
            Transition::Ready | Transition::NoStation => {}
        }
        self.say(text)
    }

    /// Disengage for `why` now (the supervisor gave up, markhold stops).
    pub fn disengage(&mut self, why: Disengage, now_s: f64) -> Result<(), CoreError> {
        let t = self.engager.disengage(why, now_s);
        self.apply(t, now_s)
    }

    /// Release the override after a disengage (nothing when markhold was not
    /// commanding: after a pilot takeover nothing more goes out as SYSID_MYGCS).
    fn release(&mut self) -> Result<(), CoreError> {
        if !self.engager.commanding() {
            return Ok(());
        }
        self.engager.released();
        Ok(self.link.release_pilot()?)
    }

    /// The supervisor's transitions of a frame: announced; giving up on the marker
    /// disengages.
    pub fn on_events(&mut self, events: &[FailsafeEvent], now_s: f64) -> Result<(), CoreError> {
        if events
            .iter()
            .any(|e| matches!(e, FailsafeEvent::MarkerLostActionDue { .. }))
        {
            self.disengage(Disengage::MarkerLost, now_s)?;
        }
        let mut texts = std::mem::take(&mut self.texts);
        texts.clear();
        self.announcer.events(events, &mut texts);
        self.announcer.due(now_s, &mut texts);
        let r = texts.iter().try_for_each(|&t| self.say(t));
        self.texts = texts;
        r
    }

    /// The exposure is (or is no longer) at a camera limit.
    pub fn exposure_at_limit(&mut self, at_limit: bool, now_s: f64) -> Result<(), CoreError> {
        match self.announcer.exposure_at_limit(at_limit, now_s) {
            Some(t) => self.say(t),
            None => Ok(()),
        }
    }

    /// The station keeper's way back toward a marker that slipped out of view runs (or
    /// no longer does); said only while engaged, when it moves the vehicle.
    pub fn searching(&mut self, on: bool, now_s: f64) -> Result<(), CoreError> {
        let on = on && self.engager.engaged();
        match self.announcer.searching(on, now_s) {
            Some(t) => self.say(t),
            None => Ok(()),
        }
    }

    /// Station error (metres, yaw degrees) as NAMED_VALUE_FLOAT `mh_err_m` and
    /// `mh_yaw_deg`, at `NAMED_VALUE_HZ` while engaged.
    pub fn station_error(&mut self, err_m: f64, yaw_deg: f64, now_s: f64) -> Result<(), CoreError> {
        if !self.engager.engaged() || !self.announcer.named_value_due(now_s) {
            return Ok(());
        }
        self.link
            .send_named_value("mh_err_m", err_m as f32, now_s)?;
        self.link
            .send_named_value("mh_yaw_deg", yaw_deg as f32, now_s)?;
        Ok(())
    }
}

impl CommandLink for EngagedLink {
    fn tick(&mut self, now_s: f64) -> Result<(), CoreError> {
        self.link.tick(now_s)?;
        let t = self.engager.observe(self.link.state(), now_s);
        self.apply(t, now_s)?;
        if self.engager.release_due(now_s) {
            self.link.release_pilot()?;
        }
        Ok(())
    }

    fn send_effort(&mut self, effort: &Effort, now_s: f64) -> Result<(), CoreError> {
        // While releasing, the neutral sent at the disengage holds (an override stays
        // until released), so nothing more goes out.
        match self.engager.state {
            EngageState::Engaged => Ok(self.link.send_effort(effort, now_s)?),
            _ => {
                self.withheld += 1;
                Ok(())
            }
        }
    }

    fn send_depth_target(&mut self, down_m: f64, now_s: f64) -> Result<(), CoreError> {
        // A command like the effort it goes with: only while engaged.
        if self.engager.state == EngageState::Engaged {
            self.link.send_depth_target(down_m, now_s)?;
        }
        Ok(())
    }

    fn send_neutral(&mut self, now_s: f64) -> Result<(), CoreError> {
        match self.engager.state {
            EngageState::Engaged => Ok(self.link.send_neutral(now_s)?),
            _ => {
                self.withheld += 1;
                Ok(())
            }
        }
    }

    fn send_setpoint(
        &mut self,
        meas: Option<&markhold_autopilot::VisionPose>,
        goal: &nalgebra::Isometry3<f64>,
        now_s: f64,
    ) -> Result<(), CoreError> {
        match self.engager.state {
            EngageState::Engaged => Ok(self.link.send_setpoint(meas, goal, now_s)?),
            _ => {
                // The estimate is not a command: the EKF needs it before the pilot can
                // select GUIDED (the vehicle refuses GUIDED without a position).
                if let Some(m) = meas {
                    self.link.send_vision_estimate(m)?;
                }
                self.withheld += 1;
                Ok(())
            }
        }
    }

    fn vehicle_heartbeat_s(&self) -> Option<f64> {
        self.link.state().last_heartbeat_s
    }

    fn vehicle_state(&self) -> Option<&VehicleState> {
        Some(self.link.state())
    }

    fn request_mode(&mut self, mode: ArduSubMode, now_s: f64) -> Result<(), CoreError> {
        self.engager.own_mode_request(mode, now_s);
        Ok(self.link.request_mode(mode, now_s)?)
    }

    fn request_arm(&mut self, arm: bool, now_s: f64) -> Result<(), CoreError> {
        Ok(self.link.request_arm(arm, now_s)?)
    }

    fn set_raw_tap(&mut self, tap: Option<SyncSender<RawFrame>>) {
        self.link.set_raw_tap(tap);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn vehicle(armed: bool, mode: ArduSubMode, changes: u64) -> VehicleState {
        let cfg = markhold_autopilot::LinkConfig::default();
        let mut v = VehicleLink::connect(&markhold_autopilot::LinkConfig {
            url: "udpin:127.0.0.1:0".into(),
            ..cfg
        })
        .unwrap()
        .state()
        .clone();
        v.heartbeat_ok = true;
        v.armed = armed;
        v.mode = Some(mode);
        v.mode_changes = changes;
        // The pilot's station heard (QGroundControl's heartbeat).
        v.station.last_s = Some(0.0);
        v.station.heartbeats = 1;
        v
    }

    #[test]
    fn no_engagement_without_the_pilot_station_and_a_silent_one_disengages() {
        let alt = ArduSubMode::AltHold;
        let mut e = Engager::new(alt, false, 5.0);
        let mut v = vehicle(false, alt, 0);
        v.station = markhold_autopilot::StationSeen::default();
        assert_eq!(e.observe(&v, 0.0), Some(Transition::Ready));
        // The pilot arms in the mode, but no station was heard: markhold waits a
        // heartbeat period for it, then, none heard (it cannot tell when it would fall
        // silent), does not engage, and says so.
        v.armed = true;
        assert_eq!(e.observe(&v, 1.0), None);
        assert_eq!(e.state(), EngageState::Pending { since_s: 1.0 });
        assert_eq!(e.observe(&v, 0.9 + STATION_WAIT_S), None);
        assert_eq!(
            e.observe(&v, 1.1 + STATION_WAIT_S),
            Some(Transition::NoStation)
        );
        assert!(!e.engaged());
        // Heard within the wait: engaged on that same request.
        let mut e2 = Engager::new(alt, false, 5.0);
        let mut w = vehicle(false, alt, 0);
        w.station = markhold_autopilot::StationSeen::default();
        e2.observe(&w, 0.0);
        w.armed = true;
        assert_eq!(e2.observe(&w, 1.0), None);
        w.station.last_s = Some(1.5);
        assert_eq!(e2.observe(&w, 1.5), Some(Transition::Engaged));
        // With the station heard, the next pilot action engages.
        let mut v = vehicle(true, ArduSubMode::Manual, 1);
        e.observe(&v, 2.0);
        v.mode = Some(alt);
        v.mode_changes = 2;
        assert_eq!(e.observe(&v, 3.0), Some(Transition::Engaged));
        // The station falls silent (the link marks it lost): disengaged, and no pilot
        // action engages again until it is heard.
        v.station.lost = true;
        assert_eq!(
            e.observe(&v, 4.0),
            Some(Transition::Disengaged(Disengage::StationLost))
        );
        assert!(e.release_due(4.1));
        v.mode = Some(ArduSubMode::Manual);
        v.mode_changes = 3;
        e.observe(&v, 5.0);
        v.mode = Some(alt);
        v.mode_changes = 4;
        assert_eq!(e.observe(&v, 6.0), Some(Transition::NoStation));
        // `--engage` (no station needed) still does not engage while one is silent.
        let mut e = Engager::new(alt, true, 5.0);
        let mut v = vehicle(true, alt, 0);
        v.station = markhold_autopilot::StationSeen::default();
        assert_eq!(e.observe(&v, 0.0), Some(Transition::Engaged));
        let mut e = Engager::new(alt, true, 5.0);
        v.station.last_s = Some(0.0);
        v.station.lost = true;
        assert_eq!(e.observe(&v, 0.0), Some(Transition::Ready));
    }

    #[test]
    fn engages_only_on_a_pilot_edge_and_never_by_itself() {
        let alt = ArduSubMode::AltHold;
        let mut e = Engager::new(alt, false, 5.0);
        // Already armed in the mode when markhold starts: ready, not engaged.
        assert_eq!(
            e.observe(&vehicle(true, alt, 0), 0.0),
            Some(Transition::Ready)
        );
        assert_eq!(e.observe(&vehicle(true, alt, 0), 0.1), None);
        // The pilot switches away and back: engaged.
        e.observe(&vehicle(true, ArduSubMode::Manual, 1), 1.0);
        assert_eq!(
            e.observe(&vehicle(true, alt, 2), 2.0),
            Some(Transition::Engaged)
        );
        // The pilot switches away: disengaged, and staying in the mode never re-engages.
        assert_eq!(
            e.observe(&vehicle(true, ArduSubMode::Manual, 3), 3.0),
            Some(Transition::Disengaged(Disengage::ModeChanged))
        );
        assert!(e.release_due(3.1));
        // markhold's own failsafe returns to the mode: not a pilot action.
        e.own_mode_request(alt, 4.0);
        assert_eq!(e.observe(&vehicle(true, alt, 4), 4.5), None);
        assert_eq!(e.observe(&vehicle(true, alt, 4), 30.0), None);
        assert_eq!(e.engagements(), 1);
    }

    #[test]
    fn disarm_and_stick_disengage() {
        let alt = ArduSubMode::AltHold;
        let mut e = Engager::new(alt, true, 5.0);
        assert_eq!(
            e.observe(&vehicle(true, alt, 0), 0.0),
            Some(Transition::Engaged)
        );
        let mut v = vehicle(true, alt, 0);
        v.pilot.deflected_s = Some(1.0);
        assert_eq!(
            e.observe(&v, 1.0),
            Some(Transition::Disengaged(Disengage::PilotInput))
        );
        let mut e = Engager::new(alt, true, 5.0);
        e.observe(&vehicle(true, alt, 0), 0.0);
        assert_eq!(
            e.observe(&vehicle(false, alt, 0), 1.0),
            Some(Transition::Disengaged(Disengage::Disarmed))
        );
    }

    #[test]
    fn a_flapping_marker_is_rate_limited_and_ends_on_the_true_state() {
        let mut a = Announcer::default();
        let mut out = Vec::new();
        let mut t = 0.0;
        // Lost / regained every 0.2 s for 10 s.
        for i in 0..50 {
            let ev = if i % 2 == 0 {
                FailsafeEvent::MarkerLost {
                    at_s: t,
                    last_seen_s: t,
                }
            } else {
                FailsafeEvent::MarkerReacquired {
                    at_s: t,
                    lost_for_s: 0.2,
                }
            };
            a.events(&[ev], &mut out);
            a.due(t, &mut out);
            t += 0.2;
        }
        // 10 s at one message per 5 s per kind: at most 3.
        assert!(out.len() <= 3, "{out:?}");
        a.due(t + FLAP_INTERVAL_S, &mut out);
        // The last state (regained) is the last said.
        assert_eq!(out.last().unwrap().1, "markhold: marker regained");
        // Every text fits STATUSTEXT.
        for d in [
            Disengage::ModeChanged,
            Disengage::Disarmed,
            Disengage::PilotInput,
            Disengage::LinkLost,
            Disengage::StationLost,
            Disengage::MarkerLost,
            Disengage::Stopped,
        ] {
            assert!(d.text().len() < 50);
        }
        let (_, t) = a.transition(Transition::NoStation, ArduSubMode::AltHold);
        assert!(t.len() < 50, "{t}");
    }

    #[test]
    fn the_way_back_is_said_when_it_starts_at_most_once_per_window() {
        let mut a = Announcer::default();
        assert_eq!(a.searching(false, 0.0), None);
        let (sev, text) = a.searching(true, 1.0).unwrap();
        assert_eq!(sev, Severity::Warning);
        assert!(text.contains("turning back") && text.len() < 50, "{text}");
        // Still searching: nothing more; found and lost again within the window: nothing.
        assert_eq!(a.searching(true, 1.1), None);
        assert_eq!(a.searching(false, 1.5), None);
        assert_eq!(a.searching(true, 2.0), None);
        assert_eq!(a.suppressed, 1);
        // After the window a new start is said again.
        a.searching(false, 3.0);
        assert!(a.searching(true, 1.0 + FLAP_INTERVAL_S + 0.1).is_some());
    }
}
