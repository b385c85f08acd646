//! The link and the station keeper against a fake ArduSub over real loopback UDP and TCP:
//! discovery, arm and mode with COMMAND_ACK (and a retry), stream requests, telemetry,
//! closed-loop station keeping, neutral on exit, heartbeat loss, TCP reconnect.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use std::time::{Duration, Instant};

use common::{FakeVehicle, Kind, STEP_S};
use markhold_autopilot::*;
use mavlink::dialects::ardupilotmega::{MavAutopilot, MavCmd, MavType};
use nalgebra::{Isometry3, Matrix6, Vector3};

const WAIT: Duration = Duration::from_secs(10);

fn cam() -> Isometry3<f64> {
    markhold_testkit::forward_camera(0.25, 0.05)
}

struct Harness {
    link: VehicleLink,
    fake: FakeVehicle,
    now: f64,
}

/// How many SET_MESSAGE_INTERVAL requests the fake vehicle has had.
fn stream_requests(r: &common::Rec) -> usize {
    r.commands
        .iter()
        .filter(|(_, c)| c.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL)
        .count()
}

/// The station keeper with the default station and controller, the camera at [`cam`].
fn default_keeper() -> StationKeeper {
    StationKeeper::new(&Default::default(), &Default::default(), cam()).unwrap()
}

impl Harness {
    /// `link` to `fake`, loop time at 0.
    fn new(link: VehicleLink, fake: FakeVehicle) -> Self {
        Self {
            link,
            fake,
            now: 0.0,
        }
    }

    /// A link listening at `url` and a fake vehicle of `kind` that connects to its address.
    fn listening(url: &str, kind: impl FnOnce(std::net::SocketAddr) -> Kind) -> Self {
        let link = VehicleLink::connect(&link_cfg(url.into())).expect("the link listens");
        let addr = link.local_addr().expect("a listening link has an address");
        Self::new(link, FakeVehicle::start(kind(addr)))
    }

    /// Ticks with loop time advancing `STEP_S` per call and a short wall sleep, until `f`
    /// holds or the wall deadline passes.
    fn tick_until(&mut self, what: &str, mut f: impl FnMut(&VehicleLink, &common::Rec) -> bool) {
        let t0 = Instant::now();
        loop {
            self.now += STEP_S;
            self.link.tick(self.now).unwrap();
            if f(&self.link, &self.fake.rec()) {
                return;
            }
            assert!(
                t0.elapsed() < WAIT,
                "timed out waiting for {what}: {:?}",
                self.link.state()
            );
            std::thread::sleep(Duration::from_millis(3));
        }
    }

    fn arm_manual(&mut self) {
        let now = self.now;
        self.tick_until("vehicle heartbeat", |l, _| l.state().discovered);
        self.link.request_mode(ArduSubMode::Manual, now).unwrap();
        self.link.request_arm(true, now).unwrap();
        self.tick_until("armed in MANUAL", |l, _| {
            let s = l.state();
            s.armed
                && s.mode == Some(ArduSubMode::Manual)
                && s.arm_command == CommandStatus::Accepted
                && s.mode_command == CommandStatus::Accepted
        });
    }

    /// The supervisor's directive now, with a frame and the marker seen this instant and
    /// the vehicle's heartbeat as the link last heard it.
    fn supervise(&self, sup: &mut Supervisor, events: &mut Vec<FailsafeEvent>) -> Directive {
        sup.update(
            &SupervisorInput {
                now_s: self.now,
                vehicle_heartbeat_s: self.link.state().last_heartbeat_s,
                last_frame_s: Some(self.now),
                marker_seen_s: Some(self.now),
                shutdown: false,
            },
            events,
        )
    }

    /// Closed loop: measurement from the fake's pose, keeper, effort on the wire, wait for
    /// the fake to apply it (one plant step per override).
    fn hold(&mut self, keeper: &mut StationKeeper, steps: usize) {
        let mut sup = Supervisor::new(&ControllerConfig::default(), self.link.config());
        let mut events = Vec::new();
        for _ in 0..steps {
            self.now += STEP_S;
            self.link.tick(self.now).unwrap();
            let t_mv = self.fake.rec().t_marker_vehicle();
            let meas = PoseMeasurement {
                stamp_s: self.now,
                t_cam_marker: (t_mv * cam()).inverse(),
                cov_cam: Matrix6::identity() * 1e-6,
            };
            let d = self.supervise(&mut sup, &mut events);
            assert_eq!(d, Directive::Command, "{events:?}");
            let e = keeper.update(self.now, Some(&meas));
            let before = self.fake.rec().steps;
            self.link.send_effort(&e, self.now).unwrap();
            let t0 = Instant::now();
            while self.fake.rec().steps <= before {
                assert!(
                    t0.elapsed() < WAIT,
                    "fake vehicle never applied the override"
                );
                std::thread::sleep(Duration::from_micros(100));
            }
            // The fake heartbeats every 10 steps (0.33 s of loop time), but its datagrams
            // or TCP bytes reach the link in wall time: on a loaded machine they can land
            // after loop time has run past the link's timeout. Let them in before time
            // moves on, so that delivery lag does not read as a silent vehicle.
            let t0 = Instant::now();
            while self.now
                - self
                    .link
                    .state()
                    .last_heartbeat_s
                    .unwrap_or(f64::NEG_INFINITY)
                > 0.5
            {
                assert!(
                    t0.elapsed() < WAIT,
                    "no vehicle message within 0.5 s of loop time: {:?}",
                    self.link.state()
                );
                std::thread::sleep(Duration::from_micros(200));
                self.link.tick(self.now).unwrap();
            }
        }
    }
}

fn link_cfg(url: String) -> LinkConfig {
    LinkConfig {
        url,
        ..Default::default()
    }
}

fn station_error(rec: &common::Rec) -> (f64, f64) {
    let p = Vector3::from(rec.pos_m) - Vector3::new(0.0, 0.0, 1.0);
    (p.norm(), rec.yaw.abs())
}

#[test]
fn udp_arm_mode_hold_station_and_neutral_on_exit() {
    let fake = FakeVehicle::start(Kind::UdpServer);
    let addr = fake.addr.unwrap();
    {
        let mut r = fake.rec();
        r.drop_arm_commands = 1;
        r.pos_m = [0.3, -0.2, 1.5];
        r.yaw = 0.3;
        r.current_m = [0.02, 0.0, 0.0];
    }
    let link = VehicleLink::connect(&link_cfg(format!("udpout:{addr}"))).unwrap();
    let mut h = Harness::new(link, fake);
    h.arm_manual();
    let mut keeper = default_keeper();
    let t_start = h.now;
    h.hold(&mut keeper, 900);
    let sim_s = h.now - t_start;

    let (pos_err, yaw_err) = station_error(&h.fake.rec());
    assert!(pos_err < 0.05, "position error {pos_err} m");
    assert!(yaw_err < 0.03, "yaw error {yaw_err} rad");

    // Neutral on exit.
    let before = h.fake.rec().rc.len();
    h.link.send_neutral(h.now).unwrap();
    let t0 = Instant::now();
    while h.fake.rec().rc.len() <= before {
        assert!(t0.elapsed() < WAIT);
        std::thread::sleep(Duration::from_millis(1));
    }

    let s = h.link.state().clone();
    let r = h.fake.rec();
    // Arm needed a retry (first COMMAND_LONG dropped); the retry counts confirmation.
    let arms: Vec<_> = r
        .commands
        .iter()
        .filter(|(_, c)| c.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM)
        .collect();
    assert!(arms.len() >= 2, "{arms:?}");
    assert_eq!(arms[0].1.confirmation, 0);
    assert_eq!(arms[1].1.confirmation, 1);
    assert!(arms
        .iter()
        .all(|(_, c)| c.param1 == 1.0 && c.target_system == 1));
    // Every command from the GCS id.
    // Every command from the vehicle's own system id (markhold is its component 191).
    assert!(r.commands.iter().all(|(sys, _)| *sys == 1));
    // Streams requested: at stream_hz (10); LOCAL_POSITION_NED too on this MANUAL link
    // (at 50 Hz at least only on an ALT_HOLD one, where the depth target is rebased on it).
    for (id, interval_us) in [
        (30.0, 1e5),
        (32.0, 1e5),
        (36.0, 1e5),
        (65.0, 1e5),
        (137.0, 1e5),
    ] {
        assert!(
            r.commands
                .iter()
                .any(|(_, c)| c.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL
                    && c.param1 == id
                    && (f64::from(c.param2) - interval_us).abs() < 1.0),
            "stream {id} not requested at {interval_us} us"
        );
    }
    // markhold's heartbeats: from the vehicle's system, component 191, an onboard
    // controller (never a ground station), autopilot invalid, ~1 Hz of loop time.
    assert!(!r.gcs_heartbeats.is_empty());
    for (sys, comp, hb) in &r.gcs_heartbeats {
        assert_eq!((*sys, *comp), (1, 191));
        assert_eq!(hb.mavtype, MavType::MAV_TYPE_ONBOARD_CONTROLLER);
        assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_INVALID);
    }
    let n_hb = r.gcs_heartbeats.len() as f64;
    assert!(
        (n_hb - h.now).abs() <= 2.0,
        "{n_hb} heartbeats in {} s",
        h.now
    );
    // Pilot input: RC overrides from 255/191 to 1/1, PWM in range, >= 20 Hz.
    assert!(r
        .rc
        .iter()
        .all(|rc| rc.sysid == 255 && rc.compid == 191 && rc.target == (1, 1)));
    assert!(r
        .rc
        .iter()
        .all(|rc| rc.ch[..6].iter().all(|p| (1100..=1900).contains(p)) && rc.ch[6..] == [0, 0]));
    assert!(
        r.rc.len() as f64 >= 20.0 * sim_s,
        "{} overrides in {sim_s} s",
        r.rc.len()
    );
    let last = r.rc.last().unwrap();
    assert_eq!(last.ch[..6], [1500; 6]);
    // The controller really commanded something (not neutral all along).
    assert!(r.rc.iter().any(|rc| rc.ch[4] > 1550));

    // Telemetry parsed.
    let d = s.depth.expect("depth");
    assert!((d.depth_m - 2.0).abs() < 0.01, "{d:?}");
    assert!((d.temperature_c - 12.34).abs() < 1e-9);
    let a = s.attitude.expect("attitude");
    assert!((a.roll - 0.01).abs() < 1e-6 && (a.pitch + 0.02).abs() < 1e-6);
    let so = s.servo_outputs.expect("servo outputs");
    assert_eq!(
        so.pwm[..8],
        [1501, 1502, 1503, 1504, 1505, 1506, 1507, 1508]
    );
    let lp = s.local_position.expect("local position");
    assert!((lp.position[2] - 2.0).abs() < 1e-6);
    assert_eq!(s.counters.sent, h.link.messages_sent());
    assert!(h.link.messages_received() > 10);
}

#[test]
fn tcpout_hold_and_reconnect() {
    let fake = FakeVehicle::start(Kind::TcpServer);
    let addr = fake.addr.unwrap();
    fake.rec().pos_m = [0.0, 0.1, 1.2];
    let link = VehicleLink::connect(&link_cfg(format!("tcpout:{addr}"))).unwrap();
    let mut h = Harness::new(link, fake);
    h.arm_manual();
    let mut keeper = default_keeper();
    h.hold(&mut keeper, 450);
    let (pos_err, _) = station_error(&h.fake.rec());
    assert!(pos_err < 0.05, "position error {pos_err} m");

    // The vehicle end drops the connection: the link notices and reconnects by itself.
    h.fake.rec().disconnect_now = true;
    h.tick_until("disconnect seen", |l, _| !l.state().transport_connected);
    h.tick_until("reconnected", |l, _| {
        l.state().transport_connected && l.state().counters.reconnects >= 1
    });
    // Pilot input flows again on the new connection.
    let before = h.fake.rec().rc.len();
    h.tick_until("pilot input after reconnect", |_, r| {
        r.rc.len() > before + 5
    });
}

#[test]
fn udp_receive_in_a_task_works_too() {
    let fake = FakeVehicle::start(Kind::UdpServer);
    let addr = fake.addr.unwrap();
    let cfg = LinkConfig {
        udp_receive_on_tick: false,
        ..link_cfg(format!("udpout:{addr}"))
    };
    let mut h = Harness::new(VehicleLink::connect(&cfg).unwrap(), fake);
    h.arm_manual();
    h.tick_until("telemetry", |l, _| l.state().depth.is_some());
}

#[test]
fn tcpin_accepts_vehicle_and_arms() {
    let mut h = Harness::listening("tcpin:127.0.0.1:0", Kind::TcpClient);
    h.arm_manual();
    assert!(h.fake.rec().armed);
}

#[test]
fn udpin_replies_to_the_vehicle_that_spoke() {
    let mut h = Harness::listening("udpin:127.0.0.1:0", Kind::UdpClient);
    let before = h.link.state().mode_changes;
    h.arm_manual();
    assert_eq!(h.fake.rec().mode, 19);
    // The fake boots in STABILIZE (0): one change to MANUAL.
    assert_eq!(h.link.state().mode_changes, before + 1);
}

#[test]
fn heartbeat_loss_stops_commanding_until_it_returns() {
    let fake = FakeVehicle::start(Kind::UdpServer);
    let addr = fake.addr.unwrap();
    let link = VehicleLink::connect(&link_cfg(format!("udpout:{addr}"))).unwrap();
    let mut h = Harness::new(link, fake);
    h.tick_until("vehicle heartbeat", |l, _| l.state().heartbeat_ok);
    let mut sup = Supervisor::new(&ControllerConfig::default(), h.link.config());
    let mut events = Vec::new();

    // Nothing commanded: the link keeps neutral pilot input going by itself.
    let rc0 = h.fake.rec().rc.len();
    let p0 = h.link.state().counters.pilot_inputs;
    for _ in 0..30 {
        h.now += STEP_S;
        h.link.tick(h.now).unwrap();
        std::thread::sleep(Duration::from_millis(2));
    }
    let sent = h.link.state().counters.pilot_inputs - p0;
    assert!(
        sent >= 20,
        "keep-alive: {sent} overrides in 1 s of loop time"
    );
    h.tick_until("keep-alive overrides", |_, r| r.rc.len() >= rc0 + 20);
    assert!(h.fake.rec().rc[rc0..]
        .iter()
        .all(|rc| rc.ch[..6] == [1500; 6]));

    // Heartbeats and telemetry stop: lost after `vehicle_timeout_s` (0.9 s) of silence.
    h.fake.rec().heartbeats_on = false;
    h.tick_until("heartbeat loss", |l, _| !l.state().heartbeat_ok);
    // Declared on the first tick more than the timeout after the last message heard
    // (loop time; how long the fake took to go quiet in wall time does not enter).
    let timeout = h.link.config().vehicle_timeout_s;
    let age = h.now - h.link.state().last_heartbeat_s.expect("heard before");
    assert!(
        age > timeout && age <= timeout + STEP_S + 1e-9,
        "lost {age} s after the last message (timeout {timeout} s)"
    );
    let d = h.supervise(&mut sup, &mut events);
    assert_eq!(d, Directive::Silent);
    assert!(events
        .iter()
        .any(|e| matches!(e, FailsafeEvent::VehicleHeartbeatLost { .. })));
    // No more pilot input while it is gone.
    std::thread::sleep(Duration::from_millis(20));
    let rc1 = h.fake.rec().rc.len();
    for _ in 0..30 {
        h.now += STEP_S;
        h.link.tick(h.now).unwrap();
    }
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(
        h.fake.rec().rc.len(),
        rc1,
        "pilot input sent to a lost vehicle"
    );

    // It comes back: streams are requested again, commanding resumes.
    let streams_before = stream_requests(&h.fake.rec());
    h.fake.rec().heartbeats_on = true;
    h.tick_until("heartbeat back", |l, _| l.state().heartbeat_ok);
    events.clear();
    let d = h.supervise(&mut sup, &mut events);
    assert_eq!(d, Directive::Command);
    assert!(events
        .iter()
        .any(|e| matches!(e, FailsafeEvent::VehicleHeartbeatRestored { .. })));
    h.tick_until("streams re-requested", |_, r| {
        stream_requests(r) >= streams_before + 5
    });
}

#[test]
fn bad_url_is_a_clear_error() {
    let e = VehicleLink::connect(&link_cfg("udpout:nowhere".into()))
        .err()
        .expect("must fail")
        .to_string();
    assert!(
        e.contains("udpout:nowhere") && e.contains("HOST:PORT"),
        "{e}"
    );
}

#[test]
fn setpoint_mode_sends_guided_targets_vision_and_origin_once() {
    let fake = FakeVehicle::start(Kind::UdpServer);
    let addr = fake.addr.unwrap();
    {
        let mut r = fake.rec();
        r.pos_m = [0.3, 0.0, 1.5];
    }
    let cfg = LinkConfig {
        url: format!("udpout:{addr}"),
        command: CommandKind::Setpoint,
        mode: LinkMode::Guided,
        origin_lat_deg: 47.5,
        origin_lon_deg: -122.25,
        origin_alt_m: -3.0,
        ..Default::default()
    };
    let link = VehicleLink::connect(&cfg).unwrap();
    let mut h = Harness::new(link, fake);
    h.tick_until("telemetry", |l, _| {
        l.state().local_position.is_some() && l.state().attitude.is_some()
    });
    // Effort commands are refused in setpoint mode, and vice versa.
    assert!(h.link.send_effort(&Effort::NEUTRAL, h.now).is_err());
    let goal = StationConfig::default().t_marker_vehicle();
    let t0 = h.now;
    let sent0 = h.link.messages_sent();
    // Marker-frame variances: x 1e-4, y 4e-4, z 9e-4 m^2; rotation 1e-6, 4e-6, 9e-6
    // rad^2 about the marker's x, y, z, with a position-rotation term (x, ry).
    let mut cov_marker =
        Matrix6::from_diagonal(&nalgebra::Vector6::new(1e-4, 4e-4, 9e-4, 1e-6, 4e-6, 9e-6));
    cov_marker[(0, 4)] = 1e-5;
    cov_marker[(4, 0)] = 1e-5;
    for _ in 0..30 {
        h.now += STEP_S;
        h.link.tick(h.now).unwrap();
        let meas = VisionPose {
            stamp_s: h.now,
            t_marker_vehicle: h.fake.rec().t_marker_vehicle(),
            cov_marker,
        };
        h.link.send_setpoint(Some(&meas), &goal, h.now).unwrap();
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(h.link.messages_sent() >= sent0 + 60);
    assert_eq!(h.link.vision_estimates(), (30, 0));
    let secs = h.now - t0;
    h.tick_until("setpoints received", |_, r| {
        r.setpoints.len() >= 30 && r.vision.len() >= 30
    });
    let r = h.fake.rec();
    // Vision estimates at >= 10 Hz of loop time.
    assert!(r.vision.len() as f64 / secs >= 10.0);
    // Vehicle at marker (0.3, 0, 1.5) facing it: L frame (-1.5, 0.3, 0), level, yaw 0.
    let v = r.vision.last().unwrap();
    assert!(
        (v.x + 1.5).abs() < 1e-5 && (v.y - 0.3).abs() < 1e-5 && v.z.abs() < 1e-5,
        "{v:?}"
    );
    assert!(v.yaw.abs() < 1e-5 && v.roll.abs() < 1e-5 && v.pitch.abs() < 1e-5);
    // The covariance on L's axes (x_L = -z_m, y_L = x_m, z_L = -y_m; level, so roll,
    // pitch and yaw are the rotation about x_L, y_L, z_L), upper triangle row-major:
    // var x_L = 9e-4, var y_L = 1e-4, var z_L = 4e-4, var roll = 9e-6, var pitch = 1e-6,
    // var yaw = 4e-6; cov(y_L, yaw) = cov(x_m, -ry_m) = -1e-5 at row 1, column 5.
    let c = v.covariance;
    let close = |a: f32, b: f64| (f64::from(a) - b).abs() < 1e-9;
    assert!(
        close(c[0], 9e-4) && close(c[6], 1e-4) && close(c[11], 4e-4),
        "{c:?}"
    );
    assert!(
        close(c[15], 9e-6) && close(c[18], 1e-6) && close(c[20], 4e-6),
        "{c:?}"
    );
    assert!(close(c[10], -1e-5), "{c:?}");
    let others: f32 = [1, 2, 3, 4, 5, 7, 8, 9, 12, 13, 14, 16, 17, 19]
        .iter()
        .map(|&i| c[i].abs())
        .sum();
    assert!(others < 1e-12, "{c:?}");
    // Target = EKF position (-1.5, 0.3, 2.0) + remaining offset (0.5, -0.3, 0).
    let sp = r.setpoints.last().unwrap();
    assert!(
        (sp.x + 1.0).abs() < 1e-5 && sp.y.abs() < 1e-5 && (sp.z - 2.0).abs() < 1e-5,
        "{sp:?}"
    );
    assert!(sp.yaw.abs() < 1e-5);
    assert_eq!(
        sp.coordinate_frame,
        mavlink::dialects::ardupilotmega::MavFrame::MAV_FRAME_LOCAL_NED
    );
    assert_eq!(
        sp.type_mask.bits() & 0b111,
        0,
        "position must not be ignored"
    );
    assert_ne!(sp.type_mask.bits() & 0b111_111_000, 0);
    assert_eq!((sp.target_system, sp.target_component), (1, 1));
    // Origin exactly once, from the vehicle's system id.
    assert_eq!(r.origins, vec![(1, 475_000_000, -1_222_500_000, -3000)]);
    let (n_vision, n_targets) = (r.vision.len(), r.setpoints.len());
    let last_sp = (sp.x, sp.y, sp.z, sp.yaw);
    drop(r);

    // No measurement: no estimate, the last target again. A measurement without a
    // usable covariance (a zero variance): no estimate either, and counted.
    h.now += STEP_S;
    h.link.tick(h.now).unwrap();
    h.link.send_setpoint(None, &goal, h.now).unwrap();
    let flat = VisionPose {
        stamp_s: h.now,
        t_marker_vehicle: goal,
        cov_marker: Matrix6::zeros(),
    };
    h.link.send_setpoint(Some(&flat), &goal, h.now).unwrap();
    assert_eq!(h.link.vision_estimates(), (30, 1));
    h.tick_until("the repeated target", |_, r| r.setpoints.len() > n_targets);
    std::thread::sleep(Duration::from_millis(20));
    h.link.tick(h.now).unwrap();
    let r = h.fake.rec();
    assert_eq!(r.vision.len(), n_vision);
    assert_eq!(r.setpoints.len(), n_targets + 1);
    let sp = r.setpoints.last().unwrap();
    assert_eq!((sp.x, sp.y, sp.z, sp.yaw), last_sp);
}

#[test]
fn udp_datagrams_sent_before_a_tick_are_applied_in_that_tick() {
    // The HIL determinism property: no sleeping, no polling; what the vehicle wrote to
    // loopback before `tick` is in the state after it.
    use mavlink::dialects::ardupilotmega::*;
    let vehicle = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let cfg = link_cfg(format!("udpout:{}", vehicle.local_addr().unwrap()));
    let mut link = VehicleLink::connect(&cfg).unwrap();
    let to = ("127.0.0.1", link.local_addr().unwrap().port());
    let h = markhold_testkit::VEHICLE_HEADER;
    for step in 0..50u32 {
        let mut buf = Vec::new();
        let hb =
            markhold_testkit::sub_heartbeat(19, MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED);
        let att = MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: step,
            yaw: step as f32 * 0.01,
            ..Default::default()
        });
        mavlink::write_v2_msg(&mut buf, h, &hb).unwrap();
        mavlink::write_v2_msg(&mut buf, h, &att).unwrap();
        vehicle.send_to(&buf, to).unwrap();
        link.tick(f64::from(step) * STEP_S).unwrap();
        let s = link.state();
        assert!(s.discovered);
        assert_eq!(s.attitude.unwrap().time_boot_ms, step);
        assert_eq!(s.heartbeats, u64::from(step) + 1);
    }
}

/// An ALT_HOLD link asks for LOCAL_POSITION_NED at 50 Hz at least (its depth target is
/// rebased on it each frame) and for the other streams at `stream_hz`.
#[test]
fn an_alt_hold_link_asks_for_the_local_position_at_50_hz() {
    let fake = FakeVehicle::start(Kind::UdpServer);
    let addr = fake.addr.unwrap();
    let cfg = LinkConfig {
        mode: LinkMode::AltHold,
        ..link_cfg(format!("udpout:{addr}"))
    };
    let link = VehicleLink::connect(&cfg).unwrap();
    let mut h = Harness::new(link, fake);
    let interval = |r: &common::Rec, id: f32| {
        r.commands
            .iter()
            .find(|(_, c)| c.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL && c.param1 == id)
            .map(|(_, c)| f64::from(c.param2))
    };
    h.tick_until("stream requests", |_, r| {
        interval(r, 32.0).is_some() && interval(r, 30.0).is_some()
    });
    let r = h.fake.rec();
    assert!(
        (interval(&r, 32.0).unwrap() - 2e4).abs() < 1.0,
        "{:?}",
        r.commands
    );
    assert!(
        (interval(&r, 30.0).unwrap() - 1e5).abs() < 1.0,
        "{:?}",
        r.commands
    );
}
