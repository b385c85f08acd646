//! Plain value types shared by the config, the keeper, the pilot mapping and the link:
//! the effort vector, the ArduSub mode numbers and angle wrapping. They depend on nothing
//! else in the crate, so every module can use them without a cycle.

use serde::Serialize;

/// Normalized efforts for ArduSub's mixer, body FRD, each in -1..1.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Effort {
    /// Forward (+x).
    pub surge: f64,
    /// Right (+y).
    pub sway: f64,
    /// Down (+z).
    pub heave: f64,
    /// Roll right.
    pub roll: f64,
    /// Pitch nose up.
    pub pitch: f64,
    /// Yaw right.
    pub yaw: f64,
}

impl Effort {
    /// All axes zero.
    pub const NEUTRAL: Effort = Effort {
        surge: 0.0,
        sway: 0.0,
        heave: 0.0,
        roll: 0.0,
        pitch: 0.0,
        yaw: 0.0,
    };

    /// The axes in order (surge, sway, heave, roll, pitch, yaw).
    pub fn to_array(&self) -> [f64; 6] {
        [
            self.surge, self.sway, self.heave, self.roll, self.pitch, self.yaw,
        ]
    }

    /// From (surge, sway, heave, roll, pitch, yaw).
    pub fn from_array(a: [f64; 6]) -> Self {
        Self {
            surge: a[0],
            sway: a[1],
            heave: a[2],
            roll: a[3],
            pitch: a[4],
            yaw: a[5],
        }
    }

    /// Every axis clamped to -1..1; NaN becomes 0 (never command garbage).
    pub fn clamped(&self) -> Self {
        let mut a = self.to_array();
        for v in &mut a {
            *v = if v.is_finite() {
                v.clamp(-1.0, 1.0)
            } else {
                0.0
            };
        }
        Self::from_array(a)
    }

    /// True when every axis is exactly zero.
    pub fn is_neutral(&self) -> bool {
        self.to_array().iter().all(|v| *v == 0.0)
    }
}

/// ArduSub flight modes (HEARTBEAT.custom_mode).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[repr(u32)]
pub enum ArduSubMode {
    /// Attitude held, pilot controls rates.
    Stabilize = 0,
    /// Rate control.
    Acro = 1,
    /// Depth held.
    AltHold = 2,
    /// Mission.
    Auto = 3,
    /// Position targets from a companion.
    Guided = 4,
    /// Circle.
    Circle = 7,
    /// Ascend to the surface.
    Surface = 9,
    /// Position hold (needs a position estimate).
    PosHold = 16,
    /// Pilot input straight into the mixer.
    Manual = 19,
    /// Motor direction detection.
    MotorDetect = 20,
    /// Hold altitude above the seabed.
    SurfTrak = 21,
}

impl ArduSubMode {
    /// From HEARTBEAT.custom_mode.
    pub fn from_custom_mode(m: u32) -> Option<Self> {
        Some(match m {
            0 => Self::Stabilize,
            1 => Self::Acro,
            2 => Self::AltHold,
            3 => Self::Auto,
            4 => Self::Guided,
            7 => Self::Circle,
            9 => Self::Surface,
            16 => Self::PosHold,
            19 => Self::Manual,
            20 => Self::MotorDetect,
            21 => Self::SurfTrak,
            _ => return None,
        })
    }

    /// The custom_mode number.
    pub fn number(self) -> u32 {
        self as u32
    }
}

/// Wraps an angle to (-pi, pi].
pub fn wrap_pi(a: f64) -> f64 {
    use std::f64::consts::PI;
    let w = (a + PI).rem_euclid(2.0 * PI) - PI;
    if w <= -PI {
        w + 2.0 * PI
    } else {
        w
    }
}
