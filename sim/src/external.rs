//! `markhold hil --vehicle URL`: camera-in-the-loop on an external MAVLink vehicle.
//!
//! The vehicle (ArduSub SITL with its own physics, or any MAVLink simulator) flies
//! itself; markhold renders what its camera would see from the vehicle's
//! LOCAL_POSITION_NED + ATTITUDE telemetry with hil's underwater camera, and controls the
//! vehicle over the same link. The marker is placed so that the vehicle's first reported
//! pose is the site's start pose (the station, displaced by the site's initial offset).

use std::time::{Duration, Instant};

use crate::error::{ensure, SimError, StepContext};
use markhold_autopilot::{VehicleLink, VehicleState};
use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use markhold_hil::camera::UnderwaterCamera;
use markhold_hil::scene::Scene;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use super::hil::{camera_model, lighting_of, loop_start, site_scene, start_offset, HilOptions};
use super::summary::{RunStats, Summary};
use markhold_core::engage::{EngagedLink, ExitPolicy};
use markhold_core::params::LoadedSite;
use markhold_core::pipeline::{CommandLink, Observers, Pipeline};

/// The vehicle's pose from its telemetry (world = its local NED frame).
pub fn pose_from_telemetry(state: &VehicleState) -> Option<Isometry3<f64>> {
    let p = state.local_position?;
    let a = state.attitude?;
    Some(Isometry3::from_parts(
        Translation3::new(p.position[0], p.position[1], p.position[2]),
        UnitQuaternion::from_euler_angles(a.roll, a.pitch, a.yaw),
    ))
}

/// hil's underwater camera, rendering from a pose set before each frame, paced at the
/// camera's frame rate against the external vehicle's real time.
pub struct ExternalCamera {
    scene: Scene,
    camera: UnderwaterCamera,
    t_vehicle_cam: Isometry3<f64>,
    t_world_vehicle: Isometry3<f64>,
    limits: ExposureLimits,
    period: Duration,
    started: Instant,
    /// The frame slot (of `period` since `started`) the next frame may take at the earliest.
    frames: u64,
    /// Slots that passed while the loop was busy: frames a real camera took and the loop
    /// never saw.
    passed_over: u64,
}

/// The slot a frame grabbed `elapsed_s` after the camera started takes, when the next
/// slot not yet used is `next`: `next` itself if its time has not come yet (the caller
/// waits for it), else the newest slot whose time has come. A real camera runs at its
/// own rate: a late loop gets the newest frame, stamped with its own time, never a
/// backlog stamped as if no time had passed.
fn frame_slot(next: u64, elapsed_s: f64, period_s: f64) -> u64 {
    let due = (elapsed_s / period_s).floor();
    if due.is_finite() && due > next as f64 {
        due as u64
    } else {
        next
    }
}

impl ExternalCamera {
    pub fn set_vehicle_pose(&mut self, t_world_vehicle: Isometry3<f64>) {
        self.t_world_vehicle = t_world_vehicle;
    }

    pub fn t_world_marker(&self) -> Isometry3<f64> {
        *self.scene.t_world_marker()
    }
}

impl Camera for ExternalCamera {
    fn name(&self) -> &str {
        "hil-external"
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        Ok(self.camera.set_exposure_us(exposure_us))
    }

    fn frames_passed_over(&self) -> u64 {
        self.passed_over
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        // A real camera delivers frames at its own rate: so does this one.
        let elapsed_s = Instant::now()
            .saturating_duration_since(self.started)
            .as_secs_f64();
        let slot = frame_slot(self.frames, elapsed_s, self.period.as_secs_f64());
        self.passed_over += slot - self.frames;
        self.frames = slot;
        let due = self.started + self.period.mul_f64(self.frames as f64);
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let time_s = self.frames as f64 * self.period.as_secs_f64();
        let t_world_cam = self.t_world_vehicle * self.t_vehicle_cam;
        self.camera.render(
            &self.scene,
            &t_world_cam,
            &self.t_world_vehicle,
            time_s,
            frame,
        );
        self.frames += 1;
        Ok(())
    }
}

/// Wait (bounded) for the vehicle's heartbeat, position and attitude.
fn wait_for_pose(link: &mut VehicleLink, started: Instant) -> Result<Isometry3<f64>, SimError> {
    let deadline = started + Duration::from_secs(15);
    while Instant::now() < deadline {
        link.tick(started.elapsed().as_secs_f64())?;
        if !link.state().discovered {
            // Refused, no such device: nothing to wait for.
            if let Some(e) = link.transport_error() {
                return Err(SimError::Run {
                    reason: format!("the vehicle link: {e}"),
                });
            }
        }
        if let Some(p) = pose_from_telemetry(link.state()) {
            if link.state().discovered {
                return Ok(p);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let s = link.state();
    Err(SimError::Run {
        reason: format!(
            "no pose from the vehicle within 15 s (heartbeat: {}, LOCAL_POSITION_NED: {}, \
             ATTITUDE: {}): is it running, and does it have a position estimate?",
            s.discovered,
            s.local_position.is_some(),
            s.attitude.is_some()
        ),
    })
}

/// The loop of an external-vehicle run: the HIL run's start, the vehicle's link.
pub fn build_loop<L: CommandLink>(
    site: &LoadedSite,
    opts: &HilOptions,
    link: L,
    observers: Observers,
) -> Result<Pipeline<L>, SimError> {
    Ok(Pipeline::new(
        site,
        loop_start(site, opts),
        link,
        observers,
    )?)
}

/// Run the loop against an external vehicle for `opts.seconds` of its real time.
pub fn run_external(
    site: &LoadedSite,
    url: &str,
    opts: &HilOptions,
    observers: Observers,
) -> Result<Summary, SimError> {
    let s = &site.site;
    let started = Instant::now();
    let mut link_cfg = s.link.clone();
    link_cfg.url = url.to_string();
    let mut link =
        VehicleLink::connect(&link_cfg).step(|| format!("connecting to the vehicle at {url}"))?;
    // No pilot input before the engagement (it engages once armed, below).
    link.set_pilot_keepalive(false);
    let t_world_vehicle0 = wait_for_pose(&mut link, started)?;

    let t_marker_station = s.station.t_marker_vehicle();
    let offset = if opts.start_on_station {
        Isometry3::identity()
    } else {
        start_offset(&s.vehicle)
    };
    let t_world_marker = t_world_vehicle0 * offset.inverse() * t_marker_station.inverse();
    let start = loop_start(site, opts);
    let method = start.method;
    let lighting = lighting_of(site, opts);
    let scenario = lighting.scenario;
    let limits = site.limits();
    let initial_us = start.initial_exposure_us;
    let scene = site_scene(site, &lighting, t_world_marker, opts.seed)?;
    let mut camera = UnderwaterCamera::new(camera_model(site, limits), opts.seed)?;
    camera.set_exposure_us(initial_us);
    let fps = s.camera.fps;
    let mut cam = ExternalCamera {
        scene,
        camera,
        t_vehicle_cam: site.t_vehicle_cam(),
        t_world_vehicle: t_world_vehicle0,
        limits,
        period: Duration::from_secs_f64(1.0 / fps),
        started: Instant::now(),
        frames: 0,
        passed_over: 0,
    };

    let mode = s.link.mode.ardusub();
    let now = started.elapsed().as_secs_f64();
    link.request_mode(mode, now)?;
    link.request_arm(true, now)?;
    let deadline = Instant::now() + Duration::from_secs(10);
    while !(link.state().armed && link.state().mode == Some(mode)) {
        ensure(Instant::now() < deadline, || SimError::Run {
            reason: format!("the vehicle at {url} did not arm in {mode:?} within 10 s"),
        })?;
        link.tick(started.elapsed().as_secs_f64())?;
        std::thread::sleep(Duration::from_millis(10));
    }

    // Engaged from the start (markhold armed it in the mode); a pilot beside it takes
    // over and gives back, and the run ends, as on a real vehicle with `markhold run`
    // (core/src/engage.rs): the same engagement, hand-back and exit.
    let link = EngagedLink::new(link, true);
    let mut pipeline = build_loop(site, opts, link, observers)?;
    let mut events = Vec::with_capacity(16);
    let frames = (opts.seconds * fps).round().max(1.0) as u64;
    let mut stats = RunStats::new(frames as usize, t_world_marker, t_marker_station);
    // The camera's clock starts with the loop (arming took wall time that is not the
    // run's), and runs until it reaches the run's length: frames the loop was too slow
    // for are passed over, not made up for afterwards.
    cam.started = Instant::now();
    let mut interrupted = false;
    let mut last_stamp = 0.0;
    let looped = (|| -> Result<(), SimError> {
        while cam.frames < frames && !interrupted {
            if opts.stop.as_ref().is_some_and(|s| s.is_set()) {
                // This frame sends neutral input and is the last.
                pipeline.set_shutdown(true);
                interrupted = true;
            }
            if let Some(p) = pose_from_telemetry(pipeline.link().inner().state()) {
                cam.set_vehicle_pose(p);
            }
            let rec = pipeline.step(&mut cam)?;
            last_stamp = rec.stamp_s;
            events.clear();
            events.extend_from_slice(pipeline.events());
            pipeline.link_mut().on_events(&events, rec.stamp_s)?;
            stats.push_external(&rec, &cam.t_world_vehicle, &cam.t_vehicle_cam);
        }
        Ok(())
    })();
    // Whatever ended the loop: the site's exit (an error hands back), then the
    // observers, then the error if there was one.
    let policy = if looped.is_ok() {
        ExitPolicy::of(&link_cfg)
    } else {
        ExitPolicy::HandBack
    };
    let exit = pipeline.link_mut().exit(policy, last_stamp);
    eprintln!(
        "markhold hil: exit: {:?}, neutral {:?}, hand back {:?}, disarm {:?}, link closed {:?}",
        exit.policy,
        exit.neutral.map(|n| n.shown),
        exit.hand_back,
        exit.disarm,
        exit.close
    );
    let finished = pipeline.finish_observers();
    looped?;
    finished?;
    let engaged = pipeline.link().engager().engagements();
    tracing::info!(engaged, "external vehicle: engagements");
    eprintln!("markhold hil: engaged {engaged} times");
    if cam.frames_passed_over() > 0 {
        tracing::info!(
            passed_over = cam.frames_passed_over(),
            of = cam.frames,
            "external vehicle: camera frames the loop was too slow for"
        );
    }
    let mut summary = stats.summary(
        method,
        scenario,
        opts.seed,
        started.elapsed().as_secs_f64(),
        0,
    );
    summary.interrupted = interrupted;
    // Truth here is the vehicle's telemetry: the plots show where it said it was.
    super::hil::write_plots_of(site, opts, &stats, &summary)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::frame_slot;

    #[test]
    fn a_late_loop_takes_the_newest_slot_and_an_early_one_waits() {
        let p = 1.0 / 30.0;
        // Early or on time: the next slot (the caller sleeps until it is due).
        assert_eq!(frame_slot(0, 0.0, p), 0);
        assert_eq!(frame_slot(5, 0.1, p), 5);
        assert_eq!(frame_slot(3, 3.5 * p, p), 3);
        // 10.5 periods in with slot 4 next: slots 4..=9 passed, 10 is the newest.
        assert_eq!(frame_slot(4, 10.5 * p, p), 10);
        // Nonsense clocks leave the slot alone.
        assert_eq!(frame_slot(7, f64::NAN, p), 7);
        assert_eq!(frame_slot(7, 1.0, 0.0), 7);
    }
}
