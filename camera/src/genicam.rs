//! `genicam:<device id>` cameras (USB3 Vision / GigE Vision, e.g. FLIR Blackfly S) through
//! Aravis 0.8 (the `aravis` crate over Debian's libaravis-dev).
//!
//! At start-up: open the device (empty id: the first one Aravis finds), ExposureAuto and
//! GainAuto off, Mono8 (or an 8-bit Bayer format, converted to grey), the calibration's
//! width and height, the site's frame rate and gain, exposure chunks on where the camera
//! has them, then a small pool of buffers queued on the stream. Per frame: the newest
//! filled buffer is popped (older ones waiting behind it are queued again unread, so a
//! slow loop acts on the latest picture rather than falling behind), copied (or
//! debayered) into the caller's frame and queued again; nothing is allocated on our side
//! after start-up.
//!
//! The exposure each frame was taken with comes from the frame's `ExposureTime` chunk
//! when the camera sends chunks, else from the `ExposureTime` feature read after the
//! frame arrived. Stamps come from the buffer's camera timestamp (seconds since the
//! first frame, plus half the exposure: the middle of the exposure).

use std::ffi::CStr;

use crate::{Camera, CameraError, ExposureLimits, Frame, FrameMeta};
use aravis::glib;
use aravis::prelude::*;
use aravis::{Auto, Buffer, BufferStatus, Camera as ArvCamera, ChunkParser, PixelFormat, Stream};
use glib::object::ObjectType;
use opencv::{core, imgproc, prelude::*};

/// Buffers queued on the stream: one being filled, one being read, two spare.
pub const DEFAULT_BUFFERS: usize = 4;

const CHUNK_EXPOSURE: &CStr = c"ChunkExposureTime";

/// A GenICam camera's start-up failed.
#[derive(Debug, thiserror::Error)]
pub enum GenicamError {
    #[error("genicam:{device}: no such camera ({reason}); list the cameras with arv-tool-0.8")]
    NotFound { device: String, reason: String },
    #[error("genicam:{device}: the camera has no exposure time feature (ExposureTime or ExposureTimeAbs), so markhold cannot control its exposure")]
    NoExposureFeature { device: String },
    #[error("genicam:{device}: {feature} not accepted: {reason}")]
    Rejected {
        device: String,
        feature: &'static str,
        reason: String,
    },
    #[error("genicam:{device}: pixel format: the camera offers none of Mono8, BayerRG8, BayerGR8, BayerGB8, BayerBG8 (it has: {available})")]
    PixelFormat { device: String, available: String },
    #[error("genicam:{device}: cannot deliver {width}x{height} frames (the calibration's size): {reason}")]
    Resolution {
        device: String,
        width: u32,
        height: u32,
        reason: String,
    },
    #[error("genicam:{device}: acquisition: {reason}")]
    Stream { device: String, reason: String },
}

impl From<GenicamError> for CameraError {
    fn from(e: GenicamError) -> Self {
        let device = match &e {
            GenicamError::NotFound { device, .. }
            | GenicamError::NoExposureFeature { device }
            | GenicamError::Rejected { device, .. }
            | GenicamError::PixelFormat { device, .. }
            | GenicamError::Resolution { device, .. }
            | GenicamError::Stream { device, .. } => format!("genicam:{device}"),
        };
        match e {
            GenicamError::NotFound { reason, .. } => CameraError::NotFound { device, reason },
            GenicamError::Rejected {
                feature, reason, ..
            } => CameraError::ControlRejected {
                device,
                control: feature.to_string(),
                reason,
            },
            other => CameraError::NotFound {
                device,
                reason: other.to_string(),
            },
        }
    }
}

/// What the camera is asked for at start-up.
#[derive(Debug, Clone, Copy)]
pub struct GenicamConfig {
    /// The calibration's image size.
    pub width: u32,
    pub height: u32,
    pub fps: f64,
    /// The site's exposure range; narrowed to what the camera accepts.
    pub limits: ExposureLimits,
    /// Exposure for the first frames, us.
    pub initial_us: f64,
    /// Analog gain, dB (set when the camera has an SFNC `Gain` feature).
    pub gain_db: f64,
    /// Buffers in the stream's pool (at least 2).
    pub buffers: usize,
    /// Longest wait for one frame, seconds.
    pub frame_timeout_s: f64,
}

/// Where the exposure a frame was taken with comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExposureSource {
    /// The frame's own `ExposureTime` chunk.
    Chunk,
    /// The `ExposureTime` feature, read after the frame arrived.
    FeatureAfterFrame,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pixels {
    Mono8,
    /// 8-bit Bayer, with the OpenCV conversion code to grey.
    Bayer8(i32),
}

/// A GenICam camera with manual exposure set per frame request.
pub struct GenicamCamera {
    name: String,
    device: String,
    cam: ArvCamera,
    stream: Stream,
    chunks: Option<ChunkParser>,
    format: PixelFormat,
    pixels: Pixels,
    width: u32,
    height: u32,
    limits: ExposureLimits,
    /// Last exposure written, and what the camera read back for it.
    written_us: f64,
    readback_us: f64,
    gain_db: f64,
    timeout_us: u64,
    t0_ns: Option<u64>,
    last_stamp_s: f64,
    seq: u64,
    /// Buffers the camera could not fill (incomplete, lost packets), skipped.
    pub skipped: u64,
    /// Complete frames passed over, after the first frame delivered, because a newer one
    /// was already waiting, or because the camera had dropped newer ones while every
    /// buffer was full. (The stream's underrun statistic, logged at close, counts packets.)
    stale: u64,
    /// The stream's underrun count at the last frame delivered.
    underruns: u64,
    /// Debayered image (allocated once at start-up for Bayer cameras).
    grey: core::Mat,
}

/// # Safety
/// `err` is null or a GError Aravis set and nobody else owns.
unsafe fn free_error(err: &mut *mut glib::ffi::GError) {
    if !err.is_null() {
        glib::ffi::g_error_free(*err);
        *err = std::ptr::null_mut();
    }
}

fn msg(e: glib::Error) -> String {
    e.message().to_string()
}

/// Make Aravis's simulated camera visible (its "Fake" interface, device id `Fake_1`)
/// and, when `only` is set, hide the USB3 Vision and GigE Vision interfaces, so that
/// opening a camera touches no hardware and sends nothing on the network. For tests.
pub fn use_fake_interface(only: bool) {
    // SAFETY: the arguments are NUL-terminated static strings; Aravis copies nothing
    // and keeps no pointer to them.
    unsafe {
        aravis_sys::arv_enable_interface(c"Fake".as_ptr());
        for iface in [c"GigEVision", c"USB3Vision"] {
            if only {
                aravis_sys::arv_disable_interface(iface.as_ptr());
            } else {
                aravis_sys::arv_enable_interface(iface.as_ptr());
            }
        }
    }
}

impl GenicamCamera {
    /// Open `device` (an Aravis device id, a GigE camera's IP address, or empty for the
    /// first camera found) and prepare acquisition as `cfg` asks.
    pub fn open(device: &str, cfg: &GenicamConfig) -> Result<Self, GenicamError> {
        let id = device_id(device)?;
        let cam = open_device(device, &id)?;
        // A camera left streaming by a previous program refuses most settings.
        let _ = cam.stop_acquisition();
        let cam_bounds = exposure_manual(&cam, device)?;
        let gain_db = gain_fixed(&cam, device, cfg.gain_db)?;
        let (format, pixels) = pixel_format(&cam, device)?;
        let (w, h) = region(&cam, device, cfg)?;
        let fps = frame_rate(&cam, device, cfg.fps);
        let chunks = Self::enable_exposure_chunk(&cam, device);
        let limits = exposure_limits(device, cfg, cam_bounds, fps)?;
        let (stream, grey) = buffers(&cam, device, cfg.buffers, pixels, (w, h))?;
        let mut me = Self {
            name: format!("genicam:{device}"),
            device: device.to_string(),
            cam,
            stream,
            chunks,
            format,
            pixels,
            width: cfg.width,
            height: cfg.height,
            limits,
            written_us: f64::NAN,
            readback_us: f64::NAN,
            gain_db,
            timeout_us: frame_timeout_us(cfg.frame_timeout_s),
            t0_ns: None,
            last_stamp_s: f64::NEG_INFINITY,
            seq: 0,
            skipped: 0,
            stale: 0,
            underruns: 0,
            grey,
        };
        me.start(limits.clamp(cfg.initial_us))?;
        tracing::info!(
            camera = %me.name,
            device_id = id.as_str(),
            model = %me.cam.model_name().map(|s| s.to_string()).unwrap_or_default(),
            pixels = ?me.pixels,
            exposure_source = ?me.exposure_source(),
            min_us = limits.min_us,
            max_us = limits.max_us,
            fps,
            "GenICam camera started"
        );
        Ok(me)
    }

    /// Write the first exposure, then start acquisition.
    fn start(&mut self, initial_us: f64) -> Result<(), GenicamError> {
        self.write_exposure(initial_us)
            .map_err(|e| GenicamError::Rejected {
                device: self.device.clone(),
                feature: "ExposureTime",
                reason: e.to_string(),
            })?;
        self.cam
            .start_acquisition()
            .map_err(|e| GenicamError::Stream {
                device: self.device.clone(),
                reason: format!("AcquisitionStart: {}", msg(e)),
            })
    }

    fn enable_exposure_chunk(cam: &ArvCamera, device: &str) -> Option<ChunkParser> {
        // The binding maps these two gboolean answers to Result<(), _> (and asserts in
        // debug builds that FALSE comes with an error): call Aravis directly.
        let mut err = std::ptr::null_mut();
        // SAFETY: `cam` is a live ArvCamera; the names are static NUL-terminated
        // strings; an error Aravis sets is freed right after each call.
        let chunks = unsafe {
            let a = aravis_sys::arv_camera_are_chunks_available(cam.as_ptr(), &mut err);
            free_error(&mut err);
            let b = aravis_sys::arv_camera_is_enumeration_entry_available(
                cam.as_ptr(),
                c"ChunkSelector".as_ptr(),
                c"ExposureTime".as_ptr(),
                &mut err,
            );
            free_error(&mut err);
            a != 0 && b != 0
        };
        let has = chunks
            && cam
                .is_feature_available("ChunkExposureTime")
                .is_ok_and(|b| b);
        if !has {
            return None;
        }
        match cam.set_chunks("ExposureTime") {
            Ok(()) => cam.create_chunk_parser(),
            Err(e) => {
                tracing::warn!(device, error = %msg(e), "ExposureTime chunk not enabled: reading the feature after each frame instead");
                None
            }
        }
    }

    /// Where each frame's exposure comes from on this camera.
    pub fn exposure_source(&self) -> ExposureSource {
        if self.chunks.is_some() {
            ExposureSource::Chunk
        } else {
            ExposureSource::FeatureAfterFrame
        }
    }

    /// The device id it was opened with (empty: the first camera found).
    pub fn device(&self) -> &str {
        &self.device
    }

    fn rejected(&self, reason: String) -> CameraError {
        CameraError::ControlRejected {
            device: self.name.clone(),
            control: "ExposureTime".into(),
            reason,
        }
    }

    fn write_exposure(&mut self, t_us: f64) -> Result<f64, CameraError> {
        self.cam
            .set_exposure_time(t_us)
            .map_err(|e| self.rejected(format!("{t_us} us: {}", msg(e))))?;
        let back = self
            .cam
            .exposure_time()
            .map_err(|e| self.rejected(format!("read back: {}", msg(e))))?;
        if !(back.is_finite() && back > 0.0) {
            return Err(self.rejected(format!("{t_us} us written, {back} us read back")));
        }
        self.written_us = t_us;
        self.readback_us = back;
        Ok(back)
    }

    /// Give `buffer` back to the stream unread, counting it when it held a complete frame
    /// after the first one delivered (what queued during start-up was never the loop's).
    fn pass_over(&mut self, buffer: Buffer) {
        if buffer.status() == BufferStatus::Success && self.seq > 0 {
            self.stale += 1;
        }
        self.stream.push_buffer(buffer);
    }

    /// The exposure `buffer` was taken with.
    fn frame_exposure_us(&self, buffer: &Buffer) -> f64 {
        if let Some(parser) = &self.chunks {
            if buffer.has_chunks() {
                let mut err = std::ptr::null_mut();
                // SAFETY: parser and buffer are live GObjects; the chunk name is a
                // static NUL-terminated string; an error is freed below.
                let v = unsafe {
                    aravis_sys::arv_chunk_parser_get_float_value(
                        parser.as_ptr(),
                        buffer.as_ptr(),
                        CHUNK_EXPOSURE.as_ptr(),
                        &mut err,
                    )
                };
                if err.is_null() {
                    if v.is_finite() && v > 0.0 {
                        return v;
                    }
                } else {
                    // SAFETY: Aravis set `err`; we own it.
                    unsafe { free_error(&mut err) };
                }
            }
        }
        match self.cam.exposure_time() {
            Ok(v) if v.is_finite() && v > 0.0 => v,
            _ => self.readback_us,
        }
    }

    fn copy_image(&mut self, buffer: &Buffer, frame: &mut Frame) -> Result<(), String> {
        let (w, h) = (buffer.image_width(), buffer.image_height());
        if (w as u32, h as u32) != (self.width, self.height) {
            return Err(format!(
                "a {w}x{h} image, expected {}x{}",
                self.width, self.height
            ));
        }
        let fmt = buffer.image_pixel_format();
        if fmt != self.format {
            return Err(format!(
                "pixel format 0x{:08x}, expected 0x{:08x}",
                fmt.raw(),
                self.format.raw()
            ));
        }
        let mut size: usize = 0;
        // SAFETY: `buffer` is a live ArvBuffer; Aravis returns a pointer into its own
        // data (valid while we hold the buffer) and its length.
        let ptr = unsafe { aravis_sys::arv_buffer_get_image_data(buffer.as_ptr(), &mut size) };
        let n = self.width as usize * self.height as usize;
        if ptr.is_null() || size < n {
            return Err(format!("{size} bytes of image data, expected {n}"));
        }
        // SAFETY: checked non-null and at least `n` bytes long above.
        let data = unsafe { std::slice::from_raw_parts(ptr as *const u8, n) };
        frame.resize(self.width, self.height);
        match self.pixels {
            Pixels::Mono8 => frame.data[..n].copy_from_slice(data),
            Pixels::Bayer8(code) => {
                let src = core::Mat::new_rows_cols_with_data::<u8>(
                    self.height as i32,
                    self.width as i32,
                    data,
                )
                .map_err(|e| e.to_string())?;
                imgproc::cvt_color(&src, &mut self.grey, code, 0).map_err(|e| e.to_string())?;
                let grey = self.grey.data_bytes().map_err(|e| e.to_string())?;
                frame.data[..n].copy_from_slice(&grey[..n]);
            }
        }
        Ok(())
    }
}

/// An Aravis error on `feature` as the start-up error that names it.
fn rejected<'a>(
    device: &'a str,
    feature: &'static str,
) -> impl Fn(glib::Error) -> GenicamError + 'a {
    move |e| GenicamError::Rejected {
        device: device.to_string(),
        feature,
        reason: msg(e),
    }
}

/// The Aravis device id to open: `device` itself, or for an empty `device` "the first
/// camera": the first id of Aravis's device lists (GigE: after a discovery broadcast),
/// opened by id (not every interface opens "any").
fn device_id(device: &str) -> Result<String, GenicamError> {
    if !device.is_empty() {
        return Ok(device.to_string());
    }
    // SAFETY: Aravis guards its device lists; the id it returns is copied at once,
    // before anything can update the lists again.
    let first = unsafe {
        aravis_sys::arv_update_device_list();
        if aravis_sys::arv_get_n_devices() == 0 {
            None
        } else {
            let p = aravis_sys::arv_get_device_id(0);
            (!p.is_null()).then(|| CStr::from_ptr(p).to_string_lossy().into_owned())
        }
    };
    first.ok_or_else(|| GenicamError::NotFound {
        device: device.to_string(),
        reason: "Aravis finds no camera on USB3 Vision or GigE Vision".into(),
    })
}

fn open_device(device: &str, id: &str) -> Result<ArvCamera, GenicamError> {
    ArvCamera::new(Some(id)).map_err(|e| GenicamError::NotFound {
        device: device.to_string(),
        reason: if device.is_empty() {
            format!("the first camera found, {id}, does not open: {}", msg(e))
        } else {
            msg(e)
        },
    })
}

/// Exposure: manual. Returns the camera's exposure bounds, us.
fn exposure_manual(cam: &ArvCamera, device: &str) -> Result<(f64, f64), GenicamError> {
    if !cam.is_exposure_time_available().unwrap_or(false) {
        return Err(GenicamError::NoExposureFeature {
            device: device.to_string(),
        });
    }
    if cam.is_exposure_auto_available().unwrap_or(false) {
        cam.set_exposure_time_auto(Auto::Off)
            .map_err(rejected(device, "ExposureAuto=Off"))?;
        let now = cam
            .exposure_time_auto()
            .map_err(rejected(device, "ExposureAuto=Off"))?;
        if now != Auto::Off {
            return Err(GenicamError::Rejected {
                device: device.to_string(),
                feature: "ExposureAuto=Off",
                reason: format!("the camera reads back ExposureAuto={now:?}"),
            });
        }
    }
    cam.exposure_time_bounds()
        .map_err(rejected(device, "ExposureTime"))
}

/// Gain: fixed at `gain_db` (within the camera's range). Returns the gain the camera
/// took, dB (0 when it has no Gain feature in dB).
fn gain_fixed(cam: &ArvCamera, device: &str, gain_db: f64) -> Result<f64, GenicamError> {
    if cam.is_gain_auto_available().unwrap_or(false) {
        cam.set_gain_auto(Auto::Off)
            .map_err(rejected(device, "GainAuto=Off"))?;
    }
    let has_db_gain = cam.is_feature_available("Gain").unwrap_or(false);
    if has_db_gain {
        let (lo, hi) = cam.gain_bounds().map_err(rejected(device, "Gain"))?;
        cam.set_gain(gain_db.clamp(lo, hi))
            .map_err(rejected(device, "Gain"))?;
        cam.gain().map_err(rejected(device, "Gain"))
    } else {
        tracing::warn!(
            device,
            "the camera has no Gain (dB) feature: gain left as it is, recorded as 0 dB"
        );
        Ok(0.0)
    }
}

/// Pixel format: Mono8, else 8-bit Bayer converted to grey.
fn pixel_format(cam: &ArvCamera, device: &str) -> Result<(PixelFormat, Pixels), GenicamError> {
    let formats = cam.dup_available_pixel_formats().unwrap_or_default();
    // GenICam names the Bayer pattern by its first row, OpenCV by its second.
    let choices = [
        (PixelFormat::MONO_8, Pixels::Mono8),
        (
            PixelFormat::BAYER_RG_8,
            Pixels::Bayer8(imgproc::COLOR_BayerBG2GRAY),
        ),
        (
            PixelFormat::BAYER_GR_8,
            Pixels::Bayer8(imgproc::COLOR_BayerGB2GRAY),
        ),
        (
            PixelFormat::BAYER_GB_8,
            Pixels::Bayer8(imgproc::COLOR_BayerGR2GRAY),
        ),
        (
            PixelFormat::BAYER_BG_8,
            Pixels::Bayer8(imgproc::COLOR_BayerRG2GRAY),
        ),
    ];
    let Some(&(format, pixels)) = choices
        .iter()
        .find(|(f, _)| formats.contains(&i64::from(f.raw())))
    else {
        let names = cam
            .dup_available_pixel_formats_as_strings()
            .map(|v| v.iter().map(|s| s.to_string()).collect::<Vec<_>>())
            .unwrap_or_default();
        return Err(GenicamError::PixelFormat {
            device: device.to_string(),
            available: if names.is_empty() {
                "none listed".into()
            } else {
                names.join(", ")
            },
        });
    };
    cam.set_pixel_format(format)
        .map_err(rejected(device, "PixelFormat"))?;
    Ok((format, pixels))
}

/// Size: the calibration's, from the sensor's top-left corner. Returns the region's
/// width and height.
fn region(cam: &ArvCamera, device: &str, cfg: &GenicamConfig) -> Result<(i32, i32), GenicamError> {
    let size_err = |reason: String| GenicamError::Resolution {
        device: device.to_string(),
        width: cfg.width,
        height: cfg.height,
        reason,
    };
    let (w, h) = (
        i32::try_from(cfg.width).unwrap_or(i32::MAX),
        i32::try_from(cfg.height).unwrap_or(i32::MAX),
    );
    let (wb, hb) = (
        cam.width_bounds().map_err(|e| size_err(msg(e)))?,
        cam.height_bounds().map_err(|e| size_err(msg(e)))?,
    );
    if !(wb.0..=wb.1).contains(&w) || !(hb.0..=hb.1).contains(&h) {
        return Err(size_err(format!(
            "the camera takes {}..{} x {}..{} pixels",
            wb.0, wb.1, hb.0, hb.1
        )));
    }
    // A region of the right size already set (e.g. a centred one the calibration
    // was made with) is kept; otherwise the region starts at the top-left corner.
    let current = cam.region().map_err(|e| size_err(msg(e)))?;
    if (current.2, current.3) != (w, h) {
        cam.set_region(0, 0, w, h).map_err(|e| size_err(msg(e)))?;
    }
    let (_, _, got_w, got_h) = cam.region().map_err(|e| size_err(msg(e)))?;
    if (got_w, got_h) != (w, h) {
        return Err(size_err(format!("the camera set {got_w}x{got_h}")));
    }
    Ok((w, h))
}

/// Frame rate, where the camera lets us set it. Returns the rate the camera reports,
/// else `fps`.
fn frame_rate(cam: &ArvCamera, device: &str, fps: f64) -> f64 {
    if fps > 0.0 && cam.is_frame_rate_available().unwrap_or(false) {
        if let Err(e) = cam.set_frame_rate(fps) {
            tracing::warn!(device, fps, error = %msg(e), "frame rate not set");
        }
    }
    cam.frame_rate()
        .ok()
        .filter(|f| f.is_finite() && *f > 0.0)
        .unwrap_or(fps)
}

/// The site's exposure range narrowed to the camera's `(min, max)`, us.
fn exposure_limits(
    device: &str,
    cfg: &GenicamConfig,
    (cam_min, cam_max): (f64, f64),
    fps: f64,
) -> Result<ExposureLimits, GenicamError> {
    let limits = ExposureLimits {
        min_us: cfg.limits.min_us.max(cam_min),
        max_us: cfg.limits.max_us.min(cam_max),
        fps,
    };
    // Empty (or NaN) range: nothing the site allows can be set.
    if matches!(
        limits.min_us.partial_cmp(&limits.max_us),
        None | Some(std::cmp::Ordering::Greater)
    ) {
        return Err(GenicamError::Rejected {
            device: device.to_string(),
            feature: "ExposureTime",
            reason: format!(
                "the camera takes {cam_min}..{cam_max} us, the site asks {}..{} us",
                cfg.limits.min_us, cfg.limits.max_us
            ),
        });
    }
    Ok(limits)
}

/// Buffers: allocated once, queued on the stream; and the debayered image a Bayer
/// camera's `w` x `h` frames are converted into.
fn buffers(
    cam: &ArvCamera,
    device: &str,
    count: usize,
    pixels: Pixels,
    (w, h): (i32, i32),
) -> Result<(Stream, core::Mat), GenicamError> {
    let stream_err = |reason: String| GenicamError::Stream {
        device: device.to_string(),
        reason,
    };
    let payload = cam.payload().map_err(|e| stream_err(msg(e)))? as usize;
    let stream = cam.create_stream().map_err(|e| stream_err(msg(e)))?;
    for _ in 0..count.max(2) {
        stream.push_buffer(Buffer::new_allocate(payload));
    }
    let grey = match pixels {
        Pixels::Mono8 => core::Mat::default(),
        Pixels::Bayer8(_) => {
            core::Mat::new_rows_cols_with_default(h, w, core::CV_8UC1, core::Scalar::all(0.0))
                .map_err(|e| stream_err(e.to_string()))?
        }
    };
    Ok((stream, grey))
}

/// Longest wait for one frame, us (1 s when `timeout_s` is not a positive number).
fn frame_timeout_us(timeout_s: f64) -> u64 {
    let timeout_s = if timeout_s.is_finite() && timeout_s > 0.0 {
        timeout_s
    } else {
        1.0
    };
    (timeout_s * 1e6) as u64
}

impl Camera for GenicamCamera {
    fn name(&self) -> &str {
        &self.name
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        // The camera rounds to its own step; the read-back says what it took.
        let t = self.limits.clamp(exposure_us);
        // Unchanged: no write (each one is a round trip to the camera).
        if t == self.written_us {
            return Ok(self.readback_us);
        }
        self.write_exposure(t)
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let read_err = |me: &Self, reason: String| CameraError::Read {
            device: me.name.clone(),
            seq: me.seq,
            reason,
        };
        let mut waited = false;
        loop {
            let Some(mut buffer) = self.stream.timeout_pop_buffer(self.timeout_us) else {
                return Err(read_err(
                    self,
                    format!("no frame within {} ms", self.timeout_us / 1000),
                ));
            };
            // Frames that queued while the loop was busy are old news to a station
            // keeper: act on the newest and give the older buffers back to the camera.
            while let Some(newer) = self.stream.try_pop_buffer() {
                self.pass_over(buffer);
                buffer = newer;
            }
            // If every buffer was full, the camera dropped frames newer than the newest
            // queued one: with the pool free again, the next frame is the fresh picture
            // (at most one frame period away). Waited for once per grab.
            let underruns = self.stream.statistics().2;
            let pool_was_full = underruns != self.underruns;
            self.underruns = underruns;
            if pool_was_full && !waited {
                waited = true;
                self.pass_over(buffer);
                continue;
            }
            let status = buffer.status();
            if status != BufferStatus::Success {
                // Incomplete frame: give the buffer back and wait for the next one.
                self.skipped += 1;
                self.stream.push_buffer(buffer);
                continue;
            }
            let copied = self.copy_image(&buffer, frame);
            let exposure_us = self.frame_exposure_us(&buffer);
            let ts = match buffer.timestamp() {
                0 => buffer.system_timestamp(),
                t => t,
            };
            self.stream.push_buffer(buffer);
            copied.map_err(|r| read_err(self, r))?;
            let t0 = *self.t0_ns.get_or_insert(ts);
            let mut stamp_s = ts.wrapping_sub(t0) as i64 as f64 * 1e-9 + exposure_us * 0.5e-6;
            // The loop's clock must increase; a camera timestamp reset must not stall it.
            if stamp_s <= self.last_stamp_s {
                stamp_s = self.last_stamp_s + 1.0 / self.limits.fps.max(1.0);
            }
            self.last_stamp_s = stamp_s;
            frame.meta = FrameMeta {
                seq: self.seq,
                stamp_s,
                exposure_us,
                gain_db: self.gain_db,
            };
            self.seq += 1;
            return Ok(());
        }
    }

    fn frames_passed_over(&self) -> u64 {
        self.stale
    }
}

impl Drop for GenicamCamera {
    fn drop(&mut self) {
        let _ = self.cam.stop_acquisition();
        let (completed, failures, underruns) = self.stream.statistics();
        tracing::info!(
            camera = %self.name,
            frames = self.seq,
            completed,
            failures,
            underruns,
            skipped = self.skipped,
            stale = self.stale,
            "GenICam stream closed"
        );
    }
}
