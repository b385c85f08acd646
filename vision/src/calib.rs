//! Pinhole camera calibration with a lens model ([`DistortionModel`]: OpenCV's
//! plumb_bob and rational models, the equidistant fisheye), read from OpenCV
//! FileStorage YAML or ROS camera_info YAML, and written as OpenCV FileStorage YAML.

use std::fmt::Write as _;

use crate::distortion::DistortionModel;
use crate::yaml::{self, Node};
use crate::VisionError;
use markhold_config::{open, AsDebug, Checks, ConfigError};
use std::path::{Path, PathBuf};

/// Intrinsics of one camera at one resolution.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraCalibration {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Coefficients of `model` in its file order (plumb_bob: k1 k2 p1 p2 [k3]; empty
    /// = no distortion).
    pub dist: Vec<f64>,
    /// The lens model of `dist` (plumb_bob when a file or a recording does not say).
    #[serde(default)]
    pub model: DistortionModel,
}

/// Where a site's camera intrinsics come from (`[camera] calibration_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CalibrationSource {
    /// Not this camera's: values to start from (a nominal field of view).
    Placeholder,
    /// Calibrated in air: under water the port's refraction changes the focal length
    /// (about 1.33x behind a flat port) and the distortion.
    InAir,
    /// Calibrated in the water, through the port, at the working distance.
    InWater,
    /// The simulator's camera: `markhold hil` renders with exactly these intrinsics
    /// (placeholders for a real camera).
    Simulated,
}

impl CalibrationSource {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Placeholder => "placeholder",
            Self::InAir => "in-air",
            Self::InWater => "in-water",
            Self::Simulated => "simulated",
        }
    }
}

/// What a calibration file says of where it was made, besides the intrinsics (keys that
/// `markhold calibrate` writes; other tools' files have none of them).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CalibrationNotes {
    /// `calibration_medium`: `water` or `air`.
    pub medium: Option<String>,
    /// `working_distance_m`: the nearest and farthest target distance of the views.
    pub working_distance_m: Option<[f64; 2]>,
    /// `avg_reprojection_error`, pixels (OpenCV's samples write it too).
    pub reprojection_rms_px: Option<f64>,
}

impl CameraCalibration {
    /// A distortion-free camera.
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            dist: Vec::new(),
            model: DistortionModel::PlumbBob,
        }
    }

    /// Check the values; the error names the field (`calibration.<field>`).
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let (w, h) = (self.width, self.height);
        let inside = "a principal point inside the image";
        let lengths = self.model.allowed_lengths();
        let dist_ok =
            lengths.contains(&self.dist.len()) && self.dist.iter().all(|k| k.is_finite());
        let dist_expected = format!(
            "{} finite coefficients ({}) for the {} model",
            lengths.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(", "),
            self.model.coefficient_names().join(" "),
            self.model
        );
        Checks::new("calibration")
            .check("image_width/image_height", format!("{w}x{h}"), w > 0 && h > 0, "a non-empty resolution")
            .positive("fx", self.fx, "a focal length > 0 px")
            .positive("fy", self.fy, "a focal length > 0 px")
            .range("cx", self.cx, open(0.0, w as f64), inside)
            .range("cy", self.cy, open(0.0, h as f64), inside)
            .check("dist", AsDebug(&self.dist), dist_ok, &dist_expected)
            .done()
    }

    /// Error unless the calibration was made at `width` x `height`.
    pub fn check_resolution(&self, width: u32, height: u32) -> Result<(), VisionError> {
        if self.width != width || self.height != height {
            return Err(VisionError::FrameSize {
                what: "the camera calibration (image_width/image_height)",
                width,
                height,
                expected_width: self.width,
                expected_height: self.height,
            });
        }
        Ok(())
    }

    /// Read an OpenCV FileStorage YAML (`camera_matrix`, `distortion_coefficients`,
    /// `image_width`, `image_height`) or a ROS camera_info YAML file. Errors name the
    /// file and the field.
    pub fn load(path: &Path) -> Result<Self, VisionError> {
        let text = markhold_config::read_regular(path, markhold_config::MAX_CONFIG_FILE_BYTES)
            .map_err(|source| VisionError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        Self::parse(&text, path)
    }

    /// Read a calibration file and check it was made at `width` x `height`; a mismatch
    /// names the file and the field.
    pub fn load_for(path: &Path, width: u32, height: u32) -> Result<Self, VisionError> {
        let c = Self::load(path)?;
        let err = |field: &str, got: u32, want: u32| VisionError::Calibration {
            path: path.to_path_buf(),
            field: field.to_string(),
            reason: format!("calibrated at {got} but the camera delivers {want}"),
        };
        if c.width != width {
            return Err(err("image_width", c.width, width));
        }
        if c.height != height {
            return Err(err("image_height", c.height, height));
        }
        Ok(c)
    }

    /// Parse the text of a calibration file (`path` only names it in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Self, VisionError> {
        let p = path.to_path_buf();
        let root = yaml::parse(text).map_err(|e| VisionError::Calibration {
            path: p.clone(),
            field: format!("line {}", e.line),
            reason: e.reason,
        })?;
        let f = Fields {
            path: p,
            root: &root,
        };

        let (width, height) = f.resolution()?;
        let (k_name, k) = f.matrix(&["camera_matrix", "cameraMatrix", "K"], Some((3, 3)))?;
        let (d_name, dist) = f.matrix(
            &["distortion_coefficients", "dist_coeffs", "distCoeffs", "D"],
            None,
        )?;
        let model = match f.scalar_opt("distortion_model") {
            Some(name) => name.parse::<DistortionModel>().map_err(|_| {
                f.err(
                    "distortion_model",
                    format!(
                        "'{name}' is not supported (plumb_bob: k1 k2 p1 p2 k3, \
                         rational_polynomial: k1 k2 p1 p2 k3 k4 k5 k6, equidistant: k1 k2 k3 k4)"
                    ),
                )
            })?,
            // OpenCV FileStorage names no model: 8 or more coefficients are the rational
            // model's (calibrateCamera with CALIB_RATIONAL_MODEL).
            None if dist.len() >= 8 => DistortionModel::Rational,
            None => DistortionModel::PlumbBob,
        };
        // Beyond the model's own coefficients (OpenCV's thin-prism and tilt terms, which
        // we do not model) only zeros are accepted.
        let mut dist = dist;
        let keep = match model {
            DistortionModel::PlumbBob => 5,
            DistortionModel::Rational => 8,
            DistortionModel::Equidistant => 4,
        };
        if !model.allowed_lengths().contains(&dist.len()) {
            let short = dist.len() < 4;
            if short || dist[keep.min(dist.len())..].iter().any(|v| *v != 0.0) {
                return Err(f.err(
                    &d_name,
                    format!(
                        "{} coefficients; the {model} model has {} (higher terms must be 0)",
                        dist.len(),
                        model.coefficient_names().join(" ")
                    ),
                ));
            }
            dist.resize(keep, 0.0);
        }
        let skew = k[1];
        if skew.abs() > 1e-9 * k[0].abs().max(1.0) || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 {
            return Err(f.err(
                &k_name,
                format!("not an upper-triangular zero-skew camera matrix: {k:?}"),
            ));
        }
        if (k[8] - 1.0).abs() > 1e-9 {
            return Err(f.err(&k_name, format!("element (2,2) is {} instead of 1", k[8])));
        }
        let calib = CameraCalibration {
            width,
            height,
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            dist,
            model,
        };
        calib.validate().map_err(|e| {
            let field = match e.key.trim_start_matches("calibration.") {
                "dist" => d_name.clone(),
                "image_width/image_height" => "image_width".to_string(),
                other => format!("{k_name} ({other})"),
            };
            f.err(&field, format!("{}: expected {}", e.value, e.expected))
        })?;
        Ok(calib)
    }
}

impl CameraCalibration {
    /// What the text of a calibration file says of where it was made (absent or
    /// malformed keys: `None`).
    pub fn parse_notes(text: &str) -> CalibrationNotes {
        let Ok(root) = yaml::parse(text) else {
            return CalibrationNotes::default();
        };
        let scalar = |k: &str| match root.get(k) {
            Some(Node::Scalar(s)) => Some(s.trim().trim_matches('"').to_string()),
            _ => None,
        };
        let working_distance_m = match root.get("working_distance_m") {
            Some(Node::Seq(v)) if v.len() == 2 => {
                let a = v[0].trim().parse::<f64>().ok();
                let b = v[1].trim().parse::<f64>().ok();
                a.zip(b).map(|(a, b)| [a, b])
            }
            _ => None,
        };
        CalibrationNotes {
            medium: scalar("calibration_medium"),
            working_distance_m,
            reprojection_rms_px: scalar("avg_reprojection_error").and_then(|s| s.parse().ok()),
        }
    }

    /// [`Self::parse_notes`] of a file; errors name the file.
    pub fn load_notes(path: &Path) -> Result<CalibrationNotes, VisionError> {
        let text = markhold_config::read_regular(path, markhold_config::MAX_CONFIG_FILE_BYTES)
            .map_err(|source| VisionError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(Self::parse_notes(&text))
    }

    /// This calibration as OpenCV FileStorage YAML (`cv::FileStorage` reads it, and so
    /// does [`Self::load`]), with a ROS-style `distortion_model` key, `notes`, and
    /// `comments` as `#` lines at the top. Numbers are written to round-trip exactly.
    pub fn to_yaml(&self, notes: &CalibrationNotes, comments: &[String]) -> String {
        let mut s = String::from("%YAML:1.0\n---\n");
        for c in comments {
            for line in c.lines() {
                let _ = writeln!(s, "# {line}");
            }
        }
        let _ = writeln!(s, "image_width: {}", self.width);
        let _ = writeln!(s, "image_height: {}", self.height);
        let matrix = |s: &mut String, name: &str, rows: usize, cols: usize, data: &[f64]| {
            let values: Vec<String> = data.iter().map(|v| format!("{v:?}")).collect();
            let _ = writeln!(
                s,
                "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]",
                values.join(", ")
            );
        };
        matrix(
            &mut s,
            "camera_matrix",
            3,
            3,
            &[self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0],
        );
        let _ = writeln!(s, "distortion_model: {}", self.model);
        matrix(
            &mut s,
            "distortion_coefficients",
            1,
            self.dist.len(),
            &self.dist,
        );
        if let Some(m) = &notes.medium {
            let _ = writeln!(s, "calibration_medium: {m}");
        }
        if let Some([a, b]) = notes.working_distance_m {
            let _ = writeln!(s, "working_distance_m: [ {a:?}, {b:?} ]");
        }
        if let Some(r) = notes.reprojection_rms_px {
            let _ = writeln!(s, "avg_reprojection_error: {r:?}");
        }
        s
    }
}

struct Fields<'a> {
    path: PathBuf,
    root: &'a Node,
}

impl Fields<'_> {
    fn err(&self, field: &str, reason: String) -> VisionError {
        VisionError::Calibration {
            path: self.path.clone(),
            field: field.to_string(),
            reason,
        }
    }

    fn scalar_opt(&self, key: &str) -> Option<&str> {
        match self.root.get(key) {
            Some(Node::Scalar(s)) => Some(s.as_str()),
            _ => None,
        }
    }

    fn uint(&self, node: &Node, field: &str) -> Result<u32, VisionError> {
        match node {
            Node::Scalar(s) => s
                .trim()
                .parse::<u32>()
                .map_err(|_| self.err(field, format!("'{s}' is not a non-negative integer"))),
            _ => Err(self.err(field, "expected an integer".into())),
        }
    }

    fn resolution(&self) -> Result<(u32, u32), VisionError> {
        match (self.root.get("image_width"), self.root.get("image_height")) {
            (Some(w), Some(h)) => Ok((self.uint(w, "image_width")?, self.uint(h, "image_height")?)),
            (Some(_), None) => Err(self.err("image_height", "missing".into())),
            (None, Some(_)) => Err(self.err("image_width", "missing".into())),
            (None, None) => match self.root.get("image_size").or(self.root.get("imageSize")) {
                Some(Node::Seq(v)) if v.len() == 2 => {
                    let w = self.uint(&Node::Scalar(v[0].clone()), "image_size")?;
                    let h = self.uint(&Node::Scalar(v[1].clone()), "image_size")?;
                    Ok((w, h))
                }
                Some(_) => Err(self.err("image_size", "expected [width, height]".into())),
                None => Err(self.err("image_width", "missing".into())),
            },
        }
    }

    /// A matrix under one of `names`: an `!!opencv-matrix` or ROS `{rows, cols,
    /// data}` mapping, or a bare sequence. Returns the name found and the data.
    fn matrix(
        &self,
        names: &[&str],
        shape: Option<(usize, usize)>,
    ) -> Result<(String, Vec<f64>), VisionError> {
        let Some((name, node)) = names
            .iter()
            .find_map(|n| self.root.get(n).map(|node| (n.to_string(), node)))
        else {
            return Err(self.err(names[0], "missing".into()));
        };
        let parse_data = |items: &[String], field: &str| -> Result<Vec<f64>, VisionError> {
            items
                .iter()
                .map(|s| {
                    s.trim()
                        .parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| self.err(field, format!("'{s}' is not a finite number")))
                })
                .collect()
        };
        let (rows, cols, data) = match node {
            Node::Seq(items) => {
                let data = parse_data(items, &name)?;
                let n = data.len();
                match shape {
                    Some((r, c)) => (r, c, data),
                    None => (1, n, data),
                }
            }
            Node::Map(_) => {
                let field = |k: &str| format!("{name}.{k}");
                let rows =
                    node.get("rows")
                        .ok_or_else(|| self.err(&field("rows"), "missing".into()))
                        .and_then(|n| self.uint(n, &field("rows")))? as usize;
                let cols =
                    node.get("cols")
                        .ok_or_else(|| self.err(&field("cols"), "missing".into()))
                        .and_then(|n| self.uint(n, &field("cols")))? as usize;
                if let Some(Node::Scalar(dt)) = node.get("dt") {
                    if dt != "d" && dt != "f" {
                        return Err(self.err(
                            &field("dt"),
                            format!("'{dt}': expected d (double) or f (float)"),
                        ));
                    }
                }
                let data = match node.get("data") {
                    Some(Node::Seq(items)) => parse_data(items, &field("data"))?,
                    Some(_) => return Err(self.err(&field("data"), "expected [v, v, ...]".into())),
                    None => return Err(self.err(&field("data"), "missing".into())),
                };
                (rows, cols, data)
            }
            Node::Scalar(s) => {
                return Err(self.err(&name, format!("expected a matrix, found '{s}'")));
            }
        };
        if rows * cols != data.len() {
            return Err(self.err(
                &format!("{name}.data"),
                format!("{} values for a {rows}x{cols} matrix", data.len()),
            ));
        }
        if let Some((r, c)) = shape {
            if (rows, cols) != (r, c) {
                return Err(self.err(&name, format!("{rows}x{cols}, expected {r}x{c}")));
            }
        } else if rows != 1 && cols != 1 && !data.is_empty() {
            return Err(self.err(&name, format!("{rows}x{cols}, expected a vector")));
        }
        Ok((name, data))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const OPENCV: &str = "%YAML:1.0
---
calibration_time: \"Mon 23 Nov 2026\"
image_width: 1440
image_height: 1080
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1.1e+03, 0., 7.2e+02, 0., 1.105e+03, 5.4e+02, 0., 0.,
       1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.2, 0.05, 1.0e-03, -2.0e-03, 0. ]
avg_reprojection_error: 0.21
";

    const ROS: &str = "image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [500.5, 0, 320.25, 0, 501, 240.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.1, -0.01, 0, 0, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [500, 0, 320, 0, 0, 501, 240, 0, 0, 0, 1, 0]
";

    fn p() -> &'static Path {
        Path::new("cam.yaml")
    }

    #[test]
    fn reads_opencv_yaml() {
        let c = CameraCalibration::parse(OPENCV, p()).unwrap();
        assert_eq!((c.width, c.height), (1440, 1080));
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (1100.0, 1105.0, 720.0, 540.0));
        assert_eq!(c.dist, vec![-0.2, 0.05, 1e-3, -2e-3, 0.0]);
    }

    #[test]
    fn reads_ros_camera_info() {
        let c = CameraCalibration::parse(ROS, p()).unwrap();
        assert_eq!((c.width, c.height), (640, 480));
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (500.5, 501.0, 320.25, 240.5));
        assert_eq!(c.dist, vec![0.1, -0.01, 0.0, 0.0, 0.0]);
    }

    fn err_of(text: &str) -> String {
        CameraCalibration::parse(text, p()).unwrap_err().to_string()
    }

    #[test]
    fn malformed_files_name_file_and_field() {
        let e = err_of(&OPENCV.replace("image_height: 1080\n", ""));
        assert!(
            e.contains("cam.yaml") && e.contains("image_height") && e.contains("missing"),
            "{e}"
        );
        let e = err_of(&OPENCV.replace("1.1e+03, 0., ", "1.1e+03, "));
        assert!(
            e.contains("camera_matrix.data") && e.contains("8 values"),
            "{e}"
        );
        let e = err_of(&OPENCV.replace("5.4e+02, 0., 0.,", "5.4e+02, 0., 0."));
        assert!(
            e.contains("camera_matrix.data") && e.contains("'0. 1.'"),
            "{e}"
        );
        let e = err_of(&OPENCV.replace("-0.2, 0.05", "-0.2, abc"));
        assert!(
            e.contains("distortion_coefficients.data") && e.contains("abc"),
            "{e}"
        );
        let e = err_of(&ROS.replace("plumb_bob", "kannala_brandt8"));
        assert!(
            e.contains("distortion_model") && e.contains("kannala_brandt8"),
            "{e}"
        );
        // A fisheye file with a non-zero fifth coefficient.
        let e = err_of(
            &ROS.replace("plumb_bob", "equidistant")
                .replace("[0.1, -0.01, 0, 0, 0]", "[0.1, -0.01, 0, 0, 0.2]"),
        );
        assert!(
            e.contains("distortion_coefficients") && e.contains("equidistant"),
            "{e}"
        );
        let e = err_of(&ROS.replace("data: [500.5, 0, 320.25", "data: [-500.5, 0, 320.25"));
        assert!(e.contains("camera_matrix (fx)"), "{e}");
        let e = err_of(&ROS.replace("cols: 5\n  data: [0.1", "cols: 5\n  data: [0.1, 0.2, 0.3,"));
        assert!(e.contains("distortion_coefficients.data"), "{e}");
        let e = err_of("image_width: 640\nimage_height: 480\ncamera_matrix: [1, 0\n");
        assert!(e.contains("line 3") && e.contains("cam.yaml"), "{e}");
        let e = err_of(&ROS.replace("image_width: 640", "image_width: wide"));
        assert!(e.contains("image_width") && e.contains("wide"), "{e}");
    }

    #[test]
    fn models_are_read_from_ros_and_opencv_files() {
        let c = CameraCalibration::parse(&ROS.replace("plumb_bob", "equidistant"), p()).unwrap();
        assert_eq!(c.model, DistortionModel::Equidistant);
        assert_eq!(c.dist, vec![0.1, -0.01, 0.0, 0.0]);
        // OpenCV's rational model: 8 coefficients and no model key.
        let eight = OPENCV
            .replace("rows: 5", "rows: 8")
            .replace("-2.0e-03, 0. ]", "-2.0e-03, 0., 0.3, 0.01, 0. ]");
        let c = CameraCalibration::parse(&eight, p()).unwrap();
        assert_eq!(c.model, DistortionModel::Rational);
        assert_eq!(c.dist.len(), 8);
        assert_eq!(c.dist[5], 0.3);
        // 14 coefficients (thin prism and tilt) that are all zero past the eighth.
        let fourteen = OPENCV.replace("rows: 5", "rows: 14").replace(
            "-2.0e-03, 0. ]",
            "-2.0e-03, 0., 0.3, 0.01, 0., 0, 0, 0, 0, 0, 0 ]",
        );
        let c = CameraCalibration::parse(&fourteen, p()).unwrap();
        assert_eq!((c.model, c.dist.len()), (DistortionModel::Rational, 8));
        let e = err_of(&fourteen.replace("0, 0, 0, 0, 0, 0 ]", "0, 0.1, 0, 0, 0, 0 ]"));
        assert!(
            e.contains("14 coefficients") && e.contains("rational_polynomial"),
            "{e}"
        );
    }

    #[test]
    fn written_files_read_back_exactly() {
        let notes = CalibrationNotes {
            medium: Some("water".into()),
            working_distance_m: Some([0.8, 1.6]),
            reprojection_rms_px: Some(0.1823),
        };
        for (model, dist) in [
            (
                DistortionModel::PlumbBob,
                vec![-0.2, 0.05, 1e-3, -2e-3, 0.1 / 3.0],
            ),
            (DistortionModel::PlumbBob, vec![]),
            (
                DistortionModel::Rational,
                vec![0.9, 0.3, 1e-3, -2e-3, 0.01, 0.75, 0.2, 0.02],
            ),
            (
                DistortionModel::Equidistant,
                vec![0.05, -0.02, 0.004, -0.001],
            ),
        ] {
            let c = CameraCalibration {
                dist,
                model,
                ..CameraCalibration::pinhole(1440, 1080, 1100.0 / 3.0, 1105.25, 720.5, 540.125)
            };
            let text = c.to_yaml(&notes, &["made by a test".to_string()]);
            let back = CameraCalibration::parse(&text, p()).unwrap();
            assert_eq!(back, c, "{text}");
            assert_eq!(CameraCalibration::parse_notes(&text), notes, "{text}");
            assert!(
                text.starts_with("%YAML:1.0\n---\n# made by a test\n"),
                "{text}"
            );
        }
        assert_eq!(
            CameraCalibration::parse_notes(OPENCV).reprojection_rms_px,
            Some(0.21)
        );
        assert_eq!(
            CameraCalibration::parse_notes(ROS),
            CalibrationNotes::default()
        );
    }

    #[test]
    fn resolution_mismatch_names_field_and_file() {
        let dir = std::env::temp_dir().join(format!("markhold-calib-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("ros.yaml");
        std::fs::write(&file, ROS).unwrap();
        let c = CameraCalibration::load(&file).unwrap();
        c.check_resolution(640, 480).unwrap();
        let e = c.check_resolution(1280, 480).unwrap_err().to_string();
        assert!(e.contains("1280x480") && e.contains("640x480"), "{e}");
        let e = CameraCalibration::load_for(&file, 640, 512)
            .unwrap_err()
            .to_string();
        assert!(e.contains("ros.yaml") && e.contains("image_height"), "{e}");
        let e = CameraCalibration::load(&dir.join("none.yaml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("none.yaml"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
