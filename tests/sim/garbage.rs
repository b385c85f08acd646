//! Garbage and truncated datagrams on every socket markhold and its HIL world listen on
//! (the vehicle endpoint, markhold's own link socket, the SITL JSON server): no panic, and
//! the link keeps working. Loopback only, ports from the OS, every wait bounded.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::{SocketAddr, UdpSocket};
use std::path::Path;
use std::time::Duration;

use markhold::params;
use markhold::sim::hil::HilOptions;
use markhold_autopilot::FailsafeEvent;

/// Seeded garbage, with the shapes that hurt parsers: empty, one magic byte, a MAVLink 2
/// header claiming more payload than it carries, a v1 header, a frame cut at every
/// length, bytes that are all 0xFD, random bytes, one oversized datagram.
fn garbage(seed: u64) -> Vec<Vec<u8>> {
    let mut x = seed | 1;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    // A heartbeat-shaped MAVLink 2 frame (CRC not valid).
    let frame: Vec<u8> = [
        0xFD, 9, 0, 0, 7, 1, 1, 0, 0, 0, 0, 0, 0, 0, 12, 3, 81, 4, 3, 0xAB, 0xCD,
    ]
    .to_vec();
    let mut out = vec![
        Vec::new(),
        vec![0xFD],
        vec![0xFE],
        vec![0xFD, 255, 0, 0, 1, 1, 1, 0, 0, 0],
        vec![0xFE, 255, 0, 1, 1, 0],
        vec![0xFD; 300],
        (0..2000).map(|_| rnd() as u8).collect(),
    ];
    for cut in 1..frame.len() {
        out.push(frame[..cut].to_vec());
    }
    for _ in 0..8 {
        let n = (rnd() % 300) as usize;
        out.push((0..n).map(|_| rnd() as u8).collect());
    }
    out
}

fn spray(sock: &UdpSocket, to: SocketAddr, seed: u64) -> usize {
    let g = garbage(seed);
    for d in &g {
        // A full socket buffer drops garbage as it would on a wire: not a failure.
        let _ = sock.send_to(d, to);
    }
    g.len()
}

/// Garbage from another loopback port on the vehicle's socket: the endpoint adopts a UDP
/// peer only on a CRC-valid frame that parses, so its telemetry stays with markhold.
#[test]
fn garbage_on_the_vehicle_socket_does_not_break_the_link() {
    garbage_run(true, false);
}

#[test]
fn garbage_on_the_link_socket_does_not_break_the_link() {
    garbage_run(false, true);
}

fn garbage_run(to_vehicle: bool, to_link: bool) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = params::load(&path).unwrap();
    // markhold's UDP link is connected to its peer: the kernel drops datagrams from any
    // other address. Garbage for the link therefore comes from the vehicle's side,
    // through the relay of a link cut that never starts.
    let opts = HilOptions {
        seconds: 6.0,
        seed: 5,
        start_on_station: true,
        faults: if to_link {
            vec!["link_cut@100000".parse().unwrap()]
        } else {
            Vec::new()
        },
        ..HilOptions::default()
    };
    let mut hil = crate::common::armed_hil(&site, &opts);
    let vehicle = hil.rig.mavlink_udp_addr();
    let attacker = crate::common::side_socket();
    let received_before = hil.pipeline.link().messages_received();
    let mut sent = 0;
    let mut events = Vec::new();
    let frames = (opts.seconds * site.site.camera.fps) as u64;
    let mut detected = 0;
    for i in 0..frames {
        if i % 3 == 0 {
            if to_vehicle {
                sent += spray(&attacker, vehicle, i);
            }
            if to_link {
                let relay = hil.faults.as_mut().unwrap().relay.as_mut().unwrap();
                for d in garbage(i + 1) {
                    sent += usize::from(relay.inject_to_markhold(&d).unwrap());
                }
            }
        }
        let (rec, _) = hil.step().unwrap();
        detected += u64::from(rec.detected);
        events.extend_from_slice(hil.pipeline.events());
    }
    assert!(sent > 1000);
    let mut buf = [0u8; 512];
    let mut to_attacker = 0;
    while attacker.recv_from(&mut buf).is_ok() {
        to_attacker += 1;
    }
    // The link kept hearing the vehicle, the vehicle kept hearing markhold.
    assert!(
        !events
            .iter()
            .any(|e| matches!(e, FailsafeEvent::VehicleHeartbeatLost { .. })),
        "{events:?}, {to_attacker} datagrams to the garbage sender"
    );
    let state = hil.pipeline.link().state();
    assert!(state.heartbeat_ok && state.armed, "{state:?}");
    assert!(hil.pipeline.link().messages_received() > received_before + 100);
    let truth = hil.rig.truth();
    assert!(truth.armed);
    assert!(detected as f64 > 0.95 * frames as f64);
    let err = (site.site.station.t_marker_vehicle().inverse()
        * site.t_world_marker().inverse()
        * truth.t_world_vehicle)
        .translation
        .vector
        .norm();
    assert!(err < 0.1, "station error {err} m");
    // The vehicle did not start talking to the garbage's sender.
    assert_eq!(to_attacker, 0, "telemetry went to the garbage sender");
}

#[test]
fn garbage_on_the_sitl_socket_is_rejected_and_serving_goes_on() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml");
    let site = params::load(&path).unwrap();
    let cfg = markhold_hil::SitlConfig {
        bind_ip: [127, 0, 0, 1].into(),
        port: 0,
    };
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    let mut server = markhold_hil::SitlServer::bind(&cfg, &site.site.vehicle, &start, 1).unwrap();
    let addr = server.local_addr().unwrap();
    let client = UdpSocket::bind("127.0.0.1:0").unwrap();
    client
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    let hz = site.site.vehicle.physics_hz as u16;
    let mut replies = 0;
    let mut sent_garbage = 0;
    let mut buf = [0u8; 2048];
    for frame in 0..20u32 {
        let g = garbage(u64::from(frame) + 11);
        for d in &g {
            client.send_to(d, addr).unwrap();
            // Garbage: handled (rejected), and no reply.
            assert!(server.serve_one(Duration::from_secs(2)).unwrap());
        }
        sent_garbage += g.len() as u64;
        // Then one valid 16-channel servo packet: answered.
        let mut p = Vec::with_capacity(40);
        p.extend_from_slice(&markhold_hil::sitl::MAGIC_16.to_le_bytes());
        p.extend_from_slice(&hz.to_le_bytes());
        p.extend_from_slice(&frame.to_le_bytes());
        for _ in 0..16 {
            p.extend_from_slice(&1500u16.to_le_bytes());
        }
        client.send_to(&p, addr).unwrap();
        assert!(server.serve_one(Duration::from_secs(2)).unwrap());
        let (n, _) = client
            .recv_from(&mut buf)
            .expect("no reply to a valid packet");
        assert!(buf[..n].starts_with(b"\n{") || buf[..n].starts_with(b"{"));
        replies += 1;
    }
    let st = server.stats();
    assert_eq!(replies, 20);
    assert_eq!(st.rejected, sent_garbage, "{st:?}");
    assert_eq!(st.replies, 20, "{st:?}");
}
