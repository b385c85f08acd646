//! The per-frame loop, the same for live, HIL and replay: only the camera, the link and
//! where time comes from differ. Data flows one way per frame:
//! camera -> vision -> station keeper -> link, then exposure -> camera.

use std::time::Instant;

use markhold_autopilot::{Effort, PoseMeasurement, StationKeeper, VehicleLink};
use markhold_exposure::{Camera, Corners, ExposureController, ExposureStep, Frame};
use markhold_vision::{MarkerObservation, MarkerTracker};
use nalgebra::Isometry3;

/// What happened on one frame, for the summary, the recorder and tests.
#[derive(Debug, Clone, Copy)]
pub struct FrameRecord {
    pub seq: u64,
    pub stamp_s: f64,
    /// Exposure this frame was taken with.
    pub exposure_used_us: f64,
    /// Exposure commanded after this frame.
    pub exposure: ExposureStep,
    pub detected: bool,
    pub corners: Option<Corners>,
    pub t_cam_marker: Option<Isometry3<f64>>,
    pub reproj_rms_px: f64,
    pub effort: Effort,
    /// Wall time from the frame being available to the command written to the socket.
    pub latency_s: f64,
}

pub struct Pipeline {
    pub tracker: MarkerTracker,
    pub exposure: Box<dyn ExposureController>,
    pub keeper: StationKeeper,
    pub link: VehicleLink,
    pub frame: Frame,
}

impl Pipeline {
    /// Run one frame through the loop.
    pub fn step(&mut self, camera: &mut dyn Camera) -> anyhow::Result<FrameRecord> {
        camera.grab(&mut self.frame)?;
        let t0 = Instant::now();
        let stamp = self.frame.meta.stamp_s;
        let obs: Option<MarkerObservation> = self.tracker.process(&self.frame)?;
        let meas = obs.as_ref().map(|o| PoseMeasurement {
            stamp_s: stamp,
            t_cam_marker: o.t_cam_marker,
            cov_cam: o.cov_cam,
        });
        let effort = self.keeper.update(stamp, meas.as_ref());
        self.link.tick(stamp)?;
        self.link.send_effort(&effort, stamp)?;
        let latency_s = t0.elapsed().as_secs_f64();

        // Exposure after the command: it does not gate the vehicle.
        let corners = obs.as_ref().map(|o| o.corners);
        let step = self.exposure.update(&self.frame, corners.as_ref());
        camera.set_exposure_us(step.exposure_us)?;
        Ok(FrameRecord {
            seq: self.frame.meta.seq,
            stamp_s: stamp,
            exposure_used_us: self.frame.meta.exposure_us,
            exposure: step,
            detected: obs.is_some(),
            corners,
            t_cam_marker: obs.as_ref().map(|o| o.t_cam_marker),
            reproj_rms_px: obs.as_ref().map_or(f64::NAN, |o| o.reproj_rms_px),
            effort,
            latency_s,
        })
    }
}
