//! Frames and camera limits shared by the controllers' unit tests.

use crate::{ExposureLimits, Frame};

/// A camera of 5 to 20,000 us at 30 fps.
pub(crate) fn limits() -> ExposureLimits {
    ExposureLimits {
        min_us: 5.0,
        max_us: 20000.0,
        fps: 30.0,
    }
}

/// A 40x30 frame of 8x8 blocks (`lo` / 200 grey) exposed for `t`.
pub(crate) fn blocks(t: f64, lo: u8) -> Frame {
    let mut f = Frame::new(40, 30);
    for (i, p) in f.data.iter_mut().enumerate() {
        let (x, y) = (i % 40, i / 40);
        *p = if (x / 8 + y / 8) % 2 == 0 { lo } else { 200 };
    }
    f.meta.exposure_us = t;
    f
}
