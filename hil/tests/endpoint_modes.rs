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
        Self::with(vehicle, EndpointConfig::default())
    }

    fn with(vehicle: VehicleConfig, endpoint: EndpointConfig) -> Self {
        let rig = HilRig::new(setup(vehicle, endpoint, false)).unwrap();
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

    /// `frames` frames without pilot input (the GCS heartbeat goes on).
    fn fly_silent(&mut self, frames: usize) {
        for _ in 0..frames {
            if self.rig.frames().is_multiple_of(30) {
                self.c.heartbeat();
            }
            self.rig.grab(&mut self.f).unwrap();
        }
    }

    /// Mean of `f` over `frames` frames flown with `rc`.
    fn mean_over(
        &mut self,
        frames: usize,
        rc: [u16; 6],
        vision: bool,
        f: impl Fn(&Self) -> f64,
    ) -> f64 {
        let mut sum = 0.0;
        for _ in 0..frames {
            self.fly(1, rc, vision);
            sum += f(self);
        }
        sum / frames as f64
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

    fn yaw_rate_dps(&self) -> f64 {
        self.rig.vehicle_state().angvel_body_rps.z.to_degrees()
    }

    /// Velocity in the heading frame: forward, right, down, m/s.
    fn body_velocity(&self) -> nalgebra::Vector3<f64> {
        let s = self.rig.vehicle_state();
        let (_, _, yaw) = s.t_world_vehicle.rotation.euler_angles();
        nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, yaw)
            .inverse_transform_vector(&s.velocity_world_mps)
    }
}

/// A vehicle whose ArduSub parameters are `text` (a MAVProxy .parm file), written to a
/// file of its own; `None` = ArduSub 4.5's defaults.
fn vehicle_with_params(name: &str, text: Option<&str>) -> VehicleConfig {
    let params_file = text.map(|t| {
        let dir = std::env::temp_dir().join(format!("markhold-modes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join(format!("{name}.parm"));
        std::fs::write(&f, t).unwrap();
        f
    });
    VehicleConfig {
        params_file,
        ..Default::default()
    }
}

fn within_5_percent(got: f64, want: f64, what: &str) {
    assert!(
        (got - want).abs() <= 0.05 * want.abs(),
        "{what}: {got:.4} against ArduSub's {want:.4}"
    );
}

const NEUTRAL: [u16; 6] = [1500; 6];

/// Attitude.cpp `get_pilot_desired_lean_angles`: full roll stick asks for ANGLE_MAX
/// (4500 cdeg), held as an angle, in STABILIZE and ALT_HOLD; a parameter file with
/// ANGLE_MAX halved halves it; released, the vehicle levels.
#[test]
fn full_stick_leans_to_angle_max_and_a_parameter_file_changes_it() {
    for (name, params, want) in [
        ("angle-default", None, 45.0),
        ("angle-half", Some("ANGLE_MAX 2250\n"), 22.5),
    ] {
        for m in [mode::STABILIZE, mode::ALT_HOLD] {
            let mut r = Run::new(vehicle_with_params(name, params));
            r.arm();
            assert_eq!(r.mode(m), MavResult::MAV_RESULT_ACCEPTED);
            let right = [1500, 1900, 1500, 1500, 1500, 1500];
            r.fly(120, right, false);
            let roll = r.mean_over(30, right, false, |r| r.rpy().0.to_degrees());
            within_5_percent(roll, want, &format!("{} roll", mode::name(m)));
            if params.is_none() {
                r.fly(300, NEUTRAL, false);
                let (roll, pitch, _) = r.rpy();
                assert!(roll.to_degrees().abs() < 3.0 && pitch.to_degrees().abs() < 3.0);
                // Pitch stick: the Heavy pitches to ANGLE_MAX as well.
                let nose_up = [1900, 1500, 1500, 1500, 1500, 1500];
                r.fly(120, nose_up, false);
                let pitch = r.mean_over(30, nose_up, false, |r| r.rpy().1.to_degrees());
                within_5_percent(pitch, want, "pitch");
            }
        }
    }
}

/// Attitude.cpp `get_pilot_desired_yaw_rate`: full yaw stick (control_in 4500) x
/// ACRO_YAW_P (3.375) = 151.9 deg/s in STABILIZE, ALT_HOLD and POSHOLD; ACRO_YAW_P halved
/// in the vehicle's parameter file halves it.
#[test]
fn yaw_rate_at_full_stick_is_stick_times_acro_yaw_p_and_a_parameter_file_changes_it() {
    for (name, params, want) in [
        ("yaw-default", None, 4500.0 * 3.375 / 100.0),
        (
            "yaw-half",
            Some("ACRO_YAW_P 1.6875\n"),
            4500.0 * 1.6875 / 100.0,
        ),
    ] {
        for m in [mode::STABILIZE, mode::ALT_HOLD, mode::POSHOLD] {
            let mut r = Run::new(vehicle_with_params(name, params));
            r.arm();
            r.fly(2, NEUTRAL, true);
            assert_eq!(r.mode(m), MavResult::MAV_RESULT_ACCEPTED);
            let yaw_right = [1500, 1500, 1500, 1900, 1500, 1500];
            r.fly(45, yaw_right, true);
            let rate = r.mean_over(30, yaw_right, true, Run::yaw_rate_dps);
            within_5_percent(rate, want, &format!("{} yaw rate", mode::name(m)));
        }
    }
}

/// mode_stabilize.cpp: released, the yaw rate target goes to zero and 250 ms later the
/// heading where the vehicle then is becomes the one held; no bounce back to where the
/// stick was released.
#[test]
fn heading_is_recaptured_250_ms_after_the_yaw_stick_is_released() {
    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    r.mode(mode::STABILIZE);
    r.fly(20, [1500, 1500, 1500, 1900, 1500, 1500], false);
    let released = r.rpy().2;
    // 8 frames at 30 fps = 267 ms: the heading just after the window.
    r.fly(8, NEUTRAL, false);
    let captured = r.rpy().2;
    r.fly(120, NEUTRAL, false);
    let held = r.rpy().2;
    let d = |a: f64, b: f64| {
        let x = (a - b).to_degrees();
        (x + 180.0).rem_euclid(360.0) - 180.0
    };
    assert!(
        d(captured, released) > 2.0,
        "it coasted on: {released} -> {captured}"
    );
    assert!(
        d(held, captured).abs() < 3.0,
        "held {held}, captured {captured}"
    );
}

/// Attitude.cpp `get_pilot_desired_climb_rate`: full throttle stick is PILOT_SPEED_UP
/// (PILOT_SPEED_DN = 0: the same down) in ALT_HOLD; the file's value halved halves it.
/// (4.5's default 500 cm/s is more than a BlueROV2 climbs: the files ask for less.)
#[test]
fn alt_hold_climb_rate_at_full_stick_is_pilot_speed_up_from_the_parameter_file() {
    for (name, params, want) in [
        ("climb-50", "PILOT_SPEED_UP 50\n", 0.5),
        ("climb-25", "PILOT_SPEED_UP 25\n", 0.25),
    ] {
        let mut r = Run::new(vehicle_with_params(name, Some(params)));
        r.arm();
        assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_ACCEPTED);
        r.fly(30, NEUTRAL, false);
        let down = [1500, 1500, 1100, 1500, 1500, 1500];
        r.fly(150, down, false);
        let vz = r.mean_over(90, down, false, |r| r.rig.truth().velocity_world_mps[2]);
        within_5_percent(vz, want, "descent rate");
        let up = [1500, 1500, 1900, 1500, 1500, 1500];
        r.fly(150, up, false);
        let vz = r.mean_over(90, up, false, |r| r.rig.truth().velocity_world_mps[2]);
        within_5_percent(-vz, want, "climb rate");
        // Released: the depth is held.
        r.fly(300, NEUTRAL, false);
        let z = r.pos().z;
        r.fly(60, NEUTRAL, false);
        assert!((r.pos().z - z).abs() < 0.05, "{z} -> {}", r.pos().z);
    }
}

/// mode_poshold.cpp / Attitude.cpp `get_pilot_desired_horizontal_rate`: forward stick is a
/// velocity target of PILOT_SPEED x (norm_input - THR_DZ x 2 / 800 x gain): full stick
/// 0.875 PILOT_SPEED; released, the position is held.
#[test]
fn poshold_forward_stick_is_a_velocity_target_of_pilot_speed() {
    for (name, params, want) in [
        ("speed-40", "PILOT_SPEED 40\n", 0.35),
        ("speed-20", "PILOT_SPEED 20\n", 0.175),
    ] {
        let mut r = Run::new(vehicle_with_params(name, Some(params)));
        r.arm();
        r.fly(2, NEUTRAL, true);
        assert_eq!(r.mode(mode::POSHOLD), MavResult::MAV_RESULT_ACCEPTED);
        let ahead = [1500, 1500, 1500, 1500, 1900, 1500];
        r.fly(120, ahead, true);
        let v = r.mean_over(30, ahead, true, |r| r.body_velocity().x);
        within_5_percent(v, want, "forward speed");
        r.fly(90, NEUTRAL, true);
        let p = r.pos();
        r.fly(60, NEUTRAL, true);
        assert!((r.pos() - p).norm() < 0.05, "{p:?} -> {:?}", r.pos());
    }
}

/// mode_surface.cpp: SURFACE climbs at WPNAV_SPEED_UP (within PILOT_SPEED_UP) and, at
/// the surface (SURFACE_DEPTH), hands over to ALT_HOLD.
#[test]
fn surface_climbs_at_wpnav_speed_up_then_holds_depth_in_alt_hold() {
    let mut r = Run::new(vehicle_with_params("surface", Some("WPNAV_SPEED_UP 60\n")));
    r.arm();
    assert_eq!(r.mode(mode::SURFACE), MavResult::MAV_RESULT_ACCEPTED);
    r.fly(120, NEUTRAL, false);
    let vz = r.mean_over(30, NEUTRAL, false, |r| r.rig.truth().velocity_world_mps[2]);
    within_5_percent(-vz, 0.6, "surfacing rate");
    r.fly(300, NEUTRAL, false);
    assert_eq!(r.rig.truth().mode, mode::ALT_HOLD);
    assert!(r.pos().z < 0.3, "depth {}", r.pos().z);
}

/// ModeAlthold::init / ModeSurface::init need a depth sensor (`control_check_barometer`);
/// `Sub::failsafe_sensors_check` switches the depth modes to MANUAL when it fails.
#[test]
fn depth_modes_need_a_depth_sensor_and_fall_back_to_manual_when_it_fails() {
    let no_sensor = EndpointConfig {
        depth_sensor: false,
        ..Default::default()
    };
    let mut r = Run::with(VehicleConfig::default(), no_sensor);
    r.arm();
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_DENIED);
    assert_eq!(r.mode(mode::SURFACE), MavResult::MAV_RESULT_DENIED);
    assert_eq!(r.mode(mode::STABILIZE), MavResult::MAV_RESULT_ACCEPTED);

    let mut r = Run::new(VehicleConfig::default());
    r.arm();
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_ACCEPTED);
    r.fly(10, NEUTRAL, false);
    r.rig.set_depth_sensor_healthy(false);
    r.fly(2, NEUTRAL, false);
    assert_eq!(r.rig.truth().mode, mode::MANUAL);
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_DENIED);
    r.rig.set_depth_sensor_healthy(true);
    r.fly(2, NEUTRAL, false);
    assert_eq!(r.mode(mode::ALT_HOLD), MavResult::MAV_RESULT_ACCEPTED);
}

/// libraries/RC_Channel: an override older than RC_OVERRIDE_TIME no longer applies, and
/// with no RC receiver the channel keeps its last value; ArduSub's pilot-input failsafe
/// (FS_PILOT_TIMEOUT 3 s) then centres the controls and disarms.
#[test]
fn an_expired_rc_override_keeps_driving_until_the_pilot_input_failsafe() {
    let mut r = Run::new(vehicle_with_params(
        "override",
        Some("RC_OVERRIDE_TIME 1\n"),
    ));
    r.arm();
    let ahead = [1500, 1500, 1500, 1500, 1700, 1500];
    r.fly(30, ahead, false);
    // 2 s without input: past RC_OVERRIDE_TIME, the forward channel still drives.
    r.fly_silent(60);
    let t = r.rig.truth();
    assert!(t.armed);
    assert!(t.pwm[..4].iter().all(|&p| p != 1500), "{:?}", t.pwm);
    assert!(r.body_velocity().x > 0.2, "{:?}", r.body_velocity());
    // Past FS_PILOT_TIMEOUT: neutral and disarmed.
    r.fly_silent(40);
    let t = r.rig.truth();
    assert!(!t.armed);
    assert!(t.pwm[..8].iter().all(|&p| p == 1500), "{:?}", t.pwm);
}

/// ALT_HOLD against the (positively buoyant) vehicle: depth held; MANUAL lets it rise.
#[test]
fn alt_hold_keeps_a_buoyant_vehicle_at_depth() {
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

/// Pilot input acts the frame-to-thrust delay (`[vehicle.delay]`) after it arrives: with
/// 100 ms the thrusters first move in the frame that spans arrival + 100 ms; with none, in
/// the frame right after it.
#[test]
fn pilot_input_acts_the_frame_to_thrust_delay_after_it_arrives() {
    let first_move = |delay_ms: f64| {
        let mut s = setup(VehicleConfig::default(), EndpointConfig::default(), false);
        s.vehicle.delay = s.vehicle.delay.scaled_to(delay_ms);
        let rig = HilRig::new(s).unwrap();
        let c = Client::new(rig.mavlink_udp_addr());
        let mut r = Run {
            rig,
            c,
            f: Frame::default(),
        };
        r.arm();
        r.fly(3, [1500; 6], false);
        let sent_at = r.rig.truth().time_s;
        for _ in 0..20 {
            r.fly(1, [1500, 1500, 1500, 1500, 1800, 1500], false);
            let t = r.rig.truth();
            if t.pwm[..4].iter().any(|&p| p != 1500) {
                return t.time_s - sent_at;
            }
        }
        panic!("the thrusters never moved with {delay_ms} ms");
    };
    let frame = 1.0 / 30.0;
    let none = first_move(0.0);
    assert!(none <= frame + 1e-6, "{none}");
    let late = first_move(100.0);
    assert!(
        (0.1..=0.1 + frame + 1e-6).contains(&late),
        "first thrust {late} s after the input"
    );
}
