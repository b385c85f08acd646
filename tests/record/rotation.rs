//! Recording rotation (`[record.rotation]`) on a real `markhold hil --record` run: the
//! recording is split into segments of bounded size or frame time, each a complete MCAP
//! file that `replay` reads to its end, with no frame lost between two segments; the
//! folder stays under its quota by deleting the oldest segments, never the open one.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::path::{Path, PathBuf};

use common::{markhold, site_path, tmp_dir};
use markhold::record::{FrameMsg, TOPIC_FRAME};

fn scratch(name: &str) -> PathBuf {
    let d = tmp_dir("rotation", name);
    std::fs::create_dir_all(d.join("rec")).unwrap();
    d
}

/// The test site with `rotation` as its `[record.rotation]`.
fn site_with(dir: &Path, rotation: &str) -> PathBuf {
    let text = std::fs::read_to_string(site_path()).unwrap();
    let site = dir.join("site.toml");
    std::fs::write(&site, format!("{text}\n[record.rotation]\n{rotation}\n")).unwrap();
    site
}

/// `hil --record DIR/rec/run.mcap` for `seconds` of simulated time; its stderr.
fn record(site: &Path, dir: &Path, seconds: &str) -> String {
    let out = markhold()
        .args(["hil", "--quiet", "--seconds", seconds, "--site"])
        .arg(site)
        .arg("--record")
        .arg(dir.join("rec/run.mcap"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{err}");
    err
}

/// A segment as found: its number (0 for the path given), bytes, and its frames' seq.
struct Segment {
    n: u32,
    path: PathBuf,
    bytes: u64,
    seqs: Vec<u64>,
    /// Frame time from its first frame to its last, s.
    span_s: f64,
}

fn segments(dir: &Path) -> Vec<Segment> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir.join("rec")).unwrap() {
        let path = e.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let n = match name.as_str() {
            "run.mcap" => 0,
            other => other
                .strip_prefix("run.")
                .and_then(|r| r.strip_suffix(".mcap"))
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("a file rotation did not make: {name}")),
        };
        let buf = std::fs::read(&path).unwrap();
        // Complete: a summary section (written only when the file is finalized).
        let summary = mcap::Summary::read(&buf)
            .unwrap()
            .unwrap_or_else(|| panic!("{name}: no summary: not finalized"));
        assert!(summary.stats.is_some(), "{name}: no statistics");
        let mut seqs = Vec::new();
        let mut stamps = Vec::new();
        for m in mcap::MessageStream::new(&buf).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == TOPIC_FRAME {
                let f: FrameMsg = serde_json::from_slice(&m.data).unwrap();
                seqs.push(f.seq);
                stamps.push(f.stamp_s);
            }
        }
        out.push(Segment {
            n,
            bytes: buf.len() as u64,
            path,
            seqs,
            span_s: stamps.last().unwrap_or(&0.0) - stamps.first().unwrap_or(&0.0),
        });
    }
    out.sort_by_key(|s| s.n);
    out
}

/// Every segment left is complete, `replay` reads it to its end, and consecutive
/// segments hold consecutive frames (nothing lost at a rotation).
fn check_complete_and_contiguous(segs: &[Segment]) {
    for s in segs {
        assert!(!s.seqs.is_empty(), "{}: no frames", s.path.display());
        let r = markhold::record::replay::replay(&s.path).unwrap();
        assert!(r.recovered.is_none(), "{}: {r:?}", s.path.display());
        assert_eq!(r.frames_recorded, s.seqs.len() as u64);
    }
    for w in segs.windows(2) {
        if w[1].n == w[0].n + 1 {
            assert_eq!(
                w[1].seqs[0],
                w[0].seqs.last().unwrap() + 1,
                "a frame lost between segments {} and {}",
                w[0].n,
                w[1].n
            );
        }
    }
}

#[test]
fn a_small_quota_keeps_the_newest_complete_segments() {
    let dir = scratch("quota");
    let site = site_with(&dir, "segment_mb = 1.0\nquota_mb = 3.0\nmin_free_mb = 0");
    let err = record(&site, &dir, "8");
    let segs = segments(&dir);
    let newest = segs.last().unwrap().n;
    assert!(
        newest >= 5,
        "8 s of 640x480 PNG is many MB: {newest} segments"
    );
    assert!(
        segs.len() < newest as usize + 1,
        "older segments deleted: {} left of {}",
        segs.len(),
        newest + 1
    );
    assert_eq!(
        segs[0].n + segs.len() as u32 - 1,
        newest,
        "the newest are kept"
    );
    assert!(err.contains("deleted"), "the deletions are logged: {err}");
    // The quota: what is left, the last segment's index and footer aside.
    let total: u64 = segs.iter().map(|s| s.bytes).sum();
    assert!(
        total <= 3_000_000 + 300_000,
        "{total} bytes left in the folder"
    );
    // Each segment: 1 MB plus at most the chunk in progress (a quarter) and its index.
    for s in &segs {
        assert!(
            s.bytes <= 1_000_000 + 250_000 + 100_000,
            "{}: {} bytes",
            s.path.display(),
            s.bytes
        );
    }
    check_complete_and_contiguous(&segs);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn segments_end_after_their_frame_time() {
    let dir = scratch("time");
    let site = site_with(&dir, "segment_s = 2.0\nmin_free_mb = 0");
    record(&site, &dir, "7");
    let segs = segments(&dir);
    let n: Vec<u32> = segs.iter().map(|s| s.n).collect();
    assert_eq!(n, [0, 1, 2, 3], "7 s in segments of 2 s, none deleted");
    for s in &segs {
        // The frame that reaches 2 s of frame time closes the segment.
        assert!(
            s.span_s <= 2.0 + 1e-6,
            "{}: {} s",
            s.path.display(),
            s.span_s
        );
    }
    assert!(
        segs[..3].iter().all(|s| s.span_s >= 2.0 - 1.0 / 30.0),
        "full segments span 2 s"
    );
    check_complete_and_contiguous(&segs);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_bad_rotation_key_is_refused_with_its_name() {
    let dir = scratch("bad");
    let site = site_with(&dir, "segment_mb = 100.0\nquota_mb = 150.0");
    let out = markhold()
        .args(["params", "check"])
        .arg(&site)
        .output()
        .unwrap();
    let err = crate::common::stderr_of_exit(&out, 78);
    assert!(
        err.contains("record.rotation.quota_mb") && err.contains("150"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
