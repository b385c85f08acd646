//! The vehicle endpoint's security: a UDP sender becomes the peer only with an acceptable
//! MAVLink frame (garbage from another port does not take the telemetry away), and
//! MAVLink 2 signing (everything sent signed, unsigned and wrongly signed input dropped).
//! Loopback only, every receive bounded.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use markhold_hil::{EndpointConfig, HilError, Vehicle, VehicleConfig, VehicleEndpoint};
use mavlink::dialects::ardupilotmega::*;
use mavlink::{MAVLinkMessageRaw, MavHeader, MavlinkReader, SigningConfig, SigningData};
use nalgebra::Isometry3;

/// A GCS on its own port that signs with `key` (or not).
struct Gcs {
    sock: UdpSocket,
    to: SocketAddr,
    seq: u8,
    signing: Option<SigningData>,
}

impl Gcs {
    fn new(to: SocketAddr, key: Option<[u8; 32]>) -> Self {
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        Self {
            sock,
            to,
            seq: 0,
            signing: key.map(|k| SigningData::from_config(SigningConfig::new(k, 1, true, false))),
        }
    }

    fn send(&mut self, msg: &MavMessage) {
        let h = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: self.seq,
        };
        self.seq = self.seq.wrapping_add(1);
        let mut out = Vec::new();
        mavlink::write_v2_msg_signed(&mut out, h, msg, self.signing.as_ref()).unwrap();
        self.sock.send_to(&out, self.to).unwrap();
    }

    fn arm(&mut self) {
        self.send(&MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: 1.0,
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        }));
    }

    /// Raw frames waiting now (until a 20 ms silence, at most 2 s).
    fn drain(&mut self) -> Vec<MAVLinkMessageRaw> {
        let mut out = Vec::new();
        let mut buf = [0u8; 65536];
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            match self.sock.recv_from(&mut buf) {
                Ok((n, _)) => {
                    let mut r = MavlinkReader::new(&buf[..n]);
                    while let Ok(m) = r.read_any_raw_message::<MavMessage>() {
                        out.push(m);
                    }
                }
                Err(_) => break,
            }
        }
        out
    }
}

fn is_ack(m: &MAVLinkMessageRaw) -> bool {
    m.message_id() == 77
}

/// The endpoint with a vehicle at rest, pumped like the rig pumps it.
struct Rig {
    ep: VehicleEndpoint,
    vehicle: Vehicle,
}

impl Rig {
    fn pump(&mut self) -> Result<usize, HilError> {
        let n = self.ep.poll(self.vehicle.time_s())?;
        self.ep.tick(&self.vehicle.state(), &[1500; 8])?;
        Ok(n)
    }
    fn mavlink_udp_addr(&self) -> SocketAddr {
        self.ep.udp_addr()
    }
    fn endpoint_peer(&self) -> Option<SocketAddr> {
        self.ep.udp_peer()
    }
    fn endpoint_stats(&self) -> markhold_hil::endpoint::EndpointStats {
        self.ep.stats()
    }
}

fn try_rig(endpoint: EndpointConfig) -> Result<Rig, HilError> {
    Ok(Rig {
        ep: VehicleEndpoint::bind(&endpoint)?,
        vehicle: Vehicle::new(&VehicleConfig::default(), &Isometry3::identity(), 1)?,
    })
}

fn rig(endpoint: EndpointConfig) -> Rig {
    try_rig(endpoint).unwrap()
}

fn key_file(name: &str, key: [u8; 32]) -> PathBuf {
    let p = std::env::temp_dir().join(format!("hil-ep-sec-{}-{name}", std::process::id()));
    std::fs::write(&p, key).unwrap();
    p
}

#[test]
fn garbage_from_another_port_does_not_become_the_peer() {
    let mut rig = rig(EndpointConfig::default());
    let mut gcs = Gcs::new(rig.mavlink_udp_addr(), None);
    gcs.arm();
    rig.pump().unwrap();
    assert!(gcs.drain().iter().any(is_ack));
    let peer = rig.endpoint_peer();
    assert_eq!(peer, Some(gcs.sock.local_addr().unwrap()));
    // Another port: empty, junk, a truncated frame, a frame with a bad CRC.
    let junk = UdpSocket::bind("127.0.0.1:0").unwrap();
    junk.set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let mut good = Vec::new();
    mavlink::write_v2_msg_signed(
        &mut good,
        MavHeader::default(),
        &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
        None,
    )
    .unwrap();
    let mut bad_crc = good.clone();
    let last = bad_crc.len() - 1;
    bad_crc[last] ^= 0xFF;
    let datagrams: [&[u8]; 5] = [
        &[],
        &[0xFD, 9, 0],
        &good[..good.len() - 3],
        &bad_crc,
        &[0x55; 64],
    ];
    let before = rig.endpoint_stats().rejected_datagrams;
    for d in datagrams {
        junk.send_to(d, rig.mavlink_udp_addr()).unwrap();
    }
    gcs.arm();
    rig.pump().unwrap();
    assert_eq!(rig.endpoint_peer(), peer, "garbage took the peer");
    assert_eq!(rig.endpoint_stats().rejected_datagrams - before, 5);
    assert!(gcs.drain().iter().any(is_ack));
    let mut buf = [0u8; 512];
    assert!(
        junk.recv_from(&mut buf).is_err(),
        "the junk sender got replies"
    );
    // A valid frame from a new port does make it the peer (udpin semantics).
    junk.send_to(&good, rig.mavlink_udp_addr()).unwrap();
    rig.pump().unwrap();
    assert_eq!(rig.endpoint_peer(), Some(junk.local_addr().unwrap()));
}

#[test]
fn signing_vehicle_signs_and_drops_unsigned_and_wrongly_signed_input() {
    let key = [0x21; 32];
    let path = key_file("key", key);
    let mut rig = rig(EndpointConfig {
        signing_key_file: Some(path.clone()),
        ..Default::default()
    });
    let verify = SigningData::from_config(SigningConfig::new(key, 0, false, false));
    // Unsigned: dropped, no peer, no reply.
    let mut plain = Gcs::new(rig.mavlink_udp_addr(), None);
    plain.arm();
    rig.pump().unwrap();
    assert!(plain.drain().is_empty());
    assert_eq!(rig.endpoint_peer(), None);
    // Signed with another key: dropped too.
    let mut wrong = Gcs::new(rig.mavlink_udp_addr(), Some([0x22; 32]));
    wrong.arm();
    rig.pump().unwrap();
    assert!(wrong.drain().is_empty());
    let st = rig.endpoint_stats();
    assert_eq!(
        (st.rejected_unsigned, st.rejected_signature),
        (1, 1),
        "{st:?}"
    );
    assert_eq!(st.messages, 0);
    assert!(!rig.ep.armed());
    // Signed with the key: obeyed, and every reply is signed with it.
    let mut good = Gcs::new(rig.mavlink_udp_addr(), Some(key));
    good.arm();
    rig.pump().unwrap();
    let replies = good.drain();
    assert!(replies.iter().any(is_ack));
    assert!(rig.ep.armed());
    for m in &replies {
        match m {
            MAVLinkMessageRaw::V2(r) => assert!(verify.verify_signature(r), "unsigned reply"),
            MAVLinkMessageRaw::V1(_) => panic!("MAVLink 1 reply"),
        }
    }
    // An unsigned RC override from the GCS id after that: not pilot input.
    plain.send(&MavMessage::RC_CHANNELS_OVERRIDE(
        RC_CHANNELS_OVERRIDE_DATA {
            chan5_raw: 1900,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        },
    ));
    rig.pump().unwrap();
    let st = rig.endpoint_stats();
    assert_eq!((st.pilot_inputs, st.rejected_unsigned), (0, 2), "{st:?}");
    assert_eq!(rig.endpoint_peer(), Some(good.sock.local_addr().unwrap()));
    // A replayed signed frame (same bytes again) is dropped.
    let mut one = Vec::new();
    let h = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 9,
    };
    mavlink::write_v2_msg_signed(
        &mut one,
        h,
        &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
        good.signing.as_ref(),
    )
    .unwrap();
    good.sock.send_to(&one, rig.mavlink_udp_addr()).unwrap();
    good.sock.send_to(&one, rig.mavlink_udp_addr()).unwrap();
    rig.pump().unwrap();
    assert_eq!(rig.endpoint_stats().rejected_signature, 2);
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn accept_unsigned_lets_both_in_and_bad_key_files_are_named() {
    let key = [0x31; 32];
    let path = key_file("open", key);
    let mut rig = rig(EndpointConfig {
        signing_key_file: Some(path.clone()),
        signing_accept_unsigned: true,
        ..Default::default()
    });
    let mut plain = Gcs::new(rig.mavlink_udp_addr(), None);
    plain.arm();
    rig.pump().unwrap();
    assert!(plain.drain().iter().any(is_ack));
    std::fs::write(&path, b"not a key").unwrap();
    let e = try_rig(EndpointConfig {
        signing_key_file: Some(path.clone()),
        ..Default::default()
    })
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("endpoint.signing_key_file"), "{e}");
    std::fs::remove_file(&path).unwrap();
}
