//! The camera calibration reader on arbitrary text: an error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = markhold_vision::CameraCalibration::parse(text, std::path::Path::new("fuzz.yaml"));
    }
});
