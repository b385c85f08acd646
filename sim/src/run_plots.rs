//! Plots of one `markhold hil` run (`--plots DIR`), drawn after the run from the runner's
//! per-frame series ([`RunStats`]): the trajectory against the station and the marker
//! (top and side view, marker frame, ground truth), exposure and metric over time,
//! detection and loop latency over time. Each is written as PNG and SVG with compare's
//! backends ([`super::plots`]).

use crate::error::SimError;
use std::path::Path;

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;

use super::plots::{both, plot_err};
use super::summary::RunStats;

/// Size of the time plots.
const SIZE: (u32, u32) = (900, 640);
/// Size of the trajectory plot (two views side by side).
const TRAJECTORY_SIZE: (u32, u32) = (1200, 600);

/// The vehicle's path and the time series.
pub const VEHICLE_COLOR: RGBColor = RGBColor(214, 39, 40);
/// The station (desired vehicle position).
pub const STATION_COLOR: RGBColor = RGBColor(44, 160, 44);
/// The marker plate.
pub const MARKER_COLOR: RGBColor = RGBColor(31, 119, 180);

/// What the plots say about the run besides its series.
#[derive(Debug, Clone)]
pub struct RunPlotInfo {
    /// Caption prefix: site, method, lighting, seed.
    pub title: String,
    /// Side of the printed marker, metres.
    pub marker_size_m: f64,
}

/// Write every plot of a run into `dir` (which must exist); returns the file names.
pub fn write_run_plots(
    stats: &RunStats,
    info: &RunPlotInfo,
    dir: &Path,
) -> Result<Vec<String>, SimError> {
    let mut files = Vec::new();
    files.extend(both!(
        dir,
        "trajectory",
        TRAJECTORY_SIZE,
        trajectory(stats, info)
    ));
    files.extend(both!(
        dir,
        "exposure_metric",
        SIZE,
        exposure_metric(stats, info)
    ));
    files.extend(both!(
        dir,
        "detection_latency",
        SIZE,
        detection_latency(stats, info)
    ));
    Ok(files)
}

/// `(lo, hi)` of the finite values, padded by `pad` of the span, at least `min_span` wide.
fn padded_range(values: impl Iterator<Item = f64>, pad: f64, min_span: f64) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return (-0.5 * min_span, 0.5 * min_span);
    }
    let mid = 0.5 * (lo + hi);
    let half = (0.5 * (hi - lo) * (1.0 + 2.0 * pad)).max(0.5 * min_span);
    (mid - half, mid + half)
}

/// One view of the trajectory in the marker frame: `h`, `v` are the marker-frame axes on
/// the horizontal and vertical axis (0 right, 1 up, 2 out of the marker face), `along`
/// the axis the marker plate is drawn along.
struct View<'a> {
    caption: &'a str,
    desc: &'a str,
    h: usize,
    v: usize,
    along: usize,
}

fn trajectory<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    stats: &RunStats,
    info: &RunPlotInfo,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let root = root
        .titled(
            &format!("{}: trajectory, marker frame, ground truth", info.title),
            ("sans-serif", 20),
        )
        .map_err(plot_err)?;
    let (w, _) = root.dim_in_pixel();
    let (left, right) = root.split_horizontally(w / 2);
    let top = View {
        caption: "top view",
        desc: "x (right of the marker) [m]; range z [m] on the vertical axis",
        h: 0,
        v: 2,
        along: 0,
    };
    let side = View {
        caption: "side view",
        desc: "range z [m]; height y (up) [m] on the vertical axis",
        h: 2,
        v: 1,
        along: 1,
    };
    trajectory_view(&left, stats, info, &top)?;
    trajectory_view(&right, stats, info, &side)
}

fn trajectory_view<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    stats: &RunStats,
    info: &RunPlotInfo,
    view: &View<'_>,
) -> Result<(), SimError> {
    let (h, v) = (view.h, view.v);
    let path: Vec<(f64, f64)> = stats.vehicle_marker.iter().map(|p| (p[h], p[v])).collect();
    let st = stats.t_marker_station().translation.vector;
    let station = (st[h], st[v]);
    let half = 0.5 * info.marker_size_m;
    let end = |s: f64| {
        let mut e = [0.0; 3];
        e[view.along] = s * half;
        (e[h], e[v])
    };
    let plate = [end(-1.0), end(1.0)];
    let xr = padded_range(
        path.iter()
            .map(|p| p.0)
            .chain([station.0, plate[0].0, plate[1].0]),
        0.08,
        0.05,
    );
    let yr = padded_range(
        path.iter()
            .map(|p| p.1)
            .chain([station.1, plate[0].1, plate[1].1]),
        0.08,
        0.05,
    );
    let mut chart = ChartBuilder::on(area)
        .caption(
            format!(
                "{}: vehicle (red) vs station (green), marker (blue)",
                view.caption
            ),
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc(view.desc)
        .draw()
        .map_err(plot_err)?;
    chart
        .draw_series(std::iter::once(PathElement::new(
            plate.to_vec(),
            MARKER_COLOR.stroke_width(4),
        )))
        .map_err(plot_err)?;
    chart
        .draw_series(std::iter::once(Circle::new(
            station,
            6,
            STATION_COLOR.filled(),
        )))
        .map_err(plot_err)?;
    if let Some(start) = path.first() {
        chart
            .draw_series(std::iter::once(Circle::new(
                *start,
                5,
                VEHICLE_COLOR.stroke_width(2),
            )))
            .map_err(plot_err)?;
    }
    chart
        .draw_series(LineSeries::new(path, VEHICLE_COLOR.stroke_width(2)))
        .map_err(plot_err)?;
    Ok(())
}

/// A time series as line segments, broken where a value is not finite (or not positive,
/// for a log axis).
fn segments(time_s: &[f64], y: &[f64], positive: bool) -> Vec<Vec<(f64, f64)>> {
    let mut out: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut cur = Vec::new();
    for (&t, &v) in time_s.iter().zip(y) {
        if v.is_finite() && (!positive || v > 0.0) {
            cur.push((t, v));
        } else if !cur.is_empty() {
            out.push(std::mem::take(&mut cur));
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

/// One panel: `y` over time on the vertical axis `y_axis` (linear or log).
fn line_panel<DB: DrawingBackend, Y>(
    area: &DrawingArea<DB, Shift>,
    caption: &str,
    desc: &str,
    t_max: f64,
    y_axis: Y,
    lines: &[Vec<(f64, f64)>],
) -> Result<(), SimError>
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..t_max, y_axis)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc(desc)
        .draw()
        .map_err(plot_err)?;
    for l in lines {
        chart
            .draw_series(LineSeries::new(
                l.iter().copied(),
                VEHICLE_COLOR.stroke_width(2),
            ))
            .map_err(plot_err)?;
    }
    Ok(())
}

/// `root` filled white and cut into an upper and a lower panel of half its height.
#[allow(clippy::type_complexity)]
fn white_halves<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
) -> Result<(DrawingArea<DB, Shift>, DrawingArea<DB, Shift>), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let (_, h) = root.dim_in_pixel();
    Ok(root.split_vertically(h / 2))
}

fn t_max(stats: &RunStats) -> f64 {
    stats.time_s.last().copied().unwrap_or(0.0).max(1e-3)
}

/// Exposure (log) and the controller's metric over time.
fn exposure_metric<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    stats: &RunStats,
    info: &RunPlotInfo,
) -> Result<(), SimError> {
    let (upper, lower) = white_halves(root)?;
    let t = t_max(stats);
    let exposure = segments(&stats.time_s, &stats.exposure_us, true);
    let (lo, hi) = exposure
        .iter()
        .flatten()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    let (lo, hi) = if lo.is_finite() && hi > 0.0 {
        (lo, hi)
    } else {
        (1.0, 10.0)
    };
    let caption = format!("{}: exposure commanded [us]", info.title);
    if hi / lo >= 3.0 {
        line_panel(
            &upper,
            &caption,
            "time [s]; exposure [us] (log) on the vertical axis",
            t,
            (lo * 0.8..hi * 1.25).log_scale(),
            &exposure,
        )?;
    } else {
        // Less than a decade: a log axis would show no tick.
        line_panel(
            &upper,
            &caption,
            "time [s]; exposure [us] on the vertical axis",
            t,
            lo * 0.9..hi * 1.1,
            &exposure,
        )?;
    }
    let metric = segments(&stats.time_s, &stats.metric, false);
    let (mlo, mhi) = padded_range(metric.iter().flatten().map(|p| p.1), 0.08, 1e-6);
    line_panel(
        &lower,
        "exposure controller's metric on each frame (gaps: none computed)",
        "time [s]; metric on the vertical axis",
        t,
        mlo..mhi,
        &metric,
    )?;
    Ok(())
}

/// Marker detected (1) or not (0) on each frame, and the loop latency, over time.
fn detection_latency<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    stats: &RunStats,
    info: &RunPlotInfo,
) -> Result<(), SimError> {
    let (upper, lower) = white_halves(root)?;
    let n = stats.detected.len().max(1);
    let rate = stats.detected.iter().filter(|d| **d).count() as f64 / n as f64;
    let detected: Vec<f64> = stats
        .detected
        .iter()
        .map(|d| if *d { 1.0 } else { 0.0 })
        .collect();
    let t = t_max(stats);
    line_panel(
        &upper,
        &format!(
            "{}: marker detected ({:.1} % of frames)",
            info.title,
            100.0 * rate
        ),
        "time [s]; detected (1) or not (0) on the vertical axis",
        t,
        -0.1..1.1,
        &segments(&stats.time_s, &detected, false),
    )?;
    let latency_ms: Vec<f64> = stats.latency_s.iter().map(|s| s * 1e3).collect();
    let hi = latency_ms
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    line_panel(
        &lower,
        "loop latency: frame available to command on the wire [ms]",
        "time [s]; latency [ms] on the vertical axis",
        t,
        0.0..(hi * 1.1).max(0.1),
        &segments(&stats.time_s, &latency_ms, false),
    )?;
    Ok(())
}
