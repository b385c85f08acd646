//! A small HTTP/1.1 client for the camera manager's REST API, bounded in every way a
//! peer could abuse: one deadline for the whole request (connect, write, every read),
//! a size limit on the head and on the body, `Content-Length`, chunked or
//! read-to-close bodies, and peer text made safe to print.
//!
//! Hand-written rather than a crate (ureq would do): the camera manager needs two
//! requests, and the deadline has to cover the whole exchange, which per-read timeouts
//! (the usual knob) do not: a reply dripped a byte at a time never trips them.

use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

/// Limits of one request.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// The whole request: connect, send, and the reply read to its end.
    pub deadline: Duration,
    /// Status line and headers.
    pub max_head: usize,
    /// The body (after de-chunking).
    pub max_body: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum HttpError {
    #[error("{what}: {source}")]
    Io {
        what: &'static str,
        source: std::io::Error,
    },
    #[error("no complete answer within {ms} ms ({got} bytes received)")]
    Deadline { ms: u128, got: usize },
    #[error("the answer's {what} is over {limit} bytes")]
    TooLarge { what: &'static str, limit: usize },
    #[error("not an HTTP answer: {0}")]
    Malformed(String),
}

/// A reply: its status and body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    pub status: u16,
    pub body: Vec<u8>,
}

/// The reader side of a request: every read waits at most until the deadline.
struct Bounded {
    s: TcpStream,
    until: Instant,
    deadline: Duration,
    got: usize,
}

impl Bounded {
    fn timed_out(&self) -> HttpError {
        HttpError::Deadline {
            ms: self.deadline.as_millis(),
            got: self.got,
        }
    }

    /// Reads some bytes into `buf`; 0 at end of stream.
    fn read_some(&mut self, buf: &mut [u8]) -> Result<usize, HttpError> {
        loop {
            let left = self.until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(self.timed_out());
            }
            // A zero timeout means "block forever" to the OS: at least a millisecond.
            let _ = self
                .s
                .set_read_timeout(Some(left.max(Duration::from_millis(1))));
            match self.s.read(buf) {
                Ok(n) => {
                    self.got += n;
                    return Ok(n);
                }
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(source) => {
                    return Err(HttpError::Io {
                        what: "reading the answer",
                        source,
                    })
                }
            }
        }
    }
}

/// What the reader holds: bytes read but not consumed, then the socket.
struct Input {
    r: Bounded,
    buf: Vec<u8>,
    pos: usize,
    eof: bool,
}

impl Input {
    /// Ensure at least one unconsumed byte (false at end of stream).
    fn fill(&mut self) -> Result<bool, HttpError> {
        if self.pos < self.buf.len() {
            return Ok(true);
        }
        if self.eof {
            return Ok(false);
        }
        self.buf.clear();
        self.pos = 0;
        self.buf.resize(4096, 0);
        let n = self.r.read_some(&mut self.buf)?;
        self.buf.truncate(n);
        self.eof = n == 0;
        Ok(n > 0)
    }

    /// A line ending in CRLF (or LF), without it, at most `limit` bytes.
    fn line(&mut self, limit: usize, what: &'static str) -> Result<Vec<u8>, HttpError> {
        let mut out = Vec::new();
        loop {
            if !self.fill()? {
                return Err(HttpError::Malformed(format!("the {what} ends early")));
            }
            let avail = &self.buf[self.pos..];
            if let Some(i) = avail.iter().position(|&b| b == b'\n') {
                out.extend_from_slice(&avail[..i]);
                self.pos += i + 1;
                if out.last() == Some(&b'\r') {
                    out.pop();
                }
                if out.len() > limit {
                    return Err(HttpError::TooLarge { what, limit });
                }
                return Ok(out);
            }
            out.extend_from_slice(avail);
            self.pos = self.buf.len();
            if out.len() > limit {
                return Err(HttpError::TooLarge { what, limit });
            }
        }
    }

    /// Exactly `n` bytes appended to `out`.
    fn exact(&mut self, n: usize, out: &mut Vec<u8>) -> Result<(), HttpError> {
        let mut left = n;
        while left > 0 {
            if !self.fill()? {
                return Err(HttpError::Malformed(format!(
                    "the body ends {left} bytes early"
                )));
            }
            let avail = &self.buf[self.pos..];
            let k = avail.len().min(left);
            out.extend_from_slice(&avail[..k]);
            self.pos += k;
            left -= k;
        }
        Ok(())
    }

    /// Everything to the end of the stream, at most `limit` bytes.
    fn read_to_close(&mut self, limit: usize, out: &mut Vec<u8>) -> Result<(), HttpError> {
        while self.fill()? {
            let avail = &self.buf[self.pos..];
            if out.len() + avail.len() > limit {
                return Err(HttpError::TooLarge {
                    what: "body",
                    limit,
                });
            }
            out.extend_from_slice(avail);
            self.pos = self.buf.len();
        }
        Ok(())
    }
}

/// Longest chunk-size line accepted (hex digits and extensions).
const MAX_CHUNK_LINE: usize = 256;

/// One request with `Connection: close`; the reply whatever its status.
pub fn request(
    addr: SocketAddr,
    host: &str,
    method: &str,
    path: &str,
    body: &[u8],
    limits: Limits,
) -> Result<Reply, HttpError> {
    let t0 = Instant::now();
    let until = t0 + limits.deadline;
    let over = |got| HttpError::Deadline {
        ms: limits.deadline.as_millis(),
        got,
    };
    // A timeout is the deadline passing; any other error names what was being done.
    let failed = |what| {
        move |source: std::io::Error| {
            if matches!(source.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) {
                over(0)
            } else {
                HttpError::Io { what, source }
            }
        }
    };
    let mut s = TcpStream::connect_timeout(&addr, limits.deadline).map_err(failed("connecting"))?;
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    let left = until.saturating_duration_since(Instant::now());
    if left.is_zero() {
        return Err(over(0));
    }
    let _ = s.set_write_timeout(Some(left));
    let _ = s.set_nodelay(true);
    s.write_all(head.as_bytes())
        .and_then(|()| s.write_all(body))
        .map_err(failed("sending the request"))?;
    let mut input = Input {
        r: Bounded {
            s,
            until,
            deadline: limits.deadline,
            got: 0,
        },
        buf: Vec::with_capacity(4096),
        pos: 0,
        eof: false,
    };
    read_reply(&mut input, limits)
}

fn read_reply(input: &mut Input, limits: Limits) -> Result<Reply, HttpError> {
    let status_line = input.line(limits.max_head, "head")?;
    let status_text = String::from_utf8_lossy(&status_line);
    let mut parts = status_text.split_whitespace();
    let status = match (parts.next(), parts.next().map(str::parse::<u16>)) {
        (Some(v), Some(Ok(code))) if v.starts_with("HTTP/1.") && (100..600).contains(&code) => code,
        _ => {
            return Err(HttpError::Malformed(format!(
                "status line {}",
                sanitize(&status_line, 80)
            )))
        }
    };
    let mut head_bytes = status_line.len();
    let mut content_length = None;
    let mut chunked = false;
    loop {
        let line = input.line(limits.max_head, "head")?;
        head_bytes += line.len() + 2;
        if head_bytes > limits.max_head {
            return Err(HttpError::TooLarge {
                what: "head",
                limit: limits.max_head,
            });
        }
        if line.is_empty() {
            break;
        }
        let text = String::from_utf8_lossy(&line);
        let Some((name, value)) = text.split_once(':') else {
            return Err(HttpError::Malformed(format!(
                "header line {}",
                sanitize(&line, 80)
            )));
        };
        let (name, value) = (name.trim().to_ascii_lowercase(), value.trim());
        if name == "content-length" {
            let n: u64 = value.parse().map_err(|_| {
                HttpError::Malformed(format!("Content-Length {}", sanitize(value.as_bytes(), 40)))
            })?;
            if n > limits.max_body as u64 {
                return Err(HttpError::TooLarge {
                    what: "body",
                    limit: limits.max_body,
                });
            }
            content_length = Some(n as usize);
        } else if name == "transfer-encoding" {
            chunked = value
                .rsplit(',')
                .next()
                .is_some_and(|v| v.trim().eq_ignore_ascii_case("chunked"));
            if !chunked {
                return Err(HttpError::Malformed(format!(
                    "Transfer-Encoding {}",
                    sanitize(value.as_bytes(), 40)
                )));
            }
        }
    }
    let mut body = Vec::new();
    if chunked {
        read_chunked(input, limits.max_body, &mut body)?;
    } else if let Some(n) = content_length {
        input.exact(n, &mut body)?;
    } else {
        input.read_to_close(limits.max_body, &mut body)?;
    }
    Ok(Reply { status, body })
}

/// A chunked body (RFC 9112 section 7.1), trailers skipped.
fn read_chunked(input: &mut Input, limit: usize, body: &mut Vec<u8>) -> Result<(), HttpError> {
    loop {
        let line = input.line(MAX_CHUNK_LINE, "chunk size line")?;
        let text = String::from_utf8_lossy(&line);
        let hex = text.split(';').next().unwrap_or("").trim();
        let size = usize::from_str_radix(hex, 16).map_err(|_| {
            HttpError::Malformed(format!("chunk size {}", sanitize(hex.as_bytes(), 40)))
        })?;
        if size == 0 {
            // Trailer fields up to the empty line.
            let mut trailers = 0usize;
            loop {
                let t = input.line(MAX_CHUNK_LINE * 16, "trailer")?;
                trailers += t.len();
                if t.is_empty() {
                    return Ok(());
                }
                if trailers > MAX_CHUNK_LINE * 16 {
                    return Err(HttpError::TooLarge {
                        what: "trailer",
                        limit: MAX_CHUNK_LINE * 16,
                    });
                }
            }
        }
        if body.len().saturating_add(size) > limit {
            return Err(HttpError::TooLarge {
                what: "body",
                limit,
            });
        }
        input.exact(size, body)?;
        let end = input.line(2, "chunk end")?;
        if !end.is_empty() {
            return Err(HttpError::Malformed("a chunk longer than its size".into()));
        }
    }
}

/// Peer text made safe for a terminal and a log line: printable ASCII kept, other bytes
/// escaped (`\xNN`, `\n`), cut after `max` characters with the length said.
pub fn sanitize(bytes: &[u8], max: usize) -> String {
    use std::fmt::Write as _;
    let mut out = String::with_capacity(max.min(bytes.len()) + 24);
    for &b in bytes {
        if out.len() >= max {
            let _ = write!(out, "... ({} bytes)", bytes.len());
            return out;
        }
        match b {
            b' '..=b'~' => out.push(b as char),
            b'\n' => out.push_str("\\n"),
            b'\r' => out.push_str("\\r"),
            b'\t' => out.push_str("\\t"),
            _ => {
                let _ = write!(out, "\\x{b:02x}");
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peer_text_is_escaped_and_cut() {
        assert_eq!(sanitize(b"ok", 10), "ok");
        assert_eq!(sanitize(b"\x1b[31mred\n", 40), "\\x1b[31mred\\n");
        let long = vec![b'a'; 1000];
        let s = sanitize(&long, 20);
        assert!(s.starts_with("aaaaaaaaaaaaaaaaaaaa... (1000 bytes)"), "{s}");
    }
}
