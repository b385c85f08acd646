//! Calibration targets and their corners in an image.
//!
//! - **ChArUco** (OpenCV 4.6 contrib aruco): a checkerboard with an ArUco marker in each
//!   white square; the markers identify the squares, `interpolateCornersCharuco` finds
//!   the checker corners between them (saddle points, refined by `cornerSubPix`), so a
//!   partial or occluded view still gives known corners. The most accurate corners of
//!   the three: a saddle point has no edge-blur bias.
//! - **Checkerboard**: `findChessboardCornersSB` (the whole inner grid must be in view).
//! - **Marker grid** (an AprilTag grid as Kalibr's `aprilgrid`, or a site's coplanar
//!   markers): each marker's four corners, decoded by OpenCV's aruco detector and
//!   refined by markhold's edge fit (`corners.rs`) with the lens model in hand, so the
//!   corners sharpen as the calibration does.
//!
//! Target coordinates: metres in the target's plane (z = 0). A marker grid uses the site
//! frame's convention (x right, y up as printed); OpenCV's boards use theirs.

use markhold_camera::{Corners, Frame};
use nalgebra::{Point3, Vector2};
use opencv::{aruco, calib3d, core, imgproc, prelude::*};

use crate::apriltag3::AprilTag3;
use crate::corners::{ClipModel, EdgeRefiner};
use crate::dict::dictionary;
use crate::error::CvContext;
use crate::pose::marker_object_points;
use crate::tracker::mat_of;
use crate::{CameraCalibration, MarkerDetector, MarkerFamily, VisionError};

/// One marker of a marker grid: its id, side, centre on the target and turn in the
/// target's plane (counter-clockwise as printed, degrees).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridMarker {
    pub id: u32,
    pub size_m: f64,
    pub centre_m: [f64; 2],
    pub turn_deg: f64,
}

/// A planar calibration target of known geometry.
#[derive(Debug, Clone, PartialEq)]
pub enum Target {
    /// `squares_x` x `squares_y` squares of `square_m`, markers of `marker_m` from
    /// `family` (ids from 0, as OpenCV's `CharucoBoard::create`).
    Charuco {
        squares_x: u32,
        squares_y: u32,
        square_m: f64,
        marker_m: f64,
        family: MarkerFamily,
    },
    /// `inner_x` x `inner_y` inner corners, squares of `square_m`.
    Checkerboard {
        inner_x: u32,
        inner_y: u32,
        square_m: f64,
    },
    /// Markers of `family` on one plane.
    Markers {
        family: MarkerFamily,
        markers: Vec<GridMarker>,
    },
}

impl Target {
    /// Kalibr's `aprilgrid`: `tags_x` x `tags_y` tags of side `tag_m`, `spacing` times
    /// the side between neighbours, ids row by row from `first_id`, the first at the
    /// top left.
    pub fn aprilgrid(
        family: MarkerFamily,
        tags_x: u32,
        tags_y: u32,
        tag_m: f64,
        spacing: f64,
        first_id: u32,
    ) -> Target {
        let pitch = tag_m * (1.0 + spacing);
        let mut markers = Vec::new();
        for j in 0..tags_y {
            for i in 0..tags_x {
                markers.push(GridMarker {
                    id: first_id + j * tags_x + i,
                    size_m: tag_m,
                    centre_m: [i as f64 * pitch, -(j as f64) * pitch],
                    turn_deg: 0.0,
                });
            }
        }
        Target::Markers { family, markers }
    }

    /// One line for reports.
    pub fn describe(&self) -> String {
        match self {
            Target::Charuco {
                squares_x,
                squares_y,
                square_m,
                marker_m,
                family,
            } => format!(
                "ChArUco {squares_x}x{squares_y} squares of {} mm, markers {} mm of {family}",
                square_m * 1e3,
                marker_m * 1e3
            ),
            Target::Checkerboard {
                inner_x,
                inner_y,
                square_m,
            } => format!(
                "checkerboard of {inner_x}x{inner_y} inner corners, squares of {} mm",
                square_m * 1e3
            ),
            Target::Markers { family, markers } => {
                format!("{} markers of {family} on one plane", markers.len())
            }
        }
    }

    /// Check the geometry; the error names what is wrong.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |reason: String| VisionError::CalibrationRefused { reason };
        match self {
            Target::Charuco {
                squares_x,
                squares_y,
                square_m,
                marker_m,
                family,
            } => {
                if *squares_x < 2 || *squares_y < 2 || *squares_x > 100 || *squares_y > 100 {
                    return Err(bad(format!(
                        "a ChArUco board of {squares_x}x{squares_y} squares: expected 2..100 each way"
                    )));
                }
                if !(*square_m > 0.0 && *marker_m > 0.0 && marker_m < square_m) {
                    return Err(bad(format!(
                        "ChArUco squares of {square_m} m with markers of {marker_m} m: expected \
                         sizes > 0 with the marker smaller than the square"
                    )));
                }
                let needed = squares_x * squares_y / 2;
                if needed > family.id_count() {
                    return Err(bad(format!(
                        "a {squares_x}x{squares_y} ChArUco board needs {needed} markers; {family} \
                         has {}",
                        family.id_count()
                    )));
                }
            }
            Target::Checkerboard {
                inner_x,
                inner_y,
                square_m,
            } => {
                if *inner_x < 2 || *inner_y < 2 || !square_m.is_finite() || *square_m <= 0.0 {
                    return Err(bad(format!(
                        "a checkerboard of {inner_x}x{inner_y} inner corners and {square_m} m \
                         squares: expected at least 2x2 and a size > 0"
                    )));
                }
            }
            Target::Markers { family, markers } => {
                if markers.is_empty() {
                    return Err(bad("a marker grid without markers".into()));
                }
                for (i, m) in markers.iter().enumerate() {
                    if m.id >= family.id_count() || !m.size_m.is_finite() || m.size_m <= 0.0 {
                        return Err(bad(format!(
                            "marker {i} of the grid: id {} of {family} ({} ids), side {} m",
                            m.id,
                            family.id_count(),
                            m.size_m
                        )));
                    }
                    if markers[..i].iter().any(|o| o.id == m.id) {
                        return Err(bad(format!("marker id {} twice in the grid", m.id)));
                    }
                }
            }
        }
        Ok(())
    }
}

/// The target's corners found in one image.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Found {
    /// (position on the target, pixel) of each corner found.
    pub points: Vec<(Point3<f64>, Vector2<f64>)>,
    /// Markers decoded (ChArUco and marker grids).
    pub markers: usize,
}

/// Finds a target's corners, with the buffers and OpenCV objects kept between images.
pub struct BoardDetector {
    target: Target,
    dict: Option<core::Ptr<aruco::Dictionary>>,
    params: core::Ptr<aruco::DetectorParameters>,
    charuco: Option<core::Ptr<aruco::CharucoBoard>>,
    edges: EdgeRefiner,
    /// AprilTag 3's detector in place of OpenCV's for a marker grid
    /// ([`BoardDetector::with_detector`]).
    apriltag: Option<AprilTag3>,
}

impl BoardDetector {
    pub fn new(target: &Target) -> Result<Self, VisionError> {
        target.validate()?;
        let mut params = aruco::DetectorParameters::create().cv("DetectorParameters::create")?;
        // OpenCV's aruco samples' detector_params.yml (the ChArUco tutorial's photographs
        // were calibrated with it); no corner refinement of OpenCV's for markers.
        params.set_polygonal_approx_accuracy_rate(0.05);
        params.set_corner_refinement_method(aruco::CornerRefineMethod::CORNER_REFINE_NONE as i32);
        let (dict, charuco) = match target {
            Target::Charuco {
                squares_x,
                squares_y,
                square_m,
                marker_m,
                family,
            } => {
                let (d, b) = charuco_board(*squares_x, *squares_y, *square_m, *marker_m, *family)?;
                (Some(d), Some(b))
            }
            Target::Markers { family, .. } => (Some(dictionary(*family)?), None),
            Target::Checkerboard { .. } => (None, None),
        };
        Ok(Self {
            target: target.clone(),
            dict,
            params,
            charuco,
            edges: EdgeRefiner::new(),
            apriltag: None,
        })
    }

    /// The same with the markers of a marker grid found and decoded by `detector`
    /// (`[marker] detector`); the corners are markhold's edge fit either way.
    pub fn with_detector(target: &Target, detector: MarkerDetector) -> Result<Self, VisionError> {
        let mut d = Self::new(target)?;
        if detector == MarkerDetector::AprilTag3 {
            let family = match target {
                Target::Markers { family, .. } => *family,
                Target::Charuco { family, .. } => *family,
                Target::Checkerboard { .. } => MarkerFamily::Aruco4x4_50,
            };
            d.apriltag = Some(AprilTag3::new(family)?);
        }
        Ok(d)
    }

    pub fn target(&self) -> &Target {
        &self.target
    }

    /// The target's corners in `frame`. `calib`: the current estimate of the camera
    /// (ChArUco interpolation through the pose, and marker edges fitted straight in
    /// undistorted coordinates); `None` on a first pass.
    pub fn detect(
        &mut self,
        frame: &Frame,
        calib: Option<&CameraCalibration>,
    ) -> Result<Found, VisionError> {
        let image = mat_of(frame, true)?;
        match self.target.clone() {
            Target::Charuco { .. } => self.charuco(&image, calib),
            Target::Checkerboard {
                inner_x,
                inner_y,
                square_m,
            } => checkerboard(&image, inner_x, inner_y, square_m),
            Target::Markers { family, markers } => {
                self.markers(frame, &image, family, &markers, calib)
            }
        }
    }

    fn detect_markers(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
    ) -> Result<(core::Vector<core::Vector<core::Point2f>>, core::Vector<i32>), VisionError> {
        let mut corners = core::Vector::<core::Vector<core::Point2f>>::new();
        let mut ids = core::Vector::<i32>::new();
        let mut rejected = core::Vector::<core::Vector<core::Point2f>>::new();
        if let Some(at) = self.apriltag.as_mut() {
            at.detect(image, |id, c| {
                corners.push(c.iter().map(|p| core::Point2f::new(p[0], p[1])).collect());
                ids.push(id as i32);
            })?;
            return Ok((corners, ids));
        }
        let Some(dict) = &self.dict else {
            return Ok((corners, ids));
        };
        aruco::detect_markers(
            image,
            dict,
            &mut corners,
            &mut ids,
            &self.params,
            &mut rejected,
        )
        .cv("detect_markers")?;
        Ok((corners, ids))
    }

    fn charuco(
        &mut self,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        calib: Option<&CameraCalibration>,
    ) -> Result<Found, VisionError> {
        let (corners, ids) = self.detect_markers(image)?;
        let mut found = Found {
            markers: ids.len(),
            ..Found::default()
        };
        let Some(board) = &self.charuco else {
            return Ok(found);
        };
        if ids.is_empty() {
            return Ok(found);
        }
        let mut ch_corners = core::Vector::<core::Point2f>::new();
        let mut ch_ids = core::Vector::<i32>::new();
        // With a calibration OpenCV places the corners through the board's pose (as its
        // calibration sample's second pass does); it knows OpenCV's own models only.
        let (k, d) = match calib {
            Some(c) if c.model != crate::DistortionModel::Equidistant => (
                core::Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])
                    .cv("camera matrix")?,
                core::Mat::from_slice(&c.dist)
                    .cv("distortion")?
                    .try_clone()
                    .cv("distortion")?,
            ),
            _ => (core::Mat::default(), core::Mat::default()),
        };
        aruco::interpolate_corners_charuco(
            &corners,
            &ids,
            image,
            board,
            &mut ch_corners,
            &mut ch_ids,
            &k,
            &d,
            2,
        )
        .cv("interpolateCornersCharuco")?;
        let obj = board.chessboard_corners();
        for (p, id) in ch_corners.iter().zip(ch_ids.iter()) {
            let Some(o) = usize::try_from(id).ok().and_then(|i| obj.get(i).ok()) else {
                continue;
            };
            found.points.push((
                Point3::new(o.x as f64, o.y as f64, o.z as f64),
                Vector2::new(p.x as f64, p.y as f64),
            ));
        }
        Ok(found)
    }

    fn markers(
        &mut self,
        frame: &Frame,
        image: &(impl core::MatTraitConst + core::ToInputArray),
        family: MarkerFamily,
        markers: &[GridMarker],
        calib: Option<&CameraCalibration>,
    ) -> Result<Found, VisionError> {
        let (corners, ids) = self.detect_markers(image)?;
        let mut found = Found::default();
        // Without an estimate the edges are fitted as straight in the image (short
        // sides: the distortion bends them little).
        let plain;
        let c = match calib {
            Some(c) => c,
            None => {
                let f = frame.width.max(frame.height) as f64;
                plain = CameraCalibration::pinhole(
                    frame.width,
                    frame.height,
                    f,
                    f,
                    frame.width as f64 / 2.0,
                    frame.height as f64 / 2.0,
                );
                &plain
            }
        };
        let cells = (family.data_bits() + 2) as f64;
        for (quad, id) in corners.iter().zip(ids.iter()) {
            let Some(m) = markers.iter().find(|m| m.id as i32 == id) else {
                continue;
            };
            if quad.len() != 4 {
                continue;
            }
            let mut q: Corners = [[0.0; 2]; 4];
            for (k, p) in quad.iter().enumerate() {
                q[k] = [p.x, p.y];
            }
            let side = (0..4)
                .map(|i| {
                    let (a, b) = (q[i], q[(i + 1) % 4]);
                    ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
                })
                .fold(f64::MAX, f64::min);
            if self
                .edges
                .refine(
                    &frame.view(),
                    c,
                    &mut q,
                    side / cells,
                    &ClipModel::default(),
                )
                .is_none()
            {
                // An edge that cannot be fitted: the marker is left out rather than
                // given a coarse corner.
                continue;
            }
            found.markers += 1;
            let obj = marker_object_points(m.size_m);
            let (sn, cs) = m.turn_deg.to_radians().sin_cos();
            for (o, p) in obj.iter().zip(&q) {
                found.points.push((
                    Point3::new(
                        cs * o.x - sn * o.y + m.centre_m[0],
                        sn * o.x + cs * o.y + m.centre_m[1],
                        0.0,
                    ),
                    Vector2::new(p[0] as f64, p[1] as f64),
                ));
            }
        }
        Ok(found)
    }
}

fn checkerboard(
    image: &impl core::ToInputArray,
    inner_x: u32,
    inner_y: u32,
    square_m: f64,
) -> Result<Found, VisionError> {
    let size = core::Size::new(inner_x as i32, inner_y as i32);
    let mut pts = core::Vector::<core::Point2f>::new();
    let flags = calib3d::CALIB_CB_NORMALIZE_IMAGE
        | calib3d::CALIB_CB_EXHAUSTIVE
        | calib3d::CALIB_CB_ACCURACY;
    let mut ok = calib3d::find_chessboard_corners_sb(image, size, &mut pts, flags)
        .cv("findChessboardCornersSB")?;
    if !ok {
        // The classic detector, refined by cornerSubPix.
        ok = calib3d::find_chessboard_corners(
            image,
            size,
            &mut pts,
            calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE,
        )
        .cv("findChessboardCorners")?;
        if ok {
            let criteria = core::TermCriteria::new(
                core::TermCriteria_COUNT + core::TermCriteria_EPS,
                40,
                0.001,
            )
            .cv("TermCriteria")?;
            imgproc::corner_sub_pix(
                image,
                &mut pts,
                core::Size::new(5, 5),
                core::Size::new(-1, -1),
                criteria,
            )
            .cv("cornerSubPix")?;
        }
    }
    let mut found = Found::default();
    if !ok || pts.len() != (inner_x * inner_y) as usize {
        return Ok(found);
    }
    for (k, p) in pts.iter().enumerate() {
        let (i, j) = (k as u32 % inner_x, k as u32 / inner_x);
        found.points.push((
            Point3::new(i as f64 * square_m, j as f64 * square_m, 0.0),
            Vector2::new(p.x as f64, p.y as f64),
        ));
    }
    Ok(found)
}

/// A grey image file (PNG, JPEG, ... as OpenCV reads them; colour is converted) as a
/// frame. Errors name the file.
pub fn read_image(path: &std::path::Path) -> Result<Frame, VisionError> {
    let img = opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_GRAYSCALE).cv("imread")?;
    if img.empty() || img.typ() != core::CV_8UC1 {
        return Err(VisionError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "not an image OpenCV can read (PNG, JPEG, BMP, TIFF, ...)",
            ),
        });
    }
    let (w, h) = (img.cols() as u32, img.rows() as u32);
    let mut frame = Frame::new(w, h);
    let cont = if img.is_continuous() {
        img
    } else {
        img.try_clone().cv("clone image")?
    };
    frame
        .data
        .copy_from_slice(&cont.data_bytes().cv("image bytes")?[..(w * h) as usize]);
    Ok(frame)
}

/// A marker of a target's printed layout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PrintedMarker {
    pub id: u32,
    /// Top-left corner of the black square on the page, metres from the board's top-left
    /// corner (y down), its side, and its turn (counter-clockwise as printed, degrees).
    pub x_m: f64,
    pub y_m: f64,
    pub size_m: f64,
    pub turn_deg: f64,
}

/// What a target looks like printed: its extent, the black squares of a checker pattern
/// and the markers, all in metres from its top-left corner (y down, as on paper).
#[derive(Debug, Clone, PartialEq)]
pub struct BoardLayout {
    pub width_m: f64,
    pub height_m: f64,
    /// Black squares: (x, y, side).
    pub squares: Vec<[f64; 3]>,
    pub markers: Vec<PrintedMarker>,
    pub family: Option<MarkerFamily>,
}

/// OpenCV's ChArUco board of these dimensions, with its dictionary.
fn charuco_board(
    squares_x: u32,
    squares_y: u32,
    square_m: f64,
    marker_m: f64,
    family: MarkerFamily,
) -> Result<(core::Ptr<aruco::Dictionary>, core::Ptr<aruco::CharucoBoard>), VisionError> {
    let d = dictionary(family)?;
    let b = aruco::CharucoBoard::create(
        squares_x as i32,
        squares_y as i32,
        square_m as f32,
        marker_m as f32,
        &d,
    )
    .cv("CharucoBoard::create")?;
    Ok((d, b))
}

impl Target {
    /// The printed layout. ChArUco boards take OpenCV's own geometry (the markers'
    /// places and ids from `CharucoBoard::create`, the squares without a marker black),
    /// so what is printed is what the detector expects.
    pub fn layout(&self) -> Result<BoardLayout, VisionError> {
        self.validate()?;
        match self {
            Target::Charuco {
                squares_x,
                squares_y,
                square_m,
                marker_m,
                family,
            } => {
                let (_, b) = charuco_board(*squares_x, *squares_y, *square_m, *marker_m, *family)?;
                let height = *squares_y as f64 * square_m;
                let mut markers = Vec::new();
                let mut white = vec![false; (squares_x * squares_y) as usize];
                for (quad, id) in b.obj_points().iter().zip(b.ids().iter()) {
                    // Corner 0 is the marker's top-left; OpenCV 4.6's board coordinates
                    // run as the printed page's (x right, y down).
                    let p0 = quad.get(0).cv("board corner")?;
                    let (x, y) = (p0.x as f64, p0.y as f64);
                    markers.push(PrintedMarker {
                        id: id as u32,
                        x_m: x,
                        y_m: y,
                        size_m: *marker_m,
                        turn_deg: 0.0,
                    });
                    let (i, j) = ((x / square_m) as usize, (y / square_m) as usize);
                    if let Some(w) = white.get_mut(j * *squares_x as usize + i) {
                        *w = true;
                    }
                }
                let mut squares = Vec::new();
                for j in 0..*squares_y as usize {
                    for i in 0..*squares_x as usize {
                        if !white[j * *squares_x as usize + i] {
                            squares.push([i as f64 * square_m, j as f64 * square_m, *square_m]);
                        }
                    }
                }
                Ok(BoardLayout {
                    width_m: *squares_x as f64 * square_m,
                    height_m: height,
                    squares,
                    markers,
                    family: Some(*family),
                })
            }
            Target::Checkerboard {
                inner_x,
                inner_y,
                square_m,
            } => {
                let (nx, ny) = (inner_x + 1, inner_y + 1);
                let mut squares = Vec::new();
                for j in 0..ny {
                    for i in 0..nx {
                        if (i + j) % 2 == 0 {
                            squares.push([i as f64 * square_m, j as f64 * square_m, *square_m]);
                        }
                    }
                }
                Ok(BoardLayout {
                    width_m: nx as f64 * square_m,
                    height_m: ny as f64 * square_m,
                    squares,
                    markers: Vec::new(),
                    family: None,
                })
            }
            Target::Markers { family, markers } => {
                // Extent of the markers (their turned corners), with one marker module of
                // white around.
                let mut lo = [f64::MAX; 2];
                let mut hi = [f64::MIN; 2];
                let cells = (family.data_bits() + 2) as f64;
                for m in markers {
                    let r = m.size_m * (0.5 * std::f64::consts::SQRT_2 + 1.0 / cells);
                    for k in 0..2 {
                        lo[k] = lo[k].min(m.centre_m[k] - r);
                        hi[k] = hi[k].max(m.centre_m[k] + r);
                    }
                }
                let printed = markers
                    .iter()
                    .map(|m| PrintedMarker {
                        id: m.id,
                        x_m: m.centre_m[0] - lo[0] - m.size_m / 2.0,
                        y_m: hi[1] - m.centre_m[1] - m.size_m / 2.0,
                        size_m: m.size_m,
                        turn_deg: m.turn_deg,
                    })
                    .collect();
                Ok(BoardLayout {
                    width_m: hi[0] - lo[0],
                    height_m: hi[1] - lo[1],
                    squares: Vec::new(),
                    markers: printed,
                    family: Some(*family),
                })
            }
        }
    }
}
