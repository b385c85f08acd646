//! A marker map from frames in which several markers are seen together: each marker's
//! pose in the site frame (the origin marker's frame), by chaining single-marker poses
//! through co-visible frames and then a bundle adjustment of every camera pose and every
//! marker pose on the corners' reprojection error.
//!
//! The bundle adjustment is Levenberg-Marquardt on the whitened corner residuals (the
//! same weighting as the tracker's pose: each marker's four corners with their 8x8
//! covariance). Its normal equations are solved through the Schur complement on the
//! marker poses: the camera poses of the frames are eliminated frame by frame (6x6
//! blocks), leaving a dense system of 6 per marker besides the origin (at most 186
//! unknowns), so thousands of frames cost little. The origin marker is held at the
//! identity: that fixes the gauge (the map's position and orientation); the scale comes
//! from the printed marker sizes.
//!
//! The camera's intrinsics can join the adjustment (the markers are then the
//! calibration target) when the frames fix them ([`IntrinsicsMode`]); the covariance
//! counts the error the corner noise does not explain (model error, repeated from one
//! viewpoint to the next), and markers declared on one plane are checked for it.

mod adjust;
mod planes;

use std::collections::HashMap;

use crate::calibration::solve::Param;
use crate::config::MarkerConfig;
use crate::{CameraCalibration, MarkerTracker, VisionError};
use adjust::Adjustment;
use markhold_camera::Frame;
use nalgebra::{Isometry3, Matrix6, SMatrix, Vector2};
pub use planes::PlaneReport;

/// One marker found in one frame, with its own pose (from its four corners alone).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeenMarker {
    pub id: u32,
    /// Sub-pixel corners in aruco order, pixels.
    pub img: [Vector2<f64>; 4],
    /// `C^-1` for the corners' covariance `C C^T` (order u0 v0 u1 v1 ...).
    pub white: SMatrix<f64, 8, 8>,
    /// The marker's pose in the camera frame from its corners alone.
    pub t_cam_marker: Isometry3<f64>,
}

/// Settings of [`MapBuilder::solve`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapSettings {
    /// Levenberg-Marquardt iterations at most, per pass (two passes: all observations,
    /// then without the outliers).
    pub max_iterations: usize,
    /// An observation (one marker in one frame) is an outlier when its corners' RMS
    /// reprojection error after the first pass exceeds this many times the median one...
    pub outlier_median_factor: f64,
    /// ... and this many pixels.
    pub outlier_floor_px: f64,
    /// Whether the camera's intrinsics join the adjustment.
    pub intrinsics: IntrinsicsMode,
    /// Frames within this distance (metres) and angle (degrees) of each other see the
    /// map from one viewpoint: they repeat one model error (the covariance counts each
    /// viewpoint once for it).
    pub viewpoint_m: f64,
    pub viewpoint_deg: f64,
    /// Intrinsics are refined only with this many viewpoints at least...
    pub min_viewpoints: usize,
    /// ... and when they come out this well determined (one standard deviation): the
    /// focal length as a fraction of itself, the principal point in pixels, the radial
    /// terms as the fraction of the radius they move the farthest corner by.
    pub max_focal_sigma: f64,
    pub max_centre_sigma_px: f64,
    pub max_radial_sigma: f64,
    /// One standard deviation of each marker's size as the corners see it, relative: a
    /// print off its stated size, an edge profile that makes a marker look smaller.
    /// Unseen by the residuals (a marker's pose absorbs its size), it moves the marker
    /// along the lines of sight; the covariance counts it.
    pub size_sigma: f64,
    /// The same error common to every marker (one printer's scale): it scales the map.
    pub scale_sigma: f64,
}

/// Whether [`MapBuilder::solve`] refines the camera's intrinsics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntrinsicsMode {
    /// Held as the calibration gives them.
    Fixed,
    /// Refined (focal length, principal point, first two radial terms, as many of them
    /// as the frames fix) when the frames fix at least the focal length; held otherwise,
    /// with the reason.
    Auto,
}

impl Default for MapSettings {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            outlier_median_factor: 5.0,
            outlier_floor_px: 1.0,
            intrinsics: IntrinsicsMode::Auto,
            viewpoint_m: 0.1,
            viewpoint_deg: 5.0,
            min_viewpoints: 4,
            max_focal_sigma: 0.005,
            max_centre_sigma_px: 3.0,
            max_radial_sigma: 0.002,
            size_sigma: 0.0005,
            scale_sigma: 0.0005,
        }
    }
}

/// One marker of an estimated map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MappedMarker {
    pub id: u32,
    pub size_m: f64,
    /// Pose in the site frame (the identity for the origin marker).
    pub t_site_marker: Isometry3<f64>,
    /// Frames of the adjustment (two or more markers in view) it was used in.
    pub frames: usize,
    /// Observations of it left out as outliers.
    pub outliers: usize,
    /// RMS reprojection error of its corners over those frames, pixels.
    pub rms_px: f64,
    /// One standard deviation of its position, largest axis, metres, and of its
    /// orientation, largest axis, degrees, from `covariance` (0 for the origin marker,
    /// which is fixed).
    pub sigma_position_m: f64,
    pub sigma_angle_deg: f64,
    /// Covariance of (tx, ty, tz, rx, ry, rz) of its pose in the site frame (left
    /// rotation error, site axes): the corner noise, the model error the residuals show
    /// (counted once per viewpoint), the intrinsics' uncertainty when they were refined,
    /// and the planes' evidence ([`MapEstimate::plane_factor`]).
    pub covariance: Matrix6<f64>,
}

/// What became of the camera's intrinsics.
#[derive(Debug, Clone, PartialEq)]
pub struct IntrinsicsReport {
    /// The intrinsics the map was solved with (refined or as given).
    pub calibration: CameraCalibration,
    /// Refined: each free parameter's (name, value given, value refined, one standard
    /// deviation). Empty: held.
    pub refined: Vec<(String, f64, f64, f64)>,
    /// Why they were held, or what the frames fixed.
    pub reason: String,
}

/// A marker map estimated by [`MapBuilder::solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct MapEstimate {
    pub origin: u32,
    /// Every marker, the origin first.
    pub markers: Vec<MappedMarker>,
    /// Frames of the adjustment (two or more markers in view).
    pub frames_used: usize,
    /// Observations (a marker in a frame) used, and left out as outliers.
    pub observations: usize,
    pub outliers: usize,
    /// RMS reprojection error over every corner used: from the chained start, and at the
    /// solution, pixels.
    pub initial_rms_px: f64,
    pub rms_px: f64,
    /// Levenberg-Marquardt iterations over every pass.
    pub iterations: usize,
    pub intrinsics: IntrinsicsReport,
    /// Distinct viewpoints among the frames (`MapSettings::viewpoint_m`, `viewpoint_deg`).
    pub viewpoints: usize,
    /// Whitened cost over its redundancy: 1 when the corners' covariance explains the
    /// residuals; above, the excess is counted as model error.
    pub variance_factor: f64,
    /// The coplanarity of each named plane.
    pub planes: Vec<PlaneReport>,
    /// The markers' out-of-plane deviations over the covariance's account of them
    /// (mean of the squared ratios); above 1 the covariance was scaled up by it.
    pub plane_factor: f64,
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct Obs {
    frame: usize,
    /// Index of the marker in the builder's list.
    marker: usize,
    img: [Vector2<f64>; 4],
    white: SMatrix<f64, 8, 8>,
    t_cam_marker: Isometry3<f64>,
}

/// Collects the markers seen per frame and solves for the map.
#[derive(Debug, Clone)]
pub struct MapBuilder {
    calib: CameraCalibration,
    /// (id, size) of each marker to map.
    markers: Vec<(u32, f64)>,
    /// The plane each marker is declared on.
    planes: Vec<Option<String>>,
    index_of_id: HashMap<u32, usize>,
    /// Observations of the frames kept (two or more markers), by frame.
    obs: Vec<Obs>,
    frames_read: usize,
    frames_kept: usize,
    /// Frames each marker was seen in, alone or not.
    seen: Vec<usize>,
}

impl MapBuilder {
    /// A builder for the markers of `marker` (the site's `[marker]` section: the origin
    /// marker and `[[marker.map]]`; their ids and sizes, not their poses) seen by a
    /// camera of calibration `calib`.
    pub fn new(marker: &MarkerConfig, calib: CameraCalibration) -> Self {
        let markers: Vec<(u32, f64)> = marker.markers().map(|m| (m.id, m.size_m)).collect();
        let index_of_id = markers
            .iter()
            .enumerate()
            .map(|(i, (id, _))| (*id, i))
            .collect();
        Self {
            calib,
            seen: vec![0; markers.len()],
            planes: marker.planes().map(|p| p.map(str::to_string)).collect(),
            markers,
            index_of_id,
            obs: Vec::new(),
            frames_read: 0,
            frames_kept: 0,
        }
    }

    /// Frames given so far, and those kept (two or more of the map's markers seen).
    pub fn frames_read(&self) -> usize {
        self.frames_read
    }

    pub fn frames_kept(&self) -> usize {
        self.frames_kept
    }

    /// Frames each marker (by id) was seen in, alone or with others.
    pub fn seen_counts(&self) -> impl Iterator<Item = (u32, usize)> + '_ {
        self.markers
            .iter()
            .zip(&self.seen)
            .map(|((id, _), n)| (*id, *n))
    }

    /// The markers seen in one frame (ids not in the map are ignored). Returns how many
    /// of the map's markers it showed; frames with fewer than two add nothing to the map.
    pub fn add_frame(&mut self, seen: impl IntoIterator<Item = SeenMarker>) -> usize {
        let start = self.obs.len();
        for s in seen {
            let Some(&m) = self.index_of_id.get(&s.id) else {
                continue;
            };
            if self.obs[start..].iter().any(|o| o.marker == m) {
                continue;
            }
            self.seen[m] += 1;
            self.obs.push(Obs {
                frame: self.frames_kept,
                marker: m,
                img: s.img,
                white: s.white,
                t_cam_marker: s.t_cam_marker,
            });
        }
        self.frames_read += 1;
        let n = self.obs.len() - start;
        if n >= 2 {
            self.frames_kept += 1;
        } else {
            self.obs.truncate(start);
        }
        n
    }

    /// Detect the map's markers in `frame` with `tracker` (a full-frame search, no
    /// tracking: each frame stands alone) and add them.
    pub fn detect(
        &mut self,
        tracker: &mut MarkerTracker,
        frame: &Frame,
    ) -> Result<usize, VisionError> {
        tracker.reset();
        tracker.process_full(frame)?;
        Ok(self.add_frame(tracker.seen_markers()))
    }

    /// The map with marker `origin` as the site frame.
    pub fn solve(&self, origin: u32, settings: &MapSettings) -> Result<MapEstimate, VisionError> {
        let Some(&o) = self.index_of_id.get(&origin) else {
            let ids: Vec<String> = self.markers.iter().map(|(id, _)| id.to_string()).collect();
            return Err(VisionError::MapOrigin {
                origin,
                ids: ids.join(", "),
            });
        };
        if self.frames_kept == 0 {
            return Err(VisionError::MapNoFrames {
                frames: self.frames_read,
            });
        }
        let t_site = self.chain(o)?;
        let mut ba = Adjustment::new(self, o, t_site, self.calib.clone(), Vec::new());
        let initial_rms_px = ba.rms_px();
        let mut iterations = ba.run(settings.max_iterations);
        let outliers = ba.reject(settings);
        if outliers > 0 {
            iterations += ba.run(settings.max_iterations);
        }
        let viewpoints = ba.viewpoints(settings).len();
        let (ba, report, more) = self.intrinsics(ba, settings, viewpoints);
        Ok(ba.estimate(
            origin,
            initial_rms_px,
            iterations + more,
            outliers,
            report,
            settings,
        ))
    }

    /// The intrinsics in the adjustment when the frames fix them (the largest set of
    /// focal length, principal point, k1, k2 whose standard deviations are within the
    /// settings'), else `ba` as it is, with the reason.
    fn intrinsics<'a>(
        &'a self,
        ba: Adjustment<'a>,
        settings: &MapSettings,
        viewpoints: usize,
    ) -> (Adjustment<'a>, IntrinsicsReport, usize) {
        let held = |reason: String| IntrinsicsReport {
            calibration: self.calib.clone(),
            refined: Vec::new(),
            reason,
        };
        if settings.intrinsics == IntrinsicsMode::Fixed {
            return (ba, held("held as given (--intrinsics fixed)".into()), 0);
        }
        if viewpoints < settings.min_viewpoints {
            let reason = format!(
                "held as given: the frames see the map from {viewpoints} viewpoint{} (at \
                 least {} are needed, {:.2} m or {:.0} degrees apart): survey from several \
                 distances and angles to refine them",
                if viewpoints == 1 { "" } else { "s" },
                settings.min_viewpoints,
                settings.viewpoint_m,
                settings.viewpoint_deg
            );
            return (ba, held(reason), 0);
        }
        let c = &self.calib;
        let focal = Param::Focal { ratio: c.fy / c.fx };
        let sets: [Vec<Param>; 3] = [
            vec![focal, Param::Cx, Param::Cy, Param::Dist(0), Param::Dist(1)],
            vec![focal, Param::Dist(0)],
            vec![focal],
        ];
        let mut iterations = 0;
        let mut last_reason = String::new();
        for set in sets {
            if set
                .iter()
                .any(|p| matches!(p, Param::Dist(i) if *i >= c.dist.len()))
            {
                continue;
            }
            let mut trial = ba.with_intrinsics(set.clone());
            iterations += trial.run(settings.max_iterations);
            let Some(sig) = trial.intrinsic_sigmas(settings) else {
                last_reason = "the adjustment with them free is singular".into();
                continue;
            };
            let r = trial.max_normalised_radius();
            let mut bad = Vec::new();
            for (p, s) in set.iter().zip(&sig) {
                let v = crate::calibration::solve::value(*p, trial.calibration());
                let (ok, what) = match p {
                    Param::Focal { .. } => (
                        *s <= settings.max_focal_sigma * v,
                        format!("f +- {:.2} %", 100.0 * s / v),
                    ),
                    Param::Cx | Param::Cy => (
                        *s <= settings.max_centre_sigma_px,
                        format!("{} +- {s:.1} px", p.name(c.model)),
                    ),
                    Param::Dist(i) => {
                        let reach = s * r.powi(2 * (*i as i32 + 1));
                        (
                            reach <= settings.max_radial_sigma,
                            format!(
                                "{} moves the farthest corner +- {:.2} %",
                                p.name(c.model),
                                100.0 * reach
                            ),
                        )
                    }
                    _ => (true, String::new()),
                };
                if !ok {
                    bad.push(what);
                }
            }
            if bad.is_empty() {
                let refined: Vec<(String, f64, f64, f64)> = set
                    .iter()
                    .zip(&sig)
                    .map(|(p, s)| {
                        (
                            p.name(c.model),
                            crate::calibration::solve::value(*p, c),
                            crate::calibration::solve::value(*p, trial.calibration()),
                            *s,
                        )
                    })
                    .collect();
                let report = IntrinsicsReport {
                    calibration: trial.calibration().clone(),
                    reason: format!(
                        "refined ({} free) from {viewpoints} viewpoints",
                        refined
                            .iter()
                            .map(|r| r.0.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                    refined,
                };
                return (trial, report, iterations);
            }
            last_reason = bad.join(", ");
        }
        let reason = format!(
            "held as given: the frames do not fix them ({last_reason}; needed: f within {:.1} \
             %): survey from more distances and angles, nearer the image corners",
            100.0 * settings.max_focal_sigma
        );
        (ba, held(reason), iterations)
    }

    /// Start poses of the markers: from the origin, each next marker is the one seen in
    /// the most frames together with a marker already placed, placed through the medoid
    /// of those frames' relative poses (robust to a single-marker pose that took the
    /// wrong one of its two IPPE solutions). Errors list the markers not reached.
    fn chain(&self, origin: usize) -> Result<Vec<Option<Isometry3<f64>>>, VisionError> {
        let n = self.markers.len();
        // Relative poses t_a_b per ordered pair, over the frames that show both.
        let mut rel: HashMap<(usize, usize), Vec<Isometry3<f64>>> = HashMap::new();
        for frame in self.frames() {
            for a in frame {
                for b in frame {
                    if a.marker != b.marker {
                        rel.entry((a.marker, b.marker))
                            .or_default()
                            .push(a.t_cam_marker.inverse() * b.t_cam_marker);
                    }
                }
            }
        }
        let mut placed: Vec<Option<Isometry3<f64>>> = vec![None; n];
        placed[origin] = Some(Isometry3::identity());
        loop {
            let mut best: Option<(usize, usize, usize)> = None;
            for (&(a, b), v) in &rel {
                if placed[a].is_some() && placed[b].is_none() && best.is_none_or(|x| v.len() > x.2)
                {
                    best = Some((a, b, v.len()));
                }
            }
            let Some((a, b, _)) = best else {
                break;
            };
            let (Some(t_site_a), Some(v)) = (placed[a], rel.get(&(a, b))) else {
                break;
            };
            placed[b] = Some(t_site_a * medoid(v));
        }
        let missing: Vec<usize> = (0..n).filter(|m| placed[*m].is_none()).collect();
        if missing.is_empty() {
            return Ok(placed);
        }
        let describe = |m: usize| {
            let (id, _) = self.markers[m];
            match self.seen[m] {
                0 => format!("{id} (never seen)"),
                k => format!(
                    "{id} (seen in {k} frames, never together with a marker linked to the origin)"
                ),
            }
        };
        Err(VisionError::MapDisconnected {
            origin: self.markers[origin].0,
            ids: missing
                .iter()
                .map(|m| self.markers[*m].0.to_string())
                .collect::<Vec<_>>()
                .join(", "),
            detail: missing
                .iter()
                .map(|m| describe(*m))
                .collect::<Vec<_>>()
                .join("; "),
        })
    }

    /// The observations of each kept frame.
    fn frames(&self) -> impl Iterator<Item = &[Obs]> {
        self.obs.chunk_by(|a, b| a.frame == b.frame)
    }
}

/// The pose among `v` with the least summed distance to the others (translation in
/// metres plus rotation angle in radians times 0.1 m), over at most 101 evenly spaced
/// samples.
fn medoid(v: &[Isometry3<f64>]) -> Isometry3<f64> {
    let step = v.len().div_ceil(101).max(1);
    let s: Vec<&Isometry3<f64>> = v.iter().step_by(step).collect();
    let dist = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
        (a.translation.vector - b.translation.vector).norm()
            + 0.1 * a.rotation.angle_to(&b.rotation)
    };
    let mut best = (f64::MAX, *s[0]);
    for a in &s {
        let d: f64 = s.iter().map(|b| dist(a, b)).sum();
        if d < best.0 {
            best = (d, **a);
        }
    }
    best.1
}

/// `R = exp([dtheta]x) R`, `t = t + dt`: the perturbation of every pose here (as in
/// the pose refinement).
fn apply(pose: &Isometry3<f64>, delta: &[f64]) -> Isometry3<f64> {
    markhold_geometry::perturb(pose, &nalgebra::Vector6::from_column_slice(&delta[..6]))
}

#[cfg(test)]
mod tests;
