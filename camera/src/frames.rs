//! `frames:DIR` cameras: recorded frames (a folder of PNGs with a sidecar) read back
//! through OpenCV's imgcodecs, and the recorder that writes them.

use crate::cv::{mat_to_frame, CvContext};
use crate::{Camera, CameraError, ExposureLimits, Frame, FrameMeta};
use opencv::{core, imgcodecs, prelude::*};
use std::io::Read;
use std::path::{Path, PathBuf};

/// Name of the sidecar in a recording folder.
pub const SIDECAR: &str = "frames.csv";
/// The largest image file of a recording folder read.
pub const MAX_IMAGE_FILE_BYTES: u64 = 64 << 20;
/// The largest image side decoded, pixels.
pub const MAX_IMAGE_SIDE: u32 = 8192;
/// The largest sidecar read.
const MAX_SIDECAR_BYTES: u64 = 64 << 20;

/// Width and height of a PNG (its IHDR) or a JPEG (its first start-of-frame marker),
/// read from the header without decoding: what a decoder would allocate. None for other
/// data or a header cut short.
pub fn encoded_image_size(bytes: &[u8]) -> Option<(u32, u32)> {
    const PNG: &[u8] = b"\x89PNG\r\n\x1a\n";
    if bytes.starts_with(PNG) {
        // Signature, then the IHDR chunk: length (4), "IHDR", width (4), height (4).
        if bytes.get(12..16)? != b"IHDR" {
            return None;
        }
        let be = |r: std::ops::Range<usize>| {
            bytes
                .get(r)
                .map(|b| u32::from_be_bytes([b[0], b[1], b[2], b[3]]))
        };
        return Some((be(16..20)?, be(20..24)?));
    }
    if !bytes.starts_with(&[0xff, 0xd8]) {
        return None;
    }
    let mut i = 2;
    while i + 4 <= bytes.len() {
        if bytes[i] != 0xff {
            return None;
        }
        let marker = bytes[i + 1];
        if marker == 0xff {
            i += 1;
            continue;
        }
        // Markers without a length: TEM, RSTn, SOI, EOI.
        if marker == 0x01 || (0xd0..=0xd9).contains(&marker) {
            i += 2;
            continue;
        }
        let len = usize::from(u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]));
        // SOF0..SOF15, except DHT (c4), JPG (c8) and DAC (cc): precision (1), height
        // (2), width (2).
        if (0xc0..=0xcf).contains(&marker) && ![0xc4, 0xc8, 0xcc].contains(&marker) {
            let b = bytes.get(i + 5..i + 9)?;
            let h = u32::from(u16::from_be_bytes([b[0], b[1]]));
            let w = u32::from(u16::from_be_bytes([b[2], b[3]]));
            return Some((w, h));
        }
        if len < 2 {
            return None;
        }
        i += 2 + len;
    }
    None
}

/// An encoded image's size checked before decoding: within [`MAX_IMAGE_SIDE`] and, when
/// `expected` is given, equal to it. The reason when not.
pub fn check_encoded_size(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
) -> Result<(u32, u32), String> {
    let (w, h) = encoded_image_size(bytes).ok_or("not a PNG or JPEG image (no readable header)")?;
    if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        return Err(format!(
            "a {w}x{h} image: sides 1..{MAX_IMAGE_SIDE} pixels expected (not decoded)"
        ));
    }
    if let Some((ew, eh)) = expected {
        if (w, h) != (ew, eh) {
            return Err(format!(
                "a {w}x{h} image where {ew}x{eh} is expected (not decoded)"
            ));
        }
    }
    Ok((w, h))
}
const HEADER: &str = "file,seq,stamp_s,exposure_us,gain_db";

/// One line of the sidecar.
#[derive(Debug, Clone, PartialEq)]
struct Entry {
    file: PathBuf,
    meta: FrameMeta,
}

/// Frames recorded to a folder: PNG files and `frames.csv` with, per frame, the file
/// name, sequence number, stamp (s), exposure (us) and gain (dB). The exposure cannot
/// be changed: `set_exposure_us` reports the recorded exposure of the next frame.
pub struct RecordedCamera {
    name: String,
    dir: PathBuf,
    entries: Vec<Entry>,
    next: usize,
    limits: ExposureLimits,
    bytes: Vec<u8>,
    img: core::Mat,
    grey: core::Mat,
}

impl RecordedCamera {
    /// Open a recording folder; the sidecar is read and every listed file checked.
    pub fn open(dir: &Path) -> Result<Self, CameraError> {
        let sidecar = dir.join(SIDECAR);
        let text = read_bounded(&sidecar, MAX_SIDECAR_BYTES).map_err(|source| CameraError::Io {
            path: sidecar.clone(),
            source,
        })?;
        let text = String::from_utf8(text).map_err(|_| CameraError::Recording {
            path: sidecar.clone(),
            line: 1,
            reason: "not UTF-8 text".into(),
        })?;
        let bad = |line: usize, reason: String| CameraError::Recording {
            path: sidecar.clone(),
            line,
            reason,
        };
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty());
        match lines.next() {
            Some((_, h)) if h.trim() == HEADER => {}
            Some((i, h)) => return Err(bad(i + 1, format!("header '{h}': expected '{HEADER}'"))),
            None => return Err(bad(1, "empty sidecar".into())),
        }
        let mut entries: Vec<Entry> = Vec::new();
        for (i, line) in lines {
            let no = i + 1;
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            if f.len() != 5 {
                return Err(bad(
                    no,
                    format!("{} fields: expected 5 ({HEADER})", f.len()),
                ));
            }
            let num = |k: usize, name: &str| -> Result<f64, CameraError> {
                f[k].parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| bad(no, format!("{name} '{}' is not a finite number", f[k])))
            };
            // A stream camera's frame whose exposure is not known (its camera's own auto
            // exposure, or a command in flight) is recorded as NaN and read back so.
            let exposure = if f[3].eq_ignore_ascii_case("nan") {
                f64::NAN
            } else {
                num(3, "exposure_us")?
            };
            let seq = f[1]
                .parse::<u64>()
                .map_err(|_| bad(no, format!("seq '{}' is not an integer", f[1])))?;
            let meta = FrameMeta {
                seq,
                stamp_s: num(2, "stamp_s")?,
                exposure_us: exposure,
                gain_db: num(4, "gain_db")?,
            };
            if meta.exposure_us <= 0.0 {
                return Err(bad(
                    no,
                    format!("exposure_us {} must be > 0", meta.exposure_us),
                ));
            }
            if let Some(prev) = entries.last() {
                if meta.stamp_s <= prev.meta.stamp_s {
                    return Err(bad(
                        no,
                        format!("stamp_s {} does not increase", meta.stamp_s),
                    ));
                }
            }
            let file = PathBuf::from(f[0]);
            if file.is_absolute()
                || file
                    .components()
                    .any(|c| matches!(c, std::path::Component::ParentDir))
            {
                return Err(bad(
                    no,
                    format!("file '{}' must be inside the folder", f[0]),
                ));
            }
            if !dir.join(&file).is_file() {
                return Err(bad(no, format!("file '{}' not found", f[0])));
            }
            entries.push(Entry { file, meta });
        }
        if entries.is_empty() {
            return Err(bad(1, "no frames listed".into()));
        }
        // Over the known exposures (a recording with none known: 1 us, as a placeholder
        // range the loop cannot act on anyway).
        let known = || {
            entries
                .iter()
                .map(|e| e.meta.exposure_us)
                .filter(|v| v.is_finite())
        };
        let min_us = known().fold(f64::MAX, f64::min);
        let max_us = known().fold(0.0, f64::max);
        let (min_us, max_us) = if max_us > 0.0 {
            (min_us, max_us)
        } else {
            (1.0, 1.0)
        };
        let fps = if entries.len() > 1 {
            let span = entries[entries.len() - 1].meta.stamp_s - entries[0].meta.stamp_s;
            (entries.len() - 1) as f64 / span
        } else {
            0.0
        };
        Ok(Self {
            name: format!("recorded:{}", dir.display()),
            dir: dir.to_path_buf(),
            entries,
            next: 0,
            limits: ExposureLimits {
                min_us,
                max_us,
                fps,
            },
            bytes: Vec::new(),
            img: core::Mat::default(),
            grey: core::Mat::default(),
        })
    }

    /// Number of frames in the recording.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Go back to the first frame.
    pub fn rewind(&mut self) {
        self.next = 0;
    }

    /// The stamp of the frame `ahead` places after the one the next `grab` reads (0: that
    /// one), from the sidecar, without reading the image; None past the end.
    pub fn peek_stamp_s(&self, ahead: usize) -> Option<f64> {
        self.entries
            .get(self.next.checked_add(ahead)?)
            .map(|e| e.meta.stamp_s)
    }

    /// Passes over the frame the next `grab` would read, without reading its image (a
    /// real-time player drops what the loop was too slow for); false at the end.
    pub fn skip(&mut self) -> bool {
        if self.next < self.entries.len() {
            self.next += 1;
            true
        } else {
            false
        }
    }
}

impl Camera for RecordedCamera {
    fn name(&self) -> &str {
        &self.name
    }

    fn exposure_limits(&self) -> ExposureLimits {
        self.limits
    }

    fn set_exposure_us(&mut self, _exposure_us: f64) -> Result<f64, CameraError> {
        let e = self.entries.get(self.next).or(self.entries.last());
        Ok(e.map_or(0.0, |e| e.meta.exposure_us))
    }

    fn grab(&mut self, frame: &mut Frame) -> Result<(), CameraError> {
        let Some(entry) = self.entries.get(self.next) else {
            return Err(CameraError::EndOfStream {
                device: self.name.clone(),
            });
        };
        let path = self.dir.join(&entry.file);
        let read_err = |reason: String| CameraError::Read {
            device: self.name.clone(),
            seq: entry.meta.seq,
            reason,
        };
        self.bytes.clear();
        std::fs::File::open(&path)
            .and_then(|f| {
                let len = f.metadata()?.len();
                if len > MAX_IMAGE_FILE_BYTES {
                    return Err(std::io::Error::other(format!(
                        "{len} bytes: more than {MAX_IMAGE_FILE_BYTES}"
                    )));
                }
                f.take(MAX_IMAGE_FILE_BYTES).read_to_end(&mut self.bytes)
            })
            .map_err(|e| read_err(format!("{}: {e}", path.display())))?;
        check_encoded_size(&self.bytes, None)
            .map_err(|e| read_err(format!("{}: {e}", path.display())))?;
        let buf = core::Mat::from_slice(&self.bytes).map_err(|e| read_err(e.to_string()))?;
        imgcodecs::imdecode_to(&buf, imgcodecs::IMREAD_GRAYSCALE, &mut self.img)
            .map_err(|e| read_err(format!("{}: {e}", path.display())))?;
        if self.img.empty() {
            return Err(read_err(format!(
                "{}: not a readable image",
                path.display()
            )));
        }
        mat_to_frame(&self.img, &mut self.grey, frame)
            .map_err(|e| read_err(format!("{}: {e}", path.display())))?;
        frame.meta = entry.meta;
        self.next += 1;
        Ok(())
    }
}

/// The first `limit` bytes of a regular file, or an error if it is not one or is
/// longer.
fn read_bounded(path: &Path, limit: u64) -> std::io::Result<Vec<u8>> {
    let f = std::fs::File::open(path)?;
    let meta = f.metadata()?;
    if !meta.is_file() {
        return Err(std::io::Error::other("not a regular file"));
    }
    if meta.len() > limit {
        return Err(std::io::Error::other(format!(
            "{} bytes: more than {limit}",
            meta.len()
        )));
    }
    let mut out = Vec::with_capacity(meta.len() as usize);
    f.take(limit).read_to_end(&mut out)?;
    Ok(out)
}

/// Writes frames as a recording `RecordedCamera` can replay.
pub struct FrameRecorder {
    dir: PathBuf,
    sidecar: std::io::BufWriter<std::fs::File>,
    written: u64,
}

impl FrameRecorder {
    /// Create `dir` (if needed) and a fresh sidecar in it.
    pub fn create(dir: &Path) -> Result<Self, CameraError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| CameraError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let path = dir.join(SIDECAR);
        let file = std::fs::File::create(&path).map_err(io(&path))?;
        let mut sidecar = std::io::BufWriter::new(file);
        use std::io::Write;
        writeln!(sidecar, "{HEADER}").map_err(io(&path))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            sidecar,
            written: 0,
        })
    }

    /// Write one frame (PNG, lossless) and its line of the sidecar.
    pub fn write(&mut self, frame: &Frame) -> Result<(), CameraError> {
        use std::io::Write;
        let name = format!("frame_{:06}.png", self.written);
        let path = self.dir.join(&name);
        let (w, h) = (frame.width as usize, frame.height as usize);
        let data = frame.data.get(..w * h).ok_or(CameraError::FrameSize {
            what: "its pixel buffer",
            width: frame.width,
            height: frame.height,
            expected_width: frame.width,
            expected_height: (frame.data.len() / w.max(1)) as u32,
        })?;
        let img =
            core::Mat::new_rows_cols_with_data::<u8>(h as i32, w as i32, data).cv("wrap frame")?;
        let ok = imgcodecs::imwrite(&path, &img, &core::Vector::new()).cv("imwrite")?;
        if !ok {
            return Err(CameraError::Io {
                path,
                source: std::io::Error::other("OpenCV could not write the PNG"),
            });
        }
        let m = frame.meta;
        let sidecar = self.dir.join(SIDECAR);
        writeln!(
            self.sidecar,
            "{name},{},{},{},{}",
            m.seq, m.stamp_s, m.exposure_us, m.gain_db
        )
        .and_then(|_| self.sidecar.flush())
        .map_err(|source| CameraError::Io {
            path: sidecar,
            source,
        })?;
        self.written += 1;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("markhold-camera-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn recording_round_trips_pixels_and_metadata() {
        let dir = tmp("rec");
        let mut rec = FrameRecorder::create(&dir).unwrap();
        let mut f = Frame::new(37, 21);
        for k in 0..3u64 {
            for (i, p) in f.data.iter_mut().enumerate() {
                *p = ((i as u64 * 7 + k * 31) % 256) as u8;
            }
            f.meta = FrameMeta {
                seq: 10 + k,
                stamp_s: 1.5 + k as f64 / 30.0,
                exposure_us: 1000.0 * (k + 1) as f64,
                gain_db: 0.5,
            };
            rec.write(&f).unwrap();
        }
        drop(rec);
        let mut cam = RecordedCamera::open(&dir).unwrap();
        assert_eq!(cam.len(), 3);
        let lim = cam.exposure_limits();
        assert_eq!((lim.min_us, lim.max_us), (1000.0, 3000.0));
        assert!((lim.fps - 30.0).abs() < 1e-6, "{}", lim.fps);
        assert_eq!(cam.set_exposure_us(5.0).unwrap(), 1000.0);
        let mut g = Frame::default();
        for k in 0..3u64 {
            cam.grab(&mut g).unwrap();
            assert_eq!((g.width, g.height), (37, 21));
            assert_eq!(g.meta.seq, 10 + k);
            assert_eq!(g.meta.exposure_us, 1000.0 * (k + 1) as f64);
            assert!((g.meta.stamp_s - (1.5 + k as f64 / 30.0)).abs() < 1e-12);
            assert_eq!(g.data[5], ((5 * 7 + k * 31) % 256) as u8);
            assert_eq!(g.data[700], ((700 * 7 + k * 31) % 256) as u8);
        }
        assert!(matches!(
            cam.grab(&mut g),
            Err(CameraError::EndOfStream { .. })
        ));
        cam.rewind();
        cam.grab(&mut g).unwrap();
        assert_eq!(g.meta.seq, 10);
        // A frame passed over unread: the stamps come from the sidecar.
        assert_eq!(cam.peek_stamp_s(0), Some(1.5 + 1.0 / 30.0));
        assert_eq!(cam.peek_stamp_s(1), Some(1.5 + 2.0 / 30.0));
        assert_eq!(cam.peek_stamp_s(2), None);
        assert!(cam.skip());
        cam.grab(&mut g).unwrap();
        assert_eq!(g.meta.seq, 12);
        assert!(!cam.skip());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn image_sizes_are_read_from_headers_and_unknown_exposures_kept() {
        let dir = tmp("sizes");
        let mut rec = FrameRecorder::create(&dir).unwrap();
        let mut f = Frame::new(37, 21);
        f.meta.exposure_us = f64::NAN;
        rec.write(&f).unwrap();
        drop(rec);
        let png = std::fs::read(dir.join("frame_000000.png")).unwrap();
        assert_eq!(encoded_image_size(&png), Some((37, 21)));
        assert_eq!(check_encoded_size(&png, Some((37, 21))), Ok((37, 21)));
        let e = check_encoded_size(&png, Some((640, 480))).unwrap_err();
        assert!(e.contains("37x21") && e.contains("not decoded"), "{e}");
        let img = core::Mat::new_rows_cols_with_default(21, 37, core::CV_8UC1, 0.into()).unwrap();
        let mut jpg = core::Vector::<u8>::new();
        imgcodecs::imencode(".jpg", &img, &mut jpg, &core::Vector::new()).unwrap();
        assert_eq!(encoded_image_size(jpg.as_slice()), Some((37, 21)));
        // A header that claims 32768 x 32768: refused without decoding.
        let mut huge = png.clone();
        huge[16..20].copy_from_slice(&32768u32.to_be_bytes());
        huge[20..24].copy_from_slice(&32768u32.to_be_bytes());
        assert!(check_encoded_size(&huge, None).is_err());
        assert_eq!(encoded_image_size(b"not an image"), None);
        // The frame's unknown exposure is read back as such.
        let mut cam = RecordedCamera::open(&dir).unwrap();
        let mut g = Frame::default();
        cam.grab(&mut g).unwrap();
        assert!(g.meta.exposure_us.is_nan());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn malformed_sidecars_name_file_and_line() {
        let dir = tmp("bad");
        std::fs::create_dir_all(&dir).unwrap();
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(e.contains("frames.csv"), "{e}");
        let write = |body: &str| std::fs::write(dir.join(SIDECAR), body).unwrap();
        write("file,stamp\n");
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(e.contains("line 1") && e.contains("header"), "{e}");
        write(&format!("{HEADER}\nmissing.png,0,0.0,100,0\n"));
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(e.contains("line 2") && e.contains("missing.png"), "{e}");
        std::fs::write(dir.join("a.png"), b"not a png").unwrap();
        write(&format!("{HEADER}\na.png,0,0.0,abc,0\n"));
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(
            e.contains("line 2") && e.contains("exposure_us 'abc'"),
            "{e}"
        );
        write(&format!("{HEADER}\na.png,0,1.0,100,0\na.png,1,0.5,100,0\n"));
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(
            e.contains("line 3") && e.contains("does not increase"),
            "{e}"
        );
        write(&format!("{HEADER}\n../a.png,0,1.0,100,0\n"));
        let e = RecordedCamera::open(&dir).err().unwrap().to_string();
        assert!(e.contains("inside the folder"), "{e}");
        // A listed file that is not an image fails at grab, naming the file.
        write(&format!("{HEADER}\na.png,4,1.0,100,0\n"));
        let mut cam = RecordedCamera::open(&dir).unwrap();
        let e = cam.grab(&mut Frame::default()).err().unwrap().to_string();
        assert!(e.contains("a.png") && e.contains("frame 4"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
