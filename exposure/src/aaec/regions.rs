//! The regions AAEC meters: the marker boxes in view (`regions`), held for a few frames
//! after a loss, and the metric combined over them.

use super::{taken_us, Aaec, MarkerRegions};
use crate::metric::MetricValue;
use crate::{Corners, Frame, Roi};

/// Slope `"log-sum"` gives a marker's box that is washed out (negative) or black and
/// flat (positive): twice a linear camera's slope below the knee, so that such a
/// marker outweighs one that is still climbing.
const LOG_SUM_LOST_SLOPE: f64 = 4.0;
/// Clipped fraction of a marker's box from which `"log-sum"` takes it as washed out.
const LOG_SUM_WASHED_OUT: f64 = 0.5;

impl Aaec {
    /// The regions to meter (into `self.regions`) and the box around them: from the
    /// markers in view as `regions` says, else the last ones for a few frames.
    pub(super) fn select_regions(
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
    pub(super) fn evaluate_regions(&mut self, frame: &Frame) -> Option<MetricValue> {
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
}
