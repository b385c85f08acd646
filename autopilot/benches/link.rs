//! Pilot input from effort to the wire: the link's direct write on the caller's thread
//! against rust-mavlink's own connections (sync, and async driven with block_on), all to a
//! loopback UDP socket drained by a thread. One station-keeper update. Telemetry from the
//! vehicle's socket write to the link state: read in `tick` vs a reader task.

#![allow(clippy::unwrap_used)] // A benchmark's setup fails loudly when broken, by design.

use std::hint::black_box;
use std::net::UdpSocket;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use markhold_autopilot::*;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{AsyncMavConnection, MavConnection, MavHeader};
use nalgebra::{Isometry3, Matrix6, Translation3};

fn sink() -> (
    std::net::SocketAddr,
    Arc<AtomicBool>,
    std::thread::JoinHandle<()>,
) {
    let s = UdpSocket::bind("127.0.0.1:0").unwrap();
    s.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    let addr = s.local_addr().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let st = stop.clone();
    let h = std::thread::spawn(move || {
        let mut buf = [0u8; 2048];
        while !st.load(Ordering::Relaxed) {
            let _ = s.recv_from(&mut buf);
        }
    });
    (addr, stop, h)
}

fn rc_msg(map: &PilotMap, e: &Effort) -> MavMessage {
    markhold_autopilot::link::rc_override(map, e, 1, 1)
}

fn pilot_input(c: &mut Criterion) {
    let (addr, stop, h) = sink();
    let url = format!("udpout:{addr}");
    let cfg = LinkConfig {
        url: url.clone(),
        ..Default::default()
    };
    let e = Effort {
        surge: 0.2,
        sway: -0.1,
        heave: 0.05,
        roll: 0.0,
        pitch: 0.0,
        yaw: 0.03,
    };
    let map = PilotMap::from_config(&cfg);
    let header = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    };
    let mut g = c.benchmark_group("pilot_input_to_wire");

    let mut link = VehicleLink::connect(&cfg).unwrap();
    g.bench_function("markhold_direct", |b| {
        b.iter(|| link.send_effort(black_box(&e), 0.0).unwrap())
    });

    let conn = mavlink::connect::<MavMessage>(&url).unwrap();
    g.bench_function("mavlink_sync_connection", |b| {
        b.iter(|| conn.send(&header, &rc_msg(&map, black_box(&e))).unwrap())
    });

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let aconn = rt
        .block_on(mavlink::connect_async::<MavMessage>(&url))
        .unwrap();
    g.bench_function("mavlink_async_block_on", |b| {
        b.iter(|| {
            rt.block_on(aconn.send(&header, &rc_msg(&map, black_box(&e))))
                .unwrap()
        })
    });
    g.finish();
    stop.store(true, Ordering::Relaxed);
    let _ = h.join();
}

fn keeper(c: &mut Criterion) {
    let cam = markhold_testkit::forward_camera(0.2, 0.0);
    let mut k =
        StationKeeper::new(&StationConfig::default(), &ControllerConfig::default(), cam).unwrap();
    let goal = StationConfig::default().t_marker_vehicle();
    let off = Isometry3::from_parts(Translation3::new(0.1, -0.05, 1.2), goal.rotation);
    let meas = PoseMeasurement {
        stamp_s: 0.0,
        t_cam_marker: (off * cam).inverse(),
        cov_cam: Matrix6::identity() * 1e-5,
    };
    let mut t = 0.0;
    c.bench_function("station_keeper_update", |b| {
        b.iter(|| {
            t += 1.0 / 30.0;
            black_box(k.update(t, Some(black_box(&meas))))
        })
    });
}

/// Telemetry datagram written by the vehicle to the state updated by `tick`: read on the
/// caller's thread in `tick` (default) against a tokio reader task plus queue.
fn telemetry(c: &mut Criterion) {
    use mavlink::dialects::ardupilotmega::*;
    let mut g = c.benchmark_group("telemetry_to_state");
    for (name, on_tick) in [("tick_receive", true), ("task_receive", false)] {
        let vehicle = UdpSocket::bind("127.0.0.1:0").unwrap();
        let cfg = LinkConfig {
            url: format!("udpout:{}", vehicle.local_addr().unwrap()),
            udp_receive_on_tick: on_tick,
            ..Default::default()
        };
        let mut link = VehicleLink::connect(&cfg).unwrap();
        let to = ("127.0.0.1", link.local_addr().unwrap().port());
        let h = markhold_testkit::VEHICLE_HEADER;
        let mut hb = Vec::new();
        mavlink::write_v2_msg(
            &mut hb,
            h,
            &markhold_testkit::sub_heartbeat(19, MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
        )
        .unwrap();
        vehicle.send_to(&hb, to).unwrap();
        let t0 = std::time::Instant::now();
        while !link.state().discovered {
            link.tick(0.0).unwrap();
            assert!(t0.elapsed() < Duration::from_secs(5), "no discovery");
        }
        let mut k = 0u32;
        let mut buf = Vec::with_capacity(64);
        g.bench_function(name, |b| {
            b.iter(|| {
                k = k.wrapping_add(1);
                buf.clear();
                let att = MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: k,
                    ..Default::default()
                });
                mavlink::write_v2_msg(&mut buf, h, &att).unwrap();
                vehicle.send_to(&buf, to).unwrap();
                let mut spins = 0u64;
                while link.state().attitude.map(|a| a.time_boot_ms) != Some(k) {
                    link.tick(0.0).unwrap();
                    spins += 1;
                    assert!(spins < 50_000_000, "attitude never applied");
                }
            })
        });
    }
    g.finish();
}

criterion_group!(benches, pilot_input, keeper, telemetry);
criterion_main!(benches);
