//! The 6-DOF station keeper: pose error in the body frame, a covariance-weighted filter,
//! six PID axes stepped at a fixed rate on the loop's clock, and marker-loss handling.
//!
//! `StationKeeper::update` is a pure function of its inputs and its state: no wall clock,
//! no telemetry arriving behind its back, so HIL runs repeat bit for bit.

use markhold_geometry::skew;
use nalgebra::{Isometry3, Matrix3, Matrix6, UnitQuaternion, Vector3};
use serde::Serialize;

mod view;

use crate::config::{AxisConfig, ControllerConfig, StationConfig};
use crate::error::AutopilotError;
use crate::types::ArduSubMode;
pub use crate::types::{wrap_pi, Effort};

/// One marker pose from vision: the marker in the camera frame, with its 6x6 covariance
/// (tx, ty, tz, rx, ry, rz) in the camera frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseMeasurement {
    /// Frame stamp, loop seconds.
    pub stamp_s: f64,
    /// Pose of the marker in the camera frame.
    pub t_cam_marker: Isometry3<f64>,
    /// Covariance of `t_cam_marker`, camera frame.
    pub cov_cam: Matrix6<f64>,
}

/// The camera's image edges as undistorted normalized coordinates (x/z, y/z; x right,
/// y down, so `left` and `top` are negative), and the marker's half edge: what the keeper
/// needs to keep the marker in view (`StationKeeper::set_view`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewLimits {
    pub left: f64,
    pub right: f64,
    pub top: f64,
    pub bottom: f64,
    /// Half the marker's edge, metres.
    pub marker_half_m: f64,
}

/// Where the keeper stands with respect to the marker.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum KeeperStatus {
    /// No measurement yet (or since a reset).
    NoFix,
    /// Marker seen this frame; PIDs running.
    Tracking,
    /// Marker missed, within `marker_lost_hold_s`: last command held.
    Holding,
    /// Marker slipped out of view: the bounded way back (turn toward where it was last
    /// seen, then hold) runs.
    Searching,
    /// Marker lost longer than the hold: neutral.
    Lost,
}

/// What ArduSub holds by itself in the flight mode it reports, so that the keeper does
/// not close a second loop around it (ArduSub's source, this version and upstream):
/// - STABILIZE and ALT_HOLD hold roll and pitch level: the roll and pitch sticks are lean
///   angle targets (`get_pilot_desired_lean_angles`), and the station is level, so the
///   keeper sends none (its own roll/pitch loop around ArduSub's attitude loop, a frame
///   late, made both oscillate).
/// - They hold the heading: the yaw stick is a yaw *rate*, `stick * ACRO_YAW_P` centidegrees
///   per second (Attitude.cpp `get_pilot_desired_yaw_rate`), and 250 ms after it returns
///   to centre ArduSub holds the heading it then has (control_althold.cpp /
///   mode_althold.cpp `althold_run`). The keeper's yaw effort is therefore already
///   integrated by ArduSub: its integral term would make a double integrator (the
///   heading wound up and swung), so it is off, and so is its derivative
///   (`fit_yaw_to_rate_stick`).
/// - ALT_HOLD also holds depth: with the vehicle's depth in telemetry the keeper's heave
///   goes to ArduSub's depth controller as a target (`StationKeeper::depth_target_m`),
///   not as throttle stick (see there).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct AutopilotHolds {
    /// Roll and pitch held level.
    pub attitude: bool,
    /// Heading held, yaw stick a rate.
    pub heading: bool,
    /// Depth held, and a depth target taken (SET_POSITION_TARGET_GLOBAL_INT).
    pub depth: bool,
}

impl AutopilotHolds {
    /// The holds of an ArduSub flight mode (none while it is unknown, in MANUAL and in the
    /// position-target modes, where the keeper does not send efforts).
    pub fn of_mode(mode: Option<ArduSubMode>) -> Self {
        match mode {
            Some(ArduSubMode::Stabilize) => Self {
                attitude: true,
                heading: true,
                depth: false,
            },
            Some(ArduSubMode::AltHold) => Self {
                attitude: true,
                heading: true,
                depth: true,
            },
            _ => Self::default(),
        }
    }
}

/// Body-frame pose error of the vehicle relative to its station: the goal expressed in the
/// current body frame. (surge, sway, heave) in metres, (roll, pitch, yaw) in radians, yaw
/// wrapped to (-pi, pi].
pub fn body_error(
    t_marker_vehicle_meas: &Isometry3<f64>,
    t_marker_vehicle_goal: &Isometry3<f64>,
) -> [f64; 6] {
    let t_b_goal = t_marker_vehicle_meas.inverse() * t_marker_vehicle_goal;
    let p = t_b_goal.translation.vector;
    let (r, pi, y) = t_b_goal.rotation.euler_angles();
    [p.x, p.y, p.z, wrap_pi(r), wrap_pi(pi), wrap_pi(y)]
}

/// Propagates the camera-frame covariance of `t_cam_marker` to the body-frame error.
/// Perturbation model: t' = t + dt, R' = exp(dr) R, both in the camera frame.
fn body_error_variances(
    r_body_cam: &Matrix3<f64>,
    t_cam_marker: &Isometry3<f64>,
    t_marker_goal: &Vector3<f64>,
    cov_cam: &Matrix6<f64>,
) -> [f64; 6] {
    let a = t_cam_marker.rotation * t_marker_goal;
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(r_body_cam);
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-(r_body_cam * skew(&a))));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(r_body_cam);
    let c = j * cov_cam * j.transpose();
    [
        c[(0, 0)],
        c[(1, 1)],
        c[(2, 2)],
        c[(3, 3)],
        c[(4, 4)],
        c[(5, 5)],
    ]
}

/// Random-walk Kalman filter per axis: weights each measurement by its variance against the
/// prediction, and bridges frames where the marker is missed (prediction only).
#[derive(Clone, Debug)]
struct PoseFilter {
    x: [f64; 6],
    p: [f64; 6],
    q: [f64; 6],
    init: bool,
    gate_sigma: f64,
    rejects: u32,
}

impl PoseFilter {
    const MIN_VAR: f64 = 1e-10;
    const REJECTS_BEFORE_RESET: u32 = 3;

    fn new(q_trans: f64, q_rot: f64, gate_sigma: f64) -> Self {
        Self {
            x: [0.0; 6],
            p: [0.0; 6],
            q: [q_trans, q_trans, q_trans, q_rot, q_rot, q_rot],
            init: false,
            gate_sigma,
            rejects: 0,
        }
    }

    fn reset(&mut self) {
        self.init = false;
        self.rejects = 0;
    }

    fn predict(&mut self, dt: f64) {
        if self.init {
            for i in 0..6 {
                self.p[i] += self.q[i] * dt;
            }
        }
    }

    fn init_from(&mut self, z: &[f64; 6], var: &[f64; 6]) {
        self.x = *z;
        for (p, v) in self.p.iter_mut().zip(var) {
            *p = v.max(Self::MIN_VAR);
        }
        self.init = true;
        self.rejects = 0;
    }

    fn innovation(&self, z: &[f64; 6], i: usize) -> f64 {
        if i >= 3 {
            wrap_pi(z[i] - self.x[i])
        } else {
            z[i] - self.x[i]
        }
    }

    // Six parallel per-axis arrays: an index reads clearer than a four-way zip.
    #[allow(clippy::needless_range_loop)]
    fn update(&mut self, z: &[f64; 6], var: &[f64; 6]) -> Gate {
        if !self.init {
            self.init_from(z, var);
            return Gate::Accepted;
        }
        // Innovation gate per axis: a pose flip (IPPE's second solution) or a misdetection
        // jumps far outside what the prediction allows; a few in a row mean the vehicle
        // really is elsewhere, so start over from the measurement.
        if self.gate_sigma > 0.0 {
            let outside = (0..6).any(|i| {
                let s = self.p[i] + var[i].max(Self::MIN_VAR);
                let v = self.innovation(z, i);
                v * v > self.gate_sigma * self.gate_sigma * s
            });
            if outside {
                self.rejects += 1;
                if self.rejects >= Self::REJECTS_BEFORE_RESET {
                    self.init_from(z, var);
                    return Gate::Reinitialized;
                }
                return Gate::Rejected;
            }
        }
        self.rejects = 0;
        for i in 0..6 {
            let r = var[i].max(Self::MIN_VAR);
            let k = self.p[i] / (self.p[i] + r);
            let innov = self.innovation(z, i);
            self.x[i] += k * innov;
            if i >= 3 {
                self.x[i] = wrap_pi(self.x[i]);
            }
            self.p[i] *= 1.0 - k;
        }
        Gate::Accepted
    }
}

/// What the filter did with a measurement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Gate {
    Accepted,
    Rejected,
    Reinitialized,
}

/// One PID axis: P and I (with its clamp) from the pid crate stepped at a fixed rate, the
/// derivative on the filtered measurement rate, clamping anti-windup and the output limit.
#[derive(Clone, Debug)]
struct Axis {
    pid: pid::Pid<f64>,
    cfg: AxisConfig,
    ki_step: f64,
    wrap: bool,
    prev_err: Option<f64>,
    rate: f64,
    last_out: f64,
    last_i: f64,
    /// Output dead band with hysteresis: the axis starts commanding at `band` and stops
    /// below `band / 2` (effort; 0 = off).
    band: f64,
    /// The axis commands (outside the band, or inside it but not yet below the release).
    active: bool,
    /// The integral term runs (off where the autopilot integrates the command itself).
    integrate: bool,
    /// The derivative term runs (off where the autopilot damps the axis itself).
    derivative: bool,
}

impl Axis {
    fn new(cfg: &AxisConfig, dt_step: f64, wrap: bool, band: f64) -> Self {
        let ki_step = cfg.ki * dt_step;
        let mut pid = pid::Pid::new(0.0, f64::MAX);
        pid.p(cfg.kp, cfg.p_limit).i(ki_step, cfg.i_limit);
        Self {
            pid,
            cfg: *cfg,
            ki_step,
            wrap,
            prev_err: None,
            rate: 0.0,
            last_out: 0.0,
            last_i: 0.0,
            band,
            active: false,
            integrate: true,
            derivative: true,
        }
    }

    fn reset(&mut self) {
        self.pid.reset_integral_term();
        self.prev_err = None;
        self.rate = 0.0;
        self.last_out = 0.0;
        self.last_i = 0.0;
        self.active = false;
    }

    /// New error sample at frame rate: updates the filtered error rate. The goal is fixed,
    /// so the error rate is minus the measurement rate: no derivative kick.
    fn observe(&mut self, err: f64, dt: f64, alpha: f64) {
        if let Some(prev) = self.prev_err {
            if dt > 0.0 {
                let de = if self.wrap {
                    wrap_pi(err - prev)
                } else {
                    err - prev
                };
                self.rate += alpha * (de / dt - self.rate);
            }
        }
        self.prev_err = Some(err);
    }

    /// One fixed-rate step.
    fn step(&mut self, err: f64) -> f64 {
        let lim = self.cfg.output_limit;
        // Clamping anti-windup: do not integrate further into a saturated output.
        let saturated = self.last_out.abs() >= lim && lim > 0.0;
        let pushing = saturated && err.signum() == self.last_out.signum();
        self.pid.ki = if pushing || !self.integrate {
            0.0
        } else {
            self.ki_step
        };
        // The crate computes setpoint - measurement: feed -err against a zero setpoint so
        // that angle wrapping is ours.
        let o = self.pid.next_control_output(-err);
        let d = if self.derivative {
            (self.cfg.kd * self.rate).clamp(-self.cfg.d_limit, self.cfg.d_limit)
        } else {
            0.0
        };
        self.last_i = o.i;
        let out = (o.p + o.i + d).clamp(-lim, lim);
        self.last_out = if out.is_finite() { out } else { 0.0 };
        self.banded(self.last_out)
    }

    /// The output through the dead band: zero until it leaves the band, then passed on
    /// until it falls below half the band. Noise on a command near zero then no longer
    /// flips its sign each step (each flip is a jump across the dead zones the link
    /// compensates), and a standing disturbance, which the integral carries out of the
    /// band, is still opposed. The PID itself (and its anti-windup) sees the unbanded
    /// output.
    fn banded(&mut self, out: f64) -> f64 {
        if self.band <= 0.0 {
            return out;
        }
        let mag = out.abs();
        self.active = if self.active {
            mag >= 0.5 * self.band
        } else {
            mag >= self.band
        };
        if self.active {
            out
        } else {
            0.0
        }
    }
}

/// ALT_HOLD's depth target is used within this heave error (m); farther off, the
/// approach is flown with the throttle stick as in the other modes.
const DEPTH_TARGET_WITHIN_M: f64 = 0.05;

/// Holds the vehicle at its station in front of the marker.
#[derive(Clone, Debug)]
pub struct StationKeeper {
    axes: [Axis; 6],
    filter: PoseFilter,
    t_vehicle_cam: Isometry3<f64>,
    t_marker_goal: Isometry3<f64>,
    dt_step: f64,
    deriv_tau_s: f64,
    hold_s: f64,
    max_gap_s: f64,
    max_steps: u32,
    last_stamp: Option<f64>,
    last_seen: Option<f64>,
    acc: f64,
    out: Effort,
    raw_error: Option<[f64; 6]>,
    status: KeeperStatus,
    att_now: Option<UnitQuaternion<f64>>,
    att_prev: Option<UnitQuaternion<f64>>,
    rejected: u64,
    /// The PIDs' output before the view guard.
    pid_out: Effort,
    view: Option<view::ViewGuard>,
    last_view: Option<view::LastSeen>,
    nav: view::Nav,
    search_max_s: f64,
    /// What the autopilot holds in its current mode (`set_autopilot_mode`).
    holds: AutopilotHolds,
    /// This frame's depth target for ALT_HOLD (`depth_target_m`).
    depth_target: Option<f64>,
    /// `ControllerConfig::climb_stick_scale` / `yaw_rate_stick_scale`.
    climb_stick_scale: f64,
    yaw_rate_stick_scale: f64,
}

impl StationKeeper {
    /// Builds the keeper; validates both configs and the camera mount.
    pub fn new(
        station: &StationConfig,
        ctl: &ControllerConfig,
        t_vehicle_cam: Isometry3<f64>,
    ) -> Result<Self, AutopilotError> {
        station.validate()?;
        ctl.validate()?;
        let tv = t_vehicle_cam.translation.vector;
        let q = t_vehicle_cam.rotation;
        if !(tv.iter().all(|v| v.is_finite()) && q.coords.iter().all(|v| v.is_finite())) {
            let value = format!("{t_vehicle_cam:?}");
            let e = markhold_config::ConfigError::new(
                "camera.mount",
                value,
                "t_vehicle_cam must be finite",
            );
            return Err(e.into());
        }
        let dt_step = 1.0 / ctl.rate_hz;
        let a = ctl.axes_named();
        let band = ctl.output_deadband;
        let axes = [
            Axis::new(a[0].1, dt_step, false, band),
            Axis::new(a[1].1, dt_step, false, band),
            Axis::new(a[2].1, dt_step, false, band),
            Axis::new(a[3].1, dt_step, true, band),
            Axis::new(a[4].1, dt_step, true, band),
            Axis::new(a[5].1, dt_step, true, band),
        ];
        Ok(Self {
            axes,
            filter: PoseFilter::new(
                ctl.filter_q_trans_m2_per_s,
                ctl.filter_q_rot_rad2_per_s,
                ctl.filter_gate_sigma,
            ),
            t_vehicle_cam,
            t_marker_goal: station.t_marker_vehicle(),
            dt_step,
            deriv_tau_s: 1.0 / (2.0 * std::f64::consts::PI * ctl.derivative_filter_hz),
            hold_s: ctl.marker_lost_hold_s,
            max_gap_s: ctl.max_gap_s,
            max_steps: (ctl.max_gap_s * ctl.rate_hz).ceil().max(1.0) as u32,
            last_stamp: None,
            last_seen: None,
            acc: 0.0,
            out: Effort::NEUTRAL,
            raw_error: None,
            status: KeeperStatus::NoFix,
            att_now: None,
            att_prev: None,
            rejected: 0,
            pid_out: Effort::NEUTRAL,
            view: None,
            last_view: None,
            nav: view::Nav::default(),
            search_max_s: ctl.marker_lost_action_after_s,
            holds: AutopilotHolds::default(),
            depth_target: None,
            climb_stick_scale: ctl.climb_stick_scale,
            yaw_rate_stick_scale: ctl.yaw_rate_stick_scale,
        })
    }

    /// Desired vehicle pose in the marker frame.
    pub fn t_marker_vehicle_goal(&self) -> Isometry3<f64> {
        self.t_marker_goal
    }

    /// Vehicle pose in the marker frame from a camera measurement, through the mount.
    pub fn t_marker_vehicle(&self, t_cam_marker: &Isometry3<f64>) -> Isometry3<f64> {
        (self.t_vehicle_cam * t_cam_marker).inverse()
    }

    fn usable(m: &PoseMeasurement) -> bool {
        let t = &m.t_cam_marker;
        t.translation.vector.iter().all(|v| v.is_finite())
            && t.rotation.coords.iter().all(|v| v.is_finite())
            && m.cov_cam.iter().all(|v| v.is_finite())
    }

    /// One control step at frame time `stamp_s` (monotonic loop time), with this frame's
    /// measurement if the marker was seen. Handles marker loss (hold briefly, then neutral).
    pub fn update(&mut self, stamp_s: f64, meas: Option<&PoseMeasurement>) -> Effort {
        if !stamp_s.is_finite() {
            return self.out;
        }
        let dt = match self.last_stamp {
            Some(last) => stamp_s - last,
            None => 0.0,
        };
        if dt < 0.0 || dt > self.max_gap_s {
            // Time went backwards or a long gap: the state is stale.
            tracing::debug!(dt, "station keeper: clock jump, reset");
            self.reset_state();
        }
        let dt = dt.clamp(0.0, self.max_gap_s);
        self.last_stamp = Some(stamp_s);
        self.depth_target = None;
        self.filter.predict(dt);
        let bridged = self.propagate_attitude();

        let meas = meas.filter(|m| Self::usable(m));
        let mut seen = false;
        if let Some(m) = meas {
            let reacquired = !matches!(self.status, KeeperStatus::Tracking | KeeperStatus::Holding);
            if reacquired {
                // Fresh start: old integrals and rates belong to another situation.
                for a in &mut self.axes {
                    a.reset();
                }
                self.filter.reset();
            }
            let z = body_error(&self.t_marker_vehicle(&m.t_cam_marker), &self.t_marker_goal);
            let var = body_error_variances(
                self.t_vehicle_cam.rotation.to_rotation_matrix().matrix(),
                &m.t_cam_marker,
                &self.t_marker_goal.translation.vector,
                &m.cov_cam,
            );
            self.raw_error = Some(z);
            match self.filter.update(&z, &var) {
                Gate::Accepted => seen = true,
                Gate::Reinitialized => {
                    // The world really moved: restart the rates so the jump is no kick.
                    for a in &mut self.axes {
                        a.prev_err = None;
                        a.rate = 0.0;
                    }
                    seen = true;
                }
                Gate::Rejected => {
                    self.rejected += 1;
                    tracing::debug!(stamp_s, "station keeper: measurement outside the gate");
                }
            }
            if seen {
                if reacquired {
                    // Run one step right away instead of waiting a controller period.
                    self.acc = self.dt_step;
                } else {
                    self.acc += dt;
                }
                self.last_seen = Some(stamp_s);
                self.status = KeeperStatus::Tracking;
                self.run_pids(dt);
                if let Some(g) = &self.view {
                    let seen = g.last_seen(&self.t_vehicle_cam, &m.t_cam_marker, self.nav);
                    g.apply(&mut self.out, &seen.edge);
                    self.last_view = Some(seen);
                }
                self.depth_target = self.autopilot_depth_target();
            }
        }
        if !seen {
            self.missed(stamp_s, dt, bridged);
        }
        self.out
    }

    /// A frame without a usable measurement: the way back when the marker slipped out at
    /// an edge (or the hold is over), else hold (or bridge), then neutral.
    fn missed(&mut self, stamp_s: f64, dt: f64, bridged: bool) {
        let age = self.last_seen.map(|t| stamp_s - t);
        if let (Some(a), Some(g), Some(seen)) = (age, &self.view, &self.last_view) {
            let at_edge = seen.edge.margin < g.guard;
            if self.status != KeeperStatus::Lost && (at_edge || a > self.hold_s) {
                match g.search(seen, a, self.search_max_s, self.nav) {
                    Some(e) => {
                        if self.status != KeeperStatus::Searching {
                            tracing::info!(stamp_s, "station keeper: marker out of view, way back");
                        }
                        self.status = KeeperStatus::Searching;
                        self.out = e;
                        return;
                    }
                    None if a <= self.search_max_s => {
                        // Turned back, or nothing to turn yet: hold still and look again
                        // next frame (a drift can still make a turn worth it), until the
                        // lost action is due.
                        self.status = KeeperStatus::Searching;
                        self.out = Effort::NEUTRAL;
                        return;
                    }
                    None => {}
                }
            }
        }
        match age {
            Some(a) if a <= self.hold_s && self.status != KeeperStatus::Lost => {
                self.status = KeeperStatus::Holding;
                if bridged {
                    // The attitude-propagated error keeps the loop closed.
                    self.acc += dt;
                    self.run_pids(dt);
                }
            }
            Some(_) => {
                if self.status != KeeperStatus::Lost {
                    tracing::info!(stamp_s, "station keeper: marker lost, neutral");
                }
                self.status = KeeperStatus::Lost;
                self.out = Effort::NEUTRAL;
            }
            None => {
                self.status = KeeperStatus::NoFix;
                self.out = Effort::NEUTRAL;
            }
        }
    }

    /// Steps the PIDs on the filtered error for the controller periods due.
    fn run_pids(&mut self, dt: f64) {
        let alpha = if dt > 0.0 {
            dt / (self.deriv_tau_s + dt)
        } else {
            0.0
        };
        let x = self.filter.x;
        for (a, e) in self.axes.iter_mut().zip(x.iter()) {
            a.observe(*e, dt, alpha);
        }
        let mut steps = 0;
        while self.acc + 1e-9 >= self.dt_step && steps < self.max_steps {
            let mut o = [0.0; 6];
            for (i, a) in self.axes.iter_mut().enumerate() {
                o[i] = a.step(x[i]);
            }
            if self.holds.attitude {
                // ArduSub holds the station's level attitude itself.
                o[3] = 0.0;
                o[4] = 0.0;
            }
            if self.depth_to_autopilot() {
                // The depth goes to ArduSub's depth controller as a target instead.
                self.axes[2].reset();
                o[2] = 0.0;
            }
            // Rate sticks: the mode turns the stick into a climb or yaw rate, scaled to
            // the rates the gains are tuned on.
            if self.holds.depth {
                o[2] *= self.climb_stick_scale;
            }
            if self.holds.heading {
                o[5] *= self.yaw_rate_stick_scale;
            }
            self.pid_out = Effort::from_array(o);
            self.acc -= self.dt_step;
            steps += 1;
        }
        self.acc = self.acc.clamp(0.0, self.dt_step);
        self.out = self.pid_out;
    }

    /// The camera's field of view and the marker's size: from now on the keeper keeps the
    /// marker's image out of a guard band along the image edges, and after the marker
    /// slipped out it turns back toward where it was last seen (with `set_heading`).
    pub fn set_view(&mut self, limits: ViewLimits) {
        let a = &self.axes;
        let out_limit = [0, 1, 2, 3, 4, 5].map(|i| a[i].cfg.output_limit);
        self.view = Some(view::ViewGuard::new(
            limits,
            &self.t_vehicle_cam,
            &self.t_marker_goal,
            out_limit,
        ));
    }

    /// The vehicle's heading from telemetry (ATTITUDE yaw, rad), given before `update`
    /// for the same frame: the way back turns on it. Unlike `set_attitude` it does not
    /// feed the pose filter.
    pub fn set_heading(&mut self, yaw_rad: f64) {
        self.nav.heading_rad = yaw_rad.is_finite().then_some(yaw_rad);
    }

    /// The vehicle's local position (north, east, m) from telemetry, when it has a
    /// position source (LOCAL_POSITION_NED), given before `update` for the same frame:
    /// the way back then turns toward where the marker is after the vehicle drifted,
    /// not only toward where it was seen. `None` when there is none.
    pub fn set_position_ne(&mut self, ne: Option<[f64; 2]>) {
        self.nav.position_ne = ne.filter(|p| p.iter().all(|v| v.is_finite()));
    }

    /// The vehicle's depth (local position down, m) from telemetry, given before
    /// `update` for the same frame: the way back returns to the depth the marker was
    /// last seen from. `None` when unknown.
    pub fn set_depth(&mut self, down_m: Option<f64>) {
        self.nav.down_m = down_m.filter(|d| d.is_finite());
    }

    /// The flight mode the vehicle reports (HEARTBEAT), given before `update` for the
    /// same frame: the keeper leaves to ArduSub what that mode holds by itself
    /// ([`AutopilotHolds`]). Unknown (`None`) holds nothing.
    pub fn set_autopilot_mode(&mut self, mode: Option<ArduSubMode>) {
        let holds = AutopilotHolds::of_mode(mode);
        if holds == self.holds {
            return;
        }
        self.holds = holds;
        let [_, _, heave, roll, pitch, yaw] = &mut self.axes;
        heave.reset();
        for (a, held) in [
            (roll, holds.attitude),
            (pitch, holds.attitude),
            (yaw, holds.heading),
        ] {
            // What was integrated under the other mode does not carry over.
            a.reset();
            a.integrate = !held;
        }
        self.fit_yaw_to_rate_stick(holds.heading);
    }

    /// The yaw loop through a heading-holding mode's rate stick: proportional only.
    /// ArduSub turns the stick into a yaw rate (`get_pilot_desired_yaw_rate`, 152 deg/s
    /// at full stick with ACRO_YAW_P 3.375) that its attitude controller follows with its
    /// own lag (input shaping, the attitude loop, the vehicle's inertia) and damps
    /// itself; the keeper's derivative, a rate feedback through that lag and the
    /// camera's frame, closed a second loop around ArduSub's own that limit-cycled at
    /// about 1 Hz, +-8 degrees on SITL (docs/design/sitl.md). So the heading error alone
    /// commands the rate; the integral is off as well (ArduSub integrates the rate).
    fn fit_yaw_to_rate_stick(&mut self, heading_held: bool) {
        self.axes[5].derivative = !heading_held;
    }

    /// What the keeper leaves to the autopilot now.
    pub fn autopilot_holds(&self) -> AutopilotHolds {
        self.holds
    }

    /// This frame's depth target for ALT_HOLD, metres down in the vehicle's local frame
    /// (LOCAL_POSITION_NED's z, as given to `set_depth`), for the link to send as
    /// SET_POSITION_TARGET_GLOBAL_INT; None when the heave goes out as stick (any other
    /// mode, no depth telemetry, the marker not seen this frame, the view guard
    /// steering heave, a heave error beyond 5 cm: the approach is flown on the stick).
    ///
    /// The target is the vehicle's depth estimate now plus the camera's heave error: the
    /// station's depth in the autopilot's own frame. ArduSub's depth controller then
    /// closes the loop on its 400 Hz estimate, and the outer loop through the camera
    /// moves its target each frame, so what its estimate wanders from the true depth
    /// (barometer noise, its filter) is taken out too: the target moves with the
    /// estimate. The throttle stick instead moves ArduSub's target only past a dead zone
    /// (THR_DZ, or this fork's 5 % of throttle), so its smallest command is already a
    /// climb of 10-19 cm/s.
    pub fn depth_target_m(&self) -> Option<f64> {
        self.depth_target
    }

    /// The heave goes to the autopilot's depth controller: ALT_HOLD with the vehicle's
    /// depth in telemetry.
    fn depth_to_autopilot(&self) -> bool {
        self.holds.depth
            && self.nav.down_m.is_some()
            && self.filter.x[2].abs() <= DEPTH_TARGET_WITHIN_M
    }

    fn autopilot_depth_target(&self) -> Option<f64> {
        if !self.depth_to_autopilot() || self.out.heave != 0.0 {
            return None;
        }
        let down = self.nav.down_m?;
        let target = down + self.filter.x[2];
        target.is_finite().then_some(target)
    }

    /// Where the guard band starts: a fraction of the image inside its edges.
    pub fn view_guard_margin(&self) -> Option<f64> {
        self.view.as_ref().map(|v| v.guard)
    }

    /// Vehicle attitude from telemetry (ATTITUDE roll, pitch, yaw in rad, FRD body in the
    /// autopilot's NED frame), given before `update` for the same frame. Optional: with it
    /// the filter turns its error estimate by the vehicle's rotation between frames, and
    /// missed frames within the hold keep the PIDs running on that estimate instead of
    /// holding the last command. Feed it from the loop's clock (sim attitude in HIL) to
    /// stay deterministic.
    pub fn set_attitude(&mut self, roll: f64, pitch: f64, yaw: f64) {
        if roll.is_finite() && pitch.is_finite() && yaw.is_finite() {
            self.att_now = Some(UnitQuaternion::from_euler_angles(roll, pitch, yaw));
        }
    }

    /// Prediction step from the attitude change since the previous update: the goal is
    /// fixed in the world, so in the body frame it turns by the inverse rotation. Returns
    /// true when a fresh attitude was applied.
    fn propagate_attitude(&mut self) -> bool {
        let Some(q_now) = self.att_now.take() else {
            return false;
        };
        let applied = match self.att_prev {
            Some(q_prev) if self.filter.init => {
                let inv = (q_prev.inverse() * q_now).inverse();
                let x = self.filter.x;
                let p = inv * Vector3::new(x[0], x[1], x[2]);
                let r = inv * UnitQuaternion::from_euler_angles(x[3], x[4], x[5]);
                let (rr, rp, ry) = r.euler_angles();
                self.filter.x = [p.x, p.y, p.z, rr, rp, ry];
                true
            }
            _ => false,
        };
        self.att_prev = Some(q_now);
        applied
    }

    /// Last body-frame pose error (surge, sway, heave m; roll, pitch, yaw rad) the PIDs
    /// used (filtered), if any.
    pub fn error(&self) -> Option<[f64; 6]> {
        if self.filter.init {
            Some(self.filter.x)
        } else {
            None
        }
    }

    /// The integral terms of the six axes (effort; surge, sway, heave, roll, pitch, yaw)
    /// after the last PID step: what the keeper has learned of a standing disturbance.
    pub fn integrals(&self) -> [f64; 6] {
        [0, 1, 2, 3, 4, 5].map(|i| self.axes[i].last_i)
    }

    /// Last unfiltered body-frame error from a measurement.
    pub fn raw_error(&self) -> Option<[f64; 6]> {
        self.raw_error
    }

    /// Measurements the filter's innovation gate has rejected so far.
    pub fn rejected_measurements(&self) -> u64 {
        self.rejected
    }

    /// Tracking, holding, lost, or no fix yet.
    pub fn status(&self) -> KeeperStatus {
        self.status
    }

    /// Seconds since the marker was last seen at loop time `now_s`, if ever seen.
    pub fn marker_age_s(&self, now_s: f64) -> Option<f64> {
        self.last_seen.map(|t| now_s - t)
    }

    /// Last output.
    pub fn last_effort(&self) -> Effort {
        self.out
    }

    fn reset_state(&mut self) {
        for a in &mut self.axes {
            a.reset();
        }
        self.filter.reset();
        self.acc = 0.0;
        self.out = Effort::NEUTRAL;
        self.pid_out = Effort::NEUTRAL;
        self.status = KeeperStatus::NoFix;
        self.last_seen = None;
        self.last_view = None;
        self.att_prev = None;
    }

    /// Forgets integrals, rates, the filter and the marker history (mode change, re-arm).
    pub fn reset(&mut self) {
        self.reset_state();
        self.last_stamp = None;
        self.raw_error = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Translation3};

    fn forward_cam() -> Isometry3<f64> {
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
            Vector3::new(0.0, 1.0, 0.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(1.0, 0.0, 0.0),
        ]));
        Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.0),
            UnitQuaternion::from_rotation_matrix(&r),
        )
    }

    /// Marker pose in the camera for a vehicle at `t_marker_vehicle`.
    fn meas_for(stamp: f64, t_mv: &Isometry3<f64>) -> PoseMeasurement {
        let t_cm = (t_mv * forward_cam()).inverse();
        PoseMeasurement {
            stamp_s: stamp,
            t_cam_marker: t_cm,
            cov_cam: Matrix6::identity() * 1e-6,
        }
    }

    fn keeper() -> StationKeeper {
        StationKeeper::new(
            &StationConfig::default(),
            &ControllerConfig::default(),
            forward_cam(),
        )
        .unwrap()
    }

    #[test]
    fn output_dead_band_has_hysteresis() {
        let cfg = AxisConfig {
            kp: 1.0,
            ki: 0.0,
            kd: 0.0,
            p_limit: 1.0,
            i_limit: 0.0,
            d_limit: 0.5,
            output_limit: 1.0,
        };
        let mut a = Axis::new(&cfg, 0.02, false, 0.01);
        // Inside the band from rest: nothing; out of it: passed on; back down to half
        // the band: still passed on; below half: nothing again.
        let outs: Vec<f64> = [0.008, -0.008, 0.012, 0.006, -0.004, -0.009, -0.011]
            .iter()
            .map(|e| a.step(*e))
            .collect();
        assert_eq!(outs, vec![0.0, 0.0, 0.012, 0.006, 0.0, 0.0, -0.011]);
        // Off: everything passes.
        let mut a = Axis::new(&cfg, 0.02, false, 0.0);
        assert_eq!(a.step(0.001), 0.001);
    }

    #[test]
    fn in_alt_hold_roll_and_pitch_are_left_to_ardusub_and_yaw_does_not_integrate() {
        // Rolled, pitched and yawed off the station, held there: in MANUAL every axis
        // answers and yaw's integral grows; in ALT_HOLD (and STABILIZE) roll and pitch
        // stay neutral and yaw is proportional only, as ArduSub turns it into a rate.
        let goal = StationConfig::default().t_marker_vehicle();
        let off = goal
            * Isometry3::rotation(Vector3::new(0.05, -0.04, 0.0))
            * Isometry3::rotation(Vector3::new(0.0, 0.0, 0.1));
        let run = |mode: Option<ArduSubMode>| {
            let mut k = keeper();
            let mut outs = Vec::new();
            for i in 0..60 {
                let t = i as f64 / 30.0;
                k.set_autopilot_mode(mode);
                outs.push(k.update(t, Some(&meas_for(t, &off))));
            }
            (k.autopilot_holds(), outs)
        };
        let (holds, manual) = run(Some(ArduSubMode::Manual));
        assert_eq!(holds, AutopilotHolds::default());
        let (first, last) = (manual[1], manual[59]);
        assert!(
            first.roll.abs() > 0.01 && first.pitch.abs() > 0.01,
            "{first:?}"
        );
        assert!(
            last.yaw.abs() > first.yaw.abs() + 1e-3,
            "{first:?} {last:?}"
        );
        for mode in [ArduSubMode::AltHold, ArduSubMode::Stabilize] {
            let (holds, held) = run(Some(mode));
            assert!(holds.attitude && holds.heading, "{mode:?}");
            assert!(held.iter().all(|e| e.roll == 0.0 && e.pitch == 0.0));
            let (first, last) = (held[1], held[59]);
            assert!(first.yaw.abs() > 0.01, "{first:?}");
            assert!((last.yaw - first.yaw).abs() < 1e-9, "{first:?} {last:?}");
            // The translation axes are the keeper's in every mode.
            assert_eq!(
                (last.surge, last.sway, last.heave),
                (manual[59].surge, manual[59].sway, manual[59].heave)
            );
        }
        // Unknown mode (no heartbeat yet): nothing is left to the autopilot.
        assert_eq!(run(None).0, AutopilotHolds::default());
    }

    #[test]
    fn rate_sticks_are_scaled_in_the_modes_that_read_them_as_rates() {
        // 20 cm above the station (past the depth-target band, so heave is stick) and
        // yawed 0.1 rad, no depth telemetry: the keeper's outputs with the shipped scales
        // against scales of 1, per mode.
        let goal = StationConfig::default().t_marker_vehicle();
        let off = goal
            * Isometry3::translation(0.0, 0.0, -0.2)
            * Isometry3::rotation(Vector3::new(0.0, 0.0, 0.1));
        let run = |mode: ArduSubMode, ctl: &ControllerConfig| {
            let mut k = StationKeeper::new(&StationConfig::default(), ctl, forward_cam()).unwrap();
            let mut last = Effort::NEUTRAL;
            for i in 0..10 {
                let t = i as f64 / 30.0;
                k.set_autopilot_mode(Some(mode));
                last = k.update(t, Some(&meas_for(t, &off)));
            }
            last
        };
        let shipped = ControllerConfig::default();
        let unscaled = ControllerConfig {
            climb_stick_scale: 1.0,
            yaw_rate_stick_scale: 1.0,
            ..ControllerConfig::default()
        };
        for (mode, heave, yaw) in [
            (ArduSubMode::Manual, 1.0, 1.0),
            (ArduSubMode::Stabilize, 1.0, 0.3),
            (ArduSubMode::AltHold, 0.1, 0.3),
        ] {
            let (a, b) = (run(mode, &shipped), run(mode, &unscaled));
            assert!(b.heave.abs() > 0.01 && b.yaw.abs() > 0.01, "{mode:?} {b:?}");
            assert!(
                (a.heave - heave * b.heave).abs() < 1e-12,
                "{mode:?} {a:?} {b:?}"
            );
            assert!((a.yaw - yaw * b.yaw).abs() < 1e-12, "{mode:?} {a:?} {b:?}");
            assert_eq!((a.surge, a.sway), (b.surge, b.sway), "{mode:?}");
        }
    }

    #[test]
    fn in_alt_hold_with_depth_telemetry_the_heave_is_a_depth_target() {
        // 3 cm above the station, held there, the vehicle reporting 3 m down.
        let goal = StationConfig::default().t_marker_vehicle();
        let run_at =
            |above_m: f64, mode: Option<ArduSubMode>, depth: Option<f64>, last_seen: bool| {
                let above = goal * Isometry3::translation(0.0, 0.0, -above_m);
                let mut k = keeper();
                let mut last = (Effort::NEUTRAL, None);
                for i in 0..30 {
                    let t = i as f64 / 30.0;
                    k.set_autopilot_mode(mode);
                    k.set_depth(depth);
                    let m = meas_for(t, &above);
                    let e = k.update(t, (last_seen || i < 29).then_some(&m));
                    last = (e, k.depth_target_m());
                }
                last
            };
        let run = |mode, depth, last_seen| run_at(0.03, mode, depth, last_seen);
        // ALT_HOLD with the depth known: no throttle stick, the target 3 cm deeper than
        // the vehicle's own depth estimate.
        let (e, target) = run(Some(ArduSubMode::AltHold), Some(3.0), true);
        assert_eq!(e.heave, 0.0, "{e:?}");
        let target = target.unwrap();
        assert!((target - 3.03).abs() < 1e-3, "{target}");
        // 10 cm off: the approach on the stick, a climb rate scaled to the gains' plant.
        let climb = ControllerConfig::default().climb_stick_scale;
        let (e, target) = run_at(0.1, Some(ArduSubMode::AltHold), Some(3.0), true);
        assert!(
            e.heave > 0.05 * climb && target.is_none(),
            "{e:?} {target:?}"
        );
        // Without depth telemetry, or in a mode that takes no depth target: the stick.
        for (mode, depth) in [
            (Some(ArduSubMode::AltHold), None),
            (Some(ArduSubMode::Stabilize), Some(3.0)),
            (Some(ArduSubMode::Manual), Some(3.0)),
        ] {
            let (e, target) = run(mode, depth, true);
            let scale = if mode == Some(ArduSubMode::AltHold) {
                climb
            } else {
                1.0
            };
            assert!(e.heave > 0.01 * scale, "{mode:?} {depth:?}: {e:?}");
            assert_eq!(target, None, "{mode:?} {depth:?}");
        }
        // A frame without the marker sends no target (ArduSub holds the last one) and
        // no stick either.
        let (e, target) = run(Some(ArduSubMode::AltHold), Some(3.0), false);
        assert_eq!((e.heave, target), (0.0, None));
    }

    #[test]
    fn wrap_pi_range() {
        use std::f64::consts::PI;
        assert!((wrap_pi(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert!((wrap_pi(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap_pi(PI), PI);
        assert_eq!(wrap_pi(-PI), PI);
        assert!(
            (wrap_pi(179f64.to_radians() - (-179f64).to_radians()) - (-2f64).to_radians()).abs()
                < 1e-12
        );
    }

    #[test]
    fn on_station_gives_zero_error_and_neutral() {
        let mut k = keeper();
        let goal = StationConfig::default().t_marker_vehicle();
        let e = k.update(0.0, Some(&meas_for(0.0, &goal)));
        let err = k.error().unwrap();
        assert!(err.iter().all(|v| v.abs() < 1e-9), "{err:?}");
        assert!(e.to_array().iter().all(|v| v.abs() < 1e-9), "{e:?}");
    }

    #[test]
    fn too_far_drives_forward_too_right_drives_left() {
        let mut k = keeper();
        // 0.3 m too far from the marker (marker +z), 0.2 m to the right (+x_m).
        let goal = StationConfig::default().t_marker_vehicle();
        let t = Isometry3::from_parts(Translation3::new(0.2, 0.0, 1.3), goal.rotation);
        let e = k.update(0.0, Some(&meas_for(0.0, &t)));
        let err = k.error().unwrap();
        assert!((err[0] - 0.3).abs() < 1e-6, "{err:?}");
        assert!((err[1] + 0.2).abs() < 1e-6, "{err:?}");
        assert!(e.surge > 0.1 && e.sway < -0.1, "{e:?}");
        assert!(e.heave.abs() < 1e-9 && e.yaw.abs() < 1e-9);
    }

    #[test]
    fn too_high_drives_down_and_yawed_left_turns_right() {
        let mut k = keeper();
        let st = StationConfig::default();
        // 0.2 m above the station (marker +y) and yawed 10 degrees left.
        let goal = st.t_marker_vehicle();
        let yaw_left = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -10f64.to_radians());
        let t = Isometry3::from_parts(Translation3::new(0.0, 0.2, 1.0), goal.rotation * yaw_left);
        let e = k.update(0.0, Some(&meas_for(0.0, &t)));
        let err = k.error().unwrap();
        assert!((err[5] - 10f64.to_radians()).abs() < 1e-6, "{err:?}");
        assert!(e.heave > 0.05, "{e:?}");
        assert!(e.yaw > 0.05, "{e:?}");
    }

    #[test]
    fn hold_then_neutral_then_reset_on_reacquire() {
        let ctl = ControllerConfig {
            marker_lost_hold_s: 0.2,
            ..Default::default()
        };
        let mut k = StationKeeper::new(&StationConfig::default(), &ctl, forward_cam()).unwrap();
        let goal = StationConfig::default().t_marker_vehicle();
        let off = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.5), goal.rotation);
        let mut t = 0.0;
        let mut last = Effort::NEUTRAL;
        for _ in 0..30 {
            last = k.update(t, Some(&meas_for(t, &off)));
            t += 1.0 / 30.0;
        }
        assert!(last.surge > 0.0);
        // Missed frames: held.
        let h = k.update(t, None);
        assert_eq!(h, last);
        assert_eq!(k.status(), KeeperStatus::Holding);
        t += 0.3;
        let n = k.update(t, None);
        assert!(n.is_neutral());
        assert_eq!(k.status(), KeeperStatus::Lost);
        // Still lost a frame later, still neutral.
        t += 1.0 / 30.0;
        assert!(k.update(t, None).is_neutral());
        // Re-acquired on station: integral was reset, so output is ~zero.
        t += 1.0 / 30.0;
        let e = k.update(t, Some(&meas_for(t, &goal)));
        assert_eq!(k.status(), KeeperStatus::Tracking);
        assert!(e.surge.abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn integral_grows_with_time_not_with_frame_count() {
        // Same 1 s of constant error at 15 Hz and 60 Hz frames: similar integral.
        let goal = StationConfig::default().t_marker_vehicle();
        let off = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.1), goal.rotation);
        let run = |fps: f64| {
            let mut k = keeper();
            let mut e = Effort::NEUTRAL;
            let n = fps as usize * 3;
            for i in 0..=n {
                let t = i as f64 / fps;
                e = k.update(t, Some(&meas_for(t, &off)));
            }
            e.surge
        };
        let a = run(15.0);
        let b = run(60.0);
        let p_only = 0.8 * 0.1;
        assert!(a > p_only + 0.01 && b > p_only + 0.01, "{a} {b}");
        assert!((a - b).abs() < 0.01, "{a} vs {b}");
    }

    #[test]
    fn covariance_weights_measurements() {
        // A noisy measurement moves the estimate less than a precise one.
        let goal = StationConfig::default().t_marker_vehicle();
        let off = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.2), goal.rotation);
        let run = |var: f64| {
            // Gate off: this is about the weighting, not about outliers.
            let ctl = ControllerConfig {
                filter_gate_sigma: 0.0,
                ..Default::default()
            };
            let mut k = StationKeeper::new(&StationConfig::default(), &ctl, forward_cam()).unwrap();
            let mut m = meas_for(0.0, &goal);
            m.cov_cam = Matrix6::identity() * 1e-6;
            k.update(0.0, Some(&m));
            let mut m2 = meas_for(0.05, &off);
            m2.cov_cam = Matrix6::identity() * var;
            k.update(0.05, Some(&m2));
            k.error().unwrap()[0]
        };
        let precise = run(1e-6);
        let noisy = run(1e-1);
        assert!(precise > 0.15, "{precise}");
        assert!(noisy < 0.05, "{noisy}");
    }

    #[test]
    fn deterministic() {
        let goal = StationConfig::default().t_marker_vehicle();
        let run = || {
            let mut k = keeper();
            let mut v = Vec::new();
            for i in 0..100 {
                let t = i as f64 * 0.033;
                let off = Isometry3::from_parts(
                    Translation3::new(0.1 * (t * 3.0).sin(), 0.05, 1.0 + 0.2 * t.cos()),
                    goal.rotation,
                );
                let m = (i % 7 != 3).then(|| meas_for(t, &off));
                v.push(k.update(t, m.as_ref()));
            }
            v
        };
        let a = run();
        let b = run();
        assert_eq!(a, b);
    }

    #[test]
    fn attitude_bridges_missed_frames() {
        let goal = StationConfig::default().t_marker_vehicle();
        let run = |with_attitude: bool| {
            let mut k = keeper();
            let mut t = 0.0;
            for _ in 0..10 {
                if with_attitude {
                    k.set_attitude(0.0, 0.0, 0.0);
                }
                k.update(t, Some(&meas_for(t, &goal)));
                t += 1.0 / 30.0;
            }
            // Marker missed while the vehicle turns 0.2 rad to the right.
            if with_attitude {
                k.set_attitude(0.0, 0.0, 0.2);
            }
            let e = k.update(t, None);
            (e, k.error().unwrap())
        };
        let (held, _) = run(false);
        assert!(held.yaw.abs() < 1e-9, "no attitude: last command held");
        let (bridged, err) = run(true);
        assert!((err[5] + 0.2).abs() < 1e-9, "{err:?}");
        // Turned right of the goal: the bridged loop turns back left.
        assert!(bridged.yaw < -0.05, "{bridged:?}");
        // Turning in place about the station point leaves the position error at zero.
        assert!(err[..3].iter().all(|v| v.abs() < 1e-9), "{err:?}");
    }

    #[test]
    fn attitude_prediction_then_measurement_agree() {
        // With the vehicle really turned, prediction and measurement say the same.
        let goal = StationConfig::default().t_marker_vehicle();
        let turned = Isometry3::from_parts(
            goal.translation,
            goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.1),
        );
        let mut k = keeper();
        k.set_attitude(0.0, 0.0, 0.0);
        k.update(0.0, Some(&meas_for(0.0, &goal)));
        k.set_attitude(0.0, 0.0, 0.1);
        k.update(0.04, Some(&meas_for(0.04, &turned)));
        let err = k.error().unwrap();
        let raw = k.raw_error().unwrap();
        for i in 0..6 {
            assert!((err[i] - raw[i]).abs() < 1e-6, "{err:?} vs {raw:?}");
        }
    }

    #[test]
    fn gate_rejects_a_flipped_pose_then_follows_a_real_jump() {
        let goal = StationConfig::default().t_marker_vehicle();
        let mut k = keeper();
        let mut t = 0.0;
        let mut last = Effort::NEUTRAL;
        for _ in 0..30 {
            last = k.update(t, Some(&meas_for(t, &goal)));
            t += 1.0 / 30.0;
        }
        // One frame with a 30 degree pitch flip (a planar-pose ambiguity): ignored.
        let flip = Isometry3::from_parts(
            goal.translation,
            goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.5),
        );
        let e = k.update(t, Some(&meas_for(t, &flip)));
        assert_eq!(k.rejected_measurements(), 1);
        assert_eq!(e, last, "held through the outlier");
        assert_eq!(k.status(), KeeperStatus::Holding);
        assert!(k.error().unwrap()[4].abs() < 1e-6);
        t += 1.0 / 30.0;
        let e = k.update(t, Some(&meas_for(t, &goal)));
        assert_eq!(k.status(), KeeperStatus::Tracking);
        assert!(e.pitch.abs() < 1e-9);
        // The vehicle really is 0.5 m further: after a few rejections the filter follows.
        let moved = Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.5), goal.rotation);
        for _ in 0..3 {
            t += 1.0 / 30.0;
            k.update(t, Some(&meas_for(t, &moved)));
        }
        assert!(
            (k.error().unwrap()[0] - 0.5).abs() < 1e-6,
            "{:?}",
            k.error()
        );
        assert_eq!(k.rejected_measurements(), 3);
        t += 1.0 / 30.0;
        let e = k.update(t, Some(&meas_for(t, &moved)));
        assert!(e.surge > 0.3, "{e:?}");
    }

    /// 62 x 48 degree view (the pool camera), 0.15 m marker.
    fn pool_view() -> ViewLimits {
        ViewLimits {
            left: -0.6,
            right: 0.6,
            top: -0.45,
            bottom: 0.45,
            marker_half_m: 0.075,
        }
    }

    #[test]
    fn guard_takes_out_the_push_toward_the_edge_and_pushes_back() {
        let goal = StationConfig::default().t_marker_vehicle();
        // Left of the station and turned 40 degrees right: the marker's image is near
        // the left edge.
        let turned = goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7);
        let t = Isometry3::from_parts(Translation3::new(-0.25, 0.0, 1.0), turned);
        let run = |view: bool| {
            let mut k = keeper();
            if view {
                k.set_view(pool_view());
            }
            let e = k.update(0.0, Some(&meas_for(0.0, &t)));
            (e, k.view_guard_margin())
        };
        let (plain, none) = run(false);
        let (guarded, guard) = run(true);
        assert_eq!(none, None);
        assert!((guard.unwrap() - 0.12).abs() < 1e-9, "{guard:?}");
        // The PIDs turn left (here at the limit) and translate forward-right toward the
        // station, which slides the image out at the left edge: the guard keeps the turn
        // and takes that translation out (here it reverses it: point first, then move).
        assert!(
            plain.yaw < 0.0 && guarded.yaw <= plain.yaw,
            "{plain:?} vs {guarded:?}"
        );
        assert!(plain.surge > 0.05 && plain.sway > 0.05, "{plain:?}");
        assert!(guarded.surge < 0.0 && guarded.sway < 0.0, "{guarded:?}");
    }

    #[test]
    fn guard_leaves_a_centred_marker_alone() {
        let goal = StationConfig::default().t_marker_vehicle();
        let t = Isometry3::from_parts(Translation3::new(0.05, 0.02, 1.2), goal.rotation);
        let mut a = keeper();
        let mut b = keeper();
        b.set_view(pool_view());
        for i in 0..20 {
            let ts = i as f64 / 30.0;
            assert_eq!(
                a.update(ts, Some(&meas_for(ts, &t))),
                b.update(ts, Some(&meas_for(ts, &t)))
            );
        }
    }

    #[test]
    fn way_back_turns_toward_where_the_marker_left_then_holds() {
        let goal = StationConfig::default().t_marker_vehicle();
        // Marker near the left edge: the vehicle turned 25 degrees right of facing it.
        let turned = goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.45);
        let t = Isometry3::from_parts(goal.translation, turned);
        let mut k = keeper();
        k.set_view(pool_view());
        k.set_heading(0.45);
        k.update(0.0, Some(&meas_for(0.0, &t)));
        assert_eq!(k.status(), KeeperStatus::Tracking);
        // Gone at the left edge: at once (no hold of the last command) a left turn.
        k.set_heading(0.45);
        let e = k.update(1.0 / 30.0, None);
        assert_eq!(k.status(), KeeperStatus::Searching);
        assert!(e.yaw < -0.1, "{e:?}");
        assert!(e.surge == 0.0 && e.sway == 0.0, "{e:?}");
        // Turned to where it was seen (the camera's axis on the marker): hold still.
        let bearing = {
            let c = (forward_cam() * meas_for(0.0, &t).t_cam_marker)
                .translation
                .vector;
            c.y.atan2(c.x)
        };
        k.set_heading(0.45 + bearing);
        let e = k.update(2.0 / 30.0, None);
        assert!(e.is_neutral(), "{e:?}");
        // Bounded: past the marker-loss action time the keeper is lost and neutral.
        let after = ControllerConfig::default().marker_lost_action_after_s;
        let mut ts = 2.0 / 30.0;
        let mut e = Effort::NEUTRAL;
        while ts < after + 0.1 {
            ts += 1.0 / 30.0;
            k.set_heading(0.0);
            e = k.update(ts, None);
        }
        assert!(e.is_neutral(), "{e:?}");
        assert_eq!(k.status(), KeeperStatus::Lost);
    }

    #[test]
    fn way_back_without_heading_holds_still() {
        let goal = StationConfig::default().t_marker_vehicle();
        let turned = goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.45);
        let t = Isometry3::from_parts(goal.translation, turned);
        let mut k = keeper();
        k.set_view(pool_view());
        k.update(0.0, Some(&meas_for(0.0, &t)));
        let e = k.update(1.0 / 30.0, None);
        assert!(e.is_neutral(), "{e:?}");
    }

    #[test]
    fn way_back_follows_the_drift_with_a_position() {
        // Seen straight ahead, then the vehicle drifts 0.6 m to the right (east, the
        // marker's +x) with its heading held: the marker is now to the left.
        let goal = StationConfig::default().t_marker_vehicle();
        let mut k = keeper();
        k.set_view(pool_view());
        k.set_heading(0.0);
        k.set_position_ne(Some([-1.0, 0.0]));
        k.update(0.0, Some(&meas_for(0.0, &goal)));
        k.set_heading(0.0);
        k.set_position_ne(Some([-1.0, 0.6]));
        let e = k.update(1.0, None);
        assert_eq!(k.status(), KeeperStatus::Searching);
        assert!(e.yaw < -0.1, "{e:?}");
    }

    #[test]
    fn way_back_returns_to_the_depth_and_keeps_looking_past_the_hold() {
        // Hidden in mid-image (no edge), the vehicle floats up without drifting sideways:
        // nothing to turn, so past the hold it keeps searching (not lost) and heaves down
        // to the depth it saw the marker from; a later drift still gets its turn.
        let goal = StationConfig::default().t_marker_vehicle();
        let mut k = keeper();
        k.set_view(pool_view());
        k.set_heading(0.0);
        k.set_position_ne(Some([-1.0, 0.0]));
        k.set_depth(Some(3.0));
        k.update(0.0, Some(&meas_for(0.0, &goal)));
        let hold = ControllerConfig::default().marker_lost_hold_s;
        k.set_depth(Some(2.8));
        let e = k.update(hold + 0.5, None);
        assert_eq!(k.status(), KeeperStatus::Searching);
        assert!(e.heave > 0.05 && e.yaw == 0.0, "{e:?}");
        k.set_depth(Some(2.99));
        let e = k.update(hold + 0.6, None);
        assert!(e.is_neutral(), "{e:?}");
        assert_eq!(k.status(), KeeperStatus::Searching);
        k.set_position_ne(Some([-1.0, 0.6]));
        let e = k.update(hold + 1.0, None);
        assert!(e.yaw < -0.1, "{e:?}");
    }

    mod props {
        use super::*;
        use proptest::prelude::*;

        fn axis_cfg() -> impl Strategy<Value = AxisConfig> {
            (
                0.0..5.0f64,
                0.0..2.0f64,
                0.0..2.0f64,
                0.0..1.0f64,
                0.0..0.5f64,
                0.0..1.0f64,
                0.01..1.0f64,
            )
                .prop_map(|(kp, ki, kd, p_limit, i_limit, d_limit, output_limit)| {
                    AxisConfig {
                        kp,
                        ki,
                        kd,
                        p_limit,
                        i_limit,
                        d_limit,
                        output_limit,
                    }
                })
        }

        proptest! {
            #[test]
            fn pid_output_within_limits(cfg in axis_cfg(), errs in prop::collection::vec(-100.0..100.0f64, 1..200), wrap in any::<bool>()) {
                let mut a = Axis::new(&cfg, 0.02, wrap, 0.0);
                for e in errs {
                    a.observe(e, 0.033, 0.3);
                    let o = a.step(e);
                    prop_assert!(o.abs() <= cfg.output_limit + 1e-12, "{} > {}", o, cfg.output_limit);
                    prop_assert!(a.last_i.abs() <= cfg.i_limit + 1e-12);
                }
            }

            #[test]
            fn integral_bounded_and_unwinds_under_saturation(cfg in axis_cfg(), big in 1.0..50.0f64, n in 10usize..500) {
                // A large constant error saturates the output; the integral must stay within
                // its clamp and stop growing once saturated, so a reversed error brings the
                // output off the limit within a few steps.
                let mut a = Axis::new(&cfg, 0.02, false, 0.0);
                let mut i_at_sat = None;
                for _ in 0..n {
                    let o = a.step(big);
                    prop_assert!(a.last_i.abs() <= cfg.i_limit + 1e-12);
                    if o >= cfg.output_limit && i_at_sat.is_none() {
                        i_at_sat = Some(a.last_i);
                    }
                }
                if let Some(i0) = i_at_sat {
                    // Conditional integration: no growth while saturated, beyond one step.
                    prop_assert!(a.last_i <= i0 + big * cfg.ki * 0.02 + 1e-12);
                }
                let mut o = a.step(-big);
                for _ in 0..3 {
                    o = a.step(-big);
                }
                if cfg.kp * big > cfg.i_limit + 1e-9 && cfg.p_limit > cfg.i_limit + 1e-9 {
                    prop_assert!(o < cfg.output_limit, "still saturated after reversal: {}", o);
                }
            }

            #[test]
            fn yaw_error_is_wrapped(meas_yaw in -20.0..20.0f64, goal_yaw in -3.1..3.1f64) {
                let goal = Isometry3::from_parts(
                    Translation3::new(0.0, 0.0, 1.0),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), goal_yaw),
                );
                let meas = Isometry3::from_parts(
                    Translation3::new(0.0, 0.0, 1.0),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), meas_yaw),
                );
                let e = body_error(&meas, &goal);
                use std::f64::consts::PI;
                prop_assert!(e[5] > -PI - 1e-12 && e[5] <= PI + 1e-12);
                let want = wrap_pi(goal_yaw - meas_yaw);
                // Same angle modulo 2 pi (both ends of the range are the same heading).
                prop_assert!(wrap_pi(e[5] - want).abs() < 1e-9, "{} vs {}", e[5], want);
                // The shortest way round: the P term pushes toward the goal.
                let mut a = Axis::new(&AxisConfig { kp: 1.0, ki: 0.0, kd: 0.0, ..Default::default() }, 0.02, true, 0.0);
                let o = a.step(e[5]);
                if e[5].abs() > 1e-6 {
                    prop_assert_eq!(o.signum(), e[5].signum());
                }
            }

            #[test]
            fn effort_in_range_for_any_pose(x in -5.0..5.0f64, y in -5.0..5.0f64, z in 0.2..5.0f64, yaw in -3.1..3.1f64, var in 1e-8..1.0f64) {
                let mut k = keeper();
                let goal = StationConfig::default().t_marker_vehicle();
                let t = Isometry3::from_parts(
                    Translation3::new(x, y, z),
                    goal.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                );
                let ctl = ControllerConfig::default();
                for i in 0..10 {
                    let ts = i as f64 * 0.04;
                    let mut m = meas_for(ts, &t);
                    m.cov_cam = Matrix6::identity() * var;
                    let e = k.update(ts, Some(&m));
                    for ((_, ax), v) in ctl.axes_named().iter().zip(e.to_array()) {
                        prop_assert!(v.abs() <= ax.output_limit + 1e-12);
                    }
                }
            }
        }
    }
}
