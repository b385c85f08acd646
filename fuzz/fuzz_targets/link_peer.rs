//! A listening UDP link's framing and peer choice on arbitrary datagrams from several
//! senders: never a panic, and the checks of `udpin_peer_check` hold (the peer is only
//! ever a sender of a valid frame from the vehicle's ids and never changes once chosen).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    markhold_autopilot::fuzzing::udpin_peer_check(data);
});
