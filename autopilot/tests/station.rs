//! The pilot's station and the SYSID_MYGCS gate, on loop time driven by hand: a raw
//! loopback socket plays the vehicle (1/1) and, through the same socket as a router
//! would forward it, QGroundControl's heartbeat (255/190). The caller keeps asking for
//! pilot input on every tick, as a careless one would: the link alone must stop it.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::net::{SocketAddr, UdpSocket};

use markhold_autopilot::link::STATION_RELAY_S;
use markhold_autopilot::mavlink::dialects::ardupilotmega::*;
use markhold_autopilot::mavlink::{self, MavHeader, MavlinkReader};
use markhold_autopilot::{station_timeout_s, Effort, LinkConfig, VehicleLink};

struct Peer {
    sock: UdpSocket,
    seq: u8,
}

impl Peer {
    fn send(&mut self, to: SocketAddr, ids: (u8, u8), msg: &MavMessage) {
        let h = MavHeader {
            system_id: u32::from(ids.0),
            component_id: ids.1,
            sequence: self.seq,
        };
        self.seq = self.seq.wrapping_add(1);
        let mut out = Vec::new();
        mavlink::write_v2_msg_signed(&mut out, h, msg, None).unwrap();
        self.sock.send_to(&out, to).unwrap();
    }

    /// Every frame the link sent since the last call: (system, component, message).
    fn read(&self) -> Vec<(u32, u8, MavMessage)> {
        let mut out = Vec::new();
        let mut buf = [0u8; 4096];
        while let Ok(n) = self.sock.recv(&mut buf) {
            let mut r = MavlinkReader::new(&buf[..n]);
            while let Ok((h, m)) = r.read_any_message::<MavMessage>() {
                out.push((h.system_id, h.component_id, m));
            }
        }
        out
    }
}

fn heartbeat(mavtype: MavType, autopilot: MavAutopilot) -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 19,
        mavtype,
        autopilot,
        base_mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

fn param(name: &str, value: f32) -> MavMessage {
    MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
        param_value: value,
        param_count: 1,
        param_index: 0,
        param_id: name.into(),
        param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
    })
}

#[test]
fn station_timeout_is_half_the_gcs_timeout_within_one_heartbeat_period_and_1_4_s() {
    assert_eq!(station_timeout_s(2.5), 1.25);
    assert_eq!(station_timeout_s(5.0), 1.4);
    assert_eq!(station_timeout_s(1.0), 1.2);
    assert_eq!(station_timeout_s(f64::NAN), 1.4);
}

#[test]
fn pilot_input_stops_when_the_station_falls_silent_and_resumes_when_it_is_heard() {
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.set_nonblocking(true).unwrap();
    let mut link = VehicleLink::connect(&LinkConfig {
        url: format!("udpout:{}", sock.local_addr().unwrap()),
        ..LinkConfig::default()
    })
    .unwrap();
    let to = link.local_addr().unwrap();
    let mut p = Peer { sock, seq: 0 };
    let vehicle = (1, 1);
    let qgc = (255, 190);
    let effort = Effort {
        surge: 0.3,
        ..Effort::NEUTRAL
    };
    // Pilot frames (255) and other frames, by loop time.
    let mut pilot_at = Vec::new();
    let mut ids = std::collections::BTreeSet::new();
    let step = 1.0 / 30.0;
    // The station heartbeats at 1 Hz until 3 s, is silent until 6 s, then comes back.
    let station_on = |t: f64| !(3.0..6.0).contains(&t);
    let mut last_station = None;
    for k in 0..=270 {
        let t = k as f64 * step;
        if k % 3 == 0 {
            p.send(
                to,
                vehicle,
                &heartbeat(
                    MavType::MAV_TYPE_SUBMARINE,
                    MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                ),
            );
        }
        if k % 30 == 0 && station_on(t) {
            p.send(
                to,
                qgc,
                &heartbeat(MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID),
            );
            last_station = Some(t);
        }
        if k == 10 {
            p.send(to, vehicle, &param("FS_GCS_TIMEOUT", 2.5));
        }
        link.tick(t).unwrap();
        link.send_effort(&effort, t).unwrap();
        for (sys, comp, m) in p.read() {
            let pilot = matches!(m, MavMessage::RC_CHANNELS_OVERRIDE(_));
            ids.insert((sys, comp, pilot));
            if let MavMessage::HEARTBEAT(hb) = &m {
                assert_eq!(hb.mavtype, MavType::MAV_TYPE_ONBOARD_CONTROLLER);
            }
            if pilot {
                pilot_at.push(t);
            }
        }
        if t > 1.0 && t < 3.0 {
            // A live station: never lost; pilot input relayed for STATION_RELAY_S after
            // each of its heartbeats, withheld for the rest of the second.
            assert!(!link.station_lost(), "at {t}");
            let since = t - last_station.unwrap();
            assert_eq!(
                link.gcs_traffic_allowed(),
                since <= STATION_RELAY_S,
                "at {t}"
            );
        }
    }
    // Only pilot input as 255; everything from component 191.
    for (sys, comp, pilot) in &ids {
        assert_eq!((*sys, *comp), (if *pilot { 255 } else { 1 }, 191));
    }
    assert_eq!(link.fs_gcs_timeout_s(), (2.5, true));
    assert_eq!(link.station_timeout_s(), 1.25);
    // Station heartbeats at 0, 1, 2 s, none at 3, 4, 5 s: its last one before the
    // silence at 2 s; pilot input ends within the relay window of it.
    let silent_from = 2.0;
    let limit = silent_from + STATION_RELAY_S + 1e-9;
    let during: Vec<f64> = pilot_at
        .iter()
        .cloned()
        .filter(|t| *t > limit && *t < 6.0)
        .collect();
    assert!(
        during.is_empty(),
        "pilot input while the station was silent: {during:?}"
    );
    assert!(pilot_at
        .iter()
        .any(|t| *t > limit - 2.0 * step && *t <= limit));
    // Between two live heartbeats (1 s and 2 s) the same pause.
    assert!(!pilot_at
        .iter()
        .any(|t| *t > 1.0 + STATION_RELAY_S + 1e-9 && *t < 2.0 - 1e-9));
    let st = link.state();
    assert!(st.counters.gcs_withheld > 50, "{:?}", st.counters);
    assert_eq!(st.station.losses, 1);
    assert_eq!(st.station.component_id, Some(190));
    // Heard again at 6 s: pilot input goes out again.
    assert!(pilot_at.iter().any(|t| *t >= 6.0), "{pilot_at:?}");
    assert!(!link.station_lost());
    assert_eq!(last_station, Some(9.0));
}
