//! A guard between GStreamer's `rtspsrc` and an RTSP server: rtspsrc believes the sizes
//! a server declares (a `Content-Length: 2000000000` answer took 2 GB of memory) and
//! reads a header line for as long as it keeps coming. The guard listens on loopback,
//! rtspsrc connects to it, and it relays to the server, checking every message the
//! server sends: a head (status line and headers) of at most [`MAX_HEAD`] bytes, a body
//! of at most [`MAX_BODY`] (an SDP is a few hundred bytes), interleaved RTP/RTCP frames
//! (`$`, channel, 16-bit length) passed as they are. Anything else closes both
//! connections and the reason is kept for the camera's error. What rtspsrc sends goes to
//! the server unchanged.
//!
//! RTP over UDP does not pass through the guard: the server sends it to the address the
//! RTSP connection came from, which is this host.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// The largest head (status line and headers) of a server's message.
pub const MAX_HEAD: usize = 16 << 10;
/// The largest body of a server's message.
pub const MAX_BODY: usize = 64 << 10;
/// How long connecting to the server may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);
/// Poll period of the guard's threads (they check the stop flag this often).
const POLL: Duration = Duration::from_millis(50);

/// A running guard; stops (closing every connection) when dropped.
pub struct RtspGuard {
    port: u16,
    stop: Arc<AtomicBool>,
    failure: Arc<Mutex<Option<String>>>,
    conns: Arc<Mutex<Vec<TcpStream>>>,
    thread: Option<JoinHandle<()>>,
}

/// `rtsp://[user@]host[:port]/path` -> (host:port, path with the leading slash).
pub fn split_url(url: &str) -> Option<(String, String)> {
    let rest = url.strip_prefix("rtsp://")?;
    let (authority, path) = match rest.find('/') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, "/"),
    };
    let hostport = authority.rsplit('@').next()?;
    if hostport.is_empty() {
        return None;
    }
    let has_port = match hostport.rfind(':') {
        Some(i) => !hostport[i..].contains(']'),
        None => false,
    };
    let hostport = if has_port {
        hostport.to_string()
    } else {
        format!("{hostport}:554")
    };
    Some((hostport, path.to_string()))
}

impl RtspGuard {
    /// Listens on 127.0.0.1 (any free port) for rtspsrc, relaying to `server`.
    pub fn start(server: &str) -> std::io::Result<Self> {
        let addr = server.to_socket_addrs()?.next().ok_or_else(|| {
            std::io::Error::new(
                ErrorKind::NotFound,
                format!("{server} resolves to no address"),
            )
        })?;
        let listener = TcpListener::bind("127.0.0.1:0")?;
        listener.set_nonblocking(true)?;
        let port = listener.local_addr()?.port();
        let stop = Arc::new(AtomicBool::new(false));
        let failure = Arc::new(Mutex::new(None));
        let conns = Arc::new(Mutex::new(Vec::new()));
        let (s, f, c) = (stop.clone(), failure.clone(), conns.clone());
        let thread = std::thread::Builder::new()
            .name("markhold-rtsp-guard".into())
            .spawn(move || accept_loop(&listener, addr, &s, &f, &c))?;
        Ok(Self {
            port,
            stop,
            failure,
            conns,
            thread: Some(thread),
        })
    }

    /// The port rtspsrc connects to.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Why the guard cut a connection, if it did.
    pub fn failure(&self) -> Option<String> {
        self.failure
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Close every connection now (rtspsrc's reads end at once).
    pub fn close_all(&self) {
        let conns = self
            .conns
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        for c in conns.iter() {
            let _ = c.shutdown(Shutdown::Both);
        }
    }
}

impl Drop for RtspGuard {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.close_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn accept_loop(
    listener: &TcpListener,
    server: SocketAddr,
    stop: &Arc<AtomicBool>,
    failure: &Arc<Mutex<Option<String>>>,
    conns: &Arc<Mutex<Vec<TcpStream>>>,
) {
    let mut relays: Vec<JoinHandle<()>> = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        relays.retain(|t| !t.is_finished());
        match listener.accept() {
            Ok((client, _)) => {
                let upstream = match TcpStream::connect_timeout(&server, CONNECT_TIMEOUT) {
                    Ok(u) => u,
                    Err(e) => {
                        note(failure, format!("connecting to {server}: {e}"));
                        let _ = client.shutdown(Shutdown::Both);
                        continue;
                    }
                };
                let pair = (
                    client.try_clone(),
                    upstream.try_clone(),
                    client.set_nonblocking(false),
                );
                let (Ok(c2), Ok(u2), Ok(())) = pair else {
                    continue;
                };
                {
                    let mut list = conns
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner);
                    list.retain(|c| c.peer_addr().is_ok());
                    if let (Ok(a), Ok(b)) = (client.try_clone(), upstream.try_clone()) {
                        list.push(a);
                        list.push(b);
                    }
                }
                let (s1, s2, f) = (stop.clone(), stop.clone(), failure.clone());
                // rtspsrc -> server: unchanged.
                if let Ok(t) = std::thread::Builder::new()
                    .name("markhold-rtsp-up".into())
                    .spawn(move || copy(client, upstream, &s1))
                {
                    relays.push(t);
                }
                // server -> rtspsrc: checked.
                if let Ok(t) = std::thread::Builder::new()
                    .name("markhold-rtsp-down".into())
                    .spawn(move || {
                        if let Err(why) = checked_copy(u2, c2, server, &s2) {
                            note(&f, why);
                        }
                    })
                {
                    relays.push(t);
                }
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(POLL / 5),
            Err(_) => std::thread::sleep(POLL),
        }
    }
    for t in relays {
        let _ = t.join();
    }
}

fn note(failure: &Mutex<Option<String>>, why: String) {
    tracing::warn!("rtsp guard: {why}");
    let mut f = failure
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    f.get_or_insert(why);
}

/// Reads some bytes, giving up when `stop` is set; 0 at end of stream.
fn read_some(s: &mut TcpStream, buf: &mut [u8], stop: &AtomicBool) -> std::io::Result<usize> {
    let _ = s.set_read_timeout(Some(POLL));
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(0);
        }
        match s.read(buf) {
            Ok(n) => return Ok(n),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) => {}
            Err(e) => return Err(e),
        }
    }
}

fn copy(mut from: TcpStream, mut to: TcpStream, stop: &AtomicBool) {
    let mut buf = [0u8; 16 << 10];
    while let Ok(n) = read_some(&mut from, &mut buf, stop) {
        if n == 0 || to.write_all(&buf[..n]).is_err() {
            break;
        }
    }
    let _ = to.shutdown(Shutdown::Write);
}

/// Where the server's stream is.
enum Part {
    /// At the start of a message or frame.
    Start,
    /// In a head, this many bytes in.
    Head(usize),
    /// In a body or a frame's payload, this many bytes left.
    Body(usize),
    /// In an interleaved frame's header after its `$`, this many bytes read.
    Frame(usize),
}

/// Relays the server's bytes after checking the framing (see the module doc).
fn checked_copy(
    mut from: TcpStream,
    mut to: TcpStream,
    server: SocketAddr,
    stop: &AtomicBool,
) -> Result<(), String> {
    let mut buf = [0u8; 16 << 10];
    let mut part = Part::Start;
    // The head so far (bounded by MAX_HEAD), to find its end and its Content-Length.
    let mut head: Vec<u8> = Vec::with_capacity(1024);
    let mut frame_hdr = [0u8; 3];
    let close = |to: &TcpStream, from: &TcpStream| {
        let _ = to.shutdown(Shutdown::Both);
        let _ = from.shutdown(Shutdown::Both);
    };
    loop {
        let n = match read_some(&mut from, &mut buf, stop) {
            Ok(0) | Err(_) => {
                let _ = to.shutdown(Shutdown::Write);
                return Ok(());
            }
            Ok(n) => n,
        };
        let mut i = 0;
        while i < n {
            match part {
                Part::Start if buf[i] == b'$' => part = Part::Frame(0),
                Part::Start => {
                    head.clear();
                    part = Part::Head(0);
                    continue;
                }
                Part::Frame(k) => {
                    // After '$': channel, then the length (big-endian u16).
                    frame_hdr[k] = buf[i];
                    part = if k == 2 {
                        match usize::from(u16::from_be_bytes([frame_hdr[1], frame_hdr[2]])) {
                            0 => Part::Start,
                            len => Part::Body(len),
                        }
                    } else {
                        Part::Frame(k + 1)
                    };
                }
                Part::Head(k) => {
                    head.push(buf[i]);
                    if k + 1 > MAX_HEAD {
                        close(&to, &from);
                        return Err(format!(
                            "{server} sent a head over {MAX_HEAD} bytes: connection closed"
                        ));
                    }
                    part = Part::Head(k + 1);
                    if head.ends_with(b"\r\n\r\n") || head.ends_with(b"\n\n") {
                        let len = content_length(&head).map_err(|e| {
                            close(&to, &from);
                            format!("{server}: {e}: connection closed")
                        })?;
                        if len > MAX_BODY {
                            close(&to, &from);
                            return Err(format!(
                                "{server} declared a body of {len} bytes (more than {MAX_BODY}): connection closed"
                            ));
                        }
                        part = if len == 0 {
                            Part::Start
                        } else {
                            Part::Body(len)
                        };
                    }
                }
                Part::Body(left) => {
                    let k = left.min(n - i);
                    i += k;
                    part = if left == k {
                        Part::Start
                    } else {
                        Part::Body(left - k)
                    };
                    continue;
                }
            }
            i += 1;
        }
        if to.write_all(&buf[..n]).is_err() {
            let _ = from.shutdown(Shutdown::Both);
            return Ok(());
        }
    }
}

/// The Content-Length of a head (0 without one).
fn content_length(head: &[u8]) -> Result<usize, String> {
    let text = String::from_utf8_lossy(head);
    for line in text.lines() {
        if let Some((k, v)) = line.split_once(':') {
            if k.trim().eq_ignore_ascii_case("content-length") {
                return v
                    .trim()
                    .parse::<usize>()
                    .map_err(|_| "an unreadable Content-Length".to_string());
            }
        }
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_split_into_server_and_path() {
        assert_eq!(
            split_url("rtsp://192.168.2.2:8554/video_stream"),
            Some(("192.168.2.2:8554".into(), "/video_stream".into()))
        );
        assert_eq!(
            split_url("rtsp://user:pw@cam.local/a/b"),
            Some(("cam.local:554".into(), "/a/b".into()))
        );
        assert_eq!(
            split_url("rtsp://[::1]:8554/x"),
            Some(("[::1]:8554".into(), "/x".into()))
        );
        assert_eq!(split_url("rtsp:///x"), None);
    }

    #[test]
    fn content_length_is_read_or_refused() {
        assert_eq!(content_length(b"RTSP/1.0 200 OK\r\nCSeq: 1\r\n\r\n"), Ok(0));
        assert_eq!(
            content_length(b"RTSP/1.0 200 OK\r\ncontent-length: 12\r\n\r\n"),
            Ok(12)
        );
        assert!(content_length(b"RTSP/1.0 200 OK\r\nContent-Length: -1\r\n\r\n").is_err());
    }
}
