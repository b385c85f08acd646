//! The vehicle: the BlueROV2 frames ArduSub knows by FRAME_CONFIG, their motor factor
//! tables and where their thrusters sit. The field checks the autopilot's FRAME_CONFIG
//! against it (preflight); the simulator mixes and pushes with it.
//!
//! Efforts follow docs/frames.md: `[surge, sway, heave (+down), roll, pitch, yaw]`, FRD.
//! Sources: ArduPilot's libraries/AP_Motors/AP_Motors6DOF.h (`sub_frame_t`: the
//! FRAME_CONFIG values) and AP_Motors6DOF.cpp (`setup_motors`: the factor tables),
//! docs/reference/ardusub.md.

use markhold_config::ConfigError;
use nalgebra::Vector3;
use serde::{de::IntoDeserializer, Deserialize, Serialize};

/// The vehicle frame (ArduSub FRAME_CONFIG). Its names in a site file
/// (`[vehicle] frame`) are parsed in one place: serde's derive below, which
/// [`Frame6Dof::from_str`](std::str::FromStr) also goes through.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Frame6Dof {
    /// BlueROV2 Heavy: 8 thrusters, `vectored_6dof`, fully 6-DOF.
    #[default]
    Heavy,
    /// BlueROV2: 6 thrusters, `vectored`, no pitch authority.
    Standard,
}

/// Maximum number of motors (Heavy).
pub const MAX_MOTORS: usize = 8;

/// Per-motor factors: (roll, pitch, yaw, throttle, forward, lateral), ArduSub's tables.
const FACTORS_COMMON: [[f64; 6]; 4] = [
    [0.0, 0.0, 1.0, 0.0, -1.0, 1.0],
    [0.0, 0.0, -1.0, 0.0, -1.0, -1.0],
    [0.0, 0.0, -1.0, 0.0, 1.0, 1.0],
    [0.0, 0.0, 1.0, 0.0, 1.0, -1.0],
];
const FACTORS_VECTORED: [[f64; 6]; 2] = [
    [1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
];
const FACTORS_HEAVY: [[f64; 6]; 4] = [
    [1.0, -1.0, 0.0, -1.0, 0.0, 0.0],
    [-1.0, -1.0, 0.0, -1.0, 0.0, 0.0],
    [1.0, 1.0, 0.0, -1.0, 0.0, 0.0],
    [-1.0, 1.0, 0.0, -1.0, 0.0, 0.0],
];

/// Where a thruster sits (body FRD, metres from the centre of gravity) and which way a
/// positive command pushes the vehicle (unit vector, body FRD).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThrusterMount {
    pub position_m: Vector3<f64>,
    pub direction: Vector3<f64>,
}

impl Frame6Dof {
    /// Both frames, Heavy first.
    pub const ALL: [Frame6Dof; 2] = [Frame6Dof::Heavy, Frame6Dof::Standard];

    /// The frame's name in a site file.
    pub fn as_str(self) -> &'static str {
        match self {
            Frame6Dof::Heavy => "heavy",
            Frame6Dof::Standard => "standard",
        }
    }

    pub fn motor_count(self) -> usize {
        match self {
            Frame6Dof::Heavy => 8,
            Frame6Dof::Standard => 6,
        }
    }

    /// ArduSub's FRAME_CONFIG for this frame (`sub_frame_t`: 1 = SUB_FRAME_VECTORED,
    /// 2 = SUB_FRAME_VECTORED_6DOF).
    pub fn frame_config(self) -> i64 {
        match self {
            Frame6Dof::Heavy => 2,
            Frame6Dof::Standard => 1,
        }
    }

    /// The frame of a FRAME_CONFIG value (`None`: a frame markhold does not describe).
    pub fn from_frame_config(value: i64) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.frame_config() == value)
    }

    /// Per-motor factors (roll, pitch, yaw, throttle, forward, lateral), ArduSub's table
    /// for the frame; rows past [`Self::motor_count`] are zero.
    pub fn motor_factors(self) -> [[f64; 6]; MAX_MOTORS] {
        let mut factors = [[0.0; 6]; MAX_MOTORS];
        factors[..4].copy_from_slice(&FACTORS_COMMON);
        match self {
            Frame6Dof::Standard => factors[4..6].copy_from_slice(&FACTORS_VECTORED),
            Frame6Dof::Heavy => factors[4..8].copy_from_slice(&FACTORS_HEAVY),
        }
        factors
    }

    /// The thrusters' positions and directions, consistent with the factor tables;
    /// motors past [`Self::motor_count`] have zero position and direction.
    pub fn thruster_mounts(self) -> [ThrusterMount; MAX_MOTORS] {
        let s = std::f64::consts::FRAC_1_SQRT_2;
        // Horizontal thrusters below the centre of gravity, where Wu 2018 and von Benzon
        // et al. 2022 put them: (+-0.156, +-0.111, 0.085) m from the body origin (their
        // thruster configuration matrix: roll / pitch arms 0.707 x 0.085 = 0.06 m, yaw arm
        // 0.707 x (0.156 + 0.111) = 0.1888 m). The Heavy's CG is at the origin; the
        // BlueROV2's is 0.02 m below it (Wu), so its thrusters sit 0.065 m below its CG.
        // Surge therefore pitches the nose up.
        let below_cg = match self {
            Frame6Dof::Heavy => 0.085,
            Frame6Dof::Standard => 0.065,
        };
        let horiz = |x: f64, y: f64, dx: f64, dy: f64| ThrusterMount {
            position_m: Vector3::new(x, y, below_cg),
            direction: Vector3::new(dx * s, dy * s, 0.0),
        };
        let vert = |x: f64, y: f64, z: f64| ThrusterMount {
            position_m: Vector3::new(x, y, z),
            direction: Vector3::new(0.0, 0.0, 1.0),
        };
        let unused = ThrusterMount {
            position_m: Vector3::zeros(),
            direction: Vector3::zeros(),
        };
        let mut mounts = [unused; MAX_MOTORS];
        mounts[0] = horiz(0.156, 0.111, -1.0, 1.0);
        mounts[1] = horiz(0.156, -0.111, -1.0, -1.0);
        mounts[2] = horiz(-0.156, 0.111, 1.0, 1.0);
        mounts[3] = horiz(-0.156, -0.111, 1.0, -1.0);
        match self {
            Frame6Dof::Standard => {
                mounts[4] = vert(0.0, 0.109, -0.077);
                mounts[5] = vert(0.0, -0.109, -0.077);
            }
            Frame6Dof::Heavy => {
                mounts[4] = vert(0.118, 0.215, -0.064);
                mounts[5] = vert(0.118, -0.215, -0.064);
                mounts[6] = vert(-0.118, 0.215, -0.064);
                mounts[7] = vert(-0.118, -0.215, -0.064);
            }
        }
        mounts
    }
}

impl std::fmt::Display for Frame6Dof {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Frame6Dof {
    type Err = ConfigError;
    /// A frame's name as a site file writes it, through the same parser as the file.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let de: serde::de::value::StrDeserializer<'_, serde::de::value::Error> =
            s.into_deserializer();
        Self::deserialize(de)
            .map_err(|_| ConfigError::new("vehicle.frame", s, "\"heavy\" or \"standard\""))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_frame_config_round_trip() {
        for frame in Frame6Dof::ALL {
            assert_eq!(frame.as_str().parse::<Frame6Dof>().ok(), Some(frame));
            assert_eq!(
                Frame6Dof::from_frame_config(frame.frame_config()),
                Some(frame)
            );
        }
        assert_eq!(Frame6Dof::Heavy.frame_config(), 2);
        assert_eq!(Frame6Dof::Standard.frame_config(), 1);
        assert_eq!(Frame6Dof::from_frame_config(0), None);
        let e = "light".parse::<Frame6Dof>().unwrap_err().to_string();
        assert!(e.contains("vehicle.frame") && e.contains("light"), "{e}");
    }

    #[test]
    fn every_motor_has_a_factor_row_and_a_thruster() {
        for frame in Frame6Dof::ALL {
            let (f, m) = (frame.motor_factors(), frame.thruster_mounts());
            for (i, (f, m)) in f.iter().zip(&m).enumerate() {
                let used = i < frame.motor_count();
                assert_eq!(f.iter().any(|v| *v != 0.0), used, "{frame} motor {i}");
                assert_eq!(m.direction.norm() > 0.0, used, "{frame} motor {i}");
            }
        }
    }
}
