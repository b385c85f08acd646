//! Dive-site parameter files: one TOML file per site, each section owned by the crate
//! that uses it. Loading validates everything once; errors name the file, line, key,
//! value and what was expected, and map to exit code 78 (EX_CONFIG).

use std::ops::Range;
use std::path::{Path, PathBuf};

use markhold_autopilot::{ControllerConfig, LinkConfig, StationConfig};
use markhold_config::{above, open_closed, AsDebug, Checks, ConfigError};
use markhold_exposure::{ExposureConfig, ExposureLimits, ResponseModel};
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerConfig};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use toml::de::{DeTable, DeValue};

pub use sim_sections::{LightingConfig, SensorConfig, VehicleConfig, WaterConfig};

/// The simulator's sections, typed and checked by markhold-hil.
#[cfg(feature = "sim")]
mod sim_sections {
    pub use markhold_hil::camera::SensorConfig;
    pub use markhold_hil::scene::{LightingConfig, WaterConfig};
    pub use markhold_hil::VehicleConfig;
}

/// A build without the simulator reads its sections as plain tables: parsed, kept and
/// printed as written, not checked.
#[cfg(not(feature = "sim"))]
mod sim_sections {
    pub type SensorConfig = toml::Table;
    pub type LightingConfig = toml::Table;
    pub type WaterConfig = toml::Table;
    pub type VehicleConfig = toml::Table;
}

/// What `params check` says about the simulator's sections in this build.
#[cfg(feature = "sim")]
pub const SIM_SECTIONS_NOTE: Option<&str> = None;
#[cfg(not(feature = "sim"))]
pub const SIM_SECTIONS_NOTE: Option<&str> = Some(
    "[water], [lighting], [vehicle] and [camera] sensor are not checked: \
     this build has no simulator (cargo feature `sim`)",
);

/// Exit code for a bad configuration (sysexits EX_CONFIG).
pub const EXIT_CONFIG: i32 = 78;

#[derive(Debug, thiserror::Error)]
pub enum ParamsError {
    /// The OS error is in the message and not a `source`, so `{:#}` prints it once.
    #[error("{file}: cannot read: {error}")]
    Read {
        file: PathBuf,
        error: std::io::Error,
    },
    #[error("{file}:{line}:{column}: {key}{message}")]
    Parse {
        file: PathBuf,
        line: usize,
        column: usize,
        /// `section.key = value: ` of the offending line, when the error points at one.
        key: String,
        message: String,
    },
    /// A value out of range, located in its file.
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{file}:{line}:{column}: {key} = {value}: {reason}")]
    ReferencedFile {
        file: PathBuf,
        line: usize,
        column: usize,
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
    /// Where the intrinsics come from: `placeholder`, `in-air`, `in-water` or
    /// `simulated` (`params check` and `run` warn unless `in-water`; unset: unknown).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_source: Option<markhold_vision::CalibrationSource>,
    #[serde(default)]
    pub fx_px: Option<f64>,
    #[serde(default)]
    pub fy_px: Option<f64>,
    #[serde(default)]
    pub cx_px: Option<f64>,
    #[serde(default)]
    pub cy_px: Option<f64>,
    /// k1 k2 p1 p2 k3.
    #[serde(default, deserialize_with = "markhold_config::exact_array")]
    pub distortion: [f64; 5],
    /// Camera position in the vehicle body frame (FRD), metres.
    #[serde(
        default = "default_mount_position",
        deserialize_with = "markhold_config::exact_array"
    )]
    pub mount_position_m: [f64; 3],
    /// Roll, pitch, yaw of the camera relative to a forward-looking mount, degrees
    /// (pitch -15 tilts it 15 degrees down).
    #[serde(default, deserialize_with = "markhold_config::exact_array")]
    pub mount_rpy_deg: [f64; 3],
    /// Sensor noise and sensitivity (used by the HIL camera).
    #[serde(default)]
    pub sensor: SensorConfig,
    /// How exposure reaches a stream camera (`[camera.control]`).
    #[serde(default)]
    pub control: crate::control::ControlConfig,
    /// When a stream camera's exposure is markhold's: `engaged` (default: only while the
    /// pilot has engaged markhold; put back as found otherwise) or `always` (from start
    /// to exit: a camera nobody else watches).
    #[serde(default)]
    pub control_exposure: ControlExposure,
    /// `markhold run` ends after this long without a camera frame (wall seconds; the
    /// vehicle gets neutral input from `controller.vision_stall_s` on).
    #[serde(default = "default_stall_exit")]
    pub stall_exit_s: f64,
    /// The camera response (`linear` by default; `table` or `polynomial` as calibrated
    /// by `markhold response fit`), used by every exposure method that needs one and by
    /// the HIL camera. A table file is relative to the site file.
    #[serde(default)]
    pub response: ResponseModel,
}

/// `[camera] control_exposure`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlExposure {
    /// Only while engaged.
    #[default]
    Engaged,
    /// From start to exit.
    Always,
}

fn default_stall_exit() -> f64 {
    10.0
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
    /// How `--record` stores frames.
    #[serde(default)]
    pub record: crate::record::RecordSection,
    /// Who may open the live view (`--foxglove`).
    #[serde(default)]
    pub live: crate::record::live::LiveSection,
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

    /// The site as a run uses it: defaults filled in, and the camera's intrinsics and
    /// distortion those of the calibration in use (the calibration file's when there is
    /// one, else the inline values or their defaults). Distortion beyond the five
    /// coefficients a site file holds is in [`LoadedSite::calibration`].
    pub fn effective(&self) -> Site {
        let mut s = self.site.clone();
        let c = &self.calibration;
        s.camera.fx_px = Some(c.fx);
        s.camera.fy_px = Some(c.fy);
        s.camera.cx_px = Some(c.cx);
        s.camera.cy_px = Some(c.cy);
        s.camera.distortion = [0.0; 5];
        for (d, v) in s.camera.distortion.iter_mut().zip(&c.dist) {
            *d = *v;
        }
        s
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

/// The site text's keys with their spans, for messages that point at a line.
/// A place in the site file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Position {
    line: usize,
    column: usize,
}

struct Located<'t> {
    text: &'t str,
    doc: DeTable<'t>,
}

impl<'t> Located<'t> {
    /// Parses what it can: a file with a syntax error still locates its other keys.
    fn new(text: &'t str) -> Self {
        let (doc, _) = DeTable::parse_recoverable(text);
        Self {
            text,
            doc: doc.into_inner(),
        }
    }

    /// Line and column (1-based; the column in characters) of a byte offset.
    fn position_of_offset(&self, offset: usize) -> Position {
        let end = offset.min(self.text.len());
        let before = self.text.get(..end).unwrap_or(self.text);
        let line_start = before.rfind('\n').map_or(0, |i| i + 1);
        Position {
            line: before.matches('\n').count() + 1,
            column: before[line_start..].chars().count() + 1,
        }
    }

    /// Where a dotted key such as `camera.sensor.read_noise_e` (also inside an inline
    /// table) or `lighting.vehicle_lamps[1].direction` has its value. A key the file
    /// leaves out is reported at the nearest table that the file has, else at 1:1.
    fn position_of_key(&self, dotted: &str) -> Position {
        let mut table = &self.doc;
        let mut at = Position { line: 1, column: 1 };
        for segment in dotted.split('.') {
            let (name, index) = match segment.split_once('[') {
                Some((n, i)) => (n, i.trim_end_matches(']').parse::<usize>().ok()),
                None => (segment, None),
            };
            let Some((key, value)) = table.iter().find(|(k, _)| k.get_ref() == name) else {
                break;
            };
            at = self.position_of_offset(key.span().start);
            let value = match (value.get_ref(), index) {
                (DeValue::Array(items), Some(i)) => match items.get(i) {
                    Some(item) => item,
                    None => break,
                },
                _ => value,
            };
            match value.get_ref() {
                DeValue::Table(t) => table = t,
                _ => {
                    at = self.position_of_offset(value.span().start);
                    break;
                }
            }
        }
        at
    }

    #[cfg(test)]
    fn line_of_key(&self, dotted: &str) -> usize {
        self.position_of_key(dotted).line
    }

    /// `section.key = value: ` of the innermost non-table value at `offset`, for parse
    /// errors (serde's messages name neither).
    fn key_at(&self, offset: usize) -> Option<String> {
        let mut found = None;
        self.find_at(&self.doc, "", offset, &mut found);
        found.map(|(key, span)| format!("{key} = {}: ", &self.text[span]))
    }

    fn find_at(
        &self,
        table: &DeTable<'t>,
        prefix: &str,
        offset: usize,
        found: &mut Option<(String, Range<usize>)>,
    ) {
        for (key, value) in table {
            let dotted = if prefix.is_empty() {
                key.get_ref().to_string()
            } else {
                format!("{prefix}.{}", key.get_ref())
            };
            let here = key.span().contains(&offset) || value.span().contains(&offset);
            match value.get_ref() {
                DeValue::Table(t) => self.find_at(t, &dotted, offset, found),
                DeValue::Array(items) if items.iter().any(|i| i.get_ref().is_table()) => {
                    for item in items.iter() {
                        if let DeValue::Table(t) = item.get_ref() {
                            self.find_at(t, &dotted, offset, found);
                        }
                    }
                }
                _ if here => *found = Some((dotted, value.span())),
                _ => {}
            }
        }
    }
}

/// The crate error of a section, located in the site file.
fn located(path: &Path, at: &Located<'_>, e: ConfigError) -> ParamsError {
    let p = at.position_of_key(&e.key);
    ParamsError::Config(e.at_column(path, p.line, p.column))
}

/// Read, parse and validate a site file.
pub fn load(path: &Path) -> Result<LoadedSite, ParamsError> {
    let text = markhold_config::read_regular(path, markhold_config::MAX_CONFIG_FILE_BYTES)
        .map_err(|error| ParamsError::Read {
            file: path.to_path_buf(),
            error,
        })?;
    parse(path, &text)
}

/// A regular file of at most `max_bytes` (see [`markhold_config::open_regular`]).
pub fn open_regular(path: &Path, max_bytes: u64) -> std::io::Result<std::fs::File> {
    markhold_config::open_regular(path, max_bytes)
}

/// A command line's `--initial-exposure-us`, checked as the site's
/// `camera.initial_exposure_us` would be (and finite); the error names the flag.
pub fn check_initial_exposure(site: &Site, value: f64) -> Result<(), ParamsError> {
    let mut s = site.clone();
    s.camera.initial_exposure_us = value;
    let flag = "--initial-exposure-us";
    if !value.is_finite() {
        return Err(ConfigError::new(flag, value, "a positive exposure in microseconds").into());
    }
    validate_site(&s).map_err(|mut e| {
        e.key = flag.into();
        ParamsError::Config(e)
    })
}

/// A configuration error found after loading (by a command's own check), located in the
/// site file when the file can still be read.
pub fn locate(path: &Path, e: ConfigError) -> ParamsError {
    match markhold_config::read_regular(path, markhold_config::MAX_CONFIG_FILE_BYTES) {
        Ok(text) => located(path, &Located::new(&text), e),
        Err(_) => ParamsError::Config(e.at(path, 1)),
    }
}

/// Check a site read from elsewhere than a site file (a recording) like a site file.
pub fn check(site: &Site) -> Result<(), ConfigError> {
    validate(site)
}

/// Parse and validate site text read from `path` (relative files resolve against it).
pub fn parse(path: &Path, text: &str) -> Result<LoadedSite, ParamsError> {
    let parsed: Result<Site, _> = toml::from_str(text);
    let at = Located::new(text);
    let mut site = parsed.map_err(|e| {
        let offset = e.span().map(|s| s.start);
        let p = at.position_of_offset(offset.unwrap_or(0));
        ParamsError::Parse {
            file: path.to_path_buf(),
            line: p.line,
            column: p.column,
            key: offset.and_then(|o| at.key_at(o)).unwrap_or_default(),
            message: e.message().trim().to_string(),
        }
    })?;
    validate(&site).map_err(|e| located(path, &at, e))?;

    let base = path.parent().unwrap_or(Path::new("."));
    site.camera.response = site.camera.response.relative_to(base);
    if let ResponseModel::Table { file } = &site.camera.response {
        // Read once here so a missing or malformed table is a config error at start.
        let referenced = referenced_file(path, &at, "camera.response", file);
        site.camera
            .response
            .load()
            .map_err(|e| referenced(e.to_string()))?;
    }
    if let Some(rel) = &site.camera.calibration_file {
        let full = base.join(rel);
        site.camera.calibration_file = Some(full.clone());
    }
    let calibration = calibration_of(path, &at, &site.camera)?;
    // The marker must be in view at the station (docs/frames.md).
    crate::feasibility::check_site(&site, &calibration, None).map_err(|e| located(path, &at, e))?;
    if let Some(rel) = &site.link.signing_key_file {
        // Relative to the site file, like the calibration file; checked here so a
        // missing or malformed key is a config error before anything starts.
        let full = base.join(rel);
        let referenced = referenced_file(path, &at, "link.signing_key_file", rel);
        markhold_config::open_regular(&full, 1024)
            .map_err(|e| referenced(format!("{}: {e}", full.display())))?;
        markhold_autopilot::link::read_key(&full).map_err(|e| referenced(e.to_string()))?;
        // The saved signing timestamp beside the key (absent on a first start).
        let state = markhold_autopilot::signing_clock::state_path(&full);
        markhold_autopilot::signing_clock::read_state(&state)
            .map_err(|e| referenced(e.to_string()))?;
        site.link.signing_key_file = Some(full);
    }
    #[cfg(feature = "sim")]
    if let Some(rel) = &site.vehicle.params_file {
        // The vehicle's ArduSub parameter file, relative to the site file, read here so a
        // bad value is a config error naming the parameter file and its line.
        let full = base.join(rel);
        markhold_hil::endpoint::ArduSubParams::read(&full).map_err(|e| {
            if e.file.is_some() {
                ParamsError::Config(e)
            } else {
                located(path, &at, e)
            }
        })?;
        site.vehicle.params_file = Some(full);
    }
    Ok(LoadedSite {
        path: path.to_path_buf(),
        site,
        calibration,
    })
}

/// Every section of a parsed site, in file order of the usual site file.
fn validate(site: &Site) -> Result<(), ConfigError> {
    validate_site(site)?;
    if site.exposure.response != ResponseModel::Linear {
        return Err(ConfigError::new(
            "exposure.response",
            AsDebug(&site.exposure.response),
            "no response here: the camera response is `[camera] response`",
        ));
    }
    site.camera.response.validate()?;
    validate_sim(site)?;
    site.marker.validate()?;
    validate_marker_sizes(site)?;
    site.vision.validate()?;
    site.exposure.validate()?;
    site.station.validate()?;
    site.controller.validate()?;
    site.link.validate()?;
    site.record.validate()?;
    site.live.validate()
}

/// The largest marker side, metres: what the simulator renders (`hil` refuses more), so
/// a site `params check` passes also runs in `hil`; a real marker is far smaller.
pub const MAX_MARKER_SIZE_M: f64 = 10.0;

#[rustfmt::skip]
fn validate_marker_sizes(site: &Site) -> Result<(), ConfigError> {
    let m = &site.marker;
    let side = "a size in (0, 10] metres";
    Checks::new("marker")
        .range("size_m", m.size_m, open_closed(0.0, MAX_MARKER_SIZE_M), side)
        .done()?;
    for (i, mm) in m.map.iter().enumerate() {
        Checks::new(format!("marker.map[{i}]"))
            .range("size_m", mm.size_m, open_closed(0.0, MAX_MARKER_SIZE_M), side)
            .done()?;
    }
    Ok(())
}

#[cfg(feature = "sim")]
fn validate_sim(site: &Site) -> Result<(), ConfigError> {
    site.water.validate()?;
    site.lighting.validate()?;
    site.vehicle.validate()?;
    site.camera.sensor.validate()
}

/// Without the simulator its sections stay unchecked (see [`SIM_SECTIONS_NOTE`]).
#[cfg(not(feature = "sim"))]
fn validate_sim(_: &Site) -> Result<(), ConfigError> {
    Ok(())
}

/// The error for a file a site key names (`key = value` at its line in `path`) that
/// cannot be used, with the reason.
fn referenced_file(
    path: &Path,
    at: &Located<'_>,
    key: &'static str,
    value: &Path,
) -> impl Fn(String) -> ParamsError {
    let p = at.position_of_key(key);
    let file = path.to_path_buf();
    let value = value.display().to_string();
    move |reason| ParamsError::ReferencedFile {
        file: file.clone(),
        line: p.line,
        column: p.column,
        key: key.into(),
        value: value.clone(),
        reason,
    }
}

fn calibration_of(
    path: &Path,
    at: &Located<'_>,
    cam: &CameraSection,
) -> Result<CameraCalibration, ParamsError> {
    if let Some(file) = &cam.calibration_file {
        let referenced = referenced_file(path, at, "camera.calibration_file", file);
        let calib = CameraCalibration::load(file).map_err(|e| referenced(e.to_string()))?;
        calib
            .check_resolution(cam.width_px, cam.height_px)
            .map_err(|e| referenced(e.to_string()))?;
        return Ok(calib);
    }
    // Inline intrinsics, all four: a guessed focal length would scale every pose.
    let need = |key: &str, v: Option<f64>| {
        v.ok_or_else(|| {
            located(
                path,
                at,
                ConfigError::new(
                    format!("camera.{key}"),
                    "missing",
                    "the camera's intrinsics in pixels (fx_px, fy_px, cx_px, cy_px), \
                     or camera.calibration_file",
                ),
            )
        })
    };
    Ok(CameraCalibration {
        width: cam.width_px,
        height: cam.height_px,
        fx: need("fx_px", cam.fx_px)?,
        fy: need("fy_px", cam.fy_px)?,
        cx: need("cx_px", cam.cx_px)?,
        cy: need("cy_px", cam.cy_px)?,
        dist: cam.distortion.to_vec(),
        model: markhold_vision::DistortionModel::PlumbBob,
    })
}

#[rustfmt::skip]
fn validate_site(site: &Site) -> Result<(), ConfigError> {
    let s = &site.site;
    Checks::new("site")
        .check("name", AsDebug(&s.name), !s.name.trim().is_empty(), "a non-empty name")
        .check("name", AsDebug(&s.name), !s.name.chars().any(char::is_control) && s.name.len() <= 200, "a name of at most 200 characters without control characters (newlines, escapes)")
        .range("depth_m", s.depth_m, 0.0..=300.0, "a depth in metres, 0..300")
        .done()?;
    let c = &site.camera;
    let pixels = "a positive number of pixels";
    let distortion_ok = c.distortion.iter().all(|k| k.is_finite());
    Checks::new("camera")
        .range("width_px", c.width_px, 16..=8192, "16..8192 pixels")
        .range("height_px", c.height_px, 16..=8192, "16..8192 pixels")
        .range("fps", c.fps, open_closed(0.0, 500.0), "frames per second in (0, 500]")
        .range("exposure_min_us", c.exposure_min_us, above(0.0), "a positive exposure in microseconds")
        .range("exposure_max_us", c.exposure_max_us, above(c.exposure_min_us), "microseconds, more than exposure_min_us")
        .range("initial_exposure_us", c.initial_exposure_us, above(0.0), "a positive exposure in microseconds")
        .range("gain_db", c.gain_db, -20.0..=48.0, "a gain in dB, -20..48")
        .range("actuation_delay_frames", c.actuation_delay_frames, ..=10, "0..10 frames")
        .range("stall_exit_s", c.stall_exit_s, 1.0..=3600.0, "seconds without frames before a run ends, 1..3600")
        .opt(c.fx_px, |k, v| k.positive("fx_px", v, pixels))
        .opt(c.fy_px, |k, v| k.positive("fy_px", v, pixels))
        .opt(c.cx_px, |k, v| k.positive("cx_px", v, pixels))
        .opt(c.cy_px, |k, v| k.positive("cy_px", v, pixels))
        .check("distortion", AsDebug(c.distortion), distortion_ok, "five finite numbers k1 k2 p1 p2 k3")
        .all("mount_position_m", &c.mount_position_m, -2.0..=2.0, "a position on the vehicle, each coordinate within 2 m")
        .all("mount_rpy_deg", &c.mount_rpy_deg, -180.0..=180.0, "angles in degrees within -180..180")
        .done()
}

#[cfg(test)]
mod tests {
    use super::*;

    const POOL: &str = include_str!("../../params/pool.toml");

    /// Pool with `line` inserted after the `[camera]` header, and the error of parsing it.
    #[cfg(feature = "sim")]
    fn camera_error(line: &str) -> ParamsError {
        let text = POOL.replacen("[camera]\n", &format!("[camera]\n{line}\n"), 1);
        match parse(Path::new("/sites/pool.toml"), &text) {
            Ok(_) => panic!("`{line}` was accepted"),
            Err(e) => e,
        }
    }

    #[cfg(feature = "sim")]
    fn camera_line() -> usize {
        POOL.lines()
            .position(|l| l == "[camera]")
            .expect("pool has [camera]")
            + 2
    }

    #[test]
    fn missing_intrinsics_are_an_error_not_a_default() {
        for key in ["fx_px", "fy_px", "cx_px", "cy_px"] {
            let text: String = POOL
                .lines()
                .filter(|l| !l.starts_with(key))
                .map(|l| format!("{l}\n"))
                .collect();
            let e = parse(Path::new("/sites/pool.toml"), &text)
                .expect_err(key)
                .to_string();
            assert!(e.contains(&format!("camera.{key}")), "{e}");
        }
    }

    #[test]
    fn pool_is_valid() {
        parse(Path::new("/sites/pool.toml"), POOL).expect("pool.toml");
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_key_inside_an_inline_table_is_reported_at_its_own_line() {
        let e = camera_error("sensor = { read_noise_e = -1.0 }");
        assert_eq!(
            e.to_string(),
            format!(
                "/sites/pool.toml:{}:{}: camera.sensor.read_noise_e = -1: expected a noise in \
                 [0, 1000] electrons",
                camera_line(),
                "sensor = { read_noise_e = ".len() + 1
            )
        );
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_type_error_inside_an_inline_table_names_the_inner_key() {
        let e = camera_error("sensor = { read_noise_e = \"x\" }");
        let ParamsError::Parse { line, key, .. } = e else {
            panic!("not a parse error: {e}");
        };
        assert_eq!(
            (line, key.as_str()),
            (camera_line(), "camera.sensor.read_noise_e = \"x\": ")
        );
    }

    #[test]
    fn a_key_of_a_sub_table_is_reported_at_its_line() {
        let text = format!("{POOL}\n[controller.yaw]\nkp = 0.5\noutput_limit = 1.5\n");
        let e = parse(Path::new("/sites/pool.toml"), &text).expect_err("output_limit 1.5");
        let ParamsError::Config(e) = e else {
            panic!("not a range error: {e}");
        };
        assert_eq!(e.key, "controller.yaw.output_limit");
        assert_eq!(e.line, Some(text.lines().count()));
    }

    /// Pool with `entries` (`[[marker.map]]` tables) appended, and its parse result.
    fn with_map(entries: &str) -> (String, Result<LoadedSite, ParamsError>) {
        let text = format!("{POOL}\n{entries}");
        let r = parse(Path::new("/sites/pool.toml"), &text);
        (text, r)
    }

    /// Line (1-based) of the `n`th line of `text` that starts with `prefix`.
    fn nth_line(text: &str, prefix: &str, n: usize) -> usize {
        text.lines()
            .enumerate()
            .filter(|(_, l)| l.starts_with(prefix))
            .nth(n)
            .map(|(i, _)| i + 1)
            .expect("line")
    }

    const RIGHT: &str = "[[marker.map]]\nid = 1\nsize_m = 0.1\nposition_m = [0.3, 0.0, 0.0]\n";

    #[test]
    fn a_marker_map_loads_with_its_poses() {
        let (_, r) = with_map(&format!(
            "{RIGHT}[[marker.map]]\nid = 2\nsize_m = 0.2\nposition_m = [-0.4, 0.1, 0.05]\n\
             rpy_deg = [0.0, 90.0, 0.0]\n"
        ));
        let site = r.expect("a valid map");
        let m = &site.site.marker;
        assert_eq!(m.len(), 3);
        let placed: Vec<_> = m.markers().collect();
        assert_eq!(placed[0].t_site_marker, Isometry3::identity());
        assert_eq!((placed[1].id, placed[1].size_m), (1, 0.1));
        // Turned 90 degrees about the site's y (up): its face (z) points along site +x.
        let z = placed[2].t_site_marker.rotation * Vector3::z();
        assert!((z - Vector3::x()).norm() < 1e-12, "{z}");
        assert_eq!(
            placed[2].t_site_marker.translation.vector,
            Vector3::new(-0.4, 0.1, 0.05)
        );
        // Printed back as written (what `params check` shows).
        let text = toml::to_string_pretty(&site.effective()).expect("toml");
        assert!(
            text.contains("[[marker.map]]") && text.contains("rpy_deg"),
            "{text}"
        );
        // A map of one prints no map.
        let pool = parse(Path::new("/sites/pool.toml"), POOL).expect("pool");
        let text = toml::to_string_pretty(&pool.effective()).expect("toml");
        assert!(!text.contains("marker.map"), "{text}");
    }

    /// A bad map is refused with file, line, key and value.
    #[test]
    fn a_bad_marker_map_names_file_line_key_and_value() {
        let cases: [(&str, &str, usize, &str, &str); 6] = [
            // A second marker with the origin's id.
            (
                "[[marker.map]]\nid = 0\nsize_m = 0.1\nposition_m = [0.3, 0.0, 0.0]\n",
                "id = ",
                0,
                "marker.map[0].id = 0",
                "an id no other marker of the map has",
            ),
            // Two map markers with one id: the second is reported.
            (
                "[[marker.map]]\nid = 1\nsize_m = 0.1\nposition_m = [0.3, 0.0, 0.0]\n\
                 [[marker.map]]\nid = 1\nsize_m = 0.1\nposition_m = [0.6, 0.0, 0.0]\n",
                "id = ",
                1,
                "marker.map[1].id = 1",
                "an id no other marker",
            ),
            (
                "[[marker.map]]\nid = 587\nsize_m = 0.1\nposition_m = [0.3, 0.0, 0.0]\n",
                "id = ",
                0,
                "marker.map[0].id = 587",
                "an id of apriltag_36h11 in 0..587",
            ),
            (
                "[[marker.map]]\nid = 1\nsize_m = 0.0\nposition_m = [0.3, 0.0, 0.0]\n",
                "size_m = 0.0",
                0,
                "marker.map[0].size_m = 0",
                "a size > 0 in metres",
            ),
            (
                "[[marker.map]]\nid = 1\nsize_m = 0.1\nposition_m = [nan, 0.0, 0.0]\n",
                "position_m = [nan",
                0,
                "marker.map[0].position_m = [NaN, 0.0, 0.0]",
                "a position in the site frame",
            ),
            (
                "[[marker.map]]\nid = 1\nsize_m = 0.1\nposition_m = [0.3, 0.0, 0.0]\n\
                 rpy_deg = [0.0, 400.0, 0.0]\n",
                "rpy_deg",
                0,
                "marker.map[0].rpy_deg = [0.0, 400.0, 0.0]",
                "angles in degrees within -180..180",
            ),
        ];
        for (entries, prefix, nth, key_value, expected) in cases {
            let (text, r) = with_map(entries);
            // The origin's own `id = 0` line in [marker] comes first.
            let skip = usize::from(prefix == "id = ");
            let line = nth_line(&text, prefix, nth + skip);
            let Err(ParamsError::Config(e)) = r else {
                panic!("{entries}: not refused as a range error");
            };
            let msg = e.to_string();
            assert!(
                msg.starts_with(&format!("/sites/pool.toml:{line}:"))
                    && msg.contains(&format!("{key_value}: expected {expected}")),
                "{entries}: {msg}"
            );
        }
    }

    #[test]
    fn a_key_left_out_is_reported_at_its_table() {
        let at = Located::new("[site]\nname = \"x\"\n\n[camera]\nfps = 1.0\n");
        assert_eq!(at.line_of_key("camera.exposure_max_us"), 4);
        assert_eq!(at.line_of_key("camera.fps"), 5);
        assert_eq!(at.line_of_key("nowhere.key"), 1);
    }
}
