//! Byte transports for the vehicle link: URL parsing, writers that put bytes on the wire
//! from the caller's thread, UDP read in `tick` on the caller's thread, and tokio reader
//! tasks (TCP, serial, optionally UDP) that decode frames into a bounded queue.

use std::io::Write;
use std::net::{SocketAddr, ToSocketAddrs};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{
    AsyncMavlinkReader, MAVLinkMessageRaw, MavHeader, MavlinkReader, Message, SigningData,
};
use tokio::io::{AsyncRead, AsyncWriteExt, ReadBuf};
use tokio::sync::Notify;

use crate::error::AutopilotError;

/// Wall-clock waits bounding reconnect attempts (never used for control timing).
const RECONNECT_BACKOFF: Duration = Duration::from_millis(500);
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);
/// Decoded messages waiting for `tick`; beyond this the oldest traffic is dropped.
const QUEUE_LEN: usize = 1024;
/// Largest MAVLink 2 frame with signature.
pub(crate) const MAX_FRAME: usize = 280;
/// Receive buffer asked for on UDP sockets (SO_RCVBUF). The kernel's default (about
/// 200 kB) holds some 160 small datagrams on loopback: a burst of traffic between two
/// ticks (10 000 messages/s at 30 frames/s is 333 per tick) overflowed it and took the
/// vehicle's heartbeats with it. Linux caps the request at `net.core.rmem_max` (and
/// doubles it for bookkeeping); the size obtained is logged and kept.
pub const UDP_RECV_BUFFER_BYTES: usize = 4 << 20;

/// A parsed link URL.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Endpoint {
    /// Listen on a UDP address; reply to the last peer that spoke.
    UdpIn(String),
    /// Send to a UDP address from an ephemeral port.
    UdpOut(String),
    /// Connect to a TCP server (SITL 5760, BlueOS 5777).
    TcpOut(String),
    /// Accept one TCP client at a time.
    TcpIn(String),
    /// Serial device and baud rate.
    Serial {
        /// Device path, e.g. /dev/ttyACM0.
        path: String,
        /// Baud rate.
        baud: u32,
    },
}

fn bad(url: &str, reason: impl Into<String>) -> AutopilotError {
    AutopilotError::InvalidUrl {
        url: url.to_string(),
        reason: reason.into(),
    }
}

fn check_host_port(url: &str, hp: &str) -> Result<String, AutopilotError> {
    let (host, port) = hp
        .rsplit_once(':')
        .ok_or_else(|| bad(url, "expected HOST:PORT"))?;
    if host.is_empty() {
        return Err(bad(url, "empty host"));
    }
    port.parse::<u16>()
        .map_err(|_| bad(url, format!("port `{port}` is not a number 0..65535")))?;
    Ok(hp.to_string())
}

/// The connection strings markhold accepts, as named in every refusal. They mean what
/// pymavlink's `mavutil.mavlink_connection` and MAVProxy's `--master` make of them.
pub const URL_FORMS: &str = "udpin:HOST:PORT or udp:HOST:PORT (listen), \
udpout:HOST:PORT (send to), tcp:HOST:PORT or tcpout:HOST:PORT (connect), \
tcpin:HOST:PORT (accept), serial:DEVICE:BAUD, serial:DEVICE,BAUD or /dev/DEVICE,BAUD";

/// Schemes other tools know that markhold does not implement.
const NOT_IMPLEMENTED: [(&str, &str); 5] = [
    (
        "udpbcast",
        "UDP broadcast is not implemented: send to the vehicle with udpout:VEHICLE_IP:PORT, \
         or listen with udpin:0.0.0.0:PORT",
    ),
    ("mcast", "UDP multicast is not implemented"),
    ("ws", "WebSocket links are not implemented"),
    ("wss", "WebSocket links are not implemented"),
    ("wsserver", "WebSocket links are not implemented"),
];

/// A refusal that names the accepted forms.
fn refuse(url: &str, reason: impl std::fmt::Display) -> AutopilotError {
    bad(url, format!("{reason}; use one of: {URL_FORMS}"))
}

/// `DEVICE:BAUD` or `DEVICE,BAUD` (a comma first, as in pymavlink and MAVProxy).
fn parse_serial(url: &str, rest: &str) -> Result<Endpoint, AutopilotError> {
    let (path, baud) = rest
        .rsplit_once(',')
        .or_else(|| rest.rsplit_once(':'))
        .ok_or_else(|| {
            refuse(
                url,
                format!("serial device `{rest}` has no baud rate (e.g. {rest},115200)"),
            )
        })?;
    if path.is_empty() {
        return Err(bad(url, "empty serial device"));
    }
    let baud: u32 = baud
        .parse()
        .map_err(|_| bad(url, format!("baud `{baud}` is not a number")))?;
    if baud == 0 {
        return Err(bad(url, "baud must be > 0"));
    }
    Ok(Endpoint::Serial {
        path: path.to_string(),
        baud,
    })
}

impl Endpoint {
    /// Parses a connection string the way pymavlink's `mavutil.mavlink_connection` and
    /// MAVProxy's `--master` read it: `udpin:` and `udp:` listen (HOST:PORT is the local
    /// address), `udpout:` sends to HOST:PORT, `tcp:` (also `tcpout:`) connects, `tcpin:`
    /// accepts; a serial device is `serial:DEVICE:BAUD`, `serial:DEVICE,BAUD` or a path
    /// `/dev/...,BAUD` (or `:BAUD`). Refused, naming the accepted forms: a bare HOST:PORT
    /// (pymavlink listens on it, MAVProxy's `--out` sends to it), a device without a baud
    /// rate, and the schemes markhold does not implement (`udpbcast:`, `mcast:`, `ws:`).
    pub fn parse(url: &str) -> Result<Self, AutopilotError> {
        if url.starts_with('/') {
            return parse_serial(url, url);
        }
        let Some((scheme, rest)) = url.split_once(':') else {
            return Err(refuse(url, "expected SCHEME:ADDRESS"));
        };
        match scheme {
            "udpin" | "udp" => Ok(Self::UdpIn(check_host_port(url, rest)?)),
            "udpout" => Ok(Self::UdpOut(check_host_port(url, rest)?)),
            "tcp" | "tcpout" => Ok(Self::TcpOut(check_host_port(url, rest)?)),
            "tcpin" => Ok(Self::TcpIn(check_host_port(url, rest)?)),
            "serial" => parse_serial(url, rest),
            _ => {
                if let Some((_, why)) = NOT_IMPLEMENTED.iter().find(|(s, _)| *s == scheme) {
                    return Err(refuse(url, format!("`{scheme}:` is refused: {why}")));
                }
                if !rest.is_empty() && rest.bytes().all(|b| b.is_ascii_digit()) {
                    return Err(refuse(
                        url,
                        format!(
                            "a bare HOST:PORT is ambiguous (pymavlink listens on it, MAVProxy's \
                             --out sends to it): write udpin:{url} to listen or udpout:{url} \
                             to send"
                        ),
                    ));
                }
                Err(refuse(url, format!("unknown scheme `{scheme}`")))
            }
        }
    }
}

fn resolve(url: &str, hp: &str) -> Result<SocketAddr, AutopilotError> {
    hp.to_socket_addrs()
        .map_err(|e| bad(url, format!("cannot resolve `{hp}`: {e}")))?
        .next()
        .ok_or_else(|| bad(url, format!("`{hp}` resolves to no address")))
}

/// What the reader tasks hand to the link.
// Unboxed on purpose: the bounded queue's slots are allocated once, messages are not.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub(crate) enum Incoming {
    /// A decoded message, with the frame's bytes (for the raw tap).
    Msg(MavHeader, MavMessage, FrameBytes),
    /// The byte stream (TCP, serial) came up.
    Connected(String),
    /// The byte stream went down; the task reconnects by itself.
    Disconnected(String),
}

/// One frame's bytes by value (no allocation), magic to signature.
#[derive(Clone, Copy)]
pub(crate) struct FrameBytes {
    len: u16,
    bytes: [u8; MAX_FRAME],
}

impl std::fmt::Debug for FrameBytes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FrameBytes({} bytes)", self.len)
    }
}

impl FrameBytes {
    fn of(raw: &MAVLinkMessageRaw) -> Self {
        let b = match raw {
            MAVLinkMessageRaw::V1(r) => r.raw_bytes(),
            MAVLinkMessageRaw::V2(r) => r.raw_bytes(),
        };
        let n = b.len().min(MAX_FRAME);
        let mut bytes = [0u8; MAX_FRAME];
        bytes[..n].copy_from_slice(&b[..n]);
        Self {
            len: n as u16,
            bytes,
        }
    }

    pub(crate) fn as_slice(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }
}

/// Counters shared with the tasks.
#[derive(Debug, Default)]
pub(crate) struct TaskCounters {
    pub(crate) dropped_rx: AtomicU64,
    pub(crate) parse_errors: AtomicU64,
    pub(crate) reconnects: AtomicU64,
    /// Frames dropped by signing: signed with another key, or replayed.
    pub(crate) bad_signature: AtomicU64,
    /// Frames dropped by signing: unsigned (or MAVLink 1) while signing is on.
    pub(crate) unsigned: AtomicU64,
    /// Why the last connect (tcp) or open (serial) failed; cleared when one succeeds.
    pub(crate) last_error: Mutex<Option<String>>,
    /// The link is closing: a stream that ends is not made again.
    pub(crate) closing: std::sync::atomic::AtomicBool,
}

impl TaskCounters {
    fn set_error(&self, e: Option<String>) {
        if let Ok(mut g) = self.last_error.lock() {
            *g = e;
        }
    }
}

/// Verify (with signing on) and parse one CRC-valid raw frame; rejections are counted.
/// MAVLink 1 and unsigned MAVLink 2 follow the config's `allow_unsigned` (false here).
pub(crate) fn accept(
    raw: &MAVLinkMessageRaw,
    signing: Option<&SigningData>,
    counters: &TaskCounters,
) -> Option<(MavHeader, MavMessage)> {
    if let Some(sd) = signing {
        let ok = match raw {
            MAVLinkMessageRaw::V1(_) => false,
            MAVLinkMessageRaw::V2(r) => sd.verify_signature(r),
        };
        if !ok {
            let signed =
                matches!(raw, MAVLinkMessageRaw::V2(r) if r.incompatibility_flags() & 0x01 != 0);
            let c = if signed {
                &counters.bad_signature
            } else {
                &counters.unsigned
            };
            c.fetch_add(1, Ordering::Relaxed);
            return None;
        }
    }
    let h = MavHeader {
        system_id: raw.system_id(),
        component_id: raw.component_id(),
        sequence: raw.sequence(),
    };
    match MavMessage::parse(raw.version(), raw.message_id(), raw.payload()) {
        Ok(m) => Some((h, m)),
        Err(e) => {
            counters.parse_errors.fetch_add(1, Ordering::Relaxed);
            tracing::debug!(error = %e, "mavlink parse error");
            None
        }
    }
}

/// Ask for a larger receive buffer on a UDP socket; returns the size the kernel granted.
fn grow_recv_buffer(sock: &std::net::UdpSocket) -> Option<usize> {
    let s = socket2::SockRef::from(sock);
    if let Err(e) = s.set_recv_buffer_size(UDP_RECV_BUFFER_BYTES) {
        tracing::warn!(error = %e, "SO_RCVBUF not set");
    }
    let got = s.recv_buffer_size().ok();
    tracing::debug!(asked = UDP_RECV_BUFFER_BYTES, ?got, "udp receive buffer");
    got
}

/// Where outgoing bytes go.
pub(crate) enum Writer {
    Udp {
        sock: std::net::UdpSocket,
        dest: Arc<Mutex<Option<SocketAddr>>>,
        /// udpout: the socket is connected to the vehicle, so `send` skips the per-packet
        /// route lookup and the lock.
        connected: bool,
    },
    Tcp {
        stream: Arc<Mutex<TcpSlot>>,
        /// Connection generation the pending remainder belongs to.
        gen: u64,
        pending: Vec<u8>,
    },
    Serial {
        tx: tokio::sync::mpsc::Sender<([u8; MAX_FRAME], usize)>,
    },
}

/// The current TCP connection, replaced by the task on every (re)connect.
#[derive(Debug, Default)]
pub(crate) struct TcpSlot {
    stream: Option<std::net::TcpStream>,
    gen: u64,
}

/// Outcome of one write.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum WriteOutcome {
    /// On the wire (or, for serial, handed to the writer task).
    Sent,
    /// No peer yet (udpin before anyone spoke, TCP not connected).
    NoPeer,
    /// Transport buffers full: frame dropped whole.
    Dropped,
}

const TCP_PENDING_CAP: usize = 16 * 1024;

impl Writer {
    pub(crate) fn write(&mut self, bytes: &[u8]) -> std::io::Result<WriteOutcome> {
        match self {
            Writer::Udp {
                sock,
                dest,
                connected,
            } => {
                let r = if *connected {
                    sock.send(bytes)
                } else {
                    let d = match dest.lock() {
                        Ok(g) => *g,
                        Err(p) => *p.into_inner(),
                    };
                    let Some(d) = d else {
                        return Ok(WriteOutcome::NoPeer);
                    };
                    sock.send_to(bytes, d)
                };
                match r {
                    Ok(_) => Ok(WriteOutcome::Sent),
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        Ok(WriteOutcome::Dropped)
                    }
                    // ICMP port unreachable from an earlier datagram: the vehicle is not
                    // listening yet; heartbeat loss handles it.
                    Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {
                        Ok(WriteOutcome::Dropped)
                    }
                    Err(e) => Err(e),
                }
            }
            Writer::Tcp {
                stream,
                gen,
                pending,
            } => {
                let mut g = match stream.lock() {
                    Ok(g) => g,
                    Err(p) => p.into_inner(),
                };
                if g.gen != *gen {
                    // A new connection: half a frame from the old one would only be noise.
                    pending.clear();
                    *gen = g.gen;
                }
                let Some(s) = g.stream.as_mut() else {
                    pending.clear();
                    return Ok(WriteOutcome::NoPeer);
                };
                // Keep frames whole and in order: finish the remainder of an earlier one.
                if !pending.is_empty() {
                    match s.write(pending) {
                        Ok(n) => {
                            pending.drain(..n);
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                        Err(_) => {
                            pending.clear();
                            return Ok(WriteOutcome::Dropped);
                        }
                    }
                }
                if !pending.is_empty() {
                    if pending.len() + bytes.len() > TCP_PENDING_CAP {
                        return Ok(WriteOutcome::Dropped);
                    }
                    pending.extend_from_slice(bytes);
                    return Ok(WriteOutcome::Sent);
                }
                match s.write(bytes) {
                    Ok(n) => {
                        if n < bytes.len() {
                            pending.extend_from_slice(&bytes[n..]);
                        }
                        Ok(WriteOutcome::Sent)
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        pending.extend_from_slice(bytes);
                        Ok(WriteOutcome::Sent)
                    }
                    // The reader task sees the broken stream and reconnects.
                    Err(_) => Ok(WriteOutcome::Dropped),
                }
            }
            Writer::Serial { tx } => {
                let mut f = [0u8; MAX_FRAME];
                let n = bytes.len().min(MAX_FRAME);
                f[..n].copy_from_slice(&bytes[..n]);
                match tx.try_send((f, n)) {
                    Ok(()) => Ok(WriteOutcome::Sent),
                    Err(_) => Ok(WriteOutcome::Dropped),
                }
            }
        }
    }

    /// Flushes a TCP remainder, if any.
    pub(crate) fn flush(&mut self) {
        if let Writer::Tcp { pending, .. } = self {
            if !pending.is_empty() {
                let _ = self.write(&[]);
            }
        }
    }
}

/// A running transport: the runtime with its reader task, the writer, and the queue.
pub(crate) struct Transport {
    rt: Option<tokio::runtime::Runtime>,
    pub(crate) writer: Writer,
    pub(crate) rx: Receiver<Incoming>,
    pub(crate) counters: Arc<TaskCounters>,
    reconnect: Arc<Notify>,
    local_addr: Option<SocketAddr>,
    /// UDP is connectionless: it is "connected" from the start.
    pub(crate) always_connected: bool,
    /// UDP read on the caller's thread by `tick` (instead of a task).
    tick_rx: Option<TickReceiver>,
    /// SO_RCVBUF the kernel granted the UDP socket.
    pub(crate) udp_recv_buffer: Option<usize>,
}

/// Read-ahead for datagrams read in `tick`: several full datagrams.
const TICK_READ_CAPACITY: usize = 64 * 1024;

/// The peer of a listening UDP link (`udpin:`): nobody until a CRC-valid frame (with a
/// verified signature when signing is on) comes from the expected vehicle system and
/// component ids; that sender is then the peer for good, and datagrams from any other
/// address are dropped before they are parsed. Before that, only such frames pass.
#[derive(Debug)]
pub(crate) struct PeerGate {
    /// Where replies go (shared with the writer).
    dest: Arc<Mutex<Option<SocketAddr>>>,
    /// Sender of the datagram read last (the one that completed the frame being parsed).
    last_from: Option<SocketAddr>,
    adopted: Option<SocketAddr>,
    vehicle: (u8, u8),
}

impl PeerGate {
    pub(crate) fn new(dest: Arc<Mutex<Option<SocketAddr>>>, vehicle: (u8, u8)) -> Self {
        Self {
            dest,
            last_from: None,
            adopted: None,
            vehicle,
        }
    }

    /// A datagram from `from` arrived: false when it must be dropped unread.
    pub(crate) fn datagram(&mut self, from: SocketAddr) -> bool {
        match self.adopted {
            Some(peer) if peer != from => false,
            _ => {
                self.last_from = Some(from);
                true
            }
        }
    }

    /// A valid frame with `header` was parsed from the last datagram: whether it may go
    /// to the link. The first one from the vehicle's ids makes its sender the peer.
    pub(crate) fn frame(&mut self, header: &MavHeader) -> bool {
        if self.adopted.is_some() {
            return true;
        }
        if (header.system_id, header.component_id) != (u32::from(self.vehicle.0), self.vehicle.1) {
            return false;
        }
        let Some(from) = self.last_from else {
            return false;
        };
        self.adopted = Some(from);
        if let Ok(mut d) = self.dest.lock() {
            *d = Some(from);
        }
        tracing::info!(peer = %from, "udpin: vehicle peer adopted");
        true
    }
}

pub(crate) fn gate_datagram(gate: &Option<Arc<Mutex<PeerGate>>>, from: SocketAddr) -> bool {
    match gate {
        Some(g) => g.lock().map(|mut g| g.datagram(from)).unwrap_or(false),
        None => true,
    }
}

pub(crate) fn gate_frame(gate: Option<&Mutex<PeerGate>>, header: &MavHeader) -> bool {
    match gate {
        Some(g) => g.lock().map(|mut g| g.frame(header)).unwrap_or(false),
        None => true,
    }
}

/// Non-blocking datagram source for the frame reader; for udpin, filtered by the gate.
struct UdpSrc {
    sock: std::net::UdpSocket,
    gate: Option<Arc<Mutex<PeerGate>>>,
}

impl std::io::Read for UdpSrc {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        loop {
            match self.sock.recv_from(buf) {
                Ok((n, addr)) => {
                    if !gate_datagram(&self.gate, addr) {
                        continue;
                    }
                    return Ok(n);
                }
                // ICMP port unreachable from an earlier send: not a receive error.
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => continue,
                Err(e) => return Err(e),
            }
        }
    }
}

struct TickReceiver {
    reader: MavlinkReader<UdpSrc>,
    gate: Option<Arc<Mutex<PeerGate>>>,
    signing: Option<Arc<SigningData>>,
    /// The bytes of the last frame `poll_tick` returned (for a raw tap).
    last: [u8; MAX_FRAME],
    last_len: usize,
}

/// How [`Transport::close`] went.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Closed {
    /// "udp", "tcp" or "serial".
    pub(crate) kind: &'static str,
    /// Every byte handed to the transport went to the socket or device.
    pub(crate) flushed: bool,
    /// TCP: the vehicle closed its side after reading ours (no reset possible).
    pub(crate) peer_closed: bool,
}

/// Write `pending` out to `s` (non-blocking) until done or `deadline`.
fn write_out(mut s: &std::net::TcpStream, pending: &mut Vec<u8>, deadline: Instant) -> bool {
    while !pending.is_empty() {
        match s.write(pending) {
            Ok(0) => return false,
            Ok(n) => {
                pending.drain(..n);
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    return false;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            Err(_) => return false,
        }
    }
    true
}

/// Wait until the transport task says its stream ended (its count of ended streams
/// passes `ended_before`) or `deadline`; what it queues meanwhile is dropped.
fn wait_stream_end(
    counters: &TaskCounters,
    rx: &Receiver<Incoming>,
    ended_before: u64,
    deadline: Instant,
) -> bool {
    loop {
        while rx.try_recv().is_ok() {}
        if counters.reconnects.load(Ordering::Acquire) > ended_before {
            return true;
        }
        if Instant::now() >= deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

impl Transport {
    /// Close the link so that nothing already written is lost, within `timeout`:
    /// TCP writes out any remainder, shuts its sending side (the vehicle reads every
    /// byte before the end of the stream) and reads on until the vehicle closes its
    /// side, because a socket closed with unread received data sends a reset; serial
    /// lets its writer task write and flush what is queued. UDP datagrams are already
    /// on the wire. The transport task does not reconnect afterwards.
    pub(crate) fn close(&mut self, timeout: Duration) -> Closed {
        let deadline = Instant::now() + timeout;
        let ended_before = self.counters.reconnects.load(Ordering::Acquire);
        self.counters.closing.store(true, Ordering::Release);
        match &mut self.writer {
            Writer::Udp { .. } => Closed {
                kind: "udp",
                flushed: true,
                peer_closed: false,
            },
            Writer::Tcp {
                stream, pending, ..
            } => {
                let s = match stream.lock() {
                    Ok(g) => g.stream.as_ref().and_then(|s| s.try_clone().ok()),
                    Err(p) => p
                        .into_inner()
                        .stream
                        .as_ref()
                        .and_then(|s| s.try_clone().ok()),
                };
                let Some(s) = s else {
                    let flushed = pending.is_empty();
                    pending.clear();
                    return Closed {
                        kind: "tcp",
                        flushed,
                        peer_closed: false,
                    };
                };
                let flushed = write_out(&s, pending, deadline);
                pending.clear();
                let _ = s.shutdown(std::net::Shutdown::Write);
                let peer_closed = wait_stream_end(&self.counters, &self.rx, ended_before, deadline);
                Closed {
                    kind: "tcp",
                    flushed,
                    peer_closed,
                }
            }
            Writer::Serial { tx } => {
                // The writer task ends once its sender is gone and the queue written.
                let (closed, _) = tokio::sync::mpsc::channel(1);
                drop(std::mem::replace(tx, closed));
                let flushed = wait_stream_end(&self.counters, &self.rx, ended_before, deadline);
                Closed {
                    kind: "serial",
                    flushed,
                    peer_closed: false,
                }
            }
        }
    }
}

impl Drop for Transport {
    fn drop(&mut self) {
        // Not closed by `close` (an early return, a panic): at least end the TCP stream
        // after what was written, before the socket goes.
        if let Writer::Tcp {
            stream, pending, ..
        } = &mut self.writer
        {
            if let Ok(g) = stream.lock() {
                if let Some(s) = g.stream.as_ref() {
                    let _ = write_out(s, pending, Instant::now());
                    let _ = s.shutdown(std::net::Shutdown::Write);
                }
            }
        }
        if let Some(rt) = self.rt.take() {
            // Never blocks, so the link may be dropped inside an async context too.
            rt.shutdown_background();
        }
    }
}

fn push(tx: &SyncSender<Incoming>, counters: &TaskCounters, m: Incoming) {
    match tx.try_send(m) {
        Ok(()) => {}
        Err(TrySendError::Full(_)) => {
            counters.dropped_rx.fetch_add(1, Ordering::Relaxed);
        }
        Err(TrySendError::Disconnected(_)) => {}
    }
}

/// Reads frames until the source fails; returns why.
async fn pump<R: AsyncRead + Unpin>(
    reader: &mut AsyncMavlinkReader<R>,
    signing: Option<&SigningData>,
    gate: Option<&Mutex<PeerGate>>,
    tx: &SyncSender<Incoming>,
    counters: &TaskCounters,
) -> String {
    loop {
        match reader.read_any_raw_message::<MavMessage>().await {
            Ok(raw) => {
                if let Some((h, m)) = accept(&raw, signing, counters) {
                    if gate_frame(gate, &h) {
                        push(tx, counters, Incoming::Msg(h, m, FrameBytes::of(&raw)));
                    }
                }
            }
            Err(MessageReadError::Io(e)) => return e.to_string(),
            Err(MessageReadError::Parse(e)) => {
                counters.parse_errors.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(error = %e, "mavlink parse error");
            }
        }
    }
}

/// Datagram source for the frame reader; for udpin, filtered by the gate.
struct UdpRead {
    sock: Arc<tokio::net::UdpSocket>,
    gate: Option<Arc<Mutex<PeerGate>>>,
}

impl AsyncRead for UdpRead {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        match self.sock.poll_recv_from(cx, buf) {
            Poll::Ready(Ok(addr)) => {
                if !gate_datagram(&self.gate, addr) {
                    // Dropped: nothing was read; look at the next datagram.
                    buf.clear();
                    cx.waker().wake_by_ref();
                    return Poll::Pending;
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) if e.kind() == std::io::ErrorKind::ConnectionRefused => {
                // A previous send hit a closed port: not fatal for a datagram socket.
                cx.waker().wake_by_ref();
                Poll::Pending
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => Poll::Pending,
        }
    }
}

/// What every transport starts from: the runtime for its tasks, the queue from the tasks
/// to `tick`, the counters and reconnect signal both sides share, and the signing key.
struct Parts {
    rt: tokio::runtime::Runtime,
    tx: SyncSender<Incoming>,
    rx: Receiver<Incoming>,
    counters: Arc<TaskCounters>,
    reconnect: Arc<Notify>,
    signing: Option<Arc<SigningData>>,
}

impl Parts {
    fn new(url: &str, signing: Option<Arc<SigningData>>) -> Result<Self, AutopilotError> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("markhold-link")
            .enable_all()
            .build()
            .map_err(|e| AutopilotError::Open {
                what: "runtime",
                target: url.to_string(),
                source: e,
            })?;
        let (tx, rx) = std::sync::mpsc::sync_channel(QUEUE_LEN);
        Ok(Self {
            rt,
            tx,
            rx,
            counters: Arc::new(TaskCounters::default()),
            reconnect: Arc::new(Notify::new()),
            signing,
        })
    }
}

/// The error of a failed socket call while opening `target`.
fn open_err(what: &'static str, target: &str) -> impl FnOnce(std::io::Error) -> AutopilotError {
    let target = target.to_string();
    move |e| AutopilotError::Open {
        what,
        target,
        source: e,
    }
}

/// A listening link bound to every address is reachable from any network the machine
/// is on: say so (the link still only adopts the vehicle as its peer).
fn warn_wildcard(url: &str, local: Option<SocketAddr>) {
    if local.is_some_and(|a| a.ip().is_unspecified()) {
        tracing::warn!(
            "{url}: listening on every network interface; any host that can reach this \
             port can talk to the link (bind the vehicle network's own address, or use \
             MAVLink signing)"
        );
    }
}

/// The UDP socket of `udpin:`/`udpout:`, bound (and for udpout connected), non-blocking;
/// with the destination (None for udpin until a peer speaks).
fn bind_udp(
    url: &str,
    hp: &str,
    udpin: bool,
) -> Result<(std::net::UdpSocket, Option<SocketAddr>), AutopilotError> {
    let (bind, dest) = if udpin {
        (resolve(url, hp)?, None)
    } else {
        let d = resolve(url, hp)?;
        let any: SocketAddr = if d.is_ipv4() {
            ([0, 0, 0, 0], 0).into()
        } else {
            (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
        };
        (any, Some(d))
    };
    let sock = std::net::UdpSocket::bind(bind).map_err(open_err("udp socket", hp))?;
    if let Some(d) = dest {
        sock.connect(d).map_err(open_err("udp socket", hp))?;
    }
    sock.set_nonblocking(true)
        .map_err(open_err("udp socket", hp))?;
    Ok((sock, dest))
}

impl Transport {
    /// Opens the endpoint: sockets that must exist (udp, tcpin listener) are bound here so
    /// errors surface at once; stream connections are made by the task.
    /// `vehicle`: the vehicle's system and component ids, the only sender a listening
    /// link (udpin, tcpin) takes as its peer.
    pub(crate) fn open(
        url: &str,
        signing: Option<Arc<SigningData>>,
        receive_on_tick: bool,
        vehicle: (u8, u8),
    ) -> Result<Self, AutopilotError> {
        let ep = Endpoint::parse(url)?;
        let parts = Parts::new(url, signing)?;
        match ep {
            Endpoint::UdpIn(hp) => Self::open_udp(parts, url, &hp, Some(vehicle), receive_on_tick),
            Endpoint::UdpOut(hp) => Self::open_udp(parts, url, &hp, None, receive_on_tick),
            Endpoint::TcpOut(hp) => Self::open_tcp_out(parts, url, &hp),
            Endpoint::TcpIn(hp) => Self::open_tcp_in(parts, url, &hp, vehicle),
            Endpoint::Serial { path, baud } => Ok(Self::open_serial(parts, path, baud)),
        }
    }

    fn open_udp(
        p: Parts,
        url: &str,
        hp: &str,
        udpin: Option<(u8, u8)>,
        receive_on_tick: bool,
    ) -> Result<Self, AutopilotError> {
        let (sock, dest) = bind_udp(url, hp, udpin.is_some())?;
        let udp_recv_buffer = grow_recv_buffer(&sock);
        let local = sock.local_addr().ok();
        if udpin.is_some() {
            warn_wildcard(url, local);
        }
        let wsock = sock.try_clone().map_err(open_err("udp socket", hp))?;
        let dest = Arc::new(Mutex::new(dest));
        let gate = udpin.map(|ids| Arc::new(Mutex::new(PeerGate::new(dest.clone(), ids))));
        let tick_rx = if receive_on_tick {
            // Datagrams are read by `tick` on the caller's thread: on loopback (HIL)
            // everything the vehicle sent before the tick is seen in that tick, so
            // the link state does not depend on thread scheduling.
            Some(TickReceiver {
                reader: MavlinkReader::with_capacity(
                    TICK_READ_CAPACITY,
                    UdpSrc {
                        sock,
                        gate: gate.clone(),
                    },
                ),
                gate,
                signing: p.signing.clone(),
                last: [0; MAX_FRAME],
                last_len: 0,
            })
        } else {
            let asock = {
                let _g = p.rt.enter();
                tokio::net::UdpSocket::from_std(sock).map_err(open_err("udp socket", hp))?
            };
            let (signing, tx, c) = (p.signing, p.tx, p.counters.clone());
            p.rt.spawn(async move {
                let mut reader = AsyncMavlinkReader::new(UdpRead {
                    sock: Arc::new(asock),
                    gate: gate.clone(),
                });
                loop {
                    let why = pump(&mut reader, signing.as_deref(), gate.as_deref(), &tx, &c).await;
                    tracing::warn!(%why, "udp receive error");
                    tokio::time::sleep(RECONNECT_BACKOFF).await;
                }
            });
            None
        };
        Ok(Self {
            rt: Some(p.rt),
            writer: Writer::Udp {
                sock: wsock,
                dest,
                connected: udpin.is_none(),
            },
            rx: p.rx,
            counters: p.counters,
            reconnect: p.reconnect,
            local_addr: local,
            always_connected: true,
            tick_rx,
            udp_recv_buffer,
        })
    }

    fn open_tcp_out(p: Parts, url: &str, hp: &str) -> Result<Self, AutopilotError> {
        let addr = resolve(url, hp)?;
        let slot: Arc<Mutex<TcpSlot>> = Arc::default();
        let s2 = slot.clone();
        let c = p.counters.clone();
        let rc = p.reconnect.clone();
        let (signing, tx) = (p.signing, p.tx);
        p.rt.spawn(async move {
            while !c.closing.load(Ordering::Acquire) {
                match tokio::time::timeout(CONNECT_TIMEOUT, tokio::net::TcpStream::connect(addr))
                    .await
                {
                    Ok(Ok(s)) => {
                        c.set_error(None);
                        serve_tcp(s, &s2, signing.as_deref(), None, &tx, &c, &rc).await;
                        c.reconnects.fetch_add(1, Ordering::Release);
                        if c.closing.load(Ordering::Acquire) {
                            break;
                        }
                    }
                    Ok(Err(e)) => {
                        tracing::debug!(%addr, error = %e, "tcp connect failed");
                        c.set_error(Some(format!("connecting to {addr}: {e}")));
                    }
                    Err(_) => {
                        tracing::debug!(%addr, "tcp connect timed out");
                        c.set_error(Some(format!("connecting to {addr}: timed out")));
                    }
                }
                tokio::time::sleep(RECONNECT_BACKOFF).await;
            }
        });
        Ok(Self::tcp(p.rt, p.rx, p.counters, p.reconnect, slot, None))
    }

    fn open_tcp_in(
        p: Parts,
        url: &str,
        hp: &str,
        vehicle: (u8, u8),
    ) -> Result<Self, AutopilotError> {
        let addr = resolve(url, hp)?;
        let l = std::net::TcpListener::bind(addr).map_err(open_err("tcp listener", hp))?;
        l.set_nonblocking(true)
            .map_err(open_err("tcp listener", hp))?;
        let local = l.local_addr().ok();
        warn_wildcard(url, local);
        let listener = {
            let _g = p.rt.enter();
            tokio::net::TcpListener::from_std(l).map_err(open_err("tcp listener", hp))?
        };
        let slot: Arc<Mutex<TcpSlot>> = Arc::default();
        let s2 = slot.clone();
        let c = p.counters.clone();
        let rc = p.reconnect.clone();
        let (signing, tx) = (p.signing, p.tx);
        p.rt.spawn(async move {
            while !c.closing.load(Ordering::Acquire) {
                match listener.accept().await {
                    Ok((s, peer)) => {
                        tracing::info!(%peer, "tcp client connected");
                        serve_tcp(s, &s2, signing.as_deref(), Some(vehicle), &tx, &c, &rc).await;
                        c.reconnects.fetch_add(1, Ordering::Release);
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "tcp accept failed");
                        tokio::time::sleep(RECONNECT_BACKOFF).await;
                    }
                }
            }
        });
        Ok(Self::tcp(p.rt, p.rx, p.counters, p.reconnect, slot, local))
    }

    /// A TCP transport (either direction) whose task fills `slot` with the connection.
    fn tcp(
        rt: tokio::runtime::Runtime,
        rx: Receiver<Incoming>,
        counters: Arc<TaskCounters>,
        reconnect: Arc<Notify>,
        slot: Arc<Mutex<TcpSlot>>,
        local_addr: Option<SocketAddr>,
    ) -> Self {
        Self {
            rt: Some(rt),
            writer: Writer::Tcp {
                stream: slot,
                gen: 0,
                pending: Vec::with_capacity(TCP_PENDING_CAP),
            },
            rx,
            counters,
            reconnect,
            local_addr,
            always_connected: false,
            tick_rx: None,
            udp_recv_buffer: None,
        }
    }

    fn open_serial(p: Parts, path: String, baud: u32) -> Self {
        let (wtx, mut wrx) = tokio::sync::mpsc::channel::<([u8; MAX_FRAME], usize)>(256);
        let c = p.counters.clone();
        let rc = p.reconnect.clone();
        let (signing, tx) = (p.signing, p.tx);
        p.rt.spawn(async move {
            while !c.closing.load(Ordering::Acquire) {
                let builder = tokio_serial::new(path.as_str(), baud);
                match tokio_serial::SerialStream::open(&builder) {
                    Ok(port) => {
                        c.set_error(None);
                        push(&tx, &c, Incoming::Connected(path.clone()));
                        let (r, mut w) = tokio::io::split(port);
                        let mut reader = AsyncMavlinkReader::new(r);
                        let why = tokio::select! {
                            why = pump(&mut reader, signing.as_deref(), None, &tx, &c) => why,
                            why = async {
                                while let Some((f, n)) = wrx.recv().await {
                                    if let Err(e) = w.write_all(&f[..n]).await {
                                        return e.to_string();
                                    }
                                }
                                // Closed by `Transport::close`: what was queued is
                                // written; flush it to the device before stopping.
                                if let Err(e) = w.flush().await {
                                    return format!("flush at close: {e}");
                                }
                                "writer closed".to_string()
                            } => why,
                            _ = rc.notified() => "reconnect requested".to_string(),
                        };
                        push(&tx, &c, Incoming::Disconnected(why));
                        c.reconnects.fetch_add(1, Ordering::Release);
                        if c.closing.load(Ordering::Acquire) {
                            break;
                        }
                    }
                    Err(e) => {
                        tracing::debug!(%path, error = %e, "serial open failed");
                        c.set_error(Some(format!("opening {path}: {e}")));
                    }
                }
                // Frames queued while the port was down are stale: drop them.
                while wrx.try_recv().is_ok() {}
                tokio::time::sleep(RECONNECT_BACKOFF).await;
            }
        });
        Self {
            rt: Some(p.rt),
            writer: Writer::Serial { tx: wtx },
            rx: p.rx,
            counters: p.counters,
            reconnect: p.reconnect,
            local_addr: None,
            always_connected: false,
            tick_rx: None,
            udp_recv_buffer: None,
        }
    }

    /// Next message read on the caller's thread (UDP with `receive_on_tick`); None when
    /// the socket has nothing more now.
    pub(crate) fn poll_tick(&mut self) -> Option<(MavHeader, MavMessage)> {
        let rx = self.tick_rx.as_mut()?;
        loop {
            match rx.reader.read_any_raw_message::<MavMessage>() {
                Ok(raw) => {
                    if let Some(m) = accept(&raw, rx.signing.as_deref(), &self.counters) {
                        if !gate_frame(rx.gate.as_deref(), &m.0) {
                            continue;
                        }
                        let bytes = match &raw {
                            MAVLinkMessageRaw::V1(r) => r.raw_bytes(),
                            MAVLinkMessageRaw::V2(r) => r.raw_bytes(),
                        };
                        let n = bytes.len().min(MAX_FRAME);
                        rx.last[..n].copy_from_slice(&bytes[..n]);
                        rx.last_len = n;
                        return Some(m);
                    }
                }
                Err(MessageReadError::Parse(e)) => {
                    self.counters.parse_errors.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!(error = %e, "mavlink parse error");
                }
                Err(MessageReadError::Io(e)) => {
                    if e.kind() != std::io::ErrorKind::WouldBlock {
                        tracing::warn!(error = %e, "udp receive error");
                    }
                    return None;
                }
            }
        }
    }

    /// The bytes of the frame the last `poll_tick` returned.
    pub(crate) fn last_tick_frame(&self) -> &[u8] {
        match &self.tick_rx {
            Some(rx) => &rx.last[..rx.last_len],
            None => &[],
        }
    }

    /// Why the stream transport's last connect or open failed (none once one worked).
    pub(crate) fn last_error(&self) -> Option<String> {
        self.counters.last_error.lock().ok().and_then(|g| g.clone())
    }

    /// Local socket address (udp, tcpin), useful with port 0.
    pub(crate) fn local_addr(&self) -> Option<SocketAddr> {
        self.local_addr
    }

    /// Asks a stream transport to drop its connection and make a new one.
    pub(crate) fn request_reconnect(&self) {
        // notify_waiters stores no permit: a request made while already reconnecting must
        // not tear down the fresh connection.
        self.reconnect.notify_waiters();
    }
}

/// A tcpin client that has not sent a valid frame from the vehicle's ids by then is
/// closed, so a silent or foreign client cannot hold the listener.
const TCP_ADOPT_TIMEOUT: Duration = Duration::from_secs(5);

/// Wait (bounded) for the first valid frame from `vehicle` on a tcpin client; it goes
/// to the link. Why not, when the client is to be closed.
async fn adopt_tcp<R: AsyncRead + Unpin>(
    reader: &mut AsyncMavlinkReader<R>,
    signing: Option<&SigningData>,
    vehicle: (u8, u8),
    tx: &SyncSender<Incoming>,
    c: &TaskCounters,
) -> Result<(), String> {
    let wait = async {
        loop {
            match reader.read_any_raw_message::<MavMessage>().await {
                Ok(raw) => {
                    if let Some((h, m)) = accept(&raw, signing, c) {
                        if (h.system_id, h.component_id) == (u32::from(vehicle.0), vehicle.1) {
                            push(tx, c, Incoming::Msg(h, m, FrameBytes::of(&raw)));
                            return Ok(());
                        }
                    }
                }
                Err(MessageReadError::Io(e)) => return Err(e.to_string()),
                Err(MessageReadError::Parse(_)) => {
                    c.parse_errors.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    };
    match tokio::time::timeout(TCP_ADOPT_TIMEOUT, wait).await {
        Ok(r) => r,
        Err(_) => Err(format!(
            "no valid frame from vehicle {}/{} within {} s",
            vehicle.0,
            vehicle.1,
            TCP_ADOPT_TIMEOUT.as_secs()
        )),
    }
}

async fn serve_tcp(
    s: tokio::net::TcpStream,
    slot: &Mutex<TcpSlot>,
    signing: Option<&SigningData>,
    adopt: Option<(u8, u8)>,
    tx: &SyncSender<Incoming>,
    c: &TaskCounters,
    reconnect: &Notify,
) {
    let peer = s
        .peer_addr()
        .map(|a| a.to_string())
        .unwrap_or_else(|_| "?".into());
    let _ = s.set_nodelay(true);
    // A std clone of the socket lets the caller's thread write without the runtime.
    let std_s = match s.into_std() {
        Ok(x) => x,
        Err(e) => {
            tracing::warn!(error = %e, "tcp into_std failed");
            return;
        }
    };
    let w = match std_s.try_clone() {
        Ok(w) => w,
        Err(e) => {
            tracing::warn!(error = %e, "tcp clone failed");
            return;
        }
    };
    let s = match tokio::net::TcpStream::from_std(std_s) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!(error = %e, "tcp from_std failed");
            return;
        }
    };
    let mut reader = AsyncMavlinkReader::new(s);
    if let Some(vehicle) = adopt {
        // tcpin: the client is the vehicle only once it says so with a valid frame;
        // until then nothing is sent to it.
        if let Err(why) = adopt_tcp(&mut reader, signing, vehicle, tx, c).await {
            tracing::warn!(%peer, %why, "tcp client closed: not the vehicle");
            let _ = w.shutdown(std::net::Shutdown::Both);
            return;
        }
    }
    if let Ok(mut g) = slot.lock() {
        g.stream = Some(w);
        g.gen += 1;
    }
    push(tx, c, Incoming::Connected(peer.clone()));
    let why = tokio::select! {
        why = pump(&mut reader, signing, None, tx, c) => why,
        _ = reconnect.notified() => "reconnect requested".to_string(),
    };
    if let Ok(mut g) = slot.lock() {
        if let Some(w) = g.stream.take() {
            let _ = w.shutdown(std::net::Shutdown::Both);
        }
    }
    tracing::warn!(%peer, %why, "tcp link down");
    push(tx, c, Incoming::Disconnected(why));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The connection-string table: every accepted form and the endpoint it means
    /// (pymavlink's `mavlink_connection` and MAVProxy's `--master` read them the same).
    #[test]
    fn parses_every_form() {
        let serial = |path: &str, baud| Endpoint::Serial {
            path: path.into(),
            baud,
        };
        for (url, want) in [
            (
                "udpin:0.0.0.0:14550",
                Endpoint::UdpIn("0.0.0.0:14550".into()),
            ),
            ("udp:0.0.0.0:14550", Endpoint::UdpIn("0.0.0.0:14550".into())),
            ("udp:[::1]:14550", Endpoint::UdpIn("[::1]:14550".into())),
            (
                "udpout:127.0.0.1:14550",
                Endpoint::UdpOut("127.0.0.1:14550".into()),
            ),
            (
                "tcp:localhost:5760",
                Endpoint::TcpOut("localhost:5760".into()),
            ),
            (
                "tcpout:localhost:5760",
                Endpoint::TcpOut("localhost:5760".into()),
            ),
            ("tcpin:127.0.0.1:0", Endpoint::TcpIn("127.0.0.1:0".into())),
            ("serial:/dev/ttyACM0:115200", serial("/dev/ttyACM0", 115200)),
            ("serial:/dev/ttyACM0,57600", serial("/dev/ttyACM0", 57600)),
            ("/dev/ttyACM0,115200", serial("/dev/ttyACM0", 115200)),
            ("/dev/ttyUSB0:57600", serial("/dev/ttyUSB0", 57600)),
            ("serial:COM3:57600", serial("COM3", 57600)),
            (
                "/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0,921600",
                serial("/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0", 921600),
            ),
        ] {
            assert_eq!(Endpoint::parse(url).unwrap(), want, "{url}");
        }
    }

    /// Every refused form says why and names the forms to use instead.
    #[test]
    fn refuses_ambiguous_and_unknown_forms_naming_the_alternatives() {
        for (url, why) in [
            ("127.0.0.1:14550", "ambiguous"),
            ("192.168.2.2:14550", "udpout:192.168.2.2:14550"),
            (
                "udpbcast:192.168.2.255:14550",
                "broadcast is not implemented",
            ),
            ("mcast:239.255.145.50:14550", "multicast"),
            ("ws:127.0.0.1:5760", "WebSocket"),
            ("wsserver:127.0.0.1:5760", "WebSocket"),
            ("ftp:1.2.3.4:5", "unknown scheme `ftp`"),
            ("nocolon", "SCHEME:ADDRESS"),
            ("/dev/ttyACM0", "no baud rate"),
            ("serial:/dev/ttyACM0", "no baud rate"),
        ] {
            let e = Endpoint::parse(url).unwrap_err().to_string();
            assert!(e.contains(why) && e.contains(url), "{url}: {e}");
            for alt in ["udpin:", "udp:", "udpout:", "tcp:", "tcpin:", "serial:"] {
                assert!(e.contains(alt), "{url}: {e} does not name {alt}");
            }
        }
    }

    #[test]
    fn rejects_bad_addresses_with_a_reason() {
        for (u, why) in [
            ("udpout:127.0.0.1", "HOST:PORT"),
            ("udp:127.0.0.1:99999", "port"),
            ("serial:/dev/ttyACM0:fast", "baud"),
            ("/dev/ttyACM0,0", "baud must be > 0"),
            ("tcpout::5760", "empty host"),
            ("tcp::5760", "empty host"),
        ] {
            let e = Endpoint::parse(u).unwrap_err().to_string();
            assert!(e.contains(why) && e.contains(u), "{u}: {e}");
        }
    }
}
