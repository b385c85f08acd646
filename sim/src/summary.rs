//! Run statistics and the `--summary` JSON. Everything but the wall-clock fields
//! (`wall_seconds`, `realtime_factor`, `world_wall_seconds`, `world_realtime_factor`,
//! `loop_latency_p99_ms`, `stream_added_latency_*`) is a function of the seed: the same seed gives the same numbers.

use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;
use markhold_hil::Truth;
use nalgebra::{Isometry3, Vector3};
use serde::Serialize;

use markhold_core::pipeline::FrameRecord;

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
    /// The pose's own error: the vehicle's position from the frame's vision pose (the
    /// camera's pose in the site frame composed with the camera mount) against the
    /// vehicle's true position in the site frame (with `--vehicle`: its telemetry, that
    /// runner's truth), RMS over the frames of the last half of the run that have a pose
    /// (NaN, `null` in the JSON, when none has). The vehicle's point, not the camera's: the
    /// one the station keeper holds.
    pub pose_position_rms_m: f64,
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
    /// The simulated loop's delay from a frame's stamp to the thrust its command asks
    /// for (`[vehicle.delay]`, all stages), milliseconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame_to_thrust_ms: Option<f64>,
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
    /// Setpoint mode: the covariance sent with each vision estimate against the true
    /// error, as the HIL vehicle received it (absent in effort mode).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vision_nees: Option<VisionNeesSummary>,
    /// The paper's methods: every step of the law fell under its gate, so the exposure
    /// never moved from where the law started (absent when it moved, and for the other
    /// methods); logged as a warning when it is seen.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_gate_stall: Option<markhold_exposure::GateStall>,
}

/// NEES of the vision estimates the HIL vehicle received: position (3 dof) and yaw (1
/// dof) against the vehicle's true pose in the estimates' frame. Consistent: each mean
/// inside its bounds (the two-sided 95 % interval of the mean of `frames` independent
/// chi-square draws), about 95 % of frames under the per-frame 95 % quantile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct VisionNeesSummary {
    /// Estimates compared with the truth.
    pub frames: u64,
    /// Estimates without a usable covariance, and estimates matching no truth stamp.
    pub without_covariance: u64,
    pub unmatched: u64,
    pub nees_pos_mean: f64,
    pub nees_pos_mean_bounds_95: [f64; 2],
    /// Fraction of frames with position NEES under chi-square(3)'s 95 % quantile (7.81).
    pub nees_pos_inside_95: f64,
    pub nees_yaw_mean: f64,
    pub nees_yaw_mean_bounds_95: [f64; 2],
    /// Fraction of frames with yaw NEES under chi-square(1)'s 95 % quantile (3.84).
    pub nees_yaw_inside_95: f64,
}

impl VisionNeesSummary {
    pub fn of(n: &markhold_hil::endpoint::VisionNees) -> Self {
        use markhold_geometry::stats::mean_bounds_95;
        let (plo, phi) = mean_bounds_95(3.0, n.frames);
        let (ylo, yhi) = mean_bounds_95(1.0, n.frames);
        Self {
            frames: n.frames,
            without_covariance: n.without_covariance,
            unmatched: n.unmatched,
            nees_pos_mean: n.pos_mean(),
            nees_pos_mean_bounds_95: [plo, phi],
            nees_pos_inside_95: n.pos_inside_fraction(),
            nees_yaw_mean: n.yaw_mean(),
            nees_yaw_mean_bounds_95: [ylo, yhi],
            nees_yaw_inside_95: n.yaw_inside_fraction(),
        }
    }

    /// Both means inside their 95 % bounds.
    pub fn consistent(&self) -> bool {
        let inside = |m: f64, b: [f64; 2]| m >= b[0] && m <= b[1];
        self.frames > 0
            && inside(self.nees_pos_mean, self.nees_pos_mean_bounds_95)
            && inside(self.nees_yaw_mean, self.nees_yaw_mean_bounds_95)
    }
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
    /// Vehicle position from each frame's vision pose against the truth, site frame,
    /// metres (NaN for a frame without a pose).
    pub pose_pos_err_m: Vec<f64>,
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
            pose_pos_err_m: Vec::with_capacity(frames),
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
        // The vehicle from the vision pose, on the mount the camera really has (the
        // site's: the simulated vehicle carries the site's camera mount).
        let pose_err = rec.t_cam_marker.map_or(f64::NAN, |t_cam_marker| {
            let t_cam_vehicle = truth.t_world_cam.inverse() * truth.t_world_vehicle;
            let est = t_cam_marker.inverse() * t_cam_vehicle;
            (est.translation.vector - t_marker_vehicle.translation.vector).norm()
        });
        self.pose_pos_err_m.push(pose_err);
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
        let pose_position_rms_m = rms_finite(&self.pose_pos_err_m[n / 2..]);
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
            pose_position_rms_m,
            final_position_error_m: self.pos_err_m.last().copied().unwrap_or(f64::NAN),
            final_yaw_error_deg: self.yaw_err_deg.last().copied().unwrap_or(f64::NAN),
            exposure_convergence_frames: convergence_frames(&self.exposure_us, 0.05),
            exposure_first_within_frames: first_within_frames(&self.exposure_us, 0.05),
            final_exposure_us: self.exposure_us.last().copied().unwrap_or(f64::NAN),
            loop_latency_p99_ms: percentile(&self.latency_s, 0.99) * 1e3,
            measured_position_cov_det: cov_det(&self.measured),
            lockstep_timeouts,
            frame_to_thrust_ms: None,
            interrupted: false,
            faults: Vec::new(),
            camera_transport: None,
            stream_delay_estimate_frames: None,
            stream_added_latency_p50_ms: None,
            stream_added_latency_p99_ms: None,
            vision_nees: None,
            exposure_gate_stall: None,
        }
    }
}

pub fn rms(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

/// RMS of the finite samples (NaN when none is).
pub fn rms_finite(v: &[f64]) -> f64 {
    let (sum, n) = v
        .iter()
        .filter(|x| x.is_finite())
        .fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 {
        return f64::NAN;
    }
    (sum / n as f64).sqrt()
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

    /// A frame at `t` whose vision pose is `pose` (none: no detection).
    fn frame(t: f64, pose: Option<Isometry3<f64>>) -> FrameRecord {
        FrameRecord {
            seq: 0,
            stamp_s: t,
            exposure_used_us: 2000.0,
            exposure: markhold_exposure::ExposureStep {
                exposure_us: 2000.0,
                metric: 0.5,
                used_frame: true,
                roi: None,
            },
            detected: pose.is_some(),
            corners: None,
            t_cam_marker: pose,
            cov_cam: None,
            reproj_rms_px: f64::NAN,
            markers_used: u32::from(pose.is_some()),
            effort: Default::default(),
            directive: markhold_autopilot::Directive::Command,
            latency_s: 0.0,
        }
    }

    #[test]
    fn pose_position_rms_is_the_vehicle_from_the_pose_against_the_truth_over_the_last_half() {
        use nalgebra::{Translation3, UnitQuaternion};
        let t_world_marker = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, -4.0),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
        );
        let t_world_vehicle = Isometry3::from_parts(
            Translation3::new(1.3, 1.1, -4.2),
            UnitQuaternion::from_euler_angles(0.0, 0.05, -1.2),
        );
        // Camera 0.2 m ahead of the vehicle's origin, along its x.
        let t_vehicle_cam = Isometry3::translation(0.2, 0.0, 0.0);
        let t_world_cam = t_world_vehicle * t_vehicle_cam;
        let truth = Truth {
            time_s: 0.0,
            t_world_vehicle,
            t_world_cam,
            t_cam_marker: t_world_cam.inverse() * t_world_marker,
            velocity_world_mps: [0.0; 3],
            armed: true,
            mode: 2,
            pwm: [1500; 8],
            lockstep_timeouts: 0,
        };
        let t_marker_cam = truth.t_cam_marker.inverse();
        // The camera shifted 3 mm, 4 mm in the site frame: the vehicle with it, 5 mm.
        let shifted = (Isometry3::translation(0.003, 0.004, 0.0) * t_marker_cam).inverse();
        // The camera turned 0.01 rad about its own z: the camera's point stays, the
        // vehicle's, 0.2 m behind it, swings 2 * 0.2 * sin(0.005).
        let turned = (t_marker_cam * Isometry3::rotation(Vector3::z() * 0.01)).inverse();
        let lever = 2.0 * 0.2 * (0.005f64).sin();
        // Frames 0-2 are the first half: the 1 m error of frame 1 is outside the window;
        // frame 5 has no pose and does not count.
        let poses = [
            None,
            Some(Isometry3::translation(1.0, 0.0, 0.0) * truth.t_cam_marker),
            None,
            Some(shifted),
            Some(turned),
            None,
        ];
        let mut stats = RunStats::new(poses.len(), t_world_marker, Isometry3::identity());
        for (i, pose) in poses.iter().enumerate() {
            stats.push(&frame(i as f64 / 30.0, *pose), &truth);
        }
        assert!(stats.pose_pos_err_m[0].is_nan() && stats.pose_pos_err_m[5].is_nan());
        assert!((stats.pose_pos_err_m[3] - 0.005).abs() < 1e-12);
        assert!((stats.pose_pos_err_m[4] - lever).abs() < 1e-12);
        let s = stats.summary(ExposureMethod::Aaec, LightingScenario::Normal, 1, 1.0, 0);
        let expect = ((0.005f64.powi(2) + lever.powi(2)) / 2.0).sqrt();
        assert!((s.pose_position_rms_m - expect).abs() < 1e-12, "{s:?}");

        // No pose in the window: NaN (the JSON's null).
        let mut none = RunStats::new(4, t_world_marker, Isometry3::identity());
        for i in 0..4 {
            let pose = (i < 2).then_some(truth.t_cam_marker);
            none.push(&frame(f64::from(i) / 30.0, pose), &truth);
        }
        let s = none.summary(ExposureMethod::Aaec, LightingScenario::Normal, 1, 1.0, 0);
        assert!(s.pose_position_rms_m.is_nan());
        let json = serde_json::to_value(&s).unwrap();
        assert!(json["pose_position_rms_m"].is_null(), "{json}");
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
