//! Which exposure a streamed frame was taken with.
//!
//! A stream carries no per-frame exposure: a command takes effect some frames later
//! (camera pipeline, encoder, transport), and that delay is not known in advance. The
//! delay is estimated online from the step response of the frame mean after each
//! exposure change that is large enough to see; each frame is then attributed to the
//! exposure in force when it was exposed. Frames in the window where the estimates
//! disagree (or, before enough estimates, in the whole search window) get no exposure
//! (NaN): AAEC uses only frames exposed as commanded, so it skips them.
//!
//! Everything lives in fixed arrays: nothing is allocated per frame.

/// Longest delay searched for, frames.
pub const MAX_DELAY_FRAMES: u32 = 12;
/// Steps whose estimates make up the window.
const RECENT: usize = 5;
/// Estimates needed before the window narrows from the whole search range.
const MIN_ESTIMATES: usize = 3;
/// Smallest exposure change (|ln ratio|) whose step response is looked for.
const MIN_STEP_LN: f64 = 0.15;
/// Commands remembered.
const CHANGES: usize = 32;

#[derive(Debug, Clone, Copy, Default)]
struct Change {
    /// Frames up to this one were delivered before the command.
    after_seq: u64,
    exposure_us: f64,
    /// The exposure at start-up: in force from the first frame.
    initial: bool,
}

/// A step whose response is being looked for.
#[derive(Debug, Clone, Copy)]
struct Pending {
    after_seq: u64,
    /// ln of the mean of the last frame before the command.
    ln_mean0: f64,
    ln_ratio: f64,
}

/// Online delay estimate and per-frame exposure attribution.
#[derive(Debug, Clone)]
pub struct Attribution {
    changes: [Change; CHANGES],
    /// Changes recorded (the newest is at `(n - 1) % CHANGES`).
    n: usize,
    estimates: [u32; RECENT],
    n_estimates: usize,
    pending: Option<Pending>,
    /// Last delivered frame's seq and ln mean.
    last: Option<(u64, f64)>,
}

impl Attribution {
    /// Starts with `initial_us` in force since before the first frame.
    pub fn new(initial_us: f64) -> Self {
        let mut a = Self {
            changes: [Change::default(); CHANGES],
            n: 0,
            estimates: [0; RECENT],
            n_estimates: 0,
            pending: None,
            last: None,
        };
        a.push(Change {
            after_seq: 0,
            exposure_us: initial_us,
            initial: true,
        });
        a
    }

    fn push(&mut self, c: Change) {
        self.changes[self.n % CHANGES] = c;
        self.n += 1;
    }

    /// A new exposure was commanded after the last delivered frame.
    pub fn commanded(&mut self, exposure_us: f64) {
        let newest = self.changes[(self.n - 1) % CHANGES];
        if (exposure_us - newest.exposure_us).abs() < 1e-9 {
            return;
        }
        let after_seq = self.last.map_or(0, |(s, _)| s);
        // A new step before the last one was seen spoils that estimate.
        self.pending = None;
        let ln_ratio = (exposure_us / newest.exposure_us).ln();
        if let Some((_, ln_mean0)) = self.last {
            if ln_ratio.abs() >= MIN_STEP_LN && ln_mean0.is_finite() {
                self.pending = Some(Pending {
                    after_seq,
                    ln_mean0,
                    ln_ratio,
                });
            }
        }
        self.push(Change {
            after_seq,
            exposure_us,
            initial: false,
        });
    }

    /// The delay window `[lo, hi]`: a frame `o` frames after a command (o = 0: the
    /// first frame delivered after it) has the new exposure if `o >= hi`, the old one
    /// if `o < lo`, and is uncertain in between.
    pub fn window(&self) -> (u32, u32) {
        if self.n_estimates < MIN_ESTIMATES {
            return (0, MAX_DELAY_FRAMES);
        }
        let k = self.n_estimates.min(RECENT);
        let e = &self.estimates[..k];
        let lo = e.iter().copied().min().unwrap_or(0);
        let hi = e.iter().copied().max().unwrap_or(MAX_DELAY_FRAMES);
        (lo, hi)
    }

    /// The median of the recent delay estimates, frames (None before any step was seen).
    pub fn delay_frames(&self) -> Option<u32> {
        let k = self.n_estimates.min(RECENT);
        if k == 0 {
            return None;
        }
        let mut e = [0u32; RECENT];
        e[..k].copy_from_slice(&self.estimates[..k]);
        e[..k].sort_unstable();
        Some(e[k / 2])
    }

    /// Steps whose delay was measured.
    pub fn steps_measured(&self) -> usize {
        self.n_estimates
    }

    /// A frame was delivered (`seq` counts every frame the camera took, passed over or
    /// not; `mean` is its mean grey level). Returns the exposure it was taken with, or
    /// NaN when that is uncertain.
    pub fn frame(&mut self, seq: u64, mean: f64) -> f64 {
        let ln_mean = if mean > 2.0 && mean < 250.0 {
            mean.ln()
        } else {
            f64::NAN
        };
        self.observe_step(seq, ln_mean);
        self.last = Some((seq, ln_mean));
        self.attribute(seq)
    }

    fn observe_step(&mut self, seq: u64, ln_mean: f64) {
        let Some(p) = self.pending else {
            return;
        };
        let o = seq.saturating_sub(p.after_seq + 1);
        if o > u64::from(MAX_DELAY_FRAMES) {
            self.pending = None;
            return;
        }
        if !ln_mean.is_finite() {
            return;
        }
        let moved = ln_mean - p.ln_mean0;
        // Half the expected change in the expected direction: the new exposure is in.
        if moved * p.ln_ratio.signum() >= 0.5 * p.ln_ratio.abs() {
            self.estimates.copy_within(0..RECENT - 1, 1);
            self.estimates[0] = o as u32;
            self.n_estimates += 1;
            self.pending = None;
        }
    }

    fn attribute(&self, seq: u64) -> f64 {
        let (lo, hi) = self.window();
        let kept = self.n.min(CHANGES);
        // Newest first: the first change fully in force decides, unless a newer one
        // may already be.
        for i in 0..kept {
            let c = self.changes[(self.n - 1 - i) % CHANGES];
            if c.initial {
                return c.exposure_us;
            }
            let o = seq.saturating_sub(c.after_seq + 1);
            if seq <= c.after_seq || o < u64::from(lo) {
                continue;
            }
            if o >= u64::from(hi) {
                return c.exposure_us;
            }
            return f64::NAN;
        }
        f64::NAN
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera whose frame mean follows its exposure `delay` frames late.
    fn run(delay: u64, steps: &[(u64, f64)], frames: u64) -> (Attribution, Vec<(f64, f64)>) {
        let mut a = Attribution::new(1000.0);
        let mut history = vec![1000.0f64; frames as usize + 1];
        let mut out = Vec::new();
        for seq in 1..=frames {
            let taken = history[seq as usize];
            let mean = (taken / 1000.0 * 60.0).min(240.0);
            let got = a.frame(seq, mean);
            out.push((got, taken));
            if let Some(&(_, t)) = steps.iter().find(|(s, _)| *s == seq) {
                a.commanded(t);
                for h in history.iter_mut().skip((seq + 1 + delay) as usize) {
                    *h = t;
                }
            }
        }
        (a, out)
    }

    #[test]
    fn estimates_the_delay_and_never_misattributes() {
        for delay in [0u64, 2, 4, 8] {
            let steps: Vec<(u64, f64)> = (0..8)
                .map(|i| (10 + 20 * i, if i % 2 == 0 { 1500.0 } else { 1000.0 }))
                .collect();
            let (a, out) = run(delay, &steps, 200);
            assert_eq!(a.delay_frames(), Some(delay as u32), "delay {delay}");
            for (got, taken) in &out {
                assert!(
                    got.is_nan() || (got - taken).abs() < 1e-9,
                    "{got} vs {taken}"
                );
            }
            // Once the window closed, no frame is left uncertain.
            assert!(out[150..].iter().all(|(g, _)| !g.is_nan()), "delay {delay}");
        }
    }

    #[test]
    fn small_steps_are_not_measured_but_still_attributed_conservatively() {
        let (a, out) = run(3, &[(10, 1050.0)], 40);
        assert_eq!(a.steps_measured(), 0);
        assert!(out[10..10 + MAX_DELAY_FRAMES as usize]
            .iter()
            .all(|(g, _)| g.is_nan()));
        assert!((out[30].0 - 1050.0).abs() < 1e-9);
    }
}
