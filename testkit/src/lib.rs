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
