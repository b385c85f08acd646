//! markhold-exposure: exposure controllers over the frames of markhold-camera.
//!
//! Pure Rust, no OpenCV. The controllers follow `docs/reference/exposure-spec.md`: AAEC as
//! the paper's code ran it (`aaec_paper`: RoI + momentum on a soft-percentile gradient
//! metric) and markhold's own AAEC (`aaec`), AEC (Zhang et al. 2017, and as the AAEC
//! paper's code ran it), GEC with Shim's constants and as the AAEC paper's code ran it,
//! and a camera's mean-intensity AE. Each method is declared once, in [`METHODS`].

mod aaec;
mod aaec_paper;
mod aec;
mod aec_paper;
mod gec;
mod gec_paper;
mod mean;
mod method;
pub mod metric;
pub mod paper_code;
pub mod pyramid;
pub mod reference;
mod response;
#[cfg(test)]
mod test_frames;

pub use aaec::{Aaec, AaecConfig, AaecFallback, MarkerRegions, StepLaw};
pub use aaec_paper::{AaecPaper, AaecPaperConfig, LawStep, PaperGate, PaperMomentum};
pub use aec::{Aec, AecConfig};
pub use aec_paper::{AecPaper, AecPaperConfig};
pub use gec::{
    best_gamma, fit_quintic, fit_quintic_points, gec_ratio, Gec, GecConfig, GecScorer, GEC_GAMMAS,
};
pub use gec_paper::{
    gec_paper_gamma, gec_paper_update, quantize_abs, GecPaper, GecPaperConfig, GecPaperScorer,
    GecRegion, GEC_PAPER_ANCHORS,
};
pub use mean::{MeanAe, MeanAeConfig};
pub use method::{ExposureMethod, MethodInfo, PaperFigures, METHODS};
pub use metric::{soft_percentile_weights, GradientMetric, MetricParams, MetricValue, RankWeights};
pub use paper_code::{
    code_command, code_region, EtaScaling, GateStall, PaperFrames, PaperMetric, PaperMetricEval,
    PaperMetricParams, PaperMetricValue, PaperResponse, PreDetection,
};
pub use response::{Response, ResponseModel, PAPER_CODE_G_PRIME};
// Frames and the camera seam live in markhold-camera; re-exported for the controllers' users.
pub use markhold_camera::{
    Camera, CameraError, Corners, ExposureLimits, Frame, FrameMeta, ImageView, Roi,
};

pub use markhold_config::ConfigError;
use serde::{Deserialize, Serialize};

/// Errors of this crate. Config errors name the key and the value.
#[derive(Debug, thiserror::Error)]
pub enum ExposureError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("camera response table {}: cannot read: {source}", file.display())]
    ResponseIo {
        file: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("camera response table {}, line {line}: '{value}': expected {expected}", file.display())]
    ResponseTable {
        file: std::path::PathBuf,
        line: usize,
        value: String,
        expected: String,
    },
    #[error("camera response table {}: {count} values, expected 256", file.display())]
    ResponseTableLength {
        file: std::path::PathBuf,
        count: usize,
    },
}

/// What one controller update decided.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct ExposureStep {
    /// Exposure to command next, microseconds, within the camera's limits.
    pub exposure_us: f64,
    /// The controller's metric on this frame (NaN when it computed none).
    pub metric: f64,
    /// False when the frame was skipped (not exposed at the last commanded value).
    pub used_frame: bool,
    /// The region the controller metered, when it metered a region.
    pub roi: Option<Roi>,
}

impl ExposureStep {
    /// A frame the controller did not use: the exposure stays at `exposure_us`.
    pub fn skipped(exposure_us: f64) -> Self {
        Self {
            exposure_us,
            metric: f64::NAN,
            used_frame: false,
            roi: None,
        }
    }

    /// A frame the controller used: its `metric`, the region it metered (`roi`) and the
    /// exposure it commands next.
    pub fn used(exposure_us: f64, metric: f64, roi: Option<Roi>) -> Self {
        Self {
            exposure_us,
            metric,
            used_frame: true,
            roi,
        }
    }
}

/// An exposure controller: fed every frame, it decides the next exposure.
pub trait ExposureController: Send {
    fn method(&self) -> ExposureMethod;
    /// Feed one frame and, when the marker was detected in it, its corners.
    fn update(&mut self, frame: &Frame, marker: Option<&Corners>) -> ExposureStep;
    /// Feed one frame with every marker of the map in view: `marker` is the one the pose
    /// names (see [`ExposureController::update`]), `in_view` the corners of every marker
    /// the pose used (it among them). A controller that meters one marker uses `marker`.
    fn update_in_view(
        &mut self,
        frame: &Frame,
        marker: Option<&Corners>,
        _in_view: &[Corners],
    ) -> ExposureStep {
        self.update(frame, marker)
    }
    /// Size the per-marker buffers for a map of `markers` markers (at start-up: the
    /// per-frame path then allocates nothing).
    fn reserve_markers(&mut self, _markers: usize) {}
    /// The exposure last commanded, microseconds.
    fn commanded_us(&self) -> f64;
    /// Forget all state and command `exposure_us` next.
    fn reset(&mut self, exposure_us: f64);
    /// A gated law that has never moved (the paper's methods; none for the others).
    fn gate_stall(&self) -> Option<GateStall> {
        None
    }
}

/// True when `frame` was exposed with `commanded_us` (within rounding of the driver).
/// markhold's controllers only learn from such frames: a camera applies a new value late
/// (the paper's methods by default use every frame, as its code did).
pub fn exposed_as_commanded(frame: &Frame, commanded_us: f64) -> bool {
    let t = frame.meta.exposure_us;
    (t - commanded_us).abs() <= 1e-3 * commanded_us.abs().max(1.0) + 0.5
}

/// The `[exposure]` section of a site file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ExposureConfig {
    /// Which controller runs.
    pub method: ExposureMethod,
    /// Parameters of the mean-intensity AE ("default").
    pub default: MeanAeConfig,
    /// Parameters of markhold's AAEC.
    pub aaec: AaecConfig,
    /// Parameters of the paper's AAEC.
    pub aaec_paper: AaecPaperConfig,
    /// Parameters of AEC (also AAEC's fallback when `aaec.fallback = "aec"`).
    pub aec: AecConfig,
    /// Parameters of AEC as the paper's code ran it.
    pub aec_paper: AecPaperConfig,
    /// Parameters of GEC.
    pub gec: GecConfig,
    /// Parameters of the paper's GEC baseline.
    pub gec_paper: GecPaperConfig,
    /// The camera response the gradient controllers assume (and HIL renders with). A
    /// site file gives it as `[camera] response` and the binary sets it from there; it
    /// is never written, and read only so that the binary can name it when a file still
    /// has it here.
    #[serde(skip_serializing)]
    pub response: ResponseModel,
}

impl Default for ExposureConfig {
    fn default() -> Self {
        Self {
            method: ExposureMethod::Aaec,
            default: MeanAeConfig::default(),
            aaec: AaecConfig::default(),
            aaec_paper: AaecPaperConfig::default(),
            aec: AecConfig::default(),
            aec_paper: AecPaperConfig::default(),
            gec: GecConfig::default(),
            gec_paper: GecPaperConfig::default(),
            response: ResponseModel::default(),
        }
    }
}

impl ExposureConfig {
    /// Check every range (files are read by [`ResponseModel::load`]); the error names
    /// the key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.default.validate()?;
        self.aaec.validate()?;
        self.aaec_paper.validate()?;
        self.aec.validate()?;
        self.aec_paper.validate()?;
        self.gec.validate()?;
        self.gec_paper.validate()?;
        self.response.validate()
    }
}

/// Build the configured controller for a camera with `limits`, starting at `initial_us`.
pub fn build_controller(
    cfg: &ExposureConfig,
    method: ExposureMethod,
    limits: ExposureLimits,
    initial_us: f64,
) -> Result<Box<dyn ExposureController>, ExposureError> {
    method.build(cfg, limits, initial_us)
}
