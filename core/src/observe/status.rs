//! The run's status for the web page (`--web`): engagement, marker, exposure, position
//! error, link and failsafe state, and the newest camera frame at a bounded rate.
//!
//! The loop never waits on the page. Per frame it writes a fixed-size [`Status`] and, at
//! most `snapshot_hz` times per second of frame time, copies the pixels into a buffer
//! made at start. Both slots are taken with `try_lock`: while the web thread holds one
//! (to copy a few hundred bytes, or to swap its own buffer in) this frame's update is
//! skipped and the next frame's carries the news (newest wins). Nothing is allocated on
//! the loop's side after the first frame of a size.

use crate::CoreError;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};

use markhold_autopilot::{ArduSubMode, FailsafeEvent};
use markhold_exposure::{Corners, Roi};
use nalgebra::Isometry3;
use serde::Serialize;

use crate::params::LoadedSite;
use crate::pipeline::{FrameView, Observer};

/// Whether markhold is commanding, as the runner's engagement sees it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Engagement {
    /// A runner without pilot engagement (`hil` against its own simulated vehicle):
    /// markhold commands whenever the supervisor lets it.
    #[default]
    Always,
    /// The vehicle not heard yet.
    Waiting,
    /// Waits for the pilot to engage (arm in the site's mode, or switch to it armed).
    Ready,
    /// Commanding.
    Engaged,
    /// Just let go: neutral, then the override released.
    Releasing,
    /// The pilot engaged; waits to hear the pilot's station before commanding.
    Pending,
}

impl Engagement {
    fn code(self) -> u8 {
        self as u8
    }

    fn from_code(c: u8) -> Self {
        [
            Self::Always,
            Self::Waiting,
            Self::Ready,
            Self::Engaged,
            Self::Releasing,
            Self::Pending,
        ]
        .get(usize::from(c))
        .copied()
        .unwrap_or_default()
    }
}

impl From<crate::engage::EngageState> for Engagement {
    fn from(s: crate::engage::EngageState) -> Self {
        use crate::engage::EngageState as E;
        match s {
            E::Waiting => Self::Waiting,
            E::Ready => Self::Ready,
            E::Engaged => Self::Engaged,
            E::Releasing { .. } => Self::Releasing,
            E::Pending { .. } => Self::Pending,
        }
    }
}

/// The marker in the last frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct MarkerStatus {
    pub detected: bool,
    /// Markers of the map the pose used.
    pub markers_used: u32,
    pub reproj_rms_px: Option<f64>,
    /// Frame time the marker was last seen.
    pub seen_s: Option<f64>,
}

/// The exposure of the last frame and the one commanded after it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ExposureStatus {
    pub used_us: f64,
    pub next_us: f64,
    pub gain_db: f64,
    pub metric: Option<f64>,
    /// The controller learned from this frame.
    pub used_frame: bool,
}

/// Where the vehicle is against its station (the station keeper's body-frame error).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PositionError {
    pub distance_m: f64,
    /// Forward, right, down, metres (docs/frames.md).
    pub xyz_m: [f64; 3],
    pub yaw_deg: f64,
}

/// The link's view of the vehicle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LinkStatus {
    pub system_id: u8,
    pub armed: bool,
    pub mode: Option<ArduSubMode>,
    /// The vehicle is heard within the link's timeout.
    pub heard: bool,
    /// Frame time the vehicle was last heard.
    pub heard_s: Option<f64>,
    /// ArduSub reports a failsafe (HEARTBEAT system_status CRITICAL or EMERGENCY).
    pub vehicle_failsafe: bool,
    pub sent: u64,
    pub received: u64,
    /// Pilot input (RC override / MANUAL_CONTROL) markhold sent.
    pub pilot_inputs_sent: u64,
    /// Frame time of the pilot's own last input.
    pub pilot_input_s: Option<f64>,
}

/// markhold's failsafe supervisor.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FailsafeStatus {
    pub vehicle_lost: bool,
    pub vision_stalled: bool,
    pub marker_lost: bool,
    pub shutting_down: bool,
    /// The last transition, with its frame time.
    pub last: Option<FailsafeEvent>,
}

/// Everything the page shows about the loop, as of the newest frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Status {
    /// Frames the loop stepped so far.
    pub frames: u64,
    /// Frames the loop stepped per second of frame time, over the last second or more
    /// (a loop slower than its camera acts on fewer frames than the camera gives).
    pub effective_fps: Option<f64>,
    pub seq: u64,
    pub stamp_s: f64,
    pub engagement: Engagement,
    pub marker: MarkerStatus,
    pub exposure: ExposureStatus,
    pub position: Option<PositionError>,
    /// What the supervisor let through: command, neutral, silent, shutdown.
    pub directive: &'static str,
    /// The station keeper's effort: surge, sway, heave, roll, pitch, yaw.
    pub effort: [f64; 6],
    pub link: Option<LinkStatus>,
    pub failsafe: FailsafeStatus,
}

/// The newest camera frame handed to the page, with what to draw on it.
#[derive(Debug, Clone, Default)]
pub struct Snapshot {
    pub seq: u64,
    pub stamp_s: f64,
    pub width: u32,
    pub height: u32,
    /// 8-bit grey, `width * height`.
    pub data: Vec<u8>,
    /// The tracked marker's corners.
    pub corners: Option<Corners>,
    /// The region the exposure controller metered.
    pub roi: Option<Roi>,
    /// Not yet taken by the page.
    fresh: bool,
}

impl Snapshot {
    /// A buffer for `width` x `height` frames, made once.
    pub fn with_capacity(width: u32, height: u32) -> Self {
        Self {
            data: Vec::with_capacity(width as usize * height as usize),
            ..Self::default()
        }
    }
}

struct BoardInner {
    status: Mutex<Status>,
    snapshot: Mutex<Snapshot>,
    engagement: AtomicU8,
    /// The frame size the buffers are made for.
    size: (u32, u32),
}

/// What the loop publishes and the web page reads; cheap to clone (shared).
#[derive(Clone)]
pub struct StatusBoard(Arc<BoardInner>);

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Plain copies under the lock: what a panicking holder left is consistent.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl StatusBoard {
    /// A board for frames of `width` x `height` (the snapshot buffer is made here).
    pub fn new(width: u32, height: u32) -> Self {
        Self(Arc::new(BoardInner {
            status: Mutex::new(Status::default()),
            snapshot: Mutex::new(Snapshot::with_capacity(width, height)),
            engagement: AtomicU8::new(Engagement::Always.code()),
            size: (width, height),
        }))
    }

    /// The page's own buffer for [`Self::take_snapshot`], made at start like the board's:
    /// the swap then never hands the loop a buffer too small for a frame.
    pub fn spare_snapshot(&self) -> Snapshot {
        let (w, h) = self.0.size;
        Snapshot::with_capacity(w, h)
    }

    /// The runner's engagement (a runner with pilot engagement sets it every frame).
    pub fn set_engagement(&self, e: impl Into<Engagement>) {
        self.0.engagement.store(e.into().code(), Ordering::Relaxed);
    }

    /// The newest status (a copy).
    pub fn status(&self) -> Status {
        let mut s = *lock(&self.0.status);
        s.engagement = Engagement::from_code(self.0.engagement.load(Ordering::Relaxed));
        s
    }

    /// Swap the newest frame into `mine` if one came since the last take; true if so.
    /// `mine`'s old buffer goes back to the board (no allocation on either side).
    pub fn take_snapshot(&self, mine: &mut Snapshot) -> bool {
        let mut slot = lock(&self.0.snapshot);
        if !slot.fresh {
            return false;
        }
        std::mem::swap(&mut *slot, mine);
        slot.fresh = false;
        mine.fresh = false;
        true
    }

    /// The loop's side: the status, unless the page holds it right now.
    fn publish(&self, s: &Status) -> bool {
        match self.0.status.try_lock() {
            Ok(mut slot) => {
                *slot = *s;
                true
            }
            Err(TryLockError::Poisoned(p)) => {
                *p.into_inner() = *s;
                true
            }
            Err(TryLockError::WouldBlock) => false,
        }
    }

    /// The loop's side: the frame's pixels, unless the page holds the slot right now.
    fn offer_frame(&self, v: &FrameView<'_>) -> bool {
        let mut slot = match self.0.snapshot.try_lock() {
            Ok(s) => s,
            Err(TryLockError::Poisoned(p)) => p.into_inner(),
            Err(TryLockError::WouldBlock) => return false,
        };
        let f = v.frame;
        let n = (f.width as usize * f.height as usize).min(f.data.len());
        slot.data.clear();
        // Within the capacity made at start for this size: no allocation.
        slot.data.extend_from_slice(&f.data[..n]);
        slot.seq = v.rec.seq;
        slot.stamp_s = v.rec.stamp_s;
        slot.width = f.width;
        slot.height = f.height;
        slot.corners = v.rec.corners;
        slot.roi = v.rec.exposure.roi;
        slot.fresh = true;
        true
    }
}

/// The observer that keeps a [`StatusBoard`] up to date.
pub struct StatusObserver {
    board: StatusBoard,
    t_vehicle_cam: Isometry3<f64>,
    goal: Isometry3<f64>,
    /// Frame time between two snapshots, s.
    snapshot_period_s: f64,
    last_snapshot_s: Option<f64>,
    status: Status,
    /// Published with the next frame (the page held the slot).
    behind: bool,
    /// Dropped at the end of the run (the web server, which stops then).
    keep: Option<Box<dyn Send>>,
    /// The rate's window: its first frame time and the frames since.
    rate_window: Option<(f64, u64)>,
}

impl StatusObserver {
    /// Publish to `board`; a frame at most `snapshot_hz` times per second of frame time.
    pub fn new(site: &LoadedSite, board: StatusBoard, snapshot_hz: f64) -> Self {
        Self {
            board,
            t_vehicle_cam: site.t_vehicle_cam(),
            goal: site.site.station.t_marker_vehicle(),
            snapshot_period_s: if snapshot_hz > 0.0 {
                1.0 / snapshot_hz
            } else {
                f64::INFINITY
            },
            last_snapshot_s: None,
            status: Status::default(),
            behind: false,
            keep: None,
            rate_window: None,
        }
    }

    /// Keep `thing` (the web server) alive until the run finishes.
    pub fn keeping(mut self, thing: impl Send + 'static) -> Self {
        self.keep = Some(Box::new(thing));
        self
    }

    fn update(&mut self, v: &FrameView<'_>) {
        let r = v.rec;
        let s = &mut self.status;
        s.frames += 1;
        self.rate_window = match self.rate_window {
            Some((t0, k)) if r.stamp_s >= t0 => {
                let span = r.stamp_s - t0;
                if span >= 1.0 {
                    s.effective_fps = Some((k + 1) as f64 / span);
                    Some((r.stamp_s, 0))
                } else {
                    Some((t0, k + 1))
                }
            }
            _ => Some((r.stamp_s, 0)),
        };
        s.seq = r.seq;
        s.stamp_s = r.stamp_s;
        if r.detected {
            s.marker.seen_s = Some(r.stamp_s);
        }
        s.marker.detected = r.detected;
        s.marker.markers_used = r.markers_used;
        s.marker.reproj_rms_px = r.reproj_rms_px.is_finite().then_some(r.reproj_rms_px);
        s.exposure = ExposureStatus {
            used_us: r.exposure_used_us,
            next_us: r.exposure.exposure_us,
            gain_db: v.frame.meta.gain_db,
            metric: r.exposure.metric.is_finite().then_some(r.exposure.metric),
            used_frame: r.exposure.used_frame,
        };
        s.position = r.t_cam_marker.map(|t_cam_marker| {
            let meas = (self.t_vehicle_cam * t_cam_marker).inverse();
            let e = markhold_autopilot::keeper::body_error(&meas, &self.goal);
            PositionError {
                distance_m: (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt(),
                xyz_m: [e[0], e[1], e[2]],
                yaw_deg: e[5].to_degrees(),
            }
        });
        s.directive = crate::record::directive_name(r.directive);
        let e = &r.effort;
        s.effort = [e.surge, e.sway, e.heave, e.roll, e.pitch, e.yaw];
        // Copy fields only: the state's strings would allocate.
        s.link = v.vehicle.map(|st| LinkStatus {
            system_id: st.system_id,
            armed: st.armed,
            mode: st.mode,
            heard: st.heartbeat_ok,
            heard_s: st.last_heartbeat_s,
            vehicle_failsafe: st.vehicle_failsafe,
            sent: st.counters.sent,
            received: st.counters.received,
            pilot_inputs_sent: st.counters.pilot_inputs,
            pilot_input_s: st.pilot.last_s,
        });
        let f = &mut s.failsafe;
        for e in v.events {
            match e {
                FailsafeEvent::VehicleHeartbeatLost { .. } => f.vehicle_lost = true,
                FailsafeEvent::VehicleHeartbeatRestored { .. }
                | FailsafeEvent::VehicleConnected { .. } => f.vehicle_lost = false,
                FailsafeEvent::VisionStalled { .. } => f.vision_stalled = true,
                FailsafeEvent::VisionRestored { .. } => f.vision_stalled = false,
                FailsafeEvent::MarkerLost { .. } => f.marker_lost = true,
                FailsafeEvent::MarkerReacquired { .. } => f.marker_lost = false,
                FailsafeEvent::ShutdownRequested { .. } => f.shutting_down = true,
                // Others (the marker-loss action) change no flag; `last` names them.
                _ => {}
            }
            f.last = Some(*e);
        }
        f.shutting_down |= v.shutdown;
    }
}

impl Observer for StatusObserver {
    fn name(&self) -> &'static str {
        "status"
    }

    fn frame(&mut self, v: &FrameView<'_>) {
        self.update(v);
        self.behind = !self.board.publish(&self.status);
        let due = self
            .last_snapshot_s
            .is_none_or(|t| v.rec.stamp_s - t >= self.snapshot_period_s || v.rec.stamp_s < t);
        if due && self.board.offer_frame(v) {
            self.last_snapshot_s = Some(v.rec.stamp_s);
        }
    }

    fn finish(mut self: Box<Self>) -> Result<(), CoreError> {
        if self.behind {
            self.board.publish(&self.status);
        }
        drop(self.keep.take());
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;

    #[test]
    fn engagement_codes_round_trip() {
        for e in [
            Engagement::Always,
            Engagement::Waiting,
            Engagement::Ready,
            Engagement::Engaged,
            Engagement::Releasing,
            Engagement::Pending,
        ] {
            assert_eq!(Engagement::from_code(e.code()), e);
        }
        assert_eq!(Engagement::from_code(200), Engagement::Always);
    }

    #[test]
    fn a_held_slot_skips_the_update_and_the_snapshot_swaps_buffers() {
        let board = StatusBoard::new(4, 2);
        let s = Status {
            frames: 3,
            ..Status::default()
        };
        {
            let _held = board.0.status.lock().unwrap();
            assert!(!board.publish(&s), "the loop does not wait for the page");
        }
        assert!(board.publish(&s));
        assert_eq!(board.status().frames, 3);
        board.set_engagement(Engagement::Engaged);
        assert_eq!(board.status().engagement, Engagement::Engaged);

        let mut mine = board.spare_snapshot();
        assert!(!board.take_snapshot(&mut mine), "nothing offered yet");
        {
            let mut slot = board.0.snapshot.lock().unwrap();
            slot.data.extend_from_slice(&[1, 2, 3, 4, 5, 6, 7, 8]);
            slot.fresh = true;
        }
        assert!(board.take_snapshot(&mut mine));
        assert_eq!(mine.data, [1, 2, 3, 4, 5, 6, 7, 8]);
        assert!(!board.take_snapshot(&mut mine), "taken once");
        // The buffer handed back to the loop holds a whole frame: no allocation there.
        assert!(board.0.snapshot.lock().unwrap().data.capacity() >= 4 * 2);
    }
}
