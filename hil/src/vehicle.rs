//! The BlueROV2 / BlueROV2 Heavy rigid body (rapier3d), with buoyancy, added mass,
//! damping, T200 thrusters, water current with gusts, and surface waves.
//!
//! Model (Fossen form, body FRD, origin at the centre of gravity):
//! - rigid mass and inertia plus the diagonal added mass. rapier has one scalar mass, so
//!   the body is given the rigid mass and each body-axis force is scaled by
//!   `m / (m + X_u_dot)` (per axis) before it is applied: the resulting acceleration is
//!   exactly that of the diagonal mass matrix. Added inertia is added to rapier's
//!   (diagonal) principal inertia directly.
//! - damping `-(Dl + Dq |nu_r|) nu_r` per axis on the velocity relative to the water;
//! - weight at the CG against buoyancy at the CB: a net vertical force and a righting
//!   moment; buoyancy fades out as the vehicle breaches the surface (world z = 0);
//! - thrusters at their mounts (see [`crate::mixer`]), scaled by the model error;
//! - tether drag at the tether's attachment point, and a constant external force and
//!   moment (see [`crate::disturbance`]).
//!
//! Gravity is applied by hand (rapier's gravity is zero) so that the added-mass scaling
//! applies to it too. World frame is NED (docs/frames.md); rapier works in f32 inside.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rapier3d::dynamics::{MassProperties, RigidBodyBuilder, RigidBodyHandle};
use rapier3d::math::{Pose as RPose, Rotation as RRot, Vector as RVec};
use rapier3d::pipeline::PhysicsWorld;
use serde::{Deserialize, Serialize};

use crate::disturbance::{ModelError, TetherConfig};
use crate::endpoint::ArduSubParams;
use crate::mixer::{Frame6Dof, Mixer, MAX_MOTORS};
use crate::thruster::{Thruster, ThrusterConfig};
use crate::HilError;
use markhold_config::{above, AsDebug, Checks, ConfigError};

/// Standard gravity, m/s^2.
pub const GRAVITY_MPS2: f64 = 9.81;

/// Mass, buoyancy and hydrodynamic coefficients of a frame (SI units; the six-element
/// arrays are per axis: surge, sway, heave, roll, pitch, yaw).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Hydrodynamics {
    pub mass_kg: f64,
    /// Displaced volume, m^3: buoyancy is this x water density x g.
    pub volume_m3: f64,
    /// Buoyancy, N (in [`Hydrodynamics::for_frame`] for sea water; a site's
    /// [`VehicleConfig::hydrodynamics`] uses its own water density).
    pub buoyancy_n: f64,
    /// Centre of buoyancy relative to the centre of gravity, body FRD, metres.
    pub cb_from_cg_m: [f64; 3],
    /// Rigid-body principal inertia about the CG, kg m^2.
    pub inertia_kgm2: [f64; 3],
    /// Added mass (kg) and added inertia (kg m^2), diagonal.
    pub added_mass: [f64; 6],
    /// Linear damping: N s/m for translation, N m s/rad for rotation.
    pub damping_linear: [f64; 6],
    /// Quadratic damping: N s^2/m^2 for translation, N m s^2/rad^2 for rotation.
    pub damping_quadratic: [f64; 6],
}

impl Hydrodynamics {
    /// Published tables: Wu 2018 (BlueROV2) and von Benzon et al. 2022 (Heavy, volume
    /// 0.0134 m^3). Wu gives the buoyancy (114.8 N) rather than the volume; the volume
    /// here is that buoyancy in fresh water of 1000 kg/m^3 (an assumption: the water is
    /// not stated). Buoyancy is given for sea water (1025 kg/m^3).
    pub fn for_frame(frame: Frame6Dof) -> Self {
        let sea = |volume_m3: f64| WaterDensity::SEA_KG_M3 * GRAVITY_MPS2 * volume_m3;
        match frame {
            Frame6Dof::Standard => Self {
                mass_kg: 11.5,
                volume_m3: 114.8 / (1000.0 * GRAVITY_MPS2),
                buoyancy_n: sea(114.8 / (1000.0 * GRAVITY_MPS2)),
                cb_from_cg_m: [0.0, 0.0, -0.02],
                inertia_kgm2: [0.16, 0.16, 0.16],
                added_mass: [5.5, 12.7, 14.57, 0.12, 0.12, 0.12],
                damping_linear: [4.03, 6.22, 5.18, 0.07, 0.07, 0.07],
                damping_quadratic: [18.18, 21.66, 36.99, 1.55, 1.55, 1.55],
            },
            Frame6Dof::Heavy => Self {
                mass_kg: 13.5,
                volume_m3: 0.0134,
                buoyancy_n: sea(0.0134),
                cb_from_cg_m: [0.0, 0.0, -0.01],
                inertia_kgm2: [0.26, 0.23, 0.37],
                added_mass: [6.36, 7.12, 18.68, 0.189, 0.135, 0.222],
                damping_linear: [13.7, 0.0, 33.0, 0.0, 0.8, 0.0],
                damping_quadratic: [141.0, 217.0, 190.0, 1.19, 0.47, 1.50],
            },
        }
    }
}

/// The water the vehicle floats in (`vehicle.water_density`): `"fresh"`, `"brackish"`,
/// `"sea"`, or a density in kg/m^3.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum WaterDensity {
    Named(WaterKind),
    KgM3(f64),
}

/// Named waters of [`WaterDensity`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaterKind {
    /// 997 kg/m^3 (fresh water at 25 C).
    Fresh,
    /// 1010 kg/m^3 (the middle of brackish water's 1005-1015).
    Brackish,
    /// 1025 kg/m^3 (sea water near the surface).
    Sea,
}

impl WaterDensity {
    pub const FRESH_KG_M3: f64 = 997.0;
    pub const BRACKISH_KG_M3: f64 = 1010.0;
    pub const SEA_KG_M3: f64 = 1025.0;

    pub fn kg_m3(self) -> f64 {
        match self {
            Self::Named(WaterKind::Fresh) => Self::FRESH_KG_M3,
            Self::Named(WaterKind::Brackish) => Self::BRACKISH_KG_M3,
            Self::Named(WaterKind::Sea) => Self::SEA_KG_M3,
            Self::KgM3(v) => v,
        }
    }
}

impl Default for WaterDensity {
    fn default() -> Self {
        Self::Named(WaterKind::Sea)
    }
}

/// `[vehicle.battery]`: the pack the thrusters run from. Its voltage sags with the
/// current the thrusters draw (the T200 table's current column): V = open circuit -
/// internal resistance x current.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BatteryConfig {
    /// Open-circuit voltage, volts. 14.8 V: Blue Robotics' 4S lithium-ion packs' nominal
    /// voltage (16.8 V full, 12.0 V empty; bluerobotics.com/learn/battery-info).
    pub open_circuit_v: f64,
    /// Internal resistance of the pack and its wiring, ohms. Blue Robotics publishes none:
    /// 0.05 ohm is an assumption; measure yours from the drop under a known current.
    pub internal_resistance_ohm: f64,
}

impl Default for BatteryConfig {
    fn default() -> Self {
        Self {
            open_circuit_v: 14.8,
            internal_resistance_ohm: 0.05,
        }
    }
}

/// `[vehicle]` section of a site file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VehicleConfig {
    /// "heavy" (8 thrusters) or "standard" (6 thrusters).
    pub frame: Frame6Dof,
    /// Fixed physics rate, Hz.
    pub physics_hz: f64,
    /// Overrides of the published tables (absent = the frame's table).
    pub mass_kg: Option<f64>,
    pub buoyancy_n: Option<f64>,
    pub cb_from_cg_m: Option<[f64; 3]>,
    pub inertia_kgm2: Option<[f64; 3]>,
    pub added_mass: Option<[f64; 6]>,
    pub damping_linear: Option<[f64; 6]>,
    pub damping_quadratic: Option<[f64; 6]>,
    pub thruster: ThrusterConfig,
    /// The pack the thrusters run from.
    pub battery: BatteryConfig,
    /// Water density for buoyancy: "fresh", "brackish", "sea" or kg/m^3.
    pub water_density: WaterDensity,
    /// Constant water current, NED, m/s.
    pub current_mps: [f64; 3],
    /// Added to the current from `current_change_at_s` on, NED, m/s (a current that
    /// turns or strengthens mid-run).
    pub current_change_mps: [f64; 3],
    /// When the current changes, simulation seconds.
    pub current_change_at_s: f64,
    /// Standard deviation of the gusts added to the current, per NED axis, m/s.
    pub gust_std_mps: [f64; 3],
    /// Correlation time of the gusts (Ornstein-Uhlenbeck), seconds.
    pub gust_time_constant_s: f64,
    /// Significant height of surface waves, metres (0 = no waves).
    pub wave_height_m: f64,
    /// Wave period, seconds.
    pub wave_period_s: f64,
    /// Direction the waves travel toward, degrees from north (clockwise).
    pub wave_direction_deg: f64,
    /// Start offset from the station: translation, metres (split over the three axes).
    pub initial_offset_m: f64,
    /// Start offset from the station: yaw, degrees.
    pub initial_offset_deg: f64,
    /// The tether (`[vehicle.tether]`; absent = no tether).
    pub tether: Option<TetherConfig>,
    /// Constant external force on the centre of gravity, world NED, newtons.
    pub external_force_n: [f64; 3],
    /// Constant external moment, world NED axes, newton metres.
    pub external_moment_nm: [f64; 3],
    /// How the vehicle differs from its model (`[vehicle.model_error]`).
    pub model_error: ModelError,
    /// Age of what the vehicle's telemetry reports (attitude, position, depth) when it is
    /// sent, milliseconds of simulation time.
    pub telemetry_latency_ms: f64,
    /// Frame to thrust, stage by stage (`[vehicle.delay]`): how long after a frame's stamp
    /// the command computed from it acts.
    pub delay: crate::delay::DelayConfig,
    /// The vehicle's ArduSub parameters: a QGroundControl `.params` or MAVProxy `.parm`
    /// file (unknown names ignored); absent = ArduSub 4.5's defaults. The simulated
    /// autopilot's pilot scaling, failsafes and MOT_FV_CPLNG_K mixing follow it.
    pub params_file: Option<std::path::PathBuf>,
}

impl Default for VehicleConfig {
    fn default() -> Self {
        Self {
            frame: Frame6Dof::Heavy,
            physics_hz: 400.0,
            mass_kg: None,
            buoyancy_n: None,
            cb_from_cg_m: None,
            inertia_kgm2: None,
            added_mass: None,
            damping_linear: None,
            damping_quadratic: None,
            thruster: ThrusterConfig::default(),
            battery: BatteryConfig::default(),
            water_density: WaterDensity::default(),
            current_mps: [0.0; 3],
            current_change_mps: [0.0; 3],
            current_change_at_s: 0.0,
            gust_std_mps: [0.0; 3],
            gust_time_constant_s: 5.0,
            wave_height_m: 0.0,
            wave_period_s: 6.0,
            wave_direction_deg: 0.0,
            initial_offset_m: 0.3,
            initial_offset_deg: 10.0,
            tether: None,
            external_force_n: [0.0; 3],
            external_moment_nm: [0.0; 3],
            model_error: ModelError::default(),
            telemetry_latency_ms: 0.0,
            delay: crate::delay::DelayConfig::default(),
            params_file: None,
        }
    }
}

/// Each element finite, then each >= 0, the first bad element reported.
fn non_negative(c: Checks, name: &str, v: &[f64]) -> Checks {
    c.each_finite(name, v, "finite numbers")
        .each(name, v, 0.0.., "non-negative numbers")
}

impl VehicleConfig {
    #[rustfmt::skip]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let no_zero_inertia = |v: &[f64; 3]| !v.contains(&0.0);
        Checks::new("vehicle")
            .finite_range("physics_hz", self.physics_hz, 10.0..=10_000.0, "10..=10000 Hz")
            .opt(self.mass_kg, |c, m| {
                c.positive("mass_kg", m, "a positive mass in kg")
            })
            .opt(self.buoyancy_n, |c, b| non_negative(c, "buoyancy_n", &[b]))
            .opt(self.cb_from_cg_m.as_ref(), |c, v| {
                c.each_finite("cb_from_cg_m", v, "finite numbers")
            })
            .opt(self.inertia_kgm2.as_ref(), |c, v| {
                non_negative(c, "inertia_kgm2", v).check(
                    "inertia_kgm2",
                    AsDebug(v),
                    no_zero_inertia(v),
                    "positive",
                )
            })
            .opt(self.added_mass.as_ref(), |c, v| {
                non_negative(c, "added_mass", v)
            })
            .opt(self.damping_linear.as_ref(), |c, v| {
                non_negative(c, "damping_linear", v)
            })
            .opt(self.damping_quadratic.as_ref(), |c, v| {
                non_negative(c, "damping_quadratic", v)
            })
            .then(|| self.thruster.validate())
            .finite_range("water_density", self.water_density.kg_m3(), 900.0..=1100.0,
                "\"fresh\", \"brackish\", \"sea\" or 900..=1100 kg/m^3")
            .finite_range("battery.open_circuit_v", self.battery.open_circuit_v, 6.0..=30.0, "6..=30 V")
            .finite_range("battery.internal_resistance_ohm", self.battery.internal_resistance_ohm,
                0.0..=1.0, "0..=1 ohm")
            .each_finite("current_mps", &self.current_mps, "finite numbers")
            .each_finite("current_change_mps", &self.current_change_mps, "finite numbers")
            .with(|c| non_negative(c, "current_change_at_s", &[self.current_change_at_s]))
            .with(|c| non_negative(c, "gust_std_mps", &self.gust_std_mps))
            .positive("gust_time_constant_s", self.gust_time_constant_s, "a positive number of seconds")
            .with(|c| non_negative(c, "wave_height_m", &[self.wave_height_m]))
            .finite_range("wave_period_s", self.wave_period_s, above(0.5), "> 0.5 s")
            .finite("wave_direction_deg", self.wave_direction_deg, "finite numbers")
            .with(|c| non_negative(c, "initial_offset_m", &[self.initial_offset_m]))
            .finite("initial_offset_deg", self.initial_offset_deg, "finite numbers")
            .opt(self.tether.as_ref(), |c, t| c.then(|| t.validate()))
            .each_finite("external_force_n", &self.external_force_n, "finite numbers")
            .each("external_force_n", &self.external_force_n, -1000.0..=1000.0, "-1000..=1000 N")
            .each_finite("external_moment_nm", &self.external_moment_nm, "finite numbers")
            .each("external_moment_nm", &self.external_moment_nm, -500.0..=500.0, "-500..=500 N m")
            .then(|| self.model_error.validate())
            .finite_range("telemetry_latency_ms", self.telemetry_latency_ms, 0.0..=1000.0, "0..=1000 ms")
            .then(|| self.delay.validate())
            .done()
    }

    /// The ArduSub parameters: `params_file` read, or ArduSub 4.5's defaults.
    pub fn ardusub_params(&self) -> Result<ArduSubParams, ConfigError> {
        match &self.params_file {
            Some(path) => ArduSubParams::read(path),
            None => Ok(ArduSubParams::default()),
        }
    }

    /// The frame's published table in this site's water, with this config's overrides
    /// applied (`buoyancy_n` wins over volume x density x g) and then the model error's
    /// buoyancy offset.
    pub fn hydrodynamics(&self) -> Hydrodynamics {
        let mut h = Hydrodynamics::for_frame(self.frame);
        h.buoyancy_n = h.volume_m3 * self.water_density.kg_m3() * GRAVITY_MPS2;
        if let Some(v) = self.mass_kg {
            h.mass_kg = v;
        }
        if let Some(v) = self.buoyancy_n {
            h.buoyancy_n = v;
        }
        if let Some(v) = self.cb_from_cg_m {
            h.cb_from_cg_m = v;
        }
        if let Some(v) = self.inertia_kgm2 {
            h.inertia_kgm2 = v;
        }
        if let Some(v) = self.added_mass {
            h.added_mass = v;
        }
        if let Some(v) = self.damping_linear {
            h.damping_linear = v;
        }
        if let Some(v) = self.damping_quadratic {
            h.damping_quadratic = v;
        }
        h.buoyancy_n = (h.buoyancy_n + self.model_error.buoyancy_offset_n).max(0.0);
        h
    }

    /// Physics step, seconds.
    pub fn dt_s(&self) -> f64 {
        1.0 / self.physics_hz
    }

    /// The start pose: `t_world_station` moved by the configured offset, in the vehicle's
    /// own axes (`initial_offset_m` spread as (1, 1, 1)/sqrt(3) forward/right/down) and
    /// yawed by `initial_offset_deg`.
    pub fn start_pose(&self, t_world_station: &Isometry3<f64>) -> Isometry3<f64> {
        let d = self.initial_offset_m / 3f64.sqrt();
        let offset = Isometry3::from_parts(
            Translation3::new(d, d, d),
            UnitQuaternion::from_euler_angles(0.0, 0.0, self.initial_offset_deg.to_radians()),
        );
        t_world_station * offset
    }
}

/// How the vehicle moves (for experiments that separate vision from control).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VehicleMotion {
    /// Full dynamics: thrusters, buoyancy, damping, current.
    #[default]
    Free,
    /// Held still at its start pose (thrusters are ignored).
    Fixed,
    /// Moved at a constant world velocity (NED, m/s) with fixed attitude.
    Kinematic { velocity_world_mps: [f64; 3] },
}

/// What the vehicle's sensors would measure, and the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleState {
    pub time_s: f64,
    pub t_world_vehicle: Isometry3<f64>,
    /// Velocity of the CG, world NED, m/s.
    pub velocity_world_mps: Vector3<f64>,
    /// Angular velocity, body FRD, rad/s (what a gyro measures).
    pub angvel_body_rps: Vector3<f64>,
    /// Specific force (acceleration minus gravity), body FRD, m/s^2 (what an
    /// accelerometer measures: about (0, 0, -9.81) at rest).
    pub specific_force_body_mps2: Vector3<f64>,
    /// Water velocity at the vehicle (current + gusts + waves), world NED, m/s.
    pub water_velocity_world_mps: Vector3<f64>,
}

/// The simulated vehicle.
pub struct Vehicle {
    cfg: VehicleConfig,
    hydro: Hydrodynamics,
    mixer: Mixer,
    /// The ArduSub parameters (`VehicleConfig::params_file`).
    ardusub: ArduSubParams,
    thrusters: [Thruster; MAX_MOTORS],
    world: PhysicsWorld,
    body: RigidBodyHandle,
    rng: ChaCha8Rng,
    gust: Vector3<f64>,
    motion: VehicleMotion,
    step_count: u64,
    dt: f64,
    accel_world: Vector3<f64>,
    water_world: Vector3<f64>,
    /// Per body axis: rigid mass / (rigid + added) mass.
    axis_scale: Vector3<f64>,
    /// Battery voltage the thrusters see now, volts (sagged by `current_a`).
    battery_v: f64,
    /// Current all thrusters drew on the last step, amperes.
    current_a: f64,
}

fn to_rvec(v: &Vector3<f64>) -> RVec {
    RVec::new(v.x as f32, v.y as f32, v.z as f32)
}

fn from_rvec(v: RVec) -> Vector3<f64> {
    Vector3::new(v.x as f64, v.y as f64, v.z as f64)
}

fn to_rpose(p: &Isometry3<f64>) -> RPose {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    RPose::from_parts(
        to_rvec(&t),
        RRot::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32).normalize(),
    )
}

fn from_rpose(p: &RPose) -> Isometry3<f64> {
    let r = p.rotation;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(
        r.w as f64, r.x as f64, r.y as f64, r.z as f64,
    ));
    Isometry3::from_parts(Translation3::from(from_rvec(p.translation)), q)
}

/// One standard normal sample (Box-Muller; rand_distr is not a dependency).
pub(crate) fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    use rand::Rng;
    let u1: f64 = rng.random::<f64>().max(f64::MIN_POSITIVE);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

impl Vehicle {
    /// A vehicle at `t_world_vehicle`, at rest. `seed` drives the gusts.
    pub fn new(
        cfg: &VehicleConfig,
        t_world_vehicle: &Isometry3<f64>,
        seed: u64,
    ) -> Result<Self, HilError> {
        cfg.validate()?;
        let ardusub = cfg.ardusub_params()?;
        let hydro = cfg.hydrodynamics();
        let dt = cfg.dt_s();
        let mut world = PhysicsWorld::new();
        world.gravity = RVec::ZERO;
        world.integration_parameters.dt = dt as f32;
        let inertia = Vector3::new(
            hydro.inertia_kgm2[0] + hydro.added_mass[3],
            hydro.inertia_kgm2[1] + hydro.added_mass[4],
            hydro.inertia_kgm2[2] + hydro.added_mass[5],
        );
        let props = MassProperties::new(RVec::ZERO, hydro.mass_kg as f32, to_rvec(&inertia));
        let rb = RigidBodyBuilder::dynamic()
            .pose(to_rpose(t_world_vehicle))
            .additional_mass_properties(props)
            .can_sleep(false)
            .build();
        let body = world.bodies.insert(rb);
        let axis_scale = Vector3::new(
            hydro.mass_kg / (hydro.mass_kg + hydro.added_mass[0]),
            hydro.mass_kg / (hydro.mass_kg + hydro.added_mass[1]),
            hydro.mass_kg / (hydro.mass_kg + hydro.added_mass[2]),
        );
        // Parse the thruster table now, not on the first physics step.
        crate::thruster::t200();
        let mut v = Self {
            cfg: cfg.clone(),
            hydro,
            mixer: Mixer::new(cfg.frame).with_fv_coupling(ardusub.mot_fv_cplng_k),
            ardusub,
            thrusters: [Thruster::default(); MAX_MOTORS],
            world,
            body,
            rng: ChaCha8Rng::seed_from_u64(seed),
            gust: Vector3::zeros(),
            motion: VehicleMotion::Free,
            step_count: 0,
            dt,
            accel_world: Vector3::zeros(),
            water_world: Vector3::zeros(),
            axis_scale,
            battery_v: cfg.battery.open_circuit_v,
            current_a: 0.0,
        };
        // Start the gusts from their stationary distribution, not from calm.
        for i in 0..3 {
            v.gust[i] = cfg.gust_std_mps[i] * gaussian(&mut v.rng);
        }
        v.water_world = v.water_velocity(t_world_vehicle.translation.vector, 0.0);
        Ok(v)
    }

    pub fn config(&self) -> &VehicleConfig {
        &self.cfg
    }

    pub fn hydro(&self) -> &Hydrodynamics {
        &self.hydro
    }

    pub fn mixer(&self) -> &Mixer {
        &self.mixer
    }

    /// The vehicle's ArduSub parameters (`VehicleConfig::params_file`).
    pub fn ardusub_params(&self) -> &ArduSubParams {
        &self.ardusub
    }

    pub fn frame(&self) -> Frame6Dof {
        self.cfg.frame
    }

    /// Fixed physics step, seconds.
    pub fn dt_s(&self) -> f64 {
        self.dt
    }

    /// Simulation time, seconds (step count x dt, so it never drifts).
    pub fn time_s(&self) -> f64 {
        self.step_count as f64 * self.dt
    }

    pub fn motion(&self) -> VehicleMotion {
        self.motion
    }

    pub fn set_motion(&mut self, motion: VehicleMotion) {
        self.motion = motion;
        if motion != VehicleMotion::Free {
            if let Some(rb) = self.world.bodies.get_mut(self.body) {
                rb.set_angvel(RVec::ZERO, false);
                let v = match motion {
                    VehicleMotion::Kinematic { velocity_world_mps } => {
                        to_rvec(&Vector3::from(velocity_world_mps))
                    }
                    _ => RVec::ZERO,
                };
                rb.set_linvel(v, false);
            }
        }
    }

    /// Thrust each motor delivers now, newtons.
    pub fn thrusts_n(&self) -> [f64; MAX_MOTORS] {
        let k = self.cfg.model_error.thrust_scale;
        self.thrusters.map(|t| t.thrust_n() * k)
    }

    /// Battery voltage at the thrusters now, volts.
    pub fn battery_v(&self) -> f64 {
        self.battery_v
    }

    /// Current the thrusters drew on the last step, amperes.
    pub fn current_a(&self) -> f64 {
        self.current_a
    }

    /// Put the vehicle at `pose`, at rest, with idle thrusters (time continues).
    pub fn teleport(&mut self, pose: &Isometry3<f64>) {
        if let Some(rb) = self.world.bodies.get_mut(self.body) {
            rb.set_position(to_rpose(pose), true);
            rb.set_linvel(RVec::ZERO, true);
            rb.set_angvel(RVec::ZERO, true);
        }
        for t in &mut self.thrusters {
            t.reset();
        }
        self.accel_world = Vector3::zeros();
    }

    /// Restart the clock at zero and teleport (SITL reset).
    pub fn reset(&mut self, pose: &Isometry3<f64>) {
        self.step_count = 0;
        self.teleport(pose);
    }

    /// Water velocity (current + gusts + waves) at a world position and time.
    fn water_velocity(&self, p_world: Vector3<f64>, t: f64) -> Vector3<f64> {
        let mut w = Vector3::from(self.cfg.current_mps) + self.gust;
        if t >= self.cfg.current_change_at_s {
            w += Vector3::from(self.cfg.current_change_mps);
        }
        if self.cfg.wave_height_m > 0.0 {
            // Linear deep-water wave: orbital speed pi H / T, decaying as exp(-k depth).
            let omega = std::f64::consts::TAU / self.cfg.wave_period_s;
            let k = omega * omega / GRAVITY_MPS2;
            let depth = p_world.z.max(0.0);
            let amp = std::f64::consts::PI * self.cfg.wave_height_m / self.cfg.wave_period_s
                * (-k * depth).exp();
            let dir = self.cfg.wave_direction_deg.to_radians();
            let (s, c) = dir.sin_cos();
            let phase = omega * t - k * (c * p_world.x + s * p_world.y);
            let horiz = amp * phase.cos();
            w.x += horiz * c;
            w.y += horiz * s;
            // Crest (phase 0): water moves with the wave; it rises a quarter period before.
            w.z += -amp * phase.sin();
        }
        w
    }

    /// Tether drag and the constant external force and moment, body FRD about the CG.
    fn external_wrench_body(
        cfg: &VehicleConfig,
        water_world: &Vector3<f64>,
        r: &UnitQuaternion<f64>,
        v_world: &Vector3<f64>,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let mut f = r.inverse_transform_vector(&Vector3::from(cfg.external_force_n));
        let mut m = r.inverse_transform_vector(&Vector3::from(cfg.external_moment_nm));
        if let Some(t) = &cfg.tether {
            let ft = r.inverse_transform_vector(&t.force_world_n(
                water_world,
                v_world,
                cfg.water_density.kg_m3(),
            ));
            f += ft;
            m += Vector3::from(t.attachment_m).cross(&ft);
        }
        (f, m)
    }

    /// The tether's pull on the vehicle now, world NED, newtons (zero without a tether).
    pub fn tether_force_world_n(&self) -> Vector3<f64> {
        match (&self.cfg.tether, self.world.bodies.get(self.body)) {
            (Some(t), Some(rb)) => t.force_world_n(
                &self.water_world,
                &from_rvec(rb.linvel()),
                self.cfg.water_density.kg_m3(),
            ),
            _ => Vector3::zeros(),
        }
    }

    /// Advance one physics step with the given servo outputs (1500 = idle).
    pub fn step(&mut self, pwm: &[u16; MAX_MOTORS]) {
        let dt = self.dt;
        let t = self.time_s();
        // Gusts: exact Ornstein-Uhlenbeck update with the configured std and time constant.
        let a = (-dt / self.cfg.gust_time_constant_s).exp();
        let b = (1.0 - a * a).sqrt();
        for i in 0..3 {
            if self.cfg.gust_std_mps[i] > 0.0 {
                self.gust[i] =
                    a * self.gust[i] + b * self.cfg.gust_std_mps[i] * gaussian(&mut self.rng);
            }
        }
        // The pack sags with the current drawn on the last step.
        let bat = &self.cfg.battery;
        self.battery_v =
            (bat.open_circuit_v - bat.internal_resistance_ohm * self.current_a).max(0.0);
        let mut thrust = [0.0; MAX_MOTORS];
        let mut current = 0.0;
        for (i, th) in self
            .thrusters
            .iter_mut()
            .enumerate()
            .take(self.mixer.motor_count())
        {
            let p = pwm[i] as f64;
            thrust[i] = th.step(&self.cfg.thruster, p, self.battery_v, dt)
                * self.cfg.model_error.thrust_scale;
            current += self.cfg.thruster.current_a(p, self.battery_v);
        }
        self.current_a = current;
        let Some(pose) = self
            .world
            .bodies
            .get(self.body)
            .map(|rb| from_rpose(rb.position()))
        else {
            return;
        };
        self.water_world = self.water_velocity(pose.translation.vector, t);
        let Some(rb) = self.world.bodies.get_mut(self.body) else {
            return;
        };
        let v_before = from_rvec(rb.linvel());
        match self.motion {
            VehicleMotion::Free => {}
            VehicleMotion::Fixed => {
                self.step_count += 1;
                self.accel_world = Vector3::zeros();
                return;
            }
            VehicleMotion::Kinematic { velocity_world_mps } => {
                let v = Vector3::from(velocity_world_mps);
                let mut p = pose;
                p.translation.vector += v * dt;
                rb.set_position(to_rpose(&p), false);
                rb.set_linvel(to_rvec(&v), false);
                self.step_count += 1;
                self.accel_world = Vector3::zeros();
                return;
            }
        }
        let r = pose.rotation;
        let h = &self.hydro;
        // Velocities relative to the water, body frame.
        let v_rel_b = r.inverse_transform_vector(&(v_before - self.water_world));
        let w_b = r.inverse_transform_vector(&from_rvec(rb.angvel()));
        let nu = [v_rel_b.x, v_rel_b.y, v_rel_b.z, w_b.x, w_b.y, w_b.z];
        let mut damp = [0.0; 6];
        for i in 0..6 {
            damp[i] = -(h.damping_linear[i] + h.damping_quadratic[i] * nu[i].abs()) * nu[i];
        }
        // Buoyancy fades over the last 0.15 m as the vehicle breaches the surface.
        let depth = pose.translation.vector.z;
        let submerged = ((depth + 0.15) / 0.3).clamp(0.0, 1.0);
        let weight_w = Vector3::new(0.0, 0.0, h.mass_kg * GRAVITY_MPS2);
        let buoy_w = Vector3::new(0.0, 0.0, -h.buoyancy_n * submerged);
        let buoy_b = r.inverse_transform_vector(&buoy_w);
        let (f_thr, m_thr) = self.mixer.wrench(&thrust);
        let (f_ext, m_ext) =
            Self::external_wrench_body(&self.cfg, &self.water_world, &r, &v_before);
        let f_b = f_thr
            + Vector3::new(damp[0], damp[1], damp[2])
            + r.inverse_transform_vector(&weight_w)
            + buoy_b
            + f_ext;
        let m_b = m_thr
            + Vector3::new(damp[3], damp[4], damp[5])
            + Vector3::from(h.cb_from_cg_m).cross(&buoy_b)
            + m_ext;
        let f_w = r.transform_vector(&f_b.component_mul(&self.axis_scale));
        let m_w = r.transform_vector(&m_b);
        rb.reset_forces(false);
        rb.reset_torques(false);
        rb.add_force(to_rvec(&f_w), true);
        rb.add_torque(to_rvec(&m_w), true);
        self.world.step();
        self.step_count += 1;
        if let Some(rb) = self.world.bodies.get(self.body) {
            self.accel_world = (from_rvec(rb.linvel()) - v_before) / dt;
        }
    }

    /// The state now.
    pub fn state(&self) -> VehicleState {
        let (pose, v, w) = match self.world.bodies.get(self.body) {
            Some(rb) => (
                from_rpose(rb.position()),
                from_rvec(rb.linvel()),
                from_rvec(rb.angvel()),
            ),
            None => (Isometry3::identity(), Vector3::zeros(), Vector3::zeros()),
        };
        let g = Vector3::new(0.0, 0.0, GRAVITY_MPS2);
        VehicleState {
            time_s: self.time_s(),
            t_world_vehicle: pose,
            velocity_world_mps: v,
            angvel_body_rps: pose.rotation.inverse_transform_vector(&w),
            specific_force_body_mps2: pose
                .rotation
                .inverse_transform_vector(&(self.accel_world - g)),
            water_velocity_world_mps: self.water_world,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(depth: f64) -> Isometry3<f64> {
        Isometry3::translation(0.0, 0.0, depth)
    }

    fn run(v: &mut Vehicle, pwm: &[u16; MAX_MOTORS], seconds: f64) {
        let n = (seconds / v.dt_s()).round() as usize;
        for _ in 0..n {
            v.step(pwm);
        }
    }

    #[test]
    fn at_rest_slightly_buoyant_vehicle_rises_slowly_and_stays_level() {
        for frame in [Frame6Dof::Heavy, Frame6Dof::Standard] {
            let cfg = VehicleConfig {
                frame,
                ..Default::default()
            };
            let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
            let idle = v.mixer().mix_pwm(&[0.0; 6], false);
            run(&mut v, &idle, 10.0);
            let s = v.state();
            let h = v.hydro();
            let net_up = h.buoyancy_n - h.mass_kg * GRAVITY_MPS2;
            assert!(net_up > 0.0);
            // Terminal heave speed from the damping table: Dl v + Dq v^2 = net buoyancy.
            let (dl, dq) = (h.damping_linear[2], h.damping_quadratic[2]);
            let v_term = (-dl + (dl * dl + 4.0 * dq * net_up).sqrt()) / (2.0 * dq);
            let vz = s.velocity_world_mps.z;
            assert!(vz < 0.0, "{frame}: should rise, vz = {vz}");
            assert!(
                (-vz - v_term).abs() < 0.1 * v_term,
                "{frame}: vz {vz} vs {v_term}"
            );
            assert!(s.velocity_world_mps.xy().norm() < 1e-3, "{frame}: {s:?}");
            let (roll, pitch, _) = s.t_world_vehicle.rotation.euler_angles();
            assert!(
                roll.abs() < 1e-3 && pitch.abs() < 1e-3,
                "{frame}: {roll} {pitch}"
            );
            // An accelerometer at (near) rest reads minus gravity, body FRD.
            let f = s.specific_force_body_mps2;
            assert!(
                (f - Vector3::new(0.0, 0.0, -GRAVITY_MPS2)).norm() < 0.05,
                "{f:?}"
            );
        }
    }

    #[test]
    fn forward_effort_reaches_terminal_speed_of_damping_table() {
        for frame in [Frame6Dof::Heavy, Frame6Dof::Standard] {
            let cfg = VehicleConfig {
                frame,
                // The thrusters sit below the CG, so surge pitches the nose up; a 2 m
                // metacentric height keeps that pitch under a degree and the surge axis
                // alone is tested.
                cb_from_cg_m: Some([0.0, 0.0, -2.0]),
                ..Default::default()
            };
            let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
            let pwm = v.mixer().mix_pwm(&[0.7, 0.0, 0.0, 0.0, 0.0, 0.0], true);
            run(&mut v, &pwm, 15.0);
            let volts = v.battery_v();
            let thrust = pwm.map(|p| cfg.thruster.steady_thrust_n(p as f64, volts));
            let (f, _) = v.mixer().wrench(&thrust);
            let h = v.hydro();
            let (dl, dq) = (h.damping_linear[0], h.damping_quadratic[0]);
            let v_term = (-dl + (dl * dl + 4.0 * dq * f.x).sqrt()) / (2.0 * dq);
            let s = v.state();
            let vx = s.velocity_world_mps.x;
            assert!(
                (vx - v_term).abs() < 0.03 * v_term,
                "{frame}: {vx} vs {v_term}"
            );
            assert!(
                s.velocity_world_mps.y.abs() < 0.05 * v_term,
                "{frame}: {s:?}"
            );
        }
    }

    #[test]
    fn added_mass_slows_the_start() {
        // Same force, heavier effective mass in heave than in surge: slower start.
        let cfg = VehicleConfig {
            damping_linear: Some([0.0; 6]),
            damping_quadratic: Some([0.0; 6]),
            buoyancy_n: Some(13.5 * GRAVITY_MPS2),
            // Surge pitches the nose up (thrusters below the CG): a 2 m metacentric height
            // keeps the pitch under a degree.
            cb_from_cg_m: Some([0.0, 0.0, -2.0]),
            // No sag: the hand integration below runs at the open-circuit voltage.
            battery: BatteryConfig {
                internal_resistance_ohm: 0.0,
                ..Default::default()
            },
            ..Default::default()
        };
        let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
        let pwm = v.mixer().mix_pwm(&[0.5, 0.0, 0.0, 0.0, 0.0, 0.0], true);
        run(&mut v, &pwm, 1.0);
        // Integrate the lagged thrust by hand: v = (1 / (m + Xu)) * integral of F dt.
        let mut th = [Thruster::default(); MAX_MOTORS];
        let mut impulse = 0.0;
        let n = (1.0 / v.dt_s()).round() as usize;
        for _ in 0..n {
            let mut t = [0.0; MAX_MOTORS];
            for i in 0..8 {
                t[i] = th[i].step(&cfg.thruster, pwm[i] as f64, 14.8, v.dt_s());
            }
            impulse += v.mixer().wrench(&t).0.x * v.dt_s();
        }
        let expect = impulse / (13.5 + 6.36);
        let vx = v.state().velocity_world_mps.x;
        assert!((vx - expect).abs() < 0.01 * expect, "{vx} vs {expect}");
    }

    #[test]
    fn righting_moment_levels_a_tilted_vehicle() {
        let cfg = VehicleConfig::default();
        let tilted = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 5.0),
            UnitQuaternion::from_euler_angles(0.3, 0.0, 0.0),
        );
        let mut v = Vehicle::new(&cfg, &tilted, 1).unwrap();
        run(&mut v, &[1500; 8], 20.0);
        let (roll, _, _) = v.state().t_world_vehicle.rotation.euler_angles();
        assert!(roll.abs() < 0.1, "roll {roll}");
    }

    #[test]
    fn current_carries_the_vehicle_and_gusts_are_seeded() {
        let cfg = VehicleConfig {
            current_mps: [0.2, 0.0, 0.0],
            gust_std_mps: [0.05, 0.05, 0.0],
            ..Default::default()
        };
        let mut a = Vehicle::new(&cfg, &at(5.0), 7).unwrap();
        let mut b = Vehicle::new(&cfg, &at(5.0), 7).unwrap();
        let mut c = Vehicle::new(&cfg, &at(5.0), 8).unwrap();
        for _ in 0..4000 {
            a.step(&[1500; 8]);
            b.step(&[1500; 8]);
            c.step(&[1500; 8]);
        }
        let (sa, sb, sc) = (a.state(), b.state(), c.state());
        assert_eq!(sa.t_world_vehicle, sb.t_world_vehicle);
        assert_ne!(sa.t_world_vehicle, sc.t_world_vehicle);
        assert!(sa.velocity_world_mps.x > 0.1, "{sa:?}");
    }

    #[test]
    fn a_current_that_changes_mid_run_carries_the_vehicle_from_then_on() {
        let cfg = VehicleConfig {
            current_change_mps: [0.0, 0.2, 0.0],
            current_change_at_s: 5.0,
            ..Default::default()
        };
        let mut v = Vehicle::new(&cfg, &at(5.0), 7).unwrap();
        let steps = |s: f64| (s * cfg.physics_hz).round() as usize;
        for _ in 0..steps(4.9) {
            v.step(&[1500; 8]);
        }
        assert_eq!(v.state().water_velocity_world_mps.y, 0.0);
        assert!(
            v.state().velocity_world_mps.y.abs() < 1e-6,
            "{:?}",
            v.state()
        );
        for _ in 0..steps(10.0) {
            v.step(&[1500; 8]);
        }
        assert!((v.state().water_velocity_world_mps.y - 0.2).abs() < 1e-9);
        assert!(v.state().velocity_world_mps.y > 0.1, "{:?}", v.state());
    }

    #[test]
    fn tether_and_external_force_push_the_vehicle_downstream() {
        let still = VehicleConfig {
            current_mps: [0.0, 0.2, 0.0],
            ..Default::default()
        };
        let tethered = VehicleConfig {
            tether: Some(TetherConfig::default()),
            ..still.clone()
        };
        let pushed = VehicleConfig {
            external_force_n: [0.0, 2.0, 0.0],
            ..still.clone()
        };
        let speed = |cfg: &VehicleConfig| {
            let mut v = Vehicle::new(cfg, &at(5.0), 1).unwrap();
            run(&mut v, &[1500; 8], 15.0);
            v.state().velocity_world_mps.y
        };
        let (a, b, c) = (speed(&still), speed(&tethered), speed(&pushed));
        // Drifting with the current, the tether drag still pulls downstream (the surface
        // end is fixed), so the tethered vehicle drifts faster, as does the pushed one.
        assert!(b > a + 1e-3 && c > a + 0.05, "{a} {b} {c}");
        let mut v = Vehicle::new(&tethered, &at(5.0), 1).unwrap();
        run(&mut v, &[1500; 8], 1.0);
        assert!(v.tether_force_world_n().y > 0.0);
        assert_eq!(
            Vehicle::new(&still, &at(5.0), 1)
                .unwrap()
                .tether_force_world_n(),
            Vector3::zeros()
        );
    }

    #[test]
    fn model_error_scales_thrust_and_shifts_buoyancy() {
        let weak = VehicleConfig {
            model_error: ModelError {
                thrust_scale: 0.8,
                buoyancy_offset_n: -3.0,
            },
            ..Default::default()
        };
        let mut a = Vehicle::new(&VehicleConfig::default(), &at(5.0), 1).unwrap();
        let mut b = Vehicle::new(&weak, &at(5.0), 1).unwrap();
        let pwm = a.mixer().mix_pwm(&[0.5, 0.0, 0.0, 0.0, 0.0, 0.0], true);
        // Short: raw surge on thrusters below the CG pitches the nose up over seconds.
        run(&mut a, &pwm, 0.5);
        run(&mut b, &pwm, 0.5);
        let (ta, tb) = (a.thrusts_n(), b.thrusts_n());
        for i in 0..8 {
            assert!((tb[i] - 0.8 * ta[i]).abs() < 1e-9, "{ta:?} {tb:?}");
        }
        assert!((b.hydro().buoyancy_n - (a.hydro().buoyancy_n - 3.0)).abs() < 1e-9);
        let forward = |v: &Vehicle| {
            let s = v.state();
            (s.t_world_vehicle.rotation.inverse() * s.velocity_world_mps).x
        };
        let (fa, fb) = (forward(&a), forward(&b));
        assert!(fb < 0.95 * fa && fb > 0.0, "{fa} {fb}");
    }

    #[test]
    fn fixed_and_kinematic_motion() {
        let cfg = VehicleConfig::default();
        let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
        v.set_motion(VehicleMotion::Fixed);
        run(&mut v, &[1900; 8], 1.0);
        assert_eq!(v.state().t_world_vehicle, at(5.0));
        v.set_motion(VehicleMotion::Kinematic {
            velocity_world_mps: [0.0, 0.1, 0.0],
        });
        run(&mut v, &[1900; 8], 2.0);
        let p = v.state().t_world_vehicle.translation.vector;
        assert!((p - Vector3::new(0.0, 0.2, 5.0)).norm() < 1e-4, "{p:?}");
        assert!((v.time_s() - 3.0).abs() < 1e-9);
    }

    #[test]
    fn waves_move_the_water_near_the_surface_only() {
        let cfg = VehicleConfig {
            wave_height_m: 1.0,
            ..Default::default()
        };
        let v = Vehicle::new(&cfg, &at(0.5), 1).unwrap();
        let shallow = (0..60)
            .map(|i| {
                v.water_velocity(Vector3::new(0.0, 0.0, 0.5), i as f64 * 0.1)
                    .norm()
            })
            .fold(0.0, f64::max);
        let deep = (0..60)
            .map(|i| {
                v.water_velocity(Vector3::new(0.0, 0.0, 30.0), i as f64 * 0.1)
                    .norm()
            })
            .fold(0.0, f64::max);
        assert!(shallow > 0.3, "{shallow}");
        assert!(deep < 0.1 * shallow, "{deep}");
    }

    #[test]
    fn buoyancy_follows_the_sites_water() {
        let heavy = |w: &str| -> f64 {
            let cfg: VehicleConfig =
                serde_json::from_str(&format!(r#"{{"water_density":{w}}}"#)).unwrap();
            cfg.validate().unwrap();
            cfg.hydrodynamics().buoyancy_n
        };
        let weight = 13.5 * GRAVITY_MPS2;
        // The Heavy's 0.0134 m^3: sinks slowly in fresh water, floats in the sea.
        assert!((heavy(r#""fresh""#) - 0.0134 * 997.0 * GRAVITY_MPS2).abs() < 1e-9);
        assert!(heavy(r#""fresh""#) - weight < -1.0);
        assert!(heavy(r#""sea""#) - weight > 2.0);
        assert!(heavy(r#""brackish""#) > heavy(r#""fresh""#));
        assert!((heavy("1000.0") - 0.0134 * 1000.0 * GRAVITY_MPS2).abs() < 1e-9);
        let bad: VehicleConfig = serde_json::from_str(r#"{"water_density":1500.0}"#).unwrap();
        let e = bad.validate().unwrap_err().to_string();
        assert!(
            e.contains("vehicle.water_density") && e.contains("1500"),
            "{e}"
        );
        assert!(serde_json::from_str::<VehicleConfig>(r#"{"water_density":"mud"}"#).is_err());
        // A sinking vehicle in the pool: idle, it goes down.
        let cfg = VehicleConfig {
            water_density: WaterDensity::Named(WaterKind::Fresh),
            ..Default::default()
        };
        let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
        run(&mut v, &[1500; 8], 5.0);
        assert!(v.state().velocity_world_mps.z > 0.0);
    }

    #[test]
    fn the_battery_sags_with_the_current_and_the_thrust_follows() {
        let cfg = VehicleConfig::default();
        let mut v = Vehicle::new(&cfg, &at(5.0), 1).unwrap();
        run(&mut v, &[1500; 8], 0.1);
        assert_eq!(v.battery_v(), 14.8);
        assert_eq!(v.current_a(), 0.0);
        let pwm = v.mixer().mix_pwm(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], true);
        run(&mut v, &pwm, 0.5);
        // Four horizontal T200 at full throttle draw tens of amperes: the pack sags, and
        // each thruster makes the table's thrust at the sagged voltage.
        let (volts, amps) = (v.battery_v(), v.current_a());
        assert!(amps > 40.0, "{amps}");
        assert!((volts - (14.8 - 0.05 * amps)).abs() < 0.5, "{volts} {amps}");
        let full = cfg.thruster.steady_thrust_n(1900.0, volts);
        assert!(full < cfg.thruster.steady_thrust_n(1900.0, 14.8));
        let t = v.thrusts_n();
        assert!((t[3] - full).abs() < 0.05 * full, "{t:?} {full}");
    }

    #[test]
    fn bad_config_names_the_key() {
        let cfg = VehicleConfig {
            physics_hz: 0.0,
            ..Default::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.physics_hz"), "{e}");
        let cfg = VehicleConfig {
            damping_linear: Some([1.0, -1.0, 0.0, 0.0, 0.0, 0.0]),
            ..Default::default()
        };
        assert!(cfg
            .validate()
            .unwrap_err()
            .to_string()
            .contains("vehicle.damping_linear"));
        let toml_err: Result<VehicleConfig, _> =
            serde_json::from_str(r#"{"frame":"heavy","bogus":1}"#);
        assert!(toml_err.is_err());
        let cfg = VehicleConfig {
            tether: Some(TetherConfig {
                length_m: -1.0,
                ..Default::default()
            }),
            ..Default::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.tether.length_m"), "{e}");
        let cfg = VehicleConfig {
            telemetry_latency_ms: -5.0,
            ..Default::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains("vehicle.telemetry_latency_ms"), "{e}");
        let ok: VehicleConfig = serde_json::from_str(r#"{"frame":"standard"}"#).unwrap();
        assert_eq!(ok.frame, Frame6Dof::Standard);
    }
}
