//! The `[exposure.aaec]` section: its keys, defaults and ranges.

use crate::metric::MetricParams;
use markhold_config::{open, open_closed, Checks, ConfigError};
use serde::{Deserialize, Serialize};

/// Longest interval between probes of a collapsed bracket, used frames.
pub(super) const MAX_PROBE_FRAMES: u32 = 64;

/// Default eta of the linear step law (`step_law = "linear"`), s per unit of dM/dt.
const LINEAR_LEARNING_RATE: f64 = 1e-9;

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
    /// probe around its optimum (measured in docs/design/exposure.md).
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
    /// 3; ours: 1, which puts the zero of the slope nearer the argmax of `M`: see
    /// docs/design/exposure.md).
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
    /// it can settle where the web of highlights sits, the marker's cells too dark to
    /// decode (measured in docs/design/exposure.md).
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
    /// noise over a wide range: the knee is the shortest exposure whose `M` is
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
    /// Factor above the predicted clip onset where the knee landing aims, [1, 2]: just
    /// past where `M` turns flat (measured in docs/design/exposure.md).
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
    /// dimmed) or there is no knee. A smaller mean slope is left alone: the tie-break
    /// toward the shorter exposure (its cost is measured in docs/design/exposure.md).
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
        MetricParams::configured(
            self.percentile,
            self.weight_power,
            self.saturation_grey,
            self.saturation_penalty,
        )
    }
}
