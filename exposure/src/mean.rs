//! A camera's built-in auto exposure: damped mean-intensity targeting in log
//! exposure, `ln t += kappa * (ln target - ln mean)`. The "Default" of the paper.

use markhold_config::{open, open_closed, Checks, ConfigError};

use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, Roi,
};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeanAeConfig {
    /// Target mean grey level, 1..254.
    pub target_grey: f64,
    /// Damping of the log-exposure step, (0, 1].
    pub kappa: f64,
    /// Meter on the marker's RoI instead of the whole image (a fairer baseline than a
    /// camera's own AE, which cannot know where the marker is).
    pub meter_roi: bool,
    /// Pixel subsampling step when metering (1 = every pixel).
    pub subsample: u32,
}

impl Default for MeanAeConfig {
    fn default() -> Self {
        Self {
            target_grey: 127.0,
            kappa: 0.2,
            meter_roi: false,
            subsample: 4,
        }
    }
}

impl MeanAeConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.default")
            .range("target_grey", self.target_grey, open(1.0, 254.0), "a grey level in (1, 254)")
            .range("kappa", self.kappa, open_closed(0.0, 1.0), "a damping factor in (0, 1]")
            .range("subsample", self.subsample, 1..=64, "a pixel step in 1..=64")
            .done()
    }
}

pub struct MeanAe {
    cfg: MeanAeConfig,
    limits: ExposureLimits,
    commanded_us: f64,
}

impl MeanAe {
    pub fn new(
        cfg: MeanAeConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            cfg,
            commanded_us: limits.clamp(initial_us),
            limits,
        })
    }

    /// Mean grey of `roi` in `frame`, sampling every `step`-th pixel and row.
    pub fn mean_grey(frame: &Frame, roi: Roi, step: u32) -> Option<f64> {
        let view = frame.view().crop(roi);
        if view.width == 0 || view.height == 0 {
            return None;
        }
        let step = step.max(1) as usize;
        let (mut sum, mut n) = (0u64, 0u64);
        for y in (0..view.height).step_by(step) {
            for &p in view.row(y).iter().step_by(step) {
                sum += p as u64;
                n += 1;
            }
        }
        Some(sum as f64 / n as f64)
    }
}

impl ExposureController for MeanAe {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::Default
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        let roi = match (self.cfg.meter_roi, marker) {
            (true, Some(c)) => Roi::from_corners_padded(c, 0.1, frame.width, frame.height),
            _ => None,
        };
        let metered = roi.unwrap_or_else(|| frame.full_roi());
        if !exposed_as_commanded(frame, self.commanded_us) || !frame.is_consistent() {
            return ExposureStep {
                roi,
                ..ExposureStep::skipped(self.commanded_us)
            };
        }
        let Some(mean) = Self::mean_grey(frame, metered, self.cfg.subsample) else {
            return ExposureStep {
                roi,
                ..ExposureStep::skipped(self.commanded_us)
            };
        };
        // Half a grey level keeps ln finite on an all-black frame.
        let ln_step = self.cfg.kappa * (self.cfg.target_grey.ln() - mean.max(0.5).ln());
        self.commanded_us = self.limits.clamp(self.commanded_us * ln_step.exp());
        ExposureStep::used(self.commanded_us, mean, roi)
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.commanded_us = self.limits.clamp(exposure_us);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> ExposureLimits {
        ExposureLimits {
            min_us: 10.0,
            max_us: 30_000.0,
            fps: 30.0,
        }
    }

    fn flat(grey: u8, exposure_us: f64) -> Frame {
        let mut f = Frame::new(8, 8);
        f.data.fill(grey);
        f.meta.exposure_us = exposure_us;
        f
    }

    #[test]
    fn step_is_damped_log_ratio() {
        // mean 64, target 128, kappa 0.5: ln t grows by 0.5 ln 2, t by sqrt(2).
        let cfg = MeanAeConfig {
            target_grey: 128.0,
            kappa: 0.5,
            meter_roi: false,
            subsample: 1,
        };
        let mut ae = MeanAe::new(cfg, limits(), 1000.0).unwrap();
        let s = ae.update(&flat(64, 1000.0), None);
        assert!(s.used_frame);
        assert!(
            (s.exposure_us - 1000.0 * 2f64.sqrt()).abs() < 1e-9,
            "{}",
            s.exposure_us
        );
        assert_eq!(s.metric, 64.0);
    }

    #[test]
    fn frames_not_at_commanded_exposure_are_skipped() {
        let mut ae = MeanAe::new(MeanAeConfig::default(), limits(), 1000.0).unwrap();
        let s = ae.update(&flat(10, 500.0), None);
        assert!(!s.used_frame);
        assert_eq!(s.exposure_us, 1000.0);
    }

    #[test]
    fn black_frame_saturates_at_frame_period() {
        // max_us above the frame period, so the period is what binds.
        let lim = ExposureLimits {
            max_us: 100_000.0,
            ..limits()
        };
        let mut ae = MeanAe::new(MeanAeConfig::default(), lim, 20_000.0).unwrap();
        let mut t = 20_000.0;
        for _ in 0..50 {
            t = ae.update(&flat(0, t), None).exposure_us;
            assert!(t.is_finite());
        }
        assert!((t - 1e6 / 30.0).abs() < 1e-6, "{t}");
    }

    #[test]
    fn meter_roi_meters_the_marker_box() {
        // 20x20 frame, grey 20, with a 10x10 square of 200 at (5, 5); corners on the
        // square (padded 10% -> 12x12 box at (4, 4), 100 px of 200 and 44 of 20).
        let mut f = flat(20, 1000.0);
        f.resize(20, 20);
        f.data.fill(20);
        for y in 5..15 {
            for x in 5..15 {
                f.data[y * 20 + x] = 200;
            }
        }
        f.meta.exposure_us = 1000.0;
        let corners = [[5.0, 5.0], [15.0, 5.0], [15.0, 15.0], [5.0, 15.0]];
        let cfg = MeanAeConfig {
            meter_roi: true,
            subsample: 1,
            ..Default::default()
        };
        let mut ae = MeanAe::new(cfg.clone(), limits(), 1000.0).unwrap();
        let s = ae.update(&f, Some(&corners));
        let expect = (100.0 * 200.0 + 44.0 * 20.0) / 144.0;
        assert_eq!(
            s.roi,
            Some(Roi {
                x: 4,
                y: 4,
                width: 12,
                height: 12
            })
        );
        assert!((s.metric - expect).abs() < 1e-9, "{}", s.metric);
        // Without the marker it meters the whole frame: (100*200 + 300*20) / 400 = 65.
        let mut ae = MeanAe::new(cfg, limits(), 1000.0).unwrap();
        let s = ae.update(&f, None);
        assert_eq!(s.roi, None);
        assert!((s.metric - 65.0).abs() < 1e-9);
    }

    #[test]
    fn bad_config_names_key() {
        let cfg = MeanAeConfig {
            kappa: 0.0,
            ..Default::default()
        };
        let e = MeanAe::new(cfg, limits(), 1000.0)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("default.kappa"), "{e}");
    }
}
