//! The ascent in log exposure: momentum with an adaptive step scale, the bracket of the
//! slope's zero (regula falsi, Illinois), its probes, and the searches that follow a
//! contradicted bracket or a knee landing.

use super::config::MAX_PROBE_FRAMES;
use super::knee::KneeStep;
use super::{Aaec, Sample, StepLaw};

/// A bracket narrower than this (in ln t) has collapsed onto its zero.
pub(super) const COLLAPSED_WIDTH: f64 = 0.005;
/// Smallest step (ln t, as a multiple of the probe step) of a search for the slope's
/// zero, and the first step of the one that follows a contradicted bracket.
const SEARCH_FIRST_PROBES: f64 = 2.0;
/// Fraction of the secant's predicted distance to the slope's zero that a secant search
/// steps: past the knee the slope falls faster than linearly (clipping spreads), so the
/// secant through two frames overestimates the distance.
const SECANT_DAMPING: f64 = 0.5;

impl Aaec {
    /// One ascent step in ln t from the slope `s` at `x = ln t` (`dm_dlnt`: `s M`).
    pub(super) fn ascent_step(&mut self, x: f64, s: f64, dm_dlnt: f64) -> f64 {
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
    /// with the landing's momentum, which overshoots a sharp optimum (measured in
    /// docs/design/exposure.md).
    pub(super) fn search_if_landed(&mut self, last: KneeStep) {
        if last == KneeStep::Landing && self.search.is_none() {
            self.search = Some(Search::Secant(0.0));
            self.v = 0.0;
        }
    }

    /// A step of a search for the slope's zero (`s != 0`), in its direction.
    pub(super) fn search_step(&mut self, search: Search, x: f64, s: f64, bound: f64) -> f64 {
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
    pub(super) fn collapsed(&self, b: &Bracket, t: f64) -> bool {
        (b.hi.0 - b.lo.0).abs() <= COLLAPSED_WIDTH.max((1.0 + 2.0 * self.cfg.dead_band_us / t).ln())
    }

    /// Step (in ln t) of a probe past a collapsed bracket's end: 0.5%, or the dead band
    /// at `t` microseconds if larger.
    pub(super) fn probe_step(&self, t: f64) -> f64 {
        COLLAPSED_WIDTH.max((1.0 + 1.5 * self.cfg.dead_band_us / t).ln())
    }

    /// Keep `[lo, hi]`: the latest exposures with a positive and a negative slope.
    pub(super) fn update_bracket(&mut self, x: f64, s: f64) {
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

/// A search for the slope's zero outside a bracket (it ends when a bracket forms).
#[derive(Debug, Clone, Copy)]
pub(super) enum Search {
    /// Steps in the slope's direction that double; the next one (ln t).
    Doubling(f64),
    /// Damped secant steps; the last one (ln t).
    Secant(f64),
}

/// Exposures (ln t) and slopes on both sides of the zero of the slope.
#[derive(Debug, Clone, Copy)]
pub(super) struct Bracket {
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
