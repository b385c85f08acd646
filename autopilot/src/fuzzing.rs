//! Entry points for the fuzz targets (`fuzz/`): the link's own logic on arbitrary input,
//! with its invariants checked. Not an API.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::MavlinkReader;

use crate::transport::{accept, gate_datagram, gate_frame, PeerGate, TaskCounters};

/// The vehicle ids the check's link expects.
const VEHICLE: (u8, u8) = (1, 1);

/// Datagrams from several senders through a `udpin:` link's gate, as `recv_from` gives
/// them (one per read, cut to the reader's buffer).
struct Datagrams {
    grams: VecDeque<(SocketAddr, Vec<u8>)>,
    gate: Option<Arc<Mutex<PeerGate>>>,
    /// Sender of the datagram read last.
    last: Arc<Mutex<Option<SocketAddr>>>,
}

impl std::io::Read for Datagrams {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        while let Some((from, bytes)) = self.grams.pop_front() {
            if !gate_datagram(&self.gate, from) {
                continue;
            }
            if let Ok(mut l) = self.last.lock() {
                *l = Some(from);
            }
            let n = bytes.len().min(buf.len());
            buf[..n].copy_from_slice(&bytes[..n]);
            return Ok(n);
        }
        Ok(0)
    }
}

/// `data` as datagrams (`[sender 0..3, length, bytes...]` repeated) into a `udpin:`
/// link's framing and gate. Panics when an invariant breaks: a frame reaches the link
/// before a peer is chosen unless it is from the vehicle's ids; the peer, once chosen,
/// never changes; every frame that reaches the link came from the peer.
pub fn udpin_peer_check(data: &[u8]) {
    let senders: [SocketAddr; 3] = [
        ([127, 0, 0, 1], 14550).into(),
        ([127, 0, 0, 1], 14551).into(),
        ([127, 0, 0, 2], 14550).into(),
    ];
    let mut grams = VecDeque::new();
    let mut rest = data;
    while let [who, len, tail @ ..] = rest {
        let n = usize::from(*len).min(tail.len());
        grams.push_back((senders[usize::from(*who) % 3], tail[..n].to_vec()));
        rest = &tail[n..];
    }
    let dest = Arc::new(Mutex::new(None));
    let gate = Arc::new(Mutex::new(PeerGate::new(dest.clone(), VEHICLE)));
    let last = Arc::new(Mutex::new(None));
    let mut reader = MavlinkReader::new(Datagrams {
        grams,
        gate: Some(gate.clone()),
        last: last.clone(),
    });
    let counters = TaskCounters::default();
    let mut chosen: Option<SocketAddr> = None;
    // Every message consumes at least one byte: bounded by the input.
    for _ in 0..=data.len() {
        match reader.read_any_raw_message::<MavMessage>() {
            Ok(raw) => {
                let Some((h, _)) = accept(&raw, None, &counters) else {
                    continue;
                };
                let was = chosen;
                let passed = gate_frame(Some(&gate), &h);
                let now = dest.lock().ok().and_then(|d| *d);
                if let Some(p) = was {
                    assert_eq!(now, Some(p), "the peer changed");
                }
                if passed {
                    if was.is_none() {
                        assert_eq!(
                            (h.system_id, h.component_id),
                            (u32::from(VEHICLE.0), VEHICLE.1),
                            "a frame from another id passed before a peer was chosen"
                        );
                    }
                    let from = last.lock().ok().and_then(|l| *l);
                    assert_eq!(from, now, "a frame from another sender passed");
                }
                chosen = now;
            }
            Err(MessageReadError::Parse(_)) => {}
            Err(MessageReadError::Io(_)) => break,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vehicle heartbeat after junk from another sender: that sender is never chosen.
    #[test]
    fn the_check_runs_on_junk_and_a_vehicle_frame() {
        let mut frame = Vec::new();
        let h = mavlink::MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: 0,
        };
        let msg = MavMessage::HEARTBEAT(Default::default());
        mavlink::write_v2_msg(&mut frame, h, &msg).expect("a heartbeat encodes");
        let mut data = vec![1, 8, 0xfd, 1, 2, 3, 4, 5, 6, 7];
        data.push(0);
        data.push(frame.len() as u8);
        data.extend_from_slice(&frame);
        data.extend_from_slice(&[1, 4, 9, 9, 9, 9]);
        udpin_peer_check(&data);
    }
}
