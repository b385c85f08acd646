//! The field loop in real time: `markhold run` against a free-running vehicle, stream and
//! GenICam cameras, the pymavlink vehicle, `hil --vehicle`, the live Foxglove view and the
//! web page in Chromium; and the loop's order when tracking cannot answer.
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod external_vehicle;
mod field_loop;
mod genicam;
mod hil_live;
mod loop_order;
mod run_live;
mod stream_camera;
mod web_page;
