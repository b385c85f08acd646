//! markhold's AAEC: the RoI and metric of Adaptive Active Exposure Control (Ren,
//! Lensgraf, Quattrini Li, ISER 2023) with an optimiser of its own; the paper's method as
//! published is `aaec_paper.rs`.
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

use crate::metric::{GradientMetric, MetricParams, MetricValue};
use crate::{
    exposed_as_commanded, Corners, ExposureController, ExposureError, ExposureLimits,
    ExposureMethod, ExposureStep, Frame, Response, Roi,
};
use markhold_config::{open, open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// Largest move in ln t (25%) over which the scene-change test compares M with its
/// prediction.
const SCENE_TEST_MAX_MOVE: f64 = 0.25;

/// Slope `"log-sum"` gives a marker's box that is washed out (negative) or black and
/// flat (positive): twice a linear camera's slope below the knee, so that such a
/// marker outweighs one that is still climbing.
const LOG_SUM_LOST_SLOPE: f64 = 4.0;
/// Clipped fraction of a marker's box from which `"log-sum"` takes it as washed out.
const LOG_SUM_WASHED_OUT: f64 = 0.5;

/// Longest interval between probes of a collapsed bracket, used frames.
const MAX_PROBE_FRAMES: u32 = 64;

/// Default eta of the linear step law (`step_law = "linear"`), s per unit of dM/dt.
const LINEAR_LEARNING_RATE: f64 = 1e-9;
/// A bracket narrower than this (in ln t) has collapsed onto its zero.
const COLLAPSED_WIDTH: f64 = 0.005;
/// Step scale of the ascent that resumes when a knee hold is released.
const RESTART_STEP_SCALE: f64 = 0.1;
/// Smallest step (ln t, as a multiple of the probe step) of a search for the slope's
/// zero, and the first step of the one that follows a contradicted bracket.
const SEARCH_FIRST_PROBES: f64 = 2.0;
/// Fraction of the secant's predicted distance to the slope's zero that a secant search
/// steps: past the knee the slope falls faster than linearly (clipping spreads), so the
/// secant through two frames overestimates the distance.
const SECANT_DAMPING: f64 = 0.5;

/// Grey level from which the highlight guard takes a pixel as clipped.
const CLIPPED_GREY: usize = 254;
/// Pixel and row step of the highlight guard's histogram.
const GUARD_STEP: usize = 2;

/// After a descent below the knee, a frame still clipped and with a slope below this
/// (M not rising as it does below the knee) is still above it: descend again.
const KNEE_FLAT_SLOPE: f64 = 0.5;
/// Smallest clipped fraction of the RoI taken as the marker's white cells clipping:
/// a frame above the knee steps below it, a landing holds; fewer clipped pixels
/// (highlights, caustics) leave it to the ascent.
const KNEE_CLIPPED: f64 = 0.25;
/// Slope at or below which a clipped frame starts the descent below the knee (M
/// falls steeply: the white cells clip far above the knee, as after a light change).
const KNEE_DESCEND_SLOPE: f64 = -1.0;
/// Used frames at a knee hold before its slope statistics may release it.
const HOLD_MIN_FRAMES: u32 = 6;
/// Longest memory of the knee hold's slope statistics, used frames.
const HOLD_WINDOW: u32 = 32;

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

/// What AAEC runs when the marker has been lost for more than `lost_hold_frames`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AaecFallback {
    /// Mean-intensity AE with the `[exposure.default]` parameters.
    Mean,
    /// Full-frame AEC with the `[exposure.aec]` parameters.
    Aec,
}

/// The region AAEC meters when several markers of the site's map are in view
/// (`[exposure.aaec] regions`). With one marker in view all three are the same region.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MarkerRegions {
    /// One box around the padded boxes of every marker in view.
    Union,
    /// `M` and `dM/d(ln t)` evaluated on each marker's padded box and summed.
    Sum,
    /// `ln M` summed over each marker's padded box: every marker's relative gain
    /// counts the same, however bright it is. The slope is the mean of the markers'
    /// slopes `d ln M / d ln t`; a marker's box with half its pixels clipped (washed
    /// out: its own slope says nothing) counts -4, one without gradient and dark +4
    /// (twice a linear camera's slope below the knee). `M` reported is the markers'
    /// geometric mean.
    /// The default.
    #[serde(rename = "log-sum")]
    LogSum,
    /// The padded box of the marker the pose names only: the origin marker when it is
    /// in view, else the largest (one marker's AAEC, kept for comparison).
    Single,
}

impl std::fmt::Display for MarkerRegions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Union => "union",
            Self::Sum => "sum",
            Self::LogSum => "log-sum",
            Self::Single => "single",
        })
    }
}

/// Domain of the plain momentum step (`adaptive_step = false`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepLaw {
    /// `v = gamma v + eta d ln M / d ln t`, `t <- t e^v` (markhold's).
    Log,
    /// `v = gamma v + eta_lin dM/dt`, `t <- t + v` (the paper's law).
    Linear,
}

impl std::fmt::Display for StepLaw {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Log => "log",
            Self::Linear => "linear",
        })
    }
}

/// The `[exposure.aaec]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AaecConfig {
    /// Percentile `p` where the soft-percentile weights peak, (0, 1). The paper's text
    /// recommends 0.6 to 0.9, its code uses 0.9; on a marker RoI 0.7 lands in flat
    /// cells, whose slope has spurious zeros when the white cells clip.
    pub percentile: f64,
    /// Sine-weight exponent `k`, odd in 1..=9 (published: 5).
    pub weight_power: u32,
    /// RoI padding on each side, as a fraction of the corner box (paper: 0.1).
    pub roi_pad_frac: f64,
    /// With several markers of the map in view: `"log-sum"` (default) sums `ln M` over
    /// each marker's box, `"sum"` sums `M`, `"union"` meters one box around all of
    /// them, `"single"` the marker the pose names only (see [`MarkerRegions`]).
    pub regions: MarkerRegions,
    /// Momentum factor gamma, [0, 1) (paper: 0.9).
    pub momentum: f64,
    /// Learning rate eta on the scale-free slope d ln M / d ln t, (0, 10].
    pub learning_rate: f64,
    /// Changes smaller than this are not applied, microseconds (paper's code: 1).
    pub dead_band_us: f64,
    /// Largest ratio between two consecutive commands, (1, 100].
    pub max_ratio_per_frame: f64,
    /// Adapt the step (our design); false = plain momentum in log exposure (not the
    /// paper's linear law: that is `aaec-paper`).
    pub adaptive_step: bool,
    /// Domain of the plain momentum step, `"log"` (default) or `"linear"` (the paper's
    /// law, with `linear_learning_rate`); `"linear"` needs `adaptive_step = false`.
    pub step_law: StepLaw,
    /// eta of the linear law: seconds of exposure per unit of `dM/dt`, `M` in this
    /// metric's grey levels squared and `t` in seconds, (0, 1e-6].
    pub linear_learning_rate: f64,
    /// Step scale factor on a sign change of the slope, (0, 1).
    pub step_shrink: f64,
    /// Step scale factor while the sign holds, [1, 4]; the scale never exceeds 1.
    pub step_grow: f64,
    /// Smallest step scale, (0, 1].
    pub min_step_scale: f64,
    /// Below this `M` (grey levels squared, > 0) the RoI holds no gradient to climb
    /// (black or washed out): step toward mid grey by the largest ratio.
    pub metric_floor_grey2: f64,
    /// Used frames a bracket of the optimum is trusted before the ascent restarts,
    /// 0..=1000; 0 (default) = no age limit: the bracket is dropped only on evidence
    /// (see `restart_metric_change`, `restart_slope`). An age limit makes a static scene
    /// probe around its optimum (7-21% excursions in HIL with 15).
    pub bracket_frames: u32,
    /// Scene-change test, in ln M, (0, 20]: when `ln M` differs from its prediction from
    /// the previous used frame (trapezoid rule on the two slopes) by more than this, the
    /// light changed: the ascent restarts from scratch (momentum, step scale, bracket).
    /// 0.7 = M off by 2x, about 1.4x of light on a linear camera.
    pub restart_metric_change: f64,
    /// Slope magnitude that counts as strong, (0, 10]: a strong slope that contradicts
    /// the bracket (rising above its falling end, or falling below its rising end) drops
    /// it; a weaker one is taken as noise.
    pub restart_slope: f64,
    /// Drift test, 1..=64: after this many used frames in which a collapsed bracket has
    /// seen a strong slope at one end only, step just past the other end (by the dead
    /// band) to see whether the optimum is still inside. Each confirmation doubles the
    /// interval (up to 64 frames).
    pub probe_frames: u32,
    /// Grey level from which a pixel counts as clipped, 128..=255 (official AEC: 252;
    /// ours: 255, the only level a linear sensor really clips at).
    pub saturation_grey: u8,
    /// A clipped pixel's `dG` becomes `-penalty * max(|dG|, 0.5)`, [0, 10] (official AEC:
    /// 3; ours: 1, which puts the zero of the slope within a few percent of the argmax
    /// of `M`, where 3 stops 10-20% short of it).
    pub saturation_penalty: f64,
    /// Frames the last RoI is kept after the marker is lost, 0..=1000.
    pub lost_hold_frames: u32,
    /// Controller used after that (momentum is reset on the switch).
    pub fallback: AaecFallback,
    /// Reacquisition sweep (our design; 0 = off), fallback frames 0..=1000: when the
    /// fallback has not shown the marker again after this many frames, the exposure
    /// steps through a ladder around the exposure the marker was last seen at, that
    /// exposure between every two rungs (c, c r, c, c / r, c, c r^2, ...) out to
    /// `sweep_span`; after one pass the fallback runs again for as many frames, and so
    /// on. On the first frame that shows the marker AAEC restarts from that frame's
    /// exposure. A whole-frame fallback meters what the marker is not: under caustics
    /// it settled where the web of highlights sits (HIL reef-caustics seed 5: 0.9 ms,
    /// the marker's cells too dark to decode, lost for the last 30 s of the run).
    pub sweep_after_frames: u32,
    /// Ratio between the sweep's rungs, [1.1, 16].
    pub sweep_ratio: f64,
    /// How far the sweep reaches from its centre, as a factor, [`sweep_ratio`, 1000].
    pub sweep_span: f64,
    /// Frames each rung is commanded, 1..=30 (the camera applies an exposure a frame
    /// or more late, and the marker found on a rung must still be there on the next).
    pub sweep_dwell_frames: u32,
    /// Highlight guard of the fallback, [0, 0.5] (0 = off): while the marker is lost, the
    /// brightest `highlight_frac` of the frame may not be driven above `highlight_grey`,
    /// and when that many pixels are clipped the exposure shortens by
    /// `max_ratio_per_frame`. A marker washed out in a lamp's spot (bright blob in a dark
    /// frame) is then brought back into range instead of being lengthened further by a
    /// whole-frame fallback metering the dark surround.
    pub highlight_frac: f64,
    /// Grey level the fallback may drive the brightest `highlight_frac` of the frame to,
    /// 128..=250.
    pub highlight_grey: f64,
    /// Knee landing, [0, 1) (0 = off): quantile of the RoI's grey levels taken as the
    /// marker's white cells. On a marker with evenly lit cells, `M` rises as t^2 (slope
    /// 2 on a linear camera) until the white cells clip, then is flat within its frame
    /// noise (+-10 %) over a 2x range: the knee is the shortest exposure whose `M` is
    /// as good as the best (the tie-break: least clipping and motion blur), and unlike
    /// the plateau it is measurable. After a (re)start of the ascent: from below (a
    /// strong positive slope, that quantile unclipped in 16 .. `saturation_grey - 2`)
    /// the response predicts the exposure at which it clips, and one step (or more,
    /// if bounded by `max_ratio_per_frame`) goes there times `knee_margin`; from
    /// above (that quantile clipped, a quarter of the RoI clipped and a slope <= -1,
    /// as after a light change) steps of `max_ratio_per_frame` go below the knee
    /// first. If the landing frame has a quarter of the RoI clipped and a slope below
    /// half the one the landing was predicted from, the exposure is held there (see
    /// `knee_hold_z`, `knee_hold_slope`); otherwise the ascent goes on.
    pub knee_quantile: f64,
    /// Factor above the predicted clip onset where the knee landing aims, [1, 2]: the
    /// white cells clip from about 1.0x, `M` is flat from 1.1x (HIL pool fixture).
    pub knee_margin: f64,
    /// Knee hold, downward, (0, 10]: at a knee hold, a mean slope (at least 6 used
    /// frames) below `-restart_slope` and beyond `knee_hold_z` standard deviations of
    /// its noise says a shorter exposure is better: the exposure goes down to the
    /// predicted clip onset (the landing divided by `knee_margin`) and holds there; a
    /// second such verdict lets the ascent resume.
    pub knee_hold_z: f64,
    /// Knee hold, upward, [`restart_slope`, 10]: a mean slope at a knee hold (at least
    /// 6 used frames) at or above this lets the ascent resume (at or below its
    /// negative, the exposure moves down as for `knee_hold_z`). 1 = half the slope
    /// below the knee (linear camera): the exposure is below the knee (the light
    /// dimmed) or there is no knee. A smaller mean slope is
    /// left alone: the tie-break toward the shorter exposure (in HIL daylight the mean
    /// slope just above the knee is +0.2 .. +0.5; `M` there is 5-10 % below the old
    /// settling points, 1.5-2x longer, a loss of the order of its frame noise).
    pub knee_hold_slope: f64,
}

impl Default for AaecConfig {
    fn default() -> Self {
        Self {
            percentile: 0.9,
            weight_power: 5,
            roi_pad_frac: 0.1,
            regions: MarkerRegions::LogSum,
            momentum: 0.9,
            learning_rate: 0.5,
            dead_band_us: 1.0,
            max_ratio_per_frame: 4.0,
            adaptive_step: true,
            step_law: StepLaw::Log,
            linear_learning_rate: LINEAR_LEARNING_RATE,
            step_shrink: 0.5,
            step_grow: 1.2,
            min_step_scale: 0.02,
            metric_floor_grey2: 1.0,
            bracket_frames: 0,
            restart_metric_change: 0.7,
            restart_slope: 0.25,
            probe_frames: 3,
            saturation_grey: 255,
            saturation_penalty: 1.0,
            lost_hold_frames: 5,
            fallback: AaecFallback::Mean,
            sweep_after_frames: 10,
            sweep_ratio: 2.0,
            sweep_span: 4.0,
            sweep_dwell_frames: 3,
            highlight_frac: 0.005,
            highlight_grey: 230.0,
            knee_quantile: 0.9,
            knee_margin: 1.1,
            knee_hold_z: 3.0,
            knee_hold_slope: 1.0,
        }
    }
}

impl AaecConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("exposure.aaec")
            .range("percentile", self.percentile, open(0.0, 1.0), "a fraction in (0, 1)")
            .odd("weight_power", self.weight_power, 1..=9, "an odd integer in 1..=9")
            .range("roi_pad_frac", self.roi_pad_frac, 0.0..=1.0, "a fraction in [0, 1]")
            .range("momentum", self.momentum, 0.0..1.0, "a factor in [0, 1)")
            .range("learning_rate", self.learning_rate, open_closed(0.0, 10.0), "a rate in (0, 10]")
            .range("dead_band_us", self.dead_band_us, 0.0..=1000.0, "microseconds in [0, 1000]")
            .range("max_ratio_per_frame", self.max_ratio_per_frame, open_closed(1.0, 100.0), "a ratio in (1, 100]")
            .check("step_law", self.step_law, self.step_law == StepLaw::Log || !self.adaptive_step,
                "\"log\", or \"linear\" with adaptive_step = false (the adaptive step works in log exposure)")
            .range("linear_learning_rate", self.linear_learning_rate, open_closed(0.0, 1e-6),
                "a rate in (0, 1e-6] s per unit of dM/dt")
            .range("step_shrink", self.step_shrink, open(0.0, 1.0), "a factor in (0, 1)")
            .range("step_grow", self.step_grow, 1.0..=4.0, "a factor in [1, 4]")
            .range("min_step_scale", self.min_step_scale, open_closed(0.0, 1.0), "a scale in (0, 1]")
            .positive("metric_floor_grey2", self.metric_floor_grey2, "a positive value")
            .range("bracket_frames", self.bracket_frames, ..=1000, "frames in 0..=1000 (0 = no age limit)")
            .range("restart_metric_change", self.restart_metric_change, open_closed(0.0, 20.0), "a change of ln M in (0, 20]")
            .range("restart_slope", self.restart_slope, open_closed(0.0, 10.0), "a slope in (0, 10]")
            .range("probe_frames", self.probe_frames, 1..=MAX_PROBE_FRAMES, "frames in 1..=64")
            .range("saturation_grey", self.saturation_grey, 128.., "a grey level in 128..=255")
            .range("saturation_penalty", self.saturation_penalty, 0.0..=10.0, "a factor in [0, 10]")
            .range("lost_hold_frames", self.lost_hold_frames, ..=1000, "frames in 0..=1000")
            .range("sweep_after_frames", self.sweep_after_frames, ..=1000, "frames in 0..=1000 (0 = off)")
            .range("sweep_ratio", self.sweep_ratio, 1.1..=16.0, "a factor in [1.1, 16]")
            .range("sweep_span", self.sweep_span, self.sweep_ratio..=1000.0, "a factor in [sweep_ratio, 1000]")
            .range("sweep_dwell_frames", self.sweep_dwell_frames, 1..=30, "frames in 1..=30")
            .range("highlight_frac", self.highlight_frac, 0.0..=0.5, "a fraction in [0, 0.5]")
            .range("highlight_grey", self.highlight_grey, 128.0..=250.0, "a grey level in [128, 250]")
            .range("knee_quantile", self.knee_quantile, 0.0..1.0, "a fraction in [0, 1) (0 = off)")
            .range("knee_margin", self.knee_margin, 1.0..=2.0, "a factor in [1, 2]")
            .range("knee_hold_z", self.knee_hold_z, open_closed(0.0, 10.0), "standard deviations in (0, 10]")
            .range("knee_hold_slope", self.knee_hold_slope, self.restart_slope..=10.0, "a slope in [restart_slope, 10]")
            .done()
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

    /// Grey level of the knee quantile of this frame's regions (every 2nd pixel and
    /// row of each).
    fn knee_grey(&self, frame: &Frame) -> Option<usize> {
        let q = self.cfg.knee_quantile;
        if q <= 0.0 {
            return None;
        }
        let view = frame.view();
        let (mut hist, mut n) = ([0u32; 256], 0u64);
        for &r in &self.regions {
            let (h, c) = sparse_histogram(view.crop(r));
            for (a, b) in hist.iter_mut().zip(h) {
                *a += b;
            }
            n += c;
        }
        if n == 0 {
            return None;
        }
        let want = ((q * n as f64).ceil() as u64).max(1);
        let mut acc = 0u64;
        for (g, &c) in hist.iter().enumerate() {
            acc += c as u64;
            if acc >= want {
                return Some(g);
            }
        }
        None
    }

    /// The knee landing step (ln t) from a frame at `x` with slope `s`, if it applies.
    fn knee_step(
        &mut self,
        frame: &Frame,
        x: f64,
        s: f64,
        clipped_frac: f64,
        last: KneeStep,
    ) -> Option<f64> {
        // One landing per climb, continued while a bounded step left it short.
        let short_of_landing = match self.landed {
            None => true,
            Some(xl) => last == KneeStep::Landing && x < xl - COLLAPSED_WIDTH,
        };
        if !self.cfg.adaptive_step
            || self.bracket.is_some()
            || self.hold.is_some()
            || !short_of_landing
        {
            return None;
        }
        let g = self.knee_grey(frame)?;
        let sat = self.cfg.saturation_grey as usize;
        if g + 1 >= sat
            && self.landed.is_none()
            && clipped_frac >= KNEE_CLIPPED
            && (s <= KNEE_DESCEND_SLOPE || (last == KneeStep::Descent && s < KNEE_FLAT_SLOPE))
        {
            // The brightest cells clip (a large part of the RoI) and M falls steeply
            // (or, after such a step, does not rise): above the knee, by an unknown
            // factor. Go below it by the largest steps, then land from there.
            self.v = 0.0;
            self.last_knee = KneeStep::Descent;
            return Some(-self.cfg.max_ratio_per_frame.ln());
        }
        if s < self.cfg.restart_slope || !(16..=sat.saturating_sub(2)).contains(&g) {
            return None;
        }
        let ratio = self.response.signal(sat as f64) / self.response.signal(g as f64);
        let delta = (ratio * self.cfg.knee_margin).ln();
        if delta <= 0.0 {
            return None;
        }
        // The target, not the bounded step: a landing cut short by the bound goes on.
        self.landed = Some(x + delta);
        self.landed_slope = s;
        self.last_knee = KneeStep::Landing;
        let bound = self.cfg.max_ratio_per_frame.ln();
        // Momentum as for an ascent step: if M is not flat at the landing (no knee, the
        // cells clip gradually), the ascent goes on at the pace it would have had. None
        // after a step cut short by the bound (the landing goes on from there).
        self.v = if delta <= bound { delta } else { 0.0 };
        Some(delta.min(bound))
    }

    /// On the frame at a knee landing: true to hold there (see
    /// [`AaecConfig::knee_quantile`]).
    fn hold_knee(&mut self, clipped_frac: f64, s: f64) -> bool {
        if self.bracket.is_some() || self.hold.is_some() {
            return false;
        }
        // Landed when a large part of the RoI clips (the marker's white cells, not a
        // few highlights) and M is flat: the slope has lost at least half of its value
        // below the knee (2 on a linear camera) in either direction.
        if clipped_frac < KNEE_CLIPPED || s.abs() >= 0.5 * self.landed_slope {
            return false;
        }
        self.hold = Some(Hold::default());
        self.v = 0.0;
        true
    }

    /// While held at a knee landing: the step (0 = stay), or None when the ascent
    /// resumes. Keeps the slope's mean and variance there (1/n weights, then 1/32).
    fn knee_held(&mut self, s: f64) -> Option<f64> {
        let mut h = self.hold?;
        h.age = h.age.saturating_add(1);
        // Samples in the running statistics: 1/n weights up to the window, then fixed.
        let n = h.age.min(HOLD_WINDOW);
        let a = 1.0 / n as f64;
        let d = s - h.mean;
        h.mean += a * d;
        h.var = (1.0 - a) * (h.var + a * d * d);
        // Right after the landing, a consistent fall of M (beyond the noise) corrects
        // the margin; later only a mean slope beyond `knee_hold_slope` moves the hold.
        let shorter = (h.age <= HOLD_WINDOW
            && h.mean <= -self.cfg.restart_slope
            && -h.mean > self.cfg.knee_hold_z * h.var.sqrt())
            || h.mean <= -self.cfg.knee_hold_slope;
        let longer = h.mean >= self.cfg.knee_hold_slope;
        if n < HOLD_MIN_FRAMES || !(shorter || longer) {
            self.hold = Some(h);
            return Some(0.0);
        }
        if shorter && !h.onset && self.cfg.knee_margin > 1.0 {
            // M falls past the knee: go down to the predicted clip onset and hold there.
            tracing::debug!(mean = h.mean, "aaec: knee hold moves to the clip onset");
            self.hold = Some(Hold {
                onset: true,
                ..Hold::default()
            });
            return Some(-self.cfg.knee_margin.ln());
        }
        tracing::debug!(mean = h.mean, sd = h.var.sqrt(), "aaec: knee hold released");
        self.hold = None;
        self.step_scale = RESTART_STEP_SCALE;
        self.v = 0.0;
        None
    }

    /// The regions to meter (into `self.regions`) and the box around them: from the
    /// markers in view as `regions` says, else the last ones for a few frames.
    fn select_regions(
        &mut self,
        frame: &Frame,
        marker: Option<&Corners>,
        in_view: &[Corners],
    ) -> Option<Roi> {
        let (w, h) = (frame.width, frame.height);
        let pad = self.cfg.roi_pad_frac as f32;
        let boxed = |c: &Corners| Roi::from_corners_padded(c, pad, w, h);
        self.regions.clear();
        let detected = marker.and_then(boxed).map(|primary| {
            match self.cfg.regions {
                MarkerRegions::Single => self.regions.push(primary),
                MarkerRegions::Union => {
                    let u = in_view
                        .iter()
                        .filter_map(boxed)
                        .fold(primary, |u, r| u.union(&r));
                    self.regions.push(u);
                }
                MarkerRegions::Sum | MarkerRegions::LogSum => {
                    // `in_view` holds the named marker too; without it, that one alone.
                    self.regions.extend(in_view.iter().filter_map(boxed));
                    if self.regions.is_empty() {
                        self.regions.push(primary);
                    }
                }
            }
            let first = self.regions[0];
            self.regions[1..].iter().fold(first, |u, r| u.union(r))
        });
        match detected {
            Some(r) => {
                self.lost_frames = 0;
                self.last_roi = Some(r);
                self.last_regions.clear();
                self.last_regions.extend_from_slice(&self.regions);
                self.seen_us = taken_us(frame).or(self.seen_us);
                Some(r)
            }
            None => {
                self.lost_frames = self.lost_frames.saturating_add(1);
                if self.lost_frames <= self.cfg.lost_hold_frames {
                    let last = self.last_roi?;
                    self.regions
                        .extend(self.last_regions.iter().map(|r| r.clamp_to(w, h)));
                    Some(last.clamp_to(w, h))
                } else {
                    self.last_roi = None;
                    self.last_regions.clear();
                    None
                }
            }
        }
    }

    /// The metric over this frame's regions: one region's value as it is; over several,
    /// `M` and `dM/d(ln t)` summed (`"sum"`) or `ln M` summed (`"log-sum"`, each `M`
    /// floored at `metric_floor_grey2`), the grey statistics weighted by pixel count.
    fn evaluate_regions(&mut self, frame: &Frame) -> Option<MetricValue> {
        let view = frame.view();
        let floor = self.cfg.metric_floor_grey2;
        let mut first: Option<MetricValue> = None;
        let (mut count, mut pixels) = (0usize, 0usize);
        let (mut m, mut dm, mut ln_m, mut s) = (0.0, 0.0, 0.0, 0.0);
        let (mut grey, mut sat) = (0.0, 0.0);
        for &r in &self.regions {
            let Some(v) = self.metric.evaluate(view.crop(r)) else {
                continue;
            };
            first.get_or_insert(v);
            count += 1;
            pixels += v.pixels;
            m += v.m;
            dm += v.dm_dlnt;
            let mf = v.m.max(floor);
            ln_m += mf.ln();
            s += if v.saturated_frac >= LOG_SUM_WASHED_OUT {
                -LOG_SUM_LOST_SLOPE
            } else if v.m < floor {
                if v.mean_grey < 128.0 {
                    LOG_SUM_LOST_SLOPE
                } else {
                    -LOG_SUM_LOST_SLOPE
                }
            } else {
                v.dm_dlnt / v.m
            };
            grey += v.mean_grey * v.pixels as f64;
            sat += v.saturated_frac * v.pixels as f64;
        }
        if count <= 1 {
            return first;
        }
        let n = pixels.max(1) as f64;
        let (m, dm_dlnt) = if self.cfg.regions == MarkerRegions::LogSum {
            let g = (ln_m / count as f64).exp();
            (g, g * s / count as f64)
        } else {
            (m, dm)
        };
        Some(MetricValue {
            m,
            dm_dlnt,
            pixels,
            mean_grey: grey / n,
            saturated_frac: sat / n,
        })
    }

    /// Rung `j` (1, 2, ...) of a sweep around `center_us`: x r, / r, x r^2, / r^2, ...,
    /// clamped to the camera's range; `None` where the clamp makes it the same as the
    /// rung before it on its side.
    fn rung_us(&self, center_us: f64, j: u32) -> Option<f64> {
        let e = if j % 2 == 1 {
            j.div_ceil(2) as i32
        } else {
            -((j / 2) as i32)
        };
        let r = self.cfg.sweep_ratio;
        let t = self.limits.clamp(center_us * r.powi(e));
        let before = self.limits.clamp(center_us * r.powi(e - e.signum()));
        ((t - before).abs() > 1e-9 * before).then_some(t)
    }

    /// The fallback runs `sweep_after_frames` frames, this one included, before the next
    /// pass of the sweep.
    fn schedule_sweep(&mut self) {
        self.sweep_at = self
            .lost_frames
            .saturating_add(self.cfg.sweep_after_frames)
            .saturating_sub(1);
    }

    /// The exposure to command on this update of the reacquisition sweep; `None` when
    /// its pass is over (the fallback runs again, from where it was).
    fn sweep_step(&mut self) -> Option<f64> {
        let mut sweep = match self.sweep {
            Some(s) => s,
            None => {
                let center_us = self.limits.clamp(self.seen_us.unwrap_or(self.commanded_us));
                let rungs = (self.cfg.sweep_span.ln() / self.cfg.sweep_ratio.ln() + 1e-9).floor();
                tracing::debug!(center_us, "aaec: marker still lost, sweeping the exposure");
                Sweep {
                    center_us,
                    j: 0,
                    last_j: (rungs as u32).saturating_mul(2),
                    rung_us: center_us,
                    at_center: true,
                    left: self.cfg.sweep_dwell_frames,
                    fallback_us: self.commanded_us,
                }
            }
        };
        if sweep.left == 0 {
            if !sweep.at_center {
                // Back to the centre between two rungs.
                sweep.at_center = true;
                sweep.rung_us = sweep.center_us;
            } else {
                // The next rung inside the range; past the last one the pass is over.
                loop {
                    if sweep.j >= sweep.last_j {
                        self.sweep = None;
                        self.schedule_sweep();
                        self.commanded_us = sweep.fallback_us;
                        self.fallback.reset(sweep.fallback_us);
                        return None;
                    }
                    sweep.j += 1;
                    if let Some(t) = self.rung_us(sweep.center_us, sweep.j) {
                        sweep.rung_us = t;
                        sweep.at_center = false;
                        break;
                    }
                }
            }
            sweep.left = self.cfg.sweep_dwell_frames;
        }
        sweep.left -= 1;
        self.sweep = Some(sweep);
        Some(sweep.rung_us)
    }

    /// The highlight guard: the longest exposure the fallback may command after `frame`
    /// (exposed at `t`), from the grey level reached by the brightest `highlight_frac` of
    /// the frame. When those pixels are clipped their true brightness is unknown: shorten
    /// by the per-frame bound. Otherwise the response predicts the exposure that puts
    /// them at `highlight_grey`. `None` when the guard is off or the frame is empty.
    fn highlight_cap(&self, frame: &Frame, t: f64) -> Option<f64> {
        let q = self.cfg.highlight_frac;
        if q <= 0.0 {
            return None;
        }
        let view = frame.view();
        let (hist, n) = sparse_histogram(view);
        if n == 0 {
            return None;
        }
        let want = ((q * n as f64).ceil() as u64).max(1);
        let (mut acc, mut level) = (0u64, 0usize);
        for g in (0..256).rev() {
            acc += hist[g] as u64;
            if acc >= want {
                level = g;
                break;
            }
        }
        let bound = self.cfg.max_ratio_per_frame;
        let ratio = if level >= CLIPPED_GREY {
            1.0 / bound
        } else {
            // signal(0) = 0 gives an infinite ratio: the clamp makes it the bound.
            self.response.signal(self.cfg.highlight_grey) / self.response.signal(level as f64)
        };
        Some(t * ratio.clamp(1.0 / bound, bound))
    }

    /// One ascent step in ln t from the slope `s` at `x = ln t` (`dm_dlnt`: `s M`).
    fn ascent_step(&mut self, x: f64, s: f64, dm_dlnt: f64) -> f64 {
        let bound = self.cfg.max_ratio_per_frame.ln();
        let gamma = self.cfg.momentum;
        let eta = self.cfg.learning_rate;
        if !self.cfg.adaptive_step && self.cfg.step_law == StepLaw::Linear {
            // The paper's law on this metric: dM/dt = (dM/d ln t) / t, t in seconds.
            let t_us = x.exp();
            let dm_dt = dm_dlnt / (t_us * 1e-6);
            self.v_us = gamma * self.v_us + self.cfg.linear_learning_rate * dm_dt * 1e6;
            let next = (t_us + self.v_us).max(t_us / self.cfg.max_ratio_per_frame);
            let delta = (next / t_us).ln().clamp(-bound, bound);
            // Never more momentum than the bound let through.
            self.v_us = t_us * delta.exp_m1();
            return delta;
        }
        if !self.cfg.adaptive_step {
            // The paper: v = gamma v + eta M'; t += v.
            self.v = (gamma * self.v + eta * s).clamp(-bound, bound);
            return self.v;
        }
        let flipped = matches!(self.prev, Some(p) if p.s * s < 0.0);
        self.step_scale = if flipped {
            (self.step_scale * self.cfg.step_shrink).max(self.cfg.min_step_scale)
        } else {
            (self.step_scale * self.cfg.step_grow).min(1.0)
        };
        self.update_bracket(x, s);
        let delta = match self.bracket {
            Some(b) => {
                let t = x.exp();
                if b.run >= b.probe_every && self.collapsed(&b, t) {
                    // Collapsed, and only one end has been measured for a while, with a
                    // strong slope: the other end may be stale (the optimum may have
                    // drifted past it). Probe just beyond it (0.5%, or the dead band); a
                    // strong slope there of the same sign drops the bracket.
                    let pad = self.probe_step(t);
                    let target = if b.last_side > 0 {
                        b.hi.0 + pad
                    } else {
                        b.lo.0 - pad
                    };
                    if let Some(bm) = self.bracket.as_mut() {
                        bm.probing = true;
                        bm.run = 0;
                    }
                    target - x
                } else {
                    // Secant zero of the slope between the bracket's ends (regula falsi).
                    let target = b.lo.0 + (b.hi.0 - b.lo.0) * b.lo.1 / (b.lo.1 - b.hi.1);
                    target - x
                }
            }
            None => match self.search {
                Some(search) if s != 0.0 => self.search_step(search, x, s, bound),
                Some(_) => 0.0,
                None => gamma * self.v + eta * self.step_scale * s,
            },
        };
        if self.bracket.is_some() {
            self.search = None;
        }
        let delta = delta.clamp(-bound, bound);
        // Momentum only outside a bracket, and never more than what was applied.
        self.v = if self.bracket.is_some() { 0.0 } else { delta };
        delta
    }

    /// After a landing (`last`) where M is not flat: the optimum lies past the knee by an unknown
    /// amount (a hotspot clips before the cells, or the cells clip gradually). Search for
    /// the slope's zero from the frames before and at the landing instead of going on
    /// with the landing's momentum, which overshot a sharp optimum 2-3x.
    fn search_if_landed(&mut self, last: KneeStep) {
        if last == KneeStep::Landing && self.search.is_none() {
            self.search = Some(Search::Secant(0.0));
            self.v = 0.0;
        }
    }

    /// A step of a search for the slope's zero (`s != 0`), in its direction.
    fn search_step(&mut self, search: Search, x: f64, s: f64, bound: f64) -> f64 {
        let min = SEARCH_FIRST_PROBES * self.probe_step(x.exp());
        let step = match search {
            // Doubling from the contradicted end: an optimum that drifted a little is
            // reached without overshooting it by more than the drift, one that moved far
            // in a few frames.
            Search::Doubling(step) => step,
            // Damped secant on the slope through the last two frames while it falls
            // toward zero; where it does not fall, twice the last step.
            Search::Secant(last) => {
                let to_zero = self.prev.map(|p| s * (x - p.x) / (p.s - s));
                match to_zero {
                    Some(d) if d.is_finite() && d * s > 0.0 => SECANT_DAMPING * d.abs(),
                    _ => 2.0 * last,
                }
            }
        };
        let step = step.clamp(min, bound.max(min));
        self.search = Some(match search {
            Search::Doubling(_) => Search::Doubling((2.0 * step).min(bound)),
            Search::Secant(_) => Search::Secant(step),
        });
        step.copysign(s)
    }

    /// True when the bracket is narrower than 0.5% or than the dead band resolves at
    /// `t` microseconds.
    fn collapsed(&self, b: &Bracket, t: f64) -> bool {
        (b.hi.0 - b.lo.0).abs() <= COLLAPSED_WIDTH.max((1.0 + 2.0 * self.cfg.dead_band_us / t).ln())
    }

    /// Step (in ln t) of a probe past a collapsed bracket's end: 0.5%, or the dead band
    /// at `t` microseconds if larger.
    fn probe_step(&self, t: f64) -> f64 {
        COLLAPSED_WIDTH.max((1.0 + 1.5 * self.cfg.dead_band_us / t).ln())
    }

    /// Keep `[lo, hi]`: the latest exposures with a positive and a negative slope.
    fn update_bracket(&mut self, x: f64, s: f64) {
        if s == 0.0 {
            return;
        }
        let side = if s > 0.0 { 1 } else { -1 };
        let strong = s.abs() >= self.cfg.restart_slope;
        let Some(mut b) = self.bracket else {
            if let Some(Sample { x: xp, s: sp, .. }) = self.prev {
                if sp * s < 0.0 {
                    let (lo, hi) = if s > 0.0 {
                        ((x, s), (xp, sp))
                    } else {
                        ((xp, sp), (x, s))
                    };
                    self.bracket = Some(Bracket {
                        lo,
                        hi,
                        age: 0,
                        last_side: side,
                        run: u32::from(strong),
                        probe_every: self.cfg.probe_frames,
                        probing: false,
                    });
                }
            }
            return;
        };
        b.age += 1;
        let was_probe = std::mem::take(&mut b.probing);
        // A slope that rises with exposure above the bracket's falling end (or falls
        // below its rising end) contradicts it. When strong, the optimum is outside (the
        // scene changed, or the metric is not unimodal here): drop the bracket and search
        // again, from twice a probe step that doubles while the sign holds, so a drift is
        // followed without a jump. When weak, it is noise on a collapsed bracket: the
        // point is not kept. An age limit, if configured, also drops the bracket.
        // Within half a probe step of the end, the slope's sign there is noise (where the
        // slope jumps, the jump moves with the pixel noise).
        let beyond = if side > 0 { x - b.hi.0 } else { b.lo.0 - x };
        let inverted = beyond >= 0.5 * self.probe_step(x.exp());
        let aged = self.cfg.bracket_frames > 0 && b.age >= self.cfg.bracket_frames;
        if (inverted && strong) || aged {
            tracing::debug!(inverted, aged, "aaec: bracket dropped, searching again");
            self.bracket = None;
            self.v = 0.0;
            self.search = Some(Search::Doubling(
                SEARCH_FIRST_PROBES * self.probe_step(x.exp()),
            ));
            return;
        }
        if beyond >= 0.0 {
            self.bracket = Some(b);
            return;
        }
        if was_probe && side != b.last_side {
            // The probe confirmed the stale end: the bracket holds; probe less often.
            b.probe_every = b.probe_every.saturating_mul(2).min(MAX_PROBE_FRAMES);
        }
        b.run = match (strong, side == b.last_side) {
            (true, true) => b.run + 1,
            (true, false) => 1,
            (false, _) => 0,
        };
        // Illinois: when the same end moves twice, halve the other end's slope so the
        // secant does not crawl from one side.
        if side > 0 {
            if b.last_side > 0 {
                b.hi.1 *= 0.5;
            }
            b.lo = (x, s);
        } else {
            if b.last_side < 0 {
                b.lo.1 *= 0.5;
            }
            b.hi = (x, s);
        }
        b.last_side = side;
        self.bracket = Some(b);
    }
}

/// One used frame: ln t, slope d ln M / d ln t, ln M.
#[derive(Debug, Clone, Copy)]
struct Sample {
    x: f64,
    s: f64,
    ln_m: f64,
}

/// A search for the slope's zero outside a bracket (it ends when a bracket forms).
#[derive(Debug, Clone, Copy)]
enum Search {
    /// Steps in the slope's direction that double; the next one (ln t).
    Doubling(f64),
    /// Damped secant steps; the last one (ln t).
    Secant(f64),
}

/// Exposures (ln t) and slopes on both sides of the zero of the slope.
#[derive(Debug, Clone, Copy)]
struct Bracket {
    lo: (f64, f64),
    hi: (f64, f64),
    age: u32,
    last_side: i8,
    /// Consecutive updates of the same end with a strong slope.
    run: u32,
    /// Run length after which a collapsed bracket probes its other end.
    probe_every: u32,
    /// The last step was a probe.
    probing: bool,
}

/// The knee landing's last step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum KneeStep {
    None,
    /// Toward the predicted knee.
    Landing,
    /// Below the knee by the largest step.
    Descent,
}

/// The exposure `frame` says it was taken with, when that is a real one.
fn taken_us(frame: &Frame) -> Option<f64> {
    let t = frame.meta.exposure_us;
    (t.is_finite() && t > 0.0).then_some(t)
}

/// The reacquisition sweep (see [`AaecConfig::sweep_after_frames`]).
#[derive(Debug, Clone, Copy)]
struct Sweep {
    center_us: f64,
    /// The last rung commanded (see `Aaec::rung_us`); 0 = none yet.
    j: u32,
    /// The pass's last rung.
    last_j: u32,
    rung_us: f64,
    /// `rung_us` is the centre (between two rungs).
    at_center: bool,
    /// Updates left on this rung.
    left: u32,
    /// The fallback's exposure when the sweep began (it resumes there).
    fallback_us: f64,
}

/// The slope's statistics at a knee hold.
#[derive(Debug, Clone, Copy, Default)]
struct Hold {
    mean: f64,
    var: f64,
    /// Used frames since the hold began.
    age: u32,
    /// Moved down to the predicted clip onset already.
    onset: bool,
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
        ExposureStep {
            exposure_us: next,
            metric: mv.m,
            used_frame: true,
            roi: Some(roi),
        }
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
