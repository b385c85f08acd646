//! markhold-hil: the simulated world for hardware-in-the-loop runs.
//!
//! A BlueROV2 / BlueROV2 Heavy rigid body (rapier3d) with buoyancy, added mass, damping
//! and T200 thrusters mixed like ArduSub; an ArduSub-like MAVLink endpoint; a physically
//! based underwater camera; and ArduPilot's SITL JSON physics server.

pub mod camera;
mod error;
pub mod scene;

pub use error::HilError;
