//! The vehicle endpoint over TCP on loopback, with garbage on the stream.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod rig_common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use markhold_exposure::{Camera, Frame};
use markhold_hil::{EndpointConfig, HilRig, VehicleConfig};
use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavHeader, MavlinkReader, MavlinkVersion};
use rig_common::*;

fn encode(msg: &MavMessage, seq: u8) -> Vec<u8> {
    let mut out = Vec::new();
    let h = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: seq,
    };
    mavlink::write_versioned_msg(&mut out, MavlinkVersion::V2, h, msg).unwrap();
    out
}

#[test]
fn tcp_client_arms_and_drives_and_gets_acks_through_garbage() {
    let endpoint = EndpointConfig {
        tcp_enabled: true,
        ..Default::default()
    };
    let mut rig = HilRig::new(setup(VehicleConfig::default(), endpoint, false)).unwrap();
    let addr = rig.mavlink_tcp_addr().expect("tcp enabled");
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    // Without it, Nagle's algorithm holds the small writes back for tens of ms.
    s.set_nodelay(true).unwrap();
    // Garbage, then an arm command split across two writes, then garbage again.
    let arm = encode(
        &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: 1.0,
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        }),
        0,
    );
    s.write_all(b"\xfd\x05junk\x00").unwrap();
    s.write_all(&arm[..7]).unwrap();
    // Accept the connection and read the first half.
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        rig.pump().unwrap();
        std::thread::sleep(Duration::from_millis(5));
        if !rig.truth().armed {
            s.write_all(&arm[7..]).unwrap();
            s.write_all(&[0x55; 9]).unwrap();
            break;
        }
    }
    let mut f = Frame::default();
    let deadline = Instant::now() + Duration::from_secs(5);
    while !rig.truth().armed && Instant::now() < deadline {
        rig.pump().unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(rig.truth().armed);
    for k in 0..32u8 {
        let rc = encode(
            &MavMessage::RC_CHANNELS_OVERRIDE(RC_CHANNELS_OVERRIDE_DATA {
                chan1_raw: 1500,
                chan2_raw: 1500,
                chan3_raw: 1500,
                chan4_raw: 1500,
                chan5_raw: 1800,
                chan6_raw: 1500,
                target_system: 1,
                target_component: 1,
                ..Default::default()
            }),
            k + 1,
        );
        if k == 0 {
            // A bogus MAVLink 1 start claiming a 253-byte frame: the stream decoder waits
            // for it, finds a bad CRC, and resynchronises on the next real frame.
            s.write_all(b"\xfe").unwrap();
        }
        s.write_all(&rc).unwrap();
        rig.grab(&mut f).unwrap();
    }
    assert!(
        rig.truth().velocity_world_mps[0] > 0.1,
        "{:?} {:?}",
        rig.truth(),
        rig.endpoint_stats()
    );
    // Replies arrive on the stream: an accepted ACK and armed heartbeats.
    let mut bytes = Vec::new();
    let mut buf = [0u8; 4096];
    let deadline = Instant::now() + Duration::from_secs(2);
    while Instant::now() < deadline {
        match s.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => bytes.extend_from_slice(&buf[..n]),
            Err(_) => break,
        }
    }
    let mut r = MavlinkReader::new(&bytes[..]);
    let mut msgs = Vec::new();
    while let Ok(m) = r.read_any_message::<MavMessage>() {
        msgs.push(m);
    }
    assert_eq!(
        acks(&msgs, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );
    let hb = last_heartbeat(&msgs).expect("heartbeat");
    assert!(hb
        .base_mode
        .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED));
}
