//! Where a calibration's corners fell in the image: counts on a grid of cells, how far
//! toward the image corners they reached, and a picture of it. A lens model is only
//! measured where corners fell; beyond them it is extrapolated.

use nalgebra::Vector2;
use opencv::{core, imgcodecs, imgproc, prelude::*};

use crate::error::CvContext;
use crate::VisionError;

/// Grid of the coverage, cells across and down.
pub const CELLS_X: usize = 8;
pub const CELLS_Y: usize = 6;

/// Corner counts per cell of a `CELLS_X` x `CELLS_Y` grid over the image.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    pub width: u32,
    pub height: u32,
    /// Row-major counts.
    pub counts: Vec<u32>,
    /// Fraction of the cells with at least one corner.
    pub cells_fraction: f64,
    /// The farthest corner from the image centre, as a fraction of the centre-to-corner
    /// distance.
    pub radius_fraction: f64,
}

impl Coverage {
    pub fn of(width: u32, height: u32, points: impl IntoIterator<Item = Vector2<f64>>) -> Self {
        let mut counts = vec![0u32; CELLS_X * CELLS_Y];
        let (w, h) = (width as f64, height as f64);
        let (cx, cy) = (w / 2.0, h / 2.0);
        let corner = cx.hypot(cy);
        let mut radius: f64 = 0.0;
        for p in points {
            if !(p.x >= 0.0 && p.x < w && p.y >= 0.0 && p.y < h) {
                continue;
            }
            let i = ((p.x / w * CELLS_X as f64) as usize).min(CELLS_X - 1);
            let j = ((p.y / h * CELLS_Y as f64) as usize).min(CELLS_Y - 1);
            counts[j * CELLS_X + i] += 1;
            radius = radius.max((p.x - cx).hypot(p.y - cy) / corner);
        }
        let filled = counts.iter().filter(|c| **c > 0).count();
        Self {
            width,
            height,
            cells_fraction: filled as f64 / counts.len() as f64,
            counts,
            radius_fraction: radius,
        }
    }

    /// Cells without a corner, as `(column, row)`.
    pub fn empty_cells(&self) -> Vec<(usize, usize)> {
        (0..self.counts.len())
            .filter(|k| self.counts[*k] == 0)
            .map(|k| (k % CELLS_X, k / CELLS_X))
            .collect()
    }
}

/// A PNG of the image area (at most 960 px wide): the grid's cells shaded by their
/// counts (white: none), each view's corners as dots of one colour per view (views left
/// out in grey crosses), and a caption line.
pub fn picture(
    coverage: &Coverage,
    views: &[(bool, Vec<Vector2<f64>>)],
    caption: &str,
) -> Result<Vec<u8>, VisionError> {
    let (w, h) = (coverage.width as f64, coverage.height as f64);
    let scale = (960.0 / w).clamp(0.1, 1.0);
    let (pw, ph) = ((w * scale).round() as i32, (h * scale).round() as i32);
    let band = 28;
    let mut img = core::Mat::new_rows_cols_with_default(
        ph + band,
        pw,
        core::CV_8UC3,
        core::Scalar::all(255.0),
    )
    .cv("coverage image")?;
    let max = coverage.counts.iter().copied().max().unwrap_or(0).max(1) as f64;
    let (cw, ch) = (pw as f64 / CELLS_X as f64, ph as f64 / CELLS_Y as f64);
    for j in 0..CELLS_Y {
        for i in 0..CELLS_X {
            let c = coverage.counts[j * CELLS_X + i] as f64;
            // Light blue growing darker with the count; empty cells stay white.
            let shade = if c > 0.0 {
                235.0 - 80.0 * (c / max)
            } else {
                255.0
            };
            let rect = core::Rect::new(
                (i as f64 * cw).round() as i32,
                (j as f64 * ch).round() as i32,
                cw.round() as i32,
                ch.round() as i32,
            );
            imgproc::rectangle(
                &mut img,
                rect,
                core::Scalar::new(255.0, shade + 10.0, shade, 0.0),
                imgproc::FILLED,
                imgproc::LINE_8,
                0,
            )
            .cv("coverage cell")?;
            imgproc::rectangle(
                &mut img,
                rect,
                core::Scalar::new(200.0, 200.0, 200.0, 0.0),
                1,
                imgproc::LINE_8,
                0,
            )
            .cv("coverage grid")?;
        }
    }
    for (k, (used, pts)) in views.iter().enumerate() {
        let colour = if *used {
            palette(k)
        } else {
            core::Scalar::new(150.0, 150.0, 150.0, 0.0)
        };
        for p in pts {
            let c = core::Point::new((p.x * scale).round() as i32, (p.y * scale).round() as i32);
            if *used {
                imgproc::circle(&mut img, c, 2, colour, imgproc::FILLED, imgproc::LINE_AA, 0)
                    .cv("coverage dot")?;
            } else {
                imgproc::draw_marker(
                    &mut img,
                    c,
                    colour,
                    imgproc::MARKER_CROSS,
                    5,
                    1,
                    imgproc::LINE_8,
                )
                .cv("coverage cross")?;
            }
        }
    }
    imgproc::rectangle(
        &mut img,
        core::Rect::new(0, 0, pw, ph),
        core::Scalar::all(0.0),
        1,
        imgproc::LINE_8,
        0,
    )
    .cv("coverage frame")?;
    imgproc::put_text(
        &mut img,
        caption,
        core::Point::new(6, ph + 19),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.45,
        core::Scalar::all(0.0),
        1,
        imgproc::LINE_AA,
        false,
    )
    .cv("coverage caption")?;
    let mut buf = core::Vector::<u8>::new();
    imgcodecs::imencode(".png", &img, &mut buf, &core::Vector::new()).cv("imencode png")?;
    Ok(buf.to_vec())
}

/// Distinct colours (BGR) for the views.
fn palette(k: usize) -> core::Scalar {
    const C: [(f64, f64, f64); 8] = [
        (180.0, 119.0, 31.0),
        (14.0, 127.0, 255.0),
        (44.0, 160.0, 44.0),
        (40.0, 39.0, 214.0),
        (189.0, 103.0, 148.0),
        (75.0, 86.0, 140.0),
        (194.0, 119.0, 227.0),
        (34.0, 189.0, 188.0),
    ];
    let (b, g, r) = C[k % C.len()];
    core::Scalar::new(b, g, r, 0.0)
}
