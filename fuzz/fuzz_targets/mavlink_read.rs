//! The MAVLink receive path with our dialect on an arbitrary byte stream: every frame in
//! it read (v1 and v2, signed or not), parse errors skipped, never a panic or a hang.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;

fuzz_target!(|data: &[u8]| {
    let mut r = mavlink::MavlinkReader::new(data);
    // Each message consumes at least one byte: bounded by the input length.
    for _ in 0..=data.len() {
        match r.read_any_message::<MavMessage>() {
            Ok(_) | Err(MessageReadError::Parse(_)) => {}
            Err(_) => break,
        }
    }
});
