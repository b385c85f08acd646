//! Exposure out for a stream camera: the video comes over the network, the exposure
//! goes to the camera another way, chosen by the site's `[camera.control]`.
//!
//! - `blueos_rest`: BlueOS's camera manager (mavlink-camera-manager) REST API.
//!   `GET /v4l` lists the video sources, each `{name, source, formats, controls}`, a
//!   control being `{name, cpp_type, id, state, configuration}` with `configuration`
//!   one of `{"Slider": {default, value, step, max, min}}`, `{"Menu": {default, value,
//!   options}}` or `{"Bool": {default, value}}`. `POST /v4l` with
//!   `{"device": "/dev/videoN", "v4l_id": <id>, "value": <i64>}` sets one control; the
//!   server refuses a value outside a slider's range, a menu value not among its
//!   options, and any write to a control flagged inactive (the exposure time while the
//!   camera is in auto exposure). The ids are V4L2 control ids: `auto_exposure`
//!   (V4L2_CID_EXPOSURE_AUTO, 0x009a0901; 1 = manual, 3 = aperture priority) and
//!   `exposure_time_absolute` (V4L2_CID_EXPOSURE_ABSOLUTE, 0x009a0902, units of 100 us).
//! - `v4l2`: the same two controls through a control-only handle on `/dev/videoN`
//!   (VIDIOC_QUERYCTRL / VIDIOC_S_CTRL / VIDIOC_G_CTRL), while the camera manager keeps
//!   streaming from it (V4L2 allows several opens; only the streaming one owns buffers).
//! - `none`: the exposure is left to the camera.
//!
//! Opening a control only reads: the mode and value found are kept, and nothing is
//! written until the loop takes the camera ([`ExposureControl::take`], when the pilot
//! engages markhold). [`ExposureControl::restore`] puts back what was found, the value
//! first (a manual value is refused while the camera is in auto exposure), then the
//! mode. These calls block on the network: the loop reaches them through
//! `markhold_field::camera::worker::ControlHandle`, on a thread of their own.

use std::net::{SocketAddr, ToSocketAddrs};
use std::time::Duration;

use markhold_exposure::ExposureLimits;
use serde::{Deserialize, Serialize};

pub mod http;

use self::http::{sanitize, Limits};

/// V4L2_CID_EXPOSURE_AUTO.
pub const CID_EXPOSURE_AUTO: u64 = 0x009a_0901;
/// V4L2_CID_EXPOSURE_ABSOLUTE (units of 100 us).
pub const CID_EXPOSURE_ABSOLUTE: u64 = 0x009a_0902;
/// V4L2_EXPOSURE_MANUAL.
pub const EXPOSURE_MANUAL: i64 = 1;
/// One unit of V4L2_CID_EXPOSURE_ABSOLUTE, microseconds.
pub const V4L2_EXPOSURE_UNIT_US: f64 = 100.0;

/// `exposure_absolute` units nearest `us` on the control's step, within its range.
fn exposure_units(us: f64, step_us: f64, min_units: i64, max_units: i64) -> i64 {
    let step = (step_us / V4L2_EXPOSURE_UNIT_US).max(1.0);
    let u = ((us / V4L2_EXPOSURE_UNIT_US) / step).round() * step;
    // `as` saturates (NaN to 0); the clamp keeps it in the camera's range.
    (u as i64).clamp(min_units, max_units)
}

/// A V4L2 camera's exposure controls, however they are reached (BlueOS's REST API or
/// the device's ioctls), and the exposure markhold last set on it.
trait V4l2Writes {
    /// Write control `id`.
    fn write(&self, id: u64, value: i64) -> Result<(), ControlError>;
    /// The camera has an auto-exposure control.
    fn has_auto(&self) -> bool;
    /// The exposure the camera runs at as far as markhold knows (NaN: unknown), us.
    fn current_us(&mut self) -> &mut f64;
}

/// [`V4l2Writes`] for a control with `has_auto` and `current_us` fields that writes a
/// control with its method `$write`.
macro_rules! v4l2_writes {
    ($control:ty, $write:ident) => {
        impl V4l2Writes for $control {
            fn write(&self, id: u64, value: i64) -> Result<(), ControlError> {
                self.$write(id, value)
            }
            fn has_auto(&self) -> bool {
                self.has_auto
            }
            fn current_us(&mut self) -> &mut f64 {
                &mut self.current_us
            }
        }
    };
}

/// Set `exposure_absolute` to `units` unless the camera already runs there; the exposure
/// it runs at after, us.
fn set_units(c: &mut impl V4l2Writes, units: i64) -> Result<f64, ControlError> {
    let want = units as f64 * V4L2_EXPOSURE_UNIT_US;
    if (want - *c.current_us()).abs() < 0.5 {
        return Ok(*c.current_us());
    }
    c.write(CID_EXPOSURE_ABSOLUTE, units)?;
    *c.current_us() = want;
    Ok(want)
}

/// Put back what was found: the value while still manual (an inactive control refuses
/// writes), then the mode. The found value is the camera's own: not clamped to the
/// site's range.
fn restore_found(c: &mut impl V4l2Writes, found: &Found) -> Result<(), ControlError> {
    c.write(CID_EXPOSURE_ABSOLUTE, found.exposure_units)?;
    if let (true, Some(mode)) = (c.has_auto(), found.auto_exposure) {
        c.write(CID_EXPOSURE_AUTO, mode)?;
    }
    *c.current_us() = found.known_us();
    Ok(())
}

/// `[camera.control]` of a site file.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "snake_case")]
pub enum ControlConfig {
    /// Leave exposure to the camera.
    #[default]
    None,
    /// BlueOS camera manager REST API at `url` (e.g. `http://192.168.2.2:6020`), for
    /// the source `device` (empty: the first one with an absolute exposure control).
    BlueosRest {
        url: String,
        #[serde(default)]
        device: String,
    },
    /// V4L2 controls on `device` (e.g. `/dev/video2`), beside the camera manager.
    V4l2 { device: String },
}

#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    #[error("camera manager at {url}: {reason}")]
    Rest { url: String, reason: String },
    #[error("V4L2 controls of {device}: {reason}")]
    V4l2 { device: String, reason: String },
}

/// The camera's exposure as markhold found it (and puts back).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Found {
    /// `auto_exposure` (V4L2 menu value), if the camera has the control.
    pub auto_exposure: Option<i64>,
    /// `exposure_time_absolute`, 100 us units.
    pub exposure_units: i64,
}

impl Found {
    /// The exposure the camera runs at as found, microseconds: known only in manual
    /// mode (NaN while the camera's own auto exposure runs).
    pub fn known_us(&self) -> f64 {
        match self.auto_exposure {
            Some(EXPOSURE_MANUAL) | None => self.exposure_units as f64 * V4L2_EXPOSURE_UNIT_US,
            Some(_) => f64::NAN,
        }
    }
}

/// Sets the camera's exposure, in its own units. Calls block (network, ioctl): the
/// loop never calls them itself (see `markhold_field::camera::worker`).
pub trait ExposureControl: Send {
    /// False when commands change nothing (`none`): frames then carry no exposure.
    fn controls(&self) -> bool {
        true
    }
    /// The mode and value found when the control was opened.
    fn found(&self) -> Option<Found>;
    /// Manual exposure (the first write; after it, `set_exposure_us`).
    fn take(&mut self) -> Result<(), ControlError>;
    /// Sets the exposure; returns the value set (quantized to the camera's step and
    /// clamped to its range).
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError>;
    /// Puts back `found`: the value first, then the mode.
    fn restore_to(&mut self, found: &Found) -> Result<(), ControlError>;
    /// The camera's exposure step, microseconds (0: continuous).
    fn step_us(&self) -> f64;
    /// Where the commands go, for messages and the state file.
    fn describe(&self) -> String;
}

/// Round `us` to the camera's step (at least one step).
pub fn quantize(us: f64, step_us: f64) -> f64 {
    if step_us <= 0.0 {
        return us;
    }
    ((us / step_us).round() * step_us).max(step_us)
}

/// Exposure left to the camera: commands change nothing.
pub struct NoControl;

impl ExposureControl for NoControl {
    fn controls(&self) -> bool {
        false
    }
    fn found(&self) -> Option<Found> {
        None
    }
    fn take(&mut self) -> Result<(), ControlError> {
        Ok(())
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        Ok(exposure_us)
    }
    fn restore_to(&mut self, _found: &Found) -> Result<(), ControlError> {
        Ok(())
    }
    fn step_us(&self) -> f64 {
        0.0
    }
    fn describe(&self) -> String {
        "none".into()
    }
}

/// One video source of `GET /v4l`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ApiVideoSource {
    pub name: String,
    pub source: String,
    #[serde(default)]
    pub formats: serde_json::Value,
    pub controls: Vec<ApiControl>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ApiControl {
    pub name: String,
    #[serde(default)]
    pub cpp_type: String,
    pub id: u64,
    #[serde(default)]
    pub state: serde_json::Value,
    pub configuration: ApiControlType,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub enum ApiControlType {
    Bool {
        default: i64,
        value: i64,
    },
    Slider {
        default: i64,
        value: i64,
        step: u64,
        max: i64,
        min: i64,
    },
    Menu {
        default: i64,
        value: i64,
        options: serde_json::Value,
    },
}

impl ApiControlType {
    pub fn value(&self) -> i64 {
        match self {
            Self::Bool { value, .. } | Self::Slider { value, .. } | Self::Menu { value, .. } => {
                *value
            }
        }
    }
}

/// The body of `POST /v4l`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct V4lControl<'a> {
    pub device: &'a str,
    pub v4l_id: u64,
    pub value: i64,
}

/// How long one request may take, all of it (connect, send, the whole answer).
pub const REST_DEADLINE: Duration = Duration::from_secs(2);
/// The largest `GET /v4l` answer read (every source with its formats).
pub const MAX_SOURCES_BYTES: usize = 4 << 20;
/// The largest answer to a `POST` read (the camera manager answers an empty body).
pub const MAX_POST_REPLY_BYTES: usize = 64 << 10;
/// Characters of a peer's error text kept in a message.
pub const ERROR_TEXT_CHARS: usize = 200;

/// The camera's exposure range in its units, as the server states it and as the site
/// allows: the intersection, or an error naming both.
fn unit_range(
    step: u64,
    min: i64,
    max: i64,
    limits: &ExposureLimits,
) -> Result<(i64, i64, f64), String> {
    // V4L2 integer controls are 32-bit: anything beyond is not a real camera's range.
    let fits = |v: i64| (i64::from(i32::MIN)..=i64::from(i32::MAX)).contains(&v);
    if !fits(min) || !fits(max) || min > max || step == 0 || step > i32::MAX as u64 {
        return Err(format!(
            "exposure_time_absolute has min {min}, max {max}, step {step}: not a camera's range"
        ));
    }
    let site_lo = (limits.min_us / V4L2_EXPOSURE_UNIT_US).ceil() as i64;
    let site_hi = (limits.effective_max_us() / V4L2_EXPOSURE_UNIT_US).floor() as i64;
    let lo = min.max(1).max(site_lo);
    let hi = max.min(site_hi);
    if lo > hi {
        return Err(format!(
            "exposure_time_absolute's range {min}..{max} x 100 us does not meet the site's \
             camera.exposure_min_us..exposure_max_us ({}..{} us)",
            limits.min_us,
            limits.effective_max_us()
        ));
    }
    Ok((lo, hi, V4L2_EXPOSURE_UNIT_US * step as f64))
}

/// Whether a menu's `options` list `value` (an unreadable list: assume it does).
fn menu_has(options: &serde_json::Value, value: i64) -> bool {
    match options.as_array() {
        Some(list) => list
            .iter()
            .any(|o| o.get("value").and_then(serde_json::Value::as_i64) == Some(value)),
        None => true,
    }
}

/// Exposure through the camera manager's REST API.
pub struct BlueosRest {
    url: String,
    addr: SocketAddr,
    host: String,
    device: String,
    step_us: f64,
    min_units: i64,
    max_units: i64,
    /// The camera has an `auto_exposure` control (and it offers manual).
    has_auto: bool,
    found: Found,
    /// The value in force (the last one the server accepted), microseconds.
    current_us: f64,
}

impl BlueosRest {
    /// Connects and finds the source's exposure controls, their range (intersected with
    /// the site's `limits`) and their values; writes nothing.
    pub fn open(url: &str, device: &str, limits: &ExposureLimits) -> Result<Self, ControlError> {
        let err = |reason: String| ControlError::Rest {
            url: url.to_string(),
            reason,
        };
        let hostport = url
            .strip_prefix("http://")
            .ok_or_else(|| err("expected http://HOST:PORT".into()))?
            .trim_end_matches('/');
        let addr = hostport
            .to_socket_addrs()
            .map_err(|e| err(format!("bad address {hostport:?}: {e}")))?
            .next()
            .ok_or_else(|| err(format!("{hostport:?} resolves to no address")))?;
        let mut c = Self {
            url: url.trim_end_matches('/').to_string(),
            addr,
            host: hostport.to_string(),
            device: device.to_string(),
            step_us: V4L2_EXPOSURE_UNIT_US,
            min_units: 1,
            max_units: 1,
            has_auto: false,
            found: Found {
                auto_exposure: None,
                exposure_units: 0,
            },
            current_us: f64::NAN,
        };
        let sources = c.sources()?;
        let src = sources
            .iter()
            .find(|s| {
                (c.device.is_empty() || s.source == c.device)
                    && s.controls.iter().any(|k| k.id == CID_EXPOSURE_ABSOLUTE)
            })
            .ok_or_else(|| {
                err(format!(
                    "no video source{} with exposure_time_absolute (0x{CID_EXPOSURE_ABSOLUTE:08x}) among {}",
                    if c.device.is_empty() { String::new() } else { format!(" {}", sanitize(c.device.as_bytes(), 80)) },
                    sanitize(format!("{:?}", sources.iter().map(|s| s.source.as_str()).collect::<Vec<_>>()).as_bytes(), ERROR_TEXT_CHARS)
                ))
            })?;
        c.device = src.source.clone();
        let control = |id: u64| src.controls.iter().find(|k| k.id == id);
        let Some(ApiControlType::Slider {
            step,
            min,
            max,
            value,
            ..
        }) = control(CID_EXPOSURE_ABSOLUTE).map(|k| &k.configuration)
        else {
            return Err(err(format!(
                "{}: exposure_time_absolute is not a slider",
                sanitize(c.device.as_bytes(), 80)
            )));
        };
        let (lo, hi, step_us) = unit_range(*step, *min, *max, limits)
            .map_err(|r| err(format!("{}: {r}", sanitize(c.device.as_bytes(), 80))))?;
        (c.min_units, c.max_units, c.step_us) = (lo, hi, step_us);
        let auto = match control(CID_EXPOSURE_AUTO).map(|k| &k.configuration) {
            Some(ApiControlType::Menu { value, options, .. }) => {
                if !menu_has(options, EXPOSURE_MANUAL) {
                    return Err(err(format!(
                        "{}: auto_exposure offers no manual mode ({EXPOSURE_MANUAL})",
                        sanitize(c.device.as_bytes(), 80)
                    )));
                }
                Some(*value)
            }
            _ => None,
        };
        c.has_auto = auto.is_some();
        c.found = Found {
            auto_exposure: auto,
            exposure_units: *value,
        };
        c.current_us = c.found.known_us();
        Ok(c)
    }

    /// The source (device path) whose exposure this sets.
    pub fn device(&self) -> &str {
        &self.device
    }

    fn units(&self, us: f64) -> i64 {
        exposure_units(us, self.step_us, self.min_units, self.max_units)
    }

    fn err(&self, reason: String) -> ControlError {
        ControlError::Rest {
            url: self.url.clone(),
            reason,
        }
    }

    fn call(
        &self,
        method: &str,
        path: &str,
        body: &[u8],
        max_body: usize,
    ) -> Result<Vec<u8>, ControlError> {
        let what = format!("{method} {path}");
        let reply = http::request(
            self.addr,
            &self.host,
            method,
            path,
            body,
            Limits {
                deadline: REST_DEADLINE,
                max_head: 16 << 10,
                max_body,
            },
        )
        .map_err(|e| self.err(format!("{what}: {e}")))?;
        if !(200..300).contains(&reply.status) {
            return Err(self.err(format!(
                "{what}: HTTP {}: {}",
                reply.status,
                sanitize(reply.body.trim_ascii(), ERROR_TEXT_CHARS)
            )));
        }
        Ok(reply.body)
    }

    /// `GET /v4l`.
    pub fn sources(&self) -> Result<Vec<ApiVideoSource>, ControlError> {
        let body = self.call("GET", "/v4l", b"", MAX_SOURCES_BYTES)?;
        serde_json::from_slice(&body).map_err(|e| {
            self.err(format!(
                "GET /v4l: unexpected answer: {}",
                sanitize(e.to_string().as_bytes(), ERROR_TEXT_CHARS)
            ))
        })
    }

    fn post(&self, id: u64, value: i64) -> Result<(), ControlError> {
        let body = serde_json::to_vec(&V4lControl {
            device: &self.device,
            v4l_id: id,
            value,
        })
        .map_err(|e| self.err(format!("POST /v4l: {e}")))?;
        self.call("POST", "/v4l", &body, MAX_POST_REPLY_BYTES)
            .map(|_| ())
    }
}

v4l2_writes!(BlueosRest, post);

impl ExposureControl for BlueosRest {
    fn found(&self) -> Option<Found> {
        Some(self.found)
    }
    fn take(&mut self) -> Result<(), ControlError> {
        if self.has_auto {
            self.post(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL)?;
        }
        // The value the camera ran at is unknown until markhold sets one.
        self.current_us = f64::NAN;
        Ok(())
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        let units = self.units(exposure_us);
        set_units(self, units)
    }
    fn restore_to(&mut self, found: &Found) -> Result<(), ControlError> {
        restore_found(self, found)
    }
    fn step_us(&self) -> f64 {
        self.step_us
    }
    fn describe(&self) -> String {
        format!("{} ({})", self.url, sanitize(self.device.as_bytes(), 80))
    }
}

/// `struct v4l2_control`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct V4l2Ctrl {
    id: u32,
    value: i32,
}

/// `struct v4l2_queryctrl`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct V4l2QueryCtrl {
    id: u32,
    kind: u32,
    name: [u8; 32],
    minimum: i32,
    maximum: i32,
    step: i32,
    default_value: i32,
    flags: u32,
    reserved: [u32; 2],
}

/// `_IOWR('V', nr, size)`.
const fn iowr(nr: u32, size: usize) -> libc::c_ulong {
    ((3u32 << 30) | ((size as u32) << 16) | ((b'V' as u32) << 8) | nr) as libc::c_ulong
}
const VIDIOC_G_CTRL: libc::c_ulong = iowr(27, std::mem::size_of::<V4l2Ctrl>());
const VIDIOC_S_CTRL: libc::c_ulong = iowr(28, std::mem::size_of::<V4l2Ctrl>());
const VIDIOC_QUERYCTRL: libc::c_ulong = iowr(36, std::mem::size_of::<V4l2QueryCtrl>());

/// Exposure through V4L2 controls on a handle that does not stream.
pub struct V4l2Control {
    device: String,
    file: std::fs::File,
    step_us: f64,
    min_units: i64,
    max_units: i64,
    has_auto: bool,
    found: Found,
    current_us: f64,
}

impl V4l2Control {
    /// Opens `device` and reads the exposure control's range (intersected with the
    /// site's `limits`) and the mode and value in force; writes nothing.
    pub fn open(device: &str, limits: &ExposureLimits) -> Result<Self, ControlError> {
        use std::os::unix::fs::OpenOptionsExt;
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(device)
            .map_err(|e| ControlError::V4l2 {
                device: device.to_string(),
                reason: format!("cannot open it: {e}"),
            })?;
        let mut c = Self {
            device: device.to_string(),
            file,
            step_us: V4L2_EXPOSURE_UNIT_US,
            min_units: 1,
            max_units: 1,
            has_auto: false,
            found: Found {
                auto_exposure: None,
                exposure_units: 0,
            },
            current_us: f64::NAN,
        };
        let q = c.query(CID_EXPOSURE_ABSOLUTE)?;
        let (lo, hi, step_us) = unit_range(
            u64::try_from(q.step).unwrap_or(0),
            i64::from(q.minimum),
            i64::from(q.maximum),
            limits,
        )
        .map_err(|r| c.err(r))?;
        (c.min_units, c.max_units, c.step_us) = (lo, hi, step_us);
        c.has_auto = c.query(CID_EXPOSURE_AUTO).is_ok();
        c.found = Found {
            auto_exposure: if c.has_auto {
                Some(c.get(CID_EXPOSURE_AUTO)?)
            } else {
                None
            },
            exposure_units: c.get(CID_EXPOSURE_ABSOLUTE)?,
        };
        c.current_us = c.found.known_us();
        Ok(c)
    }

    fn err(&self, reason: String) -> ControlError {
        ControlError::V4l2 {
            device: self.device.clone(),
            reason,
        }
    }

    fn ioctl<T>(&self, req: libc::c_ulong, arg: &mut T, what: &str) -> Result<(), ControlError> {
        use std::os::fd::AsRawFd;
        // SAFETY: `arg` is the `#[repr(C)]` struct the request's size encodes, borrowed
        // mutably for the call; the fd is open for the lifetime of `self.file`.
        let r = unsafe { libc::ioctl(self.file.as_raw_fd(), req, std::ptr::from_mut(arg)) };
        if r < 0 {
            return Err(self.err(format!("{what}: {}", std::io::Error::last_os_error())));
        }
        Ok(())
    }

    fn query(&self, id: u64) -> Result<V4l2QueryCtrl, ControlError> {
        let mut q = V4l2QueryCtrl {
            id: id as u32,
            kind: 0,
            name: [0; 32],
            minimum: 0,
            maximum: 0,
            step: 0,
            default_value: 0,
            flags: 0,
            reserved: [0; 2],
        };
        let name = if id == CID_EXPOSURE_AUTO {
            "auto_exposure"
        } else {
            "exposure_time_absolute"
        };
        self.ioctl(
            VIDIOC_QUERYCTRL,
            &mut q,
            &format!("VIDIOC_QUERYCTRL 0x{id:08x} ({name})"),
        )?;
        Ok(q)
    }

    fn set(&self, id: u64, value: i64) -> Result<(), ControlError> {
        let mut c = V4l2Ctrl {
            id: id as u32,
            value: value.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
        };
        self.ioctl(VIDIOC_S_CTRL, &mut c, "VIDIOC_S_CTRL")
    }

    fn get(&self, id: u64) -> Result<i64, ControlError> {
        let mut c = V4l2Ctrl {
            id: id as u32,
            value: 0,
        };
        self.ioctl(VIDIOC_G_CTRL, &mut c, "VIDIOC_G_CTRL")?;
        Ok(i64::from(c.value))
    }
}

v4l2_writes!(V4l2Control, set);

impl ExposureControl for V4l2Control {
    fn found(&self) -> Option<Found> {
        Some(self.found)
    }
    fn take(&mut self) -> Result<(), ControlError> {
        if self.has_auto {
            self.set(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL)?;
            let auto = self.get(CID_EXPOSURE_AUTO)?;
            if auto != EXPOSURE_MANUAL {
                return Err(self.err(format!(
                    "auto_exposure reads {auto} after setting manual ({EXPOSURE_MANUAL})"
                )));
            }
        }
        self.current_us = f64::NAN;
        Ok(())
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        let units = exposure_units(exposure_us, self.step_us, self.min_units, self.max_units);
        set_units(self, units)
    }
    fn restore_to(&mut self, found: &Found) -> Result<(), ControlError> {
        restore_found(self, found)
    }
    fn step_us(&self) -> f64 {
        self.step_us
    }
    fn describe(&self) -> String {
        self.device.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: ExposureLimits = ExposureLimits {
        min_us: 100.0,
        max_us: 33_300.0,
        fps: 30.0,
    };

    #[test]
    fn ioctl_numbers_match_videodev2() {
        // From linux/videodev2.h on x86_64 and aarch64.
        assert_eq!(VIDIOC_G_CTRL, 0xc008_561b);
        assert_eq!(VIDIOC_S_CTRL, 0xc008_561c);
        assert_eq!(VIDIOC_QUERYCTRL, 0xc044_5624);
    }

    #[test]
    fn v4l2_errors_name_the_device() {
        let e = V4l2Control::open("/no/such/video9", &LIMITS)
            .err()
            .map(|e| e.to_string());
        assert!(
            e.as_deref().is_some_and(|e| e.contains("/no/such/video9")),
            "{e:?}"
        );
        // Not a V4L2 device: the ioctl is refused, and the error says which.
        let e = V4l2Control::open("/dev/null", &LIMITS)
            .err()
            .map(|e| e.to_string());
        assert!(
            e.as_deref()
                .is_some_and(|e| e.contains("/dev/null") && e.contains("VIDIOC_QUERYCTRL")),
            "{e:?}"
        );
    }

    #[test]
    fn quantizes_to_the_step() {
        assert_eq!(quantize(3049.0, 100.0), 3000.0);
        assert_eq!(quantize(3050.0, 100.0), 3100.0);
        assert_eq!(quantize(10.0, 100.0), 100.0);
        assert_eq!(quantize(1234.5, 0.0), 1234.5);
    }

    #[test]
    fn a_range_is_the_camera_s_within_the_site_s_or_refused() {
        // The stock camera: 1..5000 x 100 us; the site caps at one frame (33.3 ms).
        assert_eq!(unit_range(1, 1, 5000, &LIMITS), Ok((1, 333, 100.0)));
        for (step, min, max) in [
            (1, i64::MAX, i64::MAX),
            (1, 10, 5),
            (0, 1, 5000),
            (1, i64::MIN, 5000),
            (1, 400, 5000),
        ] {
            let e = unit_range(step, min, max, &LIMITS);
            assert!(e.is_err(), "{step} {min} {max}: {e:?}");
        }
    }

    #[test]
    fn found_exposure_is_known_only_in_manual_mode() {
        let f = |a| Found {
            auto_exposure: a,
            exposure_units: 30,
        };
        assert_eq!(f(Some(1)).known_us(), 3000.0);
        assert_eq!(f(None).known_us(), 3000.0);
        assert!(f(Some(3)).known_us().is_nan());
    }
}
