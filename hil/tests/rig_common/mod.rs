//! Shared helpers of the vehicle-side integration tests: a small HIL setup and a
//! MAVLink client written against the published message set (loopback only, every
//! receive bounded by a deadline).

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
#![allow(dead_code)]

use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use markhold_exposure::ResponseModel;
use markhold_hil::camera::CameraModel;
use markhold_hil::scene::{LightingConfig, MarkerSpec, WaterConfig};
use markhold_hil::{EndpointConfig, HilSetup, VehicleConfig, VehicleMotion};
use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavHeader, MavlinkReader, MavlinkVersion};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

pub const DEPTH_M: f64 = 5.0;

/// Marker at NED (0, 0, depth) facing south (docs/frames.md).
pub fn t_world_marker() -> Isometry3<f64> {
    let r = Matrix3::from_columns(&[
        nalgebra::Vector3::new(0.0, 1.0, 0.0),
        nalgebra::Vector3::new(0.0, 0.0, -1.0),
        nalgebra::Vector3::new(-1.0, 0.0, 0.0),
    ]);
    Isometry3::from_parts(
        Translation3::new(0.0, 0.0, DEPTH_M),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
    )
}

/// Forward-looking camera: x_c = y_b, y_c = z_b, z_c = x_b.
pub fn t_vehicle_cam() -> Isometry3<f64> {
    markhold_testkit::forward_camera(0.2, 0.0)
}

pub fn small_camera() -> CameraModel {
    // The Blackfly S model (no distortion, 30 fps, 20 us to 30 ms, one frame of delay)
    // at 160x120.
    CameraModel {
        width: 160,
        height: 120,
        fx: 100.0,
        fy: 100.0,
        cx: 79.5,
        cy: 59.5,
        ..CameraModel::blackfly_s(ResponseModel::default())
    }
}

/// A 6x6 marker (4x4 code inside a black border).
pub fn marker() -> MarkerSpec {
    let mut white = vec![false; 36];
    for r in 1..5 {
        for c in 1..5 {
            white[r * 6 + c] = (r * 7 + c * 3) % 3 == 0;
        }
    }
    MarkerSpec {
        cells: 6,
        white,
        size_m: 0.15,
        plate_margin_m: 0.03,
    }
}

/// The world these tests fly: the simulated ArduSub's own response, so pilot input acts
/// as it arrives (no vision loop's frame-to-thrust delay in front of it; a test that wants
/// one sets `vehicle.delay` on the result).
pub fn setup(vehicle: VehicleConfig, endpoint: EndpointConfig, lock_step: bool) -> HilSetup {
    HilSetup {
        vehicle: VehicleConfig {
            delay: markhold_hil::DelayConfig::NONE,
            ..vehicle
        },
        endpoint,
        water: WaterConfig::default(),
        lighting: LightingConfig::default(),
        camera: small_camera(),
        t_vehicle_cam: t_vehicle_cam(),
        marker: marker(),
        t_world_marker: t_world_marker(),
        map: Vec::new(),
        t_world_vehicle_start: Isometry3::translation(-1.0, 0.0, DEPTH_M),
        motion: VehicleMotion::Free,
        seed: 42,
        lock_step,
    }
}

/// A GCS-side MAVLink client over UDP (like `udpout:` in markhold).
pub struct Client {
    pub sock: UdpSocket,
    pub to: SocketAddr,
    pub sysid: u8,
    seq: u8,
    buf: Vec<u8>,
}

impl Client {
    pub fn new(to: SocketAddr) -> Self {
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        Self {
            sock,
            to,
            sysid: 255,
            seq: 0,
            buf: vec![0; 65536],
        }
    }

    pub fn encode(&mut self, msg: &MavMessage) -> Vec<u8> {
        let mut out = Vec::new();
        let h = MavHeader {
            system_id: self.sysid as u32,
            component_id: 190,
            sequence: self.seq,
        };
        self.seq = self.seq.wrapping_add(1);
        mavlink::write_versioned_msg(&mut out, MavlinkVersion::V2, h, msg).unwrap();
        out
    }

    pub fn send(&mut self, msg: &MavMessage) {
        let b = self.encode(msg);
        self.sock.send_to(&b, self.to).unwrap();
    }

    pub fn send_raw(&self, bytes: &[u8]) {
        self.sock.send_to(bytes, self.to).unwrap();
    }

    /// Every message waiting now (reads until a 20 ms silence).
    pub fn drain(&mut self) -> Vec<(MavHeader, MavMessage)> {
        let mut out = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            match self.sock.recv_from(&mut self.buf) {
                Ok((n, _)) => {
                    let mut r = MavlinkReader::new(&self.buf[..n]);
                    while let Ok(m) = r.read_any_message::<MavMessage>() {
                        out.push(m);
                    }
                }
                Err(_) => break,
            }
        }
        out
    }

    pub fn heartbeat(&mut self) {
        self.send(&MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_GCS,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        }));
    }

    pub fn command(&mut self, command: MavCmd, p1: f32, p2: f32) {
        self.send(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: p1,
            param2: p2,
            command,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        }));
    }

    pub fn arm(&mut self, arm: bool) {
        self.command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            if arm { 1.0 } else { 0.0 },
            0.0,
        );
    }

    pub fn set_mode(&mut self, mode: u32) {
        self.command(MavCmd::MAV_CMD_DO_SET_MODE, 1.0, mode as f32);
    }

    /// RC override: [pitch, roll, throttle, yaw, forward, lateral] PWM.
    pub fn rc(&mut self, ch: [u16; 6]) {
        let [chan1_raw, chan2_raw, chan3_raw, chan4_raw, chan5_raw, chan6_raw] = ch;
        self.send(&MavMessage::RC_CHANNELS_OVERRIDE(
            RC_CHANNELS_OVERRIDE_DATA {
                chan1_raw,
                chan2_raw,
                chan3_raw,
                chan4_raw,
                chan5_raw,
                chan6_raw,
                chan7_raw: u16::MAX,
                chan8_raw: u16::MAX,
                target_system: 1,
                target_component: 1,
                ..Default::default()
            },
        ));
    }
}

pub fn acks(msgs: &[(MavHeader, MavMessage)], cmd: MavCmd) -> Vec<MavResult> {
    msgs.iter()
        .filter_map(|(_, m)| match m {
            MavMessage::COMMAND_ACK(a) if a.command == cmd => Some(a.result),
            _ => None,
        })
        .collect()
}

pub fn last_heartbeat(msgs: &[(MavHeader, MavMessage)]) -> Option<HEARTBEAT_DATA> {
    msgs.iter().rev().find_map(|(_, m)| match m {
        MavMessage::HEARTBEAT(h) => Some(h.clone()),
        _ => None,
    })
}
