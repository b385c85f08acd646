//! `markhold replay` on arbitrary bytes as an MCAP file: an error or a summary (a file
//! cut short is replayed up to its last complete chunk), never a panic, an unbounded
//! allocation or a hang.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = markhold::record::replay::replay_from(
        std::path::Path::new("fuzz.mcap"),
        data,
        data.len() as u64,
    );
});
