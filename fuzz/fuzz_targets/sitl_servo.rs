//! ArduPilot's SITL JSON servo packet parser on arbitrary datagrams: never a panic, and a
//! packet it accepts has the length its magic says.
#![no_main]

use libfuzzer_sys::fuzz_target;
use markhold_hil::sitl::{parse_servo_packet, MAGIC_16, MAGIC_32};

fuzz_target!(|data: &[u8]| {
    if let Ok(p) = parse_servo_packet(data) {
        let magic = u16::from_le_bytes([data[0], data[1]]);
        assert!(
            (magic == MAGIC_16 && data.len() == 40 && p.channels == 16)
                || (magic == MAGIC_32 && data.len() == 72 && p.channels == 32)
        );
    }
});
