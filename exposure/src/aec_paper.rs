//! AEC as the AAEC paper's code ran it (its `active_aec_ori` branch,
//! Rennylex/adaptive_active_exposure_control `src/changeParam.cpp`, from e6478c6), beside
//! markhold's `aec` (Zhang, Forster & Scaramuzza's official code's safety nets).
//!
//! Once a marker has been seen (before that nothing is commanded, `pre_detection =
//! "hold"`), on every frame: the paper's metric and derivative ([`PaperMetricEval`]) over
//! the WHOLE frame at full resolution, `|Ix|` ranking and scoring, p 0.9, k 5, the code's
//! degree-14 `g'` whatever the camera; then a plain gradient step `t <- t + alpha dM/dt`
//! with a fixed `alpha` (1e-8 s per unit of dM/dt), taken only when `|dM/dt| > 15000` and
//! the step exceeds 0.1 us; what it sends: at or below 12 us becomes 13 us, above the
//! camera's maximum the maximum, whole microseconds. No per-frame bound, no adaptive rate,
//! no fallback.

use crate::paper_code::{
    check_rate_scaling, code_command, scaled_rate, EtaScaling, GateStall, PaperFrames, PaperMetric,
    PaperMetricEval, PaperMetricParams, PaperResponse, PreDetection, StallWatch,
};
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, MeanAe, MeanAeConfig, Response,
};
use markhold_config::{open, open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// The `[exposure.aec_paper]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AecPaperConfig {
    /// Percentile `p` of the weights' peak, (0, 1) (code: 0.9).
    pub percentile: f64,
    /// Sine-weight exponent `k`, 1..=9 (code: 5).
    pub weight_power: u32,
    /// Step `alpha`: seconds of exposure per unit of `dM/dt`, (0, 1e-3] (code: 1e-8).
    pub rate: f64,
    /// A step is taken only when `|dM/dt|` (per second) exceeds this, [0, 1e12] (code:
    /// 15000).
    pub derivative_threshold: f64,
    /// ... and only when the step exceeds this, microseconds, [0, 1000] (code: 0.1).
    pub min_step_us: f64,
    /// Commands at or below `floor_us - 1` become `floor_us`, microseconds, [0, 1000]
    /// (code: 13).
    pub floor_us: f64,
    /// `abs-ix` (code) or `published`.
    pub metric: PaperMetric,
    /// `code` (its degree-14 g') or `site`.
    pub response: PaperResponse,
    /// `hold` (code: it starts at the first detection) or `camera-ae`.
    pub pre_detection: PreDetection,
    /// `every` (code) or `exposed-as-commanded`.
    pub frames: PaperFrames,
    /// `none` (code) or `roi-side` (here the region is the whole frame).
    pub eta_scaling: EtaScaling,
    /// With `eta_scaling = "roi-side"`: the frame size the rate is meant for, pixels.
    pub eta_reference_pixels: f64,
}

impl Default for AecPaperConfig {
    fn default() -> Self {
        Self {
            percentile: 0.9,
            weight_power: 5,
            rate: 1e-8,
            derivative_threshold: 15000.0,
            min_step_us: 0.1,
            floor_us: 13.0,
            metric: PaperMetric::AbsIx,
            response: PaperResponse::Code,
            pre_detection: PreDetection::Hold,
            frames: PaperFrames::Every,
            eta_scaling: EtaScaling::None,
            eta_reference_pixels: 1e6,
        }
    }
}

impl AecPaperConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.aec_paper")
            .range("percentile", self.percentile, open(0.0, 1.0), "a percentile in (0, 1)")
            .range("weight_power", self.weight_power, 1..=9, "an exponent in 1..=9")
            .range("rate", self.rate, open_closed(0.0, 1e-3),
                "a rate in (0, 1e-3] s per unit of dM/dt (the code's: 1e-8)")
            .range("derivative_threshold", self.derivative_threshold, 0.0..=1e12,
                "a derivative in [0, 1e12] per second")
            .range("min_step_us", self.min_step_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("floor_us", self.floor_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .done()?;
        check_rate_scaling("exposure.aec_paper", self.eta_scaling, self.eta_reference_pixels)
    }
}

/// AEC as the paper's code ran it. See the module documentation.
pub struct AecPaper {
    cfg: AecPaperConfig,
    limits: ExposureLimits,
    eval: PaperMetricEval,
    ae: MeanAe,
    detected: bool,
    commanded_us: f64,
    stall: StallWatch,
    last_rate: f64,
}

impl AecPaper {
    pub fn new(
        cfg: AecPaperConfig,
        site: &Response,
        ae: MeanAeConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            eval: PaperMetricEval::new(&cfg.response.resolve(site)),
            ae: MeanAe::new(ae, limits, initial_us)?,
            detected: false,
            commanded_us: limits.clamp(initial_us),
            stall: StallWatch::default(),
            last_rate: cfg.rate,
            limits,
            cfg,
        })
    }
}

impl ExposureController for AecPaper {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::AecPaper
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        let hold = ExposureStep::skipped(self.commanded_us);
        if !frame.is_consistent() {
            return hold;
        }
        if marker.is_some() && !self.detected {
            self.detected = true;
            if self.cfg.pre_detection == PreDetection::CameraAe {
                self.commanded_us = self.ae.commanded_us();
            }
        }
        if !self.detected {
            return match self.cfg.pre_detection {
                PreDetection::Hold => hold,
                PreDetection::CameraAe => {
                    let s = self.ae.update(frame, None);
                    self.commanded_us = s.exposure_us;
                    s
                }
            };
        }
        if self.cfg.frames == PaperFrames::ExposedAsCommanded
            && !exposed_as_commanded(frame, self.commanded_us)
        {
            return hold;
        }
        let params = PaperMetricParams {
            metric: self.cfg.metric,
            percentile: self.cfg.percentile,
            weight_power: self.cfg.weight_power,
        };
        let Some(v) =
            self.eval
                .evaluate(frame.view(), frame.full_roi(), self.commanded_us, &params)
        else {
            return hold;
        };
        let rate = scaled_rate(
            self.cfg.rate,
            self.cfg.eta_scaling,
            self.cfg.eta_reference_pixels,
            v.pixels,
        );
        self.last_rate = rate;
        let step_us = rate * v.dm_dt * 1e6;
        let derivative_passed = v.dm_dt.abs() > self.cfg.derivative_threshold;
        let moved = derivative_passed && step_us.abs() > self.cfg.min_step_us;
        let next = if moved {
            self.commanded_us + step_us
        } else {
            self.commanded_us
        };
        self.stall.record(step_us, derivative_passed, moved);
        self.stall
            .warn_once("aec-paper", self.cfg.min_step_us, rate);
        self.commanded_us = code_command(next, self.cfg.floor_us, &self.limits, self.commanded_us);
        ExposureStep::used(self.commanded_us, v.m, None)
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.detected = false;
        self.commanded_us = self.limits.clamp(exposure_us);
        self.ae.reset(exposure_us);
        self.stall.reset();
    }

    fn gate_stall(&self) -> Option<GateStall> {
        self.stall.stall(self.cfg.min_step_us, self.last_rate)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_frames::{blocks, limits};

    fn linear_at_1000(cfg: AecPaperConfig) -> AecPaper {
        AecPaper::new(
            cfg,
            &Response::linear(),
            MeanAeConfig::default(),
            limits(),
            1000.0,
        )
        .unwrap()
    }

    #[test]
    fn holds_until_a_marker_is_seen_then_steps_on_the_whole_frame() {
        let cfg = AecPaperConfig::default();
        let mut c = linear_at_1000(cfg);
        let s = c.update(&blocks(1000.0, 40), None);
        assert!(!s.used_frame && s.exposure_us == 1000.0);
        let corners = [[8.0, 8.0], [32.0, 8.0], [32.0, 24.0], [8.0, 24.0]];
        let f = blocks(1000.0, 40);
        let mut e = PaperMetricEval::new(&Response::paper_code());
        let params = PaperMetricParams {
            metric: PaperMetric::AbsIx,
            percentile: 0.9,
            weight_power: 5,
        };
        let v = e.evaluate(f.view(), f.full_roi(), 1000.0, &params).unwrap();
        assert!(v.dm_dt.abs() > 15000.0, "{v:?}");
        let want = code_command(1000.0 + 1e-8 * v.dm_dt * 1e6, 13.0, &limits(), 1000.0);
        let s = c.update(&f, Some(&corners));
        assert!(s.used_frame && s.roi.is_none());
        assert_eq!(s.exposure_us, want);
        // Later frames need no marker.
        assert!(c.update(&blocks(c.commanded_us(), 40), None).used_frame);
    }

    #[test]
    fn a_small_derivative_or_step_is_not_taken() {
        // A flat frame: dM/dt = 0 < 15000.
        let cfg = AecPaperConfig::default();
        let mut c = linear_at_1000(cfg);
        let corners = [[8.0, 8.0], [32.0, 8.0], [32.0, 24.0], [8.0, 24.0]];
        let s = c.update(&blocks(1000.0, 200), Some(&corners));
        assert!(s.used_frame);
        assert_eq!(s.exposure_us, 1000.0);
        // A tiny rate: the derivative passes, the step does not (0.1 us).
        let cfg = AecPaperConfig {
            rate: 1e-20,
            ..Default::default()
        };
        let mut c = linear_at_1000(cfg);
        for _ in 0..30 {
            assert_eq!(
                c.update(&blocks(1000.0, 40), Some(&corners)).exposure_us,
                1000.0
            );
        }
        let stall = c.gate_stall().unwrap();
        assert!(stall.rate_to_pass.is_some(), "{stall:?}");
    }
}
