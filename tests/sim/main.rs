//! The simulator and its commands: `markhold hil` end to end and its plots, injected
//! faults, `robustness`, station geometry, `sitl`, garbage datagrams, MAVLink signing, the
//! loop built once, and `compare` (sharded, merged and on SLURM).
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod compare;
mod compare_shard;
mod faults;
mod garbage;
mod geometry;
mod hil_e2e;
mod hil_plots;
mod loop_built_once;
mod robustness;
mod security;
mod sitl_e2e;
