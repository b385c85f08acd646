//! The printed tag, checked the way it will be used: each format is placed flat in
//! front of a pinhole camera at a known distance and the vision crate's tracker must
//! decode the id and measure the distance within 1 % (so the physical size is right).
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use super::*;
use markhold_exposure::Frame;
use markhold_vision::{CameraCalibration, DetectorConfig, MarkerConfig, MarkerTracker};

const W: usize = 1440;
const H: usize = 1080;
const F_PX: f64 = 1000.0;
/// Grey levels of the camera image: black ink, white paper, the world around the page.
const BLACK: f64 = 30.0;
const WHITE: f64 = 200.0;
const BACKGROUND: f64 = 90.0;

fn calib() -> CameraCalibration {
    CameraCalibration::pinhole(W as u32, H as u32, F_PX, F_PX, 719.5, 539.5)
}

/// Detect in `frame` and check the id, and the distance along the optical axis within
/// 1 % of where the page was placed.
fn assert_seen_at(frame: &Frame, family: MarkerFamily, id: u32, size_mm: f64, distance_m: f64) {
    let marker = MarkerConfig::single(family, id, size_mm / 1000.0);
    let mut tracker = MarkerTracker::new(&marker, &DetectorConfig::default(), calib()).unwrap();
    let obs = tracker.process(frame).unwrap().expect("marker detected");
    let z = obs.t_cam_marker.translation.z;
    assert_eq!(obs.id, id);
    assert!(
        (z / distance_m - 1.0).abs() < 0.01,
        "distance {z} m, placed at {distance_m} m"
    );
}

/// A page read back from a file is the layout's size (mm).
fn assert_page_size(l: &Layout, page_mm: (f64, f64)) {
    assert!((page_mm.0 - l.page_w_mm).abs() < 1e-3 && (page_mm.1 - l.page_h_mm).abs() < 1e-3);
}

/// The page's black rectangles (mm) painted with exact area coverage into a camera
/// frame: the page is frontal at `distance_m`, its top-left corner at pixel (500, 400).
fn camera_view(rects_mm: &[[f64; 4]], page_mm: (f64, f64), distance_m: f64) -> Frame {
    let px_per_mm = F_PX / (distance_m * 1000.0);
    let mut buf = vec![BACKGROUND; W * H];
    let to_px = |r: [f64; 4]| {
        [
            500.0 + r[0] * px_per_mm,
            400.0 + r[1] * px_per_mm,
            r[2] * px_per_mm,
            r[3] * px_per_mm,
        ]
    };
    paint(
        &mut buf,
        to_px([0.0, 0.0, page_mm.0, page_mm.1]),
        WHITE - BACKGROUND,
    );
    for r in rects_mm {
        paint(&mut buf, to_px(*r), BLACK - WHITE);
    }
    Frame {
        width: W as u32,
        height: H as u32,
        data: buf
            .iter()
            .map(|v| v.round().clamp(0.0, 255.0) as u8)
            .collect(),
        ..Frame::default()
    }
}

/// Add `delta` x the area of pixel coverage of rectangle `r` (x, y, w, h in pixels;
/// pixel (i, j) covers [i, i+1) x [j, j+1)).
fn paint(buf: &mut [f64], r: [f64; 4], delta: f64) {
    let (x0, y0, x1, y1) = (r[0], r[1], r[0] + r[2], r[1] + r[3]);
    let span =
        |a: f64, b: f64, n: usize| (a.floor().max(0.0) as usize)..(b.ceil().min(n as f64) as usize);
    for py in span(y0, y1, H) {
        let cy = (y1.min(py as f64 + 1.0) - y0.max(py as f64)).max(0.0);
        for px in span(x0, x1, W) {
            let cx = (x1.min(px as f64 + 1.0) - x0.max(px as f64)).max(0.0);
            buf[py * W + px] += delta * cx * cy;
        }
    }
}

fn attr(tag: &str, name: &str) -> f64 {
    let key = format!(" {name}=\"");
    let start = tag.find(&key).unwrap() + key.len();
    let rest = &tag[start..];
    rest[..rest.find('"').unwrap()]
        .trim_end_matches("mm")
        .parse()
        .unwrap()
}

/// The SVG's page size (from width / height in mm, checked against the viewBox) and
/// its black rectangles, in mm.
fn parse_svg(s: &str) -> ((f64, f64), Vec<[f64; 4]>) {
    let svg_tag = &s[s.find("<svg ").unwrap()..];
    let svg_tag = &svg_tag[..svg_tag.find('>').unwrap()];
    assert!(svg_tag.contains("mm\" height=\""), "{svg_tag}");
    let (w, h) = (attr(svg_tag, "width"), attr(svg_tag, "height"));
    assert!(svg_tag.contains(&format!("viewBox=\"0 0 {} {}\"", num(w), num(h))));
    assert!(svg_tag.contains("shape-rendering=\"crispEdges\""));
    let g = &s[s.find("<g fill=\"#000\">").unwrap()..s.find("</g>").unwrap()];
    let rects = g
        .lines()
        .filter(|l| l.starts_with("<rect "))
        .map(|l| {
            [
                attr(l, "x"),
                attr(l, "y"),
                attr(l, "width"),
                attr(l, "height"),
            ]
        })
        .collect();
    ((w, h), rects)
}

/// The PDF's page size and filled rectangles, in mm from the top-left; checks that the
/// cross-reference table points at the objects.
fn parse_pdf(bytes: &[u8]) -> ((f64, f64), Vec<[f64; 4]>) {
    let s = std::str::from_utf8(&bytes[15..]).unwrap();
    let s = format!("{}{s}", " ".repeat(15));
    assert!(bytes.starts_with(b"%PDF-1.4\n"));
    let startxref: usize = s[s.rfind("startxref\n").unwrap() + 10..]
        .lines()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(s[startxref..].starts_with("xref\n0 6\n"));
    for (i, line) in s[startxref..].lines().skip(3).take(5).enumerate() {
        let off: usize = line[..10].parse().unwrap();
        assert!(
            s[off..].starts_with(&format!("{} 0 obj", i + 1)),
            "object {}",
            i + 1
        );
    }
    let stream = &s[s.find("stream\n").unwrap() + 7..s.find("endstream").unwrap()];
    let len: usize = s[s.find("/Length ").unwrap() + 8..]
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(len, stream.len());
    let mb = &s[s.find("/MediaBox [").unwrap() + 11..];
    let mb: Vec<f64> = mb[..mb.find(']').unwrap()]
        .split_whitespace()
        .map(|v| v.parse().unwrap())
        .collect();
    let (w, h) = (mb[2] / PT_PER_MM, mb[3] / PT_PER_MM);
    let rects = stream
        .lines()
        .filter(|l| l.ends_with(" re"))
        .map(|l| {
            let v: Vec<f64> = l
                .split_whitespace()
                .take(4)
                .map(|v| v.parse().unwrap())
                .collect();
            let [x, y, rw, rh] = [v[0], v[1], v[2], v[3]].map(|p| p / PT_PER_MM);
            [x, h - y - rh, rw, rh]
        })
        .collect();
    ((w, h), rects)
}

/// PNG chunks: (type, data), checking every CRC.
fn chunks(png: &[u8]) -> Vec<([u8; 4], Vec<u8>)> {
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));
    let mut out = Vec::new();
    let mut at = 8;
    while at < png.len() {
        let len = u32::from_be_bytes(png[at..at + 4].try_into().unwrap()) as usize;
        let kind: [u8; 4] = png[at + 4..at + 8].try_into().unwrap();
        let data = png[at + 8..at + 8 + len].to_vec();
        let crc = u32::from_be_bytes(png[at + 8 + len..at + 12 + len].try_into().unwrap());
        assert_eq!(crc, crc32(&png[at + 4..at + 8 + len]), "CRC of {kind:?}");
        out.push((kind, data));
        at += 12 + len;
    }
    out
}

fn decode(png: &[u8]) -> core::Mat {
    let buf = core::Vector::<u8>::from_slice(png);
    imgcodecs::imdecode(&buf, imgcodecs::IMREAD_GRAYSCALE).unwrap()
}

/// Bounding box (x0, y0, x1, y1), exclusive ends, of dark pixels in rows `r0..r1`.
fn dark_box(img: &core::Mat, r0: i32, r1: i32) -> (i32, i32, i32, i32) {
    let (mut x0, mut y0, mut x1, mut y1) = (i32::MAX, i32::MAX, 0, 0);
    for y in r0..r1 {
        let row = img.at_row::<u8>(y).unwrap();
        for (x, &p) in row.iter().enumerate() {
            if p < 128 {
                let x = x as i32;
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
            }
        }
    }
    (x0, y0, x1, y1)
}

#[test]
fn crc_matches_the_png_specification() {
    // The IEND chunk's CRC, as every PNG file ends.
    assert_eq!(crc32(b"IEND"), 0xAE42_6082);
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
}

#[test]
fn png_square_is_exact_and_phys_says_the_dpi() {
    let l = Layout::new(MarkerFamily::Aruco4x4_50, 3, 50.0).unwrap();
    let png = png(&l, 600.0).unwrap();
    let ch = chunks(&png);
    assert_eq!(&ch[0].0, b"IHDR");
    let phys: Vec<_> = ch.iter().filter(|c| &c.0 == b"pHYs").collect();
    assert_eq!(phys.len(), 1);
    let d = &phys[0].1;
    let ppm_x = u32::from_be_bytes(d[0..4].try_into().unwrap());
    let ppm_y = u32::from_be_bytes(d[4..8].try_into().unwrap());
    assert_eq!((ppm_x, ppm_y, d[8]), (23622, 23622, 1));
    assert!((f64::from(ppm_x) * 0.0254 - 600.0).abs() < 0.01);

    let img = decode(&png);
    let ppmm = 600.0 / 25.4;
    assert_eq!(img.cols(), (l.page_w_mm * ppmm).round() as i32);
    // Only the paper square above the caption.
    let paper_rows = ((l.size_mm + 2.0 * l.quiet_mm) * ppmm) as i32;
    let (x0, y0, x1, y1) = dark_box(&img, 0, paper_rows);
    let want = 50.0 * ppmm;
    assert!(
        (f64::from(x1 - x0) - want).abs() <= 1.0,
        "{} vs {want}",
        x1 - x0
    );
    assert!(
        (f64::from(y1 - y0) - want).abs() <= 1.0,
        "{} vs {want}",
        y1 - y0
    );
    // The quiet zone: at least QUIET_MODULES modules of white each side.
    let quiet = (QUIET_MODULES * want / 6.0).floor() as i32;
    assert!(
        y0 >= quiet && x0 >= quiet && img.cols() - x1 >= quiet,
        "{x0} {y0} {x1}"
    );
    // The caption is below the quiet zone.
    let caption = dark_box(&img, paper_rows, img.rows());
    assert!(
        caption.1 >= y1 + quiet && caption.3 > caption.1,
        "{caption:?}"
    );
}

#[test]
fn png_in_front_of_a_camera_decodes_and_measures_its_size() {
    let (family, id, size_mm, dpi, distance_m) =
        (MarkerFamily::AprilTag36h11, 7, 150.0, 300.0, 1.3);
    let l = Layout::new(family, id, size_mm).unwrap();
    let img = decode(&png(&l, dpi).unwrap());
    // One PNG pixel is 25.4 / dpi mm on paper.
    let scale = F_PX * (25.4 / dpi) / 1000.0 / distance_m;
    let mut small = core::Mat::default();
    imgproc::resize(
        &img,
        &mut small,
        core::Size::default(),
        scale,
        scale,
        imgproc::INTER_AREA,
    )
    .unwrap();
    let mut buf = vec![BACKGROUND; W * H];
    for y in 0..small.rows() {
        for (x, &p) in small.at_row::<u8>(y).unwrap().iter().enumerate() {
            let v = BLACK + (WHITE - BLACK) * f64::from(p) / 255.0;
            buf[(y as usize + 200) * W + x + 300] = v;
        }
    }
    let frame = Frame {
        width: W as u32,
        height: H as u32,
        data: buf.iter().map(|v| v.round() as u8).collect(),
        ..Frame::default()
    };
    assert_seen_at(&frame, family, id, size_mm, distance_m);
}

#[test]
fn svg_in_front_of_a_camera_decodes_and_measures_its_size() {
    let (family, id, size_mm, distance_m) = (MarkerFamily::Aruco5x5_100, 42, 200.0, 1.7);
    let l = Layout::new(family, id, size_mm).unwrap();
    let s = svg(&l);
    assert!(
        s.contains("black square 200 mm") && s.contains("aruco_5x5_100 id 42"),
        "{s}"
    );
    let (page, rects) = parse_svg(&s);
    assert_page_size(&l, page);
    // Row runs are merged: fewer rects than black modules.
    let black = l.bitmap.white.iter().filter(|w| !**w).count();
    assert!(
        rects.len() < black,
        "{} rects for {black} modules",
        rects.len()
    );
    let frame = camera_view(&rects, page, distance_m);
    assert_seen_at(&frame, family, id, size_mm, distance_m);
}

#[test]
fn pdf_in_front_of_a_camera_decodes_and_measures_its_size() {
    let (family, id, size_mm, distance_m) = (MarkerFamily::AprilTag25h9, 11, 120.0, 0.9);
    let l = Layout::new(family, id, size_mm).unwrap();
    let bytes = pdf(&l);
    let text = String::from_utf8_lossy(&bytes);
    assert!(text.contains("/BaseFont /Helvetica") && text.contains("(apriltag_25h9 id 11) Tj"));
    let (page, rects) = parse_pdf(&bytes);
    assert_page_size(&l, page);
    let frame = camera_view(&rects, page, distance_m);
    assert_seen_at(&frame, family, id, size_mm, distance_m);
}

#[test]
fn bad_values_name_the_flag_and_the_value() {
    let e = |r: anyhow::Result<Layout>| format!("{:#}", r.unwrap_err());
    let m = e(Layout::new(MarkerFamily::Aruco4x4_50, 50, 100.0));
    assert!(m.contains("--id 50") && m.contains("0..50"), "{m}");
    for bad in [0.0, -5.0, f64::NAN] {
        let m = e(Layout::new(MarkerFamily::Aruco4x4_50, 1, bad));
        assert!(m.contains(&format!("--size-mm {bad}")), "{m}");
    }
    let m = format!("{:#}", Format::of(Path::new("tag.jpg")).unwrap_err());
    assert!(
        m.contains("--out tag.jpg") && m.contains(".svg, .pdf or .png"),
        "{m}"
    );
    assert!(Format::of(Path::new("tag")).is_err());
    assert_eq!(Format::of(Path::new("a/T.PNG")).unwrap(), Format::Png);
    let l = Layout::new(MarkerFamily::Aruco4x4_50, 1, 100.0).unwrap();
    let m = format!("{:#}", png(&l, 0.0).unwrap_err());
    assert!(m.contains("--dpi 0"), "{m}");
    let big = Layout::new(MarkerFamily::Aruco4x4_50, 1, 5000.0).unwrap();
    let m = format!("{:#}", png(&big, 600.0).unwrap_err());
    assert!(m.contains("--dpi 600") && m.contains(".svg"), "{m}");
}

#[test]
fn small_markers_widen_the_page_for_the_caption() {
    let l = Layout::new(MarkerFamily::Aruco4x4_50, 0, 20.0).unwrap();
    let paper = l.size_mm + 2.0 * l.quiet_mm;
    assert!(l.page_w_mm > paper);
    assert!(
        (l.marker_x_mm * 2.0 + l.size_mm - l.page_w_mm).abs() < 1e-9,
        "centred"
    );
    assert!(l
        .caption
        .iter()
        .all(|(_, _, y)| *y > paper && *y < l.page_h_mm));
}
