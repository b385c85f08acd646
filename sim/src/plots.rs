//! Plots of `markhold compare` (and the backend and helpers `hil --plots` shares), drawn
//! once with plotters and written twice: SVG through plotters' own SVG backend, PNG
//! through a small plotters backend on an OpenCV image
//! (OpenCV is already linked for the detector; plotters' bitmap backend would pull in a
//! font stack and an image codec we do not otherwise need).

use std::path::Path;

use crate::error::{SimError, StepContext};
use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use opencv::core::{Mat, Point, Rect, Scalar, Vec3b, Vector, CV_8UC3};
use opencv::imgproc;
use opencv::prelude::*;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_backend::{
    text_anchor::{HPos, VPos},
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
};

use super::compare::{CompareOutput, RunKind, RunSeries};

const SIZE: (u32, u32) = (900, 640);

/// Colours of the methods in every plot, by their place in [`ExposureMethod::ALL`]
/// (matplotlib's tab10 colours; a method added there gets one of its own).
const PALETTE: [RGBColor; 10] = [
    RGBColor(255, 127, 14),
    RGBColor(214, 39, 40),
    RGBColor(23, 190, 207),
    RGBColor(31, 119, 180),
    RGBColor(188, 189, 34),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

/// Colour of a method in every plot.
pub fn method_color(m: ExposureMethod) -> RGBColor {
    let i = ExposureMethod::ALL
        .iter()
        .position(|&a| a == m)
        .unwrap_or(0);
    PALETTE[i % PALETTE.len()]
}

/// A plotters backend drawing into an 8-bit BGR OpenCV image, saved as PNG on `present`.
pub struct MatBackend {
    img: Mat,
    path: std::path::PathBuf,
}

#[derive(Debug, thiserror::Error)]
pub enum MatBackendError {
    #[error("opencv: {source}")]
    OpenCv {
        #[from]
        source: opencv::Error,
    },
    #[error("the PNG encoder refused {path}")]
    Encode { path: String },
}

type DErr = DrawingErrorKind<MatBackendError>;

fn cv(e: opencv::Error) -> DErr {
    DrawingErrorKind::DrawingError(MatBackendError::OpenCv { source: e })
}

/// OpenCV's thickness for a shape drawn with `style`: filled, or its stroke width.
fn thickness<S: BackendStyle>(style: &S, fill: bool) -> i32 {
    if fill {
        imgproc::FILLED
    } else {
        style.stroke_width().max(1) as i32
    }
}

/// OpenCV draws opaque: a translucent colour (plotters' light grid) is blended with the
/// white background instead.
fn bgr(c: BackendColor) -> Scalar {
    let a = c.alpha.clamp(0.0, 1.0);
    let ch = |v: u8| f64::from(v) * a + 255.0 * (1.0 - a);
    let (r, g, b) = c.rgb;
    Scalar::new(ch(b), ch(g), ch(r), 0.0)
}

impl MatBackend {
    pub fn new(path: &Path, size: (u32, u32)) -> Result<Self, SimError> {
        let img = Mat::new_rows_cols_with_default(
            size.1 as i32,
            size.0 as i32,
            CV_8UC3,
            Scalar::all(255.0),
        )
        .step(|| "allocating the plot image".to_string())?;
        Ok(Self {
            img,
            path: path.to_path_buf(),
        })
    }

    /// Hershey font scale giving text about `px` pixels tall.
    fn scale(px: f64) -> f64 {
        (px / 30.0).max(0.3)
    }
}

impl DrawingBackend for MatBackend {
    type ErrorType = MatBackendError;

    fn get_size(&self) -> (u32, u32) {
        (self.img.cols() as u32, self.img.rows() as u32)
    }

    fn ensure_prepared(&mut self) -> Result<(), DErr> {
        Ok(())
    }

    fn present(&mut self) -> Result<(), DErr> {
        let ok = opencv::imgcodecs::imwrite(&self.path, &self.img, &Vector::new()).map_err(cv)?;
        if ok {
            Ok(())
        } else {
            Err(DrawingErrorKind::DrawingError(MatBackendError::Encode {
                path: self.path.display().to_string(),
            }))
        }
    }

    fn draw_pixel(&mut self, p: BackendCoord, c: BackendColor) -> Result<(), DErr> {
        let (w, h) = self.get_size();
        if p.0 < 0 || p.1 < 0 || p.0 >= w as i32 || p.1 >= h as i32 || c.alpha <= 0.0 {
            return Ok(());
        }
        let px = self.img.at_2d_mut::<Vec3b>(p.1, p.0).map_err(cv)?;
        let a = c.alpha.clamp(0.0, 1.0);
        let src = [c.rgb.2, c.rgb.1, c.rgb.0];
        for (d, s) in px.0.iter_mut().zip(src) {
            *d = (f64::from(*d) * (1.0 - a) + f64::from(s) * a).round() as u8;
        }
        Ok(())
    }

    fn draw_line<S: BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> Result<(), DErr> {
        imgproc::line(
            &mut self.img,
            Point::new(from.0, from.1),
            Point::new(to.0, to.1),
            bgr(style.color()),
            style.stroke_width().max(1) as i32,
            imgproc::LINE_AA,
            0,
        )
        .map_err(cv)
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        ul: BackendCoord,
        br: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DErr> {
        let thickness = thickness(style, fill);
        imgproc::rectangle(
            &mut self.img,
            Rect::new(ul.0, ul.1, br.0 - ul.0, br.1 - ul.1),
            bgr(style.color()),
            thickness,
            imgproc::LINE_8,
            0,
        )
        .map_err(cv)
    }

    fn draw_circle<S: BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DErr> {
        let thickness = thickness(style, fill);
        imgproc::circle(
            &mut self.img,
            Point::new(center.0, center.1),
            radius as i32,
            bgr(style.color()),
            thickness,
            imgproc::LINE_AA,
            0,
        )
        .map_err(cv)
    }

    fn estimate_text_size<T: BackendTextStyle>(
        &self,
        text: &str,
        style: &T,
    ) -> Result<(u32, u32), DErr> {
        let mut base = 0;
        let s = imgproc::get_text_size(
            text,
            imgproc::FONT_HERSHEY_SIMPLEX,
            Self::scale(style.size()),
            1,
            &mut base,
        )
        .map_err(cv)?;
        Ok((s.width.max(0) as u32, (s.height + base).max(0) as u32))
    }

    /// Horizontal text only (the plots put no rotated labels).
    fn draw_text<T: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &T,
        pos: BackendCoord,
    ) -> Result<(), DErr> {
        let (w, h) = self.estimate_text_size(text, style)?;
        let (w, h) = (w as i32, h as i32);
        let dx = match style.anchor().h_pos {
            HPos::Left => 0,
            HPos::Center => -w / 2,
            HPos::Right => -w,
        };
        // put_text anchors at the baseline-left; plotters anchors at the top by default.
        let dy = match style.anchor().v_pos {
            VPos::Top => h,
            VPos::Center => h / 2,
            VPos::Bottom => 0,
        };
        imgproc::put_text(
            &mut self.img,
            text,
            Point::new(pos.0 + dx, pos.1 + dy),
            imgproc::FONT_HERSHEY_SIMPLEX,
            Self::scale(style.size()),
            bgr(style.color()),
            1,
            imgproc::LINE_AA,
            false,
        )
        .map_err(cv)
    }
}

pub(crate) fn plot_err<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> SimError {
    SimError::Run {
        reason: format!("drawing a plot: {e}"),
    }
}

/// Draw with `$draw` (a function generic over the backend, called with the drawing area)
/// into `<dir>/<stem>.svg` and `<dir>/<stem>.png` (`$size` pixels, default `SIZE`);
/// evaluates to both names.
macro_rules! both {
    ($dir:expr, $stem:expr, $draw:ident($($arg:expr),*)) => {
        both!($dir, $stem, SIZE, $draw($($arg),*))
    };
    ($dir:expr, $stem:expr, $size:expr, $draw:ident($($arg:expr),*)) => {{
        let svg = format!("{}.svg", $stem);
        let png = format!("{}.png", $stem);
        {
            let path = $dir.join(&svg);
            let root = plotters::prelude::SVGBackend::new(&path, $size).into_drawing_area();
            $draw(&root, $($arg),*)?;
            root.present().map_err($crate::plots::plot_err)?;
        }
        {
            let root = $crate::plots::MatBackend::new(&$dir.join(&png), $size)?
                .into_drawing_area();
            $draw(&root, $($arg),*)?;
            root.present().map_err($crate::plots::plot_err)?;
        }
        vec![png, svg]
    }};
}
pub(crate) use both;

/// Range of `v` from its 1st to 99th percentile, padded, never empty (a few wild
/// detections must not squash the cloud into a dot).
fn robust_range(v: &mut Vec<f64>) -> (f64, f64) {
    v.retain(|x| x.is_finite());
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return (-1.0, 1.0);
    }
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.01), at(0.99));
    let pad = ((hi - lo) * 0.1).max(1e-4);
    (lo - pad, hi + pad)
}

/// The first seed's run of each method for a lighting and kind.
fn runs_of(out: &CompareOutput, l: LightingScenario, kind: RunKind) -> Vec<&RunSeries> {
    let seed = out.results.seeds.first().copied().unwrap_or(1);
    out.results
        .methods
        .iter()
        .filter_map(|m| {
            out.series
                .iter()
                .find(|s| s.method == *m && s.lighting == l && s.seed == seed && s.kind == kind)
        })
        .collect()
}

/// A chart over all of `root` (the caption at 22 pt, the axes' labels room to the left
/// and below), its mesh drawn with `x_desc` under the x axis.
#[allow(clippy::type_complexity)]
fn chart_on<'a, DB: DrawingBackend, X: AsRangedCoord, Y: AsRangedCoord>(
    root: &'a DrawingArea<DB, Shift>,
    caption: String,
    x_desc: &str,
    x: X,
    y: Y,
) -> Result<ChartContext<'a, DB, Cartesian2d<X::CoordDescType, Y::CoordDescType>>, SimError>
where
    X::CoordDescType: Ranged<ValueType = X::Value> + ValueFormatter<X::Value>,
    Y::CoordDescType: Ranged<ValueType = Y::Value> + ValueFormatter<Y::Value>,
{
    let mut chart = ChartBuilder::on(root)
        .caption(caption, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(x, y)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .draw()
        .map_err(plot_err)?;
    Ok(chart)
}

/// A method's points as small dots of its colour (`alpha` opaque), in the legend with
/// its label and `detections`.
fn draw_dots<'a, DB: DrawingBackend + 'a>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    m: ExposureMethod,
    points: impl IntoIterator<Item = (f64, f64)>,
    alpha: f64,
    detections: usize,
) -> Result<(), SimError> {
    let c = method_color(m);
    chart
        .draw_series(
            points
                .into_iter()
                .map(|q| Circle::new(q, 2, c.mix(alpha).filled())),
        )
        .map_err(plot_err)?
        .label(format!("{} ({detections} detections)", m.label()))
        .legend(move |(x, y)| Circle::new((x, y), 4, c.filled()));
    Ok(())
}

/// The series' labels in a box over the chart.
fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
) -> Result<(), SimError> {
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(plot_err)
}

/// Measured marker positions, static run: x (right) and y (down) of the camera frame,
/// millimetres from the true position.
fn static_scatter<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    runs: &[&RunSeries],
    l: LightingScenario,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let pts: Vec<(ExposureMethod, Vec<(f64, f64)>)> = runs
        .iter()
        .map(|r| {
            let p = r
                .samples
                .iter()
                .filter_map(|s| {
                    s.measured_m
                        .map(|m| ((m[0] - s.truth_m[0]) * 1e3, (m[1] - s.truth_m[1]) * 1e3))
                })
                .collect();
            (r.method, p)
        })
        .collect();
    let mut xs: Vec<f64> = pts
        .iter()
        .flat_map(|(_, p)| p.iter().map(|q| q.0))
        .collect();
    let mut ys: Vec<f64> = pts
        .iter()
        .flat_map(|(_, p)| p.iter().map(|q| q.1))
        .collect();
    let xr = robust_range(&mut xs);
    let yr = robust_range(&mut ys);
    let mut chart = chart_on(
        root,
        format!("Static: measured marker position - truth [mm], {l} lighting"),
        "x (camera right) [mm]; y (camera down) [mm] on the vertical axis",
        xr.0..xr.1,
        yr.0..yr.1,
    )?;
    for (m, p) in &pts {
        let in_view = p
            .iter()
            .copied()
            .filter(|q| q.0 >= xr.0 && q.0 <= xr.1 && q.1 >= yr.0 && q.1 <= yr.1);
        draw_dots(&mut chart, *m, in_view, 0.6, p.len())?;
    }
    draw_legend(&mut chart)
}

/// Motion run: measured marker positions against the true trajectory, x (camera right)
/// against z (range), metres.
fn motion_tracks<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    runs: &[&RunSeries],
    l: LightingScenario,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let Some(first) = runs.first() else {
        return Ok(());
    };
    let truth: Vec<(f64, f64)> = first
        .samples
        .iter()
        .map(|s| (s.truth_m[0], s.truth_m[2]))
        .collect();
    let mut xs: Vec<f64> = truth.iter().map(|p| p.0).collect();
    let mut zs: Vec<f64> = truth.iter().map(|p| p.1).collect();
    let xr = robust_range(&mut xs);
    let zmid = zs.iter().sum::<f64>() / zs.len().max(1) as f64;
    // Show +-5 cm of range around the truth: the tracking error is what matters.
    zs.clear();
    let zr = (zmid - 0.05, zmid + 0.05);
    let mut chart = chart_on(
        root,
        format!("Motion: tracked marker vs truth, {l} lighting"),
        "x (camera right) [m]; range z [m] on the vertical axis",
        xr.0..xr.1,
        zr.0..zr.1,
    )?;
    chart
        .draw_series(LineSeries::new(truth, Color::stroke_width(&BLACK, 2)))
        .map_err(plot_err)?
        .label("truth")
        .legend(|(x, y)| PathElement::new(vec![(x - 8, y), (x + 8, y)], BLACK));
    for r in runs {
        let p: Vec<(f64, f64)> = r
            .samples
            .iter()
            .filter_map(|s| s.measured_m.map(|m| (m[0], m[2])))
            .filter(|q| q.1 >= zr.0 && q.1 <= zr.1 && q.0 >= xr.0 && q.0 <= xr.1)
            .collect();
        let n = r.samples.iter().filter(|s| s.detected).count();
        draw_dots(&mut chart, r.method, p, 0.7, n)?;
    }
    draw_legend(&mut chart)
}

/// Exposure over time per method: the two convergence runs (from 10x long and 10x short).
fn exposure_time<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    runs: &[&RunSeries],
    l: LightingScenario,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let t_max = runs
        .iter()
        .filter_map(|r| r.samples.last().map(|s| s.time_s))
        .fold(0.0f64, f64::max)
        .max(1e-3);
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for r in runs {
        for s in &r.samples {
            if s.exposure_us > 0.0 {
                lo = lo.min(s.exposure_us);
                hi = hi.max(s.exposure_us);
            }
        }
    }
    if !(lo.is_finite() && hi > 0.0) {
        (lo, hi) = (1.0, 10.0);
    }
    let mut chart = chart_on(
        root,
        format!("Exposure [us] over time from 10x long and 10x short, {l} lighting"),
        "time [s]; exposure [us] (log) on the vertical axis",
        0.0..t_max,
        (lo * 0.8..hi * 1.25).log_scale(),
    )?;
    let mut labelled = Vec::new();
    for r in runs {
        let c = method_color(r.method);
        let series = chart
            .draw_series(LineSeries::new(
                r.samples.iter().map(|s| (s.time_s, s.exposure_us)),
                Color::stroke_width(&c, 2),
            ))
            .map_err(plot_err)?;
        if !labelled.contains(&r.method) {
            labelled.push(r.method);
            series
                .label(r.method.label())
                .legend(move |(x, y)| PathElement::new(vec![(x - 8, y), (x + 8, y)], c));
        }
    }
    draw_legend(&mut chart)
}

/// A method's column of a spread panel: the seeds' values and (low, mean, high).
type SpreadColumn = (ExposureMethod, Vec<f64>, Option<(f64, f64, f64)>);

/// The spread over seeds of four headline metrics (a panel each): every seed's value as a
/// dot, the mean as a bar with its 95 % confidence interval, a column per method.
fn spread<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    out: &CompareOutput,
    l: LightingScenario,
) -> Result<(), SimError> {
    root.fill(&WHITE).map_err(plot_err)?;
    let r = &out.results;
    let panels = root.split_evenly((2, 2));
    let defs: [(&str, &str, f64); 4] = [
        ("Static detection [%]", "static.detection_rate", 100.0),
        (
            "Motion: distance to trajectory [mm]",
            "motion.mean_distance_to_trajectory_m",
            1e3,
        ),
        (
            "Convergence from 10x long [s]",
            "convergence.long.seconds",
            1.0,
        ),
        ("Station: position RMS [mm]", "station.position_rms_m", 1e3),
    ];
    for (area, (title, key, scale)) in panels.iter().zip(defs) {
        // Per method: the seeds' values and the stat.
        let cols: Vec<SpreadColumn> = r
            .methods
            .iter()
            .map(|&m| {
                let vals = r
                    .cases
                    .iter()
                    .filter(|c| c.method == m && c.lighting == l)
                    .filter_map(|c| {
                        super::compare::metrics(c)
                            .into_iter()
                            .find(|(k, _)| *k == key)
                            .and_then(|(_, v)| v)
                    })
                    .map(|v| v * scale)
                    .collect();
                let st = r.case_stats(m, l).and_then(|s| s.metrics.get(key));
                let bar = st.and_then(|s| {
                    let mean = s.mean? * scale;
                    Some((
                        s.ci95_low.map_or(mean, |v| v * scale),
                        mean,
                        s.ci95_high.map_or(mean, |v| v * scale),
                    ))
                });
                (m, vals, bar)
            })
            .collect();
        let mut all: Vec<f64> = cols
            .iter()
            .flat_map(|(_, v, b)| v.iter().copied().chain(b.iter().flat_map(|b| [b.0, b.2])))
            .filter(|v| v.is_finite())
            .collect();
        all.push(0.0);
        let hi = all.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let lo = all.iter().copied().fold(f64::INFINITY, f64::min);
        let pad = ((hi - lo) * 0.08).max(1e-6);
        let n = cols.len().max(1) as f64;
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{title}, {l}"), ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(55)
            .build_cartesian_2d(-0.5..n - 0.5, (lo - pad)..(hi + pad))
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(cols.len().max(1))
            .x_label_formatter(&|x| {
                let i = x.round();
                if (x - i).abs() > 1e-6 || i < 0.0 {
                    return String::new();
                }
                r.methods
                    .get(i as usize)
                    .map_or(String::new(), |m| m.label().to_string())
            })
            .draw()
            .map_err(plot_err)?;
        for (i, (m, vals, bar)) in cols.iter().enumerate() {
            let c = method_color(*m);
            let x = i as f64;
            chart
                .draw_series(
                    vals.iter()
                        .map(|v| Circle::new((x + 0.15, *v), 3, c.mix(0.6).filled())),
                )
                .map_err(plot_err)?;
            if let Some((lo, mean, hi)) = *bar {
                let style = Color::stroke_width(&BLACK, 2);
                let path = |pts: Vec<(f64, f64)>| PathElement::new(pts, style);
                chart
                    .draw_series([
                        path(vec![(x - 0.1, lo), (x - 0.1, hi)]),
                        path(vec![(x - 0.18, lo), (x - 0.02, lo)]),
                        path(vec![(x - 0.18, hi), (x - 0.02, hi)]),
                    ])
                    .map_err(plot_err)?;
                chart
                    .draw_series([Circle::new((x - 0.1, mean), 5, c.filled())])
                    .map_err(plot_err)?;
            }
        }
    }
    Ok(())
}

/// Every plot of a compare run, per lighting; returns the file names (relative to `dir`).
pub fn write_plots(out: &CompareOutput, dir: &Path) -> Result<Vec<String>, SimError> {
    let mut files = Vec::new();
    for &l in &out.results.lightings {
        let st = runs_of(out, l, RunKind::Static);
        files.extend(both!(
            dir,
            format!("static_scatter_{l}"),
            static_scatter(&st, l)
        ));
        let mo = runs_of(out, l, RunKind::Motion);
        files.extend(both!(
            dir,
            format!("motion_tracks_{l}"),
            motion_tracks(&mo, l)
        ));
        let mut ex = runs_of(out, l, RunKind::ConvergenceLong);
        ex.extend(runs_of(out, l, RunKind::ConvergenceShort));
        files.extend(both!(dir, format!("exposure_{l}"), exposure_time(&ex, l)));
        files.extend(both!(
            dir,
            format!("spread_{l}"),
            (1100, 800),
            spread(out, l)
        ));
    }
    Ok(files)
}
