//! Fault injection for HIL runs: what the field does to a station keeper, on simulation
//! time and seeded, so a faulty run is as repeatable as a clean one.
//!
//! - Camera faults wrap the camera seam ([`FaultyCamera`]): dropped frames, late frames,
//!   an exposure command ignored or applied 3 frames late, the marker (or one marker of
//!   the map, by id) occluded, or everything out of view (painted over from the world's
//!   truth, after rendering).
//! - The link cut is a UDP relay on 127.0.0.1 between markhold's `VehicleLink` and the
//!   simulated vehicle's endpoint ([`LinkRelay`]); it is pumped from the loop, so a cut
//!   starts and ends on simulation time.
//! - [`FaultMonitor`] watches every frame and writes what the loop did during and after
//!   each fault (silent at, regained station at, ...) into the summary.

use std::fmt;
use std::io::ErrorKind;
use std::net::{SocketAddr, UdpSocket};
use std::str::FromStr;

use markhold_autopilot::{ArduSubMode, Directive, FailsafeEvent};
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use markhold_hil::camera::CameraModel;
use markhold_hil::scene::LightingScale;
use markhold_hil::{HilRig, Truth};
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

use markhold_core::pipeline::{FrameRecord, ModeTransition};

/// Errors of fault specifications and the link relay.
#[derive(Debug, thiserror::Error)]
pub enum FaultError {
    #[error(
        "--fault {spec:?}: expected KIND@START[+DURATION] (occlude also occlude:ID@START[+DURATION]), e.g. link_cut@10+3 or occlude:2@20+5"
    )]
    Syntax { spec: String },
    #[error("--fault {spec:?}: only occlude takes a marker id (occlude:ID@START[+DURATION]), not {kind}")]
    MarkerNotAllowed { spec: String, kind: &'static str },
    #[error("--fault {spec:?}: unknown kind {kind:?} (expected one of {known})")]
    UnknownKind {
        spec: String,
        kind: String,
        known: &'static str,
    },
    #[error("--fault {spec:?}: {field} {value:?} is not a {expected}")]
    BadNumber {
        spec: String,
        field: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error("link relay: {op} on {addr}: {source}")]
    Relay {
        op: &'static str,
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
}

/// What goes wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The vehicle's endpoint stops answering (all traffic both ways dropped), then returns.
    LinkCut,
    /// The origin marker (and its white plate) painted over with the surrounding grey;
    /// `occlude:ID` paints the map's marker ID instead.
    Occlude,
    /// The marker out of view: the whole frame painted with its mean grey.
    OutOfView,
    /// Frames dropped (about one in two, seeded): the loop gets the next one instead.
    DropFrames,
    /// Every frame delivered one frame late (with its own, older stamp).
    LateFrames,
    /// The camera acknowledges exposure commands but does not apply them.
    ExposureIgnored,
    /// The camera applies each exposure command 3 frames later than it would.
    ExposureLate,
    /// Every lamp (the vehicle's and the marker's) switched off, then on again at the end.
    LampOff,
    /// Daylight (ambient) 10x brighter, back at the end.
    AmbientStep,
}

/// The factor of `ambient_step`.
pub const AMBIENT_STEP_FACTOR: f64 = 10.0;

const KINDS: &str = "link_cut, occlude, out_of_view, drop_frames, late_frames, exposure_ignored, \
     exposure_late, lamp_off, ambient_step";

impl FaultKind {
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::LinkCut => "link_cut",
            FaultKind::Occlude => "occlude",
            FaultKind::OutOfView => "out_of_view",
            FaultKind::DropFrames => "drop_frames",
            FaultKind::LateFrames => "late_frames",
            FaultKind::ExposureIgnored => "exposure_ignored",
            FaultKind::ExposureLate => "exposure_late",
            FaultKind::LampOff => "lamp_off",
            FaultKind::AmbientStep => "ambient_step",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "link_cut" => FaultKind::LinkCut,
            "occlude" => FaultKind::Occlude,
            "out_of_view" => FaultKind::OutOfView,
            "drop_frames" => FaultKind::DropFrames,
            "late_frames" => FaultKind::LateFrames,
            "exposure_ignored" => FaultKind::ExposureIgnored,
            "exposure_late" => FaultKind::ExposureLate,
            "lamp_off" => FaultKind::LampOff,
            "ambient_step" => FaultKind::AmbientStep,
            _ => return None,
        })
    }
}

impl fmt::Display for FaultKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// One fault: a kind active on `[start_s, start_s + duration_s)` of simulation time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FaultSpec {
    pub kind: FaultKind,
    /// The marker of the map an `occlude` covers (`occlude:ID`); none: the origin marker.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub marker: Option<u32>,
    pub start_s: f64,
    /// Infinite: until the end of the run.
    pub duration_s: f64,
}

impl FaultSpec {
    pub fn end_s(&self) -> f64 {
        self.start_s + self.duration_s
    }

    pub fn active(&self, t_s: f64) -> bool {
        t_s >= self.start_s && t_s < self.end_s()
    }
}

impl FromStr for FaultSpec {
    type Err = FaultError;

    /// `KIND@START[+DURATION]`, seconds of simulation time; `occlude:ID@...` names the
    /// marker of the map it covers.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let syntax = || FaultError::Syntax {
            spec: s.to_string(),
        };
        let (kind, when) = s.split_once('@').ok_or_else(syntax)?;
        let (kind, id) = match kind.split_once(':') {
            Some((k, id)) => (k, Some(id)),
            None => (kind, None),
        };
        let kind = FaultKind::parse(kind.trim()).ok_or_else(|| FaultError::UnknownKind {
            spec: s.to_string(),
            kind: kind.to_string(),
            known: KINDS,
        })?;
        let marker = match id {
            None => None,
            Some(_) if kind != FaultKind::Occlude => {
                return Err(FaultError::MarkerNotAllowed {
                    spec: s.to_string(),
                    kind: kind.name(),
                })
            }
            Some(id) => Some(
                id.trim()
                    .parse::<u32>()
                    .map_err(|_| FaultError::BadNumber {
                        spec: s.to_string(),
                        field: "ID",
                        value: id.to_string(),
                        expected: "marker id (a whole number >= 0)",
                    })?,
            ),
        };
        let (start, dur) = match when.split_once('+') {
            Some((a, b)) => (a, Some(b)),
            None => (when, None),
        };
        let num = |field: &'static str, v: &str, positive: bool| -> Result<f64, FaultError> {
            let bad = || FaultError::BadNumber {
                spec: s.to_string(),
                field,
                value: v.to_string(),
                expected: if positive {
                    "positive number of seconds"
                } else {
                    "number of seconds >= 0"
                },
            };
            let x: f64 = v.trim().parse().map_err(|_| bad())?;
            let ok = x.is_finite() && if positive { x > 0.0 } else { x >= 0.0 };
            if ok {
                Ok(x)
            } else {
                Err(bad())
            }
        };
        let start_s = num("START", start, false)?;
        let duration_s = match dur {
            Some(d) => num("DURATION", d, true)?,
            None => f64::INFINITY,
        };
        Ok(Self {
            kind,
            marker,
            start_s,
            duration_s,
        })
    }
}

/// The faults of a run and the seed of their random parts.
#[derive(Debug, Clone, Default)]
pub struct FaultPlan {
    pub specs: Vec<FaultSpec>,
    pub seed: u64,
}

impl FaultPlan {
    pub fn active(&self, kind: FaultKind, t_s: f64) -> bool {
        self.specs.iter().any(|f| f.kind == kind && f.active(t_s))
    }

    pub fn has(&self, kind: FaultKind) -> bool {
        self.specs.iter().any(|f| f.kind == kind)
    }

    /// The scene's lighting at `t_s`: lamps off and the ambient step while active.
    pub fn lighting(&self, t_s: f64) -> LightingScale {
        let mut l = LightingScale::UNCHANGED;
        if self.active(FaultKind::LampOff, t_s) {
            l.lamp = 0.0;
        }
        if self.active(FaultKind::AmbientStep, t_s) {
            l.ambient *= AMBIENT_STEP_FACTOR;
        }
        l
    }
}

/// SplitMix64 of (seed, n): a per-frame coin that does not depend on how many coins were
/// drawn before (a fault window moved by one frame changes no other frame's draw).
fn coin(seed: u64, n: u64) -> u64 {
    let mut z = seed ^ n.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A UDP relay on 127.0.0.1 between markhold's link (which sends to [`LinkRelay::addr`])
/// and the vehicle's endpoint. While cut, every datagram both ways is read and dropped,
/// as a tether that went dead would.
pub struct LinkRelay {
    /// The side markhold's link talks to.
    front: UdpSocket,
    /// The side that talks to the vehicle (the vehicle answers to its address).
    back: UdpSocket,
    vehicle: SocketAddr,
    /// Where markhold's link sends from (learnt from its first datagram).
    client: Option<SocketAddr>,
    buf: Vec<u8>,
    pub stats: RelayStats,
}

/// What the relay did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct RelayStats {
    pub to_vehicle: u64,
    pub to_markhold: u64,
    pub dropped: u64,
}

impl LinkRelay {
    /// Bind both sides on 127.0.0.1 (ephemeral ports) in front of `vehicle`.
    pub fn bind(vehicle: SocketAddr) -> Result<Self, FaultError> {
        let any = SocketAddr::from(([127, 0, 0, 1], 0));
        let rel = |op, source| FaultError::Relay {
            op,
            addr: any,
            source,
        };
        let front = UdpSocket::bind(any).map_err(|e| rel("bind", e))?;
        let back = UdpSocket::bind(any).map_err(|e| rel("bind", e))?;
        front
            .set_nonblocking(true)
            .map_err(|e| rel("set_nonblocking", e))?;
        back.set_nonblocking(true)
            .map_err(|e| rel("set_nonblocking", e))?;
        Ok(Self {
            front,
            back,
            vehicle,
            client: None,
            // Larger than any MAVLink frame (280 bytes) and than most garbage.
            buf: vec![0; 4096],
            stats: RelayStats::default(),
        })
    }

    /// The address markhold's link must send to.
    pub fn addr(&self) -> Result<SocketAddr, FaultError> {
        self.front.local_addr().map_err(|e| FaultError::Relay {
            op: "local_addr",
            addr: self.vehicle,
            source: e,
        })
    }

    /// Move every waiting datagram across, or drop it when `cut`. Never blocks.
    pub fn pump(&mut self, cut: bool) -> Result<(), FaultError> {
        loop {
            match self.front.recv_from(&mut self.buf) {
                Ok((n, from)) => {
                    self.client = Some(from);
                    if cut {
                        self.stats.dropped += 1;
                    } else {
                        self.send_back(n)?;
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                // ICMP port unreachable from an earlier send shows up here on Linux.
                Err(e) if e.kind() == ErrorKind::ConnectionRefused => continue,
                Err(e) => {
                    return Err(FaultError::Relay {
                        op: "recv (markhold side)",
                        addr: self.vehicle,
                        source: e,
                    })
                }
            }
        }
        loop {
            match self.back.recv_from(&mut self.buf) {
                Ok((n, from)) => {
                    // Only the vehicle talks to the back socket.
                    if from != self.vehicle {
                        continue;
                    }
                    match (cut, self.client) {
                        (false, Some(client)) => {
                            self.send_front(n, client)?;
                        }
                        _ => self.stats.dropped += 1,
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == ErrorKind::ConnectionRefused => continue,
                Err(e) => {
                    return Err(FaultError::Relay {
                        op: "recv (vehicle side)",
                        addr: self.vehicle,
                        source: e,
                    })
                }
            }
        }
        Ok(())
    }

    /// Send `bytes` to markhold's link as if from the vehicle (the link's UDP socket is
    /// connected to the relay, so only this address reaches it): garbage and flood tests.
    /// False before markhold has sent anything (its address is not known yet).
    pub fn inject_to_markhold(&mut self, bytes: &[u8]) -> Result<bool, FaultError> {
        let Some(client) = self.client else {
            return Ok(false);
        };
        match self.front.send_to(bytes, client) {
            Ok(_) => Ok(true),
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(false),
            Err(e) => Err(FaultError::Relay {
                op: "inject to markhold",
                addr: client,
                source: e,
            }),
        }
    }

    fn send_back(&mut self, n: usize) -> Result<(), FaultError> {
        match relay_send(&self.back, &self.buf[..n], self.vehicle, "send to vehicle")? {
            true => self.stats.to_vehicle += 1,
            false => self.stats.dropped += 1,
        }
        Ok(())
    }

    fn send_front(&mut self, n: usize, client: SocketAddr) -> Result<(), FaultError> {
        match relay_send(&self.front, &self.buf[..n], client, "send to markhold")? {
            true => self.stats.to_markhold += 1,
            false => self.stats.dropped += 1,
        }
        Ok(())
    }
}

/// Send one datagram: true if sent, false if lost as on a wire (a full buffer, or a peer
/// not listening); other errors are the relay's.
fn relay_send(
    sock: &UdpSocket,
    data: &[u8],
    to: SocketAddr,
    op: &'static str,
) -> Result<bool, FaultError> {
    match sock.send_to(data, to) {
        Ok(_) => Ok(true),
        Err(e)
            if matches!(
                e.kind(),
                ErrorKind::WouldBlock | ErrorKind::ConnectionRefused
            ) =>
        {
            Ok(false)
        }
        Err(source) => Err(FaultError::Relay {
            op,
            addr: to,
            source,
        }),
    }
}

/// What a camera fault needs from the world: where the marker really is, and the
/// lights (switched before the frame is rendered, so the sensor sees the new light).
pub trait MarkerTruth {
    /// Pose of the marker in the camera frame at the last grabbed frame.
    fn true_t_cam_marker(&self) -> Isometry3<f64>;
    /// Stamp of the next frame the camera will take.
    fn next_frame_time_s(&self) -> f64;
    /// Scale the lamps and the daylight from the next frame on.
    fn set_lighting(&mut self, scale: LightingScale) -> Result<(), CameraError>;
}

impl MarkerTruth for HilRig {
    fn true_t_cam_marker(&self) -> Isometry3<f64> {
        self.truth().t_cam_marker
    }
    fn next_frame_time_s(&self) -> f64 {
        HilRig::next_frame_time_s(self)
    }
    fn set_lighting(&mut self, scale: LightingScale) -> Result<(), CameraError> {
        HilRig::set_lighting(self, scale).map_err(|e| CameraError::ControlRejected {
            device: "hil".to_string(),
            control: "lighting".to_string(),
            reason: e.to_string(),
        })
    }
}

/// Pinhole + OpenCV distortion, for painting the marker's true projection.
#[derive(Debug, Clone, Copy)]
pub struct Projection {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// k1, k2, p1, p2, k3.
    pub dist: [f64; 5],
}

impl Projection {
    pub fn of(model: &CameraModel) -> Self {
        Self {
            fx: model.fx,
            fy: model.fy,
            cx: model.cx,
            cy: model.cy,
            dist: model.dist,
        }
    }

    /// Pixel of a camera-frame point in front of the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        if p.z <= 1e-3 {
            return None;
        }
        let (x, y) = (p.x / p.z, p.y / p.z);
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Some((self.fx * xd + self.cx, self.fy * yd + self.cy))
    }
}

/// A marker `occlude` can paint over.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cover {
    pub id: u32,
    /// Its pose in the site frame (the identity for the origin marker).
    pub t_site_marker: Isometry3<f64>,
    /// Half the edge of what is painted over: the marker and its white plate, with a
    /// small rim so no white edge is left for the detector.
    pub half_m: f64,
}

impl Cover {
    /// Marker `id` at `t_site_marker` with `marker_half_m` (half its edge plus its plate
    /// margin).
    pub fn new(id: u32, t_site_marker: Isometry3<f64>, marker_half_m: f64) -> Self {
        Self {
            id,
            t_site_marker,
            half_m: marker_half_m * 1.1,
        }
    }
}

/// State of the camera faults across frames (buffers allocated once, at build).
pub struct CameraFaults {
    plan: FaultPlan,
    proj: Projection,
    /// What `occlude` can paint over, the origin marker first.
    covers: Vec<Cover>,
    /// The frame held back by `late_frames`.
    held: Frame,
    held_valid: bool,
    /// Exposure commands waiting to be applied (`exposure_late`): (frames left, value).
    pending: [(u32, f64); 8],
    pending_len: usize,
    /// Exposure the camera reported last (what an ignored command gets back).
    applied_us: f64,
    /// Frames grabbed from the inner camera.
    grabs: u64,
    /// Lighting set on the world last.
    lighting: LightingScale,
    pub stats: CameraFaultStats,
}

/// What the camera faults did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct CameraFaultStats {
    pub frames_dropped: u64,
    pub frames_late: u64,
    pub frames_occluded: u64,
    pub frames_out_of_view: u64,
    pub exposure_ignored: u64,
    pub exposure_delayed: u64,
}

/// How many frames `exposure_late` holds a command back.
pub const EXPOSURE_LATE_FRAMES: u32 = 3;

impl CameraFaults {
    /// `covers`: the markers `occlude` can paint, the origin marker first (the plain
    /// `occlude` paints it).
    pub fn new(
        plan: FaultPlan,
        proj: Projection,
        covers: Vec<Cover>,
        width: u32,
        height: u32,
        initial_exposure_us: f64,
    ) -> Self {
        Self {
            plan,
            proj,
            covers,
            held: Frame::new(width, height),
            held_valid: false,
            pending: [(0, 0.0); 8],
            pending_len: 0,
            applied_us: initial_exposure_us,
            grabs: 0,
            lighting: LightingScale::UNCHANGED,
            stats: CameraFaultStats::default(),
        }
    }

    pub fn plan(&self) -> &FaultPlan {
        &self.plan
    }
}

/// A camera with faults injected, wrapping the real one for one frame at a time (the
/// state lives in [`CameraFaults`]). The relay, when there is one, is pumped around the
/// inner grab so the vehicle's lock-step sees markhold's command and markhold's link
/// sees the telemetry of the step.
pub struct FaultyCamera<'a, C: Camera + MarkerTruth> {
    pub inner: &'a mut C,
    pub faults: &'a mut CameraFaults,
    pub relay: Option<&'a mut LinkRelay>,
    /// Simulation time now (before the grab), for the link-cut window.
    pub now_s: f64,
}

impl<C: Camera + MarkerTruth> FaultyCamera<'_, C> {
    fn pump(&mut self, t_s: f64) -> Result<(), CameraError> {
        if let Some(r) = self.relay.as_deref_mut() {
            let cut = self.faults.plan.active(FaultKind::LinkCut, t_s);
            r.pump(cut).map_err(|e| CameraError::Read {
                device: "hil+faults".to_string(),
                seq: self.faults.grabs,
                reason: e.to_string(),
            })?;
        }
        Ok(())
    }

    fn grab_inner(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        self.pump(self.now_s)?;
        // Lights switched on the stamp of the frame about to be rendered.
        let light = self.faults.plan.lighting(self.inner.next_frame_time_s());
        if light != self.faults.lighting {
            self.inner.set_lighting(light)?;
            self.faults.lighting = light;
        }
        self.inner.grab(frame)?;
        self.faults.grabs += 1;
        self.now_s = frame.meta.stamp_s;
        self.pump(self.now_s)?;
        self.tick_exposure()
    }

    /// One frame passed: apply the delayed exposure commands that are due.
    fn tick_exposure(&mut self) -> Result<(), CameraError> {
        let f = &mut *self.faults;
        let mut i = 0;
        while i < f.pending_len {
            f.pending[i].0 = f.pending[i].0.saturating_sub(1);
            if f.pending[i].0 == 0 {
                let v = f.pending[i].1;
                f.applied_us = self.inner.set_exposure_us(v)?;
                f.pending.copy_within(i + 1..f.pending_len, i);
                f.pending_len -= 1;
            } else {
                i += 1;
            }
        }
        Ok(())
    }
}

impl<C: Camera + MarkerTruth> Camera for FaultyCamera<'_, C> {
    fn name(&self) -> &str {
        "hil+faults"
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.inner.exposure_limits()
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        let t = self.now_s;
        let plan = &self.faults.plan;
        if plan.active(FaultKind::ExposureIgnored, t) {
            self.faults.stats.exposure_ignored += 1;
            // The driver says yes and keeps what it had.
            return Ok(self.faults.applied_us);
        }
        if plan.active(FaultKind::ExposureLate, t) {
            let f = &mut *self.faults;
            if f.pending_len == f.pending.len() {
                // Never more than 3 are in flight at one a frame; keep the newest anyway.
                f.pending.copy_within(1.., 0);
                f.pending_len -= 1;
            }
            f.pending[f.pending_len] = (EXPOSURE_LATE_FRAMES, exposure_us);
            f.pending_len += 1;
            f.stats.exposure_delayed += 1;
            return Ok(self.inner.exposure_limits().clamp(exposure_us));
        }
        let v = self.inner.set_exposure_us(exposure_us)?;
        self.faults.applied_us = v;
        Ok(v)
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        self.grab_inner(frame)?;
        // Dropped: the frame never reaches the loop, the next one does (at most 4 in a
        // row, so a 30 fps loop still sees a frame every 1/6 s).
        let mut dropped = 0;
        while dropped < 4
            && self
                .faults
                .plan
                .active(FaultKind::DropFrames, frame.meta.stamp_s)
            && coin(self.faults.plan.seed, self.faults.grabs) & 1 == 0
        {
            self.faults.stats.frames_dropped += 1;
            dropped += 1;
            self.grab_inner(frame)?;
        }
        let t = frame.meta.stamp_s;
        if self.faults.plan.active(FaultKind::Occlude, t) {
            let t_cam_marker = self.inner.true_t_cam_marker();
            let f = &*self.faults;
            let mut painted = false;
            let active = f.plan.specs.iter();
            for spec in active.filter(|s| s.kind == FaultKind::Occlude && s.active(t)) {
                let cover = match spec.marker {
                    None => f.covers.first(),
                    Some(id) => f.covers.iter().find(|c| c.id == id),
                };
                if let Some(c) = cover {
                    let at = t_cam_marker * c.t_site_marker;
                    painted |= paint_marker(frame, &f.proj, &at, c.half_m);
                }
            }
            if painted {
                self.faults.stats.frames_occluded += 1;
            }
        }
        if self.faults.plan.active(FaultKind::OutOfView, t) {
            fill_mean(frame);
            self.faults.stats.frames_out_of_view += 1;
        }
        if self.faults.plan.active(FaultKind::LateFrames, t) {
            // The loop gets the previous frame now; this one waits for the next grab.
            let f = &mut *self.faults;
            if f.held_valid {
                std::mem::swap(&mut f.held, frame);
                f.stats.frames_late += 1;
            } else {
                copy_frame(frame, &mut f.held);
                f.held_valid = true;
            }
        } else {
            self.faults.held_valid = false;
        }
        Ok(())
    }
}

fn copy_frame(src: &Frame, dst: &mut Frame) {
    dst.resize(src.width, src.height);
    dst.data.copy_from_slice(&src.data);
    dst.meta = src.meta;
}

/// Paint the whole frame with its mean grey (a featureless view of open water).
fn fill_mean(frame: &mut Frame) {
    let n = frame.data.len().max(1) as u64;
    let mean = (frame.data.iter().map(|&v| u64::from(v)).sum::<u64>() / n) as u8;
    frame.data.fill(mean);
}

/// Paint the marker's true projected square (half edge `half_m` in the marker plane) with
/// the mean grey of a ring just outside it. False when it is not in front of the camera.
pub fn paint_marker(
    frame: &mut Frame,
    proj: &Projection,
    t_cam_marker: &Isometry3<f64>,
    half_m: f64,
) -> bool {
    let h = half_m;
    let mut quad = [(0.0, 0.0); 4];
    for (q, (x, y)) in quad.iter_mut().zip([(-h, h), (h, h), (h, -h), (-h, -h)]) {
        match proj.project(&(t_cam_marker * Point3::new(x, y, 0.0))) {
            Some(p) => *q = p,
            None => return false,
        }
    }
    let (w, hgt) = (frame.width as i64, frame.height as i64);
    let (min_x, max_x) = quad
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        });
    let (min_y, max_y) = quad
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.1), b.max(p.1))
        });
    if max_x < 0.0 || max_y < 0.0 || min_x >= w as f64 || min_y >= hgt as f64 {
        return false;
    }
    // The surrounding grey: the mean over a ring a tenth of the size outside the box.
    let pad = 0.1 * (max_x - min_x).max(max_y - min_y) + 2.0;
    let (rx0, rx1) = (
        ((min_x - pad).floor() as i64).clamp(0, w - 1),
        ((max_x + pad).ceil() as i64).clamp(0, w - 1),
    );
    let (ry0, ry1) = (
        ((min_y - pad).floor() as i64).clamp(0, hgt - 1),
        ((max_y + pad).ceil() as i64).clamp(0, hgt - 1),
    );
    let (mut sum, mut cnt) = (0u64, 0u64);
    let stride = frame.width as usize;
    for y in [ry0, ry1] {
        for x in rx0..=rx1 {
            sum += u64::from(frame.data[y as usize * stride + x as usize]);
            cnt += 1;
        }
    }
    for x in [rx0, rx1] {
        for y in ry0..=ry1 {
            sum += u64::from(frame.data[y as usize * stride + x as usize]);
            cnt += 1;
        }
    }
    let grey = (sum / cnt.max(1)) as u8;
    // Scanline fill of the convex quad (pixel centres at +0.5).
    let y0 = (min_y.floor() as i64).max(0);
    let y1 = (max_y.ceil() as i64).min(hgt - 1);
    for y in y0..=y1 {
        let yc = y as f64 + 0.5;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for i in 0..4 {
            let (a, b) = (quad[i], quad[(i + 1) % 4]);
            if (a.1 <= yc && b.1 > yc) || (b.1 <= yc && a.1 > yc) {
                let x = a.0 + (yc - a.1) * (b.0 - a.0) / (b.1 - a.1);
                lo = lo.min(x);
                hi = hi.max(x);
            }
        }
        if lo > hi {
            continue;
        }
        // One pixel of margin each side against anti-aliased edges.
        let xa = ((lo - 1.0).floor() as i64).max(0);
        let xb = ((hi + 1.0).ceil() as i64).min(w - 1);
        if xa > xb {
            continue;
        }
        let row = y as usize * stride;
        frame.data[row + xa as usize..=row + xb as usize].fill(grey);
    }
    true
}

/// What the loop did around one fault, on simulation time (seconds).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FaultReport {
    pub kind: FaultKind,
    /// The map's marker an `occlude:ID` covered.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub marker: Option<u32>,
    pub start_s: f64,
    /// `null` in JSON for a fault that lasts to the end of the run.
    pub end_s: Option<f64>,
    /// First frame in the window the loop stopped sending pilot input (no vehicle heard).
    pub silent_at_s: Option<f64>,
    /// First frame in the window the loop sent neutral input.
    pub neutral_at_s: Option<f64>,
    /// The vehicle's heartbeat declared lost.
    pub heartbeat_lost_at_s: Option<f64>,
    /// The vehicle's heartbeat back after it was lost.
    pub heartbeat_restored_at_s: Option<f64>,
    /// First frame from the start without a detection.
    pub marker_missed_at_s: Option<f64>,
    /// The supervisor's marker-lost and marker-lost-action times.
    pub marker_lost_at_s: Option<f64>,
    pub marker_lost_action_at_s: Option<f64>,
    /// First detection at or after the end, after a miss (none when the marker was
    /// never missed).
    pub marker_detected_again_at_s: Option<f64>,
    /// After the vehicle left the station tolerance (none when it never did): the first
    /// time after the end it was back within it and stayed
    /// there for `STATION_HOLD_S`.
    pub station_regained_at_s: Option<f64>,
    /// Largest station error (truth) from the start to station regained (or the end).
    pub max_position_error_m: f64,
    /// Exposure range commanded from the start to the end of the window.
    pub exposure_min_us: f64,
    pub exposure_max_us: f64,
    /// The vehicle disarmed (its own failsafe) after the fault started, per the link.
    pub vehicle_disarmed_at_s: Option<f64>,
    /// Pilot-input frames sent (Command directive) while the vehicle was not heard.
    pub commands_while_unheard: u64,
    /// Marker-loss action: the mode markhold asked for (SURFACE, or ALT_HOLD) and when.
    pub loss_action_mode: Option<ArduSubMode>,
    pub loss_action_requested_at_s: Option<f64>,
    /// SURFACE refused or unanswered: ALT_HOLD with a climb instead, at this time.
    pub surface_fallback_at_s: Option<f64>,
    /// The vehicle's heartbeat showed the action's mode.
    pub loss_action_in_mode_at_s: Option<f64>,
    /// Marker back: the site's mode requested, and seen in the heartbeat.
    pub site_mode_requested_at_s: Option<f64>,
    pub site_mode_restored_at_s: Option<f64>,
}

/// Within this of the station (truth) counts as on station.
pub const STATION_TOL_M: f64 = 0.10;
/// ... for this long.
pub const STATION_HOLD_S: f64 = 1.0;

/// Watches the frames of a faulty run and fills one [`FaultReport`] per fault.
pub struct FaultMonitor {
    reports: Vec<FaultReport>,
    /// Per report: since when the vehicle has been within tolerance after the end.
    in_tol_since: Vec<Option<f64>>,
    t_world_marker: Isometry3<f64>,
    t_marker_station: Isometry3<f64>,
    was_armed: bool,
}

impl FaultMonitor {
    pub fn new(
        plan: &FaultPlan,
        t_world_marker: Isometry3<f64>,
        t_marker_station: Isometry3<f64>,
    ) -> Self {
        let reports = plan
            .specs
            .iter()
            .map(|f| FaultReport {
                kind: f.kind,
                marker: f.marker,
                start_s: f.start_s,
                end_s: f.duration_s.is_finite().then(|| f.end_s()),
                silent_at_s: None,
                neutral_at_s: None,
                heartbeat_lost_at_s: None,
                heartbeat_restored_at_s: None,
                marker_missed_at_s: None,
                marker_lost_at_s: None,
                marker_lost_action_at_s: None,
                marker_detected_again_at_s: None,
                station_regained_at_s: None,
                max_position_error_m: 0.0,
                exposure_min_us: f64::INFINITY,
                exposure_max_us: 0.0,
                vehicle_disarmed_at_s: None,
                commands_while_unheard: 0,
                loss_action_mode: None,
                loss_action_requested_at_s: None,
                surface_fallback_at_s: None,
                loss_action_in_mode_at_s: None,
                site_mode_requested_at_s: None,
                site_mode_restored_at_s: None,
            })
            .collect::<Vec<_>>();
        let n = reports.len();
        Self {
            reports,
            in_tol_since: vec![None; n],
            t_world_marker,
            t_marker_station,
            was_armed: true,
        }
    }

    /// One frame: its record, the world's truth after it, the supervisor's events, the
    /// loop's own mode transitions and the vehicle's armed state and heartbeat health as
    /// markhold's link knows them.
    #[allow(clippy::too_many_arguments)]
    pub fn observe(
        &mut self,
        rec: &FrameRecord,
        truth: &Truth,
        events: &[FailsafeEvent],
        transitions: &[ModeTransition],
        link_armed: bool,
        heartbeat_ok: bool,
    ) {
        let t = rec.stamp_s;
        let err = (self.t_marker_station.inverse()
            * self.t_world_marker.inverse()
            * truth.t_world_vehicle)
            .translation
            .vector
            .norm();
        let disarmed_now = self.was_armed && !link_armed;
        self.was_armed = link_armed;
        // What happens on this frame (a directive, a miss, an event) belongs to the fault
        // started most recently at or before it: with several faults in a run, an
        // effect is listed under the fault that caused it, not under every earlier one.
        let owner = self
            .reports
            .iter()
            .enumerate()
            .filter(|(_, r)| r.start_s <= t)
            .max_by(|(_, a), (_, b)| a.start_s.total_cmp(&b.start_s))
            .map(|(i, _)| i);
        for (i, (r, tol)) in self
            .reports
            .iter_mut()
            .zip(self.in_tol_since.iter_mut())
            .enumerate()
        {
            if t < r.start_s {
                continue;
            }
            let end = r.end_s.unwrap_or(f64::INFINITY);
            if t < end {
                r.exposure_min_us = r.exposure_min_us.min(rec.exposure.exposure_us);
                r.exposure_max_us = r.exposure_max_us.max(rec.exposure.exposure_us);
            }
            if r.station_regained_at_s.is_none() {
                r.max_position_error_m = r.max_position_error_m.max(err);
            }
            if owner == Some(i) {
                r.note_frame(rec, t, end, heartbeat_ok, disarmed_now);
                for e in events {
                    r.note_event(e);
                }
                for tr in transitions {
                    r.note_transition(tr);
                }
            }
            // Station regained: only after it was lost (the error left the tolerance).
            let lost_station = r.max_position_error_m > STATION_TOL_M;
            if t >= end && lost_station && r.station_regained_at_s.is_none() {
                if err <= STATION_TOL_M {
                    let since = *tol.get_or_insert(t);
                    if t - since >= STATION_HOLD_S {
                        r.station_regained_at_s = Some(since);
                    }
                } else {
                    *tol = None;
                }
            }
        }
    }

    pub fn reports(&self) -> &[FaultReport] {
        &self.reports
    }

    pub fn into_reports(self) -> Vec<FaultReport> {
        self.reports
    }
}

impl FaultReport {
    /// One frame of this fault's: its directive, detection and the vehicle's state.
    fn note_frame(
        &mut self,
        rec: &FrameRecord,
        t: f64,
        end: f64,
        heartbeat_ok: bool,
        disarmed_now: bool,
    ) {
        match rec.directive {
            Directive::Silent if self.silent_at_s.is_none() => self.silent_at_s = Some(t),
            Directive::Neutral if self.neutral_at_s.is_none() => self.neutral_at_s = Some(t),
            _ => {}
        }
        if rec.directive == Directive::Command && !heartbeat_ok {
            self.commands_while_unheard += 1;
        }
        if disarmed_now && self.vehicle_disarmed_at_s.is_none() {
            self.vehicle_disarmed_at_s = Some(t);
        }
        if !rec.detected && self.marker_missed_at_s.is_none() {
            self.marker_missed_at_s = Some(t);
        }
        // Detected again: only after a miss, once the fault is over.
        if rec.detected
            && t >= end
            && self.marker_missed_at_s.is_some()
            && self.marker_detected_again_at_s.is_none()
        {
            self.marker_detected_again_at_s = Some(t);
        }
    }

    /// The first time each failsafe event of the supervisor was seen in this fault.
    fn note_event(&mut self, e: &FailsafeEvent) {
        match *e {
            FailsafeEvent::VehicleHeartbeatLost { at_s, .. }
                if self.heartbeat_lost_at_s.is_none() =>
            {
                self.heartbeat_lost_at_s = Some(at_s)
            }
            FailsafeEvent::VehicleHeartbeatRestored { at_s, .. }
                if self.heartbeat_lost_at_s.is_some() && self.heartbeat_restored_at_s.is_none() =>
            {
                self.heartbeat_restored_at_s = Some(at_s)
            }
            FailsafeEvent::MarkerLost { at_s, .. } if self.marker_lost_at_s.is_none() => {
                self.marker_lost_at_s = Some(at_s)
            }
            FailsafeEvent::MarkerLostActionDue { at_s, .. }
                if self.marker_lost_action_at_s.is_none() =>
            {
                self.marker_lost_action_at_s = Some(at_s)
            }
            _ => {}
        }
    }

    /// The first time each mode transition of the loop was seen in this fault.
    fn note_transition(&mut self, tr: &ModeTransition) {
        match *tr {
            ModeTransition::LossActionRequested { at_s, mode, .. }
                if self.loss_action_requested_at_s.is_none() =>
            {
                self.loss_action_requested_at_s = Some(at_s);
                self.loss_action_mode = Some(mode);
            }
            ModeTransition::SurfaceFallback { at_s, .. }
                if self.surface_fallback_at_s.is_none() =>
            {
                self.surface_fallback_at_s = Some(at_s);
                self.loss_action_mode = Some(ArduSubMode::AltHold);
            }
            ModeTransition::LossActionInMode { at_s, .. }
                if self.loss_action_in_mode_at_s.is_none() =>
            {
                self.loss_action_in_mode_at_s = Some(at_s)
            }
            ModeTransition::SiteModeRequested { at_s, .. }
                if self.loss_action_requested_at_s.is_some()
                    && self.site_mode_requested_at_s.is_none() =>
            {
                self.site_mode_requested_at_s = Some(at_s)
            }
            ModeTransition::SiteModeRestored { at_s, .. }
                if self.site_mode_requested_at_s.is_some()
                    && self.site_mode_restored_at_s.is_none() =>
            {
                self.site_mode_restored_at_s = Some(at_s)
            }
            _ => {}
        }
    }
}

/// The fault machinery of one HIL run: camera faults, the relay (with a link cut), and
/// the monitor that reports.
pub struct FaultRig {
    pub camera: CameraFaults,
    pub relay: Option<LinkRelay>,
    pub monitor: FaultMonitor,
}

impl FaultRig {
    /// Pump the relay outside a frame (arming handshake): traffic passes unless cut at `t_s`.
    pub fn pump_relay(&mut self, t_s: f64) -> Result<(), FaultError> {
        let cut = self.camera.plan.active(FaultKind::LinkCut, t_s);
        match self.relay.as_mut() {
            Some(r) => r.pump(cut),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_specs() {
        let f: FaultSpec = "link_cut@10+3".parse().unwrap();
        assert_eq!(f.kind, FaultKind::LinkCut);
        assert_eq!((f.start_s, f.duration_s), (10.0, 3.0));
        assert!(f.active(10.0) && f.active(12.9) && !f.active(13.0) && !f.active(9.9));
        let g: FaultSpec = "occlude@2.5".parse().unwrap();
        assert!(g.duration_s.is_infinite() && g.active(1e6));
        for bad in [
            "link_cut",
            "nope@1",
            "occlude@-1",
            "occlude@1+0",
            "occlude@x",
            "occlude@1+inf",
        ] {
            assert!(bad.parse::<FaultSpec>().is_err(), "{bad} parsed");
        }
        let e = "occlude@1+0".parse::<FaultSpec>().unwrap_err().to_string();
        assert!(e.contains("DURATION") && e.contains("\"0\""), "{e}");
    }

    #[test]
    fn occlude_takes_a_marker_id_and_nothing_else_does() {
        let f: FaultSpec = "occlude:3@20+5".parse().unwrap();
        assert_eq!(f.kind, FaultKind::Occlude);
        assert_eq!(f.marker, Some(3));
        assert_eq!((f.start_s, f.duration_s), (20.0, 5.0));
        assert_eq!("occlude@20".parse::<FaultSpec>().unwrap().marker, None);
        let e = "occlude:x@1".parse::<FaultSpec>().unwrap_err().to_string();
        assert!(e.contains("ID") && e.contains("\"x\""), "{e}");
        let e = "occlude:-1@1".parse::<FaultSpec>().unwrap_err().to_string();
        assert!(e.contains("\"-1\""), "{e}");
        let e = "link_cut:2@1".parse::<FaultSpec>().unwrap_err().to_string();
        assert!(e.contains("only occlude") && e.contains("link_cut"), "{e}");
        // The id is in the summary's report only when given.
        let json = serde_json::to_string(&f).unwrap();
        assert!(json.contains("\"marker\":3"), "{json}");
        let plain = serde_json::to_string(&"occlude@1".parse::<FaultSpec>().unwrap()).unwrap();
        assert!(!plain.contains("marker"), "{plain}");
    }

    #[test]
    fn coin_is_fair_and_seeded() {
        let heads = (0..10_000).filter(|&n| coin(7, n) & 1 == 0).count();
        assert!((4_700..5_300).contains(&heads), "{heads}");
        assert_ne!(
            (0..64).map(|n| coin(1, n) & 1).collect::<Vec<_>>(),
            (0..64).map(|n| coin(2, n) & 1).collect::<Vec<_>>()
        );
    }

    #[test]
    fn paints_a_facing_marker_and_nothing_else() {
        let mut f = Frame::new(64, 48);
        f.data.fill(100);
        // A white square 0.2 m at 1 m in front of a 50 px focal camera: 10 px wide.
        for y in 19..29 {
            for x in 27..37 {
                f.data[y * 64 + x] = 250;
            }
        }
        let proj = Projection {
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 24.0,
            dist: [0.0; 5],
        };
        let pose = Isometry3::translation(0.0, 0.0, 1.0);
        assert!(paint_marker(&mut f, &proj, &pose, 0.1));
        assert!(f.data.iter().all(|&v| v == 100), "marker left visible");
        // Behind the camera: nothing painted.
        let behind = Isometry3::translation(0.0, 0.0, -1.0);
        f.data[0] = 7;
        assert!(!paint_marker(&mut f, &proj, &behind, 0.1));
        assert_eq!(f.data[0], 7);
    }

    /// The monitor on hand-made frames: `off_station_m` of error and `detected` per
    /// frame at 10 fps, with `events` on the frames given.
    fn monitor_run(
        specs: &[&str],
        seconds: f64,
        frame: &dyn Fn(f64) -> (bool, f64, Directive),
        events: &dyn Fn(f64) -> Vec<FailsafeEvent>,
    ) -> Vec<FaultReport> {
        let plan = FaultPlan {
            specs: specs.iter().map(|s| s.parse().unwrap()).collect(),
            seed: 1,
        };
        let mut m = FaultMonitor::new(&plan, Isometry3::identity(), Isometry3::identity());
        let n = (seconds * 10.0).round() as u64;
        for i in 1..=n {
            let t = i as f64 / 10.0;
            let (detected, err, directive) = frame(t);
            let rec = FrameRecord {
                seq: i,
                stamp_s: t,
                exposure_used_us: 2000.0,
                exposure: markhold_exposure::ExposureStep {
                    exposure_us: 2000.0,
                    metric: 0.5,
                    used_frame: true,
                    roi: None,
                },
                detected,
                corners: None,
                t_cam_marker: None,
                cov_cam: None,
                reproj_rms_px: f64::NAN,
                markers_used: 0,
                effort: Default::default(),
                directive,
                latency_s: 0.0,
            };
            let at = Isometry3::translation(err, 0.0, 0.0);
            let truth = Truth {
                time_s: t,
                t_world_vehicle: at,
                t_world_cam: at,
                t_cam_marker: Isometry3::identity(),
                velocity_world_mps: [0.0; 3],
                armed: true,
                mode: 19,
                pwm: [1500; 8],
                lockstep_timeouts: 0,
            };
            m.observe(&rec, &truth, &events(t), &[], true, true);
        }
        m.into_reports()
    }

    /// A fault with no effect (the marker seen, the vehicle on station all along): no
    /// loss, so nothing "again" or "regained".
    #[test]
    fn a_fault_with_no_effect_reports_no_recovery() {
        for kind in ["exposure_ignored", "lamp_off", "late_frames", "drop_frames"] {
            let r = monitor_run(
                &[&format!("{kind}@2+1")],
                6.0,
                &|_| (true, 0.01, Directive::Command),
                &|_| Vec::new(),
            );
            let r = &r[0];
            assert_eq!(r.marker_missed_at_s, None, "{kind}: {r:?}");
            assert_eq!(r.marker_detected_again_at_s, None, "{kind}: {r:?}");
            assert_eq!(r.station_regained_at_s, None, "{kind}: {r:?}");
            assert_eq!(r.neutral_at_s, None, "{kind}: {r:?}");
        }
    }

    /// An occlusion: missed, neutral (also when it comes after the window, as the
    /// supervisor's hold time runs out), detected again, station regained after a loss.
    #[test]
    fn an_occlusion_reports_its_loss_and_recovery() {
        let r = monitor_run(
            &["occlude@2+0.5"],
            8.0,
            &|t| {
                let hidden = (2.0..2.5).contains(&t);
                let directive = if (2.5..3.0).contains(&t) {
                    Directive::Neutral
                } else {
                    Directive::Command
                };
                let err = if (2.0..4.0).contains(&t) { 0.3 } else { 0.01 };
                (!hidden, err, directive)
            },
            &|_| Vec::new(),
        );
        let r = &r[0];
        assert_eq!(r.marker_missed_at_s, Some(2.0), "{r:?}");
        assert_eq!(r.neutral_at_s, Some(2.5), "{r:?}");
        assert_eq!(r.marker_detected_again_at_s, Some(2.5), "{r:?}");
        assert_eq!(r.station_regained_at_s, Some(4.0), "{r:?}");
    }

    /// Two faults: what happens during the second is listed under the second only.
    #[test]
    fn events_are_listed_under_the_fault_that_caused_them() {
        let r = monitor_run(
            &["link_cut@1+0.5", "occlude@4+1"],
            7.0,
            &|t| (!(4.0..=4.6).contains(&t), 0.01, Directive::Command),
            &|t| {
                if (t - 1.2).abs() < 1e-9 {
                    vec![FailsafeEvent::VehicleHeartbeatLost {
                        at_s: t,
                        age_s: 1.0,
                    }]
                } else if (t - 4.5).abs() < 1e-9 {
                    vec![FailsafeEvent::MarkerLost {
                        at_s: t,
                        last_seen_s: 3.4,
                    }]
                } else {
                    Vec::new()
                }
            },
        );
        assert_eq!(r[0].heartbeat_lost_at_s, Some(1.2), "{:?}", r[0]);
        assert_eq!(r[0].marker_lost_at_s, None, "{:?}", r[0]);
        assert_eq!(r[0].marker_missed_at_s, None, "{:?}", r[0]);
        assert_eq!(r[1].marker_lost_at_s, Some(4.5), "{:?}", r[1]);
        assert!(r[1].marker_missed_at_s.is_some(), "{:?}", r[1]);
        assert_eq!(r[1].heartbeat_lost_at_s, None, "{:?}", r[1]);
    }
}
