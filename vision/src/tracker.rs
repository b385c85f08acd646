//! Detection of the markers of the site's map (full-frame or RoI-tracked, per marker),
//! sub-pixel corners, IPPE_SQUARE pose per marker with ambiguity resolution, one joint
//! pose over every marker in view with outliers left out, and its covariance.

use crate::apriltag3::AprilTag3;
use crate::config::{DetectorConfig, MarkerConfig, MarkerDetector, PlacedMarker};
use crate::corners::{ClipModel, CornerCov, EdgeCovariance, EdgeRefiner};
use crate::dict::dictionary;
use crate::error::CvContext;
use crate::mapping::SeenMarker;
use crate::pose::{
    isotropic_corner_cov, marker_object_points, marker_rms_px, refine_pose, refine_pose_joint,
    unweighted_gain, whitening, MarkerCorners, RefinedPose,
};
use crate::{CameraCalibration, VisionError};
use markhold_camera::{Corners, Frame, Roi};
use markhold_geometry::{cov_of_inverse, cov_through};
use nalgebra::{
    Isometry3, Matrix6, Point3, SMatrix, Translation3, UnitQuaternion, Vector2, Vector3, Vector6,
};
use opencv::{aruco, calib3d, core, imgproc, prelude::*};

/// One pose of the site frame from the markers of the map in view.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerObservation {
    /// The marker whose corners are given: the origin marker when it was used, else the
    /// largest marker used.
    pub id: u32,
    /// Sub-pixel corners of marker `id` in aruco order (top-left, top-right,
    /// bottom-right, bottom-left as printed).
    pub corners: Corners,
    /// Pose of the site frame (the origin marker's frame) in the camera frame.
    pub t_cam_marker: Isometry3<f64>,
    /// Covariance of (tx, ty, tz, rx, ry, rz) of `t_cam_marker`, camera frame
    /// (translation m^2, rotation rad^2, left/global rotation error): the edge fit's
    /// noise and the clipped edges' shift.
    pub cov_cam: Matrix6<f64>,
    /// The same from the edge fit's noise alone (what the pose is weighted by): the
    /// station keeper's measurement noise, on which its filter and gate were tuned.
    pub cov_cam_fit: Matrix6<f64>,
    /// RMS reprojection error of the corners of every marker used, pixels.
    pub reproj_rms_px: f64,
    /// Found by the RoI-tracked search (false: full-frame search).
    pub tracked: bool,
    /// Markers of the map the pose was computed from.
    pub markers_used: u32,
    /// Markers of the map found in the frame but left out as outliers.
    pub outliers: u32,
}

impl MarkerObservation {
    /// Pose of the camera in the marker frame.
    pub fn t_marker_cam(&self) -> Isometry3<f64> {
        self.t_cam_marker.inverse()
    }

    /// Covariance of `t_marker_cam`, on the marker frame's axes (camera position
    /// error includes the lever arm of the rotation error).
    pub fn cov_marker(&self) -> Matrix6<f64> {
        cov_of_inverse(&self.t_cam_marker, &self.cov_cam)
    }

    /// The exposure controller's region: the corners' bounding box padded by
    /// `pad_frac` of its size, clamped to a `width` x `height` frame.
    pub fn exposure_roi(&self, pad_frac: f32, width: u32, height: u32) -> Option<Roi> {
        Roi::from_corners_padded(&self.corners, pad_frac, width, height)
    }
}

/// What [`MarkerTracker::process_tracked`] found.
// Returned by value once a frame; a Box would allocate on the per-frame path.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Tracked {
    /// The tracked search answered (`None`: found but rejected by the pose checks).
    Done(Option<MarkerObservation>),
    /// A full-frame search of this frame is needed: call
    /// [`MarkerTracker::process_full`].
    NeedsFullSearch,
}

/// Counters of what the tracker did (for logs and tests).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TrackerStats {
    pub frames: u64,
    pub full_searches: u64,
    /// Windows searched by tracking (one per tracked marker, and one per marker the map
    /// places in view without a track).
    pub tracked_searches: u64,
    /// Markers found in those windows.
    pub tracked_hits: u64,
    /// Frames with a pose.
    pub detections: u64,
    /// Marker poses where both IPPE solutions fitted and continuity chose between them.
    pub ambiguous: u64,
    /// Marker detections rejected for their reprojection error.
    pub rejected: u64,
    /// Detections whose edges could not be fitted (cornerSubPix corners used).
    pub subpix_fallbacks: u64,
    /// Markers of the map used in poses, summed over frames.
    pub markers_used: u64,
    /// Markers of the map found but left out of the joint pose (`map_outlier_rms_px`).
    pub outliers: u64,
    /// Edge points fitted, and those whose white side clipped (their sides' shift is in
    /// the pose covariance, `corner_clip_sigma_px`).
    pub edge_points: u64,
    pub clipped_edge_points: u64,
}

#[derive(Debug, Clone, Copy)]
struct TrackState {
    corners: Corners,
    stamp_s: f64,
    /// Image velocity of the marker centre, pixels per second.
    velocity_px_s: [f64; 2],
    t_cam_marker: Isometry3<f64>,
}

/// One marker of the map: where it is, its object points, and this frame's findings.
struct Slot {
    placed: PlacedMarker,
    /// Corners in the marker's own frame (for IPPE_SQUARE and its refinement).
    obj: [Point3<f64>; 4],
    obj_cv: core::Vector<core::Point3f>,
    /// Corners in the site frame (for the joint pose and the map's prediction).
    obj_site: [Point3<f64>; 4],
    track: Option<TrackState>,
    /// This frame: corners found (coarse, then refined), and whether by tracking.
    found: Option<Corners>,
    found_tracked: bool,
    /// This frame: the full search's coarse corners.
    coarse: Option<Corners>,
    /// This frame: the marker's own pose and its corners for the joint pose.
    single: Option<RefinedPose>,
    joint: MarkerCorners,
    /// This frame: the marker was used in the pose returned.
    in_pose: bool,
    /// White-to-black grey ratio of the marker's edges, last measured on enough unclipped
    /// edge points (the clipped edges' shift follows from it: `corners::ClipModel`).
    contrast: Option<f64>,
}

/// Detection + pose over the site's marker map; owns its OpenCV buffers and the
/// tracking state of every marker (all sized at start-up for the map).
pub struct MarkerTracker {
    marker: MarkerConfig,
    cfg: DetectorConfig,
    calib: CameraCalibration,
    det: Detector,
    camera_matrix: core::Mat,
    dist_coeffs: core::Mat,
    slots: Vec<Slot>,
    /// Per-slot buffers of the joint pose: corners, selected, best selection.
    joint: Vec<MarkerCorners>,
    used: Vec<bool>,
    best_used: Vec<bool>,
    img_cv: core::Vector<core::Point2f>,
    rvecs: core::Vector<core::Mat>,
    tvecs: core::Vector<core::Mat>,
    reproj: core::Mat,
    small: core::Mat,
    /// The frame at the full search's downscale, and at twice it (the bounded search).
    coarse: core::Mat,
    coarser: core::Mat,
    edges: EdgeRefiner,
    /// The last pose of the site frame (frame stamp, `t_cam_site`) while a marker is
    /// tracked: places the untracked markers of the map in the image.
    last_site: Option<(f64, Isometry3<f64>)>,
    frames_since_full: u32,
    /// The next part of the bounded search of frames without a marker
    /// ([`absent_search_part`]), and whether the last full search found nothing.
    absent_part: u32,
    searched_empty: bool,
    /// Stamp of the last frame a marker was found in.
    last_found_s: Option<f64>,
    last_search: Option<Roi>,
    stats: TrackerStats,
}

/// Correlation of the clipped edges' common shifts between the markers of a map. On the
/// HIL's maps 1 is over-confident where AAEC lands at the clip onset (the noise-clipped
/// shifts of the markers differ), 0.5 leaves the yaw too conservative (figures:
/// docs/design/vision.md, "Clipped edges").
const MAP_CLIP_CORRELATION: f64 = 0.75;

/// Perimeters a tracked window accepts, as fractions of the marker's expected perimeter
/// (its last side, or the side the map projects): a marker does not halve or double its
/// size between two frames of a track.
const TRACK_PERIMETER_RANGE: (f64, f64) = (0.5, 2.0);

/// Adaptive-threshold window of a tracked window's search, in modules of the marker as
/// searched (its expected side over the scale, over the cells of a side), within the
/// configured smallest and largest windows.
const TRACK_THRESH_WINDOW_MODULES: f64 = 2.0;

/// `(m + m^T) / 2`: a sandwich `K C K^T` symmetric to rounding.
fn sym(m: Matrix6<f64>) -> Matrix6<f64> {
    (m + m.transpose()) * 0.5
}

/// Pose covariance of the clipped edges (what the weights leave out) for the pose
/// `t_cam_frame` with edge-fit covariance `fit`, over `markers` (their corners in that
/// frame, and their image corners): each marker's own side shifts, and the markers'
/// common shifts, which share their sign but are each predicted from the marker's own
/// over-exposure: [`MAP_CLIP_CORRELATION`] of them is summed before squaring, the rest
/// added marker by marker (one marker: its whole common shift).
fn clip_covariance<'a>(
    calib: &CameraCalibration,
    markers: impl IntoIterator<Item = (&'a [Point3<f64>; 4], &'a MarkerCorners)>,
    t_cam_frame: &Isometry3<f64>,
    fit: &Matrix6<f64>,
) -> Option<Matrix6<f64>> {
    let (mut own, mut common) = (Matrix6::zeros(), Vector6::zeros());
    for (obj, m) in markers {
        let k = unweighted_gain(calib, obj, &m.img, &m.white, t_cam_frame, fit)?;
        let c = k * m.clip_common;
        own += sym(k * m.clip * k.transpose()) + c * c.transpose() * (1.0 - MAP_CLIP_CORRELATION);
        common += c;
    }
    Some(own + common * common.transpose() * MAP_CLIP_CORRELATION)
}

impl MarkerTracker {
    pub fn new(
        marker: &MarkerConfig,
        detector: &DetectorConfig,
        calib: CameraCalibration,
    ) -> Result<Self, VisionError> {
        marker.validate()?;
        detector.validate()?;
        calib.validate()?;
        if detector.opencv_threads > 0 {
            core::set_num_threads(detector.opencv_threads).cv("set_num_threads")?;
        }
        let dict = dictionary(marker.family)?;
        let mut params = aruco::DetectorParameters::create().cv("DetectorParameters::create")?;
        let d = detector;
        params.set_adaptive_thresh_win_size_min(d.adaptive_thresh_win_min_px);
        params.set_adaptive_thresh_win_size_max(d.adaptive_thresh_win_max_px);
        params.set_adaptive_thresh_win_size_step(d.adaptive_thresh_win_step_px);
        params.set_adaptive_thresh_constant(d.adaptive_thresh_constant);
        params.set_polygonal_approx_accuracy_rate(d.polygonal_approx_accuracy_rate);
        params.set_error_correction_rate(d.error_correction_rate);
        // Sub-pixel refinement is ours (refine_corners): OpenCV 4.6 uses one fixed
        // window, which reaches past the border module of a small or oblique marker
        // and biases the corner by pixels.
        params.set_corner_refinement_method(aruco::CornerRefineMethod::CORNER_REFINE_NONE as i32);

        // IPPE_SQUARE runs on normalised undistorted corners (our lens models, any of
        // them; OpenCV's solvePnP knows only its own): the identity camera, no distortion.
        let camera_matrix =
            core::Mat::from_slice_2d(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
                .cv("camera matrix")?;
        let dist_coeffs = core::Mat::default();
        let slots: Vec<Slot> = marker
            .markers()
            .map(|placed| {
                let obj = marker_object_points(placed.size_m);
                Slot {
                    placed,
                    obj,
                    obj_cv: obj
                        .iter()
                        .map(|p| core::Point3f::new(p.x as f32, p.y as f32, p.z as f32))
                        .collect(),
                    obj_site: obj.map(|p| placed.t_site_marker * p),
                    track: None,
                    found: None,
                    found_tracked: false,
                    coarse: None,
                    single: None,
                    joint: MarkerCorners::default(),
                    in_pose: false,
                    contrast: None,
                }
            })
            .collect();
        // Map index of each id of the dictionary (-1: not in the map).
        let mut index_of_id = vec![-1_i16; marker.family.id_count() as usize];
        for (i, s) in slots.iter().enumerate() {
            if let Some(e) = index_of_id.get_mut(s.placed.id as usize) {
                *e = i as i16;
            }
        }
        let n = slots.len();
        Ok(Self {
            marker: marker.clone(),
            cfg: detector.clone(),
            calib,
            det: Detector {
                index_of_id,
                found: vec![None; n],
                max_perimeter_rate: detector.max_marker_perimeter_rate,
                thresh_windows_px: (
                    detector.adaptive_thresh_win_min_px,
                    detector.adaptive_thresh_win_max_px,
                ),
                dict,
                params,
                corners: core::Vector::new(),
                ids: core::Vector::new(),
                rejected: core::Vector::new(),
                apriltag: match marker.detector {
                    MarkerDetector::OpenCv => None,
                    MarkerDetector::AprilTag3 => Some(AprilTag3::new(marker.family)?),
                },
            },
            camera_matrix,
            dist_coeffs,
            slots,
            joint: vec![MarkerCorners::default(); n],
            used: vec![false; n],
            best_used: vec![false; n],
            img_cv: core::Vector::with_capacity(4),
            rvecs: core::Vector::new(),
            tvecs: core::Vector::new(),
            reproj: core::Mat::default(),
            small: core::Mat::default(),
            coarse: core::Mat::default(),
            coarser: core::Mat::default(),
            edges: EdgeRefiner::new(),
            last_site: None,
            frames_since_full: 0,
            absent_part: 0,
            searched_empty: false,
            last_found_s: None,
            last_search: None,
            stats: TrackerStats::default(),
        })
    }

    pub fn calibration(&self) -> &CameraCalibration {
        &self.calib
    }

    pub fn marker(&self) -> &MarkerConfig {
        &self.marker
    }

    pub fn detector_config(&self) -> &DetectorConfig {
        &self.cfg
    }

    pub fn stats(&self) -> TrackerStats {
        self.stats
    }

    /// The first window the last RoI-tracked search looked in (`None` after a full
    /// search).
    pub fn last_search_roi(&self) -> Option<Roi> {
        self.last_search
    }

    /// The markers of the map found in the last frame processed, each with its own pose
    /// (from its four corners alone, not from where the map places it): what
    /// [`crate::mapping::MapBuilder`] builds a map from.
    pub fn seen_markers(&self) -> impl Iterator<Item = SeenMarker> + '_ {
        self.slots.iter().filter_map(|s| {
            s.found?;
            let single = s.single?;
            Some(SeenMarker {
                id: s.placed.id,
                img: s.joint.img,
                white: s.joint.white,
                t_cam_marker: single.t_cam_marker,
            })
        })
    }

    /// Number of markers in the site's map (the size of per-marker buffers).
    pub fn map_len(&self) -> usize {
        self.slots.len()
    }

    /// Every marker of the map in view on the last frame with a pose, in map order: the
    /// markers the pose used with their corners as found (`decoded` true), and the
    /// others where the pose places them (`decoded` false) when all four corners fall
    /// in the image: a marker washed out by a lamp, or too dark to decode, is still
    /// where the map says. Nothing after a frame without a pose.
    pub fn for_each_marker_in_view(&self, mut f: impl FnMut(u32, &Corners, bool)) {
        let Some((_, t_cam_site)) = self.last_site else {
            return;
        };
        if !self.slots.iter().any(|s| s.in_pose) {
            return;
        }
        let (w, h) = (self.calib.width as f64, self.calib.height as f64);
        for s in &self.slots {
            if s.in_pose {
                if let Some(c) = &s.found {
                    f(s.placed.id, c, true);
                    continue;
                }
            }
            let mut corners: Corners = [[0.0; 2]; 4];
            let mut inside = true;
            for (c, p) in corners.iter_mut().zip(&s.obj_site) {
                match self.calib.project(&(t_cam_site * p)) {
                    Some(uv) if (0.0..w).contains(&uv.x) && (0.0..h).contains(&uv.y) => {
                        *c = [uv.x as f32, uv.y as f32];
                    }
                    _ => inside = false,
                }
            }
            if inside {
                f(s.placed.id, &corners, false);
            }
        }
    }

    /// Forget the tracking state: the next frame gets a full-frame search.
    pub fn reset(&mut self) {
        for s in &mut self.slots {
            s.track = None;
        }
        self.last_site = None;
        self.frames_since_full = 0;
        self.searched_empty = false;
        self.last_found_s = None;
        self.last_search = None;
    }

    /// Detect the map's markers in `frame` and estimate the site frame's pose.
    /// `Ok(None)`: none seen (or every one rejected).
    pub fn process(&mut self, frame: &Frame) -> Result<Option<MarkerObservation>, VisionError> {
        match self.process_tracked(frame)? {
            Tracked::Done(obs) => Ok(obs),
            Tracked::NeedsFullSearch => self.process_full(frame),
        }
    }

    /// The first half of [`Self::process`]: the RoI-tracked search only, in a window per
    /// tracked marker and per marker the map places in view without a track. When it
    /// finds no marker (no track, every track lost, or a periodic full search due) it
    /// returns [`Tracked::NeedsFullSearch`] and [`Self::process_full`] must follow on the
    /// same frame; the loop can send its command in between, so that a full-frame search
    /// (docs/design/loop.md gives its cost) does not sit between the frame and the command.
    pub fn process_tracked(&mut self, frame: &Frame) -> Result<Tracked, VisionError> {
        let image = self.image_of(frame)?;
        self.stats.frames += 1;
        let _span = tracing::trace_span!("marker_tracker", seq = frame.meta.seq).entered();
        let stamp = frame.meta.stamp_s;
        let fresh = |t: f64| {
            let age = stamp - t;
            age >= 0.0 && age <= self.cfg.track_max_age_s
        };
        for s in &mut self.slots {
            if s.track.is_some_and(|t| !fresh(t.stamp_s)) {
                s.track = None;
            }
            s.found = None;
            s.found_tracked = false;
            s.in_pose = false;
        }
        if self.last_site.is_some_and(|(t, _)| !fresh(t)) {
            self.last_site = None;
        }

        let period = self.cfg.full_search_period_frames;
        let periodic_full = period > 0 && self.frames_since_full + 1 >= period;
        self.last_search = None;
        if periodic_full {
            return Ok(Tracked::NeedsFullSearch);
        }
        let mut searched = false;
        for i in 0..self.slots.len() {
            if self.slots[i].found.is_some() {
                // Already found in another marker's window.
                continue;
            }
            let Some((roi, scale, side)) = self.predicted_window(i, stamp) else {
                continue;
            };
            searched = true;
            self.stats.tracked_searches += 1;
            if self.last_search.is_none() {
                self.last_search = Some(roi);
            }
            self.detect_window(&image, roi, scale, Some(side))?;
            self.take_found(true);
        }
        if !searched {
            return Ok(Tracked::NeedsFullSearch);
        }
        let hits = self.slots.iter().filter(|s| s.found.is_some()).count();
        if hits == 0 {
            return Ok(Tracked::NeedsFullSearch);
        }
        self.stats.tracked_hits += hits as u64;
        self.last_found_s = Some(stamp);
        self.frames_since_full += 1;
        Ok(Tracked::Done(self.finish(frame, &image)?))
    }

    /// The second half of [`Self::process`] after [`Tracked::NeedsFullSearch`]: a
    /// full-frame search of the same frame.
    pub fn process_full(
        &mut self,
        frame: &Frame,
    ) -> Result<Option<MarkerObservation>, VisionError> {
        let _span = tracing::trace_span!("marker_full_search", seq = frame.meta.seq).entered();
        let image = self.image_of(frame)?;
        self.stats.full_searches += 1;
        self.frames_since_full = 0;
        for s in &mut self.slots {
            s.found = None;
            s.found_tracked = false;
            s.in_pose = false;
        }
        let stamp = frame.meta.stamp_s;
        // A marker found within `track_max_age_s` is likely still in view (washed out,
        // covered for a moment): search for it completely.
        let recent = self
            .last_found_s
            .is_some_and(|t| (0.0..=self.cfg.track_max_age_s).contains(&(stamp - t)));
        self.full_search(&image, recent)?;
        self.searched_empty = self.slots.iter().all(|s| s.found.is_none());
        if !self.searched_empty {
            self.last_found_s = Some(stamp);
        }
        if self.searched_empty {
            let mut lost = false;
            for s in &mut self.slots {
                lost |= s.track.take().is_some();
            }
            self.last_site = None;
            if lost {
                tracing::debug!(seq = frame.meta.seq, "marker lost");
            }
            return Ok(None);
        }
        self.finish(frame, &image)
    }

    /// The frame's pixels as an OpenCV matrix (no copy), after checking its size against
    /// the calibration and its buffer: both halves of `process` can be called on their own.
    fn image_of<'f>(
        &self,
        frame: &'f Frame,
    ) -> Result<opencv::boxed_ref::BoxedRef<'f, core::Mat>, VisionError> {
        self.calib
            .check_resolution(frame.width, frame.height)
            .map_err(|_| VisionError::FrameSize {
                what: "the camera calibration",
                width: frame.width,
                height: frame.height,
                expected_width: self.calib.width,
                expected_height: self.calib.height,
            })?;
        mat_of(frame, false)
    }

    /// The detector's last findings into the slots not found yet this frame.
    fn take_found(&mut self, tracked: bool) {
        for (s, f) in self.slots.iter_mut().zip(self.det.found.iter()) {
            if s.found.is_none() {
                if let Some((_, c)) = f {
                    s.found = Some(*c);
                    s.found_tracked = tracked;
                }
            }
        }
    }

    /// Sub-pixel corners and pose of every marker found this frame, then the site
    /// frame's pose from them (outliers left out); updates the tracks.
    fn finish(
        &mut self,
        frame: &Frame,
        image: &(impl core::MatTraitConst + core::ToInputArray),
    ) -> Result<Option<MarkerObservation>, VisionError> {
        let stamp = frame.meta.stamp_s;
        let mut valid = 0;
        for i in 0..self.slots.len() {
            self.slots[i].single = None;
            let Some(mut corners) = self.slots[i].found else {
                self.slots[i].track = None;
                continue;
            };
            let edge_cov = self.refine_corners(i, frame, image, &mut corners)?;
            self.slots[i].found = Some(corners);
            let pose = self.estimate_pose(i, &corners, &edge_cov.fit)?;
            let white = whitening(&edge_cov.fit);
            let s = &mut self.slots[i];
            match (pose, white) {
                (Some(p), Some(white)) => {
                    s.single = Some(p);
                    s.joint = MarkerCorners {
                        obj: s.obj_site,
                        img: corners.map(|c| Vector2::new(c[0] as f64, c[1] as f64)),
                        white,
                        clip: edge_cov.clip,
                        clip_common: edge_cov.clip_common,
                    };
                    valid += 1;
                }
                _ => {
                    self.stats.rejected += 1;
                    s.track = None;
                    s.found = None;
                }
            }
        }
        let result = match valid {
            0 => None,
            1 => self.single_pose(stamp),
            _ => self.joint_pose(stamp),
        };
        if self.slots.iter().all(|s| s.track.is_none()) {
            self.last_site = None;
        }
        Ok(result)
    }

    /// The site frame's pose from the one marker with a pose.
    fn single_pose(&mut self, stamp: f64) -> Option<MarkerObservation> {
        let i = self.slots.iter().position(|s| s.single.is_some())?;
        let s = &mut self.slots[i];
        let sol = s.single?;
        let corners = s.found?;
        let both = sol.covariance().and_then(|fit| {
            let clip = clip_covariance(&self.calib, [(&s.obj, &s.joint)], &sol.t_cam_marker, &fit)?;
            Some((fit, fit + clip))
        });
        let Some((fit, cov)) = both else {
            self.stats.rejected += 1;
            s.track = None;
            return None;
        };
        // The origin marker's frame is the site frame: its pose as measured.
        let (t_cam_site, cov_cam, cov_cam_fit) = if i == 0 {
            (sol.t_cam_marker, cov, fit)
        } else {
            let t_marker_site = s.placed.t_site_marker.inverse();
            (
                sol.t_cam_marker * t_marker_site,
                cov_through(&sol.t_cam_marker, &t_marker_site, &cov),
                cov_through(&sol.t_cam_marker, &t_marker_site, &fit),
            )
        };
        let tracked = s.found_tracked;
        let id = s.placed.id;
        self.stats.detections += 1;
        self.stats.markers_used += 1;
        self.update_track(i, &corners, stamp, sol.t_cam_marker);
        self.slots[i].in_pose = true;
        self.last_site = Some((stamp, t_cam_site));
        Some(MarkerObservation {
            id,
            corners,
            t_cam_marker: t_cam_site,
            cov_cam,
            cov_cam_fit,
            reproj_rms_px: sol.reproj_rms_px,
            tracked,
            markers_used: 1,
            outliers: 0,
        })
    }

    /// Covariance of the joint pose `sol` over the markers in `best_used`: (with the
    /// clipped edges' shift, the edge fit's alone).
    fn joint_covariance(&self, sol: &RefinedPose) -> Option<(Matrix6<f64>, Matrix6<f64>)> {
        let fit = sol.covariance()?;
        let used = self.joint.iter().zip(&self.best_used).filter(|(_, u)| **u);
        let clip = clip_covariance(
            &self.calib,
            used.map(|(m, _)| (&m.obj, m)),
            &sol.t_cam_marker,
            &fit,
        )?;
        Some((fit + clip, fit))
    }

    /// The site frame's pose from every marker with a pose: each marker's pose proposes
    /// one for the site, the markers whose corners fit it are refined together, and the
    /// proposal that most markers fit wins (ties: the one nearer the last pose, else the
    /// lower residual). The markers left over are outliers.
    fn joint_pose(&mut self, stamp: f64) -> Option<MarkerObservation> {
        let gate = self.cfg.map_outlier_rms_px;
        for (j, s) in self.joint.iter_mut().zip(&self.slots) {
            *j = s.joint;
        }
        let have: u32 = self.slots.iter().filter(|s| s.single.is_some()).count() as u32;
        let previous = self.last_site.map(|(_, t)| t);
        let mut best: Option<(usize, f64, RefinedPose)> = None;
        for h in 0..self.slots.len() {
            let Some(single) = self.slots[h].single else {
                continue;
            };
            if best.is_some() && self.best_used[h] {
                // Already in the best set: its proposal would find the same set.
                continue;
            }
            let init = single.t_cam_marker * self.slots[h].placed.t_site_marker.inverse();
            // A single marker's pose places the others less well than the joint one:
            // a wider gate first, then the gate itself.
            let mut pose = init;
            let mut ok = true;
            for g in [4.0 * gate, gate, gate] {
                self.select(&pose, g);
                self.used[h] |= g > gate;
                match refine_pose_joint(&self.calib, &self.joint, &self.used, &pose) {
                    Some(p) => pose = p.t_cam_marker,
                    None => {
                        ok = false;
                        break;
                    }
                }
            }
            if !ok {
                continue;
            }
            self.select(&pose, gate);
            let count = self.used.iter().filter(|u| **u).count();
            if count == 0 {
                continue;
            }
            let Some(sol) = refine_pose_joint(&self.calib, &self.joint, &self.used, &pose) else {
                continue;
            };
            let tie = match previous {
                Some(p) => (sol.t_cam_marker.translation.vector - p.translation.vector).norm(),
                None => sol.reproj_rms_px,
            };
            let better = match &best {
                None => true,
                Some((c, t, _)) => count > *c || (count == *c && tie < *t),
            };
            if better {
                best = Some((count, tie, sol));
                self.best_used.copy_from_slice(&self.used);
            }
        }
        let Some((count, _, sol)) = best else {
            for s in &mut self.slots {
                if s.single.is_some() {
                    s.track = None;
                }
            }
            self.stats.rejected += have as u64;
            return None;
        };
        let outliers = have - count as u32;
        let Some((cov_cam, cov_cam_fit)) = self.joint_covariance(&sol) else {
            self.stats.rejected += have as u64;
            for s in &mut self.slots {
                s.track = None;
            }
            return None;
        };
        let t_cam_site = sol.t_cam_marker;
        // The corners given: the origin marker's when used, else the largest used.
        let mut shown: Option<(usize, f64)> = None;
        for i in 0..self.slots.len() {
            let s = &self.slots[i];
            let (Some(corners), true) = (s.found, s.single.is_some()) else {
                continue;
            };
            if !self.best_used[i] {
                // An outlier: not tracked on, so a wrong decode is not followed.
                tracing::debug!(id = s.placed.id, "map marker left out as an outlier");
                self.slots[i].track = None;
                continue;
            }
            let side = if i == 0 { f64::MAX } else { side_px(&corners) };
            if shown.is_none_or(|(_, b)| side > b) {
                shown = Some((i, side));
            }
            // Continuity for the marker's own IPPE choice: its pose as the map puts it.
            let t_cam_marker = t_cam_site * self.slots[i].placed.t_site_marker;
            self.update_track(i, &corners, stamp, t_cam_marker);
            self.slots[i].in_pose = true;
        }
        let (i, _) = shown?;
        let s = &self.slots[i];
        let obs = MarkerObservation {
            id: s.placed.id,
            corners: s.found?,
            t_cam_marker: t_cam_site,
            cov_cam,
            cov_cam_fit,
            reproj_rms_px: sol.reproj_rms_px,
            tracked: self
                .best_used
                .iter()
                .zip(&self.slots)
                .any(|(u, s)| *u && s.found_tracked),
            markers_used: count as u32,
            outliers,
        };
        self.stats.detections += 1;
        self.stats.markers_used += count as u64;
        self.stats.outliers += outliers as u64;
        self.last_site = Some((stamp, t_cam_site));
        Some(obs)
    }

    /// `used`: the markers with a pose whose corners reproject within `gate` pixels
    /// (RMS) under the site pose `pose`.
    fn select(&mut self, pose: &Isometry3<f64>, gate: f64) {
        for ((u, s), j) in self.used.iter_mut().zip(&self.slots).zip(&self.joint) {
            *u = s.single.is_some()
                && marker_rms_px(&self.calib, j, pose).is_some_and(|r| r <= gate);
        }
    }

    fn update_track(&mut self, i: usize, corners: &Corners, stamp_s: f64, pose: Isometry3<f64>) {
        let s = &mut self.slots[i];
        let c = centre(corners);
        let velocity_px_s = match &s.track {
            Some(prev) if stamp_s > prev.stamp_s => {
                let p = centre(&prev.corners);
                let dt = stamp_s - prev.stamp_s;
                [(c[0] - p[0]) / dt, (c[1] - p[1]) / dt]
            }
            _ => [0.0, 0.0],
        };
        s.track = Some(TrackState {
            corners: *corners,
            stamp_s,
            velocity_px_s,
            t_cam_marker: pose,
        });
    }

    /// Downscale of a tracked search: about `track_target_side_px` pixels of
    /// marker side are enough to find and decode it; the edge fit then works at full
    /// resolution. Bounds the cost of tracking a close marker.
    fn track_scale(&self, side_px: f64) -> u32 {
        let s = (side_px / self.cfg.track_target_side_px).floor();
        (s as u32).clamp(1, 4)
    }

    /// Search window, scale and the marker's expected side (pixels) for marker `i` this
    /// frame: its last corners moved by the predicted motion, padded by a fraction of its
    /// side and by the motion itself; or, without a track, where the last pose of the
    /// site puts it (every corner in the image).
    fn predicted_window(&self, i: usize, stamp_s: f64) -> Option<(Roi, u32, f64)> {
        let s = &self.slots[i];
        let (pred, side, motion) = match &s.track {
            Some(t) => {
                let dt = (stamp_s - t.stamp_s).max(0.0);
                let (dx, dy) = (t.velocity_px_s[0] * dt, t.velocity_px_s[1] * dt);
                let mut pred = t.corners;
                for p in &mut pred {
                    p[0] += dx as f32;
                    p[1] += dy as f32;
                }
                (pred, side_px(&t.corners), dx.hypot(dy))
            }
            None => {
                let (_, t_cam_site) = self.last_site?;
                let mut pred: Corners = [[0.0; 2]; 4];
                for (p, o) in pred.iter_mut().zip(&s.obj_site) {
                    let uv = self.calib.project(&(t_cam_site * o))?;
                    let inside = uv.x >= 0.0
                        && uv.y >= 0.0
                        && uv.x < self.calib.width as f64
                        && uv.y < self.calib.height as f64;
                    if !inside {
                        return None;
                    }
                    *p = [uv.x as f32, uv.y as f32];
                }
                (pred, side_px(&pred), 0.0)
            }
        };
        let pad = self.cfg.track_window_scale * side
            + self.cfg.track_motion_gain * motion
            + 2.0 * self.cfg.subpix_window_px as f64;
        let roi = padded_window(&pred, pad, self.calib.width, self.calib.height)?;
        let scale = match &s.track {
            Some(t) => self.track_scale(side_px(&t.corners)),
            None => self.track_scale(side),
        };
        Some((roi, scale, side))
    }

    /// The whole image as a window.
    fn full_roi(&self) -> Roi {
        Roi {
            x: 0,
            y: 0,
            width: self.calib.width,
            height: self.calib.height,
        }
    }

    /// Full-frame search, on a downscaled image when configured (then each marker found
    /// is searched again at full resolution in a window around its coarse corners).
    ///
    /// The first search, a search with a marker tracked until now (a track lost this
    /// frame, or the periodic search), a search after one that found a marker and any
    /// search within `track_max_age_s` of the last frame a marker was found in (`recent`)
    /// are complete: the downscaled image, and the whole image at full resolution when that
    /// finds nothing (`full_search_fallback_full_res`). After a search that found
    /// nothing, with nothing tracked, the search is coarse to fine and bounded: the image
    /// at twice the downscale every frame (a marker of about 70 px or more at the
    /// default, found on its first frame), then one part of the finer searches in turn
    /// (`absent_search_part`): rows of the image at the downscale, or a band of it at
    /// full resolution.
    fn full_search(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        recent: bool,
    ) -> Result<(), VisionError> {
        let full = self.full_roi();
        let s = self.cfg.full_search_downscale;
        if s <= 1 {
            self.detect_window(image, full, 1, None)?;
            self.take_found(false);
            return Ok(());
        }
        let tracked = self.last_site.is_some() || self.slots.iter().any(|sl| sl.track.is_some());
        if tracked || recent || !self.searched_empty {
            self.absent_part = 0;
            self.complete_search(image, s)
        } else {
            self.bounded_search(image, s)
        }
    }

    /// The whole frame at `s`, and at full resolution when that finds nothing
    /// (`full_search_fallback_full_res`).
    #[inline(never)]
    fn complete_search(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        s: u32,
    ) -> Result<(), VisionError> {
        let full = self.full_roi();
        let size = core::Size::new(
            (self.calib.width / s) as i32,
            (self.calib.height / s) as i32,
        );
        imgproc::resize(image, &mut self.small, size, 0.0, 0.0, imgproc::INTER_AREA)
            .cv("resize")?;
        let coarse = self.det.detect_in(
            &self.small,
            (0.0, 0.0),
            self.cfg.min_marker_perimeter_rate,
            None,
            None,
        )?;
        if coarse > 0 {
            return self.refine_coarse(image, s);
        }
        // Too small to be found at the reduced scale? Look at full resolution.
        if self.cfg.full_search_fallback_full_res {
            self.detect_window(image, full, 1, None)?;
            self.take_found(false);
        }
        Ok(())
    }

    /// The frame at twice the downscale `s`, then one part of the finer searches in turn
    /// ([`absent_search_part`]).
    #[inline(never)]
    fn bounded_search(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        s: u32,
    ) -> Result<(), VisionError> {
        // The frame at the downscale, then at twice it (two integer-block area
        // averages: OpenCV's fast path, where one by 2 s takes its general one).
        let (w, h) = (self.calib.width / s, self.calib.height / s);
        imgproc::resize(
            image,
            &mut self.coarse,
            core::Size::new(w as i32, h as i32),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )
        .cv("resize")?;
        let half = core::Mat::roi(
            &self.coarse,
            core::Rect::new(0, 0, (w / 2 * 2) as i32, (h / 2 * 2) as i32),
        )
        .cv("roi")?;
        imgproc::resize(
            &half,
            &mut self.coarser,
            core::Size::new((w / 2).max(1) as i32, (h / 2).max(1) as i32),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )
        .cv("resize")?;
        let found = self.det.detect_in(
            &self.coarser,
            (0.0, 0.0),
            self.cfg.min_marker_perimeter_rate,
            None,
            None,
        )?;
        if found > 0 {
            return self.refine_coarse(image, 2 * s);
        }
        let (roi, scale) = absent_search_part(
            self.absent_part,
            self.calib.width,
            self.calib.height,
            self.cfg.full_search_fallback_full_res,
        );
        self.absent_part = self.absent_part.wrapping_add(1);
        if scale == 1 {
            self.detect_window(image, roi, 1, None)?;
            self.take_found(false);
            return Ok(());
        }
        // Rows of the downscaled frame: its markers' corners are coarse (the edge fit
        // refines them at full resolution, as a tracked window's).
        let (y0, y1) = (roi.y / s, ((roi.y + roi.height) / s).min(h));
        let band = core::Mat::roi(
            &self.coarse,
            core::Rect::new(0, y0 as i32, w as i32, (y1 - y0) as i32),
        )
        .cv("roi")?;
        // Rates are of the searched image's larger side: the band's is the frame's width.
        let min_rate = self.cfg.min_marker_perimeter_rate * w.max(h) as f64 / w.max(y1 - y0) as f64;
        self.det
            .detect_in(&band, (0.0, 0.0), min_rate, None, None)?;
        let sf = s as f64;
        for (_, c) in self.det.found.iter_mut().flatten() {
            for p in c.iter_mut() {
                p[0] = (p[0] as f64 * sf + (sf - 1.0) / 2.0) as f32;
                p[1] = ((p[1] as f64 + y0 as f64) * sf + (sf - 1.0) / 2.0) as f32;
            }
        }
        self.take_found(false);
        Ok(())
    }

    /// The markers of the detector's last search of the whole image downscaled by
    /// `scale`: each searched again at full resolution in a window around its coarse
    /// corners.
    fn refine_coarse(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        scale: u32,
    ) -> Result<(), VisionError> {
        for (slot, f) in self.slots.iter_mut().zip(self.det.found.iter()) {
            slot.coarse = f.map(|(_, c)| c);
        }
        // Small pixel i covers full pixels [s i, s i + s): its centre is s i + (s-1)/2.
        let sf = scale as f64;
        for i in 0..self.slots.len() {
            if self.slots[i].found.is_some() {
                continue;
            }
            let Some(mut c) = self.slots[i].coarse else {
                continue;
            };
            for p in &mut c {
                p[0] = (p[0] as f64 * sf + (sf - 1.0) / 2.0) as f32;
                p[1] = (p[1] as f64 * sf + (sf - 1.0) / 2.0) as f32;
            }
            let pad = 0.25 * side_px(&c) + 2.0 * sf + 2.0 * self.cfg.subpix_window_px as f64;
            if let Some(roi) = padded_window(&c, pad, self.calib.width, self.calib.height) {
                self.detect_window(image, roi, 1, None)?;
                self.take_found(false);
            }
        }
        Ok(())
    }

    /// Detect in `roi` of the full-resolution image, on the window downscaled by `scale`
    /// when > 1 (corners are only coarse then: the edge fit refines them at full
    /// resolution). The markers found are in `self.det.found`, in full-image pixels.
    fn detect_window(
        &mut self,
        image: &impl core::MatTraitConst,
        roi: Roi,
        scale: u32,
        expect_side_px: Option<f64>,
    ) -> Result<(), VisionError> {
        // A downscaled window is cropped to whole multiples of the scale (at most
        // `scale - 1` pixels off its right and bottom padding): then the ratio is an exact
        // integer, OpenCV's INTER_AREA takes its fast integer-block path instead of the
        // general fractional one, and small pixel i covers full pixels [s i, s i + s)
        // exactly, as the corner mapping below assumes.
        let roi = whole_blocks(roi, scale);
        let rect = core::Rect::new(
            roi.x as i32,
            roi.y as i32,
            roi.width as i32,
            roi.height as i32,
        );
        let view = core::Mat::roi(image, rect).cv("roi")?;
        // Perimeter limits are relative to the searched image's larger side: rescale
        // so a window accepts the same marker sizes in pixels as the full frame.
        let full_max = self.calib.width.max(self.calib.height) as f64;
        let roi_max = roi.width.max(roi.height).max(1) as f64;
        let mut min_rate = self.cfg.min_marker_perimeter_rate * full_max / roi_max;
        if min_rate >= 4.0 {
            self.det.found.fill(None);
            return Ok(());
        }
        // A window searched for a marker of known size passes OpenCV only the contours
        // of about that size: the others (the texture around it, its own cells) cost a
        // polygon fit and, when they make a quad, a decode against every id of the
        // dictionary. Rates are of the searched image's larger side, at any scale.
        // Its module's size is known too: one adaptive-threshold window of about two
        // modules binarises its border whole, where the configured range of windows
        // (for markers of any size) costs a threshold, contours and polygon fits each.
        let mut max_rate = None;
        let mut thresh_win = None;
        if let Some(side) = expect_side_px {
            let expected = 4.0 * side / roi_max;
            min_rate = min_rate.max(TRACK_PERIMETER_RANGE.0 * expected);
            max_rate = Some(TRACK_PERIMETER_RANGE.1 * expected);
            let cells = (self.marker.family.data_bits() + 2) as f64;
            thresh_win = Some(track_thresh_window(
                TRACK_THRESH_WINDOW_MODULES * side / f64::from(scale) / cells,
                self.cfg.adaptive_thresh_win_min_px,
                self.cfg.adaptive_thresh_win_max_px,
            ));
        }
        if scale <= 1 {
            self.det.detect_in(
                &view,
                (roi.x as f64, roi.y as f64),
                min_rate,
                max_rate,
                thresh_win,
            )?;
            return Ok(());
        }
        let size = core::Size::new(
            (roi.width / scale).max(1) as i32,
            (roi.height / scale).max(1) as i32,
        );
        imgproc::resize(&view, &mut self.small, size, 0.0, 0.0, imgproc::INTER_AREA)
            .cv("resize window")?;
        self.det
            .detect_in(&self.small, (0.0, 0.0), min_rate, max_rate, thresh_win)?;
        // Small pixel i covers full pixels [s i, s i + s): its centre is s i + (s-1)/2.
        let sf = scale as f64;
        for (_, c) in self.det.found.iter_mut().flatten() {
            for p in c.iter_mut() {
                p[0] = (roi.x as f64 + p[0] as f64 * sf + (sf - 1.0) / 2.0) as f32;
                p[1] = (roi.y as f64 + p[1] as f64 * sf + (sf - 1.0) / 2.0) as f32;
            }
        }
        Ok(())
    }

    /// Sub-pixel corners and their 8x8 covariance: edge-line fit (see `corners`),
    /// plus the floor of independent corner noise, and the clipped edges' shift apart;
    /// cv::cornerSubPix with `corner_sigma_px` when an edge cannot be measured.
    fn refine_corners(
        &mut self,
        slot: usize,
        frame: &Frame,
        image: &impl core::ToInputArray,
        corners: &mut Corners,
    ) -> Result<EdgeCovariance, VisionError> {
        let cells = (self.marker.family.data_bits() + 2) as f64;
        let min_side = (0..4)
            .map(|i| {
                let (a, b) = (corners[i], corners[(i + 1) % 4]);
                ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
            })
            .fold(f64::MAX, f64::min);
        if let Some(cov) = self.edges.refine(
            &frame.view(),
            &self.calib,
            corners,
            min_side / cells,
            &ClipModel {
                common_px: self.cfg.corner_clip_common_px,
                side_px: self.cfg.corner_clip_side_px,
                contrast: self.slots[slot].contrast,
                gain_px: self.cfg.corner_clip_gain_px,
            },
        ) {
            if cov.contrast.is_some() {
                self.slots[slot].contrast = cov.contrast;
            }
            self.stats.edge_points += u64::from(cov.points);
            self.stats.clipped_edge_points += u64::from(cov.clipped_points);
            return Ok(EdgeCovariance {
                fit: cov.fit + isotropic_corner_cov(self.cfg.corner_sigma_floor_px),
                ..cov
            });
        }
        self.stats.subpix_fallbacks += 1;
        let half = ((0.4 * min_side / cells).floor() as i32).clamp(2, self.cfg.subpix_window_px);
        self.img_cv.clear();
        for c in corners.iter() {
            self.img_cv.push(core::Point2f::new(c[0], c[1]));
        }
        let criteria = core::TermCriteria::new(
            core::TermCriteria_COUNT + core::TermCriteria_EPS,
            self.cfg.subpix_max_iterations,
            self.cfg.subpix_min_accuracy_px,
        )
        .cv("TermCriteria")?;
        imgproc::corner_sub_pix(
            image,
            &mut self.img_cv,
            core::Size::new(half, half),
            core::Size::new(-1, -1),
            criteria,
        )
        .cv("cornerSubPix")?;
        for (c, p) in corners.iter_mut().zip(self.img_cv.iter()) {
            // A corner that wandered off by more than the window is not trusted.
            if p.x.is_finite()
                && p.y.is_finite()
                && (p.x - c[0]).hypot(p.y - c[1]) <= 2.0 * half as f32
            {
                *c = [p.x, p.y];
            }
        }
        Ok(EdgeCovariance {
            fit: isotropic_corner_cov(self.cfg.corner_sigma_px),
            clip: CornerCov::zeros(),
            clip_common: SMatrix::zeros(),
            clipped_points: 0,
            points: 0,
            contrast: None,
        })
    }

    /// Pose of marker `i` in its own frame: both IPPE solutions refined by LM; the better
    /// fit wins unless the two are ambiguous, when the one closer to the marker's previous
    /// pose wins.
    fn estimate_pose(
        &mut self,
        i: usize,
        corners: &Corners,
        corner_cov: &CornerCov,
    ) -> Result<Option<RefinedPose>, VisionError> {
        self.img_cv.clear();
        for c in corners {
            let n = self.calib.undistort_pixel(c[0] as f64, c[1] as f64);
            self.img_cv.push(core::Point2f::new(n.x as f32, n.y as f32));
        }
        let n = calib3d::solve_pnp_generic(
            &self.slots[i].obj_cv,
            &self.img_cv,
            &self.camera_matrix,
            &self.dist_coeffs,
            &mut self.rvecs,
            &mut self.tvecs,
            false,
            calib3d::SolvePnPMethod::SOLVEPNP_IPPE_SQUARE,
            &core::no_array(),
            &core::no_array(),
            &mut self.reproj,
        )
        .cv("solvePnPGeneric")?;
        let img = corners.map(|c| Vector2::new(c[0] as f64, c[1] as f64));
        let obj = self.slots[i].obj;
        let mut cands: [Option<RefinedPose>; 2] = [None, None];
        for (k, cand) in cands
            .iter_mut()
            .enumerate()
            .take((n.max(0) as usize).min(2))
        {
            let r = self.rvecs.get(k).cv("rvec")?;
            let t = self.tvecs.get(k).cv("tvec")?;
            let r = mat3(&r)?;
            let t = mat3(&t)?;
            let init =
                Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r));
            *cand = refine_pose(&self.calib, &obj, &img, &init, corner_cov);
        }
        let [a, b] = cands;
        let (best, other) = match (a, b) {
            (Some(a), Some(b)) if b.reproj_rms_px < a.reproj_rms_px => (b, Some(a)),
            (Some(a), b) => (a, b),
            (None, Some(b)) => (b, None),
            (None, None) => return Ok(None),
        };
        let mut chosen = best;
        if let (Some(other), Some(prev)) = (other, self.slots[i].track.as_ref()) {
            let floor = best
                .reproj_rms_px
                .max(self.cfg.corner_sigma_floor_px)
                .max(0.05);
            let distinct = best
                .t_cam_marker
                .rotation
                .angle_to(&other.t_cam_marker.rotation)
                > 1e-3;
            if distinct && other.reproj_rms_px <= self.cfg.ambiguity_ratio * floor {
                self.stats.ambiguous += 1;
                let q = prev.t_cam_marker.rotation;
                if other.t_cam_marker.rotation.angle_to(&q)
                    < best.t_cam_marker.rotation.angle_to(&q)
                {
                    chosen = other;
                }
            }
        }
        if chosen.reproj_rms_px.is_nan() || chosen.reproj_rms_px > self.cfg.max_reproj_rms_px {
            tracing::debug!(
                rms = chosen.reproj_rms_px,
                "marker rejected: reprojection error"
            );
            return Ok(None);
        }
        Ok(Some(chosen))
    }
}

/// OpenCV's aruco detector with its reused output buffers.
struct Detector {
    /// Map index of each id of the dictionary (-1: not in the map).
    index_of_id: Vec<i16>,
    /// The last detection: per map marker, the largest copy's perimeter and corners
    /// in full-image pixels.
    found: Vec<Option<(f64, Corners)>>,
    max_perimeter_rate: f64,
    /// The configured smallest and largest adaptive-threshold windows, pixels.
    thresh_windows_px: (i32, i32),
    dict: core::Ptr<aruco::Dictionary>,
    params: core::Ptr<aruco::DetectorParameters>,
    corners: core::Vector<core::Vector<core::Point2f>>,
    ids: core::Vector<i32>,
    rejected: core::Vector<core::Vector<core::Point2f>>,
    /// AprilTag 3's detector in place of OpenCV's (`[marker] detector = "apriltag3"`).
    apriltag: Option<AprilTag3>,
}

impl Detector {
    /// Detect in `image`; the corners of each marker of the map (its largest copy)
    /// shifted by `offset` into full-image pixels go to `found`. Returns how many markers
    /// of the map were found.
    fn detect_in(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        offset: (f64, f64),
        min_perimeter_rate: f64,
        max_perimeter_rate: Option<f64>,
        thresh_win_px: Option<i32>,
    ) -> Result<usize, VisionError> {
        self.found.fill(None);
        let max_rate = max_perimeter_rate
            .map_or(self.max_perimeter_rate, |m| m.min(self.max_perimeter_rate))
            .max(min_perimeter_rate * 1.01)
            .min(4.0);
        if let Some(at) = self.apriltag.as_mut() {
            let rates = (min_perimeter_rate, max_rate);
            return at.detect_into(image, offset, rates, &self.index_of_id, &mut self.found);
        }
        self.params
            .set_min_marker_perimeter_rate(min_perimeter_rate);
        self.params.set_max_marker_perimeter_rate(max_rate);
        let (win_min, win_max) = thresh_win_px.map_or(self.thresh_windows_px, |w| (w, w));
        self.params.set_adaptive_thresh_win_size_min(win_min);
        self.params.set_adaptive_thresh_win_size_max(win_max);
        aruco::detect_markers(
            image,
            &self.dict,
            &mut self.corners,
            &mut self.ids,
            &self.params,
            &mut self.rejected,
        )
        .cv("detect_markers")?;
        let mut count = 0;
        for (i, id) in self.ids.iter().enumerate() {
            let Some(&slot) = usize::try_from(id)
                .ok()
                .and_then(|id| self.index_of_id.get(id))
            else {
                continue;
            };
            let Ok(slot) = usize::try_from(slot) else {
                continue;
            };
            let quad = self.corners.get(i).cv("detect_markers corners")?;
            if quad.len() != 4 {
                continue;
            }
            let mut c: Corners = [[0.0; 2]; 4];
            for (k, p) in quad.iter().enumerate() {
                c[k] = [
                    (p.x as f64 + offset.0) as f32,
                    (p.y as f64 + offset.1) as f32,
                ];
            }
            let perim = side_px(&c);
            // Several copies of the id: keep the largest.
            let best = &mut self.found[slot];
            if best.is_none() {
                count += 1;
            }
            if best.as_ref().is_none_or(|(b, _)| perim > *b) {
                *best = Some((perim, c));
            }
        }
        Ok(count)
    }
}

/// A frame's pixels as an OpenCV matrix (no copy): an error if its buffer holds fewer
/// bytes than its size, or (with `refuse_empty`) if it has no pixels at all.
pub(crate) fn mat_of(
    frame: &Frame,
    refuse_empty: bool,
) -> Result<opencv::boxed_ref::BoxedRef<'_, core::Mat>, VisionError> {
    let (w, h) = (frame.width as usize, frame.height as usize);
    if frame.data.len() < w * h || (refuse_empty && (w == 0 || h == 0)) {
        return Err(VisionError::FrameSize {
            what: "its pixel buffer",
            width: frame.width,
            height: frame.height,
            expected_width: frame.width,
            expected_height: (frame.data.len() / w.max(1)) as u32,
        });
    }
    core::Mat::new_rows_cols_with_data::<u8>(h as i32, w as i32, &frame.data[..w * h])
        .cv("wrap frame")
}

/// The adaptive-threshold window of `size_px` pixels, odd (OpenCV makes an even window
/// the odd one above it), within `min_px..=max_px`.
fn track_thresh_window(size_px: f64, min_px: i32, max_px: i32) -> i32 {
    // `max` before `min`: a NaN size takes the smallest window.
    let w = size_px
        .round()
        .max(f64::from(min_px))
        .min(f64::from(max_px)) as i32;
    // An even window becomes the odd one below it, unless that is under the smallest.
    if w % 2 == 1 || w - 1 < min_px {
        w | 1
    } else {
        w - 1
    }
}

fn mat3(m: &core::Mat) -> Result<Vector3<f64>, VisionError> {
    let v = m.data_typed::<f64>().cv("pose vector")?;
    if v.len() < 3 {
        return Err(VisionError::OpenCv {
            op: "solvePnPGeneric",
            source: opencv::Error::new(core::StsBadSize, "pose vector with fewer than 3 values"),
        });
    }
    Ok(Vector3::new(v[0], v[1], v[2]))
}

fn centre(c: &Corners) -> [f64; 2] {
    let mut s = [0.0; 2];
    for p in c {
        s[0] += p[0] as f64 / 4.0;
        s[1] += p[1] as f64 / 4.0;
    }
    s
}

/// Mean side length of the quadrilateral, pixels.
pub(crate) fn side_px(c: &Corners) -> f64 {
    (0..4)
        .map(|i| {
            let (a, b) = (c[i], c[(i + 1) % 4]);
            ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
        })
        .sum::<f64>()
        / 4.0
}

/// Integer window of the box, clamped to the image; `None` when empty or not finite.
/// The window around `c`'s bounding box grown by `pad` pixels on each side.
fn padded_window(c: &Corners, pad: f64, w: u32, h: u32) -> Option<Roi> {
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in c {
        x0 = x0.min(p[0] as f64);
        y0 = y0.min(p[1] as f64);
        x1 = x1.max(p[0] as f64);
        y1 = y1.max(p[1] as f64);
    }
    window(x0 - pad, y0 - pad, x1 + pad, y1 + pad, w, h)
}

fn window(x0: f64, y0: f64, x1: f64, y1: f64, w: u32, h: u32) -> Option<Roi> {
    if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) {
        return None;
    }
    let x0 = x0.floor().clamp(0.0, w as f64);
    let y0 = y0.floor().clamp(0.0, h as f64);
    let x1 = x1.ceil().clamp(0.0, w as f64);
    let y1 = y1.ceil().clamp(0.0, h as f64);
    // Too small to hold a marker with its border and the refinement window.
    if x1 - x0 < 16.0 || y1 - y0 < 16.0 {
        return None;
    }
    Some(Roi::between(x0 as u32, y0 as u32, x1 as u32, y1 as u32))
}

/// Full-resolution bands of the bounded search without a marker, and the rows two
/// neighbours share (a marker smaller than that, which the downscaled searches miss,
/// lies whole in one of them).
const ABSENT_FULL_BANDS: u32 = 16;
const ABSENT_BAND_OVERLAP_PX: u32 = 64;
/// Parts of the frame searched at the downscale in turn: each 0.4 of the frame's height
/// at 0, 0.3 and 0.6 of it (two neighbours share a tenth of the frame).
const ABSENT_COARSE_PARTS: u32 = 3;

/// Part `k` of the bounded search of a `width` x `height` frame with no marker tracked,
/// after the whole frame at twice the downscale found nothing: the window, and 1 for a
/// full-resolution band or 0 for rows searched at the downscale. With `full_res`, the
/// downscaled parts and the full-resolution bands alternate, so every part of the frame
/// is searched at the downscale once in 2 x [`ABSENT_COARSE_PARTS`] frames and at full
/// resolution once in 2 x [`ABSENT_FULL_BANDS`]. Without, the downscaled parts in turn.
fn absent_search_part(k: u32, width: u32, height: u32, full_res: bool) -> (Roi, u32) {
    let coarse = |i: u32| {
        let y = (height * 3 * i) / 10;
        let h = (height * 4).div_ceil(10).min(height - y);
        (
            Roi {
                x: 0,
                y,
                width,
                height: h,
            },
            0,
        )
    };
    if !full_res {
        return coarse(k % ABSENT_COARSE_PARTS);
    }
    if k.is_multiple_of(2) {
        return coarse((k / 2) % ABSENT_COARSE_PARTS);
    }
    let band = (k / 2) % ABSENT_FULL_BANDS;
    let y = band * height / ABSENT_FULL_BANDS;
    let h = (height.div_ceil(ABSENT_FULL_BANDS) + ABSENT_BAND_OVERLAP_PX).min(height - y);
    (
        Roi {
            x: 0,
            y,
            width,
            height: h,
        },
        1,
    )
}

/// `roi` cropped at its right and bottom to whole `scale` x `scale` blocks (unchanged
/// when it holds less than one block a side, or at scale 1).
fn whole_blocks(roi: Roi, scale: u32) -> Roi {
    if scale <= 1 || roi.width < scale || roi.height < scale {
        return roi;
    }
    Roi {
        width: roi.width / scale * scale,
        height: roi.height / scale * scale,
        ..roi
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscaled_windows_hold_whole_blocks() {
        let r = |x, y, width, height| Roi {
            x,
            y,
            width,
            height,
        };
        for scale in 1..=4 {
            for (w, h) in [(803, 601), (800, 600), (4, 3), (3, 3), (1439, 1079)] {
                let c = whole_blocks(r(7, 11, w, h), scale);
                assert_eq!((c.x, c.y), (7, 11));
                if w >= scale && h >= scale {
                    assert_eq!((c.width % scale, c.height % scale), (0, 0), "{c:?} {scale}");
                }
                assert!(c.width <= w && w - c.width < scale, "{c:?} {scale}");
                assert!(c.height <= h && h - c.height < scale, "{c:?} {scale}");
            }
        }
        // Smaller than a block: left alone (the detector rejects it as too small).
        assert_eq!(whole_blocks(r(0, 0, 2, 9), 3), r(0, 0, 2, 9));
    }

    #[test]
    fn the_bounded_search_covers_the_frame() {
        for (w, h) in [(1440, 1080), (1920, 1080), (640, 480)] {
            let cycle = 2 * ABSENT_COARSE_PARTS * ABSENT_FULL_BANDS;
            let (mut coarse, mut full) = (Vec::new(), Vec::new());
            for k in 0..cycle {
                let (r, s) = absent_search_part(k, w, h, true);
                assert_eq!((r.x, r.width), (0, w));
                assert!(r.height > 0 && r.y + r.height <= h, "{r:?}");
                assert_eq!(s, k % 2, "{k}");
                if s == 0 {
                    coarse.push((r.y, r.y + r.height));
                } else {
                    full.push((r.y, r.y + r.height));
                }
            }
            // Any run of rows up to a tenth of the frame lies whole in a downscaled
            // part, and up to the overlap in a full-resolution band.
            for (parts, span) in [(&coarse, h / 10), (&full, ABSENT_BAND_OVERLAP_PX)] {
                for y0 in 0..=h - span {
                    let y1 = y0 + span;
                    assert!(
                        parts.iter().any(|(a, b)| *a <= y0 && y1 <= *b),
                        "rows {y0}..{y1} of {h}"
                    );
                }
            }
            // Without the full-resolution bands: the downscaled parts in turn.
            for k in 0..ABSENT_COARSE_PARTS {
                assert_eq!(
                    absent_search_part(k, w, h, false),
                    absent_search_part(2 * k, w, h, true)
                );
            }
        }
    }

    #[test]
    fn tracker_is_send() {
        fn is_send<T: Send>() {}
        is_send::<MarkerTracker>();
    }

    #[test]
    fn window_clamps_and_rejects_tiny() {
        assert_eq!(
            window(-10.0, -5.0, 100.0, 50.0, 80, 40),
            Some(Roi {
                x: 0,
                y: 0,
                width: 80,
                height: 40
            })
        );
        assert_eq!(window(70.0, 30.0, 100.0, 50.0, 80, 40), None);
        assert_eq!(window(f64::NAN, 0.0, 10.0, 10.0, 80, 40), None);
    }

    #[test]
    fn a_tracked_threshold_window_is_odd_and_within_the_range() {
        // Two modules of a 36h11 marker (8 cells a side) searched at 64 and 128 px.
        assert_eq!(track_thresh_window(2.0 * 64.0 / 8.0, 3, 23), 15);
        assert_eq!(track_thresh_window(2.0 * 128.0 / 8.0, 3, 23), 23);
        assert_eq!(track_thresh_window(17.4, 3, 23), 17);
        assert_eq!(track_thresh_window(1.0, 3, 23), 3);
        assert_eq!(track_thresh_window(18.0, 3, 23), 17);
        assert_eq!(track_thresh_window(4.0, 4, 23), 5);
        assert_eq!(track_thresh_window(f64::NAN, 3, 23), 3);
    }
}
