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
use crate::{
    exposed_as_commanded, invalid, Corners, ExposureController, ExposureError, ExposureLimits,
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
    /// Saturation level and penalty of the metric (official: 250, 3).
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
            saturation_grey: 250,
            saturation_penalty: 3.0,
            exposure_min_us: 20.0,
            exposure_max_us: 15_000.0,
        }
    }
}

impl AecConfig {
    pub fn validate(&self) -> Result<(), ExposureError> {
        let check = |ok: bool, name: &str, v: &dyn std::fmt::Display, exp: &str| {
            if ok {
                Ok(())
            } else {
                Err(invalid(&format!("aec.{name}"), v, exp))
            }
        };
        let v = self.percentile;
        check(v > 0.0 && v < 1.0, "percentile", &v, "a fraction in (0, 1)")?;
        let v = self.weight_power;
        check(
            !v.is_multiple_of(2) && v <= 9,
            "weight_power",
            &v,
            "an odd integer in 1..=9",
        )?;
        let v = self.pyramid_factor;
        check(
            (1..=32).contains(&v),
            "pyramid_factor",
            &v,
            "a factor in 1..=32",
        )?;
        let v = self.rate;
        check(v > 0.0 && v <= 10.0, "rate", &v, "a rate in (0, 10]")?;
        let v = self.slope_history;
        check(
            (2..=100).contains(&v),
            "slope_history",
            &v,
            "frames in 2..=100",
        )?;
        let v = self.slope_grow;
        check(
            (1.0..=4.0).contains(&v),
            "slope_grow",
            &v,
            "a factor in [1, 4]",
        )?;
        let v = self.slope_scale_max;
        check(
            (1.0..=1e6).contains(&v),
            "slope_scale_max",
            &v,
            "a cap in [1, 1e6]",
        )?;
        let v = self.dead_band_us;
        check(
            (0.0..=1000.0).contains(&v),
            "dead_band_us",
            &v,
            "microseconds in [0, 1000]",
        )?;
        let v = self.max_change_frac;
        check(
            v > 0.0 && v <= 1.0,
            "max_change_frac",
            &v,
            "a fraction in (0, 1]",
        )?;
        let (lo, hi) = (self.mean_low_grey, self.mean_high_grey);
        check(
            (0.0..255.0).contains(&lo),
            "mean_low_grey",
            &lo,
            "a grey level in [0, 255)",
        )?;
        check(
            hi > lo && hi <= 255.0,
            "mean_high_grey",
            &hi,
            "a grey level above mean_low_grey, <= 255",
        )?;
        let v = self.target_grey;
        check(
            v > 1.0 && v < 254.0,
            "target_grey",
            &v,
            "a grey level in (1, 254)",
        )?;
        let v = self.over_frac_max;
        check(
            v > 0.0 && v <= 1.0,
            "over_frac_max",
            &v,
            "a fraction in (0, 1]",
        )?;
        let v = self.saturation_grey;
        check(v >= 128, "saturation_grey", &v, "a grey level in 128..=255")?;
        let v = self.saturation_penalty;
        check(
            (0.0..=10.0).contains(&v),
            "saturation_penalty",
            &v,
            "a factor in [0, 10]",
        )?;
        let (lo, hi) = (self.exposure_min_us, self.exposure_max_us);
        check(
            lo > 0.0 && lo.is_finite(),
            "exposure_min_us",
            &lo,
            "microseconds > 0",
        )?;
        check(
            hi > lo && hi.is_finite(),
            "exposure_max_us",
            &hi,
            "microseconds above exposure_min_us",
        )?;
        Ok(())
    }

    /// The metric parameters this configuration implies.
    pub fn metric_params(&self) -> MetricParams {
        MetricParams {
            percentile: self.percentile,
            weight_power: self.weight_power,
            saturation_grey: self.saturation_grey,
            saturation_penalty: self.saturation_penalty,
            ..MetricParams::default()
        }
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
        let hold = ExposureStep {
            exposure_us: self.commanded_us,
            metric: f64::NAN,
            used_frame: false,
            roi: None,
        };
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
        ExposureStep {
            exposure_us: self.commanded_us,
            metric: mv.m,
            used_frame: true,
            roi: None,
        }
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
