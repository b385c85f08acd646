//! AEC: active exposure control (Zhang, Forster, Scaramuzza, ICRA 2017), with the
//! safety nets of the official code (uzh-rpg/active_camera_exposure_control).
//!
//! The soft-percentile metric on the WHOLE image at a 1/8 pyramid level, then a plain
//! gradient step `t += rate * scale * t * s` with `s = dM/d(ln t) / M`:
//! - the official code adapts its rate to scene brightness with a calibrated profile
//!   of the 60th-percentile irradiance; normalizing the derivative by `M` (both scale
//!   with the square of the irradiance on a linear camera) serves the same purpose
//!   without a calibration file;
//! - `scale` grows 1.2x per frame while the last 15 derivatives agree in sign (capped
//!   at 1000) and resets to 1 when they do not;
//! - changes under `dead_band_us` are dropped; a change is clamped to 10% of `t`;
//! - when the mean grey is outside [70, 190] or more than half the pixels are >= 251,
//!   the step is `t * (127 / mean - 1)` instead (then clamped);
//! - `t` stays in [20, 15000] us by default (and in the camera's limits).

use crate::metric::{GradientMetric, MetricParams};
use crate::pyramid::Downsampler;
use markhold_config::{above, open, open_closed, Checks, ConfigError};

use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, Response,
};
use serde::{Deserialize, Serialize};

/// The `[exposure.aec]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AecConfig {
    /// Soft-percentile peak, (0, 1) (official: 0.7).
    pub percentile: f64,
    /// Sine-weight exponent, odd in 1..=9 (official: 5).
    pub weight_power: u32,
    /// Downsampling factor of the metered pyramid level, 1..=32 (official: 8).
    pub pyramid_factor: u32,
    /// Gradient-ascent rate on the scale-free slope, (0, 10].
    pub rate: f64,
    /// Frames of derivative history for the step scale, 2..=100 (official: 15).
    pub slope_history: u32,
    /// Step-scale growth while the history agrees in sign, [1, 4] (official: 1.2).
    pub slope_grow: f64,
    /// Step-scale cap, [1, 1e6] (official: 1000).
    pub slope_scale_max: f64,
    /// Changes smaller than this are dropped, microseconds (official: 1).
    pub dead_band_us: f64,
    /// Largest change per frame as a fraction of `t`, (0, 1] (official: 0.1).
    pub max_change_frac: f64,
    /// Mean grey range in which the gradient step is trusted (official: 70, 190).
    pub mean_low_grey: f64,
    pub mean_high_grey: f64,
    /// Grey of the intensity fallback's target (official: 127).
    pub target_grey: f64,
    /// Pixels at or above this grey count as over-exposed (official: 251).
    pub over_grey: u8,
    /// Over-exposed fraction above which the intensity fallback runs (official: 0.5).
    pub over_frac_max: f64,
    /// Saturation level and penalty of the metric (official: 252, 3).
    pub saturation_grey: u8,
    pub saturation_penalty: f64,
    /// Exposure range of the method, microseconds (official: 20, 15000), intersected
    /// with the camera's limits.
    pub exposure_min_us: f64,
    pub exposure_max_us: f64,
}

impl Default for AecConfig {
    fn default() -> Self {
        Self {
            percentile: 0.7,
            weight_power: 5,
            pyramid_factor: 8,
            rate: 0.5,
            slope_history: 15,
            slope_grow: 1.2,
            slope_scale_max: 1000.0,
            dead_band_us: 1.0,
            max_change_frac: 0.1,
            mean_low_grey: 70.0,
            mean_high_grey: 190.0,
            target_grey: 127.0,
            over_grey: 251,
            over_frac_max: 0.5,
            saturation_grey: 252,
            saturation_penalty: 3.0,
            exposure_min_us: 20.0,
            exposure_max_us: 15_000.0,
        }
    }
}

impl AecConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let (lo, hi) = (self.mean_low_grey, self.mean_high_grey);
        let (min_us, max_us) = (self.exposure_min_us, self.exposure_max_us);
        Checks::new("exposure.aec")
            .range("percentile", self.percentile, open(0.0, 1.0), "a fraction in (0, 1)")
            .odd("weight_power", self.weight_power, 1..=9, "an odd integer in 1..=9")
            .range("pyramid_factor", self.pyramid_factor, 1..=32, "a factor in 1..=32")
            .range("rate", self.rate, open_closed(0.0, 10.0), "a rate in (0, 10]")
            .range("slope_history", self.slope_history, 2..=100, "frames in 2..=100")
            .range("slope_grow", self.slope_grow, 1.0..=4.0, "a factor in [1, 4]")
            .range("slope_scale_max", self.slope_scale_max, 1.0..=1e6, "a cap in [1, 1e6]")
            .range("dead_band_us", self.dead_band_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("max_change_frac", self.max_change_frac, open_closed(0.0, 1.0), "a fraction in (0, 1]")
            .range("mean_low_grey", lo, 0.0..255.0, "a grey level in [0, 255)")
            .range("mean_high_grey", hi, open_closed(lo, 255.0), "a grey level above mean_low_grey, <= 255")
            .range("target_grey", self.target_grey, open(1.0, 254.0), "a grey level in (1, 254)")
            .range("over_frac_max", self.over_frac_max, open_closed(0.0, 1.0), "a fraction in (0, 1]")
            .range("saturation_grey", self.saturation_grey, 128.., "a grey level in 128..=255")
            .range("saturation_penalty", self.saturation_penalty, 0.0..=10.0, "a factor in [0, 10]")
            .positive("exposure_min_us", min_us, "microseconds > 0")
            .finite_range("exposure_max_us", max_us, above(min_us), "microseconds above exposure_min_us")
            .done()
    }

    /// The metric parameters this configuration implies.
    pub fn metric_params(&self) -> MetricParams {
        MetricParams::configured(
            self.percentile,
            self.weight_power,
            self.saturation_grey,
            self.saturation_penalty,
        )
    }
}

pub struct Aec {
    cfg: AecConfig,
    limits: ExposureLimits,
    metric: GradientMetric,
    down: Downsampler,
    commanded_us: f64,
    /// Ring of the last derivatives' signs (+1 / -1), `filled` of them valid.
    signs: Vec<i8>,
    next: usize,
    filled: usize,
    scale: f64,
}

impl Aec {
    pub fn new(
        cfg: AecConfig,
        response: &Response,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        // The method's own range, inside the camera's (the camera wins when they do not
        // overlap).
        let cam_lo = limits.min_us;
        let cam_hi = limits.effective_max_us().max(cam_lo);
        let lo = cfg.exposure_min_us.clamp(cam_lo, cam_hi);
        let hi = cfg.exposure_max_us.clamp(lo, cam_hi);
        let limits = ExposureLimits {
            min_us: lo,
            max_us: hi,
            fps: limits.fps,
        };
        Ok(Self {
            metric: GradientMetric::new(response, cfg.metric_params()),
            down: Downsampler::new(),
            commanded_us: limits.clamp(initial_us),
            limits,
            signs: vec![0; cfg.slope_history as usize],
            next: 0,
            filled: 0,
            scale: 1.0,
            cfg,
        })
    }

    /// Record the derivative's sign; grow the scale while the full history agrees.
    fn update_scale(&mut self, deriv: f64) {
        let n = self.signs.len();
        self.signs[self.next] = if deriv > 0.0 { 1 } else { -1 };
        self.next = (self.next + 1) % n;
        self.filled = (self.filled + 1).min(n);
        if self.filled < n {
            return;
        }
        let first = self.signs[0];
        if self.signs.iter().all(|&s| s == first) {
            self.scale = (self.scale * self.cfg.slope_grow).min(self.cfg.slope_scale_max);
        } else {
            self.scale = 1.0;
        }
    }
}

impl ExposureController for Aec {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::Aec
    }

    fn update(&mut self, frame: &Frame, _marker: Option<&Corners>) -> ExposureStep {
        let hold = ExposureStep::skipped(self.commanded_us);
        if !exposed_as_commanded(frame, self.commanded_us) || !frame.is_consistent() {
            return hold;
        }
        let small = self
            .down
            .run(frame.view(), self.cfg.pyramid_factor as usize);
        let (mut over, n) = (0usize, small.width * small.height);
        for y in 0..small.height {
            over += small
                .row(y)
                .iter()
                .filter(|&&p| p >= self.cfg.over_grey)
                .count();
        }
        let Some(mv) = self.metric.evaluate(small) else {
            return hold;
        };
        let t = self.commanded_us;
        let over_frac = over as f64 / n.max(1) as f64;
        let mut update = if mv.mean_grey < self.cfg.mean_low_grey
            || mv.mean_grey > self.cfg.mean_high_grey
            || over_frac > self.cfg.over_frac_max
        {
            // Too dark or too bright for the gradient: aim the mean at mid grey.
            t * (self.cfg.target_grey / mv.mean_grey.max(0.5) - 1.0)
        } else {
            let s = mv.dm_dlnt / mv.m.max(1e-9);
            self.update_scale(s);
            self.cfg.rate * self.scale * t * s
        };
        if update.abs() < self.cfg.dead_band_us {
            update = 0.0;
        }
        let cap = self.cfg.max_change_frac * t;
        update = update.clamp(-cap, cap);
        self.commanded_us = self.limits.clamp(t + update);
        ExposureStep::used(self.commanded_us, mv.m, None)
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.commanded_us = self.limits.clamp(exposure_us);
        self.filled = 0;
        self.next = 0;
        self.scale = 1.0;
    }
}
