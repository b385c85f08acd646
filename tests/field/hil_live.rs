//! `markhold hil --foxglove`: a simulated run watched live. A raw WebSocket client (the
//! Foxglove protocol, no client crate) subscribes to the exposure channel while the run
//! goes on and must receive messages from it; a browser page from an origin the site does
//! not allow is refused.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use crate::common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::{markhold, site_path, tmp_path, ws_read_frame};

/// One masked client text frame (clients must mask, RFC 6455 5.3).
fn write_text(s: &mut TcpStream, text: &str) -> std::io::Result<()> {
    let payload = text.as_bytes();
    let mask = [0x37u8, 0xfa, 0x21, 0x3d];
    let mut out = vec![0x81u8];
    if payload.len() < 126 {
        out.push(0x80 | payload.len() as u8);
    } else {
        out.push(0x80 | 126);
        out.extend_from_slice(&(payload.len() as u16).to_be_bytes());
    }
    out.extend_from_slice(&mask);
    out.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    s.write_all(&out)
}

/// `markhold hil --foxglove` on `site` for 30 s; its live-view port and a growing copy of
/// its stderr lines.
fn start_live_hil(site: &Path) -> (Child, Result<u16, String>, Arc<Mutex<Vec<String>>>) {
    let mut child = markhold()
        .args(["hil", "--site"])
        .arg(site)
        .args([
            "--seconds",
            "30",
            "--quiet",
            "--foxglove",
            "--foxglove-port",
            "0",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawning markhold hil");
    // The port is announced on stderr before the first frame.
    let stderr = child.stderr.take().expect("stderr piped");
    let lines = Arc::new(Mutex::new(Vec::new()));
    let (tx, rx) = std::sync::mpsc::channel();
    let kept = lines.clone();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("ws://127.0.0.1:").nth(1) {
                let _ = tx.send(rest.trim().parse::<u16>().ok());
            }
            kept.lock().unwrap().push(line);
        }
    });
    let port = match rx.recv_timeout(Duration::from_secs(60)) {
        Ok(Some(p)) => Ok(p),
        Ok(None) => Err("unparsable port".to_string()),
        Err(_) => Err("no live-view address on stderr within 60 s".to_string()),
    };
    (child, port, lines)
}

/// A WebSocket upgrade request (with `origin`, when given); the HTTP answer's head.
fn upgrade(port: u16, origin: Option<&str>) -> Result<(TcpStream, String), String> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    let origin = origin
        .map(|o| format!("Origin: {o}\r\n"))
        .unwrap_or_default();
    write!(
        s,
        "GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
         {origin}Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    .map_err(|e| e.to_string())?;
    let mut head = Vec::new();
    let mut b = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        s.read_exact(&mut b).map_err(|e| e.to_string())?;
        head.push(b[0]);
    }
    Ok((s, String::from_utf8_lossy(&head).to_string()))
}

/// Subscribe to the exposure channel once it is advertised; count its messageData frames
/// (opcode 1 of the binary protocol) until 10 arrived or 30 s passed.
fn count_exposure_messages(s: &mut TcpStream) -> Result<u64, String> {
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut subscribed = false;
    let mut messages = 0u64;
    while Instant::now() < deadline && messages < 10 {
        let (op, data) = ws_read_frame(s).map_err(|e| e.to_string())?;
        if op == 1 && !subscribed {
            let v: serde_json::Value = serde_json::from_slice(&data).map_err(|e| e.to_string())?;
            if v["op"] != "advertise" {
                continue;
            }
            let channels = v["channels"].as_array().ok_or("no channels")?;
            let id = channels
                .iter()
                .find(|c| c["topic"] == markhold::record::TOPIC_EXPOSURE)
                .and_then(|c| c["id"].as_u64())
                .ok_or("exposure channel not advertised")?;
            write_text(
                s,
                &format!(r#"{{"op":"subscribe","subscriptions":[{{"id":7,"channelId":{id}}}]}}"#),
            )
            .map_err(|e| e.to_string())?;
            subscribed = true;
        } else if op == 2 && data.len() > 5 && data[0] == 1 {
            let sub = u32::from_le_bytes([data[1], data[2], data[3], data[4]]);
            if sub == 7 {
                messages += 1;
            }
        }
    }
    Ok(messages)
}

#[test]
fn hil_foxglove_streams_the_exposure_channel_while_running() {
    let (mut child, port, _) = start_live_hil(&site_path());
    let result = port.and_then(|port| {
        let (mut s, head) = upgrade(port, None)?;
        if !head.starts_with("HTTP/1.1 101") {
            return Err(head);
        }
        count_exposure_messages(&mut s)
    });
    let _ = child.kill();
    let _ = child.wait();
    let messages = result.unwrap();
    assert!(
        messages >= 10,
        "only {messages} exposure messages streamed during the run"
    );
}

#[test]
fn the_live_view_refuses_origins_the_site_does_not_allow() {
    let site = tmp_path("hil-live", "origins.toml");
    let mut text = std::fs::read_to_string(site_path()).unwrap();
    text.push_str("\n[live]\nallowed_origins = [\"https://viewer.example\"]\n");
    std::fs::write(&site, text).unwrap();
    let (mut child, port, lines) = start_live_hil(&site);
    let result = port.and_then(|port| {
        // A page elsewhere, and the default Foxglove origin the site's list replaced.
        for origin in ["https://evil.example", "https://app.foxglove.dev"] {
            let (_, head) = upgrade(port, Some(origin))?;
            if !head.starts_with("HTTP/1.1 403") {
                return Err(format!("{origin} was not refused: {head}"));
            }
        }
        let (mut s, head) = upgrade(port, Some("https://viewer.example"))?;
        if !head.starts_with("HTTP/1.1 101") {
            return Err(format!("the allowed origin was refused: {head}"));
        }
        count_exposure_messages(&mut s)
    });
    // The refusal is logged with the origin it named.
    let deadline = Instant::now() + Duration::from_secs(10);
    let logged = |lines: &Mutex<Vec<String>>| {
        lines
            .lock()
            .unwrap()
            .iter()
            .any(|l| l.contains("refused") && l.contains("https://evil.example"))
    };
    while !logged(&lines) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let _ = child.wait();
    let messages = result.unwrap();
    assert!(
        messages >= 10,
        "only {messages} exposure messages streamed to the allowed origin"
    );
    assert!(
        logged(&lines),
        "no warning naming the refused origin: {:?}",
        lines.lock().unwrap()
    );
}
