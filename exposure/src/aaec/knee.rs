//! The knee landing: after a (re)start, one or two steps to a margin above the exposure
//! where the marker's white cells clip, and the hold there while `M` is flat.

use super::bracket::COLLAPSED_WIDTH;
use super::{sparse_histogram, Aaec};
use crate::Frame;

/// Step scale of the ascent that resumes when a knee hold is released.
const RESTART_STEP_SCALE: f64 = 0.1;

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

impl Aaec {
    /// Grey level of the knee quantile of this frame's regions (every 2nd pixel and
    /// row of each).
    pub(super) fn knee_grey(&self, frame: &Frame) -> Option<usize> {
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
    pub(super) fn knee_step(
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
    /// [`super::AaecConfig::knee_quantile`]).
    pub(super) fn hold_knee(&mut self, clipped_frac: f64, s: f64) -> bool {
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
    pub(super) fn knee_held(&mut self, s: f64) -> Option<f64> {
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
}

/// The knee landing's last step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum KneeStep {
    None,
    /// Toward the predicted knee.
    Landing,
    /// Below the knee by the largest step.
    Descent,
}

/// The slope's statistics at a knee hold.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Hold {
    mean: f64,
    var: f64,
    /// Used frames since the hold began.
    age: u32,
    /// Moved down to the predicted clip onset already.
    onset: bool,
}
