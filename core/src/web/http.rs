//! The little HTTP/1.1 the page needs: one request per connection (`Connection: close`),
//! a bounded head (8 KiB, 32 headers) and body (`Content-Length` only, up to what the
//! route accepts), all of it read before a deadline. Parsing is httparse's; the rest is
//! hand-written because the server must stay small and synchronous beside the loop
//! (tiny_http or hyper would do the same with more to audit for bounds).

use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// Request line and headers, bytes.
pub const MAX_HEAD: usize = 8 << 10;
/// Headers per request.
const MAX_HEADERS: usize = 32;
/// One read waits at most this long before the deadline is looked at again.
const READ_SLICE: Duration = Duration::from_millis(500);

/// A request as the routes see it.
#[derive(Debug, Clone, Default)]
pub struct Request {
    pub method: String,
    /// The path without its query (the page's queries only defeat caches).
    pub path: String,
    /// Names in lower case.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Request {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// Why no request was read (each becomes a response, or a closed connection).
#[derive(Debug)]
pub enum ReadError {
    /// The peer closed before a whole head.
    Closed,
    /// Not sent within the deadline.
    Timeout,
    /// 400 with the reason.
    Bad(String),
    /// 413 / 431: more than the route or the server takes.
    TooLarge(String),
    Io(std::io::Error),
}

/// Read one request from `stream` before `deadline`; `max_body(method, path)` is how many
/// body bytes the route takes (0: none).
pub fn read_request(
    stream: &mut TcpStream,
    deadline: Instant,
    max_body: impl Fn(&str, &str) -> usize,
) -> Result<Request, ReadError> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 4096];
    let head_len = loop {
        if let Some(i) = find_head_end(&buf) {
            break i;
        }
        if buf.len() > MAX_HEAD {
            return Err(ReadError::TooLarge(format!(
                "request head over {MAX_HEAD} bytes"
            )));
        }
        match read_some(stream, &mut chunk, deadline)? {
            0 => return Err(ReadError::Closed),
            n => buf.extend_from_slice(&chunk[..n]),
        }
    };
    if head_len > MAX_HEAD {
        return Err(ReadError::TooLarge(format!(
            "request head over {MAX_HEAD} bytes"
        )));
    }
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut req = httparse::Request::new(&mut headers);
    match req.parse(&buf[..head_len]) {
        Ok(httparse::Status::Complete(_)) => {}
        Ok(httparse::Status::Partial) => return Err(ReadError::Bad("incomplete head".into())),
        Err(httparse::Error::TooManyHeaders) => {
            return Err(ReadError::TooLarge(format!(
                "more than {MAX_HEADERS} headers"
            )))
        }
        Err(e) => return Err(ReadError::Bad(e.to_string())),
    }
    let target = req.path.unwrap_or("/");
    let path = target.split_once('?').map_or(target, |(p, _)| p);
    let mut out = Request {
        method: req.method.unwrap_or("").to_string(),
        path: path.to_string(),
        headers: req
            .headers
            .iter()
            .map(|h| {
                (
                    h.name.to_ascii_lowercase(),
                    String::from_utf8_lossy(h.value).into_owned(),
                )
            })
            .collect(),
        body: Vec::new(),
    };
    if out.header("transfer-encoding").is_some() {
        return Err(ReadError::Bad(
            "chunked bodies are not taken: send Content-Length".into(),
        ));
    }
    let len = match out.header("content-length") {
        None => 0,
        Some(v) => v
            .trim()
            .parse::<usize>()
            .map_err(|_| ReadError::Bad(format!("Content-Length {v:?}")))?,
    };
    let limit = max_body(&out.method, &out.path);
    if len > limit {
        return Err(ReadError::TooLarge(format!(
            "a body of {len} bytes; {} {} takes at most {limit}",
            out.method, out.path
        )));
    }
    out.body.reserve_exact(len);
    out.body
        .extend_from_slice(&buf[head_len..buf.len().min(head_len + len)]);
    while out.body.len() < len {
        let want = (len - out.body.len()).min(chunk.len());
        match read_some(stream, &mut chunk[..want], deadline)? {
            0 => return Err(ReadError::Closed),
            n => out.body.extend_from_slice(&chunk[..n]),
        }
    }
    Ok(out)
}

fn find_head_end(buf: &[u8]) -> Option<usize> {
    buf.windows(4).position(|w| w == b"\r\n\r\n").map(|i| i + 4)
}

fn read_some(
    stream: &mut TcpStream,
    buf: &mut [u8],
    deadline: Instant,
) -> Result<usize, ReadError> {
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(ReadError::Timeout);
        }
        stream
            .set_read_timeout(Some(left.min(READ_SLICE)))
            .map_err(ReadError::Io)?;
        match stream.read(buf) {
            Ok(n) => return Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(ReadError::Io(e)),
        }
    }
}

/// A response: status, type, body and extra headers.
#[derive(Debug, Clone)]
pub struct Response {
    pub status: u16,
    pub content_type: &'static str,
    pub body: Vec<u8>,
    pub headers: Vec<(&'static str, String)>,
}

impl Response {
    pub fn new(status: u16, content_type: &'static str, body: impl Into<Vec<u8>>) -> Self {
        Self {
            status,
            content_type,
            body: body.into(),
            headers: Vec::new(),
        }
    }

    pub fn text(status: u16, body: impl Into<String>) -> Self {
        let mut b = body.into().into_bytes();
        b.push(b'\n');
        Self::new(status, "text/plain; charset=utf-8", b)
    }

    pub fn json(status: u16, value: &impl serde::Serialize) -> Self {
        match serde_json::to_vec(value) {
            Ok(b) => Self::new(status, "application/json", b),
            Err(e) => Self::text(500, format!("serializing the answer: {e}")),
        }
    }

    pub fn with_header(mut self, name: &'static str, value: impl Into<String>) -> Self {
        self.headers.push((name, value.into()));
        self
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        409 => "Conflict",
        413 => "Content Too Large",
        422 => "Unprocessable Content",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "",
    }
}

/// Write `r` (head only for HEAD) and close: nothing is cached, nothing kept alive.
pub fn write_response(
    stream: &mut TcpStream,
    r: &Response,
    head_only: bool,
) -> std::io::Result<()> {
    let mut head = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-store\r\n\
         X-Content-Type-Options: nosniff\r\nConnection: close\r\n",
        r.status,
        reason(r.status),
        r.content_type,
        r.body.len()
    );
    for (n, v) in &r.headers {
        head.push_str(n);
        head.push_str(": ");
        head.push_str(v);
        head.push_str("\r\n");
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    if !head_only {
        stream.write_all(&r.body)?;
    }
    stream.flush()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;
    use std::net::TcpListener;

    /// `raw` sent by a client on loopback, read by the server side with `max_body`.
    fn serve(raw: &'static [u8], close: bool, max_body: usize) -> Result<Request, ReadError> {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let client = std::thread::spawn(move || {
            let mut c = TcpStream::connect(addr).unwrap();
            c.write_all(raw).unwrap();
            if close {
                c.shutdown(std::net::Shutdown::Write).unwrap();
            }
            std::thread::sleep(Duration::from_millis(600));
        });
        let (mut s, _) = l.accept().unwrap();
        let r = read_request(
            &mut s,
            Instant::now() + Duration::from_millis(400),
            |_, _| max_body,
        );
        client.join().unwrap();
        r
    }

    #[test]
    fn a_request_with_a_body_is_read_whole() {
        let r = serve(
            b"POST /site/check?x=1 HTTP/1.1\r\nHost: a\r\nContent-Length: 5\r\n\r\nhello",
            false,
            10,
        )
        .unwrap();
        assert_eq!(
            (r.method.as_str(), r.path.as_str()),
            ("POST", "/site/check")
        );
        assert_eq!(r.header("host"), Some("a"));
        assert_eq!(r.body, b"hello");
    }

    #[test]
    fn bounds_and_deadlines_hold() {
        assert!(matches!(
            serve(b"POST / HTTP/1.1\r\nContent-Length: 11\r\n\r\n", false, 10),
            Err(ReadError::TooLarge(_))
        ));
        // A head that never ends, and a body that never comes: the deadline.
        assert!(matches!(
            serve(b"GET / HTTP/1.1\r\nHost: a\r\n", false, 0),
            Err(ReadError::Timeout)
        ));
        assert!(matches!(
            serve(b"POST / HTTP/1.1\r\nContent-Length: 4\r\n\r\nab", false, 10),
            Err(ReadError::Timeout)
        ));
        assert!(matches!(
            serve(b"GET / HTTP/1.1\r\nHost: a", true, 0),
            Err(ReadError::Closed)
        ));
        assert!(matches!(
            serve(
                b"GET / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n",
                false,
                10
            ),
            Err(ReadError::Bad(_))
        ));
        static BIG: [u8; MAX_HEAD + 10] = [b'a'; MAX_HEAD + 10];
        assert!(matches!(serve(&BIG, true, 0), Err(ReadError::TooLarge(_))));
    }
}
