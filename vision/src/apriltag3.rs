//! AprilTag 3's own detector (Debian's libapriltag 3.x) as the quad finder and decoder in
//! place of OpenCV's `detectMarkers` (`[marker] detector = "apriltag3"`). It only finds
//! and decodes: the corners it gives are coarse, and the tracker refines them with
//! markhold's edge fit exactly as it does OpenCV's (`corners.rs`).
//!
//! The FFI is written here against apriltag 3's headers (`apriltag.h`,
//! `common/image_types.h`, `common/zarray.h`): six functions and four structs. The
//! `apriltag-sys` crate would build the library from its bundled source or bindgen
//! against it (bindgen, cmake, cc and the `image` crate as build dependencies) rather
//! than link the Debian package as it is.

use crate::config::{MarkerDetector, MarkerFamily};
use crate::error::CvContext;
use crate::VisionError;
use markhold_camera::Corners;
use opencv::core;
use std::os::raw::{c_int, c_void};
use std::ptr::NonNull;

#[repr(C)]
struct ImageU8 {
    width: i32,
    height: i32,
    stride: i32,
    buf: *mut u8,
}

#[repr(C)]
struct ZArray {
    el_sz: usize,
    size: c_int,
    alloc: c_int,
    data: *mut u8,
}

#[repr(C)]
struct Detection {
    family: *mut c_void,
    id: c_int,
    hamming: c_int,
    decision_margin: f32,
    h: *mut c_void,
    c: [f64; 2],
    /// Corners at tag coordinates (-1, 1), (1, 1), (1, -1), (-1, -1), counter-clockwise
    /// in the image; OpenCV's corner `k` of the same marker is `p[(5 - k) % 4]`.
    p: [[f64; 2]; 4],
}

/// The leading fields of `apriltag_detector_t` (its settings); the detector itself is
/// allocated by the library, which owns the rest of it.
#[repr(C)]
struct DetectorHead {
    nthreads: c_int,
    quad_decimate: f32,
    quad_sigma: f32,
    refine_edges: bool,
    decode_sharpening: f64,
    debug: bool,
}

type Family = c_void;

#[link(name = "apriltag")]
extern "C" {
    fn apriltag_detector_create() -> *mut DetectorHead;
    fn apriltag_detector_destroy(td: *mut DetectorHead);
    fn apriltag_detector_add_family_bits(td: *mut DetectorHead, f: *mut Family, bits: c_int);
    fn apriltag_detector_detect(td: *mut DetectorHead, im: *mut ImageU8) -> *mut ZArray;
    fn apriltag_detections_destroy(d: *mut ZArray);
    fn tag36h11_create() -> *mut Family;
    fn tag36h11_destroy(f: *mut Family);
    fn tag36h10_create() -> *mut Family;
    fn tag36h10_destroy(f: *mut Family);
    fn tag25h9_create() -> *mut Family;
    fn tag25h9_destroy(f: *mut Family);
    fn tag16h5_create() -> *mut Family;
    fn tag16h5_destroy(f: *mut Family);
}

type Create = unsafe extern "C" fn() -> *mut Family;
type Destroy = unsafe extern "C" fn(*mut Family);

/// AprilTag 3's constructor and destructor of the family, for the families it shares
/// with OpenCV (the same codes in the same id order: OpenCV's AprilTag dictionaries were
/// taken from the AprilTag library).
fn family_fns(family: MarkerFamily) -> Option<(Create, Destroy)> {
    match family {
        MarkerFamily::AprilTag36h11 => Some((tag36h11_create, tag36h11_destroy)),
        MarkerFamily::AprilTag36h10 => Some((tag36h10_create, tag36h10_destroy)),
        MarkerFamily::AprilTag25h9 => Some((tag25h9_create, tag25h9_destroy)),
        MarkerFamily::AprilTag16h5 => Some((tag16h5_create, tag16h5_destroy)),
        _ => None,
    }
}

/// AprilTag 3's detector for one family, single-threaded, at the resolution it is given
/// (no decimation of its own, no blur: the caller downscales, as the tracker does for
/// OpenCV), with its own edge refinement of the quads on (the library's default).
pub struct AprilTag3 {
    td: NonNull<DetectorHead>,
    family: NonNull<Family>,
    destroy: Destroy,
}

// SAFETY: the detector and family are owned by this value alone and used through
// `&mut self`, so by one thread at a time; with `nthreads = 1` the library starts no
// worker threads of its own.
unsafe impl Send for AprilTag3 {}

impl Drop for AprilTag3 {
    fn drop(&mut self) {
        // SAFETY: both were created in `new` and are destroyed once, the detector first
        // (it holds a reference to the family).
        unsafe {
            apriltag_detector_destroy(self.td.as_ptr());
            (self.destroy)(self.family.as_ptr());
        }
    }
}

impl AprilTag3 {
    /// The detector for `family` (one of the AprilTag families [`MarkerDetector::supports`] names), correcting up to
    /// 2 bit errors (the library's default: more grows its decode table steeply).
    pub fn new(family: MarkerFamily) -> Result<Self, VisionError> {
        let Some((create, destroy)) = family_fns(family) else {
            return Err(MarkerDetector::AprilTag3.unavailable_for(family).into());
        };
        // SAFETY: plain constructors of the library; null is checked below. The settings
        // written are the leading fields of `apriltag_detector_t` as the header lays them
        // out.
        unsafe {
            let fam = NonNull::new(create()).ok_or_else(|| alloc_error("tag family"))?;
            let Some(td) = NonNull::new(apriltag_detector_create()) else {
                destroy(fam.as_ptr());
                return Err(alloc_error("detector"));
            };
            apriltag_detector_add_family_bits(td.as_ptr(), fam.as_ptr(), 2);
            let head = &mut *td.as_ptr();
            head.nthreads = 1;
            head.quad_decimate = 1.0;
            // A blur would be applied to the caller's image in place at decimation 1.
            head.quad_sigma = 0.0;
            head.refine_edges = true;
            Ok(Self {
                td,
                family: fam,
                destroy,
            })
        }
    }

    /// Quad decimation of the library's own (1: none; 2: its default, quads found at half
    /// resolution and their corners refined on the whole image).
    pub fn set_quad_decimate(&mut self, factor: f32) {
        // SAFETY: the detector is alive and owned; a settings field.
        unsafe { (*self.td.as_ptr()).quad_decimate = factor.max(1.0) }
    }

    /// The library's own edge refinement of each quad (on by default).
    pub fn set_refine_edges(&mut self, on: bool) {
        // SAFETY: as above.
        unsafe { (*self.td.as_ptr()).refine_edges = on }
    }

    /// Every tag found in `image` (8-bit, one channel; a view into a larger image is
    /// fine): `f(id, corners)` with the corners in OpenCV's order (top-left, top-right,
    /// bottom-right, bottom-left as printed) and pixel convention (the first pixel's
    /// centre at (0, 0); AprilTag puts its outer corner there). Allocates nothing on the
    /// Rust heap (the library allocates its own working memory).
    pub fn detect(
        &mut self,
        image: &impl core::MatTraitConst,
        mut f: impl FnMut(u32, Corners),
    ) -> Result<(), VisionError> {
        if image.typ() != core::CV_8UC1 || image.dims() != 2 {
            return Err(VisionError::AprilTag {
                reason: format!(
                    "expected an 8-bit grey image, got OpenCV type {}",
                    image.typ()
                ),
            });
        }
        let (rows, cols) = (image.rows(), image.cols());
        if rows <= 0 || cols <= 0 {
            return Ok(());
        }
        let stride = image.step1(0).cv("step")? as i32;
        let mut im = ImageU8 {
            width: cols,
            height: rows,
            stride,
            buf: image.data().cast_mut(),
        };
        // SAFETY: `im` describes the Mat's pixels (rows x cols bytes with row stride
        // `stride`), alive for the call. With `quad_sigma = 0` the library only reads
        // them (a decimated or sharpened copy is its own). The detections array holds
        // `size` pointers to detections, read before it is freed.
        unsafe {
            let dets = apriltag_detector_detect(self.td.as_ptr(), &mut im);
            if dets.is_null() {
                return Err(alloc_error("detections"));
            }
            let n = usize::try_from((*dets).size).unwrap_or(0);
            for i in 0..n {
                let d = &**(*dets).data.cast::<*const Detection>().add(i);
                let Ok(id) = u32::try_from(d.id) else {
                    continue;
                };
                let mut c: Corners = [[0.0; 2]; 4];
                for (k, q) in c.iter_mut().enumerate() {
                    let p = d.p[(5 - k) % 4];
                    *q = [(p[0] - 0.5) as f32, (p[1] - 0.5) as f32];
                }
                f(id, c);
            }
            apriltag_detections_destroy(dets);
        }
        Ok(())
    }

    /// The tracker's seam (as `Detector::detect_in` does with OpenCV's): each marker of
    /// the map found in `image`, its largest copy, with corners shifted by `offset` into
    /// full-image pixels, into `found` (indexed by map slot through `index_of_id`).
    /// Markers whose perimeter lies outside `min_rate`..`max_rate` times the image's
    /// larger side are left out, as OpenCV's perimeter limits do. Returns how many
    /// markers of the map were found.
    pub(crate) fn detect_into(
        &mut self,
        image: &impl core::MatTraitConst,
        offset: (f64, f64),
        (min_rate, max_rate): (f64, f64),
        index_of_id: &[i16],
        found: &mut [Option<(f64, Corners)>],
    ) -> Result<usize, VisionError> {
        let larger = image.rows().max(image.cols()) as f64;
        let (lo, hi) = (min_rate * larger, max_rate * larger);
        let mut count = 0;
        self.detect(image, |id, mut c| {
            let slot = index_of_id
                .get(id as usize)
                .and_then(|s| usize::try_from(*s).ok());
            let Some(best) = slot.and_then(|s| found.get_mut(s)) else {
                return;
            };
            let side = crate::tracker::side_px(&c);
            if !(lo..=hi).contains(&(4.0 * side)) {
                return;
            }
            for p in &mut c {
                p[0] = (p[0] as f64 + offset.0) as f32;
                p[1] = (p[1] as f64 + offset.1) as f32;
            }
            if best.is_none() {
                count += 1;
            }
            if best.as_ref().is_none_or(|(b, _)| side > *b) {
                *best = Some((side, c));
            }
        })?;
        Ok(count)
    }
}

fn alloc_error(what: &str) -> VisionError {
    VisionError::AprilTag {
        reason: format!("could not allocate its {what}"),
    }
}
