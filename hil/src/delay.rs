//! The delay from a camera frame to the thrust its command asks for, stage by stage
//! (`[vehicle.delay]`): what a vision-guided vehicle loses between the instant the image
//! shows and the instant the thrusters are told about it.
//!
//! The simulated camera renders the vehicle's pose at the frame's stamp and markhold's
//! command for that frame reaches the simulated ArduSub at once (lock-step), so the whole
//! delay is applied where the vehicle receives it: pilot input and guided and depth targets
//! take effect `total_ms` after they arrive (see `VehicleEndpoint::set_input_delay`).
//! The thrusters' own spin-up is the thruster model's (`[vehicle.thruster]`), not a stage
//! here.

use serde::{Deserialize, Serialize};

use markhold_config::{Checks, ConfigError};

/// `[vehicle.delay]`: milliseconds per stage. The defaults are a stock BlueROV2 with
/// markhold on its companion computer, watching the Low-Light HD USB camera's H.264
/// stream (docs/design/hil.md, "Frame to thrust", gives each stage's source).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DelayConfig {
    /// From the middle of the exposure to the last row read out: a rolling-shutter
    /// sensor at 30 frames a second reads for about a frame period.
    pub exposure_readout_ms: f64,
    /// The camera's own H.264 encoder: it sends a frame once the frame is whole.
    pub encode_ms: f64,
    /// USB, the companion computer's network stack, the tether and the topside router,
    /// each way the frame and the command travel.
    pub transport_ms: f64,
    /// H.264 decoding in markhold (no B-frames: one frame in, one out).
    pub decode_ms: f64,
    /// markhold's loop: detection, pose, exposure, keeper.
    pub loop_ms: f64,
    /// MAVLink from markhold through the router to ArduSub.
    pub mavlink_ms: f64,
    /// ArduSub's main loop (400 Hz): an override received in one loop is read by the
    /// mode's controller in the next and reaches the motors in the one after: 1-2 loops.
    pub ardusub_loop_ms: f64,
}

impl Default for DelayConfig {
    fn default() -> Self {
        Self {
            exposure_readout_ms: 35.0,
            encode_ms: 33.0,
            transport_ms: 2.0,
            decode_ms: 10.0,
            loop_ms: 10.0,
            mavlink_ms: 2.0,
            ardusub_loop_ms: 3.75,
        }
    }
}

impl DelayConfig {
    /// No delay at all: the command acts at its frame's stamp.
    pub const NONE: Self = Self {
        exposure_readout_ms: 0.0,
        encode_ms: 0.0,
        transport_ms: 0.0,
        decode_ms: 0.0,
        loop_ms: 0.0,
        mavlink_ms: 0.0,
        ardusub_loop_ms: 0.0,
    };

    fn stages(&self) -> [(&'static str, f64); 7] {
        [
            ("exposure_readout_ms", self.exposure_readout_ms),
            ("encode_ms", self.encode_ms),
            ("transport_ms", self.transport_ms),
            ("decode_ms", self.decode_ms),
            ("loop_ms", self.loop_ms),
            ("mavlink_ms", self.mavlink_ms),
            ("ardusub_loop_ms", self.ardusub_loop_ms),
        ]
    }

    /// Frame to thrust, milliseconds: the sum of the stages.
    pub fn total_ms(&self) -> f64 {
        self.stages().iter().map(|(_, v)| v).sum()
    }

    /// The same stages scaled so that they sum to `total_ms` (all zero for 0; the default
    /// split when every stage is zero).
    pub fn scaled_to(&self, total_ms: f64) -> Self {
        let base = if self.total_ms() > 0.0 {
            *self
        } else {
            Self::default()
        };
        let k = total_ms / base.total_ms();
        base.map(|v| v * k)
    }

    /// Every stage through `f`.
    fn map(&self, f: impl Fn(f64) -> f64) -> Self {
        Self {
            exposure_readout_ms: f(self.exposure_readout_ms),
            encode_ms: f(self.encode_ms),
            transport_ms: f(self.transport_ms),
            decode_ms: f(self.decode_ms),
            loop_ms: f(self.loop_ms),
            mavlink_ms: f(self.mavlink_ms),
            ardusub_loop_ms: f(self.ardusub_loop_ms),
        }
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let mut c = Checks::new("vehicle.delay");
        for (name, v) in self.stages() {
            c = c.finite_range(name, v, 0.0..=MAX_TOTAL_MS, "0..=1000 ms");
        }
        c.finite_range(
            "total",
            self.total_ms(),
            0.0..=MAX_TOTAL_MS,
            "a sum of at most 1000 ms",
        )
        .done()
    }
}

/// The longest frame-to-thrust delay a site may configure, milliseconds.
pub const MAX_TOTAL_MS: f64 = 1000.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_total_is_the_sum_of_the_stages_and_scales() {
        let d = DelayConfig::default();
        assert!((d.total_ms() - 95.75).abs() < 1e-9, "{}", d.total_ms());
        let s = d.scaled_to(150.0);
        assert!((s.total_ms() - 150.0).abs() < 1e-9);
        assert!((s.encode_ms / s.decode_ms - 3.3).abs() < 1e-9);
        assert_eq!(DelayConfig::NONE.total_ms(), 0.0);
        assert!((DelayConfig::NONE.scaled_to(50.0).total_ms() - 50.0).abs() < 1e-9);
        assert_eq!(d.scaled_to(0.0).total_ms(), 0.0);
    }

    #[test]
    fn a_bad_stage_is_named() {
        let d = DelayConfig {
            decode_ms: -1.0,
            ..DelayConfig::default()
        };
        let e = d.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.delay.decode_ms"), "{e}");
        let d = DelayConfig {
            loop_ms: 600.0,
            encode_ms: 600.0,
            ..DelayConfig::default()
        };
        let e = d.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.delay.total"), "{e}");
    }
}
