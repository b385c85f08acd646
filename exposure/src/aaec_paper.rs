//! AAEC as the paper's code ran it (Ren, Lensgraf, Quattrini Li, ISER 2023;
//! Rennylex/adaptive_active_exposure_control, the published node
//! `src/aaec_exposure_node.cpp` with its launch file), beside markhold's own AAEC
//! (`aaec/`) so that the two can be compared. Each way the paper's text or markhold's
//! rules differ from the code is an option; the defaults are the code's.
//!
//! Per frame once a marker was seen, on the region (the code's: the tracker's whole-pixel
//! corner box padded by 10 % of its width and height on each side, truncated, clamped;
//! kept after the marker is lost):
//! - the metric and its derivative of [`PaperMetricEval`]: `|Ix|` ranks and scores
//!   (`metric = "abs-ix"`; `"published"`: `G = Ix^2 + Iy^2`), `dG/dt = 2 (Ix Dx + Iy Dy)`
//!   through the camera response `D = 1 / (g'(I) t)`, the code's degree-14 `g'`
//!   whatever the camera (`response = "code"`; `"site"`: the site's);
//! - momentum in linear exposure: `v = gamma v_prev + eta dM/dt`; when `|v|` exceeds the
//!   threshold (1 us) the step is taken and `v` kept, `t <- t + v`; otherwise the exposure
//!   and the stored momentum stay (`gate = "momentum"`; `"derivative"`: the paper's
//!   Algorithm 1, which steps when `|dM/dt|` reaches a threshold);
//! - what it sends: at or below 12 us becomes 13 us, above the camera's maximum the
//!   maximum, whole microseconds.
//!
//! It learns from every frame, taking it to be exposed with its last command
//! (`frames = "every"`; `"exposed-as-commanded"`: markhold's rule). Before the first
//! detection the camera's own auto exposure runs (`pre_detection = "camera-ae"`; markhold's
//! mean-intensity AE stands in for it), and the law starts from 5000 us
//! (`handoff_exposure_us`: the node reads back the driver's 0, "auto", and falls back to
//! its `default_exposure_time`); `"hold"` keeps the exposure instead.
//! Nothing else: no log-domain step, no per-frame bound, no clipped-pixel penalty, no
//! restarts, no fallback after a loss.

use crate::paper_code::{
    check_rate_scaling, code_command, code_region, scaled_rate, EtaScaling, GateStall, PaperFrames,
    PaperMetric, PaperMetricEval, PaperMetricParams, PaperResponse, PreDetection, StallWatch,
};
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, MeanAe, MeanAeConfig, Response, Roi,
};
use markhold_config::{open, open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// What holds the paper's law back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PaperGate {
    /// The code: a step is taken only when the momentum `|v|` exceeds `threshold_us`.
    Momentum,
    /// The paper's Algorithm 1: momentum and step only when `|dM/dt|` reaches
    /// `derivative_threshold` (the code's value for its momentum-free law and its AEC).
    Derivative,
}

/// The `[exposure.aaec_paper]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AaecPaperConfig {
    /// Percentile `p` of the weights' peak, (0, 1) (code: 0.9).
    pub percentile: f64,
    /// Sine-weight exponent `k`, 1..=9 (code: 5).
    pub weight_power: u32,
    /// Region padding on each side, fraction of the corner box, [0, 1] (code and
    /// paper: 0.1).
    pub roi_pad_frac: f64,
    /// Momentum factor gamma, [0, 1) (code: 0.9).
    pub momentum: f64,
    /// Learning rate eta: seconds of exposure per unit of `dM/dt`, with `M` in raw-Sobel
    /// grey levels (squared for `G`) and `t` in seconds, (0, 1e-6]. The code's history:
    /// 1e-9 (no momentum), 1e-10, 1e-12, 5e-13, 2e-13 (the published launch file).
    pub learning_rate: f64,
    /// With `gate = "momentum"`, a step is taken only when `|v|` exceeds this,
    /// microseconds, [0, 1000] (code: 1).
    pub threshold_us: f64,
    /// With `gate = "derivative"`, a step is taken only when `|dM/dt|` (per second)
    /// reaches this, [0, 1e12] (code: 15000).
    pub derivative_threshold: f64,
    /// Commands at or below `floor_us - 1` become `floor_us`, microseconds, [0, 1000]
    /// (code: 13). The camera's own limits still apply.
    pub floor_us: f64,
    /// `abs-ix` (code) or `published`.
    pub metric: PaperMetric,
    /// `code` (its degree-14 g') or `site` (the site's `[camera] response`).
    pub response: PaperResponse,
    /// `camera-ae` (code) or `hold`.
    pub pre_detection: PreDetection,
    /// With `pre_detection = "camera-ae"`: the exposure the law starts from at the first
    /// detection, microseconds, [0, 1e6]; 0 continues from the auto exposure's (code:
    /// 5000, its `default_exposure_time`).
    pub handoff_exposure_us: f64,
    /// `every` (code) or `exposed-as-commanded`.
    pub frames: PaperFrames,
    /// `momentum` (code) or `derivative` (the paper's Algorithm 1).
    pub gate: PaperGate,
    /// `none` (code) or `roi-side`: the rate times `sqrt(S / eta_reference_pixels)` for a
    /// region of `S` pixels.
    pub eta_scaling: EtaScaling,
    /// With `eta_scaling = "roi-side"`: the region size the learning rate is meant
    /// for, pixels, [1, 1e8].
    pub eta_reference_pixels: f64,
}

impl Default for AaecPaperConfig {
    fn default() -> Self {
        Self {
            percentile: 0.9,
            weight_power: 5,
            roi_pad_frac: 0.1,
            momentum: 0.9,
            learning_rate: 2e-13,
            threshold_us: 1.0,
            derivative_threshold: 15000.0,
            floor_us: 13.0,
            metric: PaperMetric::AbsIx,
            response: PaperResponse::Code,
            pre_detection: PreDetection::CameraAe,
            handoff_exposure_us: 5000.0,
            frames: PaperFrames::Every,
            gate: PaperGate::Momentum,
            eta_scaling: EtaScaling::None,
            eta_reference_pixels: 1e4,
        }
    }
}

impl AaecPaperConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.aaec_paper")
            .range("percentile", self.percentile, open(0.0, 1.0), "a percentile in (0, 1)")
            .range("weight_power", self.weight_power, 1..=9, "an exponent in 1..=9")
            .range("roi_pad_frac", self.roi_pad_frac, 0.0..=1.0, "a fraction in [0, 1]")
            .range("momentum", self.momentum, 0.0..1.0, "a factor in [0, 1)")
            .range("learning_rate", self.learning_rate, open_closed(0.0, 1e-6),
                "a rate in (0, 1e-6] s per unit of dM/dt (the code's: 1e-9 to 2e-13)")
            .range("threshold_us", self.threshold_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("derivative_threshold", self.derivative_threshold, 0.0..=1e12,
                "a derivative in [0, 1e12] per second")
            .range("floor_us", self.floor_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("handoff_exposure_us", self.handoff_exposure_us, 0.0..=1e6,
                "microseconds in [0, 1e6] (0: the auto exposure's)")
            .done()?;
        check_rate_scaling("exposure.aaec_paper", self.eta_scaling, self.eta_reference_pixels)
    }

    /// The metric settings of this section.
    pub fn metric_params(&self) -> PaperMetricParams {
        PaperMetricParams {
            metric: self.metric,
            percentile: self.percentile,
            weight_power: self.weight_power,
        }
    }

    /// The step a gate lets through, microseconds (for the stall report).
    fn gate_us(&self, rate: f64) -> f64 {
        match self.gate {
            PaperGate::Momentum => self.threshold_us,
            PaperGate::Derivative => rate * self.derivative_threshold * 1e6,
        }
    }
}

/// One update of the paper's law.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LawStep {
    /// The law's next exposure, microseconds (before what the code sends).
    pub next_us: f64,
    /// The step it computed (taken or not), microseconds.
    pub step_us: f64,
    /// The derivative passed its own gate (always, with the momentum gate).
    pub derivative_passed: bool,
    /// The step was taken.
    pub moved: bool,
}

/// The paper's update law on its own, in microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PaperMomentum {
    /// Stored momentum, microseconds.
    pub v_us: f64,
}

impl PaperMomentum {
    /// The next exposure from the current one `t_us` and the metric's derivative
    /// `dm_dt` (per second of exposure), with learning rate `rate`.
    pub fn step(&mut self, cfg: &AaecPaperConfig, rate: f64, t_us: f64, dm_dt: f64) -> LawStep {
        let v = cfg.momentum * self.v_us + rate * dm_dt * 1e6;
        let (pass, derivative_passed) = match cfg.gate {
            PaperGate::Momentum => (v.is_finite() && v.abs() > cfg.threshold_us, true),
            PaperGate::Derivative => {
                let p = dm_dt.abs() >= cfg.derivative_threshold && v.is_finite();
                (p, p)
            }
        };
        if pass {
            self.v_us = v;
        }
        LawStep {
            next_us: if pass { t_us + v } else { t_us },
            step_us: v,
            derivative_passed,
            moved: pass && v != 0.0,
        }
    }
}

/// AAEC as the paper's code ran it. See the module documentation.
pub struct AaecPaper {
    cfg: AaecPaperConfig,
    limits: ExposureLimits,
    eval: PaperMetricEval,
    law: PaperMomentum,
    /// The camera's auto exposure before the first detection.
    ae: MeanAe,
    roi: Option<Roi>,
    commanded_us: f64,
    stall: StallWatch,
    last_rate: f64,
}

impl AaecPaper {
    /// `site` is the camera's own response (used with `response = "site"`), `ae` the
    /// auto exposure that stands in for the camera's before the first detection.
    pub fn new(
        cfg: AaecPaperConfig,
        site: &Response,
        ae: MeanAeConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            eval: PaperMetricEval::new(&cfg.response.resolve(site)),
            law: PaperMomentum::default(),
            ae: MeanAe::new(ae, limits, initial_us)?,
            roi: None,
            commanded_us: limits.clamp(initial_us),
            stall: StallWatch::default(),
            last_rate: cfg.learning_rate,
            limits,
            cfg,
        })
    }

    /// The region it meters (none before the first detection).
    pub fn roi(&self) -> Option<Roi> {
        self.roi
    }

    /// Before the first detection: the camera's auto exposure, or nothing.
    fn before_detection(&mut self, frame: &Frame) -> ExposureStep {
        match self.cfg.pre_detection {
            PreDetection::Hold => ExposureStep::skipped(self.commanded_us),
            PreDetection::CameraAe => {
                let s = self.ae.update(frame, None);
                self.commanded_us = s.exposure_us;
                ExposureStep { roi: None, ..s }
            }
        }
    }
}

impl ExposureController for AaecPaper {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::AaecPaper
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        if !frame.is_consistent() {
            return ExposureStep::skipped(self.commanded_us);
        }
        if let Some(c) = marker {
            if let Some(r) = code_region(c, self.cfg.roi_pad_frac, frame.width, frame.height) {
                if self.roi.is_none() && self.cfg.pre_detection == PreDetection::CameraAe {
                    // The law takes over from the camera's auto exposure.
                    self.commanded_us = match self.cfg.handoff_exposure_us {
                        t if t > 0.0 => self.limits.clamp(t),
                        _ => self.ae.commanded_us(),
                    };
                }
                self.roi = Some(r);
            }
        }
        let Some(kept) = self.roi else {
            return self.before_detection(frame);
        };
        // The kept region of an earlier frame, within this one (a camera can change size).
        let roi = kept.clamp_to(frame.width, frame.height);
        let hold = ExposureStep::skipped(self.commanded_us);
        if roi.is_empty()
            || (self.cfg.frames == PaperFrames::ExposedAsCommanded
                && !exposed_as_commanded(frame, self.commanded_us))
        {
            return hold;
        }
        let params = self.cfg.metric_params();
        let Some(v) = self
            .eval
            .evaluate(frame.view(), roi, self.commanded_us, &params)
        else {
            return hold;
        };
        let rate = scaled_rate(
            self.cfg.learning_rate,
            self.cfg.eta_scaling,
            self.cfg.eta_reference_pixels,
            v.pixels,
        );
        self.last_rate = rate;
        let law = self.law.step(&self.cfg, rate, self.commanded_us, v.dm_dt);
        let gate_us = self.cfg.gate_us(rate);
        self.stall
            .record(law.step_us, law.derivative_passed, law.moved);
        self.stall.warn_once("aaec-paper", gate_us, rate);
        self.commanded_us = code_command(
            law.next_us,
            self.cfg.floor_us,
            &self.limits,
            self.commanded_us,
        );
        ExposureStep::used(self.commanded_us, v.m, Some(roi))
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.law = PaperMomentum::default();
        self.roi = None;
        self.commanded_us = self.limits.clamp(exposure_us);
        self.ae.reset(exposure_us);
        self.stall.reset();
    }

    fn gate_stall(&self) -> Option<GateStall> {
        self.stall
            .stall(self.cfg.gate_us(self.last_rate), self.last_rate)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_frames::{self, limits};
    use crate::ImageView;

    #[test]
    fn momentum_law_matches_a_hand_computed_sequence() {
        let cfg = AaecPaperConfig::default(); // gamma 0.9, threshold 1 us
        let eta = 2e-13;
        let mut law = PaperMomentum::default();
        // eta * dM/dt = 2e-13 * 1e7 s = 2 us.
        let s = law.step(&cfg, eta, 1000.0, 1e7);
        assert!((s.next_us - 1002.0).abs() < 1e-9 && s.moved, "{s:?}");
        // v = 0.9 * 2 + 2 = 3.8.
        let s = law.step(&cfg, eta, 1002.0, 1e7);
        assert!((s.next_us - 1005.8).abs() < 1e-9, "{s:?}");
        // v = 0.9 * 3.8 - 10 = -6.58.
        let s = law.step(&cfg, eta, 1005.0, -5e7);
        assert!((s.next_us - 998.42).abs() < 1e-9, "{s:?}");
        // v = 0.9 * -6.58 + 0.2 = -5.722.
        let s = law.step(&cfg, eta, 998.0, 1e6);
        assert!((s.next_us - 992.278).abs() < 1e-9, "{s:?}");
        assert!((law.v_us + 5.722).abs() < 1e-12);
    }

    #[test]
    fn sub_threshold_momentum_is_neither_applied_nor_kept() {
        let cfg = AaecPaperConfig::default();
        let mut law = PaperMomentum::default();
        // eta * dM/dt = 0.4 us < 1 us, every frame: nothing accumulates (the code).
        for _ in 0..10 {
            let s = law.step(&cfg, 2e-13, 500.0, 2e6);
            assert_eq!(s.next_us, 500.0);
            assert!(!s.moved);
        }
        assert_eq!(law.v_us, 0.0);
    }

    #[test]
    fn the_derivative_gate_is_algorithm_1() {
        let cfg = AaecPaperConfig {
            gate: PaperGate::Derivative,
            ..Default::default()
        };
        let mut law = PaperMomentum::default();
        // |dM/dt| under 15000: nothing, however large eta is.
        let s = law.step(&cfg, 1e-6, 500.0, 14000.0);
        assert!(!s.moved && s.next_us == 500.0 && !s.derivative_passed);
        // At 15000 the momentum is updated and applied even when |v| < 1 us.
        let s = law.step(&cfg, 2e-11, 500.0, 15000.0);
        assert!(s.moved && (s.next_us - 500.3).abs() < 1e-9, "{s:?}");
        assert!((law.v_us - 0.3).abs() < 1e-12);
    }

    /// A marker's corners on [`blocks`]' frame.
    const SQUARE: Corners = [[8.0, 8.0], [32.0, 8.0], [32.0, 24.0], [8.0, 24.0]];

    /// The law on a linear camera, starting at 1000 us.
    fn linear_at_1000(cfg: AaecPaperConfig) -> AaecPaper {
        AaecPaper::new(
            cfg,
            &Response::linear(),
            MeanAeConfig::default(),
            limits(),
            1000.0,
        )
        .unwrap()
    }

    /// A 40x30 frame of 8x8 blocks (40 / 200 grey) exposed for `t`.
    fn blocks(t: f64) -> Frame {
        test_frames::blocks(t, 40)
    }

    #[test]
    fn commands_are_clamped_and_whole_microseconds() {
        let cfg = AaecPaperConfig {
            learning_rate: 1e-9,
            pre_detection: PreDetection::Hold,
            ..Default::default()
        };
        let mut c = linear_at_1000(cfg);
        for _ in 0..5 {
            let s = c.update(&blocks(c.commanded_us()), Some(&SQUARE));
            assert!(s.used_frame);
            assert_eq!(s.exposure_us, s.exposure_us.trunc(), "{s:?}");
        }
    }

    #[test]
    fn before_the_first_detection_the_camera_ae_runs_then_the_law_starts_at_5000_us() {
        let cfg = AaecPaperConfig::default();
        let mut c = linear_at_1000(cfg.clone());
        let mut ae = MeanAe::new(MeanAeConfig::default(), limits(), 1000.0).unwrap();
        for _ in 0..4 {
            let f = blocks(c.commanded_us());
            let want = ae.update(&f, None).exposure_us;
            let got = c.update(&f, None);
            assert_eq!(got.exposure_us, want);
            assert!(got.roi.is_none());
        }
        // First detection: the law computes from 5000 us on this very frame.
        let f = blocks(c.commanded_us());
        let mut reference = PaperMetricEval::new(&Response::paper_code());
        let roi = code_region(&SQUARE, 0.1, 40, 30).unwrap();
        let v = reference
            .evaluate(f.view(), roi, 5000.0, &cfg.metric_params())
            .unwrap();
        let mut law = PaperMomentum::default();
        let next = law.step(&cfg, cfg.learning_rate, 5000.0, v.dm_dt).next_us;
        let s = c.update(&f, Some(&SQUARE));
        assert_eq!(s.exposure_us, code_command(next, 13.0, &limits(), 5000.0));
        assert_eq!(s.roi, Some(roi));
        // Lost: the region is kept.
        let s = c.update(&blocks(c.commanded_us()), None);
        assert_eq!(s.roi, Some(roi));
        assert!(s.used_frame);
    }

    #[test]
    fn every_frame_is_used_unless_told_otherwise() {
        let stale = blocks(123.0);
        for (frames, used) in [
            (PaperFrames::Every, true),
            (PaperFrames::ExposedAsCommanded, false),
        ] {
            let cfg = AaecPaperConfig {
                frames,
                pre_detection: PreDetection::Hold,
                ..Default::default()
            };
            let mut c = linear_at_1000(cfg);
            assert_eq!(c.update(&stale, Some(&SQUARE)).used_frame, used);
        }
    }

    #[test]
    fn a_law_under_its_gate_reports_the_stall() {
        let cfg = AaecPaperConfig {
            learning_rate: 1e-20,
            pre_detection: PreDetection::Hold,
            ..Default::default()
        };
        let mut c = linear_at_1000(cfg);
        for k in 0..40 {
            let s = c.update(&blocks(1000.0), Some(&SQUARE));
            assert_eq!(s.exposure_us, 1000.0);
            assert_eq!(c.gate_stall().is_some(), k + 1 >= 30, "frame {k}");
        }
        let s = c.gate_stall().unwrap();
        assert_eq!(s.gate_us, 1.0);
        assert!(s.largest_step_us > 0.0 && s.largest_step_us < 1.0, "{s:?}");
        let r = s.rate_to_pass.unwrap();
        assert!((r * s.largest_step_us / 1e-20 - 1.0).abs() < 1e-9, "{s:?}");
        // A rate that moves it: no stall.
        let cfg = AaecPaperConfig {
            learning_rate: r * 2.0,
            pre_detection: PreDetection::Hold,
            ..Default::default()
        };
        let mut c = linear_at_1000(cfg);
        for _ in 0..40 {
            let t = c.commanded_us();
            c.update(&blocks(t), Some(&SQUARE));
        }
        assert!(c.gate_stall().is_none());
    }

    #[test]
    fn metric_of_a_step_edge_by_hand() {
        // 4x3 image, left half 10, right half 50, linear camera at 1000 us, the whole
        // image as the region (12 pixels; reflect-101 at the edges). |Ix| per column:
        // 0, 160, 160, 0 in every row (the outer columns reflect onto their neighbour);
        // Iy = 0. D = I / t, so dG/dt = 2 G / t per pixel.
        let data = [10u8, 10, 50, 50, 10, 10, 50, 50, 10, 10, 50, 50];
        let view = ImageView::new(4, 3, &data).unwrap();
        let mut e = PaperMetricEval::new(&Response::linear());
        let roi = Roi {
            x: 0,
            y: 0,
            width: 4,
            height: 3,
        };
        let params = |metric| PaperMetricParams {
            metric,
            percentile: 0.9,
            weight_power: 5,
        };
        let v = e
            .evaluate(view, roi, 1000.0, &params(PaperMetric::AbsIx))
            .unwrap();
        assert_eq!(v.pixels, 12);
        let vp = e
            .evaluate(view, roi, 1000.0, &params(PaperMetric::Published))
            .unwrap();
        // Ranked ascending, 6 zeros then 6 edge pixels; the same weights for both keys.
        let mut w = Vec::new();
        let sum = crate::paper_code::code_weights(12, 0.9, 5, &mut w).unwrap();
        let top: f64 = w[6..].iter().sum::<f64>() / sum;
        assert!((v.m - 160.0 * top).abs() < 1e-9, "{}", v.m);
        assert!((vp.m - 25600.0 * top).abs() < 1e-6, "{}", vp.m);
        // dG/dt = 2 * 160 * (4 * 40 / 1e-3 s) on the edge pixels, either key.
        assert!((v.dm_dt - 5.12e7 * top).abs() < 1e-3, "{}", v.dm_dt);
        assert!((vp.dm_dt - v.dm_dt).abs() < 1e-6);
    }

    #[test]
    fn the_codes_learning_rates_are_accepted_and_out_of_range_named() {
        for eta in [1e-9, 1e-10, 1e-12, 5e-13, 2e-13] {
            let c = AaecPaperConfig {
                learning_rate: eta,
                ..Default::default()
            };
            c.validate().unwrap();
        }
        let e = AaecPaperConfig {
            learning_rate: 0.5,
            ..Default::default()
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("exposure.aaec_paper.learning_rate"), "{e}");
        let e = AaecPaperConfig {
            eta_scaling: EtaScaling::RoiSide,
            eta_reference_pixels: 0.0,
            ..Default::default()
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("exposure.aaec_paper.eta_reference_pixels"),
            "{e}"
        );
    }
}
