//! The vehicle endpoint over UDP, driven through the HIL rig as markhold would drive it.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod rig_common;

use markhold_exposure::{Camera, Frame};
use markhold_hil::endpoint::mode;
use markhold_hil::{EndpointConfig, HilRig, VehicleConfig};
use mavlink::dialects::ardupilotmega::*;
use rig_common::*;

fn rig() -> (HilRig, Client) {
    let rig = HilRig::new(setup(
        VehicleConfig::default(),
        EndpointConfig::default(),
        false,
    ))
    .unwrap();
    let client = Client::new(rig.mavlink_udp_addr());
    (rig, client)
}

/// Full forward in MANUAL pitches the nose up (the thrusters sit below the CG) and, with
/// the published 1 cm between CB and CG, turns the vehicle over within a second; a 2 m
/// metacentric height keeps it level, so forward motion is what these tests see.
fn level(vehicle: VehicleConfig) -> VehicleConfig {
    VehicleConfig {
        cb_from_cg_m: Some([0.0, 0.0, -2.0]),
        ..vehicle
    }
}

fn frames(rig: &mut HilRig, n: usize) {
    let mut f = Frame::default();
    for _ in 0..n {
        rig.grab(&mut f).unwrap();
    }
}

#[test]
fn heartbeat_arm_ack_and_armed_flag() {
    let (mut rig, mut c) = rig();
    c.heartbeat();
    c.arm(true);
    rig.pump().unwrap();
    let msgs = c.drain();
    assert_eq!(
        acks(&msgs, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );
    let hb = last_heartbeat(&msgs).expect("heartbeat at t = 0");
    assert_eq!(hb.mavtype, MavType::MAV_TYPE_SUBMARINE);
    assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
    assert_eq!(hb.custom_mode, mode::MANUAL);
    // Heartbeats are sent on simulation time: the next comes 1 s later.
    frames(&mut rig, 31);
    let msgs = c.drain();
    let hb = last_heartbeat(&msgs).expect("heartbeat after 1 s");
    assert!(hb
        .base_mode
        .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED));
    assert!(msgs.iter().all(|(h, _)| h.system_id == 1));
    assert!(rig.truth().armed);
    c.arm(false);
    rig.pump().unwrap();
    assert!(!rig.truth().armed);
    assert_eq!(rig.truth().pwm, [1500; 8]);
}

#[test]
fn pilot_input_only_from_the_gcs_system_id() {
    let mut rig = HilRig::new(setup(
        level(VehicleConfig::default()),
        EndpointConfig::default(),
        false,
    ))
    .unwrap();
    let mut c = Client::new(rig.mavlink_udp_addr());
    c.arm(true);
    rig.pump().unwrap();
    // From system 1 (not the GCS id 255): silently dropped, like ArduSub.
    c.sysid = 1;
    c.rc([1500, 1500, 1500, 1500, 1900, 1500]);
    frames(&mut rig, 3);
    assert_eq!(rig.truth().pwm, [1500; 8]);
    assert_eq!(rig.endpoint_stats().pilot_inputs_dropped, 1);
    // MANUAL_CONTROL with the wrong target: dropped too.
    c.sysid = 255;
    c.send(&MavMessage::MANUAL_CONTROL(MANUAL_CONTROL_DATA {
        x: 1000,
        z: 500,
        target: 2,
        ..Default::default()
    }));
    frames(&mut rig, 3);
    assert_eq!(rig.truth().pwm, [1500; 8]);
    assert_eq!(rig.endpoint_stats().pilot_inputs_dropped, 2);
    // From the GCS: forward. Motors 1, 2 reverse, 3, 4 forward (ArduSub's factors).
    for _ in 0..30 {
        c.rc([1500, 1500, 1500, 1500, 1900, 1500]);
        frames(&mut rig, 1);
    }
    let t = rig.truth();
    assert_eq!(&t.pwm[..4], &[1100, 1100, 1900, 1900]);
    assert_eq!(&t.pwm[4..], &[1500; 4]);
    assert!(t.velocity_world_mps[0] > 0.2, "{t:?}");
}

#[test]
fn manual_control_uses_the_joystick_gain() {
    let (mut rig, mut c) = rig();
    c.arm(true);
    c.send(&MavMessage::MANUAL_CONTROL(MANUAL_CONTROL_DATA {
        x: 1000,
        z: 500,
        target: 1,
        ..Default::default()
    }));
    frames(&mut rig, 2);
    // Full stick x gain 0.5 = 1700 us on the forward channel -> motor 3 at 1700.
    let pwm = rig.truth().pwm;
    assert_eq!(pwm[2], 1700, "{pwm:?}");
    assert_eq!(pwm[0], 1300, "{pwm:?}");
}

#[test]
fn pilot_input_failsafe_disarms_after_3_s() {
    let (mut rig, mut c) = rig();
    c.arm(true);
    c.rc([1500; 6]);
    rig.pump().unwrap();
    frames(&mut rig, 85); // 2.8 s
    assert!(rig.truth().armed);
    frames(&mut rig, 10); // 3.17 s without input
    assert!(!rig.truth().armed);
    assert_eq!(rig.endpoint_stats().failsafe_pilot, 1);
}

#[test]
fn gcs_heartbeat_failsafe_disarms_after_5_s() {
    let (mut rig, mut c) = rig();
    c.heartbeat();
    c.arm(true);
    for i in 0..180 {
        c.rc([1500; 6]);
        frames(&mut rig, 1);
        let t = rig.truth();
        if i < 145 {
            assert!(t.armed, "disarmed early at {}", t.time_s);
        }
    }
    assert!(!rig.truth().armed);
    assert_eq!(rig.endpoint_stats().failsafe_gcs, 1);
    assert_eq!(rig.endpoint_stats().failsafe_pilot, 0);
}

#[test]
fn garbage_bytes_are_skipped() {
    let (mut rig, mut c) = rig();
    c.send_raw(&[0xFD, 0x09, 0x00, 0x13, 0x37, 0xFE, 0xFE, 0x55]);
    c.send_raw(b"not mavlink at all\n");
    let mut arm = vec![0xFDu8, 0x00, 0xFE, 0x01, 0x02, 0x03];
    arm.extend(c.encode(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: 1.0,
        command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        target_system: 1,
        target_component: 1,
        ..Default::default()
    })));
    arm.extend_from_slice(&[0xAA; 7]);
    c.send_raw(&arm);
    // A frame with a corrupted CRC must not be obeyed.
    let mut bad = c.encode(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: 19.0,
        param2: 2.0,
        command: MavCmd::MAV_CMD_DO_SET_MODE,
        target_system: 1,
        target_component: 1,
        ..Default::default()
    }));
    let n = bad.len();
    bad[n - 1] ^= 0xFF;
    c.send_raw(&bad);
    c.heartbeat();
    rig.pump().unwrap();
    let msgs = c.drain();
    assert_eq!(
        acks(&msgs, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );
    assert!(acks(&msgs, MavCmd::MAV_CMD_DO_SET_MODE).is_empty());
    assert!(rig.truth().armed);
    assert_eq!(rig.truth().mode, mode::MANUAL);
}

#[test]
fn message_interval_streams_on_simulation_time() {
    let (mut rig, mut c) = rig();
    for id in [30.0, 31.0, 32.0, 36.0, 65.0, 137.0] {
        c.command(MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, id, 100_000.0);
    }
    c.command(MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 999.0, 100_000.0);
    rig.pump().unwrap();
    let msgs = c.drain();
    let a = acks(&msgs, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL);
    assert_eq!(
        a.iter()
            .filter(|r| **r == MavResult::MAV_RESULT_ACCEPTED)
            .count(),
        6
    );
    assert_eq!(
        a.iter()
            .filter(|r| **r == MavResult::MAV_RESULT_DENIED)
            .count(),
        1
    );
    frames(&mut rig, 61); // 2 s
    let msgs = c.drain();
    let count = |f: fn(&MavMessage) -> bool| msgs.iter().filter(|(_, m)| f(m)).count();
    let n_att = count(|m| matches!(m, MavMessage::ATTITUDE(_)));
    assert!((19..=22).contains(&n_att), "ATTITUDE x{n_att}");
    for (name, n) in [
        (
            "ATTITUDE_QUATERNION",
            count(|m| matches!(m, MavMessage::ATTITUDE_QUATERNION(_))),
        ),
        (
            "LOCAL_POSITION_NED",
            count(|m| matches!(m, MavMessage::LOCAL_POSITION_NED(_))),
        ),
        (
            "SERVO_OUTPUT_RAW",
            count(|m| matches!(m, MavMessage::SERVO_OUTPUT_RAW(_))),
        ),
        (
            "RC_CHANNELS",
            count(|m| matches!(m, MavMessage::RC_CHANNELS(_))),
        ),
        (
            "SCALED_PRESSURE2",
            count(|m| matches!(m, MavMessage::SCALED_PRESSURE2(_))),
        ),
    ] {
        assert!((19..=22).contains(&n), "{name} x{n}");
    }
    // Depth from the pressure sensor: about 5 m of sea water.
    let p = msgs.iter().rev().find_map(|(_, m)| match m {
        MavMessage::SCALED_PRESSURE2(p) => Some(p.press_abs),
        _ => None,
    });
    let depth = (p.unwrap() as f64 - 1013.25) * 100.0 / (1025.0 * 9.81);
    assert!(
        (depth - rig.truth().t_world_vehicle.translation.z).abs() < 0.01,
        "{depth}"
    );
    // Stop one stream.
    c.command(MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 30.0, -1.0);
    rig.pump().unwrap();
    c.drain();
    frames(&mut rig, 30);
    let msgs = c.drain();
    assert!(!msgs
        .iter()
        .any(|(_, m)| matches!(m, MavMessage::ATTITUDE(_))));
    assert!(msgs
        .iter()
        .any(|(_, m)| matches!(m, MavMessage::ATTITUDE_QUATERNION(_))));
}

#[test]
fn unsupported_mode_is_denied_and_guided_needs_a_position() {
    let (mut rig, mut c) = rig();
    c.set_mode(7); // CIRCLE: not simulated
    c.set_mode(mode::GUIDED); // no vision estimate yet
    c.set_mode(mode::ALT_HOLD);
    rig.pump().unwrap();
    let msgs = c.drain();
    assert_eq!(
        acks(&msgs, MavCmd::MAV_CMD_DO_SET_MODE),
        vec![
            MavResult::MAV_RESULT_DENIED,
            MavResult::MAV_RESULT_DENIED,
            MavResult::MAV_RESULT_ACCEPTED
        ]
    );
    assert_eq!(rig.truth().mode, mode::ALT_HOLD);
}

#[test]
fn standard_frame_drives_six_motors() {
    let vehicle = level(VehicleConfig {
        frame: markhold_hil::Frame6Dof::Standard,
        ..Default::default()
    });
    let mut rig = HilRig::new(setup(vehicle, EndpointConfig::default(), false)).unwrap();
    let mut c = Client::new(rig.mavlink_udp_addr());
    c.arm(true);
    for _ in 0..45 {
        // Forward and down (throttle below neutral).
        c.rc([1500, 1500, 1300, 1500, 1800, 1500]);
        frames(&mut rig, 1);
    }
    let t = rig.truth();
    // MOT_FV_CPLNG_K (1.0) under half throttle: the rear pair (3, 4) gets at most
    // 1 - 0.5 of forward.
    assert_eq!(&t.pwm[..4], &[1200, 1200, 1700, 1700]);
    // Throttle down: both verticals push down (positive command).
    assert_eq!(&t.pwm[4..6], &[1700, 1700]);
    assert_eq!(&t.pwm[6..], &[0, 0]);
    assert!(t.velocity_world_mps[0] > 0.2, "{t:?}");
    assert!(t.velocity_world_mps[2] > 0.05, "{t:?}");
}

#[test]
fn odometry_is_a_position_source_for_guided() {
    let (mut rig, mut c) = rig();
    c.set_mode(mode::GUIDED);
    rig.pump().unwrap();
    c.send(&MavMessage::ODOMETRY(ODOMETRY_DATA {
        x: 1.0,
        y: 2.0,
        z: 3.0,
        q: [1.0, 0.0, 0.0, 0.0],
        frame_id: MavFrame::MAV_FRAME_LOCAL_FRD,
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        ..Default::default()
    }));
    c.set_mode(mode::GUIDED);
    rig.pump().unwrap();
    let msgs = c.drain();
    assert_eq!(
        acks(&msgs, MavCmd::MAV_CMD_DO_SET_MODE),
        vec![MavResult::MAV_RESULT_DENIED, MavResult::MAV_RESULT_ACCEPTED]
    );
    // LOCAL_POSITION_NED is then reported in the odometry's frame.
    c.command(MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 32.0, 100_000.0);
    frames(&mut rig, 6);
    let msgs = c.drain();
    let p = msgs
        .iter()
        .rev()
        .find_map(|(_, m)| match m {
            MavMessage::LOCAL_POSITION_NED(p) => Some([p.x, p.y, p.z]),
            _ => None,
        })
        .expect("LOCAL_POSITION_NED");
    assert!(
        (p[0] - 1.0).abs() < 0.01 && (p[1] - 2.0).abs() < 0.01,
        "{p:?}"
    );
}
