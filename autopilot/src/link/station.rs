//! The pilot's station: watched so that markhold never keeps ArduSub's GCS failsafe quiet.
//!
//! ArduSub's `Sub::failsafe_gcs_check` (ArduSub/failsafe.cpp, run from `three_hz_loop`
//! in ArduSub/ArduSub.cpp: up to 0.3 s late) fires when nothing has come from SYSID_MYGCS
//! for FS_GCS_TIMEOUT, and it counts as contact any HEARTBEAT from that system id
//! (`GCS_MAVLINK::handle_heartbeat`), any RC_CHANNELS_OVERRIDE from it
//! (`GCS_MAVLINK::handle_rc_channels_override`) and any MANUAL_CONTROL from it aimed at
//! the vehicle (`GCS_MAVLINK_Sub::handleMessage`). markhold's pilot input has to come
//! from SYSID_MYGCS, so while it commands it is ground-station contact.
//!
//! So markhold only relays the station's contact: once the station has been heard, pilot
//! input goes out only within [`STATION_RELAY_S`] of the station's last HEARTBEAT (or its
//! own pilot input), whatever the caller asks. A live station heartbeats at 1 Hz, so
//! pilot input pauses about 0.3 s each second; ArduSub holds the last input through the
//! pause (RC_OVERRIDE_TIME and FS_PILOT_TIMEOUT are 3 s). When the station falls silent,
//! the failsafe fires at most [`STATION_RELAY_S`] and one check period (0.3 s) later than
//! without markhold: within FS_GCS_TIMEOUT + 1 s of the station's last heartbeat. Silence
//! for [`crate::config::station_timeout_s`] marks the station lost: the engagement lets
//! go and says why (as a component of the vehicle, which is not ground-station contact).

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::MavHeader;
use serde::Serialize;

use super::VehicleLink;

/// The vehicle's parameter that says how long its GCS failsafe waits.
pub(super) const FS_GCS_TIMEOUT: &str = "FS_GCS_TIMEOUT";

/// Pilot input (SYSID_MYGCS traffic) goes out only this long after the pilot's station
/// was last heard, s: markhold never extends the station's contact by more, so the
/// vehicle's GCS failsafe, checked every 0.3 s, fires within FS_GCS_TIMEOUT + 1 s of the
/// station's last heartbeat.
pub const STATION_RELAY_S: f64 = 0.7;

/// What the link heard of the pilot's station.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StationSeen {
    /// Loop time it was last heard (its HEARTBEAT, or its own pilot input).
    pub last_s: Option<f64>,
    /// Its HEARTBEATs seen.
    pub heartbeats: u64,
    /// Its component id, as last heard.
    pub component_id: Option<u8>,
    /// Heard once, then silent longer than the station timeout: markhold sends nothing
    /// as SYSID_MYGCS until it is heard again.
    pub lost: bool,
    /// Times it was lost.
    pub losses: u64,
}

impl VehicleLink {
    /// A HEARTBEAT from SYSID_MYGCS with another component id than ours is the pilot's
    /// station; so is pilot input from SYSID_MYGCS that is not ours (ArduSub counts both).
    pub(super) fn observe_station(&mut self, h: &MavHeader, msg: &MavMessage, now_s: f64) {
        if h.system_id != u32::from(self.cfg.gcs_system_id)
            || h.component_id == self.cfg.component_id
        {
            return;
        }
        let heartbeat = match msg {
            MavMessage::HEARTBEAT(_) => true,
            MavMessage::RC_CHANNELS_OVERRIDE(_) => false,
            MavMessage::MANUAL_CONTROL(m) if m.target == self.state.system_id => false,
            _ => return,
        };
        let st = &mut self.state.station;
        if st.last_s.is_none() && st.heartbeats == 0 {
            tracing::info!(
                sysid = h.system_id,
                compid = h.component_id,
                timeout_s = self.station_timeout_s,
                "pilot station heard: markhold's pilot input stops if it falls silent"
            );
        }
        if st.lost {
            tracing::info!(compid = h.component_id, "pilot station heard again");
            st.lost = false;
        }
        st.last_s = Some(now_s);
        st.component_id = Some(h.component_id);
        if heartbeat {
            st.heartbeats += 1;
        }
    }

    /// The station silent longer than the station timeout: lost (logged once per loss).
    pub(super) fn check_station(&mut self, now_s: f64) {
        let timeout = self.station_timeout_s;
        let st = &mut self.state.station;
        let Some(last) = st.last_s else { return };
        if !st.lost && now_s - last > timeout {
            st.lost = true;
            st.losses += 1;
            tracing::warn!(
                silent_s = now_s - last,
                timeout_s = timeout,
                "pilot station silent: no pilot input from markhold until it is heard again, \
                 so the vehicle's GCS failsafe fires as it would without markhold"
            );
        }
    }

    /// Whether pilot input (the SYSID_MYGCS traffic) may go out now: always while no
    /// station was ever heard (a bench, a simulator), else within [`STATION_RELAY_S`] of
    /// the station's last contact.
    pub fn gcs_traffic_allowed(&self) -> bool {
        match (self.state.station.last_s, self.last_tick_s) {
            (Some(last), Some(now)) => now - last <= STATION_RELAY_S,
            _ => true,
        }
    }

    /// The pilot's station has been heard and is silent past the station timeout.
    pub fn station_lost(&self) -> bool {
        self.state.station.lost
    }

    /// The vehicle's GCS failsafe timeout in use, s, and whether the vehicle reported it.
    pub fn fs_gcs_timeout_s(&self) -> (f64, bool) {
        (self.fs_gcs_timeout_s, self.fs_gcs_timeout_read)
    }

    /// How long the pilot's station may be silent before markhold's pilot input stops, s.
    pub fn station_timeout_s(&self) -> f64 {
        self.station_timeout_s
    }

    /// The vehicle's FS_GCS_TIMEOUT (s), as read by preflight or the link itself.
    pub fn set_fs_gcs_timeout_s(&mut self, t: f64) {
        if !(t.is_finite() && t > 0.0) {
            tracing::warn!(
                value = t,
                "FS_GCS_TIMEOUT not usable: keeping {} s",
                self.fs_gcs_timeout_s
            );
            return;
        }
        self.fs_gcs_timeout_s = t;
        self.fs_gcs_timeout_read = true;
        let bound = crate::config::station_timeout_s(t);
        if bound != self.station_timeout_s {
            tracing::info!(
                fs_gcs_timeout_s = t,
                station_timeout_s = bound,
                "vehicle's GCS failsafe timeout read"
            );
        }
        self.station_timeout_s = bound;
    }
}
