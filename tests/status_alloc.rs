//! The web page's observer allocates nothing on the loop's side: with a counting global
//! allocator, frames handed to `StatusObserver` (status every frame, the pixels every
//! frame at 30 Hz, failsafe events, a pose) allocate zero times after the first, also
//! while the page takes frames and swaps its buffer in between.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};

use markhold::observe::{StatusBoard, StatusObserver};
use markhold::pipeline::{FrameRecord, FrameView, Observer};
use markhold_autopilot::{Directive, Effort, FailsafeEvent};
use markhold_exposure::{ExposureStep, Frame};
use nalgebra::{Isometry3, Vector3};

struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

// SAFETY: every call is forwarded unchanged to the system allocator, which upholds
// GlobalAlloc's contract; the counter has no effect on the memory handed out.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's layout, as GlobalAlloc::alloc requires.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `alloc` above with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: forwarded as received, as GlobalAlloc::realloc requires.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn the_loops_side_allocates_nothing_per_frame() {
    let site = markhold::params::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pool-640.toml"),
    )
    .unwrap();
    let (w, h) = (site.calibration.width, site.calibration.height);
    let board = StatusBoard::new(w, h);
    let mut page = board.spare_snapshot();
    let mut obs = StatusObserver::new(&site, board.clone(), 30.0);
    let mut frame = Frame::new(w, h);
    let pose = Isometry3::translation(0.0, 0.0, 1.0) * Isometry3::rotation(Vector3::y() * 3.1);
    let events = [
        FailsafeEvent::MarkerLost {
            at_s: 1.0,
            last_seen_s: 0.5,
        },
        FailsafeEvent::MarkerReacquired {
            at_s: 1.0,
            lost_for_s: 0.5,
        },
    ];
    let mut step = |k: u64, obs: &mut StatusObserver| {
        frame.meta.seq = k;
        frame.meta.stamp_s = k as f64 / 30.0;
        let rec = FrameRecord {
            seq: k,
            stamp_s: frame.meta.stamp_s,
            exposure_used_us: 3000.0,
            exposure: ExposureStep::skipped(3000.0),
            detected: !k.is_multiple_of(3),
            corners: Some([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]),
            t_cam_marker: (!k.is_multiple_of(3)).then_some(pose),
            cov_cam: None,
            reproj_rms_px: 0.1,
            markers_used: 1,
            effort: Effort::default(),
            directive: Directive::Command,
            latency_s: 0.001,
        };
        let view = FrameView {
            rec: &rec,
            frame: &frame,
            heartbeat_s: Some(rec.stamp_s),
            vehicle: None,
            events: &events[..(k % 3) as usize],
            markers_in_view: &[0],
            transitions: &[],
            shutdown: false,
        };
        let before = ALLOCATIONS.load(Ordering::Relaxed);
        obs.frame(&view);
        ALLOCATIONS.load(Ordering::Relaxed) - before
    };
    // The first frame of a size may size the buffers.
    step(0, &mut obs);
    let mut allocated = 0;
    let mut taken = 0;
    for k in 1..300 {
        allocated += step(k, &mut obs);
        // The page takes a frame now and then; its buffer goes back to the loop.
        if k.is_multiple_of(7) && board.take_snapshot(&mut page) {
            taken += 1;
        }
    }
    assert_eq!(allocated, 0, "allocations on the loop's side in 299 frames");
    assert!(taken > 30, "the page took {taken} frames");
    assert_eq!(page.width, w);
    assert_eq!(board.status().frames, 300);
    // The last frame (299) had a pose: its position error is shown.
    assert!(board.status().position.is_some());
}
