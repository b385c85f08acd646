//! The scene the HIL camera sees: a marker plate (a real dictionary marker with its white
//! border) mounted in front of a rock wall that stands on a seabed, with the site's other
//! markers (its marker map) on plates of their own at their map poses, in water that
//! attenuates and scatters light, lit by daylight from above, the vehicle's lamps and,
//! in the `adversarial` scenario, a bright lamp aimed at the marker.
//!
//! Radiometry is grey (one band). Light is counted as the irradiance-equivalent that a
//! white Lambertian surface would need to look as bright ("exitance", W/m2): a surface of
//! albedo `rho` under irradiance `E` seen through a path of length `d` contributes
//! `rho * E * exp(-c d)`; the water in front of it adds backscatter
//! `B_inf * (1 - exp(-b d))` (Akkaynak & Treibitz 2018, one band).

mod texture;

use std::str::FromStr;

use nalgebra::{Isometry3, Point3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use crate::HilError;
use markhold_config::{open_closed, AsDebug, Checks, ConfigError};
pub(crate) use texture::{LitTexture, SplitMix64, Texture};

/// Water types with tabulated coefficients (green band, where a grey camera is most
/// sensitive), from the ranges reported for Jerlov oceanic / coastal types and turbid
/// rivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaterType {
    /// Open ocean (Jerlov I-II).
    Clear,
    /// Coastal water (Jerlov 3C-5C).
    Coastal,
    /// Turbid river water (the paper's Connecticut River).
    River,
}

impl WaterType {
    /// (beam attenuation c, backscatter coefficient b, diffuse attenuation K_d,
    /// veiling light over downwelling irradiance) for this water.
    fn coefficients(self) -> (f64, f64, f64, f64) {
        match self {
            Self::Clear => (0.15, 0.10, 0.06, 0.02),
            Self::Coastal => (0.50, 0.35, 0.20, 0.05),
            Self::River => (1.50, 1.10, 0.80, 0.10),
        }
    }
}

/// `[water]`: the water's optical properties. Explicit coefficients override the type's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WaterConfig {
    /// "clear", "coastal" or "river".
    #[serde(rename = "type")]
    pub water_type: WaterType,
    /// Beam attenuation of the direct signal along a path, 1/m (Beer-Lambert).
    pub attenuation_per_m: Option<f64>,
    /// Backscatter coefficient b of `B_inf (1 - exp(-b z))`, 1/m.
    pub backscatter_per_m: Option<f64>,
    /// Diffuse attenuation of downwelling daylight with depth, 1/m.
    pub daylight_attenuation_per_m: Option<f64>,
    /// Veiling light `B_inf` as a fraction of the downwelling irradiance at the camera.
    pub veiling_fraction: Option<f64>,
    /// Veiling light per unit of lamp irradiance along the view ray (single scattering
    /// of the lamps' beams), 1/m.
    pub lamp_scatter_per_m: Option<f64>,
}

impl Default for WaterConfig {
    fn default() -> Self {
        Self {
            water_type: WaterType::Coastal,
            attenuation_per_m: None,
            backscatter_per_m: None,
            daylight_attenuation_per_m: None,
            veiling_fraction: None,
            lamp_scatter_per_m: None,
        }
    }
}

/// Water coefficients resolved from a [`WaterConfig`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WaterOptics {
    pub attenuation_per_m: f64,
    pub backscatter_per_m: f64,
    pub daylight_attenuation_per_m: f64,
    pub veiling_fraction: f64,
    pub lamp_scatter_per_m: f64,
}

impl WaterConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let per_m = 0.0..=20.0;
        let in_20 = "a number in [0, 20]";
        Checks::new("water")
            .range_opt("attenuation_per_m", self.attenuation_per_m, per_m.clone(), in_20)
            .range_opt("backscatter_per_m", self.backscatter_per_m, per_m.clone(), in_20)
            .range_opt("daylight_attenuation_per_m", self.daylight_attenuation_per_m, per_m, in_20)
            .range_opt("veiling_fraction", self.veiling_fraction, 0.0..=1.0, "a number in [0, 1]")
            .range_opt("lamp_scatter_per_m", self.lamp_scatter_per_m, 0.0..=10.0, "a number in [0, 10]")
            .done()
    }

    /// The coefficients this water uses (explicit values, else the type's).
    pub fn optics(&self) -> WaterOptics {
        let (c, b, kd, veil) = self.water_type.coefficients();
        WaterOptics {
            attenuation_per_m: self.attenuation_per_m.unwrap_or(c),
            backscatter_per_m: self.backscatter_per_m.unwrap_or(b),
            daylight_attenuation_per_m: self.daylight_attenuation_per_m.unwrap_or(kd),
            veiling_fraction: self.veiling_fraction.unwrap_or(veil),
            // A small share of the scattered beam comes back toward the camera.
            lamp_scatter_per_m: self.lamp_scatter_per_m.unwrap_or(0.02 * b),
        }
    }
}

/// The lighting scenarios of the paper's experiments (plus caustics).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LightingScenario {
    /// Flat overhead daylight.
    Normal,
    /// Dim daylight, dim vehicle lamps: long exposures, visible noise.
    Low,
    /// A bright lamp on the marker, dark surroundings.
    Adversarial,
    /// Shallow, sunny: moving caustic webs over everything.
    Caustics,
}

impl LightingScenario {
    pub const ALL: [LightingScenario; 4] =
        [Self::Normal, Self::Low, Self::Adversarial, Self::Caustics];

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Normal => "normal",
            Self::Low => "low",
            Self::Adversarial => "adversarial",
            Self::Caustics => "caustics",
        }
    }
}

impl std::fmt::Display for LightingScenario {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for LightingScenario {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "normal" => Ok(Self::Normal),
            "low" => Ok(Self::Low),
            "adversarial" => Ok(Self::Adversarial),
            "caustics" => Ok(Self::Caustics),
            other => Err(format!(
                "unknown lighting scenario '{other}': expected one of normal, low, adversarial, caustics"
            )),
        }
    }
}

/// A spotlight. Position and direction are in the frame of what carries it: the vehicle
/// body (FRD) for vehicle lamps, the marker frame for the marker lamp.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LampConfig {
    pub position_m: [f64; 3],
    /// Axis of the beam (need not be unit length).
    pub direction: [f64; 3],
    /// Radiant intensity on the axis, W/sr (the irradiance at 1 m in clear water, W/m2).
    pub intensity_w_sr: f64,
    /// Half angle of the full-intensity cone, degrees.
    pub inner_half_angle_deg: f64,
    /// Half angle where the beam has faded to zero, degrees.
    pub outer_half_angle_deg: f64,
}

impl Default for LampConfig {
    fn default() -> Self {
        Self {
            position_m: [0.2, 0.0, 0.0],
            direction: [1.0, 0.0, 0.0],
            intensity_w_sr: 0.0,
            inner_half_angle_deg: 30.0,
            outer_half_angle_deg: 60.0,
        }
    }
}

impl LampConfig {
    #[rustfmt::skip]
    fn validate(&self, key: &str) -> Result<(), ConfigError> {
        let n = Vector3::from(self.direction).norm();
        let position_ok = self.position_m.iter().all(|v| v.is_finite());
        let outer = open_closed(self.inner_half_angle_deg, 90.0);
        Checks::new(key)
            .check("position_m", AsDebug(self.position_m), position_ok, "finite metres")
            .check("direction", AsDebug(self.direction), n.is_finite() && n > 1e-9, "a non-zero finite vector")
            .range("intensity_w_sr", self.intensity_w_sr, 0.0..=1e6, "an intensity in [0, 1e6] W/sr")
            .range("inner_half_angle_deg", self.inner_half_angle_deg, 0.0..89.0, "an angle in [0, 89) degrees")
            .range("outer_half_angle_deg", self.outer_half_angle_deg, outer, "an angle above inner_half_angle_deg, at most 90 degrees")
            .done()
    }
}

/// `[lighting]`: the scenario and optional overrides of its values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LightingConfig {
    pub scenario: LightingScenario,
    /// Daylight irradiance just below the surface, W/m2 (band-integrated).
    pub ambient_surface_w_m2: Option<f64>,
    /// Lamps on the vehicle (body frame). Replaces the scenario's lamps when given.
    pub vehicle_lamps: Option<Vec<LampConfig>>,
    /// A fixed lamp aimed at the marker (marker frame). Replaces the scenario's.
    pub marker_lamp: Option<LampConfig>,
    /// Caustic contrast, 0 (none) .. 1 (black gaps between the bright lines).
    pub caustics_strength: Option<f64>,
    /// Size of one caustic cell on a surface, metres.
    pub caustics_scale_m: Option<f64>,
    /// Drift speed of the caustic pattern, m/s.
    pub caustics_speed_mps: Option<f64>,
}

impl Default for LightingConfig {
    fn default() -> Self {
        Self {
            scenario: LightingScenario::Normal,
            ambient_surface_w_m2: None,
            vehicle_lamps: None,
            marker_lamp: None,
            caustics_strength: None,
            caustics_scale_m: None,
            caustics_speed_mps: None,
        }
    }
}

/// Lighting resolved from a [`LightingConfig`]: the scenario's values with overrides.
#[derive(Debug, Clone, PartialEq)]
pub struct LightingSetup {
    pub ambient_surface_w_m2: f64,
    pub vehicle_lamps: Vec<LampConfig>,
    pub marker_lamp: Option<LampConfig>,
    pub caustics_strength: f64,
    pub caustics_scale_m: f64,
    pub caustics_speed_mps: f64,
}

/// Two lamps beside the camera housing, like a BlueROV2's Lumen lights.
fn vehicle_lamp_pair(intensity_w_sr: f64) -> Vec<LampConfig> {
    [-0.12, 0.12]
        .iter()
        .map(|&y| LampConfig {
            position_m: [0.22, y, -0.05],
            direction: [1.0, 0.0, 0.0],
            intensity_w_sr,
            inner_half_angle_deg: 35.0,
            outer_half_angle_deg: 65.0,
        })
        .collect()
}

impl LightingConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let lamps = self.vehicle_lamps.as_deref().unwrap_or_default();
        Checks::new("lighting")
            .range_opt("ambient_surface_w_m2", self.ambient_surface_w_m2, 0.0..=5000.0, "an irradiance in [0, 5000] W/m2")
            .then(|| {
                let mut each = lamps.iter().enumerate();
                each.try_for_each(|(i, l)| l.validate(&format!("lighting.vehicle_lamps[{i}]")))
            })
            .then(|| {
                self.marker_lamp
                    .as_ref()
                    .map_or(Ok(()), |l| l.validate("lighting.marker_lamp"))
            })
            .range_opt("caustics_strength", self.caustics_strength, 0.0..=1.0, "a contrast in [0, 1]")
            .range_opt("caustics_scale_m", self.caustics_scale_m, 0.01..=10.0, "a size in [0.01, 10] m")
            .range_opt("caustics_speed_mps", self.caustics_speed_mps, 0.0..=10.0, "a speed in [0, 10] m/s")
            .done()
    }

    /// The scenario's values with this config's overrides.
    pub fn resolve(&self) -> LightingSetup {
        use LightingScenario::*;
        let (ambient, lamps, marker_lamp, caustics) = match self.scenario {
            Normal => (400.0, vehicle_lamp_pair(0.0), None, 0.0),
            Low => (6.0, vehicle_lamp_pair(0.3), None, 0.0),
            // Night dive: no daylight to speak of; one narrow, very bright lamp on the
            // marker from above and to the side (a glare the marker's matte black ink
            // cannot absorb once the exposure is set for the dark surroundings).
            Adversarial => (
                1.0,
                vehicle_lamp_pair(0.0),
                Some(LampConfig {
                    position_m: [0.12, 0.25, 0.7],
                    direction: [-0.12, -0.25, -0.7],
                    intensity_w_sr: 500.0,
                    inner_half_angle_deg: 8.0,
                    outer_half_angle_deg: 16.0,
                }),
                0.0,
            ),
            Caustics => (600.0, vehicle_lamp_pair(0.0), None, 0.8),
        };
        LightingSetup {
            ambient_surface_w_m2: self.ambient_surface_w_m2.unwrap_or(ambient),
            vehicle_lamps: self.vehicle_lamps.clone().unwrap_or(lamps),
            marker_lamp: self.marker_lamp.clone().or(marker_lamp),
            caustics_strength: self.caustics_strength.unwrap_or(caustics),
            caustics_scale_m: self.caustics_scale_m.unwrap_or(0.25),
            caustics_speed_mps: self.caustics_speed_mps.unwrap_or(0.15),
        }
    }
}

/// Where the background is, relative to the marker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BackgroundConfig {
    /// The rock wall behind the plate, metres behind the marker's face.
    pub wall_behind_marker_m: f64,
    /// The seabed, metres below the marker's centre.
    pub seabed_below_marker_m: f64,
    /// Mean albedo of rock and seabed.
    pub albedo_mean: f64,
    /// Albedo spread around the mean (texture contrast).
    pub albedo_spread: f64,
    /// Size of one texel of the procedural rock, metres.
    pub texel_m: f64,
}

impl Default for BackgroundConfig {
    fn default() -> Self {
        Self {
            wall_behind_marker_m: 0.05,
            seabed_below_marker_m: 1.0,
            albedo_mean: 0.25,
            albedo_spread: 0.15,
            texel_m: 0.0015,
        }
    }
}

impl BackgroundConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let (mean, spread) = (self.albedo_mean, self.albedo_spread);
        let albedo_ok = spread >= 0.0 && mean - spread >= 0.0 && mean + spread <= 1.0;
        Checks::new("scene")
            .range("wall_behind_marker_m", self.wall_behind_marker_m, 0.001..=1000.0, "a distance in [0.001, 1000] m")
            .range("seabed_below_marker_m", self.seabed_below_marker_m, 0.0..=1000.0, "a distance in [0, 1000] m")
            .check("albedo_mean", mean, albedo_ok, "albedo_mean +- albedo_spread within [0, 1]")
            .range("texel_m", self.texel_m, 1e-4..=0.1, "a size in [1e-4, 0.1] m")
            .done()
    }
}

/// The printed marker and the white plate it is printed on.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerSpec {
    /// Cells per side, including the black border.
    pub cells: usize,
    /// Row-major, top row first as printed, including the border; true = white.
    pub white: Vec<bool>,
    /// Edge of the black square, metres.
    pub size_m: f64,
    /// White plate around the marker, metres on each side.
    pub plate_margin_m: f64,
}

impl MarkerSpec {
    /// Albedo of the print at marker-frame coordinates (u, v) (white outside the black
    /// square: the plate).
    pub(crate) fn albedo(&self, u: f64, v: f64) -> f64 {
        let l = self.size_m;
        let n = self.cells as f64;
        let cu = (u + 0.5 * l) / l * n;
        let cv = (0.5 * l - v) / l * n;
        if cu < 0.0 || cv < 0.0 || cu >= n || cv >= n {
            return ALBEDO_WHITE;
        }
        let i = (cv as usize) * self.cells + cu as usize;
        if self.white[i] {
            ALBEDO_WHITE
        } else {
            ALBEDO_BLACK
        }
    }

    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let cells2 = self.cells * self.cells;
        let white = format!("{} cells", self.white.len());
        Checks::new("marker")
            .range("cells", self.cells, 3..=64, "3..=64 cells per side")
            .check("white", white, self.white.len() == cells2, &format!("cells^2 = {cells2} cells"))
            .range("size_m", self.size_m, open_closed(0.0, 10.0), "a size in (0, 10] m")
            .range("plate_margin_m", self.plate_margin_m, 0.0..=10.0, "a margin in [0, 10] m")
            .done()
    }
}

/// A marker of the map other than the origin marker: its print and where it is.
#[derive(Debug, Clone, PartialEq)]
pub struct MapPlate {
    pub marker: MarkerSpec,
    /// Pose in the origin marker's frame (the site frame).
    pub t_origin_marker: Isometry3<f64>,
    /// Pose in the world (NED), from the origin marker's.
    pub t_world_marker: Isometry3<f64>,
}

impl MapPlate {
    /// Half the edge of the white plate, metres.
    pub fn plate_half_m(&self) -> f64 {
        0.5 * self.marker.size_m + self.marker.plate_margin_m
    }
}

/// Albedo of the marker's white plate and black ink (matte print).
pub const ALBEDO_WHITE: f64 = 0.85;
pub const ALBEDO_BLACK: f64 = 0.04;
/// Specular reflectance of the marker's matte laminate (2 %; a glossy one reflects about
/// 4 %) and the Blinn-Phong exponent of its lobe: a glare spot about 15 degrees wide that
/// lifts black and white cells alike, as in the paper's adversarial pictures.
const GLOSS_REFLECTANCE: f64 = 0.02;
const GLOSS_EXPONENT: f64 = 40.0;
/// Albedo of the back of the plate (seen only from behind).
const ALBEDO_PLATE_BACK: f64 = 0.3;

/// Share of the downwelling daylight that reaches a vertical surface (the light field
/// under water is not all from above).
const SIDE_LIGHT_FRACTION: f64 = 0.35;

/// A spotlight placed in the world for one frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct WorldLamp {
    pub(crate) pos: Vector3<f64>,
    pub(crate) axis: Vector3<f64>,
    pub(crate) intensity: f64,
    pub(crate) cos_inner: f64,
    pub(crate) cos_outer: f64,
}

impl WorldLamp {
    fn place(l: &LampConfig, t_world_frame: &Isometry3<f64>) -> Self {
        let axis = t_world_frame.rotation * Unit::new_normalize(Vector3::from(l.direction));
        Self {
            pos: (t_world_frame * Point3::from(l.position_m)).coords,
            axis: axis.into_inner(),
            intensity: l.intensity_w_sr,
            cos_inner: l.inner_half_angle_deg.to_radians().cos(),
            cos_outer: l.outer_half_angle_deg.to_radians().cos(),
        }
    }

    /// Irradiance the lamp gives to a point with unit normal `n` (attenuated on the way).
    #[inline]
    fn irradiance(&self, p: &Vector3<f64>, n: Option<&Vector3<f64>>, c: f64) -> f64 {
        self.irradiance_from(p, n, c).0
    }

    /// Irradiance at `p` and the unit direction from `p` toward the lamp.
    #[inline]
    fn irradiance_from(
        &self,
        p: &Vector3<f64>,
        n: Option<&Vector3<f64>>,
        c: f64,
    ) -> (f64, Vector3<f64>) {
        let v = self.pos - p;
        let r2 = v.norm_squared().max(1e-4);
        let r = r2.sqrt();
        let l = v / r;
        let cos_axis = -l.dot(&self.axis);
        let cone = smoothstep(self.cos_outer, self.cos_inner, cos_axis);
        if cone <= 0.0 {
            return (0.0, l);
        }
        let cos_i = match n {
            Some(n) => n.dot(&l).max(0.0),
            None => 1.0,
        };
        (self.intensity * cone * cos_i * (-c * r).exp() / r2, l)
    }
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Which surface a ray hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Surface {
    Plate,
    /// A plate of the map other than the origin marker's (index into `Scene::map`).
    MapPlate(usize),
    Wall,
    Seabed,
}

/// What the light model says about one surface point seen from the camera, in
/// exitance-equivalent units (W/m2): the signal is
/// `albedo * (ambient * caustic + lamp) + glare + backscatter`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(crate) struct Shade {
    /// Daylight reflected by a white surface, attenuated on the way to the camera.
    pub(crate) ambient: f64,
    /// Lamp light reflected by a white surface, attenuated on the way to the camera.
    pub(crate) lamp: f64,
    /// Lamp light mirrored by the plate's laminate (same on black and white cells).
    pub(crate) glare: f64,
    /// Water between the camera and the point.
    pub(crate) backscatter: f64,
}

/// Multipliers on the scene's light sources, for lights switched on and off or changing
/// during a run: `lamp` scales every lamp (the vehicle's and the marker's), `ambient` the
/// daylight (and with it the water's veiling light). Applied to the light the renderer
/// computes, before the sensor: shot noise, the full well and the response see the new
/// light as they would on a real camera. 1 and 1 leave the site's lighting as it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LightingScale {
    pub lamp: f64,
    pub ambient: f64,
}

impl Default for LightingScale {
    fn default() -> Self {
        Self::UNCHANGED
    }
}

impl LightingScale {
    /// The site's lighting, unscaled.
    pub const UNCHANGED: Self = Self {
        lamp: 1.0,
        ambient: 1.0,
    };

    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("lighting_scale")
            .range("lamp", self.lamp, 0.0..=1e4, "a factor in [0, 1e4]")
            .range("ambient", self.ambient, 0.0..=1e4, "a factor in [0, 1e4]")
            .done()
    }
}

/// The world the camera renders: geometry, materials, water and light.
#[derive(Debug, Clone)]
pub struct Scene {
    pub(crate) marker: MarkerSpec,
    pub(crate) t_world_marker: Isometry3<f64>,
    /// The map's other markers (empty for a map of one).
    pub(crate) map: Vec<MapPlate>,
    pub(crate) water: WaterOptics,
    pub(crate) lighting: LightingSetup,
    pub(crate) background: BackgroundConfig,
    /// Fixed lamps in the world (the marker lamp).
    pub(crate) world_lamps: Vec<WorldLamp>,
    pub(crate) rock: Texture,
    /// The two caustic webs (same size and byte scale; see `Scene::caustic`).
    pub(crate) caustic: [Texture; 2],
    /// Caustic drift directions of the two webs (unit, in surface coordinates).
    pub(crate) caustic_dirs: [(f64, f64); 2],
    /// Lamps switched off / daylight changed during the run.
    pub(crate) scale: LightingScale,
}

/// Side of the rock texture (texels, power of two).
const ROCK_LOG2: u32 = 10;
/// The caustic webs lie on the rock texture's texel grid (same side, same texel size),
/// so one texel read gives a pixel both its albedo and its caustic light. The second
/// web's cells are 1.33x larger than the first's, so the two never tile in step.
const CAUSTIC_LAYER2_CELLS: f64 = 0.75;
/// Where the second web starts against the first, texels.
const CAUSTIC_LAYER2_SHIFT: (i64, i64) = (97, 31);

/// Cells per side of the two caustic webs on a rock texture of `side` texels of
/// `texel_m`: the configured cell size, rounded so a whole number of cells tiles the
/// texture (at least 2, at most one per 8 texels).
fn caustic_cells(side: usize, texel_m: f64, scale_m: f64) -> [usize; 2] {
    let (lo, hi) = (2.0, (side / 8).max(2) as f64);
    let a = (side as f64 * texel_m / scale_m).round().clamp(lo, hi);
    let b = (a * CAUSTIC_LAYER2_CELLS).round().clamp(lo, hi);
    [a as usize, b as usize]
}

/// Where the caustic webs are at one instant: each web's drift, in whole rock texels
/// (1.5 mm at the default texel size).
#[derive(Debug, Clone, Copy)]
pub(crate) struct CausticParams {
    pub(crate) strength: f64,
    pub(crate) shift: [(i32, i32); 2],
}

impl Scene {
    /// A scene with the default background (a rock wall 5 cm behind the plate on a seabed
    /// 1 m below the marker).
    pub fn new(
        water: &WaterConfig,
        lighting: &LightingConfig,
        marker: MarkerSpec,
        t_world_marker: Isometry3<f64>,
        seed: u64,
    ) -> Result<Self, HilError> {
        Self::with_background(
            water,
            lighting,
            &BackgroundConfig::default(),
            marker,
            t_world_marker,
            seed,
        )
    }

    pub fn with_background(
        water: &WaterConfig,
        lighting: &LightingConfig,
        background: &BackgroundConfig,
        marker: MarkerSpec,
        t_world_marker: Isometry3<f64>,
        seed: u64,
    ) -> Result<Self, HilError> {
        water.validate()?;
        lighting.validate()?;
        background.validate()?;
        marker.validate()?;
        let lighting = lighting.resolve();
        let world_lamps = lighting
            .marker_lamp
            .iter()
            .map(|l| WorldLamp::place(l, &t_world_marker))
            .collect();
        let mut rng = SplitMix64::new(seed);
        let rock = texture::rock_texture(
            rng.next_u64(),
            ROCK_LOG2,
            background.albedo_mean as f32,
            background.albedo_spread as f32,
        );
        let cells = caustic_cells(rock.side(), background.texel_m, lighting.caustics_scale_m);
        // The webs cost a few hundred milliseconds to generate: only when they are seen
        // (the seed is drawn either way so the later draws do not depend on it).
        let caustic_seed = rng.next_u64();
        let caustic = if lighting.caustics_strength > 0.0 {
            texture::caustic_textures(caustic_seed, ROCK_LOG2, cells)
        } else {
            [Texture::blank(0), Texture::blank(0)]
        };
        let a0 = rng.next_f64() * std::f64::consts::TAU;
        // The second web drifts at a clearly different angle so the pattern keeps changing.
        let a1 = a0 + 2.0 + rng.next_f64();
        Ok(Self {
            marker,
            t_world_marker,
            map: Vec::new(),
            water: water.optics(),
            lighting,
            background: background.clone(),
            world_lamps,
            rock,
            caustic,
            caustic_dirs: [(a0.cos(), a0.sin()), (a1.cos(), a1.sin())],
            scale: LightingScale::UNCHANGED,
        })
    }

    /// Scale the lamps and the daylight from the next rendered frame on.
    pub fn set_lighting(&mut self, scale: LightingScale) -> Result<(), HilError> {
        scale.validate()?;
        self.scale = scale;
        Ok(())
    }

    /// The lighting scale in force.
    pub fn lighting_scale(&self) -> LightingScale {
        self.scale
    }

    pub fn marker(&self) -> &MarkerSpec {
        &self.marker
    }

    pub fn t_world_marker(&self) -> &Isometry3<f64> {
        &self.t_world_marker
    }

    /// Put another marker of the map on its own plate, `t_origin_marker` its pose in the
    /// origin marker's frame (the site frame: x right, y up, z out of the origin marker's
    /// face). It stands in the water like the origin plate (the wall and the seabed stay
    /// where the origin marker puts them) and is lit, filtered and noised the same way.
    pub fn add_map_marker(
        &mut self,
        marker: MarkerSpec,
        t_origin_marker: Isometry3<f64>,
    ) -> Result<(), HilError> {
        marker.validate()?;
        let t = t_origin_marker.translation.vector;
        let finite = t.iter().all(|v| v.is_finite());
        Checks::new(format!("marker.map[{}]", self.map.len()))
            .check(
                "position_m",
                AsDebug([t.x, t.y, t.z]),
                finite,
                "finite metres",
            )
            .done()?;
        self.map.push(MapPlate {
            marker,
            t_origin_marker,
            t_world_marker: self.t_world_marker * t_origin_marker,
        });
        Ok(())
    }

    /// The map's other markers, in the order they were added.
    pub fn map_markers(&self) -> &[MapPlate] {
        &self.map
    }

    pub fn water(&self) -> &WaterOptics {
        &self.water
    }

    pub fn lighting(&self) -> &LightingSetup {
        &self.lighting
    }

    /// Half the edge of the white plate, metres.
    pub(crate) fn plate_half_m(&self) -> f64 {
        0.5 * self.marker.size_m + self.marker.plate_margin_m
    }

    /// All lamps lit for a frame: the world's fixed lamps and the vehicle's, placed from
    /// `t_world_vehicle`. Writes into `out` (cleared first).
    pub(crate) fn lamps_for(&self, t_world_vehicle: &Isometry3<f64>, out: &mut Vec<WorldLamp>) {
        out.clear();
        let k = self.scale.lamp;
        if k <= 0.0 {
            // Switched off: no lamp light, no beam in the water.
            return;
        }
        out.extend(self.world_lamps.iter().map(|l| WorldLamp {
            intensity: l.intensity * k,
            ..*l
        }));
        out.extend(
            self.lighting
                .vehicle_lamps
                .iter()
                .filter(|l| l.intensity_w_sr > 0.0)
                .map(|l| {
                    let mut w = WorldLamp::place(l, t_world_vehicle);
                    w.intensity *= k;
                    w
                }),
        );
    }

    /// Downwelling daylight at depth `z` (world NED, metres below the surface).
    pub(crate) fn daylight(&self, z: f64) -> f64 {
        self.scale.ambient
            * self.lighting.ambient_surface_w_m2
            * (-self.water.daylight_attenuation_per_m * z.max(0.0)).exp()
    }

    /// The light model at world point `p` on a surface with unit normal `n`, seen from
    /// `cam` along unit direction `ray` at distance `dist`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn shade(
        &self,
        p: &Vector3<f64>,
        n: &Vector3<f64>,
        cam: &Vector3<f64>,
        ray: &Vector3<f64>,
        dist: f64,
        lamps: &[WorldLamp],
        glossy: bool,
    ) -> Shade {
        let c = self.water.attenuation_per_m;
        let to_cam = (-c * dist).exp();
        // Up is -z in NED.
        let facing_up = (-n.z).max(0.0);
        let e_amb =
            self.daylight(p.z) * (SIDE_LIGHT_FRACTION + (1.0 - SIDE_LIGHT_FRACTION) * facing_up);
        let mut e_lamp = 0.0;
        let mut glare = 0.0;
        for lamp in lamps {
            let (e, l) = lamp.irradiance_from(p, Some(n), c);
            e_lamp += e;
            if glossy && e > 0.0 {
                // Blinn-Phong lobe of the laminate, energy-normalized, in exitance units.
                let h = (l - ray).normalize();
                let nh = n.dot(&h).max(0.0);
                glare +=
                    e * GLOSS_REFLECTANCE * (GLOSS_EXPONENT + 8.0) / 8.0 * nh.powf(GLOSS_EXPONENT);
            }
        }
        Shade {
            ambient: e_amb * to_cam,
            lamp: e_lamp * to_cam,
            glare: glare * to_cam,
            backscatter: self.backscatter(cam, ray, dist, lamps),
        }
    }

    /// Light scattered toward the camera by the water on a path of length `dist` (may be
    /// infinite: open water).
    pub(crate) fn backscatter(
        &self,
        cam: &Vector3<f64>,
        ray: &Vector3<f64>,
        dist: f64,
        lamps: &[WorldLamp],
    ) -> f64 {
        let w = &self.water;
        let b_inf = w.veiling_fraction * self.daylight(cam.z);
        let mut b = b_inf * (1.0 - (-w.backscatter_per_m * dist).exp());
        if !lamps.is_empty() && w.lamp_scatter_per_m > 0.0 {
            // Single scattering of the lamps' beams along the ray, midpoint rule on two
            // samples over the part of the path light can come back from.
            let reach = dist.min(4.0 / w.attenuation_per_m.max(0.25));
            let mut acc = 0.0;
            for f in [0.25, 0.75] {
                let s = f * reach;
                let q = cam + ray * s;
                let e: f64 = lamps
                    .iter()
                    .map(|l| l.irradiance(&q, None, w.attenuation_per_m))
                    .sum();
                acc += e * (-w.attenuation_per_m * s).exp();
            }
            b += w.lamp_scatter_per_m * acc * 0.5 * reach;
        }
        b
    }

    /// Where the two drifting caustic webs are at time `t`.
    pub(crate) fn caustic_params(&self, t: f64) -> CausticParams {
        let l = &self.lighting;
        let d = l.caustics_speed_mps * t / self.background.texel_m;
        let [(a, b), (c, e)] = self.caustic_dirs;
        let side = self.rock.side() as i64;
        let at = |x: f64, s: i64| ((x * d).round() as i64 + s).rem_euclid(side) as i32;
        CausticParams {
            strength: l.caustics_strength,
            shift: [
                (at(a, 0), at(b, 0)),
                (at(c, CAUSTIC_LAYER2_SHIFT.0), at(e, CAUSTIC_LAYER2_SHIFT.1)),
            ],
        }
    }

    /// Caustic factor (mean 1) at surface coordinates (u, v) metres at time `t`. Two
    /// webs drift in different directions; their mean keeps changing shape like a real
    /// caustic network. Both lie on the rock's texel grid and move in whole texels; the
    /// mean is taken on the bytes (rounded half up), as the fast renderer's per-frame
    /// texture holds it.
    pub(crate) fn caustic(&self, u: f64, v: f64, t: f64) -> f64 {
        let p = self.caustic_params(t);
        if p.strength <= 0.0 {
            return 1.0;
        }
        let k = 1.0 / self.background.texel_m;
        // The texel the rock albedo is read from.
        let (x, y) = ((u * k).floor() as i64 as i32, (v * k).floor() as i64 as i32);
        let [a, b] = &self.caustic;
        let [sa, sb] = p.shift;
        let at =
            |t: &Texture, s: (i32, i32)| t.byte(x.wrapping_add(s.0), y.wrapping_add(s.1)) as u16;
        let byte = (at(a, sa) + at(b, sb) + 1) >> 1;
        let c = a.offset as f64 + a.scale as f64 * byte as f64;
        1.0 + p.strength * (c - 1.0)
    }

    /// Rock / seabed albedo at surface coordinates (u, v) metres.
    pub(crate) fn rock_albedo(&self, u: f64, v: f64) -> f64 {
        let k = 1.0 / self.background.texel_m;
        self.rock
            .at((u * k).floor() as i64 as i32, (v * k).floor() as i64 as i32) as f64
    }

    /// Back-face albedo of the plate.
    pub(crate) fn plate_back_albedo(&self) -> f64 {
        ALBEDO_PLATE_BACK
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenarios_round_trip_through_text_and_serde() {
        for s in LightingScenario::ALL {
            assert_eq!(s.to_string().parse::<LightingScenario>(), Ok(s));
            let json = serde_json::to_string(&s).unwrap();
            assert_eq!(json, format!("\"{s}\""));
            assert_eq!(serde_json::from_str::<LightingScenario>(&json).unwrap(), s);
        }
        assert_eq!(
            "ADVERSARIAL".parse::<LightingScenario>(),
            Ok(LightingScenario::Adversarial)
        );
        let e = "bright".parse::<LightingScenario>().unwrap_err();
        assert!(e.contains("bright") && e.contains("adversarial"), "{e}");
    }

    #[test]
    fn configs_reject_unknown_keys_and_name_bad_values() {
        let w: WaterConfig =
            serde_json::from_str(r#"{"type": "river", "attenuation_per_m": 2.0}"#).unwrap();
        assert_eq!(w.optics().attenuation_per_m, 2.0);
        assert_eq!(w.optics().backscatter_per_m, 1.10);
        assert!(serde_json::from_str::<WaterConfig>(r#"{"turbidity": 1}"#).is_err());
        assert!(serde_json::from_str::<LightingConfig>(r#"{"scenario": "dusk"}"#).is_err());

        let bad = WaterConfig {
            backscatter_per_m: Some(-1.0),
            ..WaterConfig::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(
            e.contains("water.backscatter_per_m") && e.contains("-1"),
            "{e}"
        );

        let bad = LightingConfig {
            marker_lamp: Some(LampConfig {
                direction: [0.0; 3],
                ..LampConfig::default()
            }),
            ..LightingConfig::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("lighting.marker_lamp.direction"), "{e}");

        let bad = MarkerSpec {
            cells: 6,
            white: vec![true; 35],
            size_m: 0.1,
            plate_margin_m: 0.02,
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("marker.white") && e.contains("35"), "{e}");
    }

    #[test]
    fn overrides_replace_the_scenario_values() {
        let cfg = LightingConfig {
            scenario: LightingScenario::Adversarial,
            ambient_surface_w_m2: Some(50.0),
            caustics_strength: Some(0.5),
            ..LightingConfig::default()
        };
        let r = cfg.resolve();
        assert_eq!(r.ambient_surface_w_m2, 50.0);
        assert_eq!(r.caustics_strength, 0.5);
        // The scenario's marker lamp stays.
        assert!(r
            .marker_lamp
            .as_ref()
            .is_some_and(|l| l.intensity_w_sr > 100.0));
        let normal = LightingConfig::default().resolve();
        assert!(normal.marker_lamp.is_none());
        let low = LightingConfig {
            scenario: LightingScenario::Low,
            ..LightingConfig::default()
        }
        .resolve();
        assert!(normal.ambient_surface_w_m2 > 10.0 * low.ambient_surface_w_m2);
    }

    #[test]
    fn daylight_and_water_attenuate_with_path_length() {
        let lighting = LightingConfig::default();
        let water = WaterConfig::default();
        let marker = MarkerSpec {
            cells: 4,
            white: vec![false; 16],
            size_m: 0.1,
            plate_margin_m: 0.02,
        };
        let scene = Scene::new(&water, &lighting, marker, Isometry3::identity(), 1).unwrap();
        let kd = water.optics().daylight_attenuation_per_m;
        let ratio = scene.daylight(5.0) / scene.daylight(2.0);
        assert!((ratio - (-3.0 * kd).exp()).abs() < 1e-12);
        let n = Vector3::new(-1.0, 0.0, 0.0);
        let cam = Vector3::new(-1.0, 0.0, 3.0);
        let ray = Vector3::new(1.0, 0.0, 0.0);
        let p = Vector3::new(0.0, 0.0, 3.0);
        let near = scene.shade(&p, &n, &cam, &ray, 1.0, &[], false);
        let far = scene.shade(&p, &n, &cam, &ray, 3.0, &[], false);
        let c = water.optics().attenuation_per_m;
        assert!((far.ambient / near.ambient - (-2.0 * c).exp()).abs() < 1e-12);
        // Backscatter grows with the path and saturates.
        assert!(far.backscatter > near.backscatter);
        let inf = scene.backscatter(&cam, &ray, f64::INFINITY, &[]);
        assert!(inf > far.backscatter && inf.is_finite());
    }

    #[test]
    fn caustic_cells_tile_the_rock_texture_near_the_configured_size() {
        // 1024 texels of 1.5 mm = 1.536 m: 6.1 cells of 0.25 m -> 6 (0.256 m), the
        // second web 1.33x larger.
        assert_eq!(caustic_cells(1024, 0.0015, 0.25), [6, 5]);
        assert_eq!(caustic_cells(1024, 0.0015, 0.1), [15, 11]);
        // Clamped: at least 2 cells, at most one per 8 texels.
        assert_eq!(caustic_cells(1024, 0.0015, 5.0), [2, 2]);
        assert_eq!(caustic_cells(1024, 0.0015, 0.001), [128, 96]);
    }

    #[test]
    fn caustics_move_in_whole_texels_and_keep_a_unit_mean() {
        let lighting = LightingConfig {
            scenario: LightingScenario::Caustics,
            ..LightingConfig::default()
        };
        let scene = Scene::new(
            &WaterConfig::default(),
            &lighting,
            MarkerSpec {
                cells: 4,
                white: vec![false; 16],
                size_m: 0.1,
                plate_margin_m: 0.02,
            },
            Isometry3::identity(),
            5,
        )
        .unwrap();
        let texel = scene.background.texel_m;
        let speed = scene.lighting.caustics_speed_mps;
        // After one second the first web has drifted speed / texel texels (rounded).
        let [a0, _] = scene.caustic_params(0.0).shift;
        let [a1, _] = scene.caustic_params(1.0).shift;
        let moved = (((a1.0 - a0.0) as f64).powi(2) + ((a1.1 - a0.1) as f64).powi(2)).sqrt();
        assert!((moved - speed / texel).abs() <= 1.5, "{moved} texels");
        // The factor over a 1 m patch has a mean near 1 and a visible contrast.
        let (mut sum, mut lo, mut hi, n) = (0.0, f64::MAX, 0f64, 200);
        for i in 0..n {
            for j in 0..n {
                let c = scene.caustic(i as f64 * 0.005, j as f64 * 0.005, 2.0);
                sum += c;
                lo = lo.min(c);
                hi = hi.max(c);
            }
        }
        let mean = sum / (n * n) as f64;
        assert!((mean - 1.0).abs() < 0.1, "mean {mean}");
        assert!(hi > 1.5 && lo < 0.8, "{lo} .. {hi}");
    }
}
