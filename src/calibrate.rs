//! `markhold calibrate`: the camera's intrinsics and lens model from views of a printed
//! target (ChArUco board, checkerboard, AprilTag grid, or a site's coplanar markers),
//! read from a folder of images, a recording, or a live camera; the calibration file
//! the sites read, a coverage picture, and the printable target
//! (`markhold_vision::calibration` does the work; this is the command line).

use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::{bail, ensure, Context as _};
use markhold_camera::RecordedCamera;
use markhold_exposure::{Camera, CameraError, Frame};
use markhold_vision::calibration::board::{read_image, BoardDetector, GridMarker, Target};
use markhold_vision::calibration::{self, coverage, Calibration, CalibrationSettings, View};
use markhold_vision::{CalibrationNotes, CameraCalibration, DistortionModel, MarkerFamily};
use nalgebra::{Point3, Vector2};

/// Columns x rows, as `5x7`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grid {
    pub cols: u32,
    pub rows: u32,
}

impl FromStr for Grid {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("'{s}': expected COLSxROWS, e.g. 5x7");
        let (a, b) = s.split_once(['x', 'X']).ok_or_else(bad)?;
        let cols = a.trim().parse::<u32>().map_err(|_| bad())?;
        let rows = b.trim().parse::<u32>().map_err(|_| bad())?;
        if cols == 0 || rows == 0 || cols > 100 || rows > 100 {
            return Err(format!("'{s}': expected 1..100 columns and rows"));
        }
        Ok(Grid { cols, rows })
    }
}

/// The kinds of target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TargetKind {
    /// A ChArUco board (--squares, --square-mm, --marker-mm, --family).
    Charuco,
    /// A checkerboard (--inner, --square-mm).
    Checkerboard,
    /// An AprilTag grid as Kalibr's aprilgrid (--tags, --tag-mm, --spacing, --family,
    /// --first-id).
    Aprilgrid,
    /// The markers of --site ([marker] and [[marker.map]]), all on the plane z = 0 of
    /// the site frame.
    Site,
}

/// Where the calibration is made: what `[camera] calibration_source` should then say.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Medium {
    /// In the water, through the port, at the working distance.
    Water,
    /// In air (a bench calibration: wrong under water, see docs/first-dive.md).
    Air,
}

impl Medium {
    fn as_str(self) -> &'static str {
        match self {
            Medium::Water => "water",
            Medium::Air => "air",
        }
    }
}

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("source").args(["frames", "recording", "camera"])))]
pub struct CalibrateArgs {
    /// A folder of images of the target (PNG, JPEG, BMP, TIFF, in name order), or a
    /// recorded-frames folder (frames.csv, as `--camera frames:DIR` reads).
    #[arg(long, value_name = "DIR")]
    pub frames: Option<PathBuf>,
    /// A recording made with --record (its camera images).
    #[arg(long, value_name = "FILE.mcap")]
    pub recording: Option<PathBuf>,
    /// A live camera, as `run --camera` takes it (needs --site for its resolution and
    /// controls): views are kept as the target moves; Ctrl-C or --views / --seconds
    /// ends the capture.
    #[arg(long, value_name = "URL")]
    pub camera: Option<crate::field::camera::CameraUrl>,
    /// Site file: the camera for --camera, the markers for --target site, and the
    /// resolution every image must have.
    #[arg(long, value_name = "FILE")]
    pub site: Option<PathBuf>,
    /// The target printed and filmed.
    #[arg(long, value_enum)]
    pub target: TargetKind,
    /// ChArUco: squares across and down (OpenCV's -w x -h), e.g. 5x7.
    #[arg(long, value_name = "COLSxROWS")]
    pub squares: Option<Grid>,
    /// Checkerboard: inner corners across and down, e.g. 9x6.
    #[arg(long, value_name = "COLSxROWS")]
    pub inner: Option<Grid>,
    /// AprilTag grid: tags across and down, e.g. 6x6.
    #[arg(long, value_name = "COLSxROWS")]
    pub tags: Option<Grid>,
    /// ChArUco and checkerboard: side of a square as printed, millimetres.
    #[arg(long, value_name = "MM")]
    pub square_mm: Option<f64>,
    /// ChArUco: side of a marker's black square as printed, millimetres.
    #[arg(long, value_name = "MM")]
    pub marker_mm: Option<f64>,
    /// AprilTag grid: side of a tag's black square as printed, millimetres.
    #[arg(long, value_name = "MM")]
    pub tag_mm: Option<f64>,
    /// AprilTag grid: gap between tags as a fraction of the tag side (Kalibr's
    /// tagSpacing).
    #[arg(long, default_value_t = 0.3)]
    pub spacing: f64,
    /// Marker dictionary of the ChArUco board or AprilTag grid (ChArUco default
    /// aruco_6x6_250, grid default apriltag_36h11).
    #[arg(long)]
    pub family: Option<String>,
    /// AprilTag grid: id of the top-left tag (the others follow row by row).
    #[arg(long, default_value_t = 0)]
    pub first_id: u32,
    /// Where the views were taken: water (through the port, at the working distance)
    /// or air. Written into the file; the site's calibration_source should say the same.
    #[arg(long, value_enum, required_unless_present = "print_target")]
    pub medium: Option<Medium>,
    /// Lens model: plumb_bob (k1 k2 p1 p2 k3), rational (k1..k6, p1 p2; the default
    /// in water: it follows a flat port's refraction) or fisheye (equidistant k1..k4).
    /// Default: rational in water, plumb_bob in air.
    #[arg(long, value_name = "MODEL")]
    pub model: Option<DistortionModel>,
    /// One focal length for both axes (square pixels).
    #[arg(long)]
    pub fix_aspect: bool,
    /// Hold the principal point at the image centre.
    #[arg(long)]
    pub fix_principal_point: bool,
    /// Hold the tangential terms p1, p2 at zero.
    #[arg(long)]
    pub zero_tangential: bool,
    /// Use every Nth image of --frames or --recording.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub every: u64,
    /// Keep at most this many views (from a recording, a recorded-frames folder or a
    /// camera, an image is kept when the target moved by 5 % of the image diagonal or
    /// more from every view kept; a folder of pictures keeps each).
    #[arg(long, value_name = "N", default_value_t = 60)]
    pub views: usize,
    /// --camera: stop capturing after this many seconds.
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// The calibration file to write (OpenCV YAML, as the sites' calibration_file).
    #[arg(
        long,
        value_name = "FILE.yaml",
        required_unless_present = "print_target"
    )]
    pub out: Option<PathBuf>,
    /// The coverage picture (default: the --out file with .coverage.png).
    #[arg(long, value_name = "FILE.png")]
    pub coverage: Option<PathBuf>,
    /// Also write the result as JSON: the calibration, each parameter's standard
    /// deviation, each view's error, the coverage.
    #[arg(long, value_name = "FILE.json")]
    pub summary: Option<PathBuf>,
    /// Write the printable target (SVG, PDF or PNG) and stop.
    #[arg(long, value_name = "FILE")]
    pub print_target: Option<PathBuf>,
    /// --print-target PNG resolution, dots per inch.
    #[arg(long, default_value_t = crate::tag::DEFAULT_DPI)]
    pub dpi: f64,
}

/// The target the flags describe; errors name the flag.
pub fn target_of(args: &CalibrateArgs) -> anyhow::Result<Target> {
    let mm = |v: Option<f64>, flag: &str| -> anyhow::Result<f64> {
        let v = v.with_context(|| format!("--target {:?} needs {flag}", args.target))?;
        ensure!(
            v.is_finite() && v > 0.0 && v <= 10_000.0,
            "{flag} {v}: expected a size > 0 and <= 10000 millimetres"
        );
        Ok(v / 1000.0)
    };
    let family = |default: MarkerFamily| -> anyhow::Result<MarkerFamily> {
        match &args.family {
            Some(f) => f.parse().map_err(|e| anyhow::anyhow!("--family {f}: {e}")),
            None => Ok(default),
        }
    };
    let t = match args.target {
        TargetKind::Charuco => {
            let g = args
                .squares
                .context("--target charuco needs --squares COLSxROWS")?;
            Target::Charuco {
                squares_x: g.cols,
                squares_y: g.rows,
                square_m: mm(args.square_mm, "--square-mm")?,
                marker_m: mm(args.marker_mm, "--marker-mm")?,
                family: family(MarkerFamily::Aruco6x6_250)?,
            }
        }
        TargetKind::Checkerboard => {
            let g = args
                .inner
                .context("--target checkerboard needs --inner COLSxROWS")?;
            Target::Checkerboard {
                inner_x: g.cols,
                inner_y: g.rows,
                square_m: mm(args.square_mm, "--square-mm")?,
            }
        }
        TargetKind::Aprilgrid => {
            let g = args
                .tags
                .context("--target aprilgrid needs --tags COLSxROWS")?;
            ensure!(
                args.spacing.is_finite() && args.spacing > 0.0 && args.spacing <= 10.0,
                "--spacing {}: expected a gap of (0, 10] tag sides",
                args.spacing
            );
            Target::aprilgrid(
                family(MarkerFamily::AprilTag36h11)?,
                g.cols,
                g.rows,
                mm(args.tag_mm, "--tag-mm")?,
                args.spacing,
                args.first_id,
            )
        }
        TargetKind::Site => {
            let path = args
                .site
                .as_ref()
                .context("--target site needs --site FILE")?;
            site_target(&crate::params::load(path)?)?
        }
    };
    t.validate()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("the target")?;
    Ok(t)
}

/// The site's markers as a planar target: every marker on the site frame's z = 0
/// plane, facing the same way (only turned in that plane).
fn site_target(site: &crate::params::LoadedSite) -> anyhow::Result<Target> {
    let m = &site.site.marker;
    let mut markers = vec![GridMarker {
        id: m.id,
        size_m: m.size_m,
        centre_m: [0.0, 0.0],
        turn_deg: 0.0,
    }];
    for (i, e) in m.map.iter().enumerate() {
        let [r, p, y] = e.rpy_deg;
        ensure!(
            e.position_m[2].abs() < 1e-6 && r.abs() < 1e-6 && p.abs() < 1e-6,
            "{}: marker.map[{i}] (id {}) is off the origin marker's plane (position_m z = {}, \
             rpy_deg {:?}): --target site needs every marker on the plane z = 0, facing the \
             same way",
            site.path.display(),
            e.id,
            e.position_m[2],
            e.rpy_deg
        );
        markers.push(GridMarker {
            id: e.id,
            size_m: e.size_m,
            centre_m: [e.position_m[0], e.position_m[1]],
            turn_deg: y,
        });
    }
    Ok(Target::Markers {
        family: m.family,
        markers,
    })
}

/// A kept image: its frame (for the second pass) and what the first pass found.
struct Kept {
    name: String,
    frame: Frame,
    points: Vec<(Point3<f64>, Vector2<f64>)>,
}

/// Keeps the images whose target moved enough from every image kept.
struct Selector {
    detector: BoardDetector,
    kept: Vec<Kept>,
    max: usize,
    size: Option<(u32, u32)>,
    expected: Option<(u32, u32)>,
    seen: usize,
    with_target: usize,
    /// Keep every image with the target (a folder of chosen pictures), not only new views.
    keep_all: bool,
}

impl Selector {
    /// Detect the target in `frame`; keep it if it is a new view. Errors: a frame of
    /// another size than the first (or than the site's camera).
    fn offer(&mut self, name: String, frame: &Frame) -> anyhow::Result<bool> {
        self.seen += 1;
        let size = (frame.width, frame.height);
        if let Some(want) = self.expected.or(self.size) {
            ensure!(
                size == want,
                "{name}: {}x{} pixels, but {} {}x{}",
                size.0,
                size.1,
                if self.expected.is_some() {
                    "the site's camera is"
                } else {
                    "the first image is"
                },
                want.0,
                want.1
            );
        }
        self.size = Some(size);
        let found = self
            .detector
            .detect(frame, None)
            .with_context(|| format!("{name}: finding the target"))?;
        if found.points.len() < 8 {
            return Ok(false);
        }
        self.with_target += 1;
        if self.kept.len() >= self.max {
            return Ok(false);
        }
        let diag = (frame.width as f64).hypot(frame.height as f64);
        let distinct = self.kept.iter().all(|k| {
            // Mean movement of the corners both saw (few in common: a new view).
            let (mut sum, mut n) = (0.0, 0usize);
            for (x, p) in &found.points {
                if let Some((_, q)) = k.points.iter().find(|(y, _)| (y - x).norm() < 1e-9) {
                    sum += (p - q).norm();
                    n += 1;
                }
            }
            n < found.points.len() / 2 || sum / n as f64 > 0.05 * diag
        }) || self.keep_all;
        if distinct {
            self.kept.push(Kept {
                name,
                frame: frame.clone(),
                points: found.points,
            });
        }
        Ok(distinct)
    }
}

/// The command.
pub fn cli(args: CalibrateArgs) -> anyhow::Result<()> {
    let target = target_of(&args)?;
    if let Some(path) = &args.print_target {
        return crate::tag::write_board(&target, path, args.dpi);
    }
    let (Some(medium), Some(out)) = (args.medium, args.out.clone()) else {
        bail!("give --medium and --out (or --print-target FILE to print the target)");
    };
    let site = match &args.site {
        Some(p) => Some(crate::params::load(p)?),
        None => None,
    };
    let model = args.model.unwrap_or(match medium {
        Medium::Water => DistortionModel::Rational,
        Medium::Air => DistortionModel::PlumbBob,
    });
    let mut sel = Selector {
        detector: BoardDetector::new(&target).map_err(|e| anyhow::anyhow!("{e}"))?,
        kept: Vec::new(),
        max: args.views.max(3),
        size: None,
        expected: site
            .as_ref()
            .map(|s| (s.calibration.width, s.calibration.height)),
        seen: 0,
        with_target: 0,
        keep_all: false,
    };
    let source = read_source(&args, site.as_ref(), &mut sel)?;
    crate::outln!(
        "markhold calibrate: {} images of {source}, the target ({}) found in {}, {} distinct \
         views kept",
        sel.seen,
        target.describe(),
        sel.with_target,
        sel.kept.len()
    );
    let (width, height) = sel
        .size
        .with_context(|| format!("{source}: no image read"))?;
    let settings = CalibrationSettings {
        model,
        fix_aspect: args.fix_aspect,
        fix_principal_point: args.fix_principal_point,
        zero_tangential: args.zero_tangential,
        ..CalibrationSettings::default()
    };
    let views = |k: &[Kept], pts: Vec<Vec<(Point3<f64>, Vector2<f64>)>>| -> Vec<View> {
        k.iter()
            .zip(pts)
            .map(|(k, p)| View::new(k.name.clone(), p))
            .collect()
    };
    let first: Vec<_> = sel.kept.iter().map(|k| k.points.clone()).collect();
    let mut cal = calibration::calibrate(views(&sel.kept, first), width, height, &settings)
        .with_context(|| format!("{source}: calibrating"))?;
    // Second pass: the corners found again with the lens in hand (ChArUco corners placed
    // through the board's pose, marker edges fitted straight in undistorted coordinates).
    if !matches!(target, Target::Checkerboard { .. }) {
        let mut again = Vec::with_capacity(sel.kept.len());
        for k in &sel.kept {
            let found = sel
                .detector
                .detect(&k.frame, Some(&cal.calib))
                .with_context(|| format!("{}: finding the target again", k.name))?;
            again.push(found.points);
        }
        cal = calibration::calibrate(views(&sel.kept, again), width, height, &settings)
            .with_context(|| format!("{source}: calibrating (second pass)"))?;
    }
    report(&cal, medium);
    write_outputs(&args, &out, &cal, medium, &source, &target, &sel)?;
    if let Some(path) = &args.summary {
        crate::write_summary(path, &summary_of(&cal, medium))?;
    }
    Ok(())
}

/// `--summary`.
#[derive(serde::Serialize)]
struct Summary {
    medium: &'static str,
    calibration: CameraCalibration,
    rms_px: f64,
    views_used: usize,
    points_used: usize,
    /// (name, value, one standard deviation).
    parameters: Vec<(String, f64, f64)>,
    views: Vec<ViewSummary>,
    coverage_cells: f64,
    coverage_radius: f64,
    working_distance_m: [f64; 2],
}

#[derive(serde::Serialize)]
struct ViewSummary {
    name: String,
    points: usize,
    points_used: usize,
    rms_px: f64,
    tilt_deg: f64,
    distance_m: f64,
    rejected: Option<String>,
}

fn summary_of(cal: &Calibration, medium: Medium) -> Summary {
    Summary {
        medium: medium.as_str(),
        calibration: cal.calib.clone(),
        rms_px: cal.rms_px,
        views_used: cal.views_used,
        points_used: cal.points_used,
        parameters: cal.parameters.clone(),
        views: cal
            .views
            .iter()
            .map(|v| ViewSummary {
                name: v.name.clone(),
                points: v.points,
                points_used: v.points_used,
                rms_px: v.rms_px,
                tilt_deg: v.tilt_deg,
                distance_m: v.distance_m,
                rejected: v.rejected.clone(),
            })
            .collect(),
        coverage_cells: cal.coverage.cells_fraction,
        coverage_radius: cal.coverage.radius_fraction,
        working_distance_m: cal.working_distance_m,
    }
}

/// Feed every image of the source to the selector; returns the source's name.
fn read_source(
    args: &CalibrateArgs,
    site: Option<&crate::params::LoadedSite>,
    sel: &mut Selector,
) -> anyhow::Result<String> {
    if let Some(dir) = &args.frames {
        read_folder(dir, args.every, sel)?;
        return Ok(dir.display().to_string());
    }
    if let Some(path) = &args.recording {
        let read =
            crate::record::images::for_each_image::<anyhow::Error>(path, args.every, |frame| {
                sel.offer(
                    format!("{} image {}", path.display(), frame.meta.seq),
                    frame,
                )?;
                Ok(())
            })?;
        if let Some(why) = &read.ended_early {
            tracing::warn!("{}: the file ends early ({why})", path.display());
        }
        return Ok(path.display().to_string());
    }
    if let Some(url) = &args.camera {
        let site = site.context("--camera needs --site (the camera's resolution and controls)")?;
        live(site, url, args, sel)?;
        return Ok(url.to_string());
    }
    bail!("give --frames DIR, --recording FILE.mcap or --camera URL");
}

/// A recorded-frames folder (frames.csv), else every image file in name order.
fn read_folder(dir: &Path, every: u64, sel: &mut Selector) -> anyhow::Result<()> {
    if dir.join(markhold_camera::SIDECAR).is_file() {
        let mut cam = RecordedCamera::open(dir)?;
        let mut frame = Frame::new(0, 0);
        let mut i = 0u64;
        loop {
            match cam.grab(&mut frame) {
                Ok(()) => {}
                Err(CameraError::EndOfStream { .. }) => break,
                Err(e) => return Err(e).with_context(|| dir.display().to_string()),
            }
            if i.is_multiple_of(every) {
                sel.offer(
                    format!("{} frame {}", dir.display(), frame.meta.seq),
                    &frame,
                )?;
            }
            i += 1;
        }
        return Ok(());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("--frames {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .map(str::to_ascii_lowercase)
                .is_some_and(|e| {
                    ["png", "jpg", "jpeg", "bmp", "tif", "tiff", "pgm", "ppm"].contains(&e.as_str())
                })
        })
        .collect();
    files.sort();
    ensure!(
        !files.is_empty(),
        "--frames {}: no images (PNG, JPEG, BMP, TIFF) and no frames.csv",
        dir.display()
    );
    // Pictures chosen one by one: each is a view.
    sel.keep_all = true;
    for (i, f) in files.iter().enumerate() {
        if (i as u64).is_multiple_of(every) {
            let frame = read_image(f).map_err(|e| anyhow::anyhow!("{e}"))?;
            let name = f.file_name().map_or(f.display().to_string(), |n| {
                n.to_string_lossy().into_owned()
            });
            sel.offer(name, &frame)?;
        }
    }
    Ok(())
}

/// Capture from a live camera until --views, --seconds or Ctrl-C.
fn live(
    site: &crate::params::LoadedSite,
    url: &crate::field::camera::CameraUrl,
    args: &CalibrateArgs,
    sel: &mut Selector,
) -> anyhow::Result<()> {
    let stop = crate::field::signal::install()?;
    let mut cam = crate::field::camera::open_camera(
        site,
        url,
        site.site.camera.initial_exposure_us,
        &stop,
        false,
    )?;
    let start = std::time::Instant::now();
    let mut frame = Frame::new(site.calibration.width, site.calibration.height);
    eprintln!(
        "markhold calibrate: move the target through the image: near, far, tilted 20 to 45 \
         degrees, into the corners; Ctrl-C ends the capture"
    );
    while !stop.is_set() && sel.kept.len() < sel.max {
        if args
            .seconds
            .is_some_and(|s| start.elapsed().as_secs_f64() >= s)
        {
            break;
        }
        match cam.grab(&mut frame) {
            Ok(()) => {}
            Err(CameraError::EndOfStream { .. }) => break,
            Err(_) if cam.take_no_frame() => continue,
            Err(e) => return Err(e).with_context(|| url.to_string()),
        }
        let name = format!("frame {}", frame.meta.seq);
        if sel.offer(name.clone(), &frame)? {
            eprintln!("  view {} kept ({name})", sel.kept.len());
        }
    }
    Ok(())
}

/// The report on stdout.
fn report(cal: &Calibration, medium: Medium) {
    let c = &cal.calib;
    crate::outln!(
        "views: {} used of {}; corners: {}; reprojection RMS {:.3} px; {} iterations",
        cal.views_used,
        cal.views.len(),
        cal.points_used,
        cal.rms_px,
        cal.iterations
    );
    crate::outln!(
        "  view                               corners  used   RMS px  tilt deg  distance m"
    );
    for v in &cal.views {
        crate::outln!(
            "  {:<34} {:>7} {:>5} {:>8.3} {:>9.1} {:>11.3}{}",
            trim(&v.name, 34),
            v.points,
            v.points_used,
            v.rms_px,
            v.tilt_deg,
            v.distance_m,
            v.rejected
                .as_ref()
                .map_or(String::new(), |r| format!("  left out: {r}"))
        );
    }
    crate::outln!(
        "model {} ({}), {}x{}:",
        c.model,
        match medium {
            Medium::Water => "in water",
            Medium::Air => "in air",
        },
        c.width,
        c.height
    );
    for (name, value, sigma) in &cal.parameters {
        crate::outln!("  {name:<3} = {value:>14.6} +- {sigma:.6}");
    }
    let cov = &cal.coverage;
    crate::outln!(
        "coverage: corners in {:.0} % of the {}x{} cells, reaching {:.0} % of the way to the \
         image corners; target {:.2} to {:.2} m away",
        100.0 * cov.cells_fraction,
        coverage::CELLS_X,
        coverage::CELLS_Y,
        100.0 * cov.radius_fraction,
        cal.working_distance_m[0],
        cal.working_distance_m[1]
    );
    if cov.cells_fraction < 0.75 || cov.radius_fraction < 0.8 {
        crate::outln!(
            "  warning: the lens is only measured where corners fell; beyond them the model is \
             extrapolated: add views with the target in the empty cells (see the picture)"
        );
    }
    if medium == Medium::Water {
        crate::outln!(
            "  valid near {:.2} to {:.2} m: behind a flat port the calibration holds near the \
             distances it was made at (docs/design/calibration.md)",
            cal.working_distance_m[0],
            cal.working_distance_m[1]
        );
    }
}

fn trim(s: &str, n: usize) -> String {
    let count = s.chars().count();
    if count <= n {
        s.to_string()
    } else {
        format!("...{}", s.chars().skip(count - (n - 3)).collect::<String>())
    }
}

/// The calibration file, the coverage picture and the site lines.
fn write_outputs(
    args: &CalibrateArgs,
    out: &Path,
    cal: &Calibration,
    medium: Medium,
    source: &str,
    target: &Target,
    sel: &Selector,
) -> anyhow::Result<()> {
    let notes = CalibrationNotes {
        medium: Some(medium.as_str().into()),
        working_distance_m: Some(cal.working_distance_m),
        reprojection_rms_px: Some(cal.rms_px),
    };
    let comments = vec![
        format!(
            "markhold calibrate: {} of {} views of {source} ({}), {} corners, reprojection RMS \
             {:.4} px",
            cal.views_used,
            cal.views.len(),
            target.describe(),
            cal.points_used,
            cal.rms_px
        ),
        format!(
            "parameters +- 1 sigma: {}",
            cal.parameters
                .iter()
                .map(|(n, v, s)| format!("{n} {v:.6} +- {s:.6}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    ];
    let text = cal.calib.to_yaml(&notes, &comments);
    // Checked before it is written: the file reads back as the calibration.
    let back = CameraCalibration::parse(&text, out).map_err(|e| anyhow::anyhow!("{e}"))?;
    ensure!(
        back == cal.calib,
        "{}: the written file does not read back",
        out.display()
    );
    std::fs::write(out, &text).with_context(|| format!("writing --out {}", out.display()))?;
    let png_path = args
        .coverage
        .clone()
        .unwrap_or_else(|| out.with_extension("coverage.png"));
    let views: Vec<(bool, Vec<Vector2<f64>>)> = cal
        .views
        .iter()
        .map(|v| {
            let pts = sel
                .kept
                .iter()
                .find(|k| k.name == v.name)
                .map_or(Vec::new(), |k| k.points.iter().map(|p| p.1).collect());
            (v.rejected.is_none(), pts)
        })
        .collect();
    let caption = format!(
        "{} views, {} corners, RMS {:.3} px, cells {:.0} %, reach {:.0} %",
        cal.views_used,
        cal.points_used,
        cal.rms_px,
        100.0 * cal.coverage.cells_fraction,
        100.0 * cal.coverage.radius_fraction
    );
    let png =
        coverage::picture(&cal.coverage, &views, &caption).map_err(|e| anyhow::anyhow!("{e}"))?;
    std::fs::write(&png_path, png)
        .with_context(|| format!("writing the coverage picture {}", png_path.display()))?;
    crate::outln!("wrote {} and {}", out.display(), png_path.display());
    crate::outln!(
        "in the site file's [camera]:\n  calibration_file = \"{}\"\n  calibration_source = \"{}\"",
        out.display(),
        match medium {
            Medium::Water => "in-water",
            Medium::Air => "in-air",
        }
    );
    Ok(())
}

/// What `params check` and `run` say about where the site's intrinsics come from:
/// nothing for a camera calibrated in the water near the station's distance; otherwise
/// one line per problem. `real_camera`: the intrinsics serve a real camera (`run`), so
/// the simulator's count as placeholders.
pub fn site_warnings(site: &crate::params::LoadedSite, real_camera: bool) -> Vec<String> {
    use markhold_vision::CalibrationSource as S;
    let cam = &site.site.camera;
    let mut out = Vec::new();
    let calibrate = "calibrate in the water, through the port, at the working distance \
                     (`markhold calibrate --medium water`, docs/first-dive.md)";
    match cam.calibration_source {
        None => out.push(format!(
            "camera.calibration_source is not set: nothing says these intrinsics are this \
             camera's; {calibrate}, then set calibration_source = \"in-water\""
        )),
        Some(S::Placeholder) => out.push(format!(
            "the camera intrinsics are placeholders (camera.calibration_source = \
             \"placeholder\"): distances and the marker map will be off by percents and \
             flat walls will come out bent; {calibrate}"
        )),
        Some(S::InAir) => out.push(format!(
            "the camera was calibrated in air (camera.calibration_source = \"in-air\"): under \
             water a flat port makes the focal length about 1.33 times longer and adds \
             pincushion distortion, so distances come out about 25 % short; {calibrate}"
        )),
        Some(S::Simulated) if real_camera => out.push(format!(
            "the camera intrinsics are the simulator's (camera.calibration_source = \
             \"simulated\"), not this camera's; {calibrate}"
        )),
        Some(S::Simulated | S::InWater) => {}
    }
    if let Some(file) = &cam.calibration_file {
        if let Ok(notes) = CameraCalibration::load_notes(file) {
            let said = cam.calibration_source;
            match (notes.medium.as_deref(), said) {
                (Some("air"), Some(S::InWater)) => out.push(format!(
                    "{} says it was made in air, but camera.calibration_source says in-water",
                    file.display()
                )),
                (Some("water"), Some(S::InAir)) => out.push(format!(
                    "{} says it was made in water, but camera.calibration_source says in-air",
                    file.display()
                )),
                _ => {}
            }
            let d = site.site.station.distance_m;
            if let Some([near, far]) = notes.working_distance_m {
                if notes.medium.as_deref() == Some("water") && (d < 0.8 * near || d > 1.25 * far) {
                    out.push(format!(
                        "the station is {d:.2} m from the marker, but {} was made with the \
                         target {near:.2} to {far:.2} m away: behind a flat port a calibration \
                         holds near its distances; calibrate again at the station's distance",
                        file.display()
                    ));
                }
            }
        }
    }
    out
}
