//! The web page (`--web`) in a real browser: Debian's headless Chromium loads it from
//! loopback while `markhold hil` runs, runs its script, and the DOM it leaves shows the
//! status updating, the camera image loaded at the camera's size, and a bad key of the
//! site file (edited on disk during the run) at its line with `params check`'s message.
//! The recording buttons' requests close and begin segments of the run's recording.
//! Everything binds and connects to 127.0.0.1 only; every wait is bounded.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::{
    frames_camera, markhold, run_engaged, site_path, station_frames, station_rig, tmp_dir,
    RealTimeVehicle,
};

/// A markhold command with the page on loopback; SIGTERM and reaped when dropped.
struct Hil {
    child: Child,
    addr: SocketAddr,
}

impl Hil {
    /// `markhold hil` for an hour of simulated time (stopped by the test).
    fn start(site: &Path, record: &Path) -> Self {
        let mut cmd = markhold();
        cmd.args(["hil", "--quiet", "--seconds", "3600", "--site"])
            .arg(site)
            .arg("--record")
            .arg(record);
        Self::spawn(cmd)
    }

    /// `cmd --web 127.0.0.1:0`, once its page answers.
    fn spawn(mut cmd: Command) -> Self {
        let mut child = cmd
            .args(["--web", "127.0.0.1:0"])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // The address is on stderr; read it on a thread so the wait is bounded.
        let err = child.stderr.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(err).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut said = Vec::new();
        let addr = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) => match line.strip_prefix("markhold: web page on http://") {
                    Some(a) => break a.trim_end_matches('/').parse().unwrap(),
                    None => said.push(line),
                },
                Err(e) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    panic!(
                        "no web page address within 60 s ({e}); markhold said:\n{}",
                        said.join("\n")
                    );
                }
            }
        };
        Self { child, addr }
    }
}

impl Drop for Hil {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP request on loopback: (status, body).
fn http(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).unwrap();
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (status, body)
}

fn status(addr: SocketAddr) -> serde_json::Value {
    let (code, body) = http(addr, "GET", "/status.json");
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Wait (bounded) until `ok` holds for the status.
fn wait_status(addr: SocketAddr, what: &str, ok: impl Fn(&serde_json::Value) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let s = status(addr);
        if ok(&s) {
            return;
        }
        assert!(Instant::now() < deadline, "{what} within 60 s: {s}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The DOM of `url` after its script ran for 3 s of the page's time, from Debian's
/// headless Chromium with the flags this machine needs (no sandbox as root, no network
/// but loopback) and a fresh profile.
fn dom_after_script(url: &str, profile: &Path) -> String {
    let _ = std::fs::remove_dir_all(profile);
    let mut child = Command::new("chromium")
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--virtual-time-budget=3000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(url)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| {
            panic!("chromium (Debian's package; scripts/install-deps installs it): {e}")
        });
    let mut out = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut s = String::new();
        let _ = out.read_to_string(&mut s);
        let _ = tx.send(s);
    });
    let dom = rx.recv_timeout(Duration::from_secs(90));
    let _ = child.kill();
    let _ = child.wait();
    dom.expect("chromium gave no DOM within 90 s")
}

/// The value of attribute `name` of the first element whose tag starts with `start`.
fn attr(dom: &str, start: &str, name: &str) -> Option<String> {
    let at = dom.find(start)?;
    let tag = &dom[at..at + dom[at..].find('>')?];
    let key = format!(" {name}=\"");
    let v = &tag[tag.find(&key)? + key.len()..];
    Some(v[..v.find('"')?].to_string())
}

fn num(dom: &str, start: &str, name: &str) -> u64 {
    attr(dom, start, name)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{start} {name} missing in the DOM:\n{dom}"))
}

fn scratch(name: &str) -> PathBuf {
    let d = tmp_dir("web", name);
    std::fs::create_dir_all(d.join("rec")).unwrap();
    d
}

#[test]
fn the_page_in_chromium_shows_status_camera_and_a_bad_site_key() {
    let dir = scratch("page");
    let site = dir.join("site.toml");
    std::fs::copy(site_path(), &site).unwrap();
    let rec = dir.join("rec/dive.mcap");
    let hil = Hil::start(&site, &rec);
    wait_status(hil.addr, "frames", |s| {
        s["status"]["frames"].as_u64() > Some(5)
    });
    let url = format!("http://{}/", hil.addr);

    let dom = dom_after_script(&url, &dir.join("profile-1"));
    // Status: refreshed several times, and the frames it showed moved on.
    assert!(num(&dom, "<body", "data-status-updates") >= 2, "{dom}");
    let (first, last) = (
        num(&dom, "<body", "data-first-seq"),
        num(&dom, "<body", "data-last-seq"),
    );
    assert!(
        last > first,
        "the status did not update: seq {first} .. {last}"
    );
    assert!(dom.contains("seen: 1 marker(s)"), "the marker: {dom}");
    // The camera: images loaded, at the camera's size.
    assert!(num(&dom, "<img id=\"camera\"", "data-frames-shown") >= 1);
    assert_eq!(num(&dom, "<img id=\"camera\"", "data-width"), 640);
    assert_eq!(num(&dom, "<img id=\"camera\"", "data-height"), 480);
    // The site as started: it passes.
    assert_eq!(
        attr(&dom, "<section id=\"site-panel\"", "data-ok").as_deref(),
        Some("true")
    );
    assert!(!dom.contains("class=\"site-error\""));

    // A bad key written into the file while markhold runs: the page shows it in place.
    let text = std::fs::read_to_string(&site).unwrap();
    let bad = text.replacen("[marker]", "[marker]\nsize_mm = 150", 1);
    std::fs::write(&site, &bad).unwrap();
    let line = bad.lines().position(|l| l == "size_mm = 150").unwrap() + 1;
    let dom = dom_after_script(&url, &dir.join("profile-2"));
    assert_eq!(
        attr(&dom, "<section id=\"site-panel\"", "data-ok").as_deref(),
        Some("false"),
        "{dom}"
    );
    let error = &dom[dom.find("class=\"site-error\"").expect("an error shown")..];
    assert_eq!(
        attr(error, "class=\"site-error\"", "data-line"),
        Some(line.to_string())
    );
    let message = &error[error.find('>').unwrap() + 1..error.find("</div>").unwrap()];
    assert!(
        message.contains("size_mm") && message.contains(&format!(":{line}:")),
        "{message}"
    );
    // The row of that line is marked, right above its message.
    let row = format!("<span class=\"no\">{line}</span>");
    let at = dom.find(&row).expect("the line's row");
    assert!(
        dom[..at].ends_with("<div class=\"line error\">"),
        "{}",
        &dom[at.saturating_sub(60)..at + 40]
    );

    // Recording: stop closes the segment, start begins the next one.
    let s = status(hil.addr);
    assert_eq!(s["recording"]["recording"], true, "{s}");
    let (code, body) = http(hil.addr, "POST", "/record/stop");
    assert_eq!(code, 200, "{body}");
    wait_status(hil.addr, "the recording stopped", |s| {
        s["recording"]["recording"] == false
    });
    let (code, body) = http(hil.addr, "POST", "/record/start");
    assert_eq!(code, 200, "{body}");
    wait_status(hil.addr, "a second segment", |s| {
        s["recording"]["recording"] == true && s["recording"]["segments"] == 2
    });
    drop(hil);
    // Both segments are complete recordings that replay reads to their end.
    for seg in [rec.clone(), dir.join("rec/dive.1.mcap")] {
        let out = markhold::record::replay::replay(&seg).unwrap();
        assert!(out.frames_recorded > 0, "{}: {out:?}", seg.display());
        assert!(
            out.recovered.is_none(),
            "{}: not complete: {out:?}",
            seg.display()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_cockpit_widget_view_shows_the_camera_and_status_only() {
    let dir = scratch("widget");
    let site = dir.join("site.toml");
    std::fs::copy(site_path(), &site).unwrap();
    let hil = Hil::start(&site, &dir.join("w.mcap"));
    wait_status(hil.addr, "frames", |s| {
        s["status"]["frames"].as_u64() > Some(5)
    });
    let dom = dom_after_script(
        &format!("http://{}/?view=widget", hil.addr),
        &dir.join("profile"),
    );
    assert_eq!(
        attr(&dom, "<body", "class").as_deref(),
        Some("widget"),
        "{dom}"
    );
    assert!(num(&dom, "<img id=\"camera\"", "data-frames-shown") >= 1);
    assert!(num(&dom, "<body", "data-status-updates") >= 2);
    // The widget reads no site file.
    assert!(!dom.contains("class=\"line"), "{dom}");
    drop(hil);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `run` sets the engagement it has on the page: engaged (`--engage`) with the vehicle
/// heard, its link state and the camera's frames.
#[test]
fn run_shows_its_engagement_and_link_on_the_page() {
    let dir = scratch("run");
    let frames = station_frames(dir.join("frames"), 150);
    let vehicle = RealTimeVehicle::start(station_rig(false));
    let mut cmd = run_engaged(&site_path(), &frames_camera(&frames));
    cmd.args(["--link", &vehicle.link()]);
    let run = Hil::spawn(cmd);
    wait_status(run.addr, "engaged with frames and the vehicle heard", |s| {
        let st = &s["status"];
        st["engagement"] == "engaged"
            && st["frames"].as_u64() > Some(3)
            && st["link"]["heard"] == true
            && s["runner"] == "run"
    });
    let (code, body) = http(run.addr, "GET", "/snapshot.jpg");
    assert_eq!(code, 200, "{body}");
    drop(run);
    let _ = vehicle.finish();
    let _ = std::fs::remove_dir_all(&dir);
}
