//! markhold-hil: the simulated world for hardware-in-the-loop runs.
//!
//! A BlueROV2 / BlueROV2 Heavy rigid body (rapier3d) with buoyancy, added mass, damping
//! and T200 thrusters mixed like ArduSub; an ArduSub-like MAVLink endpoint; a physically
//! based underwater camera; and ArduPilot's SITL JSON physics server.

pub mod camera;
pub mod delay;
pub mod disturbance;
pub mod endpoint;
mod error;
pub mod mixer;
pub mod rig;
pub mod scene;
pub mod sitl;
pub mod thruster;
pub mod vehicle;

pub use delay::DelayConfig;
pub use disturbance::{ModelError, TetherConfig};
pub use endpoint::{EndpointConfig, VehicleEndpoint};
pub use error::HilError;
pub use markhold_config::ConfigError;
pub use mixer::{Frame6Dof, Mixer};
pub use rig::{HilRig, HilSetup, Truth};
pub use sitl::{SitlConfig, SitlServer};
pub use thruster::ThrusterConfig;
pub use vehicle::{Hydrodynamics, Vehicle, VehicleConfig, VehicleMotion, VehicleState};
