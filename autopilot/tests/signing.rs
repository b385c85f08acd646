//! MAVLink 2 signing with a key file: outgoing frames carry a valid signature (checked with
//! rust-mavlink's verifier and the same key), unsigned or wrongly signed incoming frames are
//! ignored, signed ones are accepted.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::UdpSocket;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use markhold_autopilot::*;
use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavlinkReader, SigningConfig, SigningData};

const KEY: [u8; 32] = [
    0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77, 0x88, 0x99, 0xaa, 0xbb, 0xcc, 0xdd, 0xee, 0xff, 0x00,
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09, 0x0a, 0x0b, 0x0c, 0x0d, 0x0e, 0x0f, 0x10,
];

fn key_file(name: &str, contents: &[u8]) -> PathBuf {
    let p = std::env::temp_dir().join(format!("markhold-{}-{name}", std::process::id()));
    std::fs::write(&p, contents).unwrap();
    p
}

fn hex(k: &[u8]) -> String {
    k.iter().map(|b| format!("{b:02x}")).collect()
}

/// The vehicle sends `frames` to `to`; the link then ticks 30 ms of loop time on (after
/// 10 ms of wall time).
fn send_then_tick(
    vehicle: &std::net::UdpSocket,
    to: (&str, u16),
    frames: &[Vec<u8>],
    link: &mut VehicleLink,
    now: &mut f64,
) {
    for f in frames {
        vehicle.send_to(f, to).unwrap();
    }
    *now += 0.03;
    link.tick(*now).unwrap();
    std::thread::sleep(Duration::from_millis(10));
}

fn vehicle_heartbeat(signing: Option<&SigningData>) -> Vec<u8> {
    let msg = markhold_testkit::sub_heartbeat(19, MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED);
    let h = markhold_testkit::VEHICLE_HEADER;
    let mut v = Vec::new();
    mavlink::write_v2_msg_signed(&mut v, h, &msg, signing).unwrap();
    v
}

#[test]
fn signed_link_signs_and_checks() {
    let path = key_file("key.hex", format!("{}\n", hex(&KEY)).as_bytes());
    let vehicle = UdpSocket::bind("127.0.0.1:0").unwrap();
    vehicle
        .set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    let cfg = LinkConfig {
        url: format!("udpout:{}", vehicle.local_addr().unwrap()),
        signing_key_file: Some(path.clone()),
        signing_link_id: 7,
        ..Default::default()
    };
    let mut link = VehicleLink::connect(&cfg).unwrap();
    link.tick(0.0).unwrap();

    // Outgoing: signed, and the signature checks out with the key only.
    let mut buf = [0u8; 512];
    let (n, from) = vehicle
        .recv_from(&mut buf)
        .expect("heartbeat from the link");
    assert_eq!(buf[0], 0xFD, "MAVLink 2");
    assert_eq!(buf[2] & 0x01, 0x01, "incompat flag SIGNED");
    let good = SigningData::from_config(SigningConfig::new(KEY, 0, false, false));
    let mut r = MavlinkReader::new(&buf[..n]);
    let (h, m) = r
        .read_any_message_signed::<MavMessage>(Some(&good))
        .expect("valid signature");
    // markhold's heartbeat, as a component of the vehicle (system 1 until discovered).
    assert_eq!((h.system_id, h.component_id), (1, 191));
    assert!(matches!(m, MavMessage::HEARTBEAT(_)));
    let mut wrong_key = KEY;
    wrong_key[0] ^= 1;
    let bad = SigningData::from_config(SigningConfig::new(wrong_key, 0, false, false));
    let mut r = MavlinkReader::new(&buf[..n]);
    assert!(r.read_any_message_signed::<MavMessage>(Some(&bad)).is_err());
    // The link id from the config is in the signature block (13 bytes before the end).
    assert_eq!(buf[n - 13], 7);

    // Incoming: unsigned and wrongly signed heartbeats are ignored.
    let to = ("127.0.0.1", from.port());
    let signer_bad = SigningData::from_config(SigningConfig::new(wrong_key, 0, true, false));
    let signer = SigningData::from_config(SigningConfig::new(KEY, 0, true, false));
    let mut now = 0.0;
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_millis(300) {
        let unsigned_and_bad = [
            vehicle_heartbeat(None),
            vehicle_heartbeat(Some(&signer_bad)),
        ];
        send_then_tick(&vehicle, to, &unsigned_and_bad, &mut link, &mut now);
    }
    assert!(
        !link.state().discovered,
        "accepted an unsigned or badly signed frame"
    );
    // Counted, and the wrong key is what the diagnosis names.
    let c = link.state().counters;
    assert!(
        c.rejected_unsigned > 0 && c.rejected_bad_signature > 0,
        "{c:?}"
    );
    let why = link.signing_diagnosis().expect("a diagnosis");
    assert!(why.contains("another key"), "{why}");

    // A correctly signed heartbeat is accepted.
    let t0 = Instant::now();
    while !link.state().discovered {
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "signed heartbeat not accepted"
        );
        let signed = [vehicle_heartbeat(Some(&signer))];
        send_then_tick(&vehicle, to, &signed, &mut link, &mut now);
    }
    assert_eq!(link.state().mode, Some(ArduSubMode::Manual));
    let _ = std::fs::remove_file(path);
}

#[test]
fn raw_32_byte_key_file_works_and_bad_files_are_named() {
    let raw = key_file("key.bin", &KEY);
    let cfg = LinkConfig {
        url: "udpout:127.0.0.1:9".into(),
        signing_key_file: Some(raw.clone()),
        ..Default::default()
    };
    assert!(VehicleLink::connect(&cfg).is_ok());
    let _ = std::fs::remove_file(raw);

    let short = key_file("short.key", b"abc");
    let cfg = LinkConfig {
        signing_key_file: Some(short.clone()),
        ..cfg
    };
    let e = VehicleLink::connect(&cfg)
        .err()
        .expect("must fail")
        .to_string();
    assert!(e.contains("short.key") && e.contains("32"), "{e}");
    let _ = std::fs::remove_file(short);

    let missing = LinkConfig {
        signing_key_file: Some(PathBuf::from("/nonexistent/markhold.key")),
        ..cfg
    };
    let e = VehicleLink::connect(&missing)
        .err()
        .expect("must fail")
        .to_string();
    assert!(e.contains("/nonexistent/markhold.key"), "{e}");
}
