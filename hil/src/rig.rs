//! The HIL rig: the simulated vehicle, its MAVLink endpoint and the underwater camera on
//! one simulation clock, seen by markhold as a [`Camera`] whose frames come from a world
//! that moves with the commands markhold sends.
//!
//! One `grab` = one camera frame: (lock-step) wait for the client's pilot input for this
//! frame, handle all pending MAVLink, step physics at the fixed rate up to the frame's
//! time while the endpoint's autopilot mixes efforts onto the thrusters and streams
//! telemetry on simulation time, then render the frame from the vehicle's pose.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use markhold_exposure::{Camera, CameraError, ExposureLimits, Frame};
use nalgebra::Isometry3;

use crate::camera::{CameraModel, RenderLoops, UnderwaterCamera};
use crate::endpoint::{EndpointConfig, EndpointStats, VehicleEndpoint};
use crate::mixer::MAX_MOTORS;
use crate::scene::{LightingConfig, LightingScale, MarkerSpec, Scene, WaterConfig};
use crate::vehicle::{Vehicle, VehicleConfig, VehicleMotion, VehicleState};
use crate::HilError;
use markhold_config::{open_closed, Checks};

/// How long a lock-step grab waits for the client's input, wall clock.
pub const LOCKSTEP_WAIT: Duration = Duration::from_millis(250);

/// Everything the rig is built from (the site file, resolved by the caller).
#[derive(Debug, Clone)]
pub struct HilSetup {
    pub vehicle: VehicleConfig,
    pub endpoint: EndpointConfig,
    pub water: WaterConfig,
    pub lighting: LightingConfig,
    pub camera: CameraModel,
    /// Camera mount on the vehicle (docs/frames.md).
    pub t_vehicle_cam: Isometry3<f64>,
    pub marker: MarkerSpec,
    pub t_world_marker: Isometry3<f64>,
    /// The map's other markers: each one's print and pose in the origin marker's frame
    /// (the site frame). Empty for a map of one.
    pub map: Vec<(MarkerSpec, Isometry3<f64>)>,
    pub t_world_vehicle_start: Isometry3<f64>,
    pub motion: VehicleMotion,
    pub seed: u64,
    /// Wait for the client's pilot input before each frame (once it has sent any).
    pub lock_step: bool,
}

/// Ground truth at the last grabbed frame (or now, before the first).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Truth {
    pub time_s: f64,
    pub t_world_vehicle: Isometry3<f64>,
    pub t_world_cam: Isometry3<f64>,
    pub t_cam_marker: Isometry3<f64>,
    pub velocity_world_mps: [f64; 3],
    pub armed: bool,
    /// ArduSub custom_mode.
    pub mode: u32,
    /// Servo outputs (0 for motors the frame does not have).
    pub pwm: [u16; 8],
    /// Lock-step waits that ran out without client input.
    pub lockstep_timeouts: u64,
}

/// The simulated world as a camera.
pub struct HilRig {
    vehicle: Vehicle,
    endpoint: VehicleEndpoint,
    camera: UnderwaterCamera,
    scene: Scene,
    t_vehicle_cam: Isometry3<f64>,
    t_world_marker: Isometry3<f64>,
    lock_step: bool,
    lockstep_wait: Duration,
    frames: u64,
    /// Wall time spent advancing the world and rendering (not waiting for input): what
    /// the HIL world costs, reported beside the whole loop's wall time.
    busy: Duration,
    steps: u64,
    physics_hz: f64,
    fps: f64,
    pwm: [u16; MAX_MOTORS],
    inputs_at_last_grab: u64,
    lockstep_timeouts: u64,
}

fn cam_err(seq: u64, e: HilError) -> CameraError {
    CameraError::Read {
        device: "hil".to_string(),
        seq,
        reason: e.to_string(),
    }
}

impl HilRig {
    /// Build the world and bind the MAVLink endpoint (UDP on 127.0.0.1, port from
    /// `setup.endpoint.udp_port`, 0 = any).
    pub fn new(setup: HilSetup) -> Result<Self, HilError> {
        setup.vehicle.validate()?;
        setup.endpoint.validate()?;
        let fps = setup.camera.fps;
        let physics_hz = setup.vehicle.physics_hz;
        Checks::new("camera")
            .range(
                "fps",
                fps,
                open_closed(0.0, physics_hz),
                "0 < fps <= vehicle.physics_hz",
            )
            .done()?;
        // Independent streams for the scene, the sensor noise and the gusts.
        let mut scene = Scene::new(
            &setup.water,
            &setup.lighting,
            setup.marker,
            setup.t_world_marker,
            setup.seed,
        )?;
        for (marker, t_site_marker) in setup.map {
            scene.add_map_marker(marker, t_site_marker)?;
        }
        let camera =
            UnderwaterCamera::new(setup.camera, setup.seed.wrapping_add(0x9E37_79B9_7F4A_7C15))?;
        let mut vehicle = Vehicle::new(
            &setup.vehicle,
            &setup.t_world_vehicle_start,
            setup.seed.wrapping_add(0x6A09_E667_F3BC_C908),
        )?;
        vehicle.set_motion(setup.motion);
        // The autopilot runs on the vehicle's parameters when it has a file of them.
        let mut endpoint_cfg = setup.endpoint.clone();
        if setup.vehicle.params_file.is_some() {
            endpoint_cfg.params = *vehicle.ardusub_params();
        }
        let mut endpoint = VehicleEndpoint::bind(&endpoint_cfg)?;
        endpoint.set_telemetry_latency(setup.vehicle.telemetry_latency_ms / 1000.0, vehicle.dt_s());
        endpoint.set_input_delay(setup.vehicle.delay.total_ms() / 1000.0);
        let idle = vehicle.mixer().mix_pwm(&[0.0; 6], false);
        Ok(Self {
            physics_hz: setup.vehicle.physics_hz,
            vehicle,
            endpoint,
            camera,
            scene,
            t_vehicle_cam: setup.t_vehicle_cam,
            t_world_marker: setup.t_world_marker,
            lock_step: setup.lock_step,
            lockstep_wait: LOCKSTEP_WAIT,
            frames: 0,
            busy: Duration::ZERO,
            steps: 0,
            fps,
            pwm: idle,
            inputs_at_last_grab: 0,
            lockstep_timeouts: 0,
        })
    }

    /// Where markhold sends MAVLink (`udpout:<addr>`).
    pub fn mavlink_udp_addr(&self) -> SocketAddr {
        self.endpoint.udp_addr()
    }

    /// The TCP address when `endpoint.tcp_enabled`.
    pub fn mavlink_tcp_addr(&self) -> Option<SocketAddr> {
        self.endpoint.tcp_addr()
    }

    /// Process pending MAVLink now without advancing time (answer acks, heartbeats due).
    pub fn pump(&mut self) -> Result<usize, HilError> {
        let now = self.vehicle.time_s();
        let n = self.endpoint.poll(now)?;
        let state = self.vehicle.state();
        self.endpoint.tick(&state, &self.pwm)?;
        Ok(n)
    }

    /// Make the vehicle's depth sensor fail (false) or read again (true).
    pub fn set_depth_sensor_healthy(&mut self, healthy: bool) {
        self.endpoint.set_depth_sensor_healthy(healthy);
    }

    /// Ground truth now.
    pub fn truth(&self) -> Truth {
        let s = self.vehicle.state();
        let t_world_cam = s.t_world_vehicle * self.t_vehicle_cam;
        Truth {
            time_s: s.time_s,
            t_world_vehicle: s.t_world_vehicle,
            t_world_cam,
            t_cam_marker: t_world_cam.inverse() * self.t_world_marker,
            velocity_world_mps: s.velocity_world_mps.into(),
            armed: self.endpoint.armed(),
            mode: self.endpoint.mode(),
            pwm: self.pwm,
            lockstep_timeouts: self.lockstep_timeouts,
        }
    }

    /// The vehicle's full state now.
    pub fn vehicle_state(&self) -> VehicleState {
        self.vehicle.state()
    }

    pub fn endpoint_stats(&self) -> EndpointStats {
        self.endpoint.stats()
    }

    /// Check each vision estimate the vehicle receives against the truth, its frame
    /// lying at `t_world_vision` ([`VehicleEndpoint::set_vision_frame`]).
    pub fn set_vision_frame(&mut self, t_world_vision: Isometry3<f64>) {
        self.endpoint.set_vision_frame(t_world_vision);
    }

    /// NEES of the vision estimates received (none until `set_vision_frame`).
    pub fn vision_nees(&self) -> Option<crate::endpoint::VisionNees> {
        self.endpoint.vision_nees()
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn camera_model(&self) -> &CameraModel {
        self.camera.model()
    }

    /// Simulation time, seconds.
    pub fn sim_time_s(&self) -> f64 {
        self.vehicle.time_s()
    }

    /// Frames grabbed so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Scale the lamps and the daylight from the next frame on (lamp switched off, a
    /// change of ambient light). The renderer sees the new light, so noise, clipping and
    /// the response act on it as on a real sensor.
    pub fn set_lighting(&mut self, scale: LightingScale) -> Result<(), HilError> {
        self.scene.set_lighting(scale)
    }

    /// Render with the widest build of the loops this CPU runs up to `want` (all give the
    /// same frames); returns the build chosen. The default is the widest this CPU runs.
    pub fn set_render_loops(&mut self, want: RenderLoops) -> RenderLoops {
        self.camera.set_render_loops(want)
    }

    /// The build of the renderer's loops (for the summary: the world's speed depends on it).
    pub fn render_loops(&self) -> RenderLoops {
        self.camera.render_loops()
    }

    /// How long after a frame's stamp the command computed from it acts, milliseconds
    /// (`[vehicle.delay]`).
    pub fn frame_to_thrust_ms(&self) -> f64 {
        self.vehicle.config().delay.total_ms()
    }

    /// Simulation time of the next frame `grab` will render (its stamp).
    pub fn next_frame_time_s(&self) -> f64 {
        let target = (self.frames as f64 * self.physics_hz / self.fps).round() as u64;
        target.max(self.steps) as f64 * self.vehicle.dt_s()
    }

    /// Change how long lock-step waits for the client (wall clock).
    pub fn set_lockstep_wait(&mut self, wait: Duration) {
        self.lockstep_wait = wait;
    }

    fn lockstep_inputs(&self) -> u64 {
        self.endpoint.stats().lockstep_inputs
    }

    /// Wait (bounded) until the client sent input for this frame, handling MAVLink meanwhile.
    fn wait_for_client(&mut self) -> Result<(), HilError> {
        let now = self.vehicle.time_s();
        self.endpoint.poll(now)?;
        if !self.lock_step || self.lockstep_inputs() == 0 {
            return Ok(());
        }
        let start = Instant::now();
        while self.lockstep_inputs() <= self.inputs_at_last_grab {
            let Some(left) = self.lockstep_wait.checked_sub(start.elapsed()) else {
                self.lockstep_timeouts += 1;
                tracing::debug!(frame = self.frames, "lock-step wait ran out");
                break;
            };
            self.endpoint
                .wait_readable(left.min(Duration::from_millis(5)))?;
            self.endpoint.poll(now)?;
        }
        Ok(())
    }

    /// Advance physics to simulation time `frames / fps` (integer step count: no drift).
    fn advance_to_frame(&mut self) -> Result<(), HilError> {
        let target = (self.frames as f64 * self.physics_hz / self.fps).round() as u64;
        let dt = self.vehicle.dt_s();
        while self.steps < target {
            let state = self.vehicle.state();
            let efforts = self.endpoint.efforts(&state, dt);
            self.pwm = self
                .vehicle
                .mixer()
                .mix_pwm(&efforts, self.endpoint.armed());
            self.vehicle.step(&self.pwm);
            self.steps += 1;
            let after = self.vehicle.state();
            self.endpoint.tick(&after, &self.pwm)?;
        }
        Ok(())
    }

    /// One frame without the Camera trait's error type (the work of `grab`).
    pub fn step_frame(&mut self, frame: &mut Frame) -> Result<(), HilError> {
        self.wait_for_client()?;
        self.inputs_at_last_grab = self.lockstep_inputs();
        let start = Instant::now();
        self.advance_to_frame()?;
        let state = self.vehicle.state();
        let t_world_cam = state.t_world_vehicle * self.t_vehicle_cam;
        self.camera.render(
            &self.scene,
            &t_world_cam,
            &state.t_world_vehicle,
            state.time_s,
            frame,
        );
        self.busy += start.elapsed();
        self.frames += 1;
        Ok(())
    }

    /// Wall seconds spent in `step_frame` on physics, the vehicle's MAVLink and
    /// rendering (the lock-step wait for input excluded).
    pub fn world_wall_seconds(&self) -> f64 {
        self.busy.as_secs_f64()
    }
}

impl Camera for HilRig {
    fn name(&self) -> &str {
        "hil"
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.camera.model().limits
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, CameraError> {
        Ok(self.camera.set_exposure_us(exposure_us))
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let seq = self.frames;
        self.step_frame(frame).map_err(|e| cam_err(seq, e))
    }
}

// The rig and the SITL server can be moved to another thread.
const _: () = {
    const fn assert_send<T: Send>() {}
    assert_send::<HilRig>();
    assert_send::<crate::sitl::SitlServer>();
    assert_send::<crate::endpoint::VehicleEndpoint>();
};
