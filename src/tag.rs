//! `markhold tag`: a printable marker at exact physical size, as SVG, PDF or PNG.
//!
//! The modules come from [`markhold_vision::marker_bitmap`] (the bitmap the detector
//! decodes and the HIL camera renders). `size_mm` is the edge of the black square (the
//! outer edge of the black border module), the length the site file's `marker.size_m`
//! gives the pose estimate. Around the black square is a white quiet zone of
//! [`QUIET_MODULES`] modules; the caption (family, id, size) is printed below it.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context};
use markhold_vision::{marker_bitmap, MarkerBitmap, MarkerFamily};
use opencv::{core, imgcodecs, imgproc, prelude::*};

/// White quiet zone around the black square, in modules, each side. OpenCV's aruco
/// detector finds the black square as a closed contour of its adaptive threshold, so
/// the black border needs white paper all round it; AprilTag's own printed layout has
/// one white module too. One module keeps a 150 mm marker (the shipped sites) with its
/// caption on A4 or Letter paper.
pub const QUIET_MODULES: f64 = 1.0;

/// Default PNG resolution, dots per inch.
pub const DEFAULT_DPI: f64 = 600.0;

/// Largest PNG side, pixels (a bigger marker: lower `--dpi`, or SVG / PDF).
const MAX_PNG_SIDE_PX: f64 = 30_000.0;

/// Average advance of a caption character, in em (Helvetica is about 0.55).
const CHAR_EM: f64 = 0.6;

/// Millimetres per inch.
const MM_PER_INCH: f64 = 25.4;

#[derive(clap::Args, Debug)]
pub struct TagArgs {
    /// Marker family (apriltag_36h11, aruco_4x4_50, ...).
    #[arg(long, required_unless_present = "site", conflicts_with = "site")]
    pub family: Option<String>,
    /// Marker id in the family.
    #[arg(long, required_unless_present = "site", conflicts_with = "site")]
    pub id: Option<u32>,
    /// Edge of the black square (outer edge of the black border), millimetres: what
    /// the site's `marker.size_m` means.
    #[arg(
        long,
        required_unless_present = "site",
        conflicts_with = "site",
        allow_negative_numbers = true
    )]
    pub size_mm: Option<f64>,
    /// Take family, id and size from this site file's [marker] section.
    #[arg(long, value_name = "FILE")]
    pub site: Option<PathBuf>,
    /// Output file: .svg, .pdf or .png.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// PNG resolution, dots per inch (written in the PNG's pHYs chunk).
    #[arg(long, default_value_t = DEFAULT_DPI, allow_negative_numbers = true)]
    pub dpi: f64,
}

/// Output formats, from the file's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Svg,
    Pdf,
    Png,
}

impl Format {
    /// The format of `path`, or an error naming `--out` and the path.
    pub fn of(path: &Path) -> anyhow::Result<Format> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("svg") => Ok(Format::Svg),
            Some("pdf") => Ok(Format::Pdf),
            Some("png") => Ok(Format::Png),
            _ => bail!(
                "--out {}: expected a file ending in .svg, .pdf or .png",
                path.display()
            ),
        }
    }
}

/// The page, in millimetres from its top-left corner.
#[derive(Debug, Clone)]
pub struct Layout {
    pub family: MarkerFamily,
    pub id: u32,
    pub bitmap: MarkerBitmap,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// Edge of one module, mm.
    pub module_mm: f64,
    /// Width of the white quiet zone, mm.
    pub quiet_mm: f64,
    pub page_w_mm: f64,
    pub page_h_mm: f64,
    /// Top-left corner of the black square, mm.
    pub marker_x_mm: f64,
    pub marker_y_mm: f64,
    /// Caption font size (em), mm.
    pub font_mm: f64,
    /// Caption lines with their left edge and baseline, mm.
    pub caption: Vec<(String, f64, f64)>,
}

impl Layout {
    /// The page of `id` in `family` with a black square of `size_mm`; errors name the
    /// flag and the value.
    pub fn new(family: MarkerFamily, id: u32, size_mm: f64) -> anyhow::Result<Layout> {
        ensure!(
            size_mm.is_finite() && size_mm > 0.0 && size_mm <= 10_000.0,
            "--size-mm {size_mm}: expected a size > 0 and <= 10000 millimetres"
        );
        let n = family.id_count();
        ensure!(id < n, "--id {id}: expected an id of {family} in 0..{n}");
        let bitmap =
            marker_bitmap(family, id).with_context(|| format!("drawing {family} id {id}"))?;
        let module_mm = size_mm / bitmap.cells as f64;
        let quiet_mm = QUIET_MODULES * module_mm;
        let paper_mm = size_mm + 2.0 * quiet_mm;
        let lines = [
            format!("{family} id {id}"),
            format!("black square {} mm, print at 100 %", num(size_mm)),
        ];
        let chars = lines.iter().map(|l| l.chars().count()).max().unwrap_or(1) as f64;
        let font_mm = (paper_mm / (chars * CHAR_EM + 2.0)).clamp(2.5, 8.0);
        let text_w = chars * CHAR_EM * font_mm;
        let page_w_mm = paper_mm.max(text_w + 2.0 * font_mm);
        let marker_x_mm = (page_w_mm - size_mm) / 2.0;
        let text_x = if marker_x_mm + text_w <= page_w_mm {
            marker_x_mm
        } else {
            font_mm
        };
        let first = paper_mm + 1.2 * font_mm;
        let caption = caption_lines(lines, text_x, first, font_mm);
        Ok(Layout {
            family,
            id,
            bitmap,
            size_mm,
            module_mm,
            quiet_mm,
            page_w_mm,
            page_h_mm: first + 1.4 * font_mm + 0.8 * font_mm,
            marker_x_mm,
            marker_y_mm: quiet_mm,
            font_mm,
            caption,
        })
    }

    /// Black runs of modules: (row, first column, length), row by row.
    pub fn black_runs(&self) -> Vec<(usize, usize, usize)> {
        let n = self.bitmap.cells;
        let mut runs = Vec::new();
        for r in 0..n {
            let mut c = 0;
            while c < n {
                if self.bitmap.is_white(r, c) {
                    c += 1;
                    continue;
                }
                let start = c;
                while c < n && !self.bitmap.is_white(r, c) {
                    c += 1;
                }
                runs.push((r, start, c - start));
            }
        }
        runs
    }

    /// Black rectangles in mm: (x, y, width, height) from the page's top-left.
    pub fn black_rects_mm(&self) -> Vec<[f64; 4]> {
        let m = self.module_mm;
        self.black_runs()
            .into_iter()
            .map(|(r, c, len)| {
                [
                    self.marker_x_mm + c as f64 * m,
                    self.marker_y_mm + r as f64 * m,
                    len as f64 * m,
                    m,
                ]
            })
            .collect()
    }
}

/// A number for a document: up to 4 decimals, no trailing zeros.
fn num(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".to_string()
    } else {
        s.to_string()
    }
}

/// The page as SVG: physical size in mm, a viewBox in mm, one rect per black run.
pub fn svg(l: &Layout) -> String {
    let title = format!(
        "{} id {}, black square {} mm",
        l.family,
        l.id,
        num(l.size_mm)
    );
    let desc = format!(
        "Units are millimetres. The black square (outer edge of the black border) is {} mm: \
         the site file's marker.size_m = {}. White quiet zone {} mm. Print at 100 %.",
        num(l.size_mm),
        num(l.size_mm / 1000.0),
        num(l.quiet_mm)
    );
    l.page().svg(&title, &desc, |s| {
        for [x, y, rw, rh] in l.black_rects_mm() {
            let _ = writeln!(
                s,
                r#"<rect x="{}" y="{}" width="{}" height="{}"/>"#,
                num(x),
                num(y),
                num(rw),
                num(rh)
            );
        }
    })
}

/// The caption's lines at `x` mm, the first at `first_mm`, the others 1.4 font sizes
/// apart.
fn caption_lines<const N: usize>(
    lines: [String; N],
    x: f64,
    first_mm: f64,
    font_mm: f64,
) -> Vec<(String, f64, f64)> {
    lines
        .into_iter()
        .enumerate()
        .map(|(i, l)| (l, x, first_mm + 1.4 * font_mm * i as f64))
        .collect()
}

/// What the marker's and the target's pages share: the page's size, mm, and the caption
/// (its lines at their places, mm from the top-left, and its font size).
struct Page<'a> {
    w_mm: f64,
    h_mm: f64,
    font_mm: f64,
    caption: &'a [(String, f64, f64)],
}

impl<'a> Page<'a> {
    fn new(w_mm: f64, h_mm: f64, font_mm: f64, caption: &'a [(String, f64, f64)]) -> Self {
        Page {
            w_mm,
            h_mm,
            font_mm,
            caption,
        }
    }

    /// The page as SVG with `title` and `desc` (as they are written, XML-escaped), the
    /// black shapes `black` writes over a white page, and the caption.
    fn svg(&self, title: &str, desc: &str, black: impl FnOnce(&mut String)) -> String {
        let (w, h) = (num(self.w_mm), num(self.h_mm));
        let mut s = String::new();
        let _ = writeln!(s, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}mm" height="{h}mm" viewBox="0 0 {w} {h}" shape-rendering="crispEdges">"#
        );
        let _ = writeln!(s, "<title>{title}</title>");
        let _ = writeln!(s, "<desc>{desc}</desc>");
        let _ = writeln!(
            s,
            r##"<rect x="0" y="0" width="{w}" height="{h}" fill="#fff"/>"##
        );
        let _ = writeln!(s, r##"<g fill="#000">"##);
        black(&mut s);
        let _ = writeln!(s, "</g>");
        for (text, x, y) in self.caption {
            let _ = writeln!(
                s,
                r##"<text x="{}" y="{}" font-family="Helvetica, Arial, sans-serif" font-size="{}" fill="#000">{}</text>"##,
                num(*x),
                num(*y),
                num(self.font_mm),
                xml_escape(text)
            );
        }
        s.push_str("</svg>\n");
        s
    }

    /// The page as a PDF: `content` (the black shapes, filled, in points from the
    /// bottom-left), then the caption in Helvetica.
    fn pdf(&self, mut content: String) -> Vec<u8> {
        let k = PT_PER_MM;
        for (text, x, y) in self.caption {
            let _ = writeln!(
                content,
                "BT /F1 {} Tf {} {} Td ({}) Tj ET",
                num(self.font_mm * k),
                num(x * k),
                num((self.h_mm - y) * k),
                pdf_escape(text)
            );
        }
        pdf_document(self.w_mm, self.h_mm, &content)
    }

    /// A white 8-bit grey image of the page at `dpi`, and its pixels per mm; an error for
    /// a resolution out of range or a PNG too large.
    fn png_canvas(&self, dpi: f64) -> anyhow::Result<(core::Mat, f64)> {
        ensure!(
            dpi.is_finite() && (72.0..=4800.0).contains(&dpi),
            "--dpi {dpi}: expected a resolution in 72..=4800 dots per inch"
        );
        let ppmm = dpi / MM_PER_INCH;
        let (w, h) = (self.w_mm * ppmm, self.h_mm * ppmm);
        ensure!(
            w.max(h) <= MAX_PNG_SIDE_PX,
            "--dpi {dpi}: the PNG would be {w:.0} x {h:.0} px (at most {MAX_PNG_SIDE_PX:.0} a \
             side); use a lower --dpi or .svg / .pdf"
        );
        let img = core::Mat::new_rows_cols_with_default(
            h.round() as i32,
            w.round() as i32,
            core::CV_8UC1,
            core::Scalar::all(255.0),
        )
        .context("allocating the PNG image")?;
        Ok((img, ppmm))
    }

    /// `img` (from [`Page::png_canvas`]) with the caption, as a PNG with its resolution.
    fn png(&self, mut img: core::Mat, ppmm: f64, dpi: f64) -> anyhow::Result<Vec<u8>> {
        draw_caption(&mut img, self.caption, self.font_mm, self.w_mm, ppmm)?;
        let mut buf = core::Vector::<u8>::new();
        imgcodecs::imencode(".png", &img, &mut buf, &core::Vector::new())
            .context("encoding the PNG")?;
        with_phys(&buf.to_vec(), dpi)
    }
}

impl Layout {
    fn page(&self) -> Page<'_> {
        Page::new(self.page_w_mm, self.page_h_mm, self.font_mm, &self.caption)
    }
}

fn xml_escape(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Points per millimetre (1 pt = 1/72 inch).
pub const PT_PER_MM: f64 = 72.0 / MM_PER_INCH;

/// The page as a single-page PDF 1.4: the page is the layout's size, the black runs
/// are filled rectangles, the caption is in the standard Helvetica font.
pub fn pdf(l: &Layout) -> Vec<u8> {
    let k = PT_PER_MM;
    let mut content = String::from("0 g\n");
    for [x, y, w, h] in l.black_rects_mm() {
        // PDF's origin is the bottom-left corner.
        let _ = writeln!(
            content,
            "{} {} {} {} re",
            num(x * k),
            num((l.page_h_mm - y - h) * k),
            num(w * k),
            num(h * k)
        );
    }
    content.push_str("f\n");
    l.page().pdf(content)
}

/// A one-page PDF 1.4 of `page_w_mm` x `page_h_mm` whose page is `content` (a content
/// stream in points), with Helvetica as font /F1.
fn pdf_document(page_w_mm: f64, page_h_mm: f64, content: &str) -> Vec<u8> {
    let k = PT_PER_MM;
    let objects = [
        "<< /Type /Catalog /Pages 2 0 R >>".to_string(),
        "<< /Type /Pages /Kids [3 0 R] /Count 1 >>".to_string(),
        format!(
            "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {} {}] /Contents 4 0 R \
             /Resources << /Font << /F1 5 0 R >> >> >>",
            num(page_w_mm * k),
            num(page_h_mm * k)
        ),
        format!(
            "<< /Length {} >>\nstream\n{content}endstream",
            content.len()
        ),
        "<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>"
            .to_string(),
    ];
    let mut out = b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n".to_vec();
    let mut offsets = Vec::with_capacity(objects.len());
    for (i, body) in objects.iter().enumerate() {
        offsets.push(out.len());
        out.extend_from_slice(format!("{} 0 obj\n{body}\nendobj\n", i + 1).as_bytes());
    }
    let xref = out.len();
    let mut tail = format!("xref\n0 {}\n0000000000 65535 f \n", objects.len() + 1);
    for o in offsets {
        let _ = writeln!(tail, "{o:010} 00000 n ");
    }
    let _ = write!(
        tail,
        "trailer\n<< /Size {} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n",
        objects.len() + 1
    );
    out.extend_from_slice(tail.as_bytes());
    out
}

fn pdf_escape(t: &str) -> String {
    t.replace('\\', "\\\\")
        .replace('(', "\\(")
        .replace(')', "\\)")
}

/// The page as an 8-bit grey PNG at `dpi`, with the resolution in its pHYs chunk.
/// The black square is `round(size_mm * dpi / 25.4)` pixels; module edges are rounded
/// to whole pixels, so modules differ by at most one pixel.
pub fn png(l: &Layout, dpi: f64) -> anyhow::Result<Vec<u8>> {
    let (mut img, ppmm) = l.page().png_canvas(dpi)?;
    let cells = l.bitmap.cells as i64;
    let side = (l.size_mm * ppmm).round() as i64;
    let (x0, y0) = (
        (l.marker_x_mm * ppmm).round() as i64,
        (l.marker_y_mm * ppmm).round() as i64,
    );
    // Edge of module boundary i, pixels from the square's corner.
    let edge = |i: i64| (i * side + cells / 2) / cells;
    for (r, c, len) in l.black_runs() {
        let (r, c, len) = (r as i64, c as i64, len as i64);
        let rect = core::Rect::new(
            (x0 + edge(c)) as i32,
            (y0 + edge(r)) as i32,
            (edge(c + len) - edge(c)) as i32,
            (edge(r + 1) - edge(r)) as i32,
        );
        fill_black(&mut img, rect).context("drawing a module")?;
    }
    l.page().png(img, ppmm, dpi)
}

/// `rect` of `img` black.
fn fill_black(img: &mut core::Mat, rect: core::Rect) -> opencv::Result<()> {
    let black = core::Scalar::all(0.0);
    imgproc::rectangle(img, rect, black, imgproc::FILLED, imgproc::LINE_8, 0)
}

/// The caption with OpenCV's Hershey font, cap height about that of Helvetica at the
/// layout's font size, narrowed if it would leave the page.
fn draw_caption(
    img: &mut core::Mat,
    caption: &[(String, f64, f64)],
    font_mm: f64,
    page_w_mm: f64,
    ppmm: f64,
) -> anyhow::Result<()> {
    let font = imgproc::FONT_HERSHEY_SIMPLEX;
    let cap_px = 0.72 * font_mm * ppmm;
    let thickness = ((cap_px / 12.0).round() as i32).max(1);
    let mut base = 0;
    for (text, x, y) in caption {
        let size = imgproc::get_text_size(text, font, 1.0, thickness, &mut base)
            .context("measuring the caption")?;
        let mut scale = cap_px / f64::from(size.height.max(1));
        let room = (page_w_mm - x) * ppmm;
        if f64::from(size.width) * scale > room {
            scale = room / f64::from(size.width.max(1));
        }
        let org = core::Point::new((x * ppmm).round() as i32, (y * ppmm).round() as i32);
        imgproc::put_text(
            img,
            text,
            org,
            font,
            scale,
            core::Scalar::all(0.0),
            thickness,
            imgproc::LINE_AA,
            false,
        )
        .context("drawing the caption")?;
    }
    Ok(())
}

/// `png` with a pHYs chunk (pixels per metre, both axes) right after IHDR. OpenCV's
/// encoder writes none.
pub fn with_phys(png: &[u8], dpi: f64) -> anyhow::Result<Vec<u8>> {
    const SIG: &[u8] = b"\x89PNG\r\n\x1a\n";
    // Signature, then IHDR: length (4), type (4), 13 bytes of data, CRC (4).
    let ihdr_end = SIG.len() + 4 + 4 + 13 + 4;
    ensure!(
        png.len() > ihdr_end && png.starts_with(SIG) && &png[12..16] == b"IHDR",
        "the PNG encoder wrote no IHDR chunk first"
    );
    let ppm = (dpi * 1000.0 / MM_PER_INCH).round() as u32;
    let mut chunk = Vec::with_capacity(21);
    chunk.extend_from_slice(&9u32.to_be_bytes());
    chunk.extend_from_slice(b"pHYs");
    chunk.extend_from_slice(&ppm.to_be_bytes());
    chunk.extend_from_slice(&ppm.to_be_bytes());
    chunk.push(1); // unit: metre
    let crc = crc32(&chunk[4..]);
    chunk.extend_from_slice(&crc.to_be_bytes());
    let mut out = Vec::with_capacity(png.len() + chunk.len());
    out.extend_from_slice(&png[..ihdr_end]);
    out.extend_from_slice(&chunk);
    out.extend_from_slice(&png[ihdr_end..]);
    Ok(out)
}

/// CRC-32 of PNG (ISO 3309, reflected polynomial 0xEDB88320), over type and data.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// The file's bytes for `layout` in `format`.
pub fn render(l: &Layout, format: Format, dpi: f64) -> anyhow::Result<Vec<u8>> {
    Ok(match format {
        Format::Svg => svg(l).into_bytes(),
        Format::Pdf => pdf(l),
        Format::Png => png(l, dpi)?,
    })
}

/// `markhold tag`.
/// One marker to print: family, id, black square (mm), where it goes and, for a map,
/// where it sits in the site frame.
struct Job {
    family: MarkerFamily,
    id: u32,
    size_mm: f64,
    out: PathBuf,
    /// The site file's key that gives the size.
    key: String,
    place: Option<String>,
}

/// `out` with `-id<ID>` before its extension (`dock.svg` -> `dock-id3.svg`).
pub fn per_marker_path(out: &Path, id: u32) -> PathBuf {
    let stem = out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let ext = out
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    out.with_file_name(format!("{stem}-id{id}{ext}"))
}

/// The markers `args` asks for: one, or with `--site` every marker of the site's map
/// (a map of more than one: one file per marker, `--out` with `-id<ID>` added).
fn jobs(args: &TagArgs) -> anyhow::Result<Vec<Job>> {
    let Some(path) = &args.site else {
        let (Some(family), Some(id), Some(size_mm)) = (&args.family, args.id, args.size_mm) else {
            bail!("--family, --id and --size-mm are needed without --site");
        };
        let family: MarkerFamily = family
            .parse()
            .map_err(|e| anyhow::anyhow!("--family {family}: {e}"))?;
        return Ok(vec![Job {
            family,
            id,
            size_mm,
            out: args.out.clone(),
            key: "marker.size_m".to_string(),
            place: None,
        }]);
    };
    let site = crate::params::load(path)?;
    let m = &site.site.marker;
    if m.map.is_empty() {
        return Ok(vec![Job {
            family: m.family,
            id: m.id,
            size_mm: m.size_m * 1000.0,
            out: args.out.clone(),
            key: "marker.size_m".to_string(),
            place: None,
        }]);
    }
    let origin = Job {
        family: m.family,
        id: m.id,
        size_mm: m.size_m * 1000.0,
        out: per_marker_path(&args.out, m.id),
        key: "marker.size_m".to_string(),
        place: Some("the origin of the site frame".to_string()),
    };
    let others = m.map.iter().enumerate().map(|(i, e)| {
        let [x, y, z] = e.position_m.map(num);
        let [r, p, w] = e.rpy_deg.map(num);
        Job {
            family: m.family,
            id: e.id,
            size_mm: e.size_m * 1000.0,
            out: per_marker_path(&args.out, e.id),
            key: format!("marker.map[{i}].size_m"),
            place: Some(format!(
                "marker.map[{i}]: centre at [{x}, {y}, {z}] m, rpy [{r}, {p}, {w}] deg in the site frame"
            )),
        }
    });
    Ok(std::iter::once(origin).chain(others).collect())
}

pub fn cli(args: TagArgs) -> anyhow::Result<()> {
    let format = Format::of(&args.out)?;
    let jobs = jobs(&args)?;
    // Every marker laid out and rendered before any file is written: a bad one leaves
    // no partial set behind.
    let mut done = Vec::with_capacity(jobs.len());
    for job in &jobs {
        let layout = Layout::new(job.family, job.id, job.size_mm)?;
        let bytes = render(&layout, format, args.dpi)?;
        done.push((layout, bytes));
    }
    for (job, (layout, bytes)) in jobs.iter().zip(done) {
        std::fs::write(&job.out, bytes)
            .with_context(|| format!("writing --out {}", job.out.display()))?;
        let res = if format == Format::Png {
            format!(" at {} dpi", num(args.dpi))
        } else {
            String::new()
        };
        let place = job
            .place
            .as_ref()
            .map_or(String::new(), |p| format!("; placed at {p}"));
        crate::outln!(
            "markhold tag: {}: {} id {}, black square {} mm ({} = {}), \
             quiet zone {} mm, page {} x {} mm{res}; print at 100 % and measure the black square{place}",
            job.out.display(),
            job.family,
            job.id,
            num(job.size_mm),
            job.key,
            num(job.size_mm / 1000.0),
            num(layout.quiet_mm),
            num(layout.page_w_mm),
            num(layout.page_h_mm),
        );
    }
    Ok(())
}

/// White margin around a printed calibration target, mm.
pub const BOARD_MARGIN_MM: f64 = 10.0;

/// A calibration target's page: black polygons (mm from the page's top-left, y down)
/// and a caption.
#[derive(Debug, Clone)]
pub struct BoardPage {
    pub page_w_mm: f64,
    pub page_h_mm: f64,
    /// Each black area as its corners, mm.
    pub polygons: Vec<[[f64; 2]; 4]>,
    pub font_mm: f64,
    pub caption: Vec<(String, f64, f64)>,
    pub title: String,
}

impl BoardPage {
    /// The page of `target`: its layout ([`markhold_vision::calibration::board::Target::layout`])
    /// inside a white margin, the caption below.
    pub fn new(target: &markhold_vision::calibration::board::Target) -> anyhow::Result<Self> {
        let layout = target
            .layout()
            .map_err(|e| anyhow::anyhow!("{e}"))
            .context("laying out the target")?;
        let m = BOARD_MARGIN_MM;
        let mut polygons = Vec::new();
        let rect =
            |x: f64, y: f64, w: f64, h: f64| [[x, y], [x + w, y], [x + w, y + h], [x, y + h]];
        for [x, y, side] in &layout.squares {
            polygons.push(rect(m + x * 1e3, m + y * 1e3, side * 1e3, side * 1e3));
        }
        for pm in &layout.markers {
            let Some(family) = layout.family else { break };
            let bitmap = marker_bitmap(family, pm.id)
                .with_context(|| format!("drawing {family} id {}", pm.id))?;
            let n = bitmap.cells;
            let module = pm.size_m * 1e3 / n as f64;
            let (x0, y0) = (m + pm.x_m * 1e3, m + pm.y_m * 1e3);
            let half = pm.size_m * 1e3 / 2.0;
            let (cx, cy) = (x0 + half, y0 + half);
            // Counter-clockwise as printed: y runs down the page.
            let (sn, cs) = pm.turn_deg.to_radians().sin_cos();
            let turn = |p: [f64; 2]| {
                let (dx, dy) = (p[0] - cx, p[1] - cy);
                [cx + cs * dx + sn * dy, cy - sn * dx + cs * dy]
            };
            for r in 0..n {
                let mut c = 0;
                while c < n {
                    if bitmap.is_white(r, c) {
                        c += 1;
                        continue;
                    }
                    let start = c;
                    while c < n && !bitmap.is_white(r, c) {
                        c += 1;
                    }
                    let q = rect(
                        x0 + start as f64 * module,
                        y0 + r as f64 * module,
                        (c - start) as f64 * module,
                        module,
                    );
                    polygons.push(q.map(turn));
                }
            }
        }
        let title = target.describe();
        let lines = [
            title.clone(),
            "print at 100 % on a flat, rigid sheet; measure a square or marker and check it"
                .to_string(),
        ];
        let board_w = layout.width_m * 1e3 + 2.0 * m;
        let chars = lines.iter().map(|l| l.chars().count()).max().unwrap_or(1) as f64;
        let font_mm = (board_w / (chars * CHAR_EM + 2.0)).clamp(2.5, 6.0);
        let first = layout.height_m * 1e3 + 2.0 * m + 1.2 * font_mm;
        let caption = caption_lines(lines, m, first, font_mm);
        Ok(BoardPage {
            page_w_mm: board_w.max(chars * CHAR_EM * font_mm + 2.0 * m),
            page_h_mm: first + 1.4 * font_mm + 0.8 * font_mm,
            polygons,
            font_mm,
            caption,
            title,
        })
    }

    pub fn svg(&self) -> String {
        let title = xml_escape(&self.title);
        let desc = "Units are millimetres. Print at 100 %.";
        self.page().svg(&title, desc, |s| {
            for q in &self.polygons {
                let pts: Vec<String> = q
                    .iter()
                    .map(|p| format!("{},{}", num(p[0]), num(p[1])))
                    .collect();
                let _ = writeln!(s, r#"<polygon points="{}"/>"#, pts.join(" "));
            }
        })
    }

    fn page(&self) -> Page<'_> {
        Page::new(self.page_w_mm, self.page_h_mm, self.font_mm, &self.caption)
    }

    pub fn pdf(&self) -> Vec<u8> {
        let k = PT_PER_MM;
        let mut content = String::from("0 g\n");
        for q in &self.polygons {
            for (i, p) in q.iter().enumerate() {
                let _ = writeln!(
                    content,
                    "{} {} {}",
                    num(p[0] * k),
                    num((self.page_h_mm - p[1]) * k),
                    if i == 0 { "m" } else { "l" }
                );
            }
            content.push_str("h\n");
        }
        content.push_str("f\n");
        self.page().pdf(content)
    }

    /// An 8-bit grey PNG at `dpi` (pHYs set): squares and modules with their edges on
    /// the nearest pixel boundary (turned markers' modules to 1/256 pixel).
    pub fn png(&self, dpi: f64) -> anyhow::Result<Vec<u8>> {
        let (mut img, ppmm) = self.page().png_canvas(dpi)?;
        const SHIFT: i32 = 8;
        let sub = f64::from(1 << SHIFT);
        for q in &self.polygons {
            let aligned = q[0][1] == q[1][1] && q[1][0] == q[2][0] && q[2][1] == q[3][1];
            if aligned {
                // Pixel i covers [i, i+1): an edge at x mm falls on the pixel boundary
                // nearest x * ppmm, so neighbouring areas share their boundaries.
                let (x0, x1) = ((q[0][0] * ppmm).round(), (q[1][0] * ppmm).round());
                let (y0, y1) = ((q[0][1] * ppmm).round(), (q[2][1] * ppmm).round());
                let rect =
                    core::Rect::new(x0 as i32, y0 as i32, (x1 - x0) as i32, (y1 - y0) as i32);
                if rect.width > 0 && rect.height > 0 {
                    fill_black(&mut img, rect).context("drawing the target")?;
                }
                continue;
            }
            // A turned marker's module: OpenCV fills the pixels whose centres (at i + 0.5)
            // are inside, to 1/256 pixel.
            let pts: core::Vector<core::Point> = q
                .iter()
                .map(|p| {
                    core::Point::new(
                        ((p[0] * ppmm - 0.5) * sub).round() as i32,
                        ((p[1] * ppmm - 0.5) * sub).round() as i32,
                    )
                })
                .collect();
            imgproc::fill_convex_poly(
                &mut img,
                &pts,
                core::Scalar::all(0.0),
                imgproc::LINE_8,
                SHIFT,
            )
            .context("drawing the target")?;
        }
        self.page().png(img, ppmm, dpi)
    }
}

/// `markhold calibrate --print-target`: the target's page in the format of `path`'s
/// extension.
pub fn write_board(
    target: &markhold_vision::calibration::board::Target,
    path: &Path,
    dpi: f64,
) -> anyhow::Result<()> {
    let format = Format::of(path)
        .map_err(|e| anyhow::anyhow!("{}", e.to_string().replace("--out", "--print-target")))?;
    let page = BoardPage::new(target)?;
    let bytes = match format {
        Format::Svg => page.svg().into_bytes(),
        Format::Pdf => page.pdf(),
        Format::Png => page.png(dpi)?,
    };
    std::fs::write(path, bytes)
        .with_context(|| format!("writing --print-target {}", path.display()))?;
    crate::outln!(
        "markhold calibrate: {}: {}, page {} x {} mm; print at 100 % on a flat, rigid sheet and \
         measure it",
        path.display(),
        page.title,
        num(page.page_w_mm),
        num(page.page_h_mm)
    );
    Ok(())
}

#[cfg(test)]
mod tests;
