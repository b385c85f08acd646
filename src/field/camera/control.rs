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
}

#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    #[error("camera manager at {url}: {reason}")]
    Rest { url: String, reason: String },
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
