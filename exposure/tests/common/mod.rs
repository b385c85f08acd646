//! A small scene renderer for the controller tests: a linear (or given-response) camera
//! imaging a marker-like pattern under uneven light (bright spot on the marker, dark
//! surround), with an optional caustic flicker. Deterministic.

#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
#![allow(dead_code)]

use markhold_exposure::{
    Aaec, AaecConfig, Corners, ExposureController, ExposureLimits, Frame, GradientMetric, MeanAe,
    MeanAeConfig, MetricParams, Response, Roi,
};

pub const W: u32 = 320;
pub const H: u32 = 240;

pub fn limits() -> ExposureLimits {
    ExposureLimits {
        min_us: 10.0,
        max_us: 30_000.0,
        fps: 30.0,
    }
}

/// AAEC on a linear camera with the mean AE as its fallback, both from `initial`.
pub fn aaec(cfg: AaecConfig, initial: f64) -> Aaec {
    let fallback = Box::new(MeanAe::new(MeanAeConfig::default(), limits(), initial).unwrap());
    Aaec::new(cfg, Response::linear(), limits(), initial, fallback).unwrap()
}

/// Irradiance map in units where `E * t_us / FULL_WELL_US = 1` is full well.
pub const FULL_WELL_US: f64 = 1000.0;

/// The corners of an axis-aligned square marker image with its top-left at (`mx`, `my`)
/// and `side` pixels wide, clockwise from the top-left.
pub fn square_corners(mx: f64, my: f64, side: f64) -> [[f32; 2]; 4] {
    [
        [mx as f32, my as f32],
        [(mx + side) as f32, my as f32],
        [(mx + side) as f32, (my + side) as f32],
        [mx as f32, (my + side) as f32],
    ]
}

pub struct Scene {
    pub irradiance: Vec<f64>,
    pub corners: Corners,
    pub response: Response,
    /// Multiplicative light pattern per pixel and frame (caustics), if any.
    pub caustic_amp: f64,
    /// Standard deviation of a per-pixel, per-frame sensor noise, grey levels (uniform,
    /// from a hash of pixel and frame index: deterministic).
    pub noise_grey: f64,
}

/// Reflectance of the 6x6 cell marker (black border, fixed inner bits).
pub fn marker_cell(cx: usize, cy: usize) -> f64 {
    const BITS: [[u8; 4]; 4] = [[1, 0, 1, 1], [0, 1, 0, 0], [1, 1, 0, 1], [0, 0, 1, 0]];
    if cx == 0 || cy == 0 || cx == 5 || cy == 5 {
        0.05
    } else if BITS[cy - 1][cx - 1] == 1 {
        0.9
    } else {
        0.05
    }
}

/// Reflectance of the textured surround (rock / sand) at (`px`, `py`).
pub fn rock(px: f64, py: f64) -> f64 {
    0.35 + 0.2 * (px * 0.11).sin() * (py * 0.07).cos() + 0.1 * (px * 0.023 + py * 0.031).sin()
}

/// A `w` x `h` irradiance map, each pixel the mean of `e` over a 4x4 grid of sample points
/// in it: anti-aliased edges, like a real lens.
pub fn supersampled(w: usize, h: usize, e: impl Fn(f64, f64) -> f64) -> Vec<f64> {
    let mut irradiance = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let px = x as f64 + (sx as f64 + 0.5) / 4.0;
                    let py = y as f64 + (sy as f64 + 0.5) / 4.0;
                    acc += e(px, py);
                }
            }
            irradiance[y * w + x] = acc / 16.0;
        }
    }
    irradiance
}

/// A uniform number in [0, 1) from the hash of `h` (deterministic sensor noise).
pub fn unit_hash(mut h: u64) -> f64 {
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

impl Scene {
    /// Marker of `side` pixels centred at (cx, cy); light `spot` on the marker and
    /// `ambient` elsewhere (relative irradiance).
    pub fn marker(response: Response, spot: f64, ambient: f64) -> Self {
        Self::marker_lit(response, spot, ambient, 400.0)
    }

    /// As [`Scene::marker`] with the light spot's radius in pixels.
    pub fn marker_lit(response: Response, spot: f64, ambient: f64, radius: f64) -> Self {
        let (w, h) = (W as usize, H as usize);
        let side = 120.0;
        let (mx, my) = (160.0 - side / 2.0, 120.0 - side / 2.0);
        let irradiance = supersampled(w, h, |px, py| {
            let (u, v) = ((px - mx) / side, (py - my) / side);
            let refl = if (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v) {
                marker_cell((u * 6.0) as usize, (v * 6.0) as usize)
            } else {
                rock(px, py)
            };
            let d2 = ((px - 160.0).powi(2) + (py - 120.0).powi(2)) / radius.powi(2);
            refl * (ambient + spot * (-d2).exp())
        });
        Self::still(irradiance, square_corners(mx, my, side), response)
    }

    /// The adversarial picture: a lamp lights a round plate (radius `plate_r` px) holding
    /// a marker of `side` px in a dark surround lit only by `ambient`. On the plate a
    /// veiling glare of `glare` (relative to the lamp) lifts black and white cells alike,
    /// so a long exposure clips the whole plate into one white disc.
    pub fn lamp_plate(
        response: Response,
        side: f64,
        plate_r: f64,
        spot: f64,
        ambient: f64,
        glare: f64,
    ) -> Self {
        let (w, h) = (W as usize, H as usize);
        let (cx, cy) = (160.0, 120.0);
        let (mx, my) = (cx - side / 2.0, cy - side / 2.0);
        let irradiance = supersampled(w, h, |px, py| {
            let (u, v) = ((px - mx) / side, (py - my) / side);
            let on_plate = (px - cx).powi(2) + (py - cy).powi(2) <= plate_r * plate_r;
            if on_plate {
                let refl = if (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v) {
                    marker_cell((u * 6.0) as usize, (v * 6.0) as usize)
                } else {
                    0.9
                };
                (refl + glare) * spot + refl * ambient
            } else {
                rock(px, py) * ambient
            }
        });
        Self::still(irradiance, square_corners(mx, my, side), response)
    }

    /// Mean grey of the white cells minus that of the black cells, each sampled on the
    /// middle half of the cell: a stand-in for a marker detector.
    pub fn cell_contrast(&self, frame: &Frame) -> f64 {
        let [x0, y0] = self.corners[0];
        let side = (self.corners[1][0] - x0) as f64;
        let cell = side / 6.0;
        let (mut wsum, mut wn, mut bsum, mut bn) = (0.0, 0.0, 0.0, 0.0);
        for cy in 0..6 {
            for cx in 0..6 {
                let white = marker_cell(cx, cy) > 0.5;
                let (ux, uy) = (x0 as f64 + cx as f64 * cell, y0 as f64 + cy as f64 * cell);
                let (a, b) = (
                    (0.25 * cell).ceil() as usize,
                    (0.75 * cell).floor() as usize,
                );
                for y in a..b {
                    for x in a..b {
                        let (px, py) = (ux as usize + x, uy as usize + y);
                        let g = frame.data[py * W as usize + px] as f64;
                        if white {
                            wsum += g;
                            wn += 1.0;
                        } else {
                            bsum += g;
                            bn += 1.0;
                        }
                    }
                }
            }
        }
        wsum / wn - bsum / bn
    }

    /// A smooth, gradient-rich pattern (two crossed gratings under a vignette): most
    /// pixels have gradients far above 8-bit rounding, so finite differences of `M` are
    /// clean. The "marker" is the centre 160 x 120 window.
    pub fn grating(response: Response) -> Self {
        let (w, h) = (W as usize, H as usize);
        let mut irradiance = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64, y as f64);
                let vignette = 1.0 - 0.5 * ((fx - 160.0).powi(2) + (fy - 120.0).powi(2)) / 40000.0;
                let pattern = 0.5
                    + 0.22 * (fx / 4.0).sin() * (fy / 5.0).cos()
                    + 0.18 * ((fx + 2.0 * fy) / 9.0).sin();
                irradiance[y * w + x] = vignette * pattern;
            }
        }
        let corners = [[80.0, 60.0], [240.0, 60.0], [240.0, 180.0], [80.0, 180.0]];
        Self::still(irradiance, corners, response)
    }

    /// A scene of `irradiance` with the marker at `corners`, without caustics or noise.
    fn still(irradiance: Vec<f64>, corners: [[f32; 2]; 4], response: Response) -> Self {
        Self {
            irradiance,
            corners,
            response,
            caustic_amp: 0.0,
            noise_grey: 0.0,
        }
    }

    /// Render at `t_us` into `frame` (frame index `k` drives the caustics).
    pub fn render(&self, t_us: f64, k: u64, frame: &mut Frame) {
        frame.resize(W, H);
        let scale = t_us / FULL_WELL_US;
        let ph = k as f64 * 2.3;
        for y in 0..H as usize {
            for x in 0..W as usize {
                let mut e = self.irradiance[y * W as usize + x];
                if self.caustic_amp > 0.0 {
                    // Moving bright ridges, changing every frame.
                    let c = ((x as f64 * 0.21 + ph).sin()
                        + (y as f64 * 0.17 - 1.3 * ph).sin()
                        + ((x + y) as f64 * 0.13 + 0.7 * ph).sin())
                        / 3.0;
                    e *= 1.0 + self.caustic_amp * c.max(0.0).powi(2) * 3.0;
                }
                let mut g = self.response.grey(e * scale);
                if self.noise_grey > 0.0 && g < 255.0 {
                    let u = unit_hash(
                        (x as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                            ^ (y as u64 + 1).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
                            ^ (k + 1).wrapping_mul(0x1656_67B1_9E37_79F9),
                    );
                    g += self.noise_grey * 12f64.sqrt() * (u - 0.5);
                }
                frame.data[y * W as usize + x] = g.round().clamp(0.0, 255.0) as u8;
            }
        }
        frame.meta.exposure_us = t_us;
        frame.meta.seq = k;
        frame.meta.stamp_s = k as f64 / 30.0;
    }

    /// The same scene with every irradiance multiplied by `factor` (a change of light).
    pub fn scaled(&self, factor: f64) -> Scene {
        Scene {
            irradiance: self.irradiance.iter().map(|e| e * factor).collect(),
            corners: self.corners,
            response: self.response.clone(),
            caustic_amp: self.caustic_amp,
            noise_grey: self.noise_grey,
        }
    }

    pub fn roi(&self) -> Roi {
        Roi::from_corners_padded(&self.corners, 0.1, W, H).unwrap()
    }

    /// `M` on `roi` at exposure `t_us`.
    pub fn metric_at(&self, t_us: f64, roi: Roi, params: MetricParams) -> f64 {
        let mut f = Frame::new(W, H);
        self.render(t_us, 0, &mut f);
        let mut m = GradientMetric::new(&self.response, params);
        m.evaluate(f.view().crop(roi))
            .map(|v| v.m)
            .unwrap_or(f64::NAN)
    }

    /// Argmax of `score(t)` over a log sweep of `[lo, hi]` with ratio steps of 0.5%.
    pub fn argmax(lo: f64, hi: f64, mut score: impl FnMut(f64) -> f64) -> f64 {
        let (mut best_t, mut best) = (lo, f64::MIN);
        let mut t = lo;
        while t <= hi {
            let s = score(t);
            if s > best {
                best = s;
                best_t = t;
            }
            t *= 1.005;
        }
        best_t
    }
}

/// Run a controller on the scene for `frames` frames; a command issued after frame k
/// takes effect at frame k + 1 + `delay`. Returns the exposure of every frame.
pub fn run(
    scene: &Scene,
    ctrl: &mut dyn ExposureController,
    t0: f64,
    frames: usize,
    delay: usize,
    marker: bool,
) -> Vec<f64> {
    let mut applied = vec![t0; frames + delay + 2];
    let mut frame = Frame::new(W, H);
    for k in 0..frames {
        scene.render(applied[k], k as u64, &mut frame);
        let step = ctrl.update(&frame, marker.then_some(&scene.corners));
        assert!(step.exposure_us.is_finite());
        for a in applied.iter_mut().skip(k + 1 + delay) {
            *a = step.exposure_us;
        }
    }
    applied.truncate(frames);
    applied
}

/// As [`run`], with the marker reported only in frames where the cells' contrast is at
/// least `min_contrast` grey levels (a stand-in for a detector).
pub fn run_detecting(
    scene: &Scene,
    ctrl: &mut dyn ExposureController,
    t0: f64,
    frames: usize,
    delay: usize,
    min_contrast: f64,
) -> (Vec<f64>, Vec<bool>) {
    let mut applied = vec![t0; frames + delay + 2];
    let mut seen = Vec::with_capacity(frames);
    let mut frame = Frame::new(W, H);
    for k in 0..frames {
        scene.render(applied[k], k as u64, &mut frame);
        let found = scene.cell_contrast(&frame) >= min_contrast;
        seen.push(found);
        let step = ctrl.update(&frame, found.then_some(&scene.corners));
        assert!(step.exposure_us.is_finite());
        for a in applied.iter_mut().skip(k + 1 + delay) {
            *a = step.exposure_us;
        }
    }
    applied.truncate(frames);
    (applied, seen)
}

/// First frame index from which every exposure stays within `tol` (relative) of `target`.
pub fn settled_at(exposures: &[f64], target: f64, tol: f64) -> Option<usize> {
    let mut first = None;
    for (i, &t) in exposures.iter().enumerate() {
        if ((t - target) / target).abs() <= tol {
            first.get_or_insert(i);
        } else {
            first = None;
        }
    }
    first
}
