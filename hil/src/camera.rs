//! The underwater camera: a pinhole camera with OpenCV's distortion model, mounted on the
//! vehicle, rendering the [`Scene`] through water onto a simulated sensor (shot and read
//! noise, full well, gain, the camera response, 8-bit output). A new exposure takes
//! effect `delay_frames` frames late and every frame carries the exposure it really had.

mod fast;
mod kernels;
mod reference;
mod sensor;

use std::collections::VecDeque;

use markhold_exposure::{ExposureLimits, Frame, Response, ResponseModel};
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use crate::scene::{Scene, WorldLamp};
use crate::HilError;
use markhold_config::{above, open_closed, Checks, ConfigError};
use sensor::{electrons_per_unit, SensorTables, XorShift64Star};

/// The builds of the fast renderer's per-pixel loops, narrowest first. All give the
/// same frames, pixel for pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RenderLoops {
    /// Scalar loops (what a CPU without AVX2 runs).
    Portable,
    /// Eight pixels a step.
    Avx2,
    /// AVX2, and the rock, plate and linear sensor loops sixteen pixels a step.
    Avx512,
}

impl RenderLoops {
    /// Every build, narrowest first.
    pub const ALL: [Self; 3] = [Self::Portable, Self::Avx2, Self::Avx512];

    /// Lower-case name, as `markhold hil --render-loops` takes it and the summary reports it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Portable => "portable",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }
}

impl std::str::FromStr for RenderLoops {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.to_ascii_lowercase();
        Self::ALL
            .into_iter()
            .find(|l| l.name() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Self::ALL.iter().map(|l| l.name()).collect();
                format!(
                    "unknown render loops '{s}': expected one of {}",
                    names.join(", ")
                )
            })
    }
}

impl std::fmt::Display for RenderLoops {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// `[camera.sensor]`: how the sensor turns light into electrons and electrons into noise.
/// Defaults are those of a Sony IMX273 (FLIR Blackfly S BFS-U3-16S2M, the paper's camera).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    /// Electrons a pixel holds before it clips.
    pub full_well_e: f64,
    /// Read noise, electrons RMS.
    pub read_noise_e: f64,
    /// Electrons per (W/m2 of exitance-equivalent scene light x microsecond) at 0 dB:
    /// lens aperture, pixel area and quantum efficiency in one number.
    pub electrons_per_w_m2_us: f64,
    /// Shot and read noise on (false renders the noise-free mean, for tests).
    pub noise: bool,
}

impl Default for SensorConfig {
    fn default() -> Self {
        Self {
            full_well_e: 10_500.0,
            read_noise_e: 2.3,
            electrons_per_w_m2_us: 0.035,
            noise: true,
        }
    }
}

impl SensorConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        Checks::new("camera.sensor")
            .range("full_well_e", self.full_well_e, 100.0..=1e7, "a capacity in [100, 1e7] electrons")
            .range("read_noise_e", self.read_noise_e, 0.0..=1000.0, "a noise in [0, 1000] electrons")
            .range("electrons_per_w_m2_us", self.electrons_per_w_m2_us, open_closed(0.0, 1e6), "a sensitivity in (0, 1e6]")
            .done()
    }
}

/// Intrinsics, distortion, timing, exposure and sensor of the simulated camera.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV order: k1, k2, p1, p2, k3.
    pub dist: [f64; 5],
    pub fps: f64,
    pub limits: ExposureLimits,
    pub gain_db: f64,
    /// Frames between a request and the first frame exposed with it (0 = next frame).
    pub delay_frames: u32,
    pub response: ResponseModel,
    pub sensor: SensorConfig,
}

impl CameraModel {
    /// A FLIR Blackfly S (1440x1080, 30 fps) behind a flat port with a 4.5 mm lens
    /// (about 80 degrees horizontal field of view in water), no distortion.
    pub fn blackfly_s(response: ResponseModel) -> Self {
        Self {
            width: 1440,
            height: 1080,
            fx: 860.0,
            fy: 860.0,
            cx: 719.5,
            cy: 539.5,
            dist: [0.0; 5],
            fps: 30.0,
            limits: ExposureLimits {
                min_us: 20.0,
                max_us: 30_000.0,
                fps: 30.0,
            },
            gain_db: 0.0,
            delay_frames: 1,
            response,
            sensor: SensorConfig::default(),
        }
    }

    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad_dist = self
            .dist
            .iter()
            .position(|v| !(v.is_finite() && v.abs() < 100.0));
        let l = &self.limits;
        let limits_ok = l.min_us > 0.0 && l.max_us >= l.min_us && l.max_us.is_finite();
        Checks::new("camera")
            .range("width", self.width, 8..=16384, "8..=16384 pixels")
            .range("height", self.height, 8..=16384, "8..=16384 pixels")
            .finite_range("fx", self.fx, above(1.0), "a focal length > 1 pixel")
            .finite_range("fy", self.fy, above(1.0), "a focal length > 1 pixel")
            .finite("cx", self.cx, "a finite principal point")
            .finite("cy", self.cy, "a finite principal point")
            .opt(bad_dist, |c, i| {
                let name = format!("distortion[{i}]");
                c.check(
                    &name,
                    self.dist[i],
                    false,
                    "a finite coefficient, |k| < 100",
                )
            })
            .range("fps", self.fps, open_closed(0.0, 1000.0), "a frame rate in (0, 1000]")
            .check("exposure_min_us", format!("{}..{}", l.min_us, l.max_us), limits_ok, "0 < exposure_min_us <= exposure_max_us")
            .range("gain_db", self.gain_db, 0.0..=48.0, "a gain in [0, 48] dB")
            .range("actuation_delay_frames", self.delay_frames, ..=8, "0..=8 frames")
            .then(|| self.sensor.validate())
            .done()
    }

    /// Apply the distortion to normalized coordinates (OpenCV's model).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Normalized coordinates of the ray through pixel (u, v) (pixel centres at integers),
    /// inverting the distortion by fixed-point iteration like OpenCV's undistortPoints.
    pub fn undistort_pixel(&self, u: f64, v: f64) -> (f64, f64) {
        let xd = (u - self.cx) / self.fx;
        let yd = (v - self.cy) / self.fy;
        if self.dist.iter().all(|k| *k == 0.0) {
            return (xd, yd);
        }
        let [k1, k2, p1, p2, k3] = self.dist;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            x = (xd - dx) / radial;
            y = (yd - dy) / radial;
        }
        (x, y)
    }

    /// Pixel where a point in the camera frame projects; `None` behind the camera.
    pub fn project(&self, p_cam: &Point3<f64>) -> Option<[f64; 2]> {
        if p_cam.z <= 1e-9 {
            return None;
        }
        let (x, y) = self.distort(p_cam.x / p_cam.z, p_cam.y / p_cam.z);
        Some([self.fx * x + self.cx, self.fy * y + self.cy])
    }
}

/// What both renderers need for one frame.
pub(crate) struct FrameInput<'a> {
    pub(crate) model: &'a CameraModel,
    pub(crate) scene: &'a Scene,
    pub(crate) t_wc: &'a Isometry3<f64>,
    /// The vehicle's lamps placed for this frame.
    pub(crate) lamps: &'a [WorldLamp],
    pub(crate) time_s: f64,
    /// Electrons per unit of exitance at this frame's exposure.
    pub(crate) e_per_unit: f64,
    pub(crate) tables: &'a SensorTables,
}

/// The simulated camera. Holds every buffer it renders with, so `render` allocates
/// nothing after the first frame.
pub struct UnderwaterCamera {
    model: CameraModel,
    tables: SensorTables,
    rng: XorShift64Star,
    /// Frames rendered so far (the next frame's seq).
    seq: u64,
    /// Exposure the sensor is set to now.
    current_us: f64,
    /// Requests not yet in effect: (first seq exposed with it, value).
    pending: VecDeque<(u64, f64)>,
    lamps: Vec<WorldLamp>,
    fast: fast::FastRenderer,
}

impl UnderwaterCamera {
    pub fn new(model: CameraModel, seed: u64) -> Result<Self, HilError> {
        model.validate()?;
        let response: Response = model
            .response
            .load()
            .map_err(|source| HilError::CameraResponse { source })?;
        let tables = SensorTables::new(seed, &model, &response);
        let current_us = model.limits.clamp(
            model
                .limits
                .min_us
                .max(1000.0)
                .min(model.limits.effective_max_us()),
        );
        Ok(Self {
            tables,
            rng: XorShift64Star::new(seed),
            seq: 0,
            current_us,
            pending: VecDeque::with_capacity(model.delay_frames as usize + 2),
            lamps: Vec::with_capacity(8),
            fast: fast::FastRenderer::new(&model),
            model,
        })
    }

    /// Request an exposure; takes effect `delay_frames` frames later (before the first
    /// frame: at once, as a camera configured before it streams). Returns the value the
    /// camera will use (clamped to limits).
    pub fn set_exposure_us(&mut self, us: f64) -> f64 {
        let us = self.model.limits.clamp(us);
        if self.seq == 0 {
            // Set before streaming starts: the first frame already has it.
            self.pending.clear();
            self.current_us = us;
            return us;
        }
        let effective = self.seq + self.model.delay_frames as u64;
        // Requests made before the same frame collapse: the last one wins.
        while let Some(&(s, _)) = self.pending.back() {
            if s >= effective {
                self.pending.pop_back();
            } else {
                break;
            }
        }
        self.pending.push_back((effective, us));
        us
    }

    /// The exposure the next frame will be taken with.
    pub fn next_exposure_us(&self) -> f64 {
        let mut t = self.current_us;
        for &(s, v) in &self.pending {
            if s <= self.seq {
                t = v;
            }
        }
        t
    }

    /// Render with the portable loops even where the CPU has AVX2 (both give the same
    /// frames; tests compare them).
    pub fn set_portable_render(&mut self, portable: bool) {
        self.fast.set_portable(portable);
    }

    /// Render with the widest build of the loops this CPU runs up to `want` (every
    /// build gives the same frames; tests compare them). Returns the build chosen.
    pub fn set_render_loops(&mut self, want: RenderLoops) -> RenderLoops {
        self.fast.set_loops(want)
    }

    /// The build of the loops the fast renderer runs.
    pub fn render_loops(&self) -> RenderLoops {
        self.fast.loops()
    }

    pub fn model(&self) -> &CameraModel {
        &self.model
    }

    /// Render the frame taken at `time_s` from camera pose `t_world_cam` (vehicle lamps are
    /// placed from `t_world_vehicle`) into `out` (resized to the model once, then reused),
    /// filling out.meta (seq, stamp_s = time_s, exposure_us really used, gain_db).
    pub fn render(
        &mut self,
        scene: &Scene,
        t_world_cam: &Isometry3<f64>,
        t_world_vehicle: &Isometry3<f64>,
        time_s: f64,
        out: &mut Frame,
    ) {
        self.render_with(scene, t_world_cam, t_world_vehicle, time_s, out, false);
    }

    /// The slow, obviously-correct renderer (f64 per pixel, no precomputation): the
    /// reference the fast path is tested and benchmarked against. Same state handling
    /// as [`render`](Self::render).
    pub fn render_reference(
        &mut self,
        scene: &Scene,
        t_world_cam: &Isometry3<f64>,
        t_world_vehicle: &Isometry3<f64>,
        time_s: f64,
        out: &mut Frame,
    ) {
        self.render_with(scene, t_world_cam, t_world_vehicle, time_s, out, true);
    }

    fn render_with(
        &mut self,
        scene: &Scene,
        t_world_cam: &Isometry3<f64>,
        t_world_vehicle: &Isometry3<f64>,
        time_s: f64,
        out: &mut Frame,
        reference: bool,
    ) {
        let exposure_us = self.begin_frame();
        out.resize(self.model.width, self.model.height);
        scene.lamps_for(t_world_vehicle, &mut self.lamps);
        let input = FrameInput {
            model: &self.model,
            scene,
            t_wc: t_world_cam,
            lamps: &self.lamps,
            time_s,
            e_per_unit: electrons_per_unit(&self.model, exposure_us),
            tables: &self.tables,
        };
        if reference {
            reference::render(&input, &mut self.rng, out);
        } else {
            self.fast.render(&input, &mut self.rng, out);
        }
        self.finish_frame(out, time_s, exposure_us);
    }

    /// Apply the requests due for this frame; returns its exposure.
    fn begin_frame(&mut self) -> f64 {
        while let Some(&(s, v)) = self.pending.front() {
            if s <= self.seq {
                self.current_us = v;
                self.pending.pop_front();
            } else {
                break;
            }
        }
        self.current_us
    }

    fn finish_frame(&mut self, out: &mut Frame, time_s: f64, exposure_us: f64) {
        out.meta.seq = self.seq;
        out.meta.stamp_s = time_s;
        out.meta.exposure_us = exposure_us;
        out.meta.gain_db = self.model.gain_db;
        self.seq += 1;
    }
}
