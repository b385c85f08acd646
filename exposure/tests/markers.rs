//! AAEC over several markers in view: one marker under a lamp, one in shadow. The region
//! (`[exposure.aaec] regions`) decides whether both stay readable; the single marker's
//! RoI and the camera's mean-intensity AE are measured beside it.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod common;

use common::{limits, marker_cell, rock, square_corners, supersampled, unit_hash, FULL_WELL_US};
use markhold_exposure::*;

const W: u32 = 320;
const H: u32 = 240;
/// Side of each marker, pixels.
const SIDE: f64 = 64.0;
/// Contrast (white cells minus black cells, grey levels) a detector needs: a stand-in
/// for decoding.
const MIN_CONTRAST: f64 = 30.0;

/// Two markers on a textured wall; a lamp of `lamp` (relative irradiance, with a veiling
/// glare of 0.3 of it that lifts black and white cells alike) on marker `lit`, `ambient`
/// everywhere.
struct TwoMarkers {
    irradiance: Vec<f64>,
    corners: [Corners; 2],
    /// Top-left corner of each marker.
    origin: [(f64, f64); 2],
}

impl TwoMarkers {
    fn new(lit: usize, lamp: f64, ambient: f64) -> Self {
        let origin = [(48.0, 88.0), (208.0, 88.0)];
        let (lx, ly) = (origin[lit].0 + SIDE / 2.0, origin[lit].1 + SIDE / 2.0);
        let (w, h) = (W as usize, H as usize);
        let irradiance = supersampled(w, h, |px, py| {
            let mut refl = rock(px, py);
            for &(mx, my) in &origin {
                let (u, v) = ((px - mx) / SIDE, (py - my) / SIDE);
                if (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v) {
                    refl = marker_cell((u * 6.0) as usize, (v * 6.0) as usize);
                }
            }
            // A lamp's spot: full inside 40 px of its axis, gone by 70 px.
            let r = ((px - lx).powi(2) + (py - ly).powi(2)).sqrt();
            let spot = lamp * ((70.0 - r) / 30.0).clamp(0.0, 1.0);
            (refl + 0.3) * spot + refl * ambient
        });
        let corners = origin.map(|(mx, my)| square_corners(mx, my, SIDE));
        Self {
            irradiance,
            corners,
            origin,
        }
    }

    /// A linear camera at `t_us` with 2 grey levels of deterministic noise.
    fn render(&self, t_us: f64, k: u64, frame: &mut Frame) {
        frame.resize(W, H);
        let scale = t_us / FULL_WELL_US * 255.0;
        for (i, (p, e)) in frame.data.iter_mut().zip(&self.irradiance).enumerate() {
            let u = unit_hash(
                (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                    ^ (k + 1).wrapping_mul(0x1656_67B1_9E37_79F9),
            );
            *p = (e * scale + 2.0 * 12f64.sqrt() * (u - 0.5))
                .round()
                .clamp(0.0, 255.0) as u8;
        }
        frame.meta.exposure_us = t_us;
        frame.meta.seq = k;
        frame.meta.stamp_s = k as f64 / 30.0;
    }

    /// White cells minus black cells of marker `i`, each sampled on the middle half of
    /// the cell.
    fn contrast(&self, frame: &Frame, i: usize) -> f64 {
        let (x0, y0) = self.origin[i];
        let c = SIDE / 6.0;
        let (mut ws, mut wn, mut bs, mut bn) = (0.0, 0.0, 0.0, 0.0);
        for cy in 0..6 {
            for cx in 0..6 {
                let white = marker_cell(cx, cy) > 0.5;
                let (ux, uy) = (x0 + cx as f64 * c, y0 + cy as f64 * c);
                for y in (0.25 * c).ceil() as usize..(0.75 * c).floor() as usize {
                    for x in (0.25 * c).ceil() as usize..(0.75 * c).floor() as usize {
                        let g = frame.data[(uy as usize + y) * W as usize + ux as usize + x];
                        if white {
                            ws += g as f64;
                            wn += 1.0;
                        } else {
                            bs += g as f64;
                            bn += 1.0;
                        }
                    }
                }
            }
        }
        ws / wn - bs / bn
    }
}

/// Run `ctrl` for `frames` frames (a command applies one frame late); each frame the
/// markers whose contrast reaches `MIN_CONTRAST` are "decoded", the first one decoded
/// is named (marker 0 is the map's origin). With a marker decoded the map places the
/// other in the image too: both are passed as the markers in view, as the loop does.
/// Returns the fraction of frames from `settle` on in which both markers were decoded,
/// and the last exposure.
fn run(
    scene: &TwoMarkers,
    ctrl: &mut dyn ExposureController,
    t0: f64,
    frames: usize,
    settle: usize,
) -> (f64, f64) {
    let mut frame = Frame::new(W, H);
    let (mut applied, mut next) = (t0, t0);
    let mut in_view: Vec<Corners> = Vec::with_capacity(2);
    let mut both = 0;
    for k in 0..frames {
        scene.render(applied, k as u64, &mut frame);
        applied = next;
        let decoded = [0, 1].map(|i| scene.contrast(&frame, i) >= MIN_CONTRAST);
        in_view.clear();
        if decoded.contains(&true) {
            in_view.extend_from_slice(&scene.corners);
        }
        if k >= settle && decoded == [true, true] {
            both += 1;
        }
        let named = decoded.iter().position(|&d| d).map(|i| scene.corners[i]);
        let step = ctrl.update_in_view(&frame, named.as_ref(), &in_view);
        assert!(step.exposure_us.is_finite());
        next = step.exposure_us;
    }
    (both as f64 / (frames - settle) as f64, next)
}

fn aaec_with(regions: MarkerRegions, t0: f64) -> Box<dyn ExposureController> {
    let mut cfg = ExposureConfig::default();
    cfg.aaec.regions = regions;
    build_controller(&cfg, ExposureMethod::Aaec, limits(), t0).unwrap()
}

const REGIONS: [MarkerRegions; 4] = [
    MarkerRegions::Union,
    MarkerRegions::Sum,
    MarkerRegions::LogSum,
    MarkerRegions::Single,
];

/// Both markers decoded in >= 95 % of the frames after 3 s, with the lamp on either
/// marker and from short and long starts, for the default region; the table of every
/// region and of the mean-intensity AE is printed (`--nocapture`).
#[test]
fn a_lit_and_a_dark_marker_are_both_readable() {
    let default = AaecConfig::default().regions;
    let mut worst_default = f64::MAX;
    let mut worst_single = f64::MAX;
    for lit in [0, 1] {
        let scene = TwoMarkers::new(lit, 8.0, 1.0);
        for t0 in [100.0, 5000.0] {
            for regions in REGIONS {
                let mut c = aaec_with(regions, t0);
                let (both, t) = run(&scene, c.as_mut(), t0, 300, 90);
                eprintln!("lamp on marker {lit}, from {t0} us: aaec {regions}: both decoded {:.1} %, ends at {t:.0} us", both * 100.0);
                if regions == default {
                    worst_default = worst_default.min(both);
                }
                if regions == MarkerRegions::Single {
                    worst_single = worst_single.min(both);
                }
            }
            let mut c = build_controller(
                &ExposureConfig::default(),
                ExposureMethod::Default,
                limits(),
                t0,
            )
            .unwrap();
            let (both, t) = run(&scene, c.as_mut(), t0, 300, 90);
            eprintln!("lamp on marker {lit}, from {t0} us: mean-intensity AE: both decoded {:.1} %, ends at {t:.0} us", both * 100.0);
        }
    }
    assert!(
        worst_default >= 0.95,
        "{default}: both markers decoded in {:.1} % of frames",
        worst_default * 100.0
    );
    assert!(
        worst_single < 0.95,
        "the single RoI held both markers ({:.1} %): the scene does not test the regions",
        worst_single * 100.0
    );
}

/// One marker in view: every region meters the same box, and gives the same commands
/// bit for bit (a map of one is today's AAEC).
#[test]
fn one_marker_in_view_is_the_same_for_every_region() {
    let scene = TwoMarkers::new(0, 8.0, 1.0);
    let corners = scene.corners[0];
    let mut traces = Vec::new();
    for regions in REGIONS {
        let mut c = aaec_with(regions, 300.0);
        let mut frame = Frame::new(W, H);
        let mut t = 300.0;
        let mut trace = Vec::new();
        for k in 0..120 {
            scene.render(t, k, &mut frame);
            // Lost for a while in the middle: the held regions and the fallback too.
            let seen = !(40..52).contains(&k);
            let step = if regions == MarkerRegions::Single {
                c.update(&frame, seen.then_some(&corners))
            } else {
                let in_view: &[Corners] = if seen { &[corners] } else { &[] };
                c.update_in_view(&frame, seen.then_some(&corners), in_view)
            };
            t = step.exposure_us;
            trace.push((t.to_bits(), step.metric.to_bits(), step.roi));
        }
        traces.push(trace);
    }
    for (r, t) in REGIONS.iter().zip(&traces).skip(1) {
        assert_eq!(&traces[0], t, "{r} differs from union with one marker");
    }
}

/// The union box holds both markers; `"sum"` meters each marker's own box (the step's
/// RoI is the box around them).
#[test]
fn the_step_reports_the_box_around_the_markers() {
    let scene = TwoMarkers::new(0, 8.0, 1.0);
    let pad = |c: &Corners| Roi::from_corners_padded(c, 0.1, W, H).unwrap();
    let want = pad(&scene.corners[0]).union(&pad(&scene.corners[1]));
    for regions in [MarkerRegions::Union, MarkerRegions::Sum] {
        let mut c = aaec_with(regions, 300.0);
        let mut frame = Frame::new(W, H);
        scene.render(300.0, 0, &mut frame);
        let s = c.update_in_view(&frame, Some(&scene.corners[0]), &scene.corners);
        assert_eq!(s.roi, Some(want), "{regions}");
        assert!(s.used_frame && s.metric > 0.0, "{regions}: {s:?}");
    }
}

#[test]
fn regions_are_read_and_checked_in_the_site_file() {
    let cfg: ExposureConfig = toml::from_str("[aaec]\nregions = \"log-sum\"\n").unwrap();
    assert_eq!(cfg.aaec.regions, MarkerRegions::LogSum);
    let e = toml::from_str::<ExposureConfig>("[aaec]\nregions = \"all\"\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("regions") || e.contains("all"), "{e}");
    assert!(e.contains("union") && e.contains("single"), "{e}");
}
