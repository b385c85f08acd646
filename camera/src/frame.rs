//! Frames, regions of interest, exposure limits and the camera seam.
//!
//! A [`Frame`] owns its pixel buffer so that a camera can fill the same frame every
//! tick without allocating; [`FrameMeta`] carries what the frame was really taken
//! with (a camera applies a new exposure 1-3 frames late).

use std::path::PathBuf;

/// What a frame was taken with and when.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct FrameMeta {
    /// Frame counter from the camera, starting at 0.
    pub seq: u64,
    /// Capture time (middle of the exposure), seconds on the loop's clock
    /// (simulation time in HIL, camera time on a real camera).
    pub stamp_s: f64,
    /// Exposure time this frame was really exposed with, microseconds.
    pub exposure_us: f64,
    /// Analog gain this frame was taken with, dB.
    pub gain_db: f64,
}

/// An 8-bit grey image with its metadata. Rows are packed (`stride == width`).
#[derive(Debug, Clone, Default)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
    pub meta: FrameMeta,
}

impl Frame {
    /// A black frame of the given size.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0; width as usize * height as usize],
            meta: FrameMeta::default(),
        }
    }

    /// Resize the buffer (allocates only when it grows).
    pub fn resize(&mut self, width: u32, height: u32) {
        self.width = width;
        self.height = height;
        self.data.resize(width as usize * height as usize, 0);
    }

    /// True when the buffer holds `width * height` bytes (the fields are public, so a
    /// caller can break this; controllers skip such frames instead of panicking).
    pub fn is_consistent(&self) -> bool {
        self.data.len() >= self.width as usize * self.height as usize
    }

    pub fn view(&self) -> ImageView<'_> {
        ImageView {
            width: self.width as usize,
            height: self.height as usize,
            stride: self.width as usize,
            data: &self.data,
        }
    }

    pub fn full_roi(&self) -> Roi {
        Roi {
            x: 0,
            y: 0,
            width: self.width,
            height: self.height,
        }
    }
}

/// A borrowed 8-bit grey image (possibly a window into a larger one).
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    pub width: usize,
    pub height: usize,
    /// Bytes between the starts of two rows.
    pub stride: usize,
    pub data: &'a [u8],
}

impl<'a> ImageView<'a> {
    /// A view over packed rows; errors if the buffer is too short.
    pub fn new(width: usize, height: usize, data: &'a [u8]) -> Result<Self, CameraError> {
        if data.len() < width * height {
            return Err(CameraError::BufferTooSmall {
                width,
                height,
                len: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            stride: width,
            data,
        })
    }

    pub fn row(&self, y: usize) -> &'a [u8] {
        let start = y * self.stride;
        &self.data[start..start + self.width]
    }

    /// The part of this view inside `roi` (clamped to the image; may be empty).
    pub fn crop(&self, roi: Roi) -> ImageView<'a> {
        let r = roi.clamp_to(self.width as u32, self.height as u32);
        if r.is_empty() {
            return ImageView {
                width: 0,
                height: 0,
                stride: self.stride,
                data: &self.data[..0],
            };
        }
        let start = r.y as usize * self.stride + r.x as usize;
        let end = (r.y + r.height - 1) as usize * self.stride + (r.x + r.width) as usize;
        ImageView {
            width: r.width as usize,
            height: r.height as usize,
            stride: self.stride,
            data: &self.data[start..end],
        }
    }
}

/// Marker corners in pixels, in OpenCV aruco order (top-left, top-right,
/// bottom-right, bottom-left as printed on the marker).
pub type Corners = [[f32; 2]; 4];

/// An axis-aligned pixel rectangle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct Roi {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Roi {
    /// The rectangle from corner (`x0`, `y0`) up to (`x1`, `y1`), excluded; empty where
    /// `x1 <= x0` or `y1 <= y0`.
    pub fn between(x0: u32, y0: u32, x1: u32, y1: u32) -> Roi {
        Roi {
            x: x0,
            y: y0,
            width: x1.saturating_sub(x0),
            height: y1.saturating_sub(y0),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.width == 0 || self.height == 0
    }

    pub fn area(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    /// The smallest rectangle holding both (an empty one is ignored).
    pub fn union(&self, other: &Roi) -> Roi {
        if other.is_empty() {
            return *self;
        }
        if self.is_empty() {
            return *other;
        }
        let x0 = self.x.min(other.x);
        let y0 = self.y.min(other.y);
        let x1 = (self.x + self.width).max(other.x + other.width);
        let y1 = (self.y + self.height).max(other.y + other.height);
        Roi {
            x: x0,
            y: y0,
            width: x1 - x0,
            height: y1 - y0,
        }
    }

    /// This rectangle intersected with a `w` x `h` image.
    pub fn clamp_to(&self, w: u32, h: u32) -> Roi {
        let x0 = self.x.min(w);
        let y0 = self.y.min(h);
        let x1 = self.x.saturating_add(self.width).min(w);
        let y1 = self.y.saturating_add(self.height).min(h);
        Roi::between(x0, y0, x1, y1)
    }

    /// Bounding box of the corners, padded on each side by `pad_frac` of the box's
    /// width and height, clamped to a `w` x `h` image. `None` when nothing of the box
    /// is inside the image or a corner is not finite.
    pub fn from_corners_padded(corners: &Corners, pad_frac: f32, w: u32, h: u32) -> Option<Roi> {
        if corners.iter().flatten().any(|v| !v.is_finite()) {
            return None;
        }
        let (mut x0, mut y0, mut x1, mut y1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
        for c in corners {
            x0 = x0.min(c[0]);
            y0 = y0.min(c[1]);
            x1 = x1.max(c[0]);
            y1 = y1.max(c[1]);
        }
        let (bw, bh) = (x1 - x0, y1 - y0);
        let x0 = (x0 - pad_frac * bw).floor().max(0.0);
        let y0 = (y0 - pad_frac * bh).floor().max(0.0);
        let x1 = (x1 + pad_frac * bw).ceil().min(w as f32);
        let y1 = (y1 + pad_frac * bh).ceil().min(h as f32);
        if x1 <= x0 || y1 <= y0 {
            return None;
        }
        Some(Roi::between(x0 as u32, y0 as u32, x1 as u32, y1 as u32))
    }
}

/// Exposure range a camera accepts. The usable maximum is also bounded by the frame
/// period: a frame cannot be exposed longer than 1/fps.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExposureLimits {
    pub min_us: f64,
    pub max_us: f64,
    pub fps: f64,
}

impl ExposureLimits {
    /// The longest exposure really possible: `min(max_us, 1e6 / fps)`.
    pub fn effective_max_us(&self) -> f64 {
        if self.fps > 0.0 {
            self.max_us.min(1e6 / self.fps)
        } else {
            self.max_us
        }
    }

    /// `t` clamped into the usable range (NaN maps to the minimum).
    pub fn clamp(&self, t_us: f64) -> f64 {
        if t_us.is_nan() {
            return self.min_us;
        }
        t_us.clamp(self.min_us, self.effective_max_us().max(self.min_us))
    }
}

/// Errors of this crate: what a camera reports (named fields say which device and what
/// went wrong), a recording folder's file and line, an image buffer too small.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("camera {device}: not found or cannot be opened: {reason}")]
    NotFound { device: String, reason: String },
    #[error("camera {device}: {control} not accepted: {reason}")]
    ControlRejected {
        device: String,
        control: String,
        reason: String,
    },
    #[error("camera {device}: frame {seq} could not be read: {reason}")]
    Read {
        device: String,
        seq: u64,
        reason: String,
    },
    #[error("camera {device}: no more frames")]
    EndOfStream { device: String },
    #[error("image buffer of {len} bytes is too small for {width}x{height}")]
    BufferTooSmall {
        width: usize,
        height: usize,
        len: usize,
    },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}, line {line}: {reason}")]
    Recording {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("frame is {width}x{height} but {what} expects {expected_width}x{expected_height}")]
    FrameSize {
        what: &'static str,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[cfg(feature = "opencv")]
    #[error("OpenCV {op}: {source}")]
    OpenCv {
        op: &'static str,
        #[source]
        source: opencv::Error,
    },
}

/// A source of frames whose exposure time can be commanded.
///
/// `grab` fills a caller-owned frame so that the per-frame path allocates nothing.
pub trait Camera {
    /// Short human name for logs and errors (`hil`, `v4l2:/dev/video0`, ...).
    fn name(&self) -> &str;
    /// Exposure limits of this camera.
    fn exposure_limits(&self) -> ExposureLimits;
    /// Request an exposure for the coming frames; returns the value the camera will
    /// really use (clamped or rounded by the driver). It may take effect late.
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError>;
    /// Wait for the next frame and write it into `frame`.
    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError>;
    /// Frames the camera took after the first one it delivered that `grab` passed over
    /// for a newer one, because the loop was slower than the camera. Cameras that deliver
    /// every frame say 0.
    fn frames_passed_over(&self) -> u64 {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_over_too_short_a_buffer_is_refused_with_the_sizes() {
        let data = [0u8; 11];
        let e = ImageView::new(4, 3, &data).expect_err("11 bytes < 4x3");
        assert!(
            matches!(
                e,
                CameraError::BufferTooSmall {
                    width: 4,
                    height: 3,
                    len: 11
                }
            ),
            "{e}"
        );
        assert_eq!(
            e.to_string(),
            "image buffer of 11 bytes is too small for 4x3"
        );
        let v = ImageView::new(4, 3, &[7u8; 12]).expect("12 bytes hold 4x3");
        assert_eq!((v.width, v.height, v.stride), (4, 3, 4));
        assert_eq!(v.row(2), &[7, 7, 7, 7]);
    }
}
