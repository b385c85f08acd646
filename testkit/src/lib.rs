//! Test helpers shared by markhold's crates (dev-dependency only).
//!
//! [`CountingAlloc`] wraps the system allocator and counts every allocation and
//! reallocation, per thread and for the whole process, so a test can check that a
//! per-frame path allocates nothing once warmed up:
//!
//! ```
//! #[global_allocator]
//! static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;
//!
//! fn main() {
//!     let mut buf = Vec::with_capacity(64);
//!     let before = markhold_testkit::thread_allocs();
//!     for k in 0..64u8 {
//!         buf.push(k); // within capacity: nothing allocated
//!     }
//!     assert_eq!(markhold_testkit::thread_allocs(), before);
//!     buf.push(64); // beyond: the vector grows
//!     assert!(markhold_testkit::thread_allocs() > before);
//! }
//! ```
//!
//! The counts only move in a test binary that installs it as its global allocator.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};

/// The system allocator, counting allocations and reallocations (frees are not counted).
/// Install it with `#[global_allocator]` in a test binary.
#[derive(Clone, Copy, Debug, Default)]
pub struct CountingAlloc;

static PROCESS_ALLOCS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    static THREAD_ALLOCS: Cell<u64> = const { Cell::new(0) };
}

fn count() {
    PROCESS_ALLOCS.fetch_add(1, Ordering::Relaxed);
    // `try_with`: a thread's last frees and allocations may come after its locals are
    // gone; those go uncounted on the thread (the process count still has them).
    let _ = THREAD_ALLOCS.try_with(|c| c.set(c.get() + 1));
}

/// Allocations and reallocations made so far by the calling thread.
pub fn thread_allocs() -> u64 {
    THREAD_ALLOCS.try_with(Cell::get).unwrap_or(0)
}

/// Allocations and reallocations made so far by every thread of the process.
pub fn process_allocs() -> u64 {
    PROCESS_ALLOCS.load(Ordering::Relaxed)
}

// SAFETY: every call is passed on unchanged to `System`, which upholds the
// `GlobalAlloc` contract; the counting touches only an atomic and a const-initialized
// thread local, neither of which allocates.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: the caller's guarantees for `layout` are the ones `System.alloc` needs.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator, that is from `System`, with `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        // SAFETY: `ptr` came from `System` with `layout`; the caller guarantees
        // `new_size` as `System.realloc` needs it.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Every line `out` gives (a child's stdout), sent on a channel by a thread of its own,
/// so that a test can wait for a line with a bound.
pub fn lines_on_channel(
    out: impl std::io::Read + Send + 'static,
) -> std::sync::mpsc::Receiver<String> {
    use std::io::BufRead;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Panics unless pymavlink can be imported: scripts/install-deps installs it, a test never
/// installs anything, and a missing pymavlink fails the test rather than skipping it.
#[allow(clippy::panic)] // A test helper: failing loudly is its job.
pub fn require_pymavlink() {
    let probe = std::process::Command::new("python3")
        .args(["-c", "import pymavlink.dialects.v20.ardupilotmega"])
        .output();
    match probe {
        Ok(o) if o.status.success() => {}
        Ok(o) => panic!(
            "pymavlink is not importable: run scripts/install-deps ({})",
            String::from_utf8_lossy(&o.stderr).trim()
        ),
        Err(e) => panic!("python3 cannot be run ({e}): run scripts/install-deps"),
    }
}

/// Pixel (x, y) of the synthetic marker pictures: a marker cell (`Some(white)`: 220 or
/// 30) or, outside the marker (`None`), a rocky background (60 with two interfering
/// ripples, about 20 to 100); plus sensor noise of a few grey levels (-3.5 to 3.5, a
/// fixed hash, so runs repeat).
pub fn synthetic_grey(x: usize, y: usize, cell: Option<bool>) -> u8 {
    let (fx, fy) = (x as f64, y as f64);
    let g = match cell {
        Some(true) => 220.0,
        Some(false) => 30.0,
        None => {
            60.0 + 30.0 * (fx * 0.11).sin() * (fy * 0.07).cos() + 10.0 * (fx * 0.5 + fy * 0.3).sin()
        }
    };
    let hsh = (x as u32).wrapping_mul(2_654_435_761) ^ (y as u32).wrapping_mul(40_503);
    let noise = (hsh.wrapping_mul(2_246_822_519) >> 29) as f64 - 3.5;
    (g + noise).clamp(0.0, 255.0) as u8
}

/// A forward-looking camera (x_c = y_b, y_c = z_b, z_c = x_b) at (`x`, 0, `z`) in the
/// vehicle's body frame (forward, right, down), metres: `t_vehicle_cam`.
pub fn forward_camera(x: f64, z: f64) -> nalgebra::Isometry3<f64> {
    use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        Vector3::new(0.0, 1.0, 0.0),
        Vector3::new(0.0, 0.0, 1.0),
        Vector3::new(1.0, 0.0, 0.0),
    ]));
    Isometry3::from_parts(
        Translation3::new(x, 0.0, z),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

/// The header of vehicle 1's autopilot (component 1), sequence 0.
pub const VEHICLE_HEADER: mavlink::MavHeader = mavlink::MavHeader {
    system_id: 1,
    component_id: 1,
    sequence: 0,
};

/// An active ArduSub's HEARTBEAT in flight mode `custom_mode` with `base_mode`.
pub fn sub_heartbeat(
    custom_mode: u32,
    base_mode: mavlink::dialects::ardupilotmega::MavModeFlag,
) -> mavlink::dialects::ardupilotmega::MavMessage {
    use mavlink::dialects::ardupilotmega::{
        MavAutopilot, MavMessage, MavState, MavType, HEARTBEAT_DATA,
    };
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode,
        mavtype: MavType::MAV_TYPE_SUBMARINE,
        autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode,
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[global_allocator]
    static A: CountingAlloc = CountingAlloc;

    #[test]
    fn counts_allocations_on_this_thread_and_in_the_process() {
        let (thread, process) = (thread_allocs(), process_allocs());
        let v: Vec<u64> = Vec::with_capacity(16);
        assert!(thread_allocs() > thread && v.capacity() >= 16);
        assert!(process_allocs() > process);
        let before = thread_allocs();
        let x = std::hint::black_box(3u64) * 7;
        assert_eq!(thread_allocs(), before);
        assert_eq!(x, 21);
    }
}
