//! `markhold map`: a site's `[[marker.map]]` section from a recording or a recorded-frames
//! folder in which several markers are seen together (markhold-vision's
//! [`MapBuilder`]: chained single-marker poses, then a bundle adjustment).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use markhold_camera::RecordedCamera;
use markhold_exposure::{Camera, CameraError, Frame};
use markhold_vision::mapping::{IntrinsicsMode, MapBuilder, MapEstimate, MapSettings};
use markhold_vision::{CalibrationNotes, CameraCalibration, MarkerTracker};

use crate::params::LoadedSite;

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["recording", "frames"])))]
pub struct MapArgs {
    /// Dive-site file: the camera calibration, the marker dictionary, the detector
    /// settings and the markers to map ([marker] and the ids and sizes of
    /// [[marker.map]]; their poses there are not used).
    #[arg(long)]
    pub site: PathBuf,
    /// A recording made with --record (its camera images).
    #[arg(long, value_name = "FILE.mcap")]
    pub recording: Option<PathBuf>,
    /// A recorded-frames folder (PNG files and frames.csv, as `--camera frames:DIR` reads).
    #[arg(long, value_name = "DIR")]
    pub frames: Option<PathBuf>,
    /// The marker whose frame becomes the site frame (default: the site's [marker] id).
    #[arg(long, value_name = "ID")]
    pub origin: Option<u32>,
    /// Use every Nth frame (1: all).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub every: u64,
    /// Write the map section to this file (default: stdout).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// The camera's intrinsics: `auto` refines the focal length (and the principal
    /// point and first radial terms, as far as the frames fix them) with the markers as
    /// the calibration target when the frames see them from enough viewpoints, and says
    /// why not otherwise; `fixed` holds them as the site gives them.
    #[arg(long, value_enum, default_value = "auto")]
    pub intrinsics: Intrinsics,
    /// How well each marker's printed size is known, percent (one standard deviation;
    /// measured with calipers: about 0.05): it moves the marker along the lines of
    /// sight, which no residual shows; the 1-sigma counts it.
    #[arg(long, value_name = "PERCENT", default_value_t = 0.05)]
    pub size_sigma_percent: f64,
    /// The same error common to every marker (one printer's scale), percent: it scales
    /// the map.
    #[arg(long, value_name = "PERCENT", default_value_t = 0.05)]
    pub scale_sigma_percent: f64,
    /// With refined intrinsics: write them as a calibration file (OpenCV YAML).
    #[arg(long, value_name = "FILE.yaml")]
    pub calibration_out: Option<PathBuf>,
    /// Also write the map as JSON: each marker's pose and its 6x6 covariance, the
    /// intrinsics, the planes.
    #[arg(long, value_name = "FILE.json")]
    pub summary: Option<PathBuf>,
}

/// `--summary`: one marker.
#[derive(serde::Serialize)]
struct MarkerSummary {
    id: u32,
    size_m: f64,
    position_m: [f64; 3],
    rpy_deg: [f64; 3],
    frames: usize,
    rms_px: f64,
    sigma_position_m: f64,
    sigma_angle_deg: f64,
    /// Rows of the covariance of (tx, ty, tz, rx, ry, rz), site frame.
    covariance: Vec<[f64; 6]>,
}

/// `--summary`.
#[derive(serde::Serialize)]
struct Summary {
    source: String,
    frames_read: usize,
    frames_used: usize,
    rms_px: f64,
    variance_factor: f64,
    viewpoints: usize,
    intrinsics_reason: String,
    /// (name, given, refined, sigma) of each refined intrinsic.
    intrinsics_refined: Vec<(String, f64, f64, f64)>,
    calibration: CameraCalibration,
    plane_factor: f64,
    planes: Vec<PlaneSummary>,
    markers: Vec<MarkerSummary>,
}

#[derive(serde::Serialize)]
struct PlaneSummary {
    name: String,
    ids: Vec<u32>,
    rms_m: f64,
    max_m: f64,
    max_tilt_deg: f64,
    max_sigmas: f64,
}

fn summary(source: &str, builder: &MapBuilder, est: &MapEstimate) -> Summary {
    Summary {
        source: source.to_string(),
        frames_read: builder.frames_read(),
        frames_used: est.frames_used,
        rms_px: est.rms_px,
        variance_factor: est.variance_factor,
        viewpoints: est.viewpoints,
        intrinsics_reason: est.intrinsics.reason.clone(),
        intrinsics_refined: est.intrinsics.refined.clone(),
        calibration: est.intrinsics.calibration.clone(),
        plane_factor: est.plane_factor,
        planes: est
            .planes
            .iter()
            .map(|p| PlaneSummary {
                name: p.name.clone(),
                ids: p.ids.clone(),
                rms_m: p.rms_m,
                max_m: p.max_m,
                max_tilt_deg: p.max_tilt_deg,
                max_sigmas: p.max_sigmas,
            })
            .collect(),
        markers: est
            .markers
            .iter()
            .map(|m| {
                let t = m.t_site_marker.translation.vector;
                let (r, p, y) = m.t_site_marker.rotation.euler_angles();
                MarkerSummary {
                    id: m.id,
                    size_m: m.size_m,
                    position_m: [t.x, t.y, t.z],
                    rpy_deg: [r.to_degrees(), p.to_degrees(), y.to_degrees()],
                    frames: m.frames,
                    rms_px: m.rms_px,
                    sigma_position_m: m.sigma_position_m,
                    sigma_angle_deg: m.sigma_angle_deg,
                    covariance: (0..6)
                        .map(|i| std::array::from_fn(|j| m.covariance[(i, j)]))
                        .collect(),
                }
            })
            .collect(),
    }
}

/// `--intrinsics`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Intrinsics {
    Auto,
    Fixed,
}

/// The command: read the frames, solve, write the section.
pub fn cli(args: MapArgs) -> anyhow::Result<()> {
    let site = crate::params::load(&args.site)?;
    let (source, est, builder) = build(&site, &args)?;
    let text = section(&site, &source, &builder, &est);
    if let Some(path) = &args.calibration_out {
        write_calibration(&site, &est, &source, path)?;
    }
    if let Some(path) = &args.summary {
        crate::write_summary(path, &summary(&source, &builder, &est))?;
    }
    match &args.out {
        Some(path) => {
            std::fs::write(path, &text)
                .with_context(|| format!("writing --out {}", path.display()))?;
            crate::outln!(
                "markhold map: {} markers from {} frames of {} ({} with two or more markers), \
                 reprojection RMS {:.3} px: {}",
                est.markers.len(),
                builder.frames_read(),
                source,
                est.frames_used,
                est.rms_px,
                path.display()
            );
        }
        None => crate::outln!("{}", text.trim_end()),
    }
    Ok(())
}

/// The map of the markers of `site` from the frames `args` names; errors name the file.
pub fn build(
    site: &LoadedSite,
    args: &MapArgs,
) -> anyhow::Result<(String, MapEstimate, MapBuilder)> {
    let marker = &site.site.marker;
    let origin = args.origin.unwrap_or(marker.id);
    // Checked before the frames are read (the estimator checks it again).
    if !marker.markers().any(|m| m.id == origin) {
        let ids: Vec<String> = marker.markers().map(|m| m.id.to_string()).collect();
        anyhow::bail!(
            "--origin {origin}: not a marker of {} (its markers: {})",
            site.path.display(),
            ids.join(", ")
        );
    }
    let mut tracker = MarkerTracker::new(marker, &site.site.vision, site.calibration.clone())
        .with_context(|| format!("{}: the marker detector", site.path.display()))?;
    let mut builder = MapBuilder::new(marker, site.calibration.clone());
    let source = match (&args.recording, &args.frames) {
        (Some(path), _) => {
            let read = crate::record::images::for_each_image::<anyhow::Error>(
                path,
                args.every,
                |frame| {
                    builder
                        .detect(&mut tracker, frame)
                        .with_context(|| format!("{}: image {}", path.display(), frame.meta.seq))?;
                    Ok(())
                },
            )?;
            if let Some(why) = &read.ended_early {
                tracing::warn!(
                    "{}: the file ends early ({why}): mapped from its {} complete images",
                    path.display(),
                    read.images
                );
            }
            if read.lossy > 0 {
                tracing::info!(
                    "{}: {} of the images are JPEG (lossy): corners a little less precise",
                    path.display(),
                    read.lossy
                );
            }
            path.display().to_string()
        }
        (None, Some(dir)) => {
            read_frames(dir, args.every, &mut builder, &mut tracker)?;
            dir.display().to_string()
        }
        (None, None) => anyhow::bail!("give --recording FILE.mcap or --frames DIR"),
    };
    for (flag, v) in [
        ("--size-sigma-percent", args.size_sigma_percent),
        ("--scale-sigma-percent", args.scale_sigma_percent),
    ] {
        anyhow::ensure!(
            v.is_finite() && (0.0..=10.0).contains(&v),
            "{flag} {v}: expected a percentage in 0..=10"
        );
    }
    let settings = MapSettings {
        size_sigma: args.size_sigma_percent / 100.0,
        scale_sigma: args.scale_sigma_percent / 100.0,
        intrinsics: match args.intrinsics {
            Intrinsics::Auto => IntrinsicsMode::Auto,
            Intrinsics::Fixed => IntrinsicsMode::Fixed,
        },
        ..MapSettings::default()
    };
    let est = builder
        .solve(origin, &settings)
        .with_context(|| format!("{source}: mapping the markers of {}", site.path.display()))?;
    Ok((source, est, builder))
}

/// The refined intrinsics as a calibration file; an error when they were held.
fn write_calibration(
    site: &LoadedSite,
    est: &MapEstimate,
    source: &str,
    path: &Path,
) -> anyhow::Result<()> {
    let i = &est.intrinsics;
    anyhow::ensure!(
        !i.refined.is_empty(),
        "--calibration-out {}: the intrinsics were not refined: {}",
        path.display(),
        i.reason
    );
    // Where the frames were taken is where the site's calibration was made, if it says.
    let medium = site
        .site
        .camera
        .calibration_file
        .as_ref()
        .and_then(|f| CameraCalibration::load_notes(f).ok())
        .and_then(|n| n.medium);
    let notes = CalibrationNotes {
        medium,
        working_distance_m: None,
        reprojection_rms_px: Some(est.rms_px),
    };
    let comments = vec![format!(
        "markhold map: intrinsics of {} refined on the markers of {} seen in {}: {}",
        site.path.display(),
        site.path.display(),
        source,
        i.refined
            .iter()
            .map(|(n, a, b, s)| format!("{n} {a:.4} -> {b:.4} +- {s:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    )];
    std::fs::write(path, i.calibration.to_yaml(&notes, &comments))
        .with_context(|| format!("writing --calibration-out {}", path.display()))
}

/// Every `every`th frame of a recorded-frames folder through the detector.
fn read_frames(
    dir: &Path,
    every: u64,
    builder: &mut MapBuilder,
    tracker: &mut MarkerTracker,
) -> anyhow::Result<()> {
    let mut camera = RecordedCamera::open(dir)?;
    let mut frame = Frame::new(0, 0);
    let mut index = 0u64;
    loop {
        match camera.grab(&mut frame) {
            Ok(()) => {}
            Err(CameraError::EndOfStream { .. }) => break,
            Err(e) => return Err(e).with_context(|| format!("{}", dir.display())),
        }
        if index.is_multiple_of(every) {
            builder.detect(tracker, &frame).with_context(|| {
                format!(
                    "{}: frame {} (seq {})",
                    dir.display(),
                    index,
                    frame.meta.seq
                )
            })?;
        }
        index += 1;
    }
    Ok(())
}

/// The `[[marker.map]]` section, with the figures of each marker as comments.
pub fn section(site: &LoadedSite, source: &str, builder: &MapBuilder, est: &MapEstimate) -> String {
    let marker = &site.site.marker;
    let mut s = String::new();
    let origin = &est.markers[0];
    let _ = writeln!(
        s,
        "# markhold map: {} markers of {} from {source}: {} frames read, {} with two or more \
         markers together",
        est.markers.len(),
        marker.family,
        builder.frames_read(),
        est.frames_used
    );
    let _ = writeln!(
        s,
        "# bundle adjustment: reprojection RMS {:.3} px over every corner ({:.3} px at the \
         chained start), {} iterations, {} observations, {} left out as outliers",
        est.rms_px, est.initial_rms_px, est.iterations, est.observations, est.outliers
    );
    let i = &est.intrinsics;
    let _ = writeln!(s, "# intrinsics: {}", i.reason);
    for (name, given, refined, sigma) in &i.refined {
        let _ = writeln!(s, "#   {name}: {given:.4} -> {refined:.4} +- {sigma:.4}");
    }
    let _ = writeln!(
        s,
        "# uncertainty: {} viewpoints; the residuals are {:.1}x what the corners' noise \
         explains{}",
        est.viewpoints,
        est.variance_factor.sqrt(),
        if est.variance_factor > 1.5 {
            " (model error: the 1-sigma below counts it, as a displacement over the image \
             common to every frame)"
        } else {
            ""
        }
    );
    write_planes(&mut s, est);
    if origin.id == marker.id {
        let _ = writeln!(
            s,
            "# site frame: marker {}'s ([marker] id = {}, size_m = {}); seen in {} frames, \
             reprojection RMS {:.3} px",
            origin.id, origin.id, origin.size_m, origin.frames, origin.rms_px
        );
    } else {
        let _ = writeln!(
            s,
            "# site frame: marker {}'s: set [marker] id = {}, size_m = {} (marker {} of {} \
             is in the map below); seen in {} frames, reprojection RMS {:.3} px",
            origin.id,
            origin.id,
            origin.size_m,
            marker.id,
            site.path.display(),
            origin.frames,
            origin.rms_px
        );
    }
    for m in &est.markers[1..] {
        let p = m.t_site_marker.translation.vector;
        let (r, pi, y) = m.t_site_marker.rotation.euler_angles();
        let _ = writeln!(
            s,
            "\n[[marker.map]]\n# seen in {} frames ({} left out), reprojection RMS {:.3} px, \
             1-sigma {:.2} mm, {:.3} deg",
            m.frames,
            m.outliers,
            m.rms_px,
            m.sigma_position_m * 1e3,
            m.sigma_angle_deg
        );
        let _ = writeln!(s, "id = {}\nsize_m = {}", m.id, m.size_m);
        let _ = writeln!(
            s,
            "position_m = [{}, {}, {}]",
            fixed(p.x, 4),
            fixed(p.y, 4),
            fixed(p.z, 4)
        );
        let _ = writeln!(
            s,
            "rpy_deg = [{}, {}, {}]",
            fixed(r.to_degrees(), 3),
            fixed(pi.to_degrees(), 3),
            fixed(y.to_degrees(), 3)
        );
        let plane = marker
            .map
            .iter()
            .find(|e| e.id == m.id)
            .and_then(|e| e.plane.as_ref());
        if let Some(p) = plane {
            let _ = writeln!(s, "plane = \"{p}\"");
        }
    }
    s
}

/// The plane groups' flatness, and the covariance's scale they led to.
fn write_planes(s: &mut String, est: &MapEstimate) {
    for p in &est.planes {
        let ids: Vec<String> = p.ids.iter().map(u32::to_string).collect();
        let _ = writeln!(
            *s,
            "# plane \"{}\" (markers {}): corners off a common plane by {:.1} mm RMS, {:.1} \
             mm at most (marker {}); faces tilted up to {:.2} deg (marker {}); centres off it \
             by up to {:.1} sigma{}",
            p.name,
            ids.join(", "),
            p.rms_m * 1e3,
            p.max_m * 1e3,
            p.worst_id,
            p.max_tilt_deg,
            p.tilt_id,
            p.max_sigmas,
            if p.max_sigmas > 3.0 {
                ": NOT flat as declared: the camera model is wrong (calibrate in the water) \
                 or the markers are not on one plane"
            } else {
                ""
            }
        );
    }
    if est.plane_factor > 1.0 {
        let _ = writeln!(
            *s,
            "# the planes deviate {:.1}x more than the covariance said: the 1-sigma below is \
             scaled up by that",
            est.plane_factor.sqrt()
        );
    }
}

/// `v` with `decimals` decimals and no negative zero.
fn fixed(v: f64, decimals: usize) -> String {
    let t = format!("{v:.decimals$}");
    if t.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        t.trim_start_matches('-').to_string()
    } else {
        t
    }
}
