//! markhold-autopilot (being built).
