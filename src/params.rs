//! Dive-site parameter files: one TOML file per site, each section owned by the crate
//! that uses it. Loading validates everything once; errors name the file, line, key,
//! value and what was expected, and map to exit code 78 (EX_CONFIG).

// Validation is written as `!(lo <= v && v <= hi)` on purpose: NaN fails every
// comparison, so the negated form rejects it with the same message.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::path::{Path, PathBuf};

use markhold_autopilot::{ControllerConfig, LinkConfig, StationConfig};
use markhold_exposure::{ExposureConfig, ExposureLimits};
use markhold_hil::camera::SensorConfig;
use markhold_hil::scene::{LightingConfig, WaterConfig};
use markhold_hil::VehicleConfig;
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerConfig};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Exit code for a bad configuration (sysexits EX_CONFIG).
pub const EXIT_CONFIG: i32 = 78;

#[derive(Debug, thiserror::Error)]
pub enum ParamsError {
    #[error("{file}: cannot read: {source}")]
    Read {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}:{line}: {key}{message}")]
    Parse {
        file: PathBuf,
        line: usize,
        /// `section.key = value: ` of the offending line, when the error points at one.
        key: String,
        message: String,
    },
    #[error("{file}:{line}: {key} = {value}: expected {expected}")]
    Invalid {
        file: PathBuf,
        line: usize,
        key: String,
        value: String,
        expected: String,
    },
    #[error("{file}:{line}: {key} = {value}: {reason}")]
    ReferencedFile {
        file: PathBuf,
        line: usize,
        key: String,
        value: String,
        reason: String,
    },
}

/// `[site]`: what the dive site is.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SiteInfo {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// Depth of the marker centre below the surface, metres.
    pub depth_m: f64,
}

/// `[camera]`: the physical camera, shared by exposure (limits), vision (calibration)
/// and hil (rendering).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    pub width_px: u32,
    pub height_px: u32,
    pub fps: f64,
    pub exposure_min_us: f64,
    pub exposure_max_us: f64,
    /// Exposure at start-up, microseconds.
    #[serde(default = "default_initial_exposure")]
    pub initial_exposure_us: f64,
    #[serde(default)]
    pub gain_db: f64,
    /// Frames between commanding an exposure and the first frame exposed with it.
    #[serde(default = "default_delay")]
    pub actuation_delay_frames: u32,
    /// OpenCV or ROS calibration YAML, relative to the site file. Overrides the inline
    /// intrinsics below.
    #[serde(default)]
    pub calibration_file: Option<PathBuf>,
    #[serde(default)]
    pub fx_px: Option<f64>,
    #[serde(default)]
    pub fy_px: Option<f64>,
    #[serde(default)]
    pub cx_px: Option<f64>,
    #[serde(default)]
    pub cy_px: Option<f64>,
    /// k1 k2 p1 p2 k3.
    #[serde(default)]
    pub distortion: [f64; 5],
    /// Camera position in the vehicle body frame (FRD), metres.
    #[serde(default = "default_mount_position")]
    pub mount_position_m: [f64; 3],
    /// Roll, pitch, yaw of the camera relative to a forward-looking mount, degrees
    /// (pitch -15 tilts it 15 degrees down).
    #[serde(default)]
    pub mount_rpy_deg: [f64; 3],
    /// Sensor noise and sensitivity (used by the HIL camera).
    #[serde(default)]
    pub sensor: SensorConfig,
}

fn default_initial_exposure() -> f64 {
    2000.0
}
fn default_delay() -> u32 {
    1
}
fn default_mount_position() -> [f64; 3] {
    [0.2, 0.0, 0.0]
}

/// A whole site file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Site {
    pub site: SiteInfo,
    #[serde(default)]
    pub water: WaterConfig,
    #[serde(default)]
    pub lighting: LightingConfig,
    pub marker: MarkerConfig,
    #[serde(default)]
    pub vision: DetectorConfig,
    pub camera: CameraSection,
    #[serde(default)]
    pub exposure: ExposureConfig,
    #[serde(default)]
    pub station: StationConfig,
    #[serde(default)]
    pub controller: ControllerConfig,
    #[serde(default)]
    pub link: LinkConfig,
    #[serde(default)]
    pub vehicle: VehicleConfig,
}

/// A validated site with what was derived from it.
#[derive(Debug, Clone)]
pub struct LoadedSite {
    pub path: PathBuf,
    pub site: Site,
    pub calibration: CameraCalibration,
}

impl LoadedSite {
    pub fn limits(&self) -> ExposureLimits {
        ExposureLimits {
            min_us: self.site.camera.exposure_min_us,
            max_us: self.site.camera.exposure_max_us,
            fps: self.site.camera.fps,
        }
    }

    /// Camera pose in the vehicle body frame.
    pub fn t_vehicle_cam(&self) -> Isometry3<f64> {
        t_vehicle_cam(&self.site.camera)
    }

    /// HIL world: the marker centre at NED (0, 0, depth), its face toward south
    /// (docs/frames.md).
    pub fn t_world_marker(&self) -> Isometry3<f64> {
        t_world_marker(self.site.site.depth_m)
    }
}

pub fn t_world_marker(depth_m: f64) -> Isometry3<f64> {
    // Columns: x_m = east, y_m = up, z_m = south, in NED.
    let r = Matrix3::new(0.0, 0.0, -1.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    Isometry3::from_parts(
        Translation3::new(0.0, 0.0, depth_m),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
    )
}

pub fn t_vehicle_cam(cam: &CameraSection) -> Isometry3<f64> {
    let [r, p, y] = cam.mount_rpy_deg.map(f64::to_radians);
    let tilt = Rotation3::from_euler_angles(r, p, y);
    // Forward-looking base: x_c = y_b, y_c = z_b, z_c = x_b.
    let base =
        Rotation3::from_matrix_unchecked(Matrix3::new(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0));
    let rot = UnitQuaternion::from_rotation_matrix(&(tilt * base));
    Isometry3::from_parts(Vector3::from(cam.mount_position_m).into(), rot)
}

/// Line (1-based) of `key` inside `[section]` (or `[section.sub]`) of a TOML text, for
/// messages about values that parsed but are out of range. Falls back to the section
/// header, then to line 1.
pub fn line_of_key(text: &str, dotted: &str) -> usize {
    let parts: Vec<&str> = dotted.split('.').collect();
    let (table, key) = match parts.split_last() {
        Some((k, t)) => (t.join("."), *k),
        None => (String::new(), dotted),
    };
    let mut current = String::new();
    let mut header_line = None;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.starts_with('[') {
            current = line
                .trim_matches(|c| c == '[' || c == ']')
                .trim()
                .to_string();
            if current == table {
                header_line = Some(i + 1);
            }
            continue;
        }
        if current == table {
            if let Some((k, _)) = line.split_once('=') {
                if k.trim() == key {
                    return i + 1;
                }
            }
        }
    }
    header_line.unwrap_or(1)
}

/// The dotted key and raw value of a `key = value` line (1-based), with the table it is in.
pub fn key_at_line(text: &str, line: usize) -> Option<(String, String)> {
    let mut table = String::new();
    for (i, raw) in text.lines().enumerate() {
        let l = raw.trim();
        if l.starts_with('[') {
            table = l.trim_matches(|c| c == '[' || c == ']').trim().to_string();
        }
        if i + 1 == line {
            let (k, v) = l.split_once('=')?;
            let v = v.split(" #").next().unwrap_or(v).trim();
            let k = k.trim();
            let key = if table.is_empty() {
                k.to_string()
            } else {
                format!("{table}.{k}")
            };
            return Some((key, v.to_string()));
        }
    }
    None
}

fn line_of_offset(text: &str, offset: usize) -> usize {
    text[..offset.min(text.len())].matches('\n').count() + 1
}

/// Split a crate's "key = value: expected ..." message into its parts.
fn invalid_from(
    file: &Path,
    text: &str,
    section: &str,
    key: String,
    value: String,
    expected: String,
) -> ParamsError {
    let key = if section.is_empty() || key.starts_with(&format!("{section}.")) {
        key
    } else {
        format!("{section}.{key}")
    };
    ParamsError::Invalid {
        file: file.to_path_buf(),
        line: line_of_key(text, &key),
        key,
        value,
        expected,
    }
}

/// Read, parse and validate a site file.
pub fn load(path: &Path) -> Result<LoadedSite, ParamsError> {
    let text = std::fs::read_to_string(path).map_err(|source| ParamsError::Read {
        file: path.to_path_buf(),
        source,
    })?;
    parse(path, &text)
}

/// Parse and validate site text read from `path` (relative files resolve against it).
pub fn parse(path: &Path, text: &str) -> Result<LoadedSite, ParamsError> {
    let mut site: Site = toml::from_str(text).map_err(|e| {
        let line = e.span().map(|s| line_of_offset(text, s.start)).unwrap_or(1);
        ParamsError::Parse {
            file: path.to_path_buf(),
            line,
            key: key_at_line(text, line)
                .map(|(k, v)| format!("{k} = {v}: "))
                .unwrap_or_default(),
            message: e.message().trim().to_string(),
        }
    })?;
    let inv = |section: &str, key: String, value: String, expected: String| {
        invalid_from(path, text, section, key, value, expected)
    };
    validate_site(&site).map_err(|(k, v, e)| inv("", k, v, e))?;
    crate::params_validate::validate_sections(&site)
        .map_err(|(section, k, v, e)| inv(section, k, v, e))?;

    let base = path.parent().unwrap_or(Path::new("."));
    if let Some(rel) = &site.camera.calibration_file {
        let full = base.join(rel);
        site.camera.calibration_file = Some(full.clone());
    }
    let calibration = calibration_of(path, text, &site.camera)?;
    Ok(LoadedSite {
        path: path.to_path_buf(),
        site,
        calibration,
    })
}

fn calibration_of(
    path: &Path,
    text: &str,
    cam: &CameraSection,
) -> Result<CameraCalibration, ParamsError> {
    if let Some(file) = &cam.calibration_file {
        let referenced = |reason: String| ParamsError::ReferencedFile {
            file: path.to_path_buf(),
            line: line_of_key(text, "camera.calibration_file"),
            key: "camera.calibration_file".into(),
            value: file.display().to_string(),
            reason,
        };
        let calib = CameraCalibration::load(file).map_err(|e| referenced(e.to_string()))?;
        calib
            .check_resolution(cam.width_px, cam.height_px)
            .map_err(|e| referenced(e.to_string()))?;
        return Ok(calib);
    }
    // Inline intrinsics; a centred principal point and a 62-degree horizontal field of
    // view when left out.
    let fx = cam.fx_px.unwrap_or(cam.width_px as f64 / 1.2);
    Ok(CameraCalibration {
        width: cam.width_px,
        height: cam.height_px,
        fx,
        fy: cam.fy_px.unwrap_or(fx),
        cx: cam.cx_px.unwrap_or(cam.width_px as f64 / 2.0),
        cy: cam.cy_px.unwrap_or(cam.height_px as f64 / 2.0),
        dist: cam.distortion.to_vec(),
    })
}

type Bad = (String, String, String);

fn bad(key: &str, value: impl std::fmt::Display, expected: &str) -> Bad {
    (key.to_string(), value.to_string(), expected.to_string())
}

fn validate_site(site: &Site) -> Result<(), Bad> {
    let s = &site.site;
    if s.name.trim().is_empty() {
        return Err(bad("site.name", "\"\"", "a non-empty name"));
    }
    if !(s.depth_m >= 0.0 && s.depth_m <= 300.0) {
        return Err(bad("site.depth_m", s.depth_m, "a depth in metres, 0..300"));
    }
    let c = &site.camera;
    if !(16..=8192).contains(&c.width_px) {
        return Err(bad("camera.width_px", c.width_px, "16..8192 pixels"));
    }
    if !(16..=8192).contains(&c.height_px) {
        return Err(bad("camera.height_px", c.height_px, "16..8192 pixels"));
    }
    if !(c.fps > 0.0 && c.fps <= 500.0) {
        return Err(bad("camera.fps", c.fps, "frames per second in (0, 500]"));
    }
    if !(c.exposure_min_us > 0.0) {
        return Err(bad(
            "camera.exposure_min_us",
            c.exposure_min_us,
            "a positive exposure in microseconds",
        ));
    }
    if !(c.exposure_max_us > c.exposure_min_us) {
        return Err(bad(
            "camera.exposure_max_us",
            c.exposure_max_us,
            "microseconds, more than exposure_min_us",
        ));
    }
    if !(c.initial_exposure_us > 0.0) {
        return Err(bad(
            "camera.initial_exposure_us",
            c.initial_exposure_us,
            "a positive exposure in microseconds",
        ));
    }
    if !(-20.0..=48.0).contains(&c.gain_db) {
        return Err(bad("camera.gain_db", c.gain_db, "a gain in dB, -20..48"));
    }
    if c.actuation_delay_frames > 10 {
        return Err(bad(
            "camera.actuation_delay_frames",
            c.actuation_delay_frames,
            "0..10 frames",
        ));
    }
    for (k, v) in [
        ("camera.fx_px", c.fx_px),
        ("camera.fy_px", c.fy_px),
        ("camera.cx_px", c.cx_px),
        ("camera.cy_px", c.cy_px),
    ] {
        if let Some(v) = v {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(k, v, "a positive number of pixels"));
            }
        }
    }
    if c.distortion.iter().any(|v| !v.is_finite()) {
        return Err(bad(
            "camera.distortion",
            format!("{:?}", c.distortion),
            "five finite numbers k1 k2 p1 p2 k3",
        ));
    }
    if c.mount_position_m.iter().any(|v| !(v.abs() <= 2.0)) {
        return Err(bad(
            "camera.mount_position_m",
            format!("{:?}", c.mount_position_m),
            "a position on the vehicle, each coordinate within 2 m",
        ));
    }
    if c.mount_rpy_deg.iter().any(|v| !(v.abs() <= 180.0)) {
        return Err(bad(
            "camera.mount_rpy_deg",
            format!("{:?}", c.mount_rpy_deg),
            "angles in degrees within -180..180",
        ));
    }
    Ok(())
}
