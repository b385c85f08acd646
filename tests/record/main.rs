//! Recording: MCAP recordings read back and replayed bit for bit, rotation and quota, and
//! the raw MAVLink tap.
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod mavlink_tap;
mod record_replay;
mod rotation;
