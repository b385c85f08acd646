//! Link loss from any message of the vehicle's autopilot (not only its 1 Hz heartbeat),
//! the bounded drain of the UDP socket per tick and its enlarged receive buffer. A raw
//! loopback socket plays the vehicle; loop time is driven by hand.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::UdpSocket;

use markhold_autopilot::link::MAX_MESSAGES_PER_TICK;
use markhold_autopilot::mavlink::dialects::ardupilotmega::*;
use markhold_autopilot::mavlink::{self, MavHeader};
use markhold_autopilot::{LinkConfig, VehicleLink};
use markhold_testkit::thread_allocs as allocs;

struct FakeVehicle {
    sock: UdpSocket,
    seq: u8,
}

impl FakeVehicle {
    fn send(&mut self, to: std::net::SocketAddr, sysid: u8, msg: &MavMessage) {
        let h = MavHeader {
            system_id: u32::from(sysid),
            component_id: 1,
            sequence: self.seq,
        };
        self.seq = self.seq.wrapping_add(1);
        let mut out = Vec::new();
        mavlink::write_v2_msg_signed(&mut out, h, msg, None).unwrap();
        self.sock.send_to(&out, to).unwrap();
    }

    /// `n` frames of `msg`, [`FRAMES_PER_DATAGRAM`] to a datagram (as routers may pack
    /// them); returns the number of datagrams sent.
    fn send_packed(
        &mut self,
        to: std::net::SocketAddr,
        sysid: u8,
        msg: &MavMessage,
        n: usize,
    ) -> usize {
        let mut out = Vec::new();
        let mut datagrams = 0;
        for k in 0..n {
            let h = MavHeader {
                system_id: u32::from(sysid),
                component_id: 1,
                sequence: self.seq,
            };
            self.seq = self.seq.wrapping_add(1);
            mavlink::write_v2_msg_signed(&mut out, h, msg, None).unwrap();
            if (k + 1) % FRAMES_PER_DATAGRAM == 0 || k + 1 == n {
                self.sock.send_to(&out, to).unwrap();
                out.clear();
                datagrams += 1;
            }
        }
        datagrams
    }
}

/// MAVLink frames per datagram in the bursts: the bursts must fit in the receive buffer
/// Linux grants under its default limit (net.core.rmem_max 208 KiB, granted doubled).
const FRAMES_PER_DATAGRAM: usize = 50;
/// A generous bound on the kernel's accounting of one such datagram (payload about
/// 50 x 13 bytes, plus the socket buffer's overhead).
const BYTES_PER_DATAGRAM_IN_KERNEL: usize = 4096;

fn heartbeat() -> MavMessage {
    markhold_testkit::sub_heartbeat(0, MavModeFlag::empty())
}

fn attitude() -> MavMessage {
    MavMessage::ATTITUDE(ATTITUDE_DATA::default())
}

fn setup(cfg: LinkConfig) -> (VehicleLink, FakeVehicle) {
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    let link = VehicleLink::connect(&LinkConfig {
        url: format!("udpout:{}", sock.local_addr().unwrap()),
        ..cfg
    })
    .unwrap();
    (link, FakeVehicle { sock, seq: 0 })
}

/// Heartbeats at 1 Hz and ATTITUDE at 10 Hz until `stop_all_s` (heartbeats alone stop at
/// `stop_hb_s`); returns the first loop time the link called the vehicle lost.
fn lost_at(stop_hb_s: f64, stop_all_s: f64) -> Option<f64> {
    let (mut link, mut v) = setup(LinkConfig::default());
    let to = link.local_addr().unwrap();
    let mut lost = None;
    for k in 0..=200 {
        let t = k as f64 * 0.05;
        if t < stop_all_s {
            if k % 20 == 0 && t < stop_hb_s {
                v.send(to, 1, &heartbeat());
            }
            if k % 2 == 0 {
                v.send(to, 1, &attitude());
            }
        }
        link.tick(t).unwrap();
        let s = link.state();
        if t < 0.5 {
            assert!(s.heartbeat_ok, "not heard at {t}");
        }
        if !s.heartbeat_ok && lost.is_none() {
            lost = Some(t);
        }
    }
    lost
}

/// Lost on the first tick (every 0.05 s) after `vehicle_timeout_s` without a message.
fn assert_lost_after(last_msg_s: f64, lost: f64) {
    let timeout = LinkConfig::default().vehicle_timeout_s;
    assert!(timeout <= 1.0);
    let age = lost - last_msg_s;
    assert!(
        age > timeout && age <= timeout + 0.05 + 1e-9,
        "lost at {lost}"
    );
}

#[test]
fn silence_is_noticed_within_one_second() {
    // Everything stops at 5.0 s (last ATTITUDE at 4.9 s): lost a timeout later, not up
    // to two heartbeat periods later as when only heartbeats counted.
    let lost = lost_at(100.0, 5.0).expect("never lost");
    assert_lost_after(4.9, lost);
    assert!(lost - 4.9 <= 1.0);
}

#[test]
fn telemetry_keeps_the_vehicle_heard_between_sparse_heartbeats() {
    // Heartbeats stop after the one at 2.0 s (or come late, as from a vehicle slower
    // than the loop), ATTITUDE goes on: the vehicle stays heard.
    assert_eq!(lost_at(2.5, 100.0), None);
    // A camera on the vehicle's system id (component 100) does not count.
    let (mut link, mut v) = setup(LinkConfig::default());
    let to = link.local_addr().unwrap();
    v.send(to, 1, &heartbeat());
    link.tick(0.0).unwrap();
    for k in 1..=30 {
        let h = MavHeader {
            system_id: 1,
            component_id: 100,
            sequence: k as u8,
        };
        let mut out = Vec::new();
        mavlink::write_v2_msg_signed(&mut out, h, &attitude(), None).unwrap();
        v.sock.send_to(&out, to).unwrap();
        link.tick(k as f64 * 0.05).unwrap();
    }
    assert!(!link.state().heartbeat_ok);
}

#[test]
fn another_system_does_not_keep_the_vehicle_alive() {
    let (mut link, mut v) = setup(LinkConfig::default());
    let to = link.local_addr().unwrap();
    v.send(to, 1, &heartbeat());
    link.tick(0.0).unwrap();
    assert!(link.state().heartbeat_ok);
    for k in 1..=30 {
        let t = k as f64 * 0.05;
        v.send(to, 42, &heartbeat());
        v.send(to, 42, &attitude());
        link.tick(t).unwrap();
    }
    assert!(!link.state().heartbeat_ok);
    assert_eq!(link.state().system_id, 1);
}

#[test]
fn timeout_must_cover_four_stream_messages() {
    let e = VehicleLink::connect(&LinkConfig {
        vehicle_timeout_s: 0.3,
        ..Default::default()
    })
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("link.vehicle_timeout_s"), "{e}");
    let ok = LinkConfig {
        vehicle_timeout_s: 1.0,
        stream_hz: 4.0,
        ..Default::default()
    };
    ok.validate().unwrap();
}

#[test]
fn a_burst_between_two_ticks_is_read_whole_and_bounded_per_tick() {
    let (mut link, mut v) = setup(LinkConfig::default());
    let to = link.local_addr().unwrap();
    let granted = link.udp_recv_buffer().unwrap();
    let rmem_max: usize = std::fs::read_to_string("/proc/sys/net/core/rmem_max")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(0);
    println!("SO_RCVBUF granted: {granted} bytes (rmem_max {rmem_max})");
    // The link asks for 4 MiB; Linux caps it at rmem_max and doubles it.
    let asked = markhold_autopilot::transport::UDP_RECV_BUFFER_BYTES;
    assert!(granted >= asked.min(rmem_max), "{granted}");
    // The largest burst below must fit in what was granted, or the kernel drops part of
    // it and the counts below fail for the wrong reason: say so instead.
    let n = MAX_MESSAGES_PER_TICK + 100;
    let needed = (n.div_ceil(FRAMES_PER_DATAGRAM) + 1) * BYTES_PER_DATAGRAM_IN_KERNEL;
    assert!(
        granted >= needed,
        "the UDP receive buffer granted here ({granted} bytes, net.core.rmem_max {rmem_max}) \
         is below the {needed} bytes the burst needs"
    );
    v.send(to, 1, &heartbeat());
    link.tick(0.0).unwrap();
    let before = link.messages_received();
    // 2000 foreign messages and one heartbeat at the end, all before the next tick.
    v.send_packed(to, 42, &attitude(), 2000);
    v.send(to, 1, &heartbeat());
    link.tick(0.05).unwrap();
    assert_eq!(link.messages_received() - before, 2001);
    assert_eq!(link.state().heartbeats, 2);
    // More than a batch: the tick stops at the bound, the rest waits for the next one.
    v.send_packed(to, 42, &attitude(), n);
    let before = link.messages_received();
    link.tick(0.1).unwrap();
    assert_eq!(
        link.messages_received() - before,
        MAX_MESSAGES_PER_TICK as u64
    );
    assert_eq!(link.state().counters.receive_batch_full, 1);
    link.tick(0.15).unwrap();
    assert_eq!(link.messages_received() - before, n as u64);
}

/// Allocations are counted per thread (the link's tokio threads do not count).
#[global_allocator]
static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;

#[test]
fn draining_a_burst_with_the_raw_tap_allocates_nothing() {
    let (mut link, mut v) = setup(LinkConfig::default());
    let to = link.local_addr().unwrap();
    let (tx, rx) = std::sync::mpsc::sync_channel(4096);
    link.set_raw_tap(Some(tx));
    v.send(to, 1, &heartbeat());
    link.tick(0.0).unwrap();
    link.send_effort(&markhold_autopilot::Effort::NEUTRAL, 0.0)
        .unwrap();
    let before = allocs();
    let probe = std::hint::black_box(vec![0u8; 8]);
    assert!(allocs() > before && probe.len() == 8);
    let mut total = 0;
    for k in 1..=20 {
        for _ in 0..300 {
            v.send(to, 42, &attitude());
        }
        v.send(to, 1, &attitude());
        let t = k as f64 * 0.05;
        let before = allocs();
        link.tick(t).unwrap();
        link.send_effort(&markhold_autopilot::Effort::NEUTRAL, t)
            .unwrap();
        total += allocs() - before;
        while rx.try_recv().is_ok() {}
    }
    assert!(link.state().heartbeat_ok);
    assert_eq!(link.raw_tap_dropped(), 0);
    assert_eq!(total, 0, "allocations while reading 6020 messages");
}

#[test]
fn the_raw_tap_sees_both_directions_on_the_receive_task_too() {
    let (mut link, v) = setup(LinkConfig {
        udp_receive_on_tick: false,
        ..Default::default()
    });
    let to = link.local_addr().unwrap();
    let (tx, rx) = std::sync::mpsc::sync_channel(64);
    link.set_raw_tap(Some(tx));
    let mut sent = Vec::new();
    let h = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: 77,
    };
    mavlink::write_v2_msg_signed(&mut sent, h, &heartbeat(), None).unwrap();
    v.sock.send_to(&sent, to).unwrap();
    let t0 = std::time::Instant::now();
    let mut t = 0.0;
    while !link.state().discovered {
        assert!(
            t0.elapsed() < std::time::Duration::from_secs(5),
            "not heard"
        );
        link.tick(t).unwrap();
        t += 0.01;
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    let frames: Vec<_> = rx.try_iter().collect();
    let incoming: Vec<_> = frames.iter().filter(|f| !f.outgoing).collect();
    assert_eq!(incoming.len(), 1);
    assert_eq!(incoming[0].bytes(), &sent[..]);
    // Our own heartbeat went out first, tapped as written.
    let out = frames
        .iter()
        .find(|f| f.outgoing)
        .expect("an outgoing frame");
    assert_eq!(out.bytes()[0], 0xFD);
    // Sent as the vehicle's system id (1), not as SYSID_MYGCS.
    assert_eq!(out.bytes()[5], 1);
}
