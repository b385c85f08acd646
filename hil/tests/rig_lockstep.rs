//! HilRig: lock-step with the client, determinism, and the compare experiments' motions.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod rig_common;

use std::time::Duration;

use markhold_exposure::{Camera, Frame};
use markhold_hil::{EndpointConfig, HilRig, VehicleConfig, VehicleMotion};
use rig_common::*;

/// Frames are taken on the physics step nearest to k / fps (400 Hz physics, 30 fps).
fn sim_time_of_frame(k: u64) -> f64 {
    (k as f64 * 400.0 / 30.0).round() / 400.0
}

#[test]
fn lock_step_waits_for_input_after_the_first_and_counts_timeouts() {
    let mut rig = HilRig::new(setup(
        VehicleConfig::default(),
        EndpointConfig::default(),
        true,
    ))
    .unwrap();
    rig.set_lockstep_wait(Duration::from_millis(30));
    let mut c = Client::new(rig.mavlink_udp_addr());
    let mut f = Frame::default();
    // Before any pilot input: free running.
    for _ in 0..3 {
        rig.grab(&mut f).unwrap();
    }
    assert_eq!(rig.truth().lockstep_timeouts, 0);
    c.arm(true);
    c.rc([1500; 6]);
    rig.grab(&mut f).unwrap();
    assert_eq!(rig.truth().lockstep_timeouts, 0);
    // No input for the next two frames: each waits and times out, time still advances.
    rig.grab(&mut f).unwrap();
    rig.grab(&mut f).unwrap();
    assert_eq!(rig.truth().lockstep_timeouts, 2);
    assert!((rig.truth().time_s - sim_time_of_frame(5)).abs() < 1e-9);
    // Input arriving during the wait releases the frame without a timeout.
    rig.set_lockstep_wait(Duration::from_secs(5));
    let addr = rig.mavlink_udp_addr();
    let sender = std::thread::spawn(move || {
        let mut c2 = Client::new(addr);
        std::thread::sleep(Duration::from_millis(50));
        c2.rc([1500, 1500, 1500, 1500, 1700, 1500]);
    });
    rig.grab(&mut f).unwrap();
    sender.join().unwrap();
    assert_eq!(rig.truth().lockstep_timeouts, 2);
    assert_eq!(rig.endpoint_stats().pilot_inputs, 2);
    // The input of this frame is applied to the physics of this frame.
    c.rc([1500, 1500, 1500, 1500, 1700, 1500]);
    rig.grab(&mut f).unwrap();
    assert_eq!(rig.truth().lockstep_timeouts, 2);
    assert!(rig.truth().pwm[2] > 1500, "{:?}", rig.truth().pwm);
}

/// A scripted run: arm, then a stick pattern, one RC override per frame (lock-step).
fn scripted_run(seed: u64) -> (Vec<[f64; 7]>, u64) {
    let vehicle = VehicleConfig {
        current_mps: [0.05, 0.02, 0.0],
        gust_std_mps: [0.05, 0.05, 0.01],
        // Surge in MANUAL pitches the nose up (thrusters below the CG) and, with the
        // published 1 cm between CB and CG, tips the vehicle over; a 2 m metacentric
        // height keeps it level so that the script moves it forward.
        cb_from_cg_m: Some([0.0, 0.0, -2.0]),
        ..Default::default()
    };
    let mut s = setup(vehicle, EndpointConfig::default(), true);
    s.seed = seed;
    let mut rig = HilRig::new(s).unwrap();
    rig.set_lockstep_wait(Duration::from_secs(2));
    let mut c = Client::new(rig.mavlink_udp_addr());
    let mut f = Frame::default();
    c.arm(true);
    let mut traj = Vec::new();
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for k in 0..60u16 {
        let fwd = 1500 + (k % 20) * 15;
        let yaw = 1500 - (k % 7) * 20;
        c.rc([1500, 1500, 1550, yaw, fwd, 1450]);
        rig.grab(&mut f).unwrap();
        let t = rig.truth();
        let p = t.t_world_vehicle.translation.vector;
        let q = t.t_world_vehicle.rotation.quaternion();
        traj.push([t.time_s, p.x, p.y, p.z, q.i, q.j, q.k]);
        for &b in &f.data {
            hash = (hash ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
    assert_eq!(rig.truth().lockstep_timeouts, 0);
    (traj, hash)
}

#[test]
fn same_seed_gives_a_bit_identical_run() {
    let a = scripted_run(7);
    let b = scripted_run(7);
    let c = scripted_run(8);
    assert_eq!(a.0.len(), 60);
    assert!(a
        .0
        .iter()
        .zip(&b.0)
        .all(|(x, y)| x.iter().zip(y).all(|(u, v)| u.to_bits() == v.to_bits())));
    assert_eq!(a.1, b.1, "rendered frames differ");
    assert_ne!(a.0, c.0, "a different seed should change the gusts");
    // The script really moved the vehicle.
    let (first, last) = (a.0[0], a.0[59]);
    assert!((last[1] - first[1]).abs() > 0.05, "{first:?} -> {last:?}");
}

#[test]
fn fixed_and_kinematic_motion_for_compare_experiments() {
    let mut s = setup(VehicleConfig::default(), EndpointConfig::default(), false);
    s.motion = VehicleMotion::Fixed;
    let mut rig = HilRig::new(s).unwrap();
    let mut c = Client::new(rig.mavlink_udp_addr());
    c.arm(true);
    let mut f = Frame::default();
    for _ in 0..30 {
        c.rc([1500, 1500, 1900, 1500, 1900, 1500]);
        rig.grab(&mut f).unwrap();
    }
    let t = rig.truth();
    assert_eq!(
        t.t_world_vehicle,
        nalgebra::Isometry3::translation(-1.0, 0.0, DEPTH_M)
    );
    // The marker is 1 m ahead of the vehicle, 0.8 m ahead of the camera, on its axis.
    let m = t.t_cam_marker.translation.vector;
    assert!(
        (m - nalgebra::Vector3::new(0.0, 0.0, 0.8)).norm() < 1e-9,
        "{m:?}"
    );
    assert_eq!((f.width, f.height), (160, 120));
    assert_eq!(f.meta.seq, 29);
    assert!((f.meta.stamp_s - sim_time_of_frame(29)).abs() < 1e-9);
    assert!((f.meta.stamp_s - 29.0 / 30.0).abs() <= 0.5 / 400.0);

    let mut s = setup(VehicleConfig::default(), EndpointConfig::default(), false);
    s.motion = VehicleMotion::Kinematic {
        velocity_world_mps: [0.0, 0.3, 0.0],
    };
    let mut rig = HilRig::new(s).unwrap();
    for _ in 0..31 {
        rig.grab(&mut f).unwrap();
    }
    let t = rig.truth();
    let p = t.t_world_vehicle.translation.vector;
    assert!(
        (p - nalgebra::Vector3::new(-1.0, 0.3, DEPTH_M)).norm() < 1e-4,
        "{p:?}"
    );
    assert!(
        (t.velocity_world_mps[1] - 0.3).abs() < 1e-6,
        "{:?}",
        t.velocity_world_mps
    );
}
