//! Exposure out for a stream camera: the video comes over the network, the exposure
//! goes to the camera another way, chosen by the site's `[camera.control]`.
//!
//! - `blueos_rest`: BlueOS's camera manager (mavlink-camera-manager) REST API.
//!   `GET /v4l` lists the video sources, each `{name, source, formats, controls}`, a
//!   control being `{name, cpp_type, id, state, configuration}` with `configuration`
//!   one of `{"Slider": {default, value, step, max, min}}`, `{"Menu": {default, value,
//!   options}}` or `{"Bool": {default, value}}`. `POST /v4l` with
//!   `{"device": "/dev/videoN", "v4l_id": <id>, "value": <i64>}` sets one control.
//!   The ids are V4L2 control ids: `auto_exposure` (V4L2_CID_EXPOSURE_AUTO, 0x009a0901;
//!   1 = manual, 3 = aperture priority) and `exposure_time_absolute`
//!   (V4L2_CID_EXPOSURE_ABSOLUTE, 0x009a0902, units of 100 us).
//! - `v4l2`: the same two controls through a control-only handle on `/dev/videoN`
//!   (VIDIOC_QUERYCTRL / VIDIOC_S_CTRL / VIDIOC_G_CTRL), while the camera manager keeps
//!   streaming from it (V4L2 allows several opens; only the streaming one owns buffers).
//! - `none`: the exposure is left to the camera.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

/// V4L2_CID_EXPOSURE_AUTO.
pub const CID_EXPOSURE_AUTO: u64 = 0x009a_0901;
/// V4L2_CID_EXPOSURE_ABSOLUTE (units of 100 us).
pub const CID_EXPOSURE_ABSOLUTE: u64 = 0x009a_0902;
/// V4L2_EXPOSURE_MANUAL.
pub const EXPOSURE_MANUAL: i64 = 1;
/// One unit of V4L2_CID_EXPOSURE_ABSOLUTE, microseconds.
pub const V4L2_EXPOSURE_UNIT_US: f64 = 100.0;

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

/// Sets the camera's exposure, in its own units.
pub trait ExposureControl: Send {
    /// Sets the exposure; returns the value set (quantized to the camera's step).
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError>;
    /// The camera's exposure step, microseconds (0: continuous).
    fn step_us(&self) -> f64;
    /// Where the commands go, for messages.
    fn describe(&self) -> String;
}

/// Round `us` to the camera's step (at least one step).
pub fn quantize(us: f64, step_us: f64) -> f64 {
    if step_us <= 0.0 {
        return us;
    }
    ((us / step_us).round() * step_us).max(step_us)
}

/// Exposure left to the camera: commands are ignored (and not attributed).
pub struct NoControl;

impl ExposureControl for NoControl {
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        Ok(exposure_us)
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

/// How long one request may take.
const REST_TIMEOUT: Duration = Duration::from_millis(300);
/// After a failed request, how long commands are not sent (the exposure stays).
const REST_BACKOFF: Duration = Duration::from_secs(1);

/// Exposure through the camera manager's REST API.
pub struct BlueosRest {
    url: String,
    addr: SocketAddr,
    host: String,
    device: String,
    step_us: f64,
    min_units: i64,
    max_units: i64,
    /// The value in force (the last one the server accepted), microseconds.
    current_us: f64,
    failed_at: Option<Instant>,
    body: String,
    response: Vec<u8>,
}

impl BlueosRest {
    /// Connects, finds the source's exposure controls, switches to manual exposure and
    /// sets `initial_us`, reading both back.
    pub fn open(url: &str, device: &str, initial_us: f64) -> Result<Self, ControlError> {
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
            max_units: i64::MAX,
            current_us: initial_us,
            failed_at: None,
            body: String::with_capacity(128),
            response: Vec::with_capacity(4096),
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
                    "no video source{} with exposure_time_absolute (0x{CID_EXPOSURE_ABSOLUTE:08x}) among {:?}",
                    if c.device.is_empty() { String::new() } else { format!(" {}", c.device) },
                    sources.iter().map(|s| s.source.as_str()).collect::<Vec<_>>()
                ))
            })?;
        c.device = src.source.clone();
        if let Some(ApiControlType::Slider { step, min, max, .. }) = src
            .controls
            .iter()
            .find(|k| k.id == CID_EXPOSURE_ABSOLUTE)
            .map(|k| &k.configuration)
        {
            c.step_us = V4L2_EXPOSURE_UNIT_US * (*step).max(1) as f64;
            c.min_units = (*min).max(1);
            c.max_units = *max;
        }
        c.post(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL)?;
        let units = c.units(initial_us);
        c.post(CID_EXPOSURE_ABSOLUTE, units)?;
        let back = c.sources()?;
        let read = |id: u64| {
            back.iter()
                .find(|s| s.source == c.device)
                .and_then(|s| s.controls.iter().find(|k| k.id == id))
                .map(|k| k.configuration.value())
        };
        if read(CID_EXPOSURE_AUTO) != Some(EXPOSURE_MANUAL) {
            return Err(err(format!(
                "{}: auto_exposure reads {:?} after setting manual ({EXPOSURE_MANUAL})",
                c.device,
                read(CID_EXPOSURE_AUTO)
            )));
        }
        let got = read(CID_EXPOSURE_ABSOLUTE).ok_or_else(|| {
            err(format!(
                "{}: exposure_time_absolute not read back",
                c.device
            ))
        })?;
        c.current_us = got as f64 * V4L2_EXPOSURE_UNIT_US;
        Ok(c)
    }

    /// The source (device path) whose exposure this sets.
    pub fn device(&self) -> &str {
        &self.device
    }

    fn units(&self, us: f64) -> i64 {
        let step = (self.step_us / V4L2_EXPOSURE_UNIT_US).max(1.0);
        let u = ((us / V4L2_EXPOSURE_UNIT_US) / step).round() * step;
        (u as i64).clamp(self.min_units, self.max_units.max(self.min_units))
    }

    fn err(&self, reason: String) -> ControlError {
        ControlError::Rest {
            url: self.url.clone(),
            reason,
        }
    }

    /// `GET /v4l`.
    pub fn sources(&mut self) -> Result<Vec<ApiVideoSource>, ControlError> {
        let body = self.request("GET", "/v4l", "")?;
        serde_json::from_slice(body).map_err(|e| ControlError::Rest {
            url: self.url.clone(),
            reason: format!("GET /v4l: unexpected answer: {e}"),
        })
    }

    fn post(&mut self, id: u64, value: i64) -> Result<(), ControlError> {
        use std::fmt::Write as _;
        let mut body = std::mem::take(&mut self.body);
        body.clear();
        // The device path is the server's own string (from GET /v4l); JSON-escape it.
        let dev = serde_json::to_string(&self.device).unwrap_or_else(|_| "\"\"".into());
        let _ = write!(
            body,
            "{{\"device\":{dev},\"v4l_id\":{id},\"value\":{value}}}"
        );
        let r = self.request("POST", "/v4l", &body).map(|_| ());
        self.body = body;
        r
    }

    /// One HTTP/1.1 request with `Connection: close`; returns the body of a 2xx answer.
    fn request(&mut self, method: &str, path: &str, body: &str) -> Result<&[u8], ControlError> {
        let what = format!("{method} {path}");
        let mut s = TcpStream::connect_timeout(&self.addr, REST_TIMEOUT)
            .map_err(|e| self.err(format!("{what}: {e}")))?;
        let _ = s.set_read_timeout(Some(REST_TIMEOUT));
        let _ = s.set_write_timeout(Some(REST_TIMEOUT));
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            self.host,
            body.len()
        );
        s.write_all(head.as_bytes())
            .and_then(|()| s.write_all(body.as_bytes()))
            .map_err(|e| self.err(format!("{what}: {e}")))?;
        self.response.clear();
        s.read_to_end(&mut self.response)
            .map_err(|e| self.err(format!("{what}: {e}")))?;
        let text = &self.response;
        let split = text
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .ok_or_else(|| self.err(format!("{what}: no HTTP answer")))?;
        let status_line = String::from_utf8_lossy(&text[..split]);
        let status: u16 = status_line
            .split_whitespace()
            .nth(1)
            .and_then(|c| c.parse().ok())
            .ok_or_else(|| self.err(format!("{what}: bad status line {status_line:?}")))?;
        if !(200..300).contains(&status) {
            let body = String::from_utf8_lossy(&text[split + 4..]).into_owned();
            return Err(self.err(format!("{what}: HTTP {status}: {}", body.trim())));
        }
        Ok(&self.response[split + 4..])
    }
}

impl ExposureControl for BlueosRest {
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        let units = self.units(exposure_us);
        let want = units as f64 * V4L2_EXPOSURE_UNIT_US;
        if (want - self.current_us).abs() < 0.5 {
            return Ok(self.current_us);
        }
        if self.failed_at.is_some_and(|t| t.elapsed() < REST_BACKOFF) {
            return Ok(self.current_us);
        }
        match self.post(CID_EXPOSURE_ABSOLUTE, units) {
            Ok(()) => {
                self.failed_at = None;
                self.current_us = want;
                Ok(want)
            }
            Err(e) => {
                self.failed_at = Some(Instant::now());
                Err(e)
            }
        }
    }
    fn step_us(&self) -> f64 {
        self.step_us
    }
    fn describe(&self) -> String {
        format!("{} ({})", self.url, self.device)
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
    current_us: f64,
}

impl V4l2Control {
    /// Opens `device`, reads the exposure control's range, switches to manual exposure
    /// and sets `initial_us`, reading both back.
    pub fn open(device: &str, initial_us: f64) -> Result<Self, ControlError> {
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
            max_units: i64::MAX,
            current_us: initial_us,
        };
        let q = c.query(CID_EXPOSURE_ABSOLUTE)?;
        c.step_us = V4L2_EXPOSURE_UNIT_US * f64::from(q.step.max(1));
        c.min_units = i64::from(q.minimum.max(1));
        c.max_units = i64::from(q.maximum);
        c.set(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL)?;
        let units = ((initial_us / c.step_us).round() * (c.step_us / V4L2_EXPOSURE_UNIT_US)) as i64;
        c.set(CID_EXPOSURE_ABSOLUTE, units.clamp(c.min_units, c.max_units))?;
        let auto = c.get(CID_EXPOSURE_AUTO)?;
        if auto != EXPOSURE_MANUAL {
            return Err(c.err(format!(
                "auto_exposure reads {auto} after setting manual ({EXPOSURE_MANUAL})"
            )));
        }
        c.current_us = c.get(CID_EXPOSURE_ABSOLUTE)? as f64 * V4L2_EXPOSURE_UNIT_US;
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
        self.ioctl(
            VIDIOC_QUERYCTRL,
            &mut q,
            &format!("VIDIOC_QUERYCTRL 0x{id:08x} (exposure_time_absolute)"),
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

impl ExposureControl for V4l2Control {
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, ControlError> {
        let step_units = (self.step_us / V4L2_EXPOSURE_UNIT_US).max(1.0);
        let units =
            (((exposure_us / V4L2_EXPOSURE_UNIT_US) / step_units).round() * step_units) as i64;
        let units = units.clamp(self.min_units, self.max_units.max(self.min_units));
        let want = units as f64 * V4L2_EXPOSURE_UNIT_US;
        if (want - self.current_us).abs() < 0.5 {
            return Ok(self.current_us);
        }
        self.set(CID_EXPOSURE_ABSOLUTE, units)?;
        self.current_us = want;
        Ok(want)
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

    #[test]
    fn ioctl_numbers_match_videodev2() {
        // From linux/videodev2.h on x86_64 and aarch64.
        assert_eq!(VIDIOC_G_CTRL, 0xc008_561b);
        assert_eq!(VIDIOC_S_CTRL, 0xc008_561c);
        assert_eq!(VIDIOC_QUERYCTRL, 0xc044_5624);
    }

    #[test]
    fn v4l2_errors_name_the_device() {
        let e = V4l2Control::open("/no/such/video9", 1000.0)
            .err()
            .map(|e| e.to_string());
        assert!(
            e.as_deref().is_some_and(|e| e.contains("/no/such/video9")),
            "{e:?}"
        );
        // Not a V4L2 device: the ioctl is refused, and the error says which.
        let e = V4l2Control::open("/dev/null", 1000.0)
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
}
