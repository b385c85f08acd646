//! GEC as the AAEC paper ran it as a baseline, beside Shim's published GEC (`gec.rs`).
//!
//! Shim's information metric and update rule (`gec.rs`), with the paper's settings:
//! metered on the marker's corner box padded by 25 px on each side (full resolution),
//! 11 anchor gammas, activation threshold delta 0.04 and Kp 1e-8. The paper gives the
//! anchors' count, not their values: markhold spaces them geometrically over the
//! published range, `1.9^(j/5)` for j = -5..=5 (1/1.9 .. 1.9, 1 in the middle). The
//! region is kept after the marker is lost; before the first detection the whole
//! frame is metered. No fallback for a featureless region.

use crate::gec::{best_gamma, fit_quintic_points, gec_ratio, GecScorer};
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, GecConfig, Roi,
};
use markhold_config::{open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// Number of anchor gammas of the paper's GEC baseline.
pub const GEC_PAPER_ANCHORS: usize = 11;

/// The paper's anchors (see the module documentation).
pub fn gec_paper_gammas() -> [f64; GEC_PAPER_ANCHORS] {
    let mut g = [1.0; GEC_PAPER_ANCHORS];
    for (j, v) in g.iter_mut().enumerate() {
        *v = 1.9f64.powf((j as f64 - 5.0) / 5.0);
    }
    g
}

/// The `[exposure.gec_paper]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GecPaperConfig {
    /// Padding of the marker's corner box on each side, pixels, 0..=1000 (paper: 25).
    pub roi_pad_px: u32,
    /// Activation threshold delta, [0, 1) (paper: 0.04).
    pub delta: f64,
    /// Mapping sharpness lambda, (0, 1e6] (1000, as published).
    pub lambda: f64,
    /// Proportional gain Kp, (0, 2] (paper: 1e-8).
    pub kp: f64,
    /// Nonlinearity d of the update, (0, 10] (0.1, as published).
    pub d: f64,
}

impl Default for GecPaperConfig {
    fn default() -> Self {
        Self {
            roi_pad_px: 25,
            delta: 0.04,
            lambda: 1000.0,
            kp: 1e-8,
            d: 0.1,
        }
    }
}

impl GecPaperConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.gec_paper")
            .range("roi_pad_px", self.roi_pad_px, 0..=1000, "pixels in 0..=1000")
            .range("delta", self.delta, 0.0..1.0, "a threshold in [0, 1)")
            .range("lambda", self.lambda, open_closed(0.0, 1e6), "a value in (0, 1e6]")
            .range("kp", self.kp, open_closed(0.0, 2.0), "a gain in (0, 2]")
            .range("d", self.d, open_closed(0.0, 10.0), "a value in (0, 10]")
            .done()
    }

    fn scorer_config(&self) -> GecConfig {
        GecConfig {
            downsample: 1,
            delta: self.delta,
            lambda: self.lambda,
            kp: self.kp,
            d: self.d,
            no_information_fallback: false,
        }
    }
}

/// The marker's corner box padded by `pad` pixels on each side, clamped to the image.
fn padded_box(c: &Corners, pad: u32, w: u32, h: u32) -> Option<Roi> {
    let b = Roi::from_corners_padded(c, 0.0, w, h)?;
    let x0 = b.x.saturating_sub(pad);
    let y0 = b.y.saturating_sub(pad);
    let r = Roi {
        x: x0,
        y: y0,
        width: b.width + (b.x - x0) + pad,
        height: b.height + (b.y - y0) + pad,
    }
    .clamp_to(w, h);
    (!r.is_empty()).then_some(r)
}

pub struct GecPaper {
    cfg: GecPaperConfig,
    limits: ExposureLimits,
    scorer: GecScorer,
    gammas: [f64; GEC_PAPER_ANCHORS],
    scores: [f64; GEC_PAPER_ANCHORS],
    roi: Option<Roi>,
    commanded_us: f64,
}

impl GecPaper {
    pub fn new(
        cfg: GecPaperConfig,
        limits: ExposureLimits,
        initial_us: f64,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        let gammas = gec_paper_gammas();
        Ok(Self {
            scorer: GecScorer::with_gammas(&cfg.scorer_config(), &gammas),
            gammas,
            scores: [0.0; GEC_PAPER_ANCHORS],
            roi: None,
            commanded_us: limits.clamp(initial_us),
            limits,
            cfg,
        })
    }
}

impl ExposureController for GecPaper {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::GecPaper
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        if let Some(c) = marker {
            if let Some(r) = padded_box(c, self.cfg.roi_pad_px, frame.width, frame.height) {
                self.roi = Some(r);
            }
        }
        let hold = ExposureStep::skipped(self.commanded_us);
        if !exposed_as_commanded(frame, self.commanded_us) || !frame.is_consistent() {
            return hold;
        }
        // The kept region of an earlier frame, within this one (a camera can change size).
        let kept = self.roi.map(|r| r.clamp_to(frame.width, frame.height));
        let roi = kept
            .filter(|r| !r.is_empty())
            .unwrap_or_else(|| frame.full_roi());
        let view = frame.view().crop(roi);
        if !self.scorer.scores_into(view, &mut self.scores) {
            return hold;
        }
        let gamma_hat = match fit_quintic_points(&self.gammas, &self.scores) {
            Some(c) => best_gamma(&c),
            None => 1.0,
        };
        let ratio = gec_ratio(gamma_hat, self.cfg.kp, self.cfg.d);
        self.commanded_us = self.limits.clamp(self.commanded_us * ratio);
        ExposureStep {
            exposure_us: self.commanded_us,
            metric: self.scores[GEC_PAPER_ANCHORS / 2],
            used_frame: true,
            roi: Some(roi),
        }
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.roi = None;
        self.commanded_us = self.limits.clamp(exposure_us);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchors_span_the_published_range_with_one_in_the_middle() {
        let g = gec_paper_gammas();
        assert!((g[0] - 1.0 / 1.9).abs() < 1e-12 && (g[10] - 1.9).abs() < 1e-12);
        assert_eq!(g[5], 1.0);
        assert!(g.windows(2).all(|p| p[1] > p[0]));
    }

    #[test]
    fn region_is_the_corner_box_plus_25_px_clamped() {
        let c = [
            [100.0, 100.0],
            [200.0, 100.0],
            [200.0, 180.0],
            [100.0, 180.0],
        ];
        let r = padded_box(&c, 25, 640, 480).unwrap();
        assert_eq!((r.x, r.y, r.width, r.height), (75, 75, 150, 130));
        let c = [[5.0, 5.0], [60.0, 5.0], [60.0, 40.0], [5.0, 40.0]];
        let r = padded_box(&c, 25, 50, 480).unwrap();
        assert_eq!((r.x, r.y, r.width, r.height), (0, 0, 50, 65));
    }

    #[test]
    fn meters_the_padded_marker_region_and_keeps_it() {
        let limits = ExposureLimits {
            min_us: 10.0,
            max_us: 20_000.0,
            fps: 30.0,
        };
        let mut g = GecPaper::new(GecPaperConfig::default(), limits, 1000.0).unwrap();
        let mut f = Frame::new(160, 120);
        for (i, p) in f.data.iter_mut().enumerate() {
            *p = ((i * 37 + i / 160 * 11) % 200) as u8;
        }
        f.meta.exposure_us = 1000.0;
        // Before a detection: the whole frame.
        assert_eq!(g.update(&f, None).roi, Some(f.full_roi()));
        let c = [[40.0, 30.0], [80.0, 30.0], [80.0, 70.0], [40.0, 70.0]];
        let step = g.update(&f, Some(&c));
        let want = Roi {
            x: 15,
            y: 5,
            width: 90,
            height: 90,
        };
        assert_eq!(step.roi, Some(want));
        // Its metric is the middle anchor's (gamma 1) score of that region.
        let mut sc = GecScorer::with_gammas(
            &GecPaperConfig::default().scorer_config(),
            &gec_paper_gammas(),
        );
        let mut scores = [0.0; GEC_PAPER_ANCHORS];
        assert!(sc.scores_into(f.view().crop(want), &mut scores));
        assert_eq!(step.metric, scores[5]);
        // Lost: the region is kept.
        f.meta.exposure_us = g.commanded_us();
        assert_eq!(g.update(&f, None).roi, Some(want));
    }

    #[test]
    fn the_papers_gain_barely_moves() {
        // Kp 1e-8: even the largest correction changes the exposure by < 1e-7.
        let r = gec_ratio(1.0 / 1.9, 1e-8, 0.1);
        assert!(r > 1.0 && r - 1.0 < 1e-7, "{r}");
    }
}
