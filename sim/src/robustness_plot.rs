//! The heat map of `markhold robustness`: one row per cell, one column per figure, each
//! square coloured by how much of its bound the figure uses (green: none, red: all of
//! it, dark: over it) and labelled with the value. Drawn with plotters, written as SVG
//! and PNG like compare's plots (`super::plots`).

use crate::error::SimError;
use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::plots::{both, plot_err};
use super::robustness::RobustnessResults;

/// Chatter at which the square turns red, sign changes a second.
const CHATTER_RED_HZ: f64 = 5.0;

const COLUMNS: [&str; 5] = [
    "position RMS",
    "worst excursion",
    "chatter",
    "detection",
    "held",
];
const LABEL_W: i32 = 230;
const COL_W: i32 = 140;
const ROW_H: i32 = 30;
const TOP: i32 = 70;

/// Green (0) through yellow to red (1); dark red above 1.
fn shade(used: f64) -> RGBColor {
    if !used.is_finite() || used > 1.0 {
        return RGBColor(120, 0, 0);
    }
    let u = used.clamp(0.0, 1.0);
    if u < 0.5 {
        RGBColor((80.0 + 350.0 * u) as u8, 190, 80)
    } else {
        RGBColor(240, (190.0 - 300.0 * (u - 0.5)) as u8, 60)
    }
}

fn size(r: &RobustnessResults) -> (u32, u32) {
    let w = LABEL_W + COL_W * COLUMNS.len() as i32 + 20;
    let h = TOP + ROW_H * r.cells.len() as i32 + 20;
    (w as u32, h as u32)
}

fn heat_map<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    r: &RobustnessResults,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let title = format!(
        "Robustness on {}: {} s a cell, share of the held bound",
        r.site, r.seconds
    );
    root.draw(&Text::new(title, (10, 12), ("sans-serif", 20)))
        .map_err(plot_err)?;
    for (j, c) in COLUMNS.iter().enumerate() {
        let x = LABEL_W + COL_W * j as i32 + 8;
        root.draw(&Text::new(*c, (x, TOP - 24), ("sans-serif", 15)))
            .map_err(plot_err)?;
    }
    let b = &r.bounds;
    for (i, c) in r.cells.iter().enumerate() {
        let y = TOP + ROW_H * i as i32;
        root.draw(&Text::new(
            c.cell.name.clone(),
            (10, y + 8),
            ("sans-serif", 15),
        ))
        .map_err(plot_err)?;
        let squares = [
            (
                c.position_rms_m / b.rms_m,
                format!("{:.1} mm", c.position_rms_m * 1e3),
            ),
            (
                c.worst_excursion_m / b.excursion_m,
                format!("{:.1} mm", c.worst_excursion_m * 1e3),
            ),
            (
                c.chatter_max_hz / CHATTER_RED_HZ,
                format!("{:.2}/s", c.chatter_max_hz),
            ),
            (
                (1.0 - c.detection_rate) / (1.0 - b.detection).max(1e-9),
                format!("{:.1} %", c.detection_rate * 100.0),
            ),
            (
                if c.held { 0.0 } else { 2.0 },
                if c.held { "yes" } else { "no" }.to_string(),
            ),
        ];
        for (j, (used, label)) in squares.into_iter().enumerate() {
            let x = LABEL_W + COL_W * j as i32;
            let fill = shade(used);
            root.draw(&Rectangle::new(
                [(x, y), (x + COL_W - 2, y + ROW_H - 2)],
                fill.filled(),
            ))
            .map_err(plot_err)?;
            let ink = if used > 1.0 { WHITE } else { BLACK };
            root.draw(&Text::new(
                label,
                (x + 10, y + 8),
                ("sans-serif", 14).into_font().color(&ink),
            ))
            .map_err(plot_err)?;
        }
    }
    Ok(())
}

/// `heat_map.svg` and `heat_map.png` in `dir`; returns their names.
pub fn write_heat_map(r: &RobustnessResults, dir: &Path) -> Result<Vec<String>, SimError> {
    Ok(both!(dir, "heat_map", size(r), heat_map(r)))
}
