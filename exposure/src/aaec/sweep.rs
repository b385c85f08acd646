//! While the marker is lost: the reacquisition sweep around the exposure it was last
//! seen at, and the highlight guard on the fallback.

use super::{sparse_histogram, Aaec};
use crate::Frame;

/// Grey level from which the highlight guard takes a pixel as clipped.
const CLIPPED_GREY: usize = 254;

impl Aaec {
    /// Rung `j` (1, 2, ...) of a sweep around `center_us`: x r, / r, x r^2, / r^2, ...,
    /// clamped to the camera's range; `None` where the clamp makes it the same as the
    /// rung before it on its side.
    pub(super) fn rung_us(&self, center_us: f64, j: u32) -> Option<f64> {
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
    pub(super) fn schedule_sweep(&mut self) {
        self.sweep_at = self
            .lost_frames
            .saturating_add(self.cfg.sweep_after_frames)
            .saturating_sub(1);
    }

    /// The exposure to command on this update of the reacquisition sweep; `None` when
    /// its pass is over (the fallback runs again, from where it was).
    pub(super) fn sweep_step(&mut self) -> Option<f64> {
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
    pub(super) fn highlight_cap(&self, frame: &Frame, t: f64) -> Option<f64> {
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
}

/// The reacquisition sweep (see [`super::AaecConfig::sweep_after_frames`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Sweep {
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
