//! Run statistics and the `--summary` JSON. Everything but the wall-clock fields
//! (`wall_seconds`, `realtime_factor`, `world_wall_seconds`, `world_realtime_factor`,
//! `loop_latency_p99_ms`, `stream_added_latency_*`) is a function of the seed: the same seed gives the same numbers.

use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use markhold_hil::Truth;
use nalgebra::{Isometry3, Vector3};
use serde::Serialize;

use crate::pipeline::FrameRecord;

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub exposure_method: String,
    pub lighting: String,
    pub seed: u64,
    pub frames: u64,
    pub sim_seconds: f64,
    pub wall_seconds: f64,
    /// Simulated seconds per wall second.
    pub realtime_factor: f64,
    /// Wall seconds the HIL world took (physics, the vehicle's MAVLink, rendering), and
    /// simulated seconds per such second: the world's own speed, without the loop.
    pub world_wall_seconds: f64,
    pub world_realtime_factor: f64,
    /// The renderer's loops that produced the world's speed (`portable`, `avx2`, `avx512`:
    /// the widest this CPU runs unless `--render-loops` chose narrower). Every build gives
    /// the same frames, so only the two fields above depend on it.
    pub render_loops: String,
    pub detection_rate: f64,
    /// Markers of the map the pose was computed from, mean over every frame (a frame
    /// without a pose counts 0): 1 at most for a map of one.
    pub markers_in_view_mean: f64,
    /// Vehicle vs station, ground truth, RMS over the last half of the run.
    pub position_rms_m: f64,
    pub final_position_error_m: f64,
    pub final_yaw_error_deg: f64,
    /// Frames until the exposure stays within 5% of its final value.
    pub exposure_convergence_frames: u64,
    /// Frames until the exposure is first within 5% of its final value (an excursion
    /// after that counts in `exposure_convergence_frames` only).
    pub exposure_first_within_frames: u64,
    pub final_exposure_us: f64,
    /// Frame available -> command on the wire, 99th percentile, milliseconds.
    pub loop_latency_p99_ms: f64,
    /// Determinant of the 3x3 covariance of the measured marker positions (camera frame).
    pub measured_position_cov_det: f64,
    /// Frames the HIL vehicle stepped without having received that frame's command.
    pub lockstep_timeouts: u64,
    /// Injected faults (`--fault`) with their timings and what the loop did.
    pub faults: Vec<super::faults::FaultReport>,
    /// Ended early by Ctrl-C / SIGTERM (the last frame sent neutral input).
    pub interrupted: bool,
    /// `h264-rtp` when the camera came through the stream stack (absent: in process).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera_transport: Option<String>,
    /// The stream camera's estimate of the command-to-frame delay, frames.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stream_delay_estimate_frames: Option<u32>,
    /// Wall time the stream adds per frame (encode, RTP over loopback UDP, decode,
    /// convert to grey), percentiles, milliseconds. Wall-clock fields, like the latency.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stream_added_latency_p50_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stream_added_latency_p99_ms: Option<f64>,
}

/// Frames whose series are reserved up front: a longer run grows them (a day at 30 fps
/// is 2.6 M frames; `--seconds` itself is bounded by [`MAX_SECONDS`]).
const RESERVED_FRAMES: usize = 1 << 16;

/// The longest run `hil` accepts, simulated seconds (one day).
pub const MAX_SECONDS: f64 = 86_400.0;

/// Per-frame series kept during a run (allocated once at the start); the summary and
/// `hil --plots` read them after the run.
pub struct RunStats {
    t_world_marker: Isometry3<f64>,
    t_marker_station: Isometry3<f64>,
    /// Loop time of each frame (its stamp), seconds.
    pub time_s: Vec<f64>,
    /// The exposure controller's metric on each frame (NaN when it computed none).
    pub metric: Vec<f64>,
    pub detected: Vec<bool>,
    /// Markers of the map in each frame's pose (0 without one).
    pub markers_used: Vec<u32>,
    pub exposure_us: Vec<f64>,
    pub pos_err_m: Vec<f64>,
    pub yaw_err_deg: Vec<f64>,
    pub latency_s: Vec<f64>,
    pub measured: Vec<Vector3<f64>>,
    pub true_cam_marker: Vec<Vector3<f64>>,
    pub vehicle_marker: Vec<Vector3<f64>>,
    pub last_time_s: f64,
}

impl RunStats {
    pub fn new(
        frames: usize,
        t_world_marker: Isometry3<f64>,
        t_marker_station: Isometry3<f64>,
    ) -> Self {
        let frames = frames.min(RESERVED_FRAMES);
        Self {
            t_world_marker,
            t_marker_station,
            time_s: Vec::with_capacity(frames),
            metric: Vec::with_capacity(frames),
            detected: Vec::with_capacity(frames),
            markers_used: Vec::with_capacity(frames),
            exposure_us: Vec::with_capacity(frames),
            pos_err_m: Vec::with_capacity(frames),
            yaw_err_deg: Vec::with_capacity(frames),
            latency_s: Vec::with_capacity(frames),
            measured: Vec::with_capacity(frames),
            true_cam_marker: Vec::with_capacity(frames),
            vehicle_marker: Vec::with_capacity(frames),
            last_time_s: 0.0,
        }
    }

    /// The station in the marker frame (the desired vehicle pose).
    pub fn t_marker_station(&self) -> &Isometry3<f64> {
        &self.t_marker_station
    }

    pub fn push(&mut self, rec: &FrameRecord, truth: &Truth) {
        let t_marker_vehicle = self.t_world_marker.inverse() * truth.t_world_vehicle;
        let err = self.t_marker_station.inverse() * t_marker_vehicle;
        self.pos_err_m.push(err.translation.vector.norm());
        // Heading error: yaw of the vehicle relative to its station attitude.
        let (_, _, yaw) = err.rotation.euler_angles();
        self.yaw_err_deg.push(yaw.to_degrees().abs());
        self.time_s.push(rec.stamp_s);
        self.metric.push(rec.exposure.metric);
        self.detected.push(rec.detected);
        self.markers_used.push(rec.markers_used);
        self.exposure_us.push(rec.exposure.exposure_us);
        self.latency_s.push(rec.latency_s);
        if let Some(t) = rec.t_cam_marker {
            self.measured.push(t.translation.vector);
        }
        self.true_cam_marker
            .push(truth.t_cam_marker.translation.vector);
        self.vehicle_marker
            .push(t_marker_vehicle.translation.vector);
        self.last_time_s = truth.time_s;
    }

    /// A frame of a run whose truth is an external vehicle's telemetry.
    pub fn push_external(
        &mut self,
        rec: &FrameRecord,
        t_world_vehicle: &Isometry3<f64>,
        t_vehicle_cam: &Isometry3<f64>,
    ) {
        let t_cam_marker = (t_world_vehicle * t_vehicle_cam).inverse() * self.t_world_marker;
        let truth = Truth {
            time_s: rec.stamp_s,
            t_world_vehicle: *t_world_vehicle,
            t_world_cam: t_world_vehicle * t_vehicle_cam,
            t_cam_marker,
            velocity_world_mps: [0.0; 3],
            armed: true,
            mode: 0,
            pwm: [1500; 8],
            lockstep_timeouts: 0,
        };
        self.push(rec, &truth);
    }

    pub fn summary(
        &self,
        method: ExposureMethod,
        lighting: LightingScenario,
        seed: u64,
        wall_seconds: f64,
        lockstep_timeouts: u64,
    ) -> Summary {
        let n = self.detected.len();
        let half = &self.pos_err_m[n / 2..];
        let position_rms_m = rms(half);
        Summary {
            exposure_method: method.to_string(),
            lighting: lighting.to_string(),
            seed,
            frames: n as u64,
            sim_seconds: self.last_time_s,
            wall_seconds,
            realtime_factor: if wall_seconds > 0.0 {
                self.last_time_s / wall_seconds
            } else {
                0.0
            },
            world_wall_seconds: 0.0,
            world_realtime_factor: 0.0,
            render_loops: String::new(),
            detection_rate: self.detected.iter().filter(|d| **d).count() as f64 / n.max(1) as f64,
            markers_in_view_mean: self.markers_used.iter().map(|&m| f64::from(m)).sum::<f64>()
                / n.max(1) as f64,
            position_rms_m,
            final_position_error_m: self.pos_err_m.last().copied().unwrap_or(f64::NAN),
            final_yaw_error_deg: self.yaw_err_deg.last().copied().unwrap_or(f64::NAN),
            exposure_convergence_frames: convergence_frames(&self.exposure_us, 0.05),
            exposure_first_within_frames: first_within_frames(&self.exposure_us, 0.05),
            final_exposure_us: self.exposure_us.last().copied().unwrap_or(f64::NAN),
            loop_latency_p99_ms: percentile(&self.latency_s, 0.99) * 1e3,
            measured_position_cov_det: cov_det(&self.measured),
            lockstep_timeouts,
            interrupted: false,
            faults: Vec::new(),
            camera_transport: None,
            stream_delay_estimate_frames: None,
            stream_added_latency_p50_ms: None,
            stream_added_latency_p99_ms: None,
        }
    }
}

pub fn rms(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

/// Index of the first sample after which every sample stays within `tol` (relative) of
/// the final value; the series' length when it never settles.
pub fn convergence_frames(series: &[f64], tol: f64) -> u64 {
    let Some(&last) = series.last() else { return 0 };
    let mut first_in = series.len();
    for (i, v) in series.iter().enumerate().rev() {
        if (v - last).abs() <= tol * last.abs() {
            first_in = i;
        } else {
            break;
        }
    }
    first_in as u64
}

/// Frames until the series is first within `tol` (relative) of its last value.
pub fn first_within_frames(series: &[f64], tol: f64) -> u64 {
    let Some(&last) = series.last() else { return 0 };
    series
        .iter()
        .position(|v| (v - last).abs() <= tol * last.abs())
        .unwrap_or(series.len()) as u64
}

pub fn percentile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let idx = ((s.len() - 1) as f64 * q).round() as usize;
    s[idx]
}

/// Determinant of the sample covariance of 3-vectors (NaN with fewer than 4 samples).
pub fn cov_det(points: &[Vector3<f64>]) -> f64 {
    if points.len() < 4 {
        return f64::NAN;
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let mut c = nalgebra::Matrix3::zeros();
    for p in points {
        let d = p - mean;
        c += d * d.transpose();
    }
    (c / (n - 1.0)).determinant()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn convergence_counts_frames_before_settling() {
        let s = [100.0, 50.0, 20.0, 10.4, 10.1, 10.0, 10.0];
        assert_eq!(convergence_frames(&s, 0.05), 3);
        assert_eq!(convergence_frames(&[5.0; 4], 0.05), 0);
        // Oscillating to the end: settles only at the last sample.
        assert_eq!(convergence_frames(&[1.0, 2.0, 1.0, 2.0], 0.05), 3);
    }

    #[test]
    fn percentile_and_rms() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert!((rms(&[3.0, 4.0]) - (12.5f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn cov_det_of_a_cube_cloud() {
        let mut pts = Vec::new();
        for x in [-1.0, 1.0] {
            for y in [-1.0, 1.0] {
                for z in [-1.0, 1.0] {
                    pts.push(Vector3::new(x, 2.0 * y, 3.0 * z));
                }
            }
        }
        // Variances 8/7, 32/7, 72/7 on the diagonal, zero off it.
        let expect = (8.0 / 7.0) * (32.0 / 7.0) * (72.0 / 7.0);
        assert!((cov_det(&pts) - expect).abs() < 1e-9);
    }
}
