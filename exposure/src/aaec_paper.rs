//! AAEC exactly as published (Ren, Lensgraf, Quattrini Li, ISER 2023), beside
//! markhold's own AAEC (`aaec.rs`) so that the two can be compared.
//!
//! Per used frame, on the RoI (the marker's corner box padded by 10 % of its width and
//! height on each side, clamped to the image; kept after the marker is lost, as the
//! paper's code does):
//! - `G = Ix^2 + Iy^2` with raw 3x3 Sobel (OpenCV's `Sobel(ksize = 3)`, no
//!   normalization), pixels ranked by `G` ascending (ties by position, row-major);
//!   `metric = "abs-ix"` ranks and scores by `|Ix|` instead, as the paper's code does;
//! - soft-percentile weights `sin(pi i / (2 n))^k` up to `n = floor(p S)`, then
//!   `sin(pi/2 - pi (i - n) / (2 (S - n)))^k`, normalized to sum 1; `M = sum w_i G_i`;
//! - through the camera response, `D = dI/dt = 1 / (g'(I) t)` with `t` in seconds;
//!   `dG/dt = 2 (Ix Dx + Iy Dy)` (same Sobel), `dM/dt = sum w_i (dG/dt)_i`;
//! - momentum in linear exposure: `v = gamma v_prev + eta dM/dt`; when `|v|` exceeds
//!   the threshold (1 us) the step is taken and `v` kept, `t <- t + v`; otherwise the
//!   exposure and the stored momentum stay as they were;
//! - clamps: a command at or below 12 us becomes 13 us; above the camera's maximum it is
//!   the maximum.
//!
//! Nothing else: no log-domain step, no per-frame bound, no clipped-pixel penalty, no
//! restarts, no fallback. Before the first detection there is no RoI and the exposure
//! is held (the paper's code hands the camera back to its own auto exposure there).
//! Like every markhold controller it learns only from frames exposed with the value it
//! last commanded.

use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, ImageView, Response, Roi,
};
use markhold_config::{open, open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// Which gradient the paper's metric ranks and scores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PaperMetric {
    /// As published: `G = Ix^2 + Iy^2` for ranking, score and derivative.
    Published,
    /// As in the paper's code: rank and score by `|Ix|`, differentiate `Ix^2 + Iy^2`.
    AbsIx,
}

/// The `[exposure.aaec_paper]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AaecPaperConfig {
    /// Percentile `p` of the weights' peak, (0, 1) (paper's code: 0.9).
    pub percentile: f64,
    /// Sine-weight exponent `k`, 1..=9 (paper: 5).
    pub weight_power: u32,
    /// RoI padding on each side, fraction of the corner box, [0, 1] (paper: 0.1).
    pub roi_pad_frac: f64,
    /// Momentum factor gamma, [0, 1) (paper: 0.9).
    pub momentum: f64,
    /// Learning rate eta in the paper's units: seconds of exposure per unit of `dM/dt`,
    /// with `M` in raw-Sobel grey levels squared and `t` in seconds, (0, 1e-6]. The
    /// paper's code ran 2e-13 to 1e-12 (it depends on the image scale).
    pub learning_rate: f64,
    /// A step is taken only when `|v|` exceeds this, microseconds, [0, 1000] (paper's
    /// code: 1).
    pub threshold_us: f64,
    /// Commands at or below `floor_us - 1` become `floor_us`, microseconds, [0, 1000]
    /// (paper's code: 13). The camera's own limits still apply.
    pub floor_us: f64,
    /// `published` (default) or `abs-ix` (the paper's code).
    pub metric: PaperMetric,
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
            floor_us: 13.0,
            metric: PaperMetric::Published,
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
                "a rate in (0, 1e-6] s per unit of dM/dt (paper: 2e-13 to 1e-12)")
            .range("threshold_us", self.threshold_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("floor_us", self.floor_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .done()
    }
}

/// The paper's update law on its own, in microseconds: `v = gamma v + eta dM/dt`,
/// applied (and kept) only when `|v| > threshold`; then the clamps.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PaperMomentum {
    /// Stored momentum, microseconds.
    pub v_us: f64,
}

impl PaperMomentum {
    /// The next command from the current one `t_us` and the metric's derivative
    /// `dm_dt` (per second of exposure).
    pub fn step(
        &mut self,
        cfg: &AaecPaperConfig,
        limits: &ExposureLimits,
        t_us: f64,
        dm_dt: f64,
    ) -> f64 {
        let v = cfg.momentum * self.v_us + cfg.learning_rate * dm_dt * 1e6;
        let mut next = t_us;
        if v.is_finite() && v.abs() > cfg.threshold_us {
            self.v_us = v;
            next = t_us + v;
        }
        if next <= cfg.floor_us - 1.0 {
            next = cfg.floor_us;
        }
        limits.clamp(next)
    }
}

/// The paper's metric and its derivative on one view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PaperMetricValue {
    pub m: f64,
    /// `dM/dt`, per second of exposure.
    pub dm_dt: f64,
    pub pixels: usize,
}

/// The paper's metric with reused buffers (naive: a full sort per frame, as published).
#[derive(Debug, Clone)]
pub struct PaperMetricEval {
    /// `1 / g'(I)` per grey level (`D` times the exposure in seconds).
    di_dt_s: [f64; 256],
    /// (ranking key, position, dG/dt * t) per pixel.
    pixels: Vec<(f64, u32, f64)>,
}

impl PaperMetricEval {
    pub fn new(response: &Response) -> Self {
        let mut di_dt_s = [0.0; 256];
        for (i, d) in di_dt_s.iter_mut().enumerate() {
            *d = response.di_dlnt(i as u8);
        }
        Self {
            di_dt_s,
            pixels: Vec::new(),
        }
    }

    /// `M` and `dM/dt` of `view` exposed for `t_us`, over its interior pixels (the
    /// 3x3 Sobel needs a neighbour on each side). `None` below 3x3.
    pub fn evaluate(
        &mut self,
        view: ImageView<'_>,
        t_us: f64,
        cfg: &AaecPaperConfig,
    ) -> Option<PaperMetricValue> {
        let (w, h) = (view.width, view.height);
        if w < 3 || h < 3 || t_us.is_nan() || t_us <= 0.0 {
            return None;
        }
        let t_s = t_us * 1e-6;
        self.pixels.clear();
        let need = (w - 2) * (h - 2);
        if self.pixels.capacity() < need {
            self.pixels.reserve(need);
        }
        let d = &self.di_dt_s;
        for y in 1..h - 1 {
            let (r0, r1, r2) = (view.row(y - 1), view.row(y), view.row(y + 1));
            for x in 1..w - 1 {
                let i = |r: &[u8], x: usize| r[x] as f64;
                let dd = |r: &[u8], x: usize| d[r[x] as usize];
                let ix = (i(r0, x + 1) - i(r0, x - 1))
                    + 2.0 * (i(r1, x + 1) - i(r1, x - 1))
                    + (i(r2, x + 1) - i(r2, x - 1));
                let iy = (i(r2, x - 1) + 2.0 * i(r2, x) + i(r2, x + 1))
                    - (i(r0, x - 1) + 2.0 * i(r0, x) + i(r0, x + 1));
                let dx = (dd(r0, x + 1) - dd(r0, x - 1))
                    + 2.0 * (dd(r1, x + 1) - dd(r1, x - 1))
                    + (dd(r2, x + 1) - dd(r2, x - 1));
                let dy = (dd(r2, x - 1) + 2.0 * dd(r2, x) + dd(r2, x + 1))
                    - (dd(r0, x - 1) + 2.0 * dd(r0, x) + dd(r0, x + 1));
                let key = match cfg.metric {
                    PaperMetric::Published => ix * ix + iy * iy,
                    PaperMetric::AbsIx => ix.abs(),
                };
                let pos = (y * w + x) as u32;
                self.pixels.push((key, pos, 2.0 * (ix * dx + iy * dy)));
            }
        }
        self.pixels
            .sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let s = self.pixels.len();
        let n = (s as f64 * cfg.percentile).floor() as usize;
        let k = cfg.weight_power as i32;
        let half_pi = std::f64::consts::FRAC_PI_2;
        let weight = |i: usize| {
            let arg = if i <= n {
                if n == 0 {
                    0.0
                } else {
                    half_pi * i as f64 / n as f64
                }
            } else {
                half_pi - half_pi * (i - n) as f64 / (s - n) as f64
            };
            arg.sin().powi(k)
        };
        let (mut wsum, mut m, mut dm) = (0.0, 0.0, 0.0);
        for (i, p) in self.pixels.iter().enumerate() {
            let wi = weight(i);
            wsum += wi;
            m += wi * p.0;
            dm += wi * p.2;
        }
        if wsum.is_nan() || wsum <= 0.0 {
            return None;
        }
        Some(PaperMetricValue {
            m: m / wsum,
            dm_dt: dm / wsum / t_s,
            pixels: s,
        })
    }
}

/// AAEC as published. See the module documentation.
pub struct AaecPaper {
    cfg: AaecPaperConfig,
    limits: ExposureLimits,
    eval: PaperMetricEval,
    law: PaperMomentum,
    roi: Option<Roi>,
    commanded_us: f64,
}

impl AaecPaper {
    pub fn new(
        cfg: AaecPaperConfig,
        response: &Response,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        Ok(Self {
            eval: PaperMetricEval::new(response),
            law: PaperMomentum::default(),
            roi: None,
            commanded_us: limits.clamp(initial_us),
            limits,
            cfg,
        })
    }
}

impl ExposureController for AaecPaper {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::AaecPaper
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        let hold = ExposureStep::skipped(self.commanded_us);
        if !frame.is_consistent() {
            return hold;
        }
        if let Some(c) = marker {
            let pad = self.cfg.roi_pad_frac as f32;
            if let Some(r) = Roi::from_corners_padded(c, pad, frame.width, frame.height) {
                self.roi = Some(r);
            }
        }
        // The kept RoI of an earlier frame, within this one (a camera can change size).
        let Some(roi) = self.roi.map(|r| r.clamp_to(frame.width, frame.height)) else {
            return hold;
        };
        if roi.is_empty() || !exposed_as_commanded(frame, self.commanded_us) {
            return ExposureStep { roi: None, ..hold };
        }
        let view = frame.view().crop(roi);
        let Some(v) = self.eval.evaluate(view, self.commanded_us, &self.cfg) else {
            return hold;
        };
        self.commanded_us = self
            .law
            .step(&self.cfg, &self.limits, self.commanded_us, v.dm_dt);
        ExposureStep {
            exposure_us: self.commanded_us,
            metric: v.m,
            used_frame: true,
            roi: Some(roi),
        }
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.law = PaperMomentum::default();
        self.roi = None;
        self.commanded_us = self.limits.clamp(exposure_us);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> ExposureLimits {
        ExposureLimits {
            min_us: 5.0,
            max_us: 20000.0,
            fps: 30.0,
        }
    }

    #[test]
    fn momentum_law_matches_a_hand_computed_sequence() {
        let cfg = AaecPaperConfig::default(); // gamma 0.9, eta 2e-13 s, threshold 1 us
        let mut law = PaperMomentum::default();
        // eta * dM/dt = 2e-13 * 1e7 s = 2 us.
        let t1 = law.step(&cfg, &limits(), 1000.0, 1e7);
        assert!((t1 - 1002.0).abs() < 1e-9, "{t1}");
        // v = 0.9 * 2 + 2 = 3.8.
        let t2 = law.step(&cfg, &limits(), t1, 1e7);
        assert!((t2 - 1005.8).abs() < 1e-9, "{t2}");
        // v = 0.9 * 3.8 - 10 = -6.58.
        let t3 = law.step(&cfg, &limits(), t2, -5e7);
        assert!((t3 - 999.22).abs() < 1e-9, "{t3}");
        // v = 0.9 * -6.58 + 0.2 = -5.722.
        let t4 = law.step(&cfg, &limits(), t3, 1e6);
        assert!((t4 - 993.498).abs() < 1e-9, "{t4}");
        assert!((law.v_us + 5.722).abs() < 1e-12);
    }

    #[test]
    fn sub_threshold_momentum_is_neither_applied_nor_kept() {
        let cfg = AaecPaperConfig::default();
        let mut law = PaperMomentum::default();
        // eta * dM/dt = 0.4 us < 1 us, every frame: nothing accumulates (paper's code).
        for _ in 0..10 {
            assert_eq!(law.step(&cfg, &limits(), 500.0, 2e6), 500.0);
        }
        assert_eq!(law.v_us, 0.0);
    }

    #[test]
    fn clamps_are_the_papers() {
        let cfg = AaecPaperConfig::default();
        let mut law = PaperMomentum::default();
        // 20 - 10 = 10 us <= 12: becomes 13.
        assert_eq!(law.step(&cfg, &limits(), 20.0, -5e7), 13.0);
        let mut law = PaperMomentum::default();
        // 12.5 us is above 12: kept.
        assert!((law.step(&cfg, &limits(), 14.5, -1e7) - 12.5).abs() < 1e-9);
        let mut law = PaperMomentum::default();
        assert_eq!(law.step(&cfg, &limits(), 19990.0, 1e9), 20000.0);
    }

    #[test]
    fn metric_of_a_step_edge_by_hand() {
        // 4x3 image, left half 10, right half 50, linear camera at 1000 us. Interior
        // pixels (1,1) and (2,1): both see the edge, Ix = 4 * 40 = 160, Iy = 0.
        // D = I / t: Dx = 4 * 40 / 1e-3 s. dG/dt = 2 * 160 * 160000 = 5.12e7 per s.
        let data = [10u8, 10, 50, 50, 10, 10, 50, 50, 10, 10, 50, 50];
        let view = ImageView::new(4, 3, &data).unwrap();
        let mut e = PaperMetricEval::new(&Response::linear());
        let cfg = AaecPaperConfig::default();
        let v = e.evaluate(view, 1000.0, &cfg).unwrap();
        assert_eq!(v.pixels, 2);
        assert!((v.m - 25600.0).abs() < 1e-6, "{}", v.m);
        assert!((v.dm_dt - 5.12e7).abs() < 1e-3, "{}", v.dm_dt);
        let abs = AaecPaperConfig {
            metric: PaperMetric::AbsIx,
            ..cfg
        };
        let v = e.evaluate(view, 1000.0, &abs).unwrap();
        assert!((v.m - 160.0).abs() < 1e-9, "{}", v.m);
        assert!((v.dm_dt - 5.12e7).abs() < 1e-3, "{}", v.dm_dt);
    }

    #[test]
    fn the_papers_learning_rates_are_accepted_and_out_of_range_named() {
        for eta in [2e-13, 5e-13, 1e-12] {
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
    }
}
