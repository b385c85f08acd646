//! Closing the link loses nothing written: over TCP the vehicle reads every frame and
//! then an orderly end of the stream, never a reset, even while it keeps sending
//! telemetry markhold no longer reads (a socket closed with unread data sends a reset).
//! A std TCP listener plays the vehicle.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::io::{ErrorKind, Read, Write};
use std::net::TcpListener;
use std::time::{Duration, Instant};

use markhold_autopilot::mavlink::dialects::ardupilotmega::*;
use markhold_autopilot::mavlink::{self, MavHeader, MavlinkReader};
use markhold_autopilot::{LinkConfig, VehicleLink};

fn frame(seq: u8, msg: &MavMessage) -> Vec<u8> {
    let h = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: seq,
    };
    let mut out = Vec::new();
    mavlink::write_v2_msg_signed(&mut out, h, msg, None).unwrap();
    out
}

/// How the vehicle saw markhold's stream end, and what it read before.
struct Seen {
    named: usize,
    end: &'static str,
}

#[test]
fn tcp_close_delivers_every_frame_and_ends_without_a_reset() {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    let vehicle = std::thread::spawn(move || {
        let (mut s, _) = l.accept().unwrap();
        s.set_nodelay(true).unwrap();
        let hb = frame(
            0,
            &markhold_testkit::sub_heartbeat(19, MavModeFlag::empty()),
        );
        let att = frame(1, &MavMessage::ATTITUDE(ATTITUDE_DATA::default()));
        s.set_read_timeout(Some(Duration::from_millis(5))).unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        let t0 = Instant::now();
        // Telemetry without pause, read slowly (a busy autopilot's loop), until
        // markhold's end of stream.
        let end = loop {
            assert!(t0.elapsed() < Duration::from_secs(20), "no end of stream");
            let _ = s.write_all(&hb);
            for _ in 0..20 {
                let _ = s.write_all(&att);
            }
            std::thread::sleep(Duration::from_millis(3));
            match s.read(&mut buf) {
                Ok(0) => break "eof",
                Ok(n) => got.extend_from_slice(&buf[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(e) if e.kind() == ErrorKind::ConnectionReset => break "reset",
                Err(e) => panic!("{e}"),
            }
        };
        let mut r = MavlinkReader::new(&got[..]);
        let mut named = 0;
        while let Ok((_, m)) = r.read_any_message::<MavMessage>() {
            if matches!(m, MavMessage::NAMED_VALUE_FLOAT(_)) {
                named += 1;
            }
        }
        Seen { named, end }
    });

    let mut link = VehicleLink::connect(&LinkConfig {
        url: format!("tcp:{addr}"),
        ..LinkConfig::default()
    })
    .unwrap();
    link.set_pilot_keepalive(false);
    let t0 = Instant::now();
    while !link.state().discovered {
        assert!(t0.elapsed() < Duration::from_secs(10), "vehicle not heard");
        link.tick(t0.elapsed().as_secs_f64()).unwrap();
        std::thread::sleep(Duration::from_millis(2));
    }
    // A burst the vehicle reads slowly, then the close at once: the tail is still in
    // flight (or in our own buffer) when the close starts.
    const N: usize = 2000;
    for i in 0..N {
        link.send_named_value("mh_test", i as f32, 0.0).unwrap();
    }
    let closed = link.close(5.0);
    let seen = vehicle.join().unwrap();
    assert_eq!(seen.end, "eof", "the vehicle saw a reset");
    assert_eq!(seen.named, N, "frames lost at the close");
    assert!(closed.flushed && closed.peer_closed, "{closed:?}");
    // Closed: nothing more goes out.
    let sent = link.messages_sent();
    link.send_named_value("mh_test", 0.0, 0.0).unwrap();
    assert_eq!(link.messages_sent(), sent);
}
