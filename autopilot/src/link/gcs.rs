//! What a ground station does beside pilot input: tell the pilot (STATUSTEXT,
//! NAMED_VALUE_FLOAT), hear the pilot (MANUAL_CONTROL / RC_CHANNELS_OVERRIDE from another
//! sender), hear the vehicle (STATUSTEXT, SYS_STATUS sensor health), and read parameters
//! (PARAM_REQUEST_READ / PARAM_REQUEST_LIST, AUTOPILOT_VERSION).

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavSeverity, AUTOPILOT_VERSION_DATA, MANUAL_CONTROL_DATA,
    NAMED_VALUE_FLOAT_DATA, PARAM_REQUEST_LIST_DATA, PARAM_REQUEST_READ_DATA, PARAM_VALUE_DATA,
    RC_CHANNELS_OVERRIDE_DATA, STATUSTEXT_DATA, SYS_STATUS_DATA,
};
use mavlink::MavHeader;

use super::VehicleLink;
use crate::config::PilotInput;
use crate::error::AutopilotError;

/// STATUSTEXT's text field: 50 bytes, no terminator needed when full.
pub const STATUSTEXT_MAX: usize = 50;
/// NAMED_VALUE_FLOAT's name field.
pub const NAMED_VALUE_MAX: usize = 10;
/// MANUAL_CONTROL x / y / r (of +-1000) and z away from 500 that counts as the pilot
/// moving a stick (a centred joystick still sends, with a little noise).
pub const STICK_DEFLECTION: i16 = 150;
/// RC override PWM away from 1500 that counts as a stick moved, us.
pub const PWM_DEFLECTION: u16 = 60;

/// How the pilot's own input looked, when another sender's was last heard.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct PilotSeen {
    /// Loop time of the last MANUAL_CONTROL / RC_CHANNELS_OVERRIDE from another sender.
    pub last_s: Option<f64>,
    /// Loop time of the last one with a stick out of centre.
    pub deflected_s: Option<f64>,
    /// Messages of pilot input from other senders.
    pub count: u64,
}

/// STATUSTEXT severity, as MAVLink numbers it (lower is worse).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum Severity {
    /// MAV_SEVERITY_CRITICAL (2).
    Critical,
    /// MAV_SEVERITY_WARNING (4).
    Warning,
    /// MAV_SEVERITY_NOTICE (5).
    Notice,
    /// MAV_SEVERITY_INFO (6).
    Info,
}

impl Severity {
    fn mav(self) -> MavSeverity {
        match self {
            Self::Critical => MavSeverity::MAV_SEVERITY_CRITICAL,
            Self::Warning => MavSeverity::MAV_SEVERITY_WARNING,
            Self::Notice => MavSeverity::MAV_SEVERITY_NOTICE,
            Self::Info => MavSeverity::MAV_SEVERITY_INFO,
        }
    }
}

fn manual_deflected(m: &MANUAL_CONTROL_DATA) -> bool {
    m.x.abs() > STICK_DEFLECTION
        || m.y.abs() > STICK_DEFLECTION
        || m.r.abs() > STICK_DEFLECTION
        || (m.z - 500).abs() > STICK_DEFLECTION
}

fn override_deflected(o: &RC_CHANNELS_OVERRIDE_DATA) -> bool {
    // 0 releases a channel and 65535 leaves it alone: neither is a stick.
    [
        o.chan1_raw,
        o.chan2_raw,
        o.chan3_raw,
        o.chan4_raw,
        o.chan5_raw,
        o.chan6_raw,
    ]
    .iter()
    .any(|&v| v != 0 && v != u16::MAX && v.abs_diff(1500) > PWM_DEFLECTION)
}

/// Text of a fixed-size MAVLink char array up to its first NUL.
fn text_of(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

impl VehicleLink {
    /// Pilot input from a sender that is not us and aimed at our vehicle (the pilot's
    /// QGroundControl joystick, seen where the router forwards it). True if `msg` was one.
    pub(super) fn observe_pilot(&mut self, h: &MavHeader, msg: &MavMessage, now_s: f64) -> bool {
        let ours = h.system_id == u32::from(self.cfg.gcs_system_id)
            && h.component_id == self.cfg.component_id;
        let deflected = match msg {
            MavMessage::MANUAL_CONTROL(m) if m.target == self.state.system_id => {
                manual_deflected(m)
            }
            MavMessage::RC_CHANNELS_OVERRIDE(o) if o.target_system == self.state.system_id => {
                override_deflected(o)
            }
            _ => return false,
        };
        if ours {
            return true;
        }
        let p = &mut self.state.pilot;
        if p.last_s.is_none() {
            tracing::info!(
                sysid = h.system_id,
                compid = h.component_id,
                "pilot input from another sender heard"
            );
        }
        p.last_s = Some(now_s);
        p.count += 1;
        if deflected {
            p.deflected_s = Some(now_s);
        }
        true
    }

    /// The vehicle's STATUSTEXT, SYS_STATUS, PARAM_VALUE and AUTOPILOT_VERSION.
    pub(super) fn apply_gcs(&mut self, msg: &MavMessage, now_s: f64) {
        match msg {
            MavMessage::STATUSTEXT(s) => self.apply_statustext(s),
            MavMessage::SYS_STATUS(s) => self.apply_sys_status(s),
            MavMessage::PARAM_VALUE(p) => self.apply_param(p, now_s),
            MavMessage::AUTOPILOT_VERSION(v) => self.apply_version(v),
            _ => {}
        }
    }

    fn apply_statustext(&mut self, s: &STATUSTEXT_DATA) {
        self.state.statustexts += 1;
        let text = text_of(&s.text[..]);
        let sev = s.severity as u8;
        // The vehicle's own warnings (leak, failsafes, EKF) go to markhold's log.
        if sev <= MavSeverity::MAV_SEVERITY_WARNING as u8 {
            tracing::warn!(severity = sev, "vehicle says: {text}");
        } else {
            tracing::info!(severity = sev, "vehicle says: {text}");
        }
        self.state.last_statustext = Some(text);
    }

    fn apply_sys_status(&mut self, s: &SYS_STATUS_DATA) {
        let unhealthy =
            s.onboard_control_sensors_enabled.bits() & !s.onboard_control_sensors_health.bits();
        if unhealthy != self.state.sensors_unhealthy {
            if unhealthy != 0 {
                tracing::warn!(
                    unhealthy = format!("{:#x}", unhealthy),
                    "vehicle reports enabled sensors unhealthy (SYS_STATUS)"
                );
            } else {
                tracing::info!("vehicle reports all enabled sensors healthy again (SYS_STATUS)");
            }
            self.state.sensors_unhealthy = unhealthy;
        }
    }

    fn apply_param(&mut self, p: &PARAM_VALUE_DATA, now_s: f64) {
        let name = text_of(&p.param_id[..]);
        self.state.param_count = Some(p.param_count);
        if name == super::station::FS_GCS_TIMEOUT {
            self.set_fs_gcs_timeout_s(f64::from(p.param_value));
        }
        self.params.insert(name, (p.param_value, now_s));
    }

    fn apply_version(&mut self, v: &AUTOPILOT_VERSION_DATA) {
        self.state.flight_sw_version = Some(v.flight_sw_version);
    }

    /// STATUSTEXT to every ground station: `text` cut to 50 bytes (at a char boundary).
    pub fn send_statustext(
        &mut self,
        severity: Severity,
        text: &str,
    ) -> Result<(), AutopilotError> {
        let mut end = text.len().min(STATUSTEXT_MAX);
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        tracing::info!(?severity, "statustext: {}", &text[..end]);
        let msg = MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity: severity.mav(),
            text: text[..end].into(),
            id: 0,
            chunk_seq: 0,
        });
        if self.send(&msg)? {
            self.state.counters.statustexts_sent += 1;
        }
        Ok(())
    }

    /// NAMED_VALUE_FLOAT `name` (at most 10 bytes; QGroundControl can plot it).
    pub fn send_named_value(
        &mut self,
        name: &str,
        value: f32,
        now_s: f64,
    ) -> Result<(), AutopilotError> {
        let name = &name[..name.len().min(NAMED_VALUE_MAX)];
        let msg = MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
            time_boot_ms: (now_s.max(0.0) * 1e3) as u32,
            value,
            name: name.into(),
        });
        self.send(&msg)?;
        Ok(())
    }

    /// Let go of the sticks: RC override with every channel 0 (ArduPilot hands the channel
    /// back to the pilot's input at once instead of holding the last override for
    /// RC_OVERRIDE_TIME); with MANUAL_CONTROL there is nothing to release, so nothing
    /// is sent. The keep-alive is turned off: from now on no pilot input goes out until
    /// `set_pilot_keepalive(true)`.
    pub fn release_pilot(&mut self) -> Result<(), AutopilotError> {
        self.pilot_keepalive = false;
        if self.cfg.pilot_input != PilotInput::RcOverride {
            return Ok(());
        }
        let msg = MavMessage::RC_CHANNELS_OVERRIDE(RC_CHANNELS_OVERRIDE_DATA {
            target_system: self.state.system_id,
            target_component: self.state.component_id,
            ..Default::default()
        });
        self.send(&msg)?;
        Ok(())
    }

    /// PARAM_REQUEST_READ by name; the answer lands in [`VehicleLink::param`].
    pub fn request_param(&mut self, name: &str) -> Result<(), AutopilotError> {
        let msg = MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: -1,
            target_system: self.state.system_id,
            target_component: self.state.component_id,
            param_id: name.into(),
        });
        self.send(&msg)?;
        Ok(())
    }

    /// PARAM_REQUEST_LIST: the vehicle streams every parameter as PARAM_VALUE.
    pub fn request_param_list(&mut self) -> Result<(), AutopilotError> {
        let msg = MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
            target_system: self.state.system_id,
            target_component: self.state.component_id,
        });
        self.send(&msg)?;
        Ok(())
    }

    /// MAV_CMD_REQUEST_MESSAGE for AUTOPILOT_VERSION (148), once (no retry: the version
    /// is informative).
    pub fn request_autopilot_version(&mut self) -> Result<(), AutopilotError> {
        self.command_long(
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [148.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            0,
        )?;
        Ok(())
    }

    /// A parameter's value and the loop time it arrived, if the vehicle sent it.
    pub fn param(&self, name: &str) -> Option<(f32, f64)> {
        self.params.get(name).copied()
    }

    /// Parameters received so far.
    pub fn params_received(&self) -> usize {
        self.params.len()
    }
}
