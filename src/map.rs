//! `markhold map`: a site's `[[marker.map]]` section from a recording or a recorded-frames
//! folder in which several markers are seen together (markhold-vision's
//! [`MapBuilder`]: chained single-marker poses, then a bundle adjustment).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use markhold_exposure::{Camera, CameraError, Frame};
use markhold_vision::mapping::{MapBuilder, MapEstimate, MapSettings};
use markhold_vision::{MarkerTracker, RecordedCamera};

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
}

/// The command: read the frames, solve, write the section.
pub fn cli(args: MapArgs) -> anyhow::Result<()> {
    let site = crate::params::load(&args.site)?;
    let (source, est, builder) = build(&site, &args)?;
    let text = section(&site, &source, &builder, &est);
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
            let read = crate::record::images::for_each_image(path, args.every, |frame| {
                builder
                    .detect(&mut tracker, frame)
                    .with_context(|| format!("{}: image {}", path.display(), frame.meta.seq))?;
                Ok(())
            })?;
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
    let est = builder
        .solve(origin, &MapSettings::default())
        .with_context(|| format!("{source}: mapping the markers of {}", site.path.display()))?;
    Ok((source, est, builder))
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
    }
    s
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
