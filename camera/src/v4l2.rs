//! `v4l2:/dev/videoN` cameras: a V4L2 device through OpenCV's videoio with manual
//! exposure.

use crate::cv::mat_to_frame;
use crate::{Camera, CameraError, ExposureLimits, Frame, FrameMeta};
use opencv::{core, prelude::*, videoio};
use std::path::Path;

/// A V4L2 camera through OpenCV's videoio, with the driver's auto exposure off while it
/// is open (put back as found when closed).
///
/// Exposure goes through `CAP_PROP_EXPOSURE`, which the V4L2 backend maps to
/// `V4L2_CID_EXPOSURE_ABSOLUTE` in units of 100 us (`exposure_unit_us`). Each frame
/// carries the exposure read back from the driver when it was grabbed, and the
/// buffer's timestamp as its stamp.
pub struct V4l2Camera {
    name: String,
    cap: videoio::VideoCapture,
    limits: ExposureLimits,
    exposure_unit_us: f64,
    seq: u64,
    img: core::Mat,
    grey: core::Mat,
    /// Auto-exposure mode and exposure as found at open (as the backend reads them).
    found: (Option<f64>, Option<f64>),
}

impl Drop for V4l2Camera {
    /// The camera is left as found: the exposure value first (a manual value is refused
    /// while in auto exposure), then the mode.
    fn drop(&mut self) {
        if let (Some(mode), value) = self.found {
            if let Some(v) = value {
                let _ = self.cap.set(videoio::CAP_PROP_EXPOSURE, v);
            }
            let _ = self.cap.set(videoio::CAP_PROP_AUTO_EXPOSURE, mode);
        }
    }
}

impl V4l2Camera {
    /// Open `device` (`/dev/video0`, or an index such as `0`) at `width` x `height`
    /// and `fps`, with manual exposure. A missing device, or a mode the driver does
    /// not deliver, is an error naming the device.
    pub fn open(device: &str, width: u32, height: u32, fps: f64) -> Result<Self, CameraError> {
        let name = format!("v4l2:{device}");
        let not_found = |reason: String| CameraError::NotFound {
            device: device.to_string(),
            reason,
        };
        let rejected = |control: &str, reason: String| CameraError::ControlRejected {
            device: device.to_string(),
            control: control.to_string(),
            reason,
        };
        if !(fps.is_finite() && fps > 0.0) || width == 0 || height == 0 {
            return Err(rejected(
                "mode",
                format!("{width}x{height} at {fps} fps is not a valid mode"),
            ));
        }
        let cap = if let Ok(index) = device.parse::<i32>() {
            if !Path::new(&format!("/dev/video{index}")).exists() {
                return Err(not_found(format!("/dev/video{index} does not exist")));
            }
            videoio::VideoCapture::new(index, videoio::CAP_V4L2)
        } else {
            if !Path::new(device).exists() {
                return Err(not_found("no such device file".into()));
            }
            videoio::VideoCapture::from_file(device, videoio::CAP_V4L2)
        };
        let mut cap = cap.map_err(|e| not_found(e.to_string()))?;
        if !cap.is_opened().unwrap_or(false) {
            return Err(not_found("OpenCV's V4L2 backend could not open it".into()));
        }
        let set =
            |cap: &mut videoio::VideoCapture, prop: i32, v: f64| cap.set(prop, v).unwrap_or(false);
        set(&mut cap, videoio::CAP_PROP_FRAME_WIDTH, width as f64);
        set(&mut cap, videoio::CAP_PROP_FRAME_HEIGHT, height as f64);
        set(&mut cap, videoio::CAP_PROP_FPS, fps);
        let got_w = cap.get(videoio::CAP_PROP_FRAME_WIDTH).unwrap_or(0.0) as u32;
        let got_h = cap.get(videoio::CAP_PROP_FRAME_HEIGHT).unwrap_or(0.0) as u32;
        if (got_w, got_h) != (width, height) {
            return Err(rejected(
                "resolution",
                format!("asked {width}x{height}, the driver delivers {got_w}x{got_h}"),
            ));
        }
        // The mode and value found, put back when the camera is closed.
        let found = (
            cap.get(videoio::CAP_PROP_AUTO_EXPOSURE).ok(),
            cap.get(videoio::CAP_PROP_EXPOSURE).ok(),
        );
        // V4L2_EXPOSURE_MANUAL is 1; backends that normalise controls use 0.25.
        if !set(&mut cap, videoio::CAP_PROP_AUTO_EXPOSURE, 1.0)
            && !set(&mut cap, videoio::CAP_PROP_AUTO_EXPOSURE, 0.25)
        {
            return Err(rejected(
                "auto_exposure",
                "the driver did not accept manual exposure".into(),
            ));
        }
        let frame_us = 1e6 / fps;
        Ok(Self {
            name,
            cap,
            limits: ExposureLimits {
                min_us: 100.0,
                max_us: frame_us,
                fps,
            },
            exposure_unit_us: 100.0,
            seq: 0,
            img: core::Mat::default(),
            grey: core::Mat::default(),
            found,
        })
    }

    /// Override the exposure range (the V4L2 backend of OpenCV cannot query it).
    pub fn with_exposure_limits(mut self, limits: ExposureLimits) -> Self {
        self.limits = limits;
        self
    }

    /// Microseconds per unit of the driver's exposure control (100 for
    /// `V4L2_CID_EXPOSURE_ABSOLUTE`).
    pub fn with_exposure_unit_us(mut self, unit_us: f64) -> Self {
        if unit_us > 0.0 && unit_us.is_finite() {
            self.exposure_unit_us = unit_us;
        }
        self
    }

    fn read_back_us(&self) -> f64 {
        self.cap.get(videoio::CAP_PROP_EXPOSURE).unwrap_or(f64::NAN) * self.exposure_unit_us
    }
}

impl Camera for V4l2Camera {
    fn name(&self) -> &str {
        &self.name
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        let t = self.limits.clamp(exposure_us);
        let units = (t / self.exposure_unit_us).round().max(1.0);
        let ok = self
            .cap
            .set(videoio::CAP_PROP_EXPOSURE, units)
            .map_err(|e| CameraError::ControlRejected {
                device: self.name.clone(),
                control: "exposure".into(),
                reason: e.to_string(),
            })?;
        if !ok {
            return Err(CameraError::ControlRejected {
                device: self.name.clone(),
                control: "exposure".into(),
                reason: format!("{units} units of {} us refused", self.exposure_unit_us),
            });
        }
        let back = self.read_back_us();
        Ok(if back.is_finite() && back > 0.0 {
            back
        } else {
            units * self.exposure_unit_us
        })
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let read_err = |seq: u64, reason: String| CameraError::Read {
            device: self.name.clone(),
            seq,
            reason,
        };
        let ok = self
            .cap
            .read(&mut self.img)
            .map_err(|e| read_err(self.seq, e.to_string()))?;
        if !ok || self.img.empty() {
            return Err(read_err(self.seq, "no frame from the driver".into()));
        }
        mat_to_frame(&self.img, &mut self.grey, frame)
            .map_err(|e| read_err(self.seq, e.to_string()))?;
        let stamp_ms = self.cap.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(f64::NAN);
        frame.meta = FrameMeta {
            seq: self.seq,
            stamp_s: stamp_ms / 1e3,
            exposure_us: self.read_back_us(),
            gain_db: 0.0,
        };
        self.seq += 1;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_v4l2_device_is_a_clear_error() {
        for dev in ["/dev/video97", "97"] {
            let e = V4l2Camera::open(dev, 640, 480, 30.0)
                .err()
                .expect("no such device");
            let s = e.to_string();
            assert!(matches!(e, CameraError::NotFound { .. }), "{s}");
            assert!(s.contains(dev) && s.contains("video97"), "{s}");
        }
        let e = V4l2Camera::open("/dev/video97", 640, 480, 0.0)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("mode"), "{e}");
    }
}
