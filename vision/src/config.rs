//! The `[marker]` and `[vision]` sections of a site file.

use markhold_config::{above, open, open_closed, Checks, ConfigError};

use crate::VisionError;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::aruco::PREDEFINED_DICTIONARY_NAME as D;
use serde::{Deserialize, Serialize};

/// Marker dictionaries OpenCV 4.6's aruco module knows.
#[allow(non_camel_case_types)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum MarkerFamily {
    #[serde(rename = "apriltag_36h11")]
    AprilTag36h11,
    #[serde(rename = "apriltag_36h10")]
    AprilTag36h10,
    #[serde(rename = "apriltag_25h9")]
    AprilTag25h9,
    #[serde(rename = "apriltag_16h5")]
    AprilTag16h5,
    #[serde(rename = "aruco_4x4_50")]
    Aruco4x4_50,
    #[serde(rename = "aruco_4x4_100")]
    Aruco4x4_100,
    #[serde(rename = "aruco_4x4_250")]
    Aruco4x4_250,
    #[serde(rename = "aruco_4x4_1000")]
    Aruco4x4_1000,
    #[serde(rename = "aruco_5x5_50")]
    Aruco5x5_50,
    #[serde(rename = "aruco_5x5_100")]
    Aruco5x5_100,
    #[serde(rename = "aruco_5x5_250")]
    Aruco5x5_250,
    #[serde(rename = "aruco_5x5_1000")]
    Aruco5x5_1000,
    #[serde(rename = "aruco_6x6_50")]
    Aruco6x6_50,
    #[serde(rename = "aruco_6x6_100")]
    Aruco6x6_100,
    #[serde(rename = "aruco_6x6_250")]
    Aruco6x6_250,
    #[serde(rename = "aruco_6x6_1000")]
    Aruco6x6_1000,
    #[serde(rename = "aruco_7x7_50")]
    Aruco7x7_50,
    #[serde(rename = "aruco_7x7_100")]
    Aruco7x7_100,
    #[serde(rename = "aruco_7x7_250")]
    Aruco7x7_250,
    #[serde(rename = "aruco_7x7_1000")]
    Aruco7x7_1000,
    #[serde(rename = "aruco_original")]
    ArucoOriginal,
}

use MarkerFamily as F;

/// (family, site-file name, OpenCV dictionary, number of ids, data bits per side).
#[rustfmt::skip]
const FAMILIES: [(MarkerFamily, &str, D, u32, usize); 21] = [
    (F::AprilTag36h11, "apriltag_36h11", D::DICT_APRILTAG_36h11, 587,  6),
    (F::AprilTag36h10, "apriltag_36h10", D::DICT_APRILTAG_36h10, 2320, 6),
    (F::AprilTag25h9,  "apriltag_25h9",  D::DICT_APRILTAG_25h9,  35,   5),
    (F::AprilTag16h5,  "apriltag_16h5",  D::DICT_APRILTAG_16h5,  30,   4),
    (F::Aruco4x4_50,   "aruco_4x4_50",   D::DICT_4X4_50,         50,   4),
    (F::Aruco4x4_100,  "aruco_4x4_100",  D::DICT_4X4_100,        100,  4),
    (F::Aruco4x4_250,  "aruco_4x4_250",  D::DICT_4X4_250,        250,  4),
    (F::Aruco4x4_1000, "aruco_4x4_1000", D::DICT_4X4_1000,       1000, 4),
    (F::Aruco5x5_50,   "aruco_5x5_50",   D::DICT_5X5_50,         50,   5),
    (F::Aruco5x5_100,  "aruco_5x5_100",  D::DICT_5X5_100,        100,  5),
    (F::Aruco5x5_250,  "aruco_5x5_250",  D::DICT_5X5_250,        250,  5),
    (F::Aruco5x5_1000, "aruco_5x5_1000", D::DICT_5X5_1000,       1000, 5),
    (F::Aruco6x6_50,   "aruco_6x6_50",   D::DICT_6X6_50,         50,   6),
    (F::Aruco6x6_100,  "aruco_6x6_100",  D::DICT_6X6_100,        100,  6),
    (F::Aruco6x6_250,  "aruco_6x6_250",  D::DICT_6X6_250,        250,  6),
    (F::Aruco6x6_1000, "aruco_6x6_1000", D::DICT_6X6_1000,       1000, 6),
    (F::Aruco7x7_50,   "aruco_7x7_50",   D::DICT_7X7_50,         50,   7),
    (F::Aruco7x7_100,  "aruco_7x7_100",  D::DICT_7X7_100,        100,  7),
    (F::Aruco7x7_250,  "aruco_7x7_250",  D::DICT_7X7_250,        250,  7),
    (F::Aruco7x7_1000, "aruco_7x7_1000", D::DICT_7X7_1000,       1000, 7),
    (F::ArucoOriginal, "aruco_original", D::DICT_ARUCO_ORIGINAL, 1024, 5),
];

impl MarkerFamily {
    /// Every family, in the order of the table above.
    pub fn all() -> impl Iterator<Item = MarkerFamily> {
        FAMILIES.iter().map(|f| f.0)
    }

    fn entry(self) -> &'static (MarkerFamily, &'static str, D, u32, usize) {
        // Every variant is in the table (checked by a unit test).
        FAMILIES
            .iter()
            .find(|f| f.0 == self)
            .unwrap_or(&FAMILIES[0])
    }

    /// The site-file name (`apriltag_36h11`, `aruco_4x4_50`, ...).
    pub fn as_str(self) -> &'static str {
        self.entry().1
    }

    /// Number of ids in the dictionary (valid ids are `0..id_count()`).
    pub fn id_count(self) -> u32 {
        self.entry().3
    }

    /// Data bits per side, without the black border.
    pub fn data_bits(self) -> usize {
        self.entry().4
    }

    pub(crate) fn opencv_dictionary(self) -> D {
        self.entry().2
    }
}

impl std::fmt::Display for MarkerFamily {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for MarkerFamily {
    type Err = VisionError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let lower = s.trim().to_ascii_lowercase();
        FAMILIES
            .iter()
            .find(|f| f.1 == lower)
            .map(|f| f.0)
            .ok_or_else(|| VisionError::UnknownFamily {
                name: s.to_string(),
                expected: FAMILIES.iter().map(|f| f.1).collect::<Vec<_>>().join(", "),
            })
    }
}

/// What finds and decodes the markers (`[marker] detector`); the sub-pixel corners, the
/// pose and the tracking are markhold's either way.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum MarkerDetector {
    /// OpenCV 4.6's aruco `detectMarkers` (every family).
    #[default]
    #[serde(rename = "opencv")]
    OpenCv,
    /// AprilTag 3's own detector (Debian's libapriltag; the cargo feature `apriltag3`):
    /// the AprilTag families only. On small, distant tags it finds more than OpenCV
    /// (docs/design/vision.md).
    #[serde(rename = "apriltag3")]
    AprilTag3,
}

impl MarkerDetector {
    /// The site-file name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::OpenCv => "opencv",
            Self::AprilTag3 => "apriltag3",
        }
    }

    /// Whether this build's detector decodes `family`.
    pub fn supports(self, family: MarkerFamily) -> bool {
        match self {
            Self::OpenCv => true,
            Self::AprilTag3 => {
                cfg!(feature = "apriltag3")
                    && matches!(
                        family,
                        F::AprilTag36h11 | F::AprilTag36h10 | F::AprilTag25h9 | F::AprilTag16h5
                    )
            }
        }
    }

    /// The error for a detector this build cannot use for `family`.
    pub(crate) fn unavailable_for(self, family: MarkerFamily) -> ConfigError {
        let expected = if cfg!(feature = "apriltag3") {
            format!("\"opencv\" for {family}: AprilTag 3 decodes apriltag_36h11, apriltag_36h10, apriltag_25h9 and apriltag_16h5")
        } else {
            "\"opencv\": this markhold is built without AprilTag 3 (cargo feature apriltag3, which needs Debian's libapriltag-dev)".to_string()
        };
        ConfigError::new("marker.detector", format!("\"{self}\""), expected)
    }
}

impl std::fmt::Display for MarkerDetector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The most markers a map holds (the origin marker included): bounds the work of a frame
/// and the buffers sized at start-up.
pub const MAX_MAP_MARKERS: usize = 32;

/// The `[marker]` section: the marker the station is held on (the origin of the site
/// frame) and, optionally, the other markers of the site (`[[marker.map]]`), all of one
/// dictionary. The site frame is the origin marker's frame: x right, y up as printed, z
/// out of its face, origin at its centre (docs/frames.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerConfig {
    pub family: MarkerFamily,
    /// Id of the origin marker.
    pub id: u32,
    /// Side of the origin marker's black square (outer edge of the black border), metres.
    pub size_m: f64,
    /// The site's other markers, each placed in the site frame. Empty: a map of one.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub map: Vec<MapMarker>,
    /// A name for the flat surface the origin marker is on: `markhold map` reports
    /// whether the markers of each named plane come out coplanar.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<String>,
    /// What finds and decodes the markers: `"opencv"` (the default) or `"apriltag3"`.
    #[serde(default, skip_serializing_if = "is_default_detector")]
    pub detector: MarkerDetector,
}

fn is_default_detector(d: &MarkerDetector) -> bool {
    *d == MarkerDetector::default()
}

/// One `[[marker.map]]` entry: a marker of the site placed in the site frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapMarker {
    pub id: u32,
    /// Side of the black square, metres.
    pub size_m: f64,
    /// The marker's centre in the site frame (x right, y up, z out of the origin
    /// marker's face), metres.
    #[serde(deserialize_with = "markhold_config::exact_array")]
    pub position_m: [f64; 3],
    /// The marker's orientation in the site frame, degrees: turns about the site's x,
    /// then y, then z axis (fixed axes). `[0, 0, 0]`: printed upright and facing the same
    /// way as the origin marker; `[0, -90, 0]`: on a wall to the right of it, facing
    /// left (toward the origin marker's axis).
    #[serde(default, deserialize_with = "markhold_config::exact_array")]
    pub rpy_deg: [f64; 3],
    /// A name for the flat surface the marker is on (a wall, a panel): `markhold map`
    /// reports whether the markers of each named plane come out coplanar.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<String>,
}

impl MapMarker {
    /// The marker's pose in the site frame.
    pub fn t_site_marker(&self) -> Isometry3<f64> {
        let [r, p, y] = self.rpy_deg.map(f64::to_radians);
        Isometry3::from_parts(
            Translation3::from(Vector3::from(self.position_m)),
            UnitQuaternion::from_euler_angles(r, p, y),
        )
    }
}

/// A marker of the map as the tracker uses it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedMarker {
    pub id: u32,
    pub size_m: f64,
    /// Pose in the site frame (the identity for the origin marker).
    pub t_site_marker: Isometry3<f64>,
}

impl MarkerConfig {
    /// The origin marker alone (a map of one).
    pub fn single(family: MarkerFamily, id: u32, size_m: f64) -> Self {
        Self {
            family,
            id,
            size_m,
            map: Vec::new(),
            plane: None,
            detector: MarkerDetector::default(),
        }
    }

    /// The plane name of each marker of the map, the origin marker first.
    pub fn planes(&self) -> impl Iterator<Item = Option<&str>> + '_ {
        std::iter::once(self.plane.as_deref()).chain(self.map.iter().map(|m| m.plane.as_deref()))
    }

    /// Every marker of the map, the origin marker first.
    pub fn markers(&self) -> impl Iterator<Item = PlacedMarker> + '_ {
        std::iter::once(PlacedMarker {
            id: self.id,
            size_m: self.size_m,
            t_site_marker: Isometry3::identity(),
        })
        .chain(self.map.iter().map(|m| PlacedMarker {
            id: m.id,
            size_m: m.size_m,
            t_site_marker: m.t_site_marker(),
        }))
    }

    /// Number of markers of the map (the origin marker included).
    pub fn len(&self) -> usize {
        1 + self.map.len()
    }

    /// Always false: the origin marker is always there.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Only the origin marker of this map.
    pub fn origin_only(&self) -> Self {
        Self {
            map: Vec::new(),
            ..self.clone()
        }
    }

    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let n = self.family.id_count();
        let in_family = format!("an id of {} in 0..{n}", self.family);
        if !self.detector.supports(self.family) {
            return Err(self.detector.unavailable_for(self.family));
        }
        Checks::new("marker")
            .range("id", self.id, ..n, &in_family)
            .positive("size_m", self.size_m, "a size > 0 in metres")
            .range("map", self.map.len(), ..MAX_MAP_MARKERS, &format!("at most {} markers besides the origin marker", MAX_MAP_MARKERS - 1))
            .done()?;
        for (i, m) in self.map.iter().enumerate() {
            let unique = m.id != self.id && self.map[..i].iter().all(|o| o.id != m.id);
            Checks::new(format!("marker.map[{i}]"))
                .range("id", m.id, ..n, &in_family)
                .check("id", m.id, unique, "an id no other marker of the map has (marker.id and every marker.map id differ)")
                .positive("size_m", m.size_m, "a size > 0 in metres")
                .all("position_m", &m.position_m, -1000.0..=1000.0, "a position in the site frame in metres, each coordinate finite within 1000")
                .all("rpy_deg", &m.rpy_deg, -180.0..=180.0, "angles in degrees within -180..180")
                .done()?;
        }
        Ok(())
    }
}

/// The `[vision]` section: detector, tracking and pose-estimation parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectorConfig {
    /// Smallest adaptive-threshold window, pixels (odd, >= 3).
    pub adaptive_thresh_win_min_px: i32,
    /// Largest adaptive-threshold window, pixels.
    pub adaptive_thresh_win_max_px: i32,
    /// Step between threshold windows, pixels. Each window is one pass over the
    /// searched image: the main cost of a search. A tracked window, where the marker's
    /// size is known, is thresholded once, at a window of about two of its modules
    /// within the smallest and largest.
    pub adaptive_thresh_win_step_px: i32,
    /// Constant subtracted from the local mean in adaptive thresholding, grey levels.
    pub adaptive_thresh_constant: f64,
    /// Smallest marker perimeter as a fraction of the frame's larger side.
    pub min_marker_perimeter_rate: f64,
    /// Largest marker perimeter as a fraction of the frame's larger side.
    pub max_marker_perimeter_rate: f64,
    /// Polygon approximation accuracy as a fraction of the contour's perimeter.
    pub polygonal_approx_accuracy_rate: f64,
    /// Fraction of the dictionary's correctable bits used (0..=1).
    pub error_correction_rate: f64,
    /// Half-size of the sub-pixel corner refinement window, pixels.
    pub subpix_window_px: i32,
    /// Iterations of the sub-pixel refinement.
    pub subpix_max_iterations: i32,
    /// Sub-pixel refinement stops when a corner moves less than this, pixels.
    pub subpix_min_accuracy_px: f64,
    /// RoI tracking: padding on each side of the predicted marker box, as a fraction
    /// of the marker's side in pixels.
    pub track_window_scale: f64,
    /// RoI tracking: extra padding per pixel of predicted inter-frame motion.
    pub track_motion_gain: f64,
    /// RoI tracking: the window is downscaled (by up to 4) so that the marker's side
    /// is about this many pixels, bounding the cost for a close marker.
    pub track_target_side_px: f64,
    /// Full-frame search every this many frames even while tracking (0 = never
    /// unless tracking fails). 300 (10 s at 30 fps): a full search costs several tracked
    /// frames, and at 30 it alone set the loop's latency p99 (measured in
    /// docs/design/loop.md, "Deferred full search").
    pub full_search_period_frames: u32,
    /// The loop sends a frame's command before that frame's full-frame search (when
    /// tracking cannot answer), so the search (its cost: docs/design/loop.md) does not
    /// delay the command; the marker found by it serves from the next frame on. `false`:
    /// search first, then command (one frame sooner after a re-acquisition).
    pub defer_full_search: bool,
    /// Full-frame search on an image downscaled by this factor (1 = full resolution),
    /// followed by a full-resolution RoI search for sub-pixel corners.
    pub full_search_downscale: u32,
    /// When the downscaled full search finds nothing, search again at full
    /// resolution (finds small markers; doubles the cost of frames without one).
    pub full_search_fallback_full_res: bool,
    /// Independent noise added to each corner's edge-fit covariance, pixels per
    /// axis (what the fit residuals cannot see: blur asymmetry, model error).
    pub corner_sigma_floor_px: f64,
    /// Shift of marker edges whose white side clips (all their points), pixels: the
    /// centroid of a clipped step moves towards the dark side by an amount the frame
    /// cannot show. `corner_clip_common_px` is shared by the four sides (the marker
    /// looks smaller), `corner_clip_side_px` each side's own. Added to the pose
    /// covariance, scaled by the fraction of each side's points that clip; the pose is
    /// unchanged. These hold until the marker has been seen with unclipped edge points; from
    /// then on the shift follows the white's over-exposure `r` (its white-to-black
    /// contrast measured unclipped, times the black's grey now, over the clip level):
    /// `corner_clip_gain_px (1 - 1/r)` common, `side/common` of that each side's own
    /// (a gain of 0 keeps the fixed figures).
    pub corner_clip_common_px: f64,
    pub corner_clip_side_px: f64,
    pub corner_clip_gain_px: f64,
    /// Corner noise, pixels per axis, assumed when the edge fit fails and
    /// cv::cornerSubPix corners are used instead.
    pub corner_sigma_px: f64,
    /// The two IPPE solutions are ambiguous when the worse one's reprojection RMS is
    /// within this factor of the better one's; continuity with the previous pose
    /// decides then.
    pub ambiguity_ratio: f64,
    /// A previous pose older than this (frame stamps, seconds) is not used for
    /// continuity or tracking.
    pub track_max_age_s: f64,
    /// Detections whose reprojection RMS exceeds this are rejected, pixels.
    pub max_reproj_rms_px: f64,
    /// A marker of a map whose corners reproject worse than this under the pose of all
    /// the markers in view (RMS, pixels) is an outlier (a wrong id decode, a marker moved
    /// since the map was measured): left out of the pose and counted. Sized for a map
    /// measured by hand to a few millimetres, seen from 1 to 3 m.
    pub map_outlier_rms_px: f64,
    /// OpenCV worker threads (process-wide setting; 0 leaves OpenCV's default).
    pub opencv_threads: i32,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        Self {
            adaptive_thresh_win_min_px: 3,
            adaptive_thresh_win_max_px: 23,
            adaptive_thresh_win_step_px: 10,
            adaptive_thresh_constant: 7.0,
            min_marker_perimeter_rate: 0.03,
            max_marker_perimeter_rate: 4.0,
            polygonal_approx_accuracy_rate: 0.03,
            error_correction_rate: 0.6,
            subpix_window_px: 5,
            subpix_max_iterations: 30,
            subpix_min_accuracy_px: 0.01,
            track_window_scale: 0.75,
            track_motion_gain: 2.0,
            track_target_side_px: 64.0,
            full_search_period_frames: 300,
            defer_full_search: true,
            full_search_downscale: 2,
            full_search_fallback_full_res: true,
            corner_sigma_floor_px: 0.005,
            corner_clip_common_px: 0.06,
            corner_clip_side_px: 0.042,
            corner_clip_gain_px: 0.6,
            corner_sigma_px: 0.3,
            ambiguity_ratio: 3.0,
            track_max_age_s: 0.5,
            max_reproj_rms_px: 3.0,
            map_outlier_rms_px: 8.0,
            opencv_threads: 1,
        }
    }
}

impl DetectorConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let (win_min, win_max) = (
            self.adaptive_thresh_win_min_px,
            self.adaptive_thresh_win_max_px,
        );
        let min_rate = self.min_marker_perimeter_rate;
        let max_rate = self.max_marker_perimeter_rate;
        Checks::new("vision")
            .range("adaptive_thresh_win_min_px", win_min, 3.., "a window >= 3 px")
            .range("adaptive_thresh_win_max_px", win_max, win_min..=255, "a window between adaptive_thresh_win_min_px and 255 px")
            .range("adaptive_thresh_win_step_px", self.adaptive_thresh_win_step_px, 1.., "a step >= 1 px")
            .finite("adaptive_thresh_constant", self.adaptive_thresh_constant, "a finite grey-level offset")
            .range("min_marker_perimeter_rate", min_rate, open(0.0, 4.0), "a rate in (0, 4)")
            .range("max_marker_perimeter_rate", max_rate, open_closed(min_rate, 4.0), "a rate in (min_marker_perimeter_rate, 4]")
            .range("polygonal_approx_accuracy_rate", self.polygonal_approx_accuracy_rate, open(0.0, 0.5), "a rate in (0, 0.5)")
            .range("error_correction_rate", self.error_correction_rate, 0.0..=1.0, "a rate in [0, 1]")
            .range("subpix_window_px", self.subpix_window_px, 1..=32, "a half-window in 1..=32 px")
            .range("subpix_max_iterations", self.subpix_max_iterations, 1..=1000, "a count in 1..=1000")
            .range("subpix_min_accuracy_px", self.subpix_min_accuracy_px, open(0.0, 1.0), "a distance in (0, 1) px")
            .range("track_window_scale", self.track_window_scale, 0.1..=10.0, "a fraction of the marker side in [0.1, 10]")
            .range("track_motion_gain", self.track_motion_gain, 0.0..=20.0, "a gain in [0, 20]")
            .range("track_target_side_px", self.track_target_side_px, 24.0..=10_000.0, "a marker side in [24, 10000] px")
            .range("full_search_downscale", self.full_search_downscale, 1..=8, "a factor in 1..=8")
            .positive("corner_sigma_px", self.corner_sigma_px, "a standard deviation > 0 px")
            .positive("corner_sigma_floor_px", self.corner_sigma_floor_px, "a standard deviation > 0 px")
            .range("corner_clip_common_px", self.corner_clip_common_px, 0.0..=1.0, "a standard deviation in [0, 1] px")
            .range("corner_clip_side_px", self.corner_clip_side_px, 0.0..=1.0, "a standard deviation in [0, 1] px")
            .range("corner_clip_gain_px", self.corner_clip_gain_px, 0.0..=2.0, "a shift in [0, 2] px")
            .finite_range("ambiguity_ratio", self.ambiguity_ratio, 1.0.., "a ratio >= 1")
            .positive("track_max_age_s", self.track_max_age_s, "a time > 0 s")
            // An infinite RMS bound is allowed: it rejects no detection.
            .range("max_reproj_rms_px", self.max_reproj_rms_px, above(0.0), "an RMS > 0 px")
            .positive("map_outlier_rms_px", self.map_outlier_rms_px, "a finite RMS > 0 px")
            .range("opencv_threads", self.opencv_threads, 0..=64, "a thread count in 0..=64 (0 = OpenCV's default)")
            .done()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_variant_in_table_and_names_round_trip() {
        for f in MarkerFamily::all() {
            assert_eq!(f.entry().0, f);
            let parsed: MarkerFamily = f.as_str().parse().unwrap();
            assert_eq!(parsed, f);
            assert_eq!(f.to_string(), f.as_str());
            let json = serde_json_like(f);
            assert_eq!(json, f.as_str());
        }
        assert_eq!(FAMILIES.len(), MarkerFamily::all().count());
    }

    // serde name of a unit variant, through serde's own serializer of strings.
    fn serde_json_like(f: MarkerFamily) -> String {
        use serde::de::IntoDeserializer;
        let back: MarkerFamily = MarkerFamily::deserialize(IntoDeserializer::<
            serde::de::value::Error,
        >::into_deserializer(f.as_str()))
        .unwrap();
        assert_eq!(back, f);
        back.as_str().to_string()
    }

    #[test]
    fn site_file_sections_parse_and_reject_unknown_keys() {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Site {
            marker: MarkerConfig,
            #[serde(default)]
            vision: DetectorConfig,
        }
        let site: Site = toml::from_str(
            "[marker]\nfamily = \"aruco_5x5_100\"\nid = 42\nsize_m = 0.15\n\
             [vision]\ncorner_sigma_floor_px = 0.01\nfull_search_period_frames = 10\n",
        )
        .unwrap();
        assert_eq!(site.marker.family, MarkerFamily::Aruco5x5_100);
        assert_eq!(site.marker.id, 42);
        assert_eq!(site.vision.corner_sigma_floor_px, 0.01);
        assert_eq!(site.vision.full_search_period_frames, 10);
        // Unset keys keep their defaults.
        assert_eq!(
            site.vision.subpix_window_px,
            DetectorConfig::default().subpix_window_px
        );
        let e = toml::from_str::<Site>(
            "[marker]\nfamily = \"apriltag_36h11\"\nid = 1\nsize_m = 0.1\n[vision]\nsigma = 1\n",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("sigma"), "{e}");
        let e = toml::from_str::<Site>("[marker]\nfamily = \"qr\"\nid = 1\nsize_m = 0.1\n")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("qr"), "{e}");
    }

    #[test]
    fn unknown_family_lists_choices() {
        let e = "apriltag_99"
            .parse::<MarkerFamily>()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("apriltag_99") && e.contains("aruco_4x4_50"),
            "{e}"
        );
    }

    #[test]
    fn marker_validate_names_key_and_value() {
        let m = MarkerConfig::single(MarkerFamily::Aruco4x4_50, 50, 0.2);
        let e = m.validate().unwrap_err().to_string();
        assert!(e.contains("marker.id") && e.contains("50"), "{e}");
        let m = MarkerConfig::single(MarkerFamily::AprilTag36h11, 586, -1.0);
        let e = m.validate().unwrap_err().to_string();
        assert!(e.contains("marker.size_m") && e.contains("-1"), "{e}");
        let ok = MarkerConfig { size_m: 0.15, ..m };
        ok.validate().unwrap();
    }

    #[test]
    fn marker_detector_parses_and_is_checked_against_the_family() {
        let m: MarkerConfig = toml::from_str(
            "family = \"apriltag_25h9\"\nid = 3\nsize_m = 0.1\ndetector = \"apriltag3\"\n",
        )
        .unwrap();
        assert_eq!(m.detector, MarkerDetector::AprilTag3);
        let default: MarkerConfig =
            toml::from_str("family = \"aruco_4x4_50\"\nid = 3\nsize_m = 0.1\n").unwrap();
        assert_eq!(default.detector, MarkerDetector::OpenCv);
        default.validate().unwrap();
        let e = toml::from_str::<MarkerConfig>(
            "family = \"apriltag_25h9\"\nid = 3\nsize_m = 0.1\ndetector = \"zbar\"\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("zbar") && e.contains("apriltag3"), "{e}");
        // This build decodes AprilTag families with AprilTag 3 exactly when it has the
        // feature; ArUco dictionaries never.
        assert_eq!(m.validate().is_ok(), cfg!(feature = "apriltag3"));
        let aruco = MarkerConfig {
            family: MarkerFamily::Aruco4x4_50,
            ..m
        };
        let e = aruco.validate().unwrap_err().to_string();
        assert!(
            e.starts_with("marker.detector = \"apriltag3\": expected \"opencv\""),
            "{e}"
        );
    }

    #[test]
    fn detector_validate_names_key() {
        DetectorConfig::default().validate().unwrap();
        let c = DetectorConfig {
            corner_sigma_px: 0.0,
            ..Default::default()
        };
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("vision.corner_sigma_px"), "{e}");
        let c = DetectorConfig {
            adaptive_thresh_win_max_px: 2,
            ..Default::default()
        };
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("vision.adaptive_thresh_win_max_px = 2"), "{e}");
    }
}
