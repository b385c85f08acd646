//! Keeping the marker in view: a guard band along the image edges that takes the push
//! toward the edge out of the PID efforts and points the camera back, and a bounded way
//! back after the marker slipped out (turn toward where it was last seen, then hold).
//!
//! Image motion of a normalized image point (x, y) at depth z for a camera moving with
//! velocity v and angular velocity w (both in the camera frame), the classic
//! interaction matrix of image-based visual servoing:
//! dx = (-vx + x vz) / z + x y wx - (1 + x^2) wy + y wz,
//! dy = (-vy + y vz) / z + (1 + y^2) wx - x y wy - x wz.

use nalgebra::{Isometry3, Matrix3, Point3, Vector2, Vector3};

use super::ViewLimits;
use crate::types::{wrap_pi, Effort};

/// The guard band never starts further in than this fraction of the image.
const GUARD_MAX: f64 = 0.12;
/// ... nor further out than this (a station with a thinner margin is refused).
const GUARD_MIN: f64 = 0.03;
/// The guard band is this share of the station's own margin, so the vehicle on station
/// is never inside it.
const GUARD_SHARE: f64 = 0.6;
/// Effort pushing the marker's image back inward at the edge (translation and yaw).
const PUSH: f64 = 0.15;
/// The way back: largest turn, radians, and the yaw effort per radian, limited.
const SEARCH_MAX_TURN_RAD: f64 = 1.0;
const SEARCH_YAW_GAIN: f64 = 0.8;
const SEARCH_YAW_LIMIT: f64 = 0.3;
/// The turn is done within this heading error; then hold.
const SEARCH_DONE_RAD: f64 = 0.05;
/// Heave toward a marker that left at the top or bottom edge: effort and duration.
const SEARCH_HEAVE: f64 = 0.12;
const SEARCH_HEAVE_S: f64 = 1.0;
/// Back to the depth the marker was last seen from (telemetry): heave effort per metre,
/// limited to the edge heave's effort; within the dead band, hold.
const SEARCH_DEPTH_GAIN: f64 = 1.0;
const SEARCH_DEPTH_BAND_M: f64 = 0.03;

/// The marker corner nearest an image edge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct EdgeState {
    /// Distance of the corner inside the edge, fraction of the image's width (left,
    /// right) or height (top, bottom); negative outside.
    pub margin: f64,
    /// Outward normal of that edge in the image (x right, y down).
    pub normal: Vector2<f64>,
    /// The corner in the camera frame.
    pub corner: Vector3<f64>,
}

/// Where the marker was when it was last seen, for the way back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct LastSeen {
    pub edge: EdgeState,
    /// Heading to turn by to put the marker's centre on the camera's axis, radians
    /// (+ right).
    pub turn_rad: f64,
    /// The vehicle's heading then (telemetry), if known.
    pub heading_rad: Option<f64>,
    /// The marker's horizontal position (north, east) in the vehicle's local frame, when
    /// heading and local position (telemetry) were known.
    pub marker_ne: Option<[f64; 2]>,
    /// The vehicle's depth then (local position, down, m), when known.
    pub down_m: Option<f64>,
}

/// The vehicle's navigation telemetry on a frame: heading (rad) and, when it has a
/// position source, local position north and east (m); its depth (m, down) when known.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Nav {
    pub heading_rad: Option<f64>,
    pub position_ne: Option<[f64; 2]>,
    pub down_m: Option<f64>,
}

#[derive(Clone, Debug)]
pub(super) struct ViewGuard {
    limits: ViewLimits,
    r_body_cam: Matrix3<f64>,
    /// Margin where the guard band starts.
    pub guard: f64,
    out_limit: [f64; 6],
}

impl ViewGuard {
    pub fn new(
        limits: ViewLimits,
        t_vehicle_cam: &Isometry3<f64>,
        t_marker_goal: &Isometry3<f64>,
        out_limit: [f64; 6],
    ) -> Self {
        let mut g = Self {
            limits,
            r_body_cam: *t_vehicle_cam.rotation.to_rotation_matrix().matrix(),
            guard: GUARD_MAX,
            out_limit,
        };
        let t_cam_goal_marker = (t_marker_goal * t_vehicle_cam).inverse();
        let at_goal = g.nearest_edge(&t_cam_goal_marker).margin;
        g.guard = (GUARD_SHARE * at_goal).clamp(GUARD_MIN, GUARD_MAX);
        g
    }

    /// The marker corner nearest an image edge for the marker at `t_cam_marker`.
    pub fn nearest_edge(&self, t_cam_marker: &Isometry3<f64>) -> EdgeState {
        let l = &self.limits;
        let h = l.marker_half_m;
        let (w, hh) = (l.right - l.left, l.bottom - l.top);
        let mut best = EdgeState {
            margin: f64::INFINITY,
            normal: Vector2::zeros(),
            corner: Vector3::zeros(),
        };
        for (x, y) in [(-h, h), (h, h), (h, -h), (-h, -h)] {
            let p = (t_cam_marker * Point3::new(x, y, 0.0)).coords;
            if p.z <= 1e-6 {
                // Behind the camera: outside, on the side of the centre's ray.
                continue;
            }
            let (u, v) = (p.x / p.z, p.y / p.z);
            for (m, n) in [
                ((u - l.left) / w, Vector2::new(-1.0, 0.0)),
                ((l.right - u) / w, Vector2::new(1.0, 0.0)),
                ((v - l.top) / hh, Vector2::new(0.0, -1.0)),
                ((l.bottom - v) / hh, Vector2::new(0.0, 1.0)),
            ] {
                if m < best.margin {
                    best = EdgeState {
                        margin: m,
                        normal: n,
                        corner: p,
                    };
                }
            }
        }
        best
    }

    /// Within the guard band: take out the part of the translation effort that moves the
    /// corner outward, push it back inward, and the same for yaw; the more the closer to
    /// the edge. Outside the band the efforts are left as they are.
    pub fn apply(&self, e: &mut Effort, edge: &EdgeState) {
        let w = ((self.guard - edge.margin) / self.guard).clamp(0.0, 1.0);
        if w <= 0.0 || !edge.margin.is_finite() {
            return;
        }
        let p = edge.corner;
        let z = p.z.max(0.05);
        let (x, y) = (p.x / z, p.y / z);
        let n = edge.normal;
        // Camera translation direction that moves the corner outward fastest: J_t^T n.
        let d_cam = Vector3::new(-n.x, -n.y, n.x * x + n.y * y) / z;
        let d_body = self.r_body_cam * d_cam;
        if let Some(dn) = d_body.try_normalize(1e-9) {
            let mut t = Vector3::new(e.surge, e.sway, e.heave);
            let out = t.dot(&dn);
            if out > 0.0 {
                t -= w * out * dn;
            }
            t -= w * PUSH * dn;
            (e.surge, e.sway, e.heave) = (t.x, t.y, t.z);
        }
        // Outward image speed of the corner per unit body yaw rate (+ right).
        let wc = self.r_body_cam.transpose() * Vector3::z();
        let xd = x * y * wc.x - (1.0 + x * x) * wc.y + y * wc.z;
        let yd = (1.0 + y * y) * wc.x - x * y * wc.y - x * wc.z;
        let s = n.x * xd + n.y * yd;
        if s.abs() > 0.2 {
            if e.yaw * s > 0.0 {
                e.yaw *= 1.0 - w;
            }
            e.yaw -= w * PUSH * s.signum();
        }
        self.clamp(e);
    }

    fn clamp(&self, e: &mut Effort) {
        let mut a = e.to_array();
        for (v, l) in a.iter_mut().zip(self.out_limit) {
            *v = v.clamp(-l, l);
        }
        *e = Effort::from_array(a);
    }

    /// What the way back needs from a measurement: the nearest edge, the turn that puts
    /// the marker centre on the camera's axis, and where the marker is in the local frame.
    pub fn last_seen(
        &self,
        t_vehicle_cam: &Isometry3<f64>,
        t_cam_marker: &Isometry3<f64>,
        nav: Nav,
    ) -> LastSeen {
        let c = (t_vehicle_cam * t_cam_marker).translation.vector;
        let turn_rad = wrap_pi(c.y.atan2(c.x) - self.axis_yaw());
        let marker_ne = match (nav.heading_rad, nav.position_ne) {
            (Some(psi), Some([n, e])) => {
                let (sn, cs) = psi.sin_cos();
                Some([n + cs * c.x - sn * c.y, e + sn * c.x + cs * c.y])
            }
            _ => None,
        };
        LastSeen {
            edge: self.nearest_edge(t_cam_marker),
            turn_rad,
            heading_rad: nav.heading_rad,
            marker_ne,
            down_m: nav.down_m,
        }
    }

    /// Heading of the camera's axis in the body frame, rad (+ right).
    fn axis_yaw(&self) -> f64 {
        let axis = self.r_body_cam * Vector3::z();
        axis.y.atan2(axis.x)
    }

    /// The way back `age_s` after the marker was last seen (at most `max_s`), with the
    /// vehicle's navigation now: turn the camera toward where the marker is (from the
    /// local position when known, else where it was last seen), closed on the heading
    /// telemetry and at most `SEARCH_MAX_TURN_RAD` from the heading then; heave toward it
    /// briefly if it left at the top or bottom, else back to the depth it was seen from
    /// (a vehicle without depth hold floats or sinks out of view while the marker is
    /// hidden); then hold. None when there is nothing to do (neutral).
    pub fn search(&self, seen: &LastSeen, age_s: f64, max_s: f64, nav: Nav) -> Option<Effort> {
        if !(0.0..=max_s).contains(&age_s) {
            return None;
        }
        let mut e = Effort::NEUTRAL;
        if let (Some(then), Some(now)) = (seen.heading_rad, nav.heading_rad) {
            let turn = match (seen.marker_ne, nav.position_ne) {
                (Some([mn, me]), Some([n, en])) => {
                    wrap_pi((me - en).atan2(mn - n) - self.axis_yaw() - then)
                }
                _ => seen.turn_rad,
            };
            let target = then + turn.clamp(-SEARCH_MAX_TURN_RAD, SEARCH_MAX_TURN_RAD);
            let err = wrap_pi(target - now);
            if err.abs() > SEARCH_DONE_RAD {
                e.yaw = (SEARCH_YAW_GAIN * err).clamp(-SEARCH_YAW_LIMIT, SEARCH_YAW_LIMIT);
            }
        }
        // Left at the top or bottom edge: a short heave the way that brings it back.
        // Moving the camera toward the edge's side moves the image inward (down for the
        // bottom edge of a forward-looking camera).
        let n = seen.edge.normal;
        if age_s <= SEARCH_HEAVE_S && n.y != 0.0 && seen.edge.margin < self.guard {
            let d_body = self.r_body_cam * Vector3::new(n.x, n.y, 0.0);
            if d_body.z.abs() > 0.3 {
                e.heave = SEARCH_HEAVE * d_body.z.signum();
            }
        } else if let (Some(then), Some(now)) = (seen.down_m, nav.down_m) {
            let dz = then - now;
            if dz.abs() > SEARCH_DEPTH_BAND_M {
                e.heave = (SEARCH_DEPTH_GAIN * dz).clamp(-SEARCH_HEAVE, SEARCH_HEAVE);
            }
        }
        self.clamp(&mut e);
        (!e.is_neutral()).then_some(e)
    }
}
