//! Detection of the configured marker (full-frame or RoI-tracked), sub-pixel corners,
//! IPPE_SQUARE pose with ambiguity resolution, LM refinement and covariance.

use crate::config::{DetectorConfig, MarkerConfig};
use crate::corners::{CornerCov, EdgeRefiner};
use crate::dict::dictionary;
use crate::error::CvContext;
use crate::pose::{
    cov_of_inverse, isotropic_corner_cov, marker_object_points, refine_pose, RefinedPose,
};
use crate::{CameraCalibration, VisionError};
use markhold_exposure::{Corners, Frame, Roi};
use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use opencv::{aruco, calib3d, core, imgproc, prelude::*};

/// One detection of the configured marker and its pose.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerObservation {
    pub id: u32,
    /// Sub-pixel corners in aruco order (top-left, top-right, bottom-right,
    /// bottom-left as printed).
    pub corners: Corners,
    /// Pose of the marker in the camera frame.
    pub t_cam_marker: Isometry3<f64>,
    /// Covariance of (tx, ty, tz, rx, ry, rz) of `t_cam_marker`, camera frame
    /// (translation m^2, rotation rad^2, left/global rotation error).
    pub cov_cam: Matrix6<f64>,
    /// RMS reprojection error of the four corners, pixels.
    pub reproj_rms_px: f64,
    /// Found by the RoI-tracked search (false: full-frame search).
    pub tracked: bool,
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
    pub tracked_searches: u64,
    pub tracked_hits: u64,
    pub detections: u64,
    /// Frames where both IPPE solutions fitted and continuity chose between them.
    pub ambiguous: u64,
    /// Detections rejected for their reprojection error.
    pub rejected: u64,
    /// Detections whose edges could not be fitted (cornerSubPix corners used).
    pub subpix_fallbacks: u64,
}

#[derive(Debug, Clone, Copy)]
struct TrackState {
    corners: Corners,
    stamp_s: f64,
    /// Image velocity of the marker centre, pixels per second.
    velocity_px_s: [f64; 2],
    t_cam_marker: Isometry3<f64>,
}

/// Detection + pose of one marker; owns its OpenCV buffers and the tracking state.
pub struct MarkerTracker {
    marker: MarkerConfig,
    cfg: DetectorConfig,
    calib: CameraCalibration,
    det: Detector,
    camera_matrix: core::Mat,
    dist_coeffs: core::Mat,
    obj: [Point3<f64>; 4],
    obj_cv: core::Vector<core::Point3f>,
    img_cv: core::Vector<core::Point2f>,
    rvecs: core::Vector<core::Mat>,
    tvecs: core::Vector<core::Mat>,
    reproj: core::Mat,
    small: core::Mat,
    edges: EdgeRefiner,
    track: Option<TrackState>,
    frames_since_full: u32,
    last_search: Option<Roi>,
    stats: TrackerStats,
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

        let camera_matrix = core::Mat::from_slice_2d(&[
            [calib.fx, 0.0, calib.cx],
            [0.0, calib.fy, calib.cy],
            [0.0, 0.0, 1.0],
        ])
        .cv("camera matrix")?;
        let dist_coeffs = if calib.dist.is_empty() {
            core::Mat::default()
        } else {
            core::Mat::from_slice(&calib.dist)
                .cv("distortion coefficients")?
                .try_clone()
                .cv("distortion coefficients")?
        };
        let obj = marker_object_points(marker.size_m);
        let obj_cv = obj
            .iter()
            .map(|p| core::Point3f::new(p.x as f32, p.y as f32, p.z as f32))
            .collect();
        Ok(Self {
            marker: marker.clone(),
            cfg: detector.clone(),
            calib,
            det: Detector {
                marker_id: marker.id,
                max_perimeter_rate: detector.max_marker_perimeter_rate,
                dict,
                params,
                corners: core::Vector::new(),
                ids: core::Vector::new(),
                rejected: core::Vector::new(),
            },
            camera_matrix,
            dist_coeffs,
            obj,
            obj_cv,
            img_cv: core::Vector::with_capacity(4),
            rvecs: core::Vector::new(),
            tvecs: core::Vector::new(),
            reproj: core::Mat::default(),
            small: core::Mat::default(),
            edges: EdgeRefiner::new(),
            track: None,
            frames_since_full: 0,
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

    /// The window the last RoI-tracked search looked in (`None` after a full search).
    pub fn last_search_roi(&self) -> Option<Roi> {
        self.last_search
    }

    /// Forget the tracking state: the next frame gets a full-frame search.
    pub fn reset(&mut self) {
        self.track = None;
        self.frames_since_full = 0;
        self.last_search = None;
    }

    /// Detect the configured marker id in `frame` and estimate its pose.
    /// `Ok(None)`: not seen (or rejected for its reprojection error).
    pub fn process(&mut self, frame: &Frame) -> Result<Option<MarkerObservation>, VisionError> {
        match self.process_tracked(frame)? {
            Tracked::Done(obs) => Ok(obs),
            Tracked::NeedsFullSearch => self.process_full(frame),
        }
    }

    /// The first half of [`Self::process`]: the RoI-tracked search only. When it cannot
    /// answer (no track, the track lost, or a periodic full search due) it returns
    /// [`Tracked::NeedsFullSearch`] and [`Self::process_full`] must follow on the same
    /// frame; the loop can send its command in between, so that a full-frame search
    /// (8 to 37 ms at 1440x1080) does not sit between the frame and the command.
    pub fn process_tracked(&mut self, frame: &Frame) -> Result<Tracked, VisionError> {
        let image = self.image_of(frame)?;
        self.stats.frames += 1;
        let _span = tracing::trace_span!("marker_tracker", seq = frame.meta.seq).entered();
        let stamp = frame.meta.stamp_s;
        if let Some(t) = &self.track {
            let age = stamp - t.stamp_s;
            if !(age >= 0.0 && age <= self.cfg.track_max_age_s) {
                self.track = None;
            }
        }

        let period = self.cfg.full_search_period_frames;
        let periodic_full = period > 0 && self.frames_since_full + 1 >= period;
        self.last_search = None;
        if periodic_full {
            return Ok(Tracked::NeedsFullSearch);
        }
        let Some(roi) = self.predicted_window(stamp) else {
            return Ok(Tracked::NeedsFullSearch);
        };
        self.stats.tracked_searches += 1;
        self.last_search = Some(roi);
        let Some(corners) = self.detect_window(&image, roi, self.track_scale())? else {
            return Ok(Tracked::NeedsFullSearch);
        };
        self.stats.tracked_hits += 1;
        self.frames_since_full += 1;
        Ok(Tracked::Done(self.finish(frame, &image, corners, true)?))
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
        let Some(corners) = self.full_search(&image)? else {
            if self.track.take().is_some() {
                tracing::debug!(seq = frame.meta.seq, "marker lost");
            }
            return Ok(None);
        };
        self.finish(frame, &image, corners, false)
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
        let (w, h) = (frame.width as usize, frame.height as usize);
        if frame.data.len() < w * h {
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

    /// Sub-pixel corners, pose and covariance of a found marker; updates the track.
    fn finish(
        &mut self,
        frame: &Frame,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        mut corners: Corners,
        tracked: bool,
    ) -> Result<Option<MarkerObservation>, VisionError> {
        let stamp = frame.meta.stamp_s;
        let corner_cov = self.refine_corners(frame, image, &mut corners)?;
        let Some(sol) = self.estimate_pose(&corners, &corner_cov)? else {
            self.stats.rejected += 1;
            self.track = None;
            return Ok(None);
        };
        let Some(cov_cam) = sol.covariance() else {
            self.stats.rejected += 1;
            self.track = None;
            return Ok(None);
        };
        self.stats.detections += 1;
        self.update_track(&corners, stamp, sol.t_cam_marker);
        Ok(Some(MarkerObservation {
            id: self.marker.id,
            corners,
            t_cam_marker: sol.t_cam_marker,
            cov_cam,
            reproj_rms_px: sol.reproj_rms_px,
            tracked,
        }))
    }

    fn update_track(&mut self, corners: &Corners, stamp_s: f64, pose: Isometry3<f64>) {
        let c = centre(corners);
        let velocity_px_s = match &self.track {
            Some(prev) if stamp_s > prev.stamp_s => {
                let p = centre(&prev.corners);
                let dt = stamp_s - prev.stamp_s;
                [(c[0] - p[0]) / dt, (c[1] - p[1]) / dt]
            }
            _ => [0.0, 0.0],
        };
        self.track = Some(TrackState {
            corners: *corners,
            stamp_s,
            velocity_px_s,
            t_cam_marker: pose,
        });
    }

    /// Downscale of the tracked search: about `track_target_side_px` pixels of
    /// marker side are enough to find and decode it; the edge fit then works at full
    /// resolution. Bounds the cost of tracking a close marker.
    fn track_scale(&self) -> u32 {
        let Some(t) = &self.track else { return 1 };
        let s = (side_px(&t.corners) / self.cfg.track_target_side_px).floor();
        (s as u32).clamp(1, 4)
    }

    /// Search window for this frame: the last corners moved by the predicted motion,
    /// padded by a fraction of the marker's side and by the motion itself.
    fn predicted_window(&self, stamp_s: f64) -> Option<Roi> {
        let t = self.track.as_ref()?;
        let dt = (stamp_s - t.stamp_s).max(0.0);
        let (dx, dy) = (t.velocity_px_s[0] * dt, t.velocity_px_s[1] * dt);
        let mut pred = t.corners;
        for p in &mut pred {
            p[0] += dx as f32;
            p[1] += dy as f32;
        }
        let side = side_px(&t.corners);
        let pad = self.cfg.track_window_scale * side
            + self.cfg.track_motion_gain * dx.hypot(dy)
            + 2.0 * self.cfg.subpix_window_px as f64;
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in &pred {
            x0 = x0.min(p[0] as f64);
            y0 = y0.min(p[1] as f64);
            x1 = x1.max(p[0] as f64);
            y1 = y1.max(p[1] as f64);
        }
        window(
            x0 - pad,
            y0 - pad,
            x1 + pad,
            y1 + pad,
            self.calib.width,
            self.calib.height,
        )
    }

    /// Full-frame search, on a downscaled image when configured (then refined at full
    /// resolution in a window around the coarse corners).
    fn full_search(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
    ) -> Result<Option<Corners>, VisionError> {
        let s = self.cfg.full_search_downscale;
        if s <= 1 {
            let full = Roi {
                x: 0,
                y: 0,
                width: self.calib.width,
                height: self.calib.height,
            };
            return self.detect_window(image, full, 1);
        }
        let size = core::Size::new(
            (self.calib.width / s) as i32,
            (self.calib.height / s) as i32,
        );
        imgproc::resize(image, &mut self.small, size, 0.0, 0.0, imgproc::INTER_AREA)
            .cv("resize")?;
        let coarse =
            self.det
                .detect_in(&self.small, (0.0, 0.0), self.cfg.min_marker_perimeter_rate)?;
        let Some(coarse) = coarse else {
            // Too small to be found at the reduced scale? Look at full resolution.
            if self.cfg.full_search_fallback_full_res {
                let full = Roi {
                    x: 0,
                    y: 0,
                    width: self.calib.width,
                    height: self.calib.height,
                };
                return self.detect_window(image, full, 1);
            }
            return Ok(None);
        };
        // Small pixel i covers full pixels [s i, s i + s): its centre is s i + (s-1)/2.
        let sf = s as f64;
        let mut full = coarse;
        for p in &mut full {
            p[0] = (p[0] as f64 * sf + (sf - 1.0) / 2.0) as f32;
            p[1] = (p[1] as f64 * sf + (sf - 1.0) / 2.0) as f32;
        }
        let pad = 0.25 * side_px(&full) + 2.0 * sf + 2.0 * self.cfg.subpix_window_px as f64;
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in &full {
            x0 = x0.min(p[0] as f64);
            y0 = y0.min(p[1] as f64);
            x1 = x1.max(p[0] as f64);
            y1 = y1.max(p[1] as f64);
        }
        match window(
            x0 - pad,
            y0 - pad,
            x1 + pad,
            y1 + pad,
            self.calib.width,
            self.calib.height,
        ) {
            Some(roi) => self.detect_window(image, roi, 1),
            None => Ok(None),
        }
    }

    /// Detect in `roi` of the full-resolution image; corners in full-image pixels.
    /// Detect in `roi`, on the window downscaled by `scale` when > 1 (corners are
    /// only coarse here: the edge fit refines them at full resolution).
    fn detect_window(
        &mut self,
        image: &impl core::MatTraitConst,
        roi: Roi,
        scale: u32,
    ) -> Result<Option<Corners>, VisionError> {
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
        let min_rate = self.cfg.min_marker_perimeter_rate * full_max / roi_max;
        if min_rate >= 4.0 {
            return Ok(None);
        }
        if scale <= 1 {
            return self
                .det
                .detect_in(&view, (roi.x as f64, roi.y as f64), min_rate);
        }
        let size = core::Size::new(
            (roi.width / scale).max(1) as i32,
            (roi.height / scale).max(1) as i32,
        );
        imgproc::resize(&view, &mut self.small, size, 0.0, 0.0, imgproc::INTER_AREA)
            .cv("resize window")?;
        let found = self.det.detect_in(&self.small, (0.0, 0.0), min_rate)?;
        // Small pixel i covers full pixels [s i, s i + s): its centre is s i + (s-1)/2.
        let sf = scale as f64;
        Ok(found.map(|mut c| {
            for p in &mut c {
                p[0] = (roi.x as f64 + p[0] as f64 * sf + (sf - 1.0) / 2.0) as f32;
                p[1] = (roi.y as f64 + p[1] as f64 * sf + (sf - 1.0) / 2.0) as f32;
            }
            c
        }))
    }

    /// Sub-pixel corners and their 8x8 covariance: edge-line fit (see `corners`),
    /// plus the floor of independent corner noise; cv::cornerSubPix with
    /// `corner_sigma_px` when an edge cannot be measured.
    fn refine_corners(
        &mut self,
        frame: &Frame,
        image: &impl core::ToInputArray,
        corners: &mut Corners,
    ) -> Result<CornerCov, VisionError> {
        let cells = (self.marker.family.data_bits() + 2) as f64;
        let min_side = (0..4)
            .map(|i| {
                let (a, b) = (corners[i], corners[(i + 1) % 4]);
                ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
            })
            .fold(f64::MAX, f64::min);
        if let Some(cov) = self
            .edges
            .refine(&frame.view(), &self.calib, corners, min_side / cells)
        {
            return Ok(cov + isotropic_corner_cov(self.cfg.corner_sigma_floor_px));
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
        Ok(isotropic_corner_cov(self.cfg.corner_sigma_px))
    }

    /// Both IPPE solutions refined by LM; the better fit wins unless the two are
    /// ambiguous, when the one closer to the previous pose wins.
    fn estimate_pose(
        &mut self,
        corners: &Corners,
        corner_cov: &CornerCov,
    ) -> Result<Option<RefinedPose>, VisionError> {
        self.img_cv.clear();
        for c in corners {
            self.img_cv.push(core::Point2f::new(c[0], c[1]));
        }
        let n = calib3d::solve_pnp_generic(
            &self.obj_cv,
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
        let mut cands: [Option<RefinedPose>; 2] = [None, None];
        for (i, cand) in cands
            .iter_mut()
            .enumerate()
            .take((n.max(0) as usize).min(2))
        {
            let r = self.rvecs.get(i).cv("rvec")?;
            let t = self.tvecs.get(i).cv("tvec")?;
            let r = mat3(&r)?;
            let t = mat3(&t)?;
            let init =
                Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r));
            *cand = refine_pose(&self.calib, &self.obj, &img, &init, corner_cov);
        }
        let [a, b] = cands;
        let (best, other) = match (a, b) {
            (Some(a), Some(b)) if b.reproj_rms_px < a.reproj_rms_px => (b, Some(a)),
            (Some(a), b) => (a, b),
            (None, Some(b)) => (b, None),
            (None, None) => return Ok(None),
        };
        let mut chosen = best;
        if let (Some(other), Some(prev)) = (other, self.track.as_ref()) {
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
    marker_id: u32,
    max_perimeter_rate: f64,
    dict: core::Ptr<aruco::Dictionary>,
    params: core::Ptr<aruco::DetectorParameters>,
    corners: core::Vector<core::Vector<core::Point2f>>,
    ids: core::Vector<i32>,
    rejected: core::Vector<core::Vector<core::Point2f>>,
}

impl Detector {
    /// Detect in `image`; corners of the configured id (largest copy) shifted by
    /// `offset` into full-image pixels.
    fn detect_in(
        &mut self,
        image: &impl core::ToInputArray,
        offset: (f64, f64),
        min_perimeter_rate: f64,
    ) -> Result<Option<Corners>, VisionError> {
        let max_rate = self
            .max_perimeter_rate
            .max(min_perimeter_rate * 1.01)
            .min(4.0);
        self.params
            .set_min_marker_perimeter_rate(min_perimeter_rate);
        self.params.set_max_marker_perimeter_rate(max_rate);
        aruco::detect_markers(
            image,
            &self.dict,
            &mut self.corners,
            &mut self.ids,
            &self.params,
            &mut self.rejected,
        )
        .cv("detect_markers")?;
        let mut best: Option<(f64, Corners)> = None;
        for (i, id) in self.ids.iter().enumerate() {
            if id < 0 || id as u32 != self.marker_id {
                continue;
            }
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
            if best.as_ref().is_none_or(|(b, _)| perim > *b) {
                best = Some((perim, c));
            }
        }
        Ok(best.map(|(_, c)| c))
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
fn side_px(c: &Corners) -> f64 {
    (0..4)
        .map(|i| {
            let (a, b) = (c[i], c[(i + 1) % 4]);
            ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
        })
        .sum::<f64>()
        / 4.0
}

/// Integer window of the box, clamped to the image; `None` when empty or not finite.
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
    Some(Roi {
        x: x0 as u32,
        y: y0 as u32,
        width: (x1 - x0) as u32,
        height: (y1 - y0) as u32,
    })
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
}
