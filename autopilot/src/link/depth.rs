//! ALT_HOLD's depth target: the keeper's heave through the autopilot's own depth
//! controller instead of the throttle stick.
//!
//! ArduSub (`GCS_MAVLINK_Sub::handleMessage`, MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
//! ArduSub/GCS_Mavlink.cpp) takes SET_POSITION_TARGET_GLOBAL_INT in GUIDED, AUTO's guided
//! leg and ALT_HOLD. In ALT_HOLD, when none of the three position-ignore bits of
//! `type_mask` is set, it calls `pos_control.set_alt_target(alt * 100)` and stops there:
//! `alt` is the altitude target in metres above the EKF origin (the frame of
//! LOCAL_POSITION_NED, up), the frame and latitude / longitude are not read. ALT_HOLD
//! then holds that target while the throttle stick is centred (`Sub::control_depth`,
//! control_althold.cpp).

use mavlink::dialects::ardupilotmega::{
    MavFrame, MavMessage, PositionTargetTypemask, SET_POSITION_TARGET_GLOBAL_INT_DATA,
};

use super::VehicleLink;
use crate::error::AutopilotError;
use crate::types::ArduSubMode;

/// Position used, everything else (velocity, acceleration, yaw, yaw rate) ignored.
pub fn depth_target_mask() -> PositionTargetTypemask {
    PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
}

impl VehicleLink {
    /// The depth ALT_HOLD is to hold, metres down in the vehicle's local frame (the
    /// frame of LOCAL_POSITION_NED's z), written now as SET_POSITION_TARGET_GLOBAL_INT.
    /// Sent only while the vehicle reports ALT_HOLD (elsewhere ArduSub reads the message
    /// as a GUIDED target) and for a finite depth; returns whether it was written.
    pub fn send_depth_target(&mut self, down_m: f64, now_s: f64) -> Result<bool, AutopilotError> {
        if self.state.mode != Some(ArduSubMode::AltHold) || !down_m.is_finite() {
            return Ok(false);
        }
        let msg = MavMessage::SET_POSITION_TARGET_GLOBAL_INT(SET_POSITION_TARGET_GLOBAL_INT_DATA {
            time_boot_ms: (now_s.max(0.0) * 1e3) as u32,
            alt: (-down_m) as f32,
            type_mask: depth_target_mask(),
            target_system: self.state.system_id,
            target_component: self.state.component_id,
            // Not read in ALT_HOLD; the altitude is relative to the EKF origin.
            coordinate_frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            ..Default::default()
        });
        let sent = self.send(&msg)?;
        if sent {
            self.depth_targets += 1;
        }
        Ok(sent)
    }

    /// Depth targets written (ALT_HOLD).
    pub fn depth_targets_sent(&self) -> u64 {
        self.depth_targets
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use std::net::UdpSocket;
    use std::time::Duration;

    use super::*;
    use crate::config::LinkConfig;

    fn link_to(socket: &UdpSocket) -> VehicleLink {
        let port = socket.local_addr().unwrap().port();
        VehicleLink::connect(&LinkConfig {
            url: format!("udpout:127.0.0.1:{port}"),
            ..Default::default()
        })
        .unwrap()
    }

    #[test]
    fn alt_hold_gets_the_depth_as_an_altitude_target_with_the_position_used() {
        let vehicle = UdpSocket::bind("127.0.0.1:0").unwrap();
        vehicle
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        let mut link = link_to(&vehicle);
        // Not in ALT_HOLD (unknown, MANUAL, GUIDED): ArduSub would read it otherwise.
        for mode in [None, Some(ArduSubMode::Manual), Some(ArduSubMode::Guided)] {
            link.state.mode = mode;
            assert!(!link.send_depth_target(3.25, 1.0).unwrap(), "{mode:?}");
        }
        link.state.mode = Some(ArduSubMode::AltHold);
        assert!(!link.send_depth_target(f64::NAN, 1.0).unwrap());
        assert_eq!(link.depth_targets_sent(), 0);
        assert_eq!(link.state().counters.sent, 0);
        assert!(link.send_depth_target(3.25, 1.0).unwrap());
        assert_eq!(link.depth_targets_sent(), 1);
        let mut buf = [0u8; 300];
        let n = vehicle.recv(&mut buf).unwrap();
        let mut r = mavlink::MavlinkReader::new(&buf[..n]);
        let (h, msg) = r.read_any_message_signed::<MavMessage>(None).unwrap();
        let MavMessage::SET_POSITION_TARGET_GLOBAL_INT(t) = msg else {
            panic!("{msg:?}");
        };
        // Metres up from the EKF origin: 3.25 m down.
        assert_eq!(t.alt, -3.25);
        // ArduSub ignores the whole position if any one of x, y, z is marked ignored.
        let pos_ignore = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE;
        assert!(!t.type_mask.intersects(pos_ignore), "{:?}", t.type_mask);
        assert_eq!((t.target_system, t.target_component), (1, 1));
        // From markhold's component of the vehicle's system, not as the pilot.
        let cfg = LinkConfig::default();
        assert_eq!(
            (h.system_id, h.component_id),
            (u32::from(cfg.vehicle_system_id), cfg.component_id)
        );
    }
}
