//! `markhold tag` through the built binary: the three formats, `--site`, and errors that
//! name the flag (exit 2) or the site file's key (exit 78).
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::{Path, PathBuf};

use crate::common::{markhold, outcome, repo, tmp_path};

fn scratch(name: &str) -> PathBuf {
    tmp_path("tag", name)
}

fn tag(args: &[&str]) -> (i32, String, String) {
    outcome(markhold().arg("tag").args(args))
}

/// `markhold tag --site SITE --out OUT`.
fn tag_site(site: &Path, out: &Path) -> (i32, String, String) {
    tag(&[
        "--site",
        site.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
}

/// `tag_site` for the repository's site file `site`: it succeeds; what it printed.
fn tag_repo_site(site: &str, out: &Path) -> String {
    let (code, stdout, err) = tag_site(&repo(site), out);
    assert_eq!(code, 0, "{err}");
    stdout
}

#[test]
fn writes_every_format_at_its_size() {
    for ext in ["svg", "pdf", "png"] {
        let out = scratch(&format!("t.{ext}"));
        let (code, stdout, err) = tag(&[
            "--family",
            "aruco_6x6_250",
            "--id",
            "17",
            "--size-mm",
            "100",
            "--dpi",
            "300",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{ext}: {err}");
        assert!(
            stdout.contains("black square 100 mm (marker.size_m = 0.1)"),
            "{stdout}"
        );
        let bytes = std::fs::read(&out).unwrap();
        match ext {
            // 6x6 data + border = 8 modules of 12.5 mm, one white module each side.
            "svg" => assert!(String::from_utf8(bytes)
                .unwrap()
                .contains(r#"width="125mm""#)),
            "pdf" => assert!(bytes.starts_with(b"%PDF-1.4") && bytes.ends_with(b"%%EOF\n")),
            _ => assert!(bytes.windows(4).any(|w| w == b"pHYs")),
        }
    }
}

#[test]
fn site_gives_family_id_and_size() {
    let out = scratch("pool.svg");
    let stdout = tag_repo_site("params/pool.toml", &out);
    assert!(
        stdout.contains("apriltag_36h11 id 0, black square 150 mm"),
        "{stdout}"
    );
    let svg = std::fs::read_to_string(&out).unwrap();
    assert!(svg.contains("apriltag_36h11 id 0</text>"), "{svg}");
}

/// A site with a marker map: one file per marker (`--out` with `-id<ID>`), each with its
/// own id and size, and where it goes on the site.
#[test]
fn a_map_site_gives_every_marker() {
    let out = scratch("dock.svg");
    let stdout = tag_repo_site("params/dock-map.toml", &out);
    assert!(
        !out.exists(),
        "no file under the plain --out name for a map"
    );
    for (id, mm) in [(0, 150), (1, 120), (2, 120), (3, 120), (4, 120)] {
        let path = out.with_file_name(format!("dock-id{id}.svg"));
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(
            svg.contains(&format!("apriltag_36h11 id {id}</text>")),
            "{svg}"
        );
        assert!(
            stdout.contains(&format!("apriltag_36h11 id {id}, black square {mm} mm")),
            "{stdout}"
        );
    }
    assert!(
        stdout.contains("marker.map[3].size_m = 0.12")
            && stdout.contains("centre at [0.3, -0.2, 0] m"),
        "{stdout}"
    );
}

#[test]
fn bad_flags_exit_2_naming_flag_and_value() {
    let out = scratch("bad.svg");
    let out = out.to_str().unwrap();
    let cases: [(&[&str], &str); 5] = [
        (
            &[
                "--family",
                "qr",
                "--id",
                "1",
                "--size-mm",
                "50",
                "--out",
                out,
            ],
            "--family qr",
        ),
        (
            &[
                "--family",
                "aruco_4x4_50",
                "--id",
                "50",
                "--size-mm",
                "50",
                "--out",
                out,
            ],
            "--id 50",
        ),
        (
            &[
                "--family",
                "aruco_4x4_50",
                "--id",
                "1",
                "--size-mm",
                "-3",
                "--out",
                out,
            ],
            "--size-mm -3",
        ),
        (
            &[
                "--family",
                "aruco_4x4_50",
                "--id",
                "1",
                "--size-mm",
                "0",
                "--out",
                out,
            ],
            "--size-mm 0",
        ),
        (
            &[
                "--family",
                "aruco_4x4_50",
                "--id",
                "1",
                "--size-mm",
                "50",
                "--out",
                "t.jpg",
            ],
            "--out t.jpg",
        ),
    ];
    for (args, want) in cases {
        let (code, _, err) = tag(args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
    }
    assert!(!Path::new(out).exists());
}

#[test]
fn bad_site_marker_exits_78_naming_the_key() {
    let text = std::fs::read_to_string(repo("params/pool.toml")).unwrap();
    let bad = text.replacen("id = 0", "id = 5000", 1);
    assert_ne!(bad, text);
    let site = scratch("bad-site.toml");
    std::fs::write(&site, bad).unwrap();
    let out = scratch("bad-site.png");
    let (code, _, err) = tag_site(&site, &out);
    assert_eq!(code, 78, "{err}");
    assert!(err.contains("marker.id") && err.contains("5000"), "{err}");
}
