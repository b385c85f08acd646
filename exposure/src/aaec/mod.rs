//! markhold's AAEC: the RoI and metric of Adaptive Active Exposure Control (Ren,
//! Lensgraf, Quattrini Li, ISER 2023) with an optimiser of its own; the paper's method as
//! published is `aaec_paper.rs`.
//!
//! The parts: `config` (the `[exposure.aaec]` section), `regions` (what is metered),
//! `bracket` (the ascent and the bracket of the optimum), `knee` (landing and hold),
//! `sweep` (while the marker is lost: reacquisition sweep, highlight guard).
//!
//! Per used frame: RoI = the marker's corner box padded by `roi_pad_frac` on each side,
//! `M` and `dM/d(ln t)` on it, then a momentum step in log exposure on the scale-free
//! slope `s = dM/d(ln t) / max(M, floor)` (= d ln M / d ln t).
//!
//! Beyond the paper (its open problem is oscillation when caustics fill the RoI):
//! - once the slope has changed sign, the optimum is bracketed between the latest
//!   exposures with a positive and a negative slope; momentum stops and each step goes
//!   to the secant zero of the slope inside the bracket (regula falsi, Illinois
//!   variant). Every new frame narrows the bracket, so a flickering slope cannot make
//!   the exposure wander outside it. The bracket is kept while the scene is static;
//!   it is dropped, and the ascent restarts, only on evidence that the optimum moved:
//!   the metric changes more than the slope explains (a change of light: full restart),
//!   or a strong slope contradicts the bracket (rises above its falling end); a
//!   collapsed bracket that has seen one end only for `probe_frames` frames checks the
//!   other end with a step of the dead band;
//!   `bracket_frames` can add an age limit (0 = none, the default);
//! - outside a bracket, the momentum step is scaled by a factor that halves on each
//!   sign change and grows back while the sign holds (Rprop-like);
//! - a RoI with no gradient (black, or washed out) steps toward mid grey at once;
//! - knee landing (`knee_quantile`): after a (re)start, the exposure goes in one or
//!   two steps to a fixed margin above the knee of `M` (where the marker's white cells
//!   clip, predicted from an unclipped quantile through the camera response) and holds
//!   there while `M` is flat within its noise, instead of wandering on the plateau;
//! - the per-frame change is bounded by `max_ratio_per_frame`.
//!
//! With `adaptive_step = false` it is a plain momentum ascent in log exposure (same
//! metric, same bounds, markhold's other changes kept), kept to show the difference;
//! `step_law = "linear"` then makes that momentum the paper's linear law
//! (`v = gamma v + eta dM/dt`, `t <- t + v`) on markhold's metric, so the log-domain step
//! can be switched off on its own. The paper's whole method is `aaec_paper.rs`.

mod bracket;
mod config;
mod knee;
mod regions;
mod sweep;

pub use config::{AaecConfig, AaecFallback, MarkerRegions, StepLaw};

use crate::metric::GradientMetric;
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, Response, Roi,
};
use bracket::{Bracket, Search};
use knee::{Hold, KneeStep};
use sweep::Sweep;

/// Largest move in ln t (25%) over which the scene-change test compares M with its
/// prediction.
const SCENE_TEST_MAX_MOVE: f64 = 0.25;

/// Pixel and row step of the highlight guard's histogram.
const GUARD_STEP: usize = 2;

/// Grey-level histogram of every `GUARD_STEP`-th pixel and row of `view` (on the
/// stack), and the number of pixels counted.
fn sparse_histogram(view: crate::ImageView<'_>) -> ([u32; 256], u64) {
    let mut hist = [0u32; 256];
    for y in (0..view.height).step_by(GUARD_STEP) {
        for &p in view.row(y).iter().step_by(GUARD_STEP) {
            hist[p as usize] += 1;
        }
    }
    let n = hist.iter().map(|&c| c as u64).sum();
    (hist, n)
}

pub struct Aaec {
    cfg: AaecConfig,
    limits: ExposureLimits,
    metric: GradientMetric,
    /// The camera response (the highlight guard predicts grey levels with it).
    response: Response,
    fallback: Box<dyn ExposureController>,
    commanded_us: f64,
    /// Momentum, in ln t.
    v: f64,
    /// Momentum of the linear step law, microseconds.
    v_us: f64,
    step_scale: f64,
    /// ln t and slope of the last used frame.
    prev: Option<Sample>,
    bracket: Option<Bracket>,
    /// Outside a bracket, how the next step looks for the slope's zero instead of the
    /// momentum ascent.
    search: Option<Search>,
    /// This frame's metered regions (one, or one per marker in view with `"sum"`).
    regions: Vec<Roi>,
    /// The regions of the last frame that showed a marker, and the box around them.
    last_regions: Vec<Roi>,
    last_roi: Option<Roi>,
    lost_frames: u32,
    in_fallback: bool,
    /// Exposure of the last frame that showed the marker (the sweep's centre).
    seen_us: Option<f64>,
    /// The reacquisition sweep, while it runs.
    sweep: Option<Sweep>,
    /// `lost_frames` after which the next sweep starts.
    sweep_at: u32,
    /// The knee landing of this climb: None = not taken, Some(x) = its target, ln t.
    landed: Option<f64>,
    /// What the last step was, for the knee landing.
    last_knee: KneeStep,
    /// Slope of the frame the landing was predicted from (below the knee).
    landed_slope: f64,
    /// Held at a knee landing.
    hold: Option<Hold>,
}

impl Aaec {
    /// `fallback` runs while the marker is lost (see [`AaecConfig::fallback`]).
    pub fn new(
        cfg: AaecConfig,
        response: Response,
        limits: ExposureLimits,
        initial_us: f64,
        fallback: Box<dyn ExposureController>,
    ) -> Result<Self, ExposureError> {
        cfg.validate()?;
        let metric = GradientMetric::new(&response, cfg.metric_params());
        Ok(Self {
            cfg,
            commanded_us: limits.clamp(initial_us),
            limits,
            metric,
            response,
            fallback,
            v: 0.0,
            v_us: 0.0,
            step_scale: 1.0,
            prev: None,
            bracket: None,
            search: None,
            regions: Vec::with_capacity(1),
            last_regions: Vec::with_capacity(1),
            last_roi: None,
            lost_frames: 0,
            in_fallback: false,
            seen_us: None,
            sweep: None,
            sweep_at: 0,
            landed: None,
            last_knee: KneeStep::None,
            landed_slope: 0.0,
            hold: None,
        })
    }

    pub fn config(&self) -> &AaecConfig {
        &self.cfg
    }

    /// Forget the ascent (momentum, step scale, bracket) but keep the exposure.
    fn reset_ascent(&mut self) {
        self.v = 0.0;
        self.v_us = 0.0;
        self.step_scale = 1.0;
        self.prev = None;
        self.bracket = None;
        self.search = None;
        self.landed = None;
        self.last_knee = KneeStep::None;
        self.hold = None;
    }
}

/// One used frame: ln t, slope d ln M / d ln t, ln M.
#[derive(Debug, Clone, Copy)]
struct Sample {
    x: f64,
    s: f64,
    ln_m: f64,
}

/// The exposure `frame` says it was taken with, when that is a real one.
fn taken_us(frame: &Frame) -> Option<f64> {
    let t = frame.meta.exposure_us;
    (t.is_finite() && t > 0.0).then_some(t)
}

impl ExposureController for Aaec {
    fn method(&self) -> ExposureMethod {
        ExposureMethod::Aaec
    }

    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep {
        self.update_in_view(frame, marker, &[])
    }

    fn reserve_markers(&mut self, markers: usize) {
        let n = markers.max(1);
        self.regions.reserve(n);
        self.last_regions.reserve(n);
    }

    fn update_in_view(
        &mut self,
        frame: &Frame,
        marker: Option<&Corners>,
        in_view: &[Corners],
    ) -> ExposureStep {
        // A union box can be wider than any region before it: size the metric's row
        // buffers for the whole frame on the first frame, not mid-run.
        self.metric.reserve(frame.width as usize);
        let Some(roi) = self.select_regions(frame, marker, in_view) else {
            if !self.in_fallback {
                tracing::debug!(lost = self.lost_frames, "aaec: marker lost, falling back");
                self.in_fallback = true;
                self.reset_ascent();
                self.fallback.reset(self.commanded_us);
                self.schedule_sweep();
            }
            if self.cfg.sweep_after_frames > 0 && self.lost_frames > self.sweep_at {
                if let Some(t) = self.sweep_step() {
                    self.commanded_us = t;
                    return ExposureStep::skipped(t);
                }
            }
            let t = self.commanded_us;
            let mut step = self.fallback.update(frame, None);
            let mut next = self.limits.clamp(step.exposure_us);
            if step.used_frame {
                if let Some(cap) = self.highlight_cap(frame, t) {
                    let cap = self.limits.clamp(cap);
                    if next > cap {
                        // Keep the fallback in step with what is really commanded.
                        next = cap;
                        self.fallback.reset(cap);
                    }
                }
            }
            self.commanded_us = next;
            step.exposure_us = next;
            return step;
        };
        if self.in_fallback {
            self.in_fallback = false;
            self.reset_ascent();
            if let (Some(_), Some(t)) = (self.sweep.take(), taken_us(frame)) {
                // Found on a rung: restart from the exposure this frame was taken at (the
                // command may already be a rung further on).
                self.commanded_us = self.limits.clamp(t);
            }
        }
        let hold = ExposureStep {
            roi: Some(roi),
            ..ExposureStep::skipped(self.commanded_us)
        };
        if !exposed_as_commanded(frame, self.commanded_us) || !frame.is_consistent() {
            return hold;
        }
        let Some(mv) = self.evaluate_regions(frame) else {
            return hold;
        };
        let t = self.commanded_us;
        let x = t.ln();
        let bound = self.cfg.max_ratio_per_frame.ln();
        let delta = if mv.m < self.cfg.metric_floor_grey2 {
            // No gradient to climb (black or washed out): move toward mid grey as fast
            // as allowed.
            self.reset_ascent();
            if mv.mean_grey < 128.0 {
                bound
            } else {
                -bound
            }
        } else {
            let s = mv.dm_dlnt / mv.m;
            let ln_m = mv.m.ln();
            if let Some(p) = self.prev {
                // ln M predicted from the previous frame by the trapezoid rule on the two
                // slopes (exact for a quadratic ln M); only over short moves, where that
                // holds. A larger miss is the scene, not the exposure.
                let dx = x - p.x;
                let predicted = p.ln_m + 0.5 * (p.s + s) * dx;
                if dx.abs() <= SCENE_TEST_MAX_MOVE
                    && (ln_m - predicted).abs() > self.cfg.restart_metric_change
                {
                    tracing::debug!(
                        miss = ln_m - predicted,
                        "aaec: metric changed beyond the slope's prediction, restarting"
                    );
                    self.reset_ascent();
                }
            }
            let last = std::mem::replace(&mut self.last_knee, KneeStep::None);
            let (d, why) = if let Some(d) = self.knee_held(s) {
                (d, "knee hold")
            } else if last == KneeStep::Landing && self.hold_knee(mv.saturated_frac, s) {
                (0.0, "knee hold begins")
            } else if let Some(d) = self.knee_step(frame, x, s, mv.saturated_frac, last) {
                (d, "knee landing")
            } else {
                self.search_if_landed(last);
                let d = self.ascent_step(x, s, mv.dm_dlnt);
                (
                    d,
                    if self.bracket.is_some() {
                        "bracket"
                    } else {
                        "ascent"
                    },
                )
            };
            tracing::trace!(
                t,
                s,
                m = mv.m,
                clipped = mv.saturated_frac,
                step = d,
                why,
                "aaec"
            );
            self.prev = Some(Sample { x, s, ln_m });
            d
        };
        let mut next = self.limits.clamp(t * delta.exp());
        if (next - t).abs() < self.cfg.dead_band_us {
            next = t;
        }
        if (next - t * delta.exp()).abs() > 1e-9 * t {
            // Stopped by a camera limit: do not let momentum push against it.
            self.v = 0.0;
            self.v_us = 0.0;
        }
        self.commanded_us = next;
        ExposureStep::used(next, mv.m, Some(roi))
    }

    fn commanded_us(&self) -> f64 {
        self.commanded_us
    }

    fn reset(&mut self, exposure_us: f64) {
        self.commanded_us = self.limits.clamp(exposure_us);
        self.reset_ascent();
        self.last_roi = None;
        self.last_regions.clear();
        self.lost_frames = 0;
        self.in_fallback = false;
        self.seen_us = None;
        self.sweep = None;
        self.fallback.reset(self.commanded_us);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::{MeanAe, MeanAeConfig};

    fn linear_law(eta: f64) -> Aaec {
        let cfg = AaecConfig {
            adaptive_step: false,
            step_law: StepLaw::Linear,
            linear_learning_rate: eta,
            ..AaecConfig::default()
        };
        let limits = ExposureLimits {
            min_us: 5.0,
            max_us: 20000.0,
            fps: 30.0,
        };
        let fallback = Box::new(MeanAe::new(MeanAeConfig::default(), limits, 1000.0).unwrap());
        Aaec::new(cfg, Response::linear(), limits, 1000.0, fallback).unwrap()
    }

    #[test]
    fn the_linear_step_law_follows_a_hand_computed_sequence() {
        let mut a = linear_law(1e-10);
        let mut t: f64 = 1000.0;
        // dM/dt = (dM/d ln t) / t: 2000 / 1e-3 s = 2e6; v = 1e-10 * 2e6 s = 200 us.
        // Then 1200 / 1.2e-3 = 1e6: v = 0.9 * 200 + 100 = 280 us.
        // Then -4440 / 1.48e-3 = -3e6: v = 0.9 * 280 - 300 = -48 us.
        for (dm_dlnt, want) in [(2000.0, 1200.0), (1200.0, 1480.0), (-4440.0, 1432.0)] {
            let d = a.ascent_step(t.ln(), dm_dlnt / 1000.0, dm_dlnt);
            t *= d.exp();
            assert!((t - want).abs() < 1e-6, "{t} vs {want}");
        }
    }

    #[test]
    fn the_linear_step_is_bounded_per_frame_and_keeps_only_what_was_applied() {
        let mut a = linear_law(1e-6);
        // eta dM/dt = 1e-6 * 2e6 s = 2 s: bounded to 4x (1000 -> 4000 us).
        let d = a.ascent_step(1000f64.ln(), 2.0, 2000.0);
        assert!((d - 4f64.ln()).abs() < 1e-12, "{d}");
        assert!((a.v_us - 3000.0).abs() < 1e-6, "{}", a.v_us);
    }

    #[test]
    fn the_linear_step_law_needs_the_plain_momentum() {
        let cfg = AaecConfig {
            step_law: StepLaw::Linear,
            ..AaecConfig::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(
            e.contains("exposure.aaec.step_law") && e.contains("adaptive_step = false"),
            "{e}"
        );
    }
}
