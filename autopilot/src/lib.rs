//! markhold-autopilot: a 6-DOF station keeper and an ArduSub MAVLink link with failsafes.
//!
//! - [`StationKeeper`]: six PID axes (pid crate, stepped at a fixed rate on the loop's
//!   clock) on the body-frame pose error to a station in front of the marker.
//! - [`VehicleLink`]: ArduSub session over MAVLink 2 (UDP, TCP, serial), synchronous and
//!   non-blocking for the per-frame loop.
//! - [`Supervisor`]: the failsafe state machine.
//! - [`vehicle`]: the vehicle description (frames, FRAME_CONFIG, motor factors and
//!   thruster layout) that preflight and the simulator read.
//!
//! Frames and units: `docs/frames.md` of the workspace.

pub mod config;
pub mod error;
#[doc(hidden)]
pub mod fuzzing;
pub mod keeper;
pub mod link;
pub mod pilot;
pub mod signing_clock;
pub mod supervisor;
pub mod transport;
pub mod types;
pub mod vehicle;
pub mod vision_pose;

pub use config::{
    station_timeout_s, AxisConfig, CommandKind, ControllerConfig, LinkConfig, LinkMode,
    MarkerLostAction, OnExit, PilotInput, StationConfig,
};
pub use error::AutopilotError;
pub use keeper::{AutopilotHolds, KeeperStatus, PoseMeasurement, StationKeeper, ViewLimits};
pub use link::{
    CloseReport, CommandStatus, NeutralShown, PilotSeen, RawFrame, RcChannels, Settled, Severity,
    StationSeen, VehicleLink, VehicleState,
};
pub use markhold_config::ConfigError;
/// The mavlink crate the link is built on (same version and features), for callers that
/// build or check frames themselves (tests, tools).
pub use mavlink;
pub use pilot::PilotMap;
pub use supervisor::{Directive, FailsafeEvent, Supervisor, SupervisorInput};
pub use types::{wrap_pi, ArduSubMode, Effort};
pub use vehicle::Frame6Dof;
pub use vision_pose::VisionPose;

#[cfg(test)]
mod tests {
    /// The integrator may move the loop (and so these) to another thread.
    #[test]
    fn loop_parts_are_send() {
        fn send<T: Send>() {}
        send::<crate::VehicleLink>();
        send::<crate::StationKeeper>();
        send::<crate::Supervisor>();
        send::<crate::VehicleState>();
    }
}
