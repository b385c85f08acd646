//! The BlueOS extension's files, checked without a container engine (none runs on the
//! machines the tests run on): the Dockerfile's base images, the three platforms it
//! builds, the cargo build it runs (field features: no simulator, no Aravis), the labels
//! BlueOS reads (present, JSON where BlueOS parses JSON, host networking, the V4L2
//! devices and the page's port in the permissions), and the entry point (POSIX sh
//! syntax, BlueOS's MAVLink router, the pilot engages, the page on every address).
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::collections::BTreeMap;
use std::path::Path;

fn repo(p: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(p))
        .unwrap_or_else(|e| panic!("{p}: {e}"))
}

/// Dockerfile instructions with continuation lines joined and comments dropped.
fn instructions(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('#') || (t.is_empty() && cur.is_empty()) {
            continue;
        }
        if let Some(head) = t.strip_suffix('\\') {
            cur.push_str(head);
            cur.push(' ');
        } else {
            cur.push_str(t);
            out.push(std::mem::take(&mut cur));
        }
    }
    out
}

/// `LABEL key=value` values as Docker reads them: single quotes literal, double quotes
/// with `\"` escapes and `${ARG}` replaced by the ARG's default.
fn labels(ins: &[String]) -> BTreeMap<String, String> {
    let mut args = BTreeMap::new();
    let mut out = BTreeMap::new();
    for i in ins {
        if let Some(a) = i.strip_prefix("ARG ") {
            if let Some((k, v)) = a.split_once('=') {
                args.insert(k.trim().to_string(), v.trim().to_string());
            }
        }
        let Some(rest) = i.strip_prefix("LABEL ") else {
            continue;
        };
        let (k, v) = rest.split_once('=').unwrap();
        let v = v.trim();
        let value = if let Some(inner) = v.strip_prefix('\'').and_then(|v| v.strip_suffix('\'')) {
            inner.to_string()
        } else if let Some(inner) = v.strip_prefix('"').and_then(|v| v.strip_suffix('"')) {
            let mut s = inner.replace("\\\"", "\"");
            for (name, val) in &args {
                s = s.replace(&format!("${{{name}}}"), val);
            }
            s
        } else {
            v.to_string()
        };
        out.insert(k.trim().to_string(), value);
    }
    out
}

#[test]
fn dockerfile_builds_the_field_binary_on_debian_bookworm() {
    let ins = instructions(&repo("Dockerfile"));
    let froms: Vec<&String> = ins.iter().filter(|i| i.starts_with("FROM ")).collect();
    assert_eq!(
        froms.len(),
        2,
        "a build stage and a runtime stage: {froms:?}"
    );
    assert!(
        froms[0].starts_with("FROM debian:bookworm "),
        "{}",
        froms[0]
    );
    assert_eq!(froms[1], "FROM debian:bookworm-slim");
    let build = ins
        .iter()
        .find(|i| i.contains("cargo build"))
        .expect("a cargo build");
    assert!(build.contains("--release"), "{build}");
    assert!(build.contains("--locked"), "{build}");
    assert!(build.contains("--no-default-features"), "{build}");
    assert!(
        !build.contains("genicam") && !build.contains("sim"),
        "{build}"
    );
    // OpenCV from Debian, in both stages; no Aravis.
    let text = ins.join("\n");
    assert!(
        text.contains("libopencv-dev"),
        "build stage: Debian's OpenCV"
    );
    assert!(
        text.contains("libopencv-contrib406"),
        "runtime: aruco is in contrib"
    );
    assert!(!text.contains("aravis"), "the image has no Aravis");
    // No platform pinned: buildx builds each platform.
    assert!(!text.contains("--platform="), "{text}");
    assert!(ins
        .iter()
        .any(|i| i == "ENTRYPOINT [\"/usr/local/bin/markhold-extension\"]"));
    let ignore = repo(".dockerignore");
    assert!(
        ignore.lines().any(|l| l.trim() == "target"),
        "the context leaves out target/"
    );
}

#[test]
fn the_labels_blueos_reads_are_present_and_valid() {
    let l = labels(&instructions(&repo("Dockerfile")));
    for key in [
        "version",
        "type",
        "tags",
        "company",
        "authors",
        "readme",
        "links",
        "requirements",
        "permissions",
    ] {
        assert!(l.contains_key(key), "LABEL {key} missing: {l:?}");
    }
    assert_eq!(l["version"], env!("CARGO_PKG_VERSION"));
    let json = |k: &str| -> serde_json::Value {
        serde_json::from_str(&l[k])
            .unwrap_or_else(|e| panic!("LABEL {k} is not JSON: {e}: {}", l[k]))
    };
    assert!(json("tags").as_array().is_some_and(|a| !a.is_empty()));
    assert!(json("authors").as_array().is_some_and(|a| !a.is_empty()));
    assert!(json("company")["name"].is_string());
    assert!(json("links")["documentation"]
        .as_str()
        .unwrap()
        .ends_with("docs/first-dive.md"));
    assert!(
        l["readme"].ends_with("docs/blueos-extension.md"),
        "{}",
        l["readme"]
    );
    let p = json("permissions");
    let host = &p["HostConfig"];
    assert_eq!(host["NetworkMode"], "host", "{p}");
    assert!(host["Binds"]
        .as_array()
        .unwrap()
        .iter()
        .any(|b| b.as_str().unwrap().starts_with("/dev:/dev")));
    assert!(
        host["DeviceCgroupRules"]
            .as_array()
            .unwrap()
            .iter()
            .any(|r| r == "c 81:* rmw"),
        "V4L2 devices (major 81): {p}"
    );
    assert_ne!(host["Privileged"], true, "no privileged container: {p}");
}

#[test]
fn the_entry_point_talks_to_blueos_and_leaves_engaging_to_the_pilot() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("blueos/entrypoint.sh");
    crate::common::run_ok(std::process::Command::new("sh").arg("-n").arg(&path));
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert!(mode & 0o111 != 0, "entrypoint.sh is not executable");
    }
    let text = repo("blueos/entrypoint.sh");
    assert!(
        text.contains("tcp:127.0.0.1:5777"),
        "BlueOS's MAVLink router TCP server"
    );
    assert!(text.contains("markhold preflight"));
    assert!(text.contains("markhold run"));
    assert!(
        !text.contains("--engage"),
        "the pilot engages, not the extension"
    );
}

/// The platforms a multi-platform build makes, as the Dockerfile declares them: the
/// documented `buildx --platform` list, and the toolchain chosen per Debian architecture
/// (any other architecture stops the build with a message).
#[test]
fn dockerfile_declares_arm_v7_arm64_and_amd64() {
    let text = repo("Dockerfile");
    let want = ["linux/arm/v7", "linux/arm64", "linux/amd64"];
    let documented = text
        .lines()
        .find_map(|l| l.split("--platform ").nth(1))
        .expect("the buildx command in the header");
    let mut listed: Vec<&str> = documented
        .split_whitespace()
        .next()
        .unwrap()
        .split(',')
        .collect();
    listed.sort_unstable();
    let mut sorted = want;
    sorted.sort_unstable();
    assert_eq!(listed, sorted, "{documented}");
    // Debian's architecture of each platform -> the Rust host built for it.
    let ins = instructions(&text);
    let rustup = ins
        .iter()
        .find(|i| i.contains("rustup") && i.contains("dpkg --print-architecture"))
        .expect("the toolchain chosen per architecture");
    for (arch, host) in [
        ("armhf", "armv7-unknown-linux-gnueabihf"),
        ("arm64", "aarch64-unknown-linux-gnu"),
        ("amd64", "x86_64-unknown-linux-gnu"),
    ] {
        assert!(
            rustup.contains(&format!("{arch}) host={host} ;;")),
            "{arch} -> {host}: {rustup}"
        );
    }
    assert!(
        rustup.contains("*) echo") && rustup.contains("exit 1"),
        "another architecture stops the build: {rustup}"
    );
    assert!(rustup.contains("--default-host \"${host}\""), "{rustup}");
    // Debian packages only (bookworm builds OpenCV 4.6 and GStreamer for all three).
    assert!(
        !text.contains("pip install") && !text.contains("npm "),
        "{text}"
    );
}

/// The page BlueOS lists in its sidebar: served on every address (its helper only scans
/// ports listening on 0.0.0.0 or ::), on the port the permissions name.
#[test]
fn the_extension_serves_its_page_where_blueos_looks() {
    let l = labels(&instructions(&repo("Dockerfile")));
    let p: serde_json::Value = serde_json::from_str(&l["permissions"]).unwrap();
    let port = markhold::web::EXTENSION_PORT;
    assert!(
        p["ExposedPorts"][format!("{port}/tcp")].is_object(),
        "the page's port in ExposedPorts: {p}"
    );
    let entry = repo("blueos/entrypoint.sh");
    assert!(
        entry.contains(&format!("0.0.0.0:{port}")) && entry.contains("--web"),
        "{entry}"
    );
    assert!(entry.contains("--foxglove-bind 0.0.0.0"), "{entry}");
    let docker = repo("Dockerfile");
    assert!(docker.contains(&format!("EXPOSE {port}/tcp")), "{docker}");
}
