//! Camera calibration from views of a planar target with known geometry (a ChArUco
//! board, a checkerboard, an AprilTag grid): the intrinsics and lens model that
//! minimise the corners' reprojection error, with per-view errors, rejection of bad
//! views and corners, the refusal of view sets that cannot fix the focal length, the
//! coverage of the image, and the parameters' standard deviations.
//!
//! - [`board`]: the targets, their corners found in an image.
//! - [`init`]: starting values from homographies (Zhang 2000).
//! - [`solve`]: Levenberg-Marquardt over the intrinsics and every view's pose.
//! - [`coverage`]: where the corners fell, as numbers and as a picture.

pub mod board;
pub mod coverage;
pub mod init;
pub mod solve;

use nalgebra::{Isometry3, Matrix3, Point3, Vector2, Vector3};

use crate::distortion::DistortionModel;
use crate::{CameraCalibration, VisionError};
use coverage::Coverage;
use solve::Param;

/// One image's target corners: each corner's position on the target (metres, the
/// target's plane is z = 0) and where it was found in the image (pixels).
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// The image's name (file name, or frame number), for reports.
    pub name: String,
    pub points: Vec<(Point3<f64>, Vector2<f64>)>,
    /// Points in use (false: left out as outliers).
    pub(crate) used: Vec<bool>,
}

impl View {
    pub fn new(name: impl Into<String>, points: Vec<(Point3<f64>, Vector2<f64>)>) -> Self {
        let used = vec![true; points.len()];
        Self {
            name: name.into(),
            points,
            used,
        }
    }

    fn used_count(&self) -> usize {
        self.used.iter().filter(|u| **u).count()
    }
}

/// How to calibrate.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationSettings {
    pub model: DistortionModel,
    /// One focal length for both axes (square pixels).
    pub fix_aspect: bool,
    /// Principal point held at the image centre.
    pub fix_principal_point: bool,
    /// Tangential terms (p1, p2) held at zero (plumb_bob and rational).
    pub zero_tangential: bool,
    /// Views with fewer corners than this are not used.
    pub min_points_per_view: usize,
    /// Fewer usable views than this: refused.
    pub min_views: usize,
    /// The most tilted view must be tilted more than this from face-on, degrees: views
    /// that all face the camera cannot tell the focal length from the distance.
    pub min_tilt_deg: f64,
    /// One standard deviation of the focal length above this fraction of it: refused.
    pub max_focal_sigma: f64,
    /// A view whose median corner error exceeds this many times the median view's, and
    /// `reject_view_floor_px`, is left out (blur, a bent target, a wrong decode).
    pub reject_view_factor: f64,
    pub reject_view_floor_px: f64,
    /// A corner whose error exceeds this many times the median corner's, and
    /// `reject_point_floor_px`, is left out.
    pub reject_point_factor: f64,
    pub reject_point_floor_px: f64,
    pub max_iterations: usize,
}

impl Default for CalibrationSettings {
    fn default() -> Self {
        Self {
            model: DistortionModel::PlumbBob,
            fix_aspect: false,
            fix_principal_point: false,
            zero_tangential: false,
            min_points_per_view: 8,
            min_views: 3,
            min_tilt_deg: 10.0,
            max_focal_sigma: 0.05,
            reject_view_factor: 3.0,
            reject_view_floor_px: 0.5,
            reject_point_factor: 5.0,
            reject_point_floor_px: 1.0,
            max_iterations: 200,
        }
    }
}

/// What became of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewReport {
    pub name: String,
    /// Corners found, and used in the final solution.
    pub points: usize,
    pub points_used: usize,
    /// RMS reprojection error of its corners used, pixels (NaN: not solved).
    pub rms_px: f64,
    /// Why the view was left out (`None`: used).
    pub rejected: Option<String>,
    /// Angle between the target's normal and the optical axis, degrees.
    pub tilt_deg: f64,
    /// Distance of the target's centre from the camera, metres.
    pub distance_m: f64,
}

/// A calibration and how it was reached.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub calib: CameraCalibration,
    /// RMS reprojection error over every corner used, pixels.
    pub rms_px: f64,
    pub views: Vec<ViewReport>,
    /// One standard deviation of each free parameter (name, value, sigma).
    pub parameters: Vec<(String, f64, f64)>,
    pub coverage: Coverage,
    /// The nearest and farthest target distance of the views used, metres.
    pub working_distance_m: [f64; 2],
    pub iterations: usize,
    /// Views used and corners used.
    pub views_used: usize,
    pub points_used: usize,
}

fn refuse(reason: impl Into<String>) -> VisionError {
    VisionError::CalibrationRefused {
        reason: reason.into(),
    }
}

/// The free parameters for `settings` at the start values `c`.
fn free_params(settings: &CalibrationSettings, c: &CameraCalibration, lens: bool) -> Vec<Param> {
    let mut p = if settings.fix_aspect {
        vec![Param::Focal { ratio: c.fy / c.fx }]
    } else {
        vec![Param::Fx, Param::Fy]
    };
    if !settings.fix_principal_point {
        p.extend([Param::Cx, Param::Cy]);
    }
    if lens {
        for i in 0..settings.model.full_len() {
            let tangential = settings.model != DistortionModel::Equidistant && (i == 2 || i == 3);
            if tangential && settings.zero_tangential {
                continue;
            }
            p.push(Param::Dist(i));
        }
    }
    p
}

/// Tilt from face-on (degrees) and distance (metres) of a target pose.
fn tilt_and_distance(pose: &Isometry3<f64>, view: &View) -> (f64, f64) {
    let n = pose.rotation * Vector3::z();
    let tilt = n.z.abs().min(1.0).acos().to_degrees();
    let centre = view
        .points
        .iter()
        .fold(Vector3::zeros(), |a, (x, _)| a + x.coords)
        / view.points.len().max(1) as f64;
    let d = (pose * Point3::from(centre)).coords.norm();
    (tilt, d)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

/// Calibrate a camera of `width` x `height` from `views`. Refuses (with the reason) a
/// set of views that cannot fix the intrinsics: too few views, every view face-on, a
/// focal length left uncertain.
#[allow(clippy::too_many_lines)] // The stages in order: start, solve, reject, report.
pub fn calibrate(
    mut views: Vec<View>,
    width: u32,
    height: u32,
    settings: &CalibrationSettings,
) -> Result<Calibration, VisionError> {
    let mut reports: Vec<ViewReport> = views
        .iter()
        .map(|v| ViewReport {
            name: v.name.clone(),
            points: v.points.len(),
            points_used: 0,
            rms_px: f64::NAN,
            rejected: None,
            tilt_deg: f64::NAN,
            distance_m: f64::NAN,
        })
        .collect();
    // Views of too few corners, and those without a homography, are not used.
    let mut homographies = Vec::new();
    let mut index = Vec::new();
    for (i, v) in views.iter().enumerate() {
        if v.points.len() < settings.min_points_per_view {
            reports[i].rejected = Some(format!(
                "{} corners, fewer than {}",
                v.points.len(),
                settings.min_points_per_view
            ));
            continue;
        }
        if v.points.iter().any(|(x, _)| x.z.abs() > 1e-9) {
            return Err(refuse(format!(
                "view {}: the target is not planar (a corner off z = 0)",
                v.name
            )));
        }
        match init::homography(v) {
            Some(h) => {
                homographies.push(h);
                index.push(i);
            }
            None => {
                reports[i].rejected = Some("its corners give no homography (collinear?)".into());
            }
        }
    }
    let n_views = index.len();
    if n_views < settings.min_views {
        return Err(refuse(format!(
            "{n_views} usable view{} of {} images: a calibration needs at least {} views of \
             the target, tilted differently (one view cannot tell the focal length from the \
             target's distance)",
            if n_views == 1 { "" } else { "s" },
            views.len(),
            settings.min_views
        )));
    }
    let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
    let face_on = |tilts: &[f64]| {
        format!(
            "every view shows the target within {:.1} degrees of face-on (tilts {}): such \
             views cannot tell the focal length from the distance; tilt the target 20 to 45 \
             degrees about different axes in some views",
            tilts.iter().copied().fold(0.0, f64::max),
            tilts
                .iter()
                .map(|t| format!("{t:.1}"))
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    // A rough focal length for the tilts of the message when the equations fail.
    let rough_tilts = |f: f64| -> Vec<f64> {
        let k = Matrix3::new(f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0);
        homographies
            .iter()
            .zip(&index)
            .filter_map(|(h, i)| {
                init::pose_from_homography(h, &k).map(|p| tilt_and_distance(&p, &views[*i]).0)
            })
            .collect()
    };
    let Some((f0, _)) = init::focal_lengths(&homographies, cx, cy, true) else {
        return Err(refuse(face_on(&rough_tilts(width.max(height) as f64))));
    };
    let mut calib = CameraCalibration {
        width,
        height,
        fx: f0,
        fy: f0,
        cx,
        cy,
        dist: vec![0.0; settings.model.full_len()],
        model: settings.model,
    };
    let k = Matrix3::new(f0, 0.0, cx, 0.0, f0, cy, 0.0, 0.0, 1.0);
    let mut used_views: Vec<View> = Vec::with_capacity(n_views);
    let mut poses = Vec::with_capacity(n_views);
    for (h, &i) in homographies.iter().zip(&index) {
        let Some(p0) = init::pose_from_homography(h, &k) else {
            return Err(refuse(format!(
                "view {}: no pose from its homography",
                views[i].name
            )));
        };
        // Each pose refined alone under the start intrinsics.
        let one = std::slice::from_ref(&views[i]);
        let p = solve::solve(calib.clone(), vec![p0], one, &[], 50).map_or(p0, |s| s.poses[0]);
        poses.push(p);
        used_views.push(std::mem::replace(&mut views[i], View::new("", Vec::new())));
    }
    let tilts: Vec<f64> = poses
        .iter()
        .zip(&used_views)
        .map(|(p, v)| tilt_and_distance(p, v).0)
        .collect();
    if tilts.iter().all(|t| *t < settings.min_tilt_deg) {
        return Err(refuse(face_on(&tilts)));
    }
    // Pinhole first, then the lens.
    let pinhole = free_params(settings, &calib, false);
    if let Some(s) = solve::solve(calib.clone(), poses.clone(), &used_views, &pinhole, 50) {
        calib = s.calib;
        poses = s.poses;
    }
    let mut params = free_params(settings, &calib, true);
    let mut sol = solve::solve(calib, poses, &used_views, &params, settings.max_iterations)
        .ok_or_else(|| refuse("the least squares failed (a target behind the camera)"))?;
    let mut out_view = vec![None::<String>; used_views.len()];
    for _round in 0..3 {
        let mut changed = false;
        // Views whose typical corner is far off the median view's (a view's median
        // error, so that one bad corner does not condemn its view).
        let errs = solve::point_errors(&sol.calib, &used_views, &sol.poses);
        let view_median: Vec<f64> = errs
            .iter()
            .zip(&used_views)
            .map(|(e, v)| {
                let mut x: Vec<f64> = e
                    .iter()
                    .zip(&v.used)
                    .filter(|(_, u)| **u)
                    .map(|(x, _)| *x)
                    .collect();
                median(&mut x)
            })
            .collect();
        let mut meds: Vec<f64> = view_median
            .iter()
            .zip(&out_view)
            .filter(|(_, o)| o.is_none())
            .map(|(r, _)| *r)
            .collect();
        let med = median(&mut meds);
        let gate = (settings.reject_view_factor * med).max(settings.reject_view_floor_px);
        let mut order: Vec<usize> = (0..used_views.len()).collect();
        order.sort_by(|a, b| view_median[*b].total_cmp(&view_median[*a]));
        let mut left = out_view.iter().filter(|o| o.is_none()).count();
        for i in order {
            let r = view_median[i];
            if out_view[i].is_none() && left > settings.min_views && (r > gate || r.is_nan()) {
                out_view[i] = Some(format!(
                    "median corner error {r:.3} px, over {:.1}x the median view's {med:.3} px",
                    settings.reject_view_factor
                ));
                used_views[i].used.iter_mut().for_each(|u| *u = false);
                left -= 1;
                changed = true;
            }
        }
        // Corners far above the median corner, in the views kept.
        let mut all: Vec<f64> = errs
            .iter()
            .zip(&used_views)
            .flat_map(|(e, v)| e.iter().zip(&v.used).filter(|(_, u)| **u).map(|(x, _)| *x))
            .collect();
        let med_p = median(&mut all);
        let gate_p = (settings.reject_point_factor * med_p).max(settings.reject_point_floor_px);
        for (e, v) in errs.iter().zip(used_views.iter_mut()) {
            let keep_min = settings.min_points_per_view;
            let mut left = v.used_count();
            for (k, x) in e.iter().enumerate() {
                if v.used[k] && left > keep_min && (*x > gate_p || x.is_nan()) {
                    v.used[k] = false;
                    left -= 1;
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
        params = free_params(settings, &sol.calib, true);
        let kept: Vec<usize> = (0..used_views.len())
            .filter(|i| out_view[*i].is_none())
            .collect();
        let sub_views: Vec<View> = kept.iter().map(|i| used_views[*i].clone()).collect();
        let sub_poses: Vec<_> = kept.iter().map(|i| sol.poses[*i]).collect();
        let s = solve::solve(
            sol.calib.clone(),
            sub_poses,
            &sub_views,
            &params,
            settings.max_iterations,
        )
        .ok_or_else(|| refuse("the least squares failed after leaving out bad views"))?;
        // Back to every view's slot (left-out views keep their last pose).
        let mut poses_all = sol.poses.clone();
        for (j, i) in kept.iter().enumerate() {
            poses_all[*i] = s.poses[j];
        }
        let view_rms_all = solve::view_rms(&s.calib, &used_views, &poses_all);
        sol = solve::Solution {
            poses: poses_all,
            view_rms_px: view_rms_all,
            ..s
        };
    }
    // The left-out views' errors are reported under the final intrinsics.
    let mut all_used = used_views.clone();
    for v in &mut all_used {
        v.used.iter_mut().for_each(|u| *u = true);
    }
    let all_rms = solve::view_rms(&sol.calib, &all_used, &sol.poses);
    let focal_sigma = sol.sigma(|p| matches!(p, Param::Fx | Param::Focal { .. }));
    let rel = focal_sigma / sol.calib.fx;
    if rel.is_nan() {
        return Err(refuse(format!(
            "the views do not fix every parameter of the {} model (its normal matrix is \
             singular at fx = {:.1} px): use a model with fewer lens terms (plumb_bob), or \
             add views that fill the image's corners, tilted 20 to 45 degrees",
            sol.calib.model, sol.calib.fx
        )));
    }
    if rel > settings.max_focal_sigma {
        return Err(refuse(format!(
            "the views leave the focal length uncertain: fx = {:.1} +- {:.1} px ({:.1} %, more \
             than {:.1} %); add views tilted 20 to 45 degrees, nearer and farther",
            sol.calib.fx,
            focal_sigma,
            100.0 * rel,
            100.0 * settings.max_focal_sigma
        )));
    }
    let mut dmin = f64::MAX;
    let mut dmax: f64 = 0.0;
    for (j, &i) in index.iter().enumerate() {
        let (tilt, d) = tilt_and_distance(&sol.poses[j], &used_views[j]);
        let r = &mut reports[i];
        r.tilt_deg = tilt;
        r.distance_m = d;
        r.rms_px = if out_view[j].is_some() {
            all_rms[j]
        } else {
            sol.view_rms_px[j]
        };
        r.points_used = if out_view[j].is_some() {
            0
        } else {
            used_views[j].used_count()
        };
        r.rejected = out_view[j].clone();
        if out_view[j].is_none() {
            dmin = dmin.min(d);
            dmax = dmax.max(d);
        }
    }
    let kept: Vec<&View> = used_views
        .iter()
        .zip(&out_view)
        .filter(|(_, o)| o.is_none())
        .map(|(v, _)| v)
        .collect();
    let coverage = Coverage::of(
        width,
        height,
        kept.iter().flat_map(|v| {
            v.points
                .iter()
                .zip(&v.used)
                .filter(|(_, u)| **u)
                .map(|(p, _)| p.1)
        }),
    );
    let parameters = sol
        .params
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let sigma = sol
                .covariance
                .as_ref()
                .map_or(f64::NAN, |c| c[(i, i)].max(0.0).sqrt());
            (p.name(sol.calib.model), solve::value(*p, &sol.calib), sigma)
        })
        .collect();
    Ok(Calibration {
        rms_px: sol.rms_px,
        views_used: kept.len(),
        points_used: sol.points,
        calib: sol.calib,
        views: reports,
        parameters,
        coverage,
        working_distance_m: [dmin, dmax],
        iterations: sol.iterations,
    })
}

#[cfg(test)]
mod tests;
