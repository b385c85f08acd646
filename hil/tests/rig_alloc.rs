//! The per-frame path (MAVLink, autopilot, mixer, render) allocates nothing after the
//! first frames, counted with a global allocator per thread. rapier3d 0.36 itself
//! allocates twice per physics step (its modified-body list and the island solver's
//! cursors, seen with a backtrace): the rig must add nothing to what the bare vehicle
//! allocates over the same number of steps.

mod rig_common;

use markhold_exposure::{Camera, Frame};
use markhold_hil::{EndpointConfig, HilRig, VehicleConfig};
use markhold_testkit::thread_allocs as allocs;
use rig_common::*;

#[global_allocator]
static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;

#[test]
fn grabbing_frames_allocates_nothing_after_warm_up() {
    let vehicle = VehicleConfig {
        gust_std_mps: [0.05, 0.05, 0.0],
        ..Default::default()
    };
    let mut rig = HilRig::new(setup(vehicle, EndpointConfig::default(), true)).unwrap();
    let mut c = Client::new(rig.mavlink_udp_addr());
    let mut f = Frame::default();
    c.heartbeat();
    c.arm(true);
    c.set_mode(markhold_hil::endpoint::mode::STABILIZE);
    for id in [30.0, 31.0, 32.0, 36.0, 65.0, 137.0] {
        c.command(
            mavlink::dialects::ardupilotmega::MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            id,
            50_000.0,
        );
    }
    // Messages for all the frames, encoded up front (the client's allocations are not
    // the rig's).
    let rc: Vec<Vec<u8>> = (0..90u16)
        .map(|k| {
            c.encode(
                &mavlink::dialects::ardupilotmega::MavMessage::RC_CHANNELS_OVERRIDE(
                    mavlink::dialects::ardupilotmega::RC_CHANNELS_OVERRIDE_DATA {
                        chan1_raw: 1500,
                        chan2_raw: 1500,
                        chan3_raw: 1500 + k % 5 * 20,
                        chan4_raw: 1450,
                        chan5_raw: 1700,
                        chan6_raw: 1500,
                        target_system: 1,
                        target_component: 1,
                        ..Default::default()
                    },
                ),
            )
        })
        .collect();
    for m in &rc[..30] {
        c.send_raw(m);
        rig.grab(&mut f).unwrap();
    }
    let before = allocs();
    for m in &rc[30..] {
        c.send_raw(m);
        rig.grab(&mut f).unwrap();
    }
    let n = allocs() - before;
    assert!(rig.truth().armed);
    assert_eq!(rig.truth().lockstep_timeouts, 0);
    // The same number of physics steps on a bare vehicle.
    let steps = ((90.0f64 * 400.0 / 30.0).round() - (30.0f64 * 400.0 / 30.0).round()) as usize;
    let mut v = markhold_hil::Vehicle::new(
        &VehicleConfig::default(),
        &nalgebra::Isometry3::translation(0.0, 0.0, 5.0),
        1,
    )
    .unwrap();
    for _ in 0..100 {
        v.step(&[1500; 8]);
    }
    let before = allocs();
    for _ in 0..steps {
        v.step(&[1600; 8]);
    }
    let physics = allocs() - before;
    assert!(
        physics <= 2 * steps as u64,
        "rapier: {physics} allocations in {steps} steps"
    );
    assert_eq!(
        n, physics,
        "rig: {n} allocations in 60 frames, physics alone {physics}"
    );
}
