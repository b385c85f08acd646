//! `markhold hil --foxglove`: a simulated run watched live. A raw WebSocket client (the
//! Foxglove protocol, no client crate) subscribes to the exposure channel while the run
//! goes on and must receive messages from it.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::Stdio;
use std::time::{Duration, Instant};

use common::{markhold, site_path, ws_read_frame};

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

#[test]
fn hil_foxglove_streams_the_exposure_channel_while_running() {
    let mut child = markhold()
        .args(["hil", "--site"])
        .arg(site_path())
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
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("ws://127.0.0.1:").nth(1) {
                let _ = tx.send(rest.trim().parse::<u16>().ok());
            }
        }
    });
    let port = rx.recv_timeout(Duration::from_secs(60));
    let result = (|| -> Result<u64, String> {
        let port = port
            .map_err(|_| "no live-view address on stderr within 60 s".to_string())?
            .ok_or("unparsable port")?;
        let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
        s.set_read_timeout(Some(Duration::from_secs(10)))
            .map_err(|e| e.to_string())?;
        write!(
            s,
            "GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
             Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
        )
        .map_err(|e| e.to_string())?;
        let mut head = Vec::new();
        let mut b = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            s.read_exact(&mut b).map_err(|e| e.to_string())?;
            head.push(b[0]);
        }
        let head = String::from_utf8_lossy(&head).to_string();
        if !head.starts_with("HTTP/1.1 101") {
            return Err(head);
        }
        // Find the exposure channel's id in the advertisement, subscribe, count binary
        // messageData frames (opcode 1 of the binary protocol) for that subscription.
        let deadline = Instant::now() + Duration::from_secs(30);
        let mut subscribed = false;
        let mut messages = 0u64;
        while Instant::now() < deadline && messages < 10 {
            let (op, data) = ws_read_frame(&mut s).map_err(|e| e.to_string())?;
            if op == 1 && !subscribed {
                let v: serde_json::Value =
                    serde_json::from_slice(&data).map_err(|e| e.to_string())?;
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
                    &mut s,
                    &format!(
                        r#"{{"op":"subscribe","subscriptions":[{{"id":7,"channelId":{id}}}]}}"#
                    ),
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
    })();
    let _ = child.kill();
    let _ = child.wait();
    let messages = result.unwrap();
    assert!(
        messages >= 10,
        "only {messages} exposure messages streamed during the run"
    );
}
