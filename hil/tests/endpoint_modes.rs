//! The simulated autopilot's flight modes, flown through MAVLink like a client would.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod rig_common;

use markhold_exposure::{Camera, Frame};
use markhold_hil::endpoint::mode;
use markhold_hil::{EndpointConfig, HilRig, VehicleConfig};
use mavlink::dialects::ardupilotmega::*;
use rig_common::*;

struct Run {
    rig: HilRig,
    c: Client,
    f: Frame,
}

impl Run {
    fn new(vehicle: VehicleConfig) -> Self {
        let rig = HilRig::new(setup(vehicle, EndpointConfig::default(), false)).unwrap();
        let c = Client::new(rig.mavlink_udp_addr());
        Self {
            rig,
            c,
            f: Frame::default(),
        }
    }

    /// `frames` frames with the same RC sticks, and (if `vision`) a vision position
    /// estimate from the truth each frame, like markhold's marker pose would give.
    fn fly(&mut self, frames: usize, rc: [u16; 6], vision: bool) {
        for _ in 0..frames {
            if self.rig.frames().is_multiple_of(30) {
                self.c.heartbeat();
            }
            self.c.rc(rc);
            if vision {
                self.send_vision();
            }
            self.rig.grab(&mut self.f).unwrap();
        }
    }

    fn send_vision(&mut self) {
        let t = self.rig.truth();
        let p = t.t_world_vehicle.translation.vector;
        let (roll, pitch, yaw) = t.t_world_vehicle.rotation.euler_angles();
        self.c.send(&MavMessage::VISION_POSITION_ESTIMATE(
            VISION_POSITION_ESTIMATE_DATA {
                usec: (t.time_s * 1e6) as u64,
                x: p.x as f32,
                y: p.y as f32,
                z: p.z as f32,
                roll: roll as f32,
                pitch: pitch as f32,
                yaw: yaw as f32,
                ..Default::default()
            },
        ));
    }

    fn mode(&mut self, m: u32) -> MavResult {
        self.c.set_mode(m);
        self.rig.pump().unwrap();
        let msgs = self.c.drain();
        acks(&msgs, MavCmd::MAV_CMD_DO_SET_MODE)[0]
    }

    fn arm(&mut self) {
        self.c.heartbeat();
        self.c.arm(true);
        self.rig.pump().unwrap();
        self.c.drain();
        assert!(self.rig.truth().armed);
    }

    fn rpy(&self) -> (f64, f64, f64) {
        self.rig.truth().t_world_vehicle.rotation.euler_angles()
    }

    fn pos(&self) -> nalgebra::Vector3<f64> {
        self.rig.truth().t_world_vehicle.translation.vector
    }
}

const NEUTRAL: [u16; 6] = [1500; 6];

#[test]
fn stabilize_holds_the_commanded_roll_and_levels_on_release() {
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    assert_eq!(r.mode(mode::STABILIZE), MavResult::MAV_RESULT_ACCEPTED);
    // Full right roll stick: 30 degrees of roll, held (not a rate).
    r.fly(150, [1500, 1900, 1500, 1500, 1500, 1500], false);
    let (roll, _, _) = r.rpy();
    assert!(
        (roll.to_degrees() - 30.0).abs() < 6.0,
        "roll {}",
        roll.to_degrees()
    );
    r.fly(60, [1500, 1900, 1500, 1500, 1500, 1500], false);
    let (roll2, _, _) = r.rpy();
    assert!((roll2 - roll).abs() < 0.05, "{roll} -> {roll2}");
    r.fly(150, NEUTRAL, false);
    let (roll, pitch, _) = r.rpy();
    assert!(
        roll.abs().to_degrees() < 3.0 && pitch.abs().to_degrees() < 3.0,
        "{roll} {pitch}"
    );
}

#[test]
fn stabilize_holds_heading_and_yaw_stick_turns() {
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    r.mode(mode::STABILIZE);
    r.fly(60, [1500, 1500, 1500, 1500, 1800, 1500], false); // forward: heading held
    let (_, _, yaw) = r.rpy();
    assert!(yaw.abs().to_degrees() < 3.0, "yaw {}", yaw.to_degrees());
    r.fly(60, [1500, 1500, 1500, 1900, 1500, 1500], false); // 2 s of full right yaw
    let (_, _, yaw) = r.rpy();
    assert!(yaw.to_degrees() > 60.0, "yaw {}", yaw.to_degrees());
}

#[test]
fn alt_hold_keeps_a_buoyant_vehicle_at_depth_and_throttle_climbs() {
    // In MANUAL the (positively buoyant) vehicle rises.
    let mut m = Run::new(VehicleConfig::default());
    m.arm();
    m.fly(300, NEUTRAL, false);
    let rise = DEPTH_M - m.pos().z;
    assert!(rise > 0.2, "manual rise {rise}");

    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_ACCEPTED);
    r.fly(300, NEUTRAL, false);
    let err = r.pos().z - DEPTH_M;
    assert!(err.abs() < 0.05, "alt hold depth error {err}");
    // Throttle down (below 1500) descends, then the new depth is held.
    r.fly(60, [1500, 1500, 1200, 1500, 1500, 1500], false);
    let z1 = r.pos().z;
    assert!(z1 > DEPTH_M + 0.3, "descended to {z1}");
    r.fly(150, NEUTRAL, false);
    assert!((r.pos().z - z1).abs() < 0.15, "{z1} -> {}", r.pos().z);
}

#[test]
fn guided_flies_to_a_position_target_in_the_vision_frame() {
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    r.fly(5, NEUTRAL, true);
    assert_eq!(r.mode(mode::GUIDED), MavResult::MAV_RESULT_ACCEPTED);
    let start = r.pos();
    let target = start + nalgebra::Vector3::new(0.5, -0.3, 0.2);
    for _ in 0..450 {
        r.c.send(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(
            SET_POSITION_TARGET_LOCAL_NED_DATA {
                x: target.x as f32,
                y: target.y as f32,
                z: target.z as f32,
                yaw: 0.3,
                type_mask: PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
                target_system: 1,
                target_component: 1,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            },
        ));
        r.fly(1, NEUTRAL, true);
    }
    let err = r.pos() - target;
    assert!(err.norm() < 0.08, "guided error {err:?}");
    let (_, _, yaw) = r.rpy();
    assert!((yaw - 0.3).abs() < 0.05, "yaw {yaw}");
    assert!(r.rig.endpoint_stats().guided_targets >= 450);
}

#[test]
fn poshold_resists_a_current_that_carries_a_manual_vehicle_away() {
    let current = VehicleConfig {
        current_mps: [0.0, 0.15, 0.0],
        ..Default::default()
    };
    let mut m = Run::new(current.clone());
    m.arm();
    m.fly(300, NEUTRAL, true);
    let drift = m.pos().y;
    assert!(drift > 0.8, "manual drift {drift}");

    let mut r = Run::new(current);
    r.arm();
    r.fly(2, NEUTRAL, true);
    assert_eq!(r.mode(mode::POSHOLD), MavResult::MAV_RESULT_ACCEPTED);
    r.fly(300, NEUTRAL, true);
    let p = r.pos();
    assert!(
        p.y.abs() < 0.15 && (p.x + 1.0).abs() < 0.15,
        "poshold drifted to {p:?}"
    );
    assert!((p.z - DEPTH_M).abs() < 0.1, "{p:?}");
}

/// ArduSub's ALT_HOLD (`GCS_MAVLINK_Sub::handleMessage`, ArduSub/GCS_Mavlink.cpp):
/// SET_POSITION_TARGET_GLOBAL_INT with none of the x, y, z ignore bits set sets the
/// depth target (`pos_control.set_alt_target(alt * 100)`, metres up from the origin of
/// LOCAL_POSITION_NED); with any one of them set the position is ignored; outside
/// ALT_HOLD (here STABILIZE) nothing is taken.
#[test]
fn alt_hold_takes_a_depth_target_from_set_position_target_global_int() {
    let target = |alt: f32, mask: PositionTargetTypemask| {
        MavMessage::SET_POSITION_TARGET_GLOBAL_INT(SET_POSITION_TARGET_GLOBAL_INT_DATA {
            alt,
            type_mask: mask,
            target_system: 1,
            target_component: 1,
            coordinate_frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            ..Default::default()
        })
    };
    let position_only = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE;
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    // STABILIZE: not taken.
    assert_eq!(r.mode(mode::STABILIZE), MavResult::MAV_RESULT_ACCEPTED);
    r.c.send(&target(-(DEPTH_M as f32 + 0.5), position_only));
    r.fly(1, NEUTRAL, false);
    assert_eq!(r.rig.endpoint_stats().depth_targets, 0);
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_ACCEPTED);
    r.fly(60, NEUTRAL, false);
    let held = r.pos().z;
    // x and y ignored (only z meant): ArduSub ignores the whole position.
    r.c.send(&target(
        -(DEPTH_M as f32 + 0.5),
        position_only
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
            | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE,
    ));
    r.fly(120, NEUTRAL, false);
    assert_eq!(r.rig.endpoint_stats().depth_targets, 0);
    assert!((r.pos().z - held).abs() < 0.03, "{held} -> {}", r.pos().z);
    // Position used: the vehicle goes to the depth and holds it.
    r.c.send(&target(-(DEPTH_M as f32 + 0.5), position_only));
    r.fly(240, NEUTRAL, false);
    let z = r.pos().z;
    assert!((z - (DEPTH_M + 0.5)).abs() < 0.06, "depth {z}");
    assert_eq!(r.rig.endpoint_stats().depth_targets, 1);
    // Every stick input (1 + 60 + 120 + 240 frames) and the three targets.
    assert_eq!(r.rig.endpoint_stats().lockstep_inputs, 421 + 3);
}

#[test]
fn guided_velocity_targets_then_hold_after_the_target_times_out() {
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    r.fly(5, NEUTRAL, true);
    assert_eq!(r.mode(mode::GUIDED), MavResult::MAV_RESULT_ACCEPTED);
    let start = r.pos();
    // 0.2 m/s east in the body frame of a vehicle facing north = sway right.
    for _ in 0..150 {
        r.c.send(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(
            SET_POSITION_TARGET_LOCAL_NED_DATA {
                vy: 0.2,
                type_mask: PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE
                    | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
                target_system: 1,
                target_component: 1,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
                ..Default::default()
            },
        ));
        r.fly(1, NEUTRAL, true);
    }
    let v = r.rig.truth().velocity_world_mps;
    assert!((v[1] - 0.2).abs() < 0.04 && v[0].abs() < 0.04, "{v:?}");
    let moved = r.pos() - start;
    assert!((0.7..1.1).contains(&moved.y), "{moved:?}");
    assert!(moved.z.abs() < 0.05, "depth held: {moved:?}");
    // No more targets: after the 3 s timeout the vehicle holds where it is.
    r.fly(120, NEUTRAL, true);
    let p1 = r.pos();
    r.fly(90, NEUTRAL, true);
    assert!((r.pos() - p1).norm() < 0.05, "{p1:?} -> {:?}", r.pos());
}
