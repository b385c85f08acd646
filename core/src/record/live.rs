//! The live view (`--foxglove`): markhold's own Foxglove WebSocket server, on 127.0.0.1
//! unless `--foxglove-bind` names another address (the topside's way in on a vehicle).
//!
//! foxglove's `WebSocketServer` gives no access to the handshake's headers, so it cannot
//! refuse a browser page by its `Origin`: any page open on the same machine could read the
//! camera feed. This server can. It is a [`foxglove::Sink`] on the recorder's context (so it
//! sees exactly the recorded channels and messages) plus a small synchronous WebSocket
//! server (tungstenite) speaking the subset of the Foxglove WebSocket protocol v1 a viewer
//! needs: `serverInfo`, `advertise` (inline schemas), `unadvertise`, `subscribe`,
//! `unsubscribe` and binary `messageData`. The message types are foxglove's own
//! (`foxglove::ws_protocol`).
//!
//! - Handshake: an `Origin` header must be one of `[live] allowed_origins` (403 and a
//!   warning naming it otherwise); a request without one (a native client such as Foxglove
//!   desktop) is let in. The subprotocol is `foxglove.sdk.v1` or the older
//!   `foxglove.websocket.v1` (400 without either).
//! - Each client has a bounded queue (messages and bytes). The sink only ever `try_send`s:
//!   a client that falls behind loses messages (counted, warned about once), the recorder's
//!   writer thread and the loop never wait for it.

use std::collections::{BTreeMap, HashMap};
use std::io::ErrorKind;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use foxglove::ws_protocol::client::ClientMessage;
use foxglove::ws_protocol::server::advertise::advertise_channels;
use foxglove::ws_protocol::server::{MessageData, ServerInfo, Unadvertise};
use foxglove::ws_protocol::{BinaryMessage, JsonMessage};
use foxglove::{ChannelId, Context, FoxgloveError, Metadata, RawChannel, Sink, SinkId};
use serde::{Deserialize, Serialize};
use tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tungstenite::http::{HeaderValue, StatusCode};
use tungstenite::{Message, WebSocket};

/// Subprotocols served, preferred first (both carry inline schemas in `advertise`).
pub const SUBPROTOCOLS: [&str; 2] = ["foxglove.sdk.v1", "foxglove.websocket.v1"];
/// Messages a client may have waiting; beyond, new ones are dropped for it.
const QUEUE_MESSAGES: usize = 1024;
/// Bytes a client may have waiting (a few seconds of PNG frames at 640x480).
const QUEUE_BYTES: usize = 32 << 20;
/// Clients served at once; more are closed at once.
const MAX_CLIENTS: usize = 8;
/// How long a client may take to send its upgrade request.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(3);
/// How long one write may block before the client is dropped as stalled.
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// How often a client thread looks for queued messages and a stop.
const POLL: Duration = Duration::from_millis(10);

/// `[live]` of a site file: who may open the live view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveSection {
    /// Web origins (`scheme://host[:port]`) whose pages may connect. A client that sends no
    /// `Origin` (not a browser) is always let in.
    #[serde(default = "default_allowed_origins")]
    pub allowed_origins: Vec<String>,
}

fn default_allowed_origins() -> Vec<String> {
    vec![
        "https://app.foxglove.dev".into(),
        "https://studio.foxglove.dev".into(),
    ]
}

impl Default for LiveSection {
    fn default() -> Self {
        Self {
            allowed_origins: default_allowed_origins(),
        }
    }
}

impl LiveSection {
    pub fn validate(&self) -> Result<(), markhold_config::ConfigError> {
        let c = markhold_config::Checks::new("live").check(
            "allowed_origins",
            format!("{} entries", self.allowed_origins.len()),
            self.allowed_origins.len() <= 64,
            "at most 64 origins",
        );
        self.allowed_origins
            .iter()
            .fold(c, |c, o| {
                c.check(
                    "allowed_origins",
                    format!("{o:?}"),
                    is_origin(o),
                    "origins as a browser sends them: scheme://host[:port] (no path or \
                     trailing slash; an empty host only for schemes other than http and \
                     https) or null",
                )
            })
            .done()
    }
}

/// An `Origin` header's value: `scheme://host[:port]` with nothing else (an empty host
/// only for schemes other than http and https, as a desktop app's `file://`), or `null`
/// (which browsers also send for sandboxed pages of any site).
fn is_origin(s: &str) -> bool {
    if s == "null" {
        return true;
    }
    let Some((scheme, rest)) = s.split_once("://") else {
        return false;
    };
    let scheme_ok = scheme.starts_with(|c: char| c.is_ascii_lowercase())
        && scheme
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || "+-.".contains(c));
    let web = scheme == "http" || scheme == "https";
    let (host, port) = match rest.rsplit_once(':') {
        // An IPv6 literal's colons sit inside the brackets.
        Some((h, p)) if !p.contains(']') => (h, Some(p)),
        _ => (rest, None),
    };
    let host_ok = (!host.is_empty() || (!web && port.is_none()))
        && host.len() <= 253
        && host
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-.[]:".contains(c));
    let port_ok = port.is_none_or(|p| !p.is_empty() && p.len() <= 5 && p.parse::<u16>().is_ok());
    scheme_ok && host_ok && port_ok
}

/// The running live view; stops (and leaves the recorder's context) when dropped.
pub struct LiveServer {
    port: u16,
    stop: Arc<AtomicBool>,
    sink: Arc<LiveSink>,
    context: Arc<Context>,
    thread: Option<JoinHandle<()>>,
}

impl LiveServer {
    /// Listen on 127.0.0.1:`port` (0: any free port) and stream `context`'s channels.
    pub fn start(context: &Arc<Context>, port: u16, live: &LiveSection) -> std::io::Result<Self> {
        Self::start_on(context, Ipv4Addr::LOCALHOST.into(), port, live)
    }

    /// Listen on `ip`:`port`: an address the topside reaches (`0.0.0.0` on the vehicle);
    /// browser pages are still let in only from `[live] allowed_origins`.
    pub fn start_on(
        context: &Arc<Context>,
        ip: IpAddr,
        port: u16,
        live: &LiveSection,
    ) -> std::io::Result<Self> {
        let listener = TcpListener::bind((ip, port))?;
        listener.set_nonblocking(true)?;
        let port = listener.local_addr()?.port();
        let sink = Arc::new(LiveSink {
            id: SinkId::next(),
            state: Mutex::new(State::default()),
            dropped: AtomicU64::new(0),
        });
        // Registration hands the sink every existing channel (`add_channels`).
        context.add_sink(sink.clone());
        let stop = Arc::new(AtomicBool::new(false));
        let origins: Arc<[String]> = live.allowed_origins.clone().into();
        let (s, k) = (stop.clone(), sink.clone());
        let thread = std::thread::Builder::new()
            .name("markhold-live".into())
            .spawn(move || accept_loop(&listener, &k, &origins, &s));
        let thread = match thread {
            Ok(t) => t,
            Err(e) => {
                context.remove_sink(sink.id);
                return Err(e);
            }
        };
        Ok(Self {
            port,
            stop,
            sink,
            context: context.clone(),
            thread: Some(thread),
        })
    }

    pub fn port(&self) -> u16 {
        self.port
    }

    /// Messages dropped so far because a client did not keep up (all clients).
    pub fn dropped(&self) -> u64 {
        self.sink.dropped.load(Ordering::Relaxed)
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.context.remove_sink(self.sink.id);
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A connected client as the sink sees it.
struct ClientSlot {
    id: u64,
    peer: SocketAddr,
    /// Channel id -> the client's subscription id.
    subscriptions: HashMap<u64, u32>,
    data: SyncSender<Vec<u8>>,
    /// Advertisements: rare and small, never dropped.
    control: Sender<String>,
    queued_bytes: Arc<AtomicUsize>,
    dropped: u64,
}

#[derive(Default)]
struct State {
    channels: BTreeMap<u64, Arc<RawChannel>>,
    clients: Vec<ClientSlot>,
    next_client: u64,
}

struct LiveSink {
    id: SinkId,
    state: Mutex<State>,
    dropped: AtomicU64,
}

impl LiveSink {
    fn state(&self) -> MutexGuard<'_, State> {
        // A client thread that panicked leaves consistent data behind (plain inserts).
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Add a client; returns its id and the advertisement of every channel so far.
    fn register(
        &self,
        peer: SocketAddr,
        data: SyncSender<Vec<u8>>,
        control: Sender<String>,
        queued_bytes: Arc<AtomicUsize>,
    ) -> (u64, String) {
        let mut st = self.state();
        let id = st.next_client;
        st.next_client += 1;
        let advertise = advertise_channels(st.channels.values()).to_string();
        st.clients.push(ClientSlot {
            id,
            peer,
            subscriptions: HashMap::new(),
            data,
            control,
            queued_bytes,
            dropped: 0,
        });
        (id, advertise)
    }

    fn unregister(&self, id: u64) {
        let mut st = self.state();
        if let Some(i) = st.clients.iter().position(|c| c.id == id) {
            let c = st.clients.swap_remove(i);
            if c.dropped > 0 {
                tracing::warn!(
                    "live view: {} disconnected; {} messages were dropped for it",
                    c.peer,
                    c.dropped
                );
            }
        }
    }

    fn handle(&self, id: u64, msg: ClientMessage<'_>) {
        let mut st = self.state();
        let State {
            channels, clients, ..
        } = &mut *st;
        let Some(c) = clients.iter_mut().find(|c| c.id == id) else {
            return;
        };
        match msg {
            ClientMessage::Subscribe(s) => {
                for sub in s.subscriptions {
                    if channels.contains_key(&sub.channel_id) {
                        c.subscriptions.insert(sub.channel_id, sub.id);
                    }
                }
            }
            ClientMessage::Unsubscribe(u) => c
                .subscriptions
                .retain(|_, sub| !u.subscription_ids.contains(sub)),
            // Publishing, parameters, services, assets: not offered (no capabilities).
            other => tracing::debug!("live view: ignored a client message: {other:?}"),
        }
    }
}

impl Sink for LiveSink {
    fn id(&self) -> SinkId {
        self.id
    }

    fn log(
        &self,
        channel: &RawChannel,
        msg: &[u8],
        metadata: &Metadata,
    ) -> Result<(), FoxgloveError> {
        let channel_id = u64::from(channel.id());
        let mut st = self.state();
        for c in st.clients.iter_mut() {
            let Some(&sub) = c.subscriptions.get(&channel_id) else {
                continue;
            };
            let len = 13 + msg.len();
            if c.queued_bytes.load(Ordering::Relaxed) + len > QUEUE_BYTES {
                self.dropped_one(c);
                continue;
            }
            let bytes = MessageData::new(sub, metadata.log_time, msg).to_bytes();
            c.queued_bytes.fetch_add(len, Ordering::Relaxed);
            match c.data.try_send(bytes) {
                Ok(()) => {}
                Err(TrySendError::Full(_)) => {
                    c.queued_bytes.fetch_sub(len, Ordering::Relaxed);
                    self.dropped_one(c);
                }
                // The client thread is gone; it unregisters itself.
                Err(TrySendError::Disconnected(_)) => {
                    c.queued_bytes.fetch_sub(len, Ordering::Relaxed);
                }
            }
        }
        Ok(())
    }

    fn add_channels(&self, channels: &[&Arc<RawChannel>]) -> Option<Vec<ChannelId>> {
        let mut st = self.state();
        for ch in channels {
            st.channels.insert(u64::from(ch.id()), Arc::clone(ch));
        }
        let advertise = advertise_channels(channels.iter().copied()).to_string();
        for c in &st.clients {
            let _ = c.control.send(advertise.clone());
        }
        None
    }

    fn remove_channel(&self, channel: &RawChannel) {
        let id = u64::from(channel.id());
        let mut st = self.state();
        st.channels.remove(&id);
        let unadvertise = Unadvertise::new([id]).to_string();
        for c in st.clients.iter_mut() {
            c.subscriptions.remove(&id);
            let _ = c.control.send(unadvertise.clone());
        }
    }
}

impl LiveSink {
    fn dropped_one(&self, c: &mut ClientSlot) {
        if c.dropped == 0 {
            tracing::warn!(
                "live view: {} is not keeping up; dropping messages for it (the run goes on)",
                c.peer
            );
        }
        c.dropped += 1;
        self.dropped.fetch_add(1, Ordering::Relaxed);
    }
}

fn accept_loop(
    listener: &TcpListener,
    sink: &Arc<LiveSink>,
    origins: &Arc<[String]>,
    stop: &Arc<AtomicBool>,
) {
    let mut clients: Vec<JoinHandle<()>> = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        clients.retain(|t| !t.is_finished());
        match listener.accept() {
            Ok((stream, peer)) => {
                if clients.len() >= MAX_CLIENTS {
                    tracing::warn!("live view: {peer} refused, {MAX_CLIENTS} clients already");
                    continue;
                }
                let (sink, origins, stop) = (sink.clone(), origins.clone(), stop.clone());
                let spawned = std::thread::Builder::new()
                    .name("markhold-live-client".into())
                    .spawn(move || serve_client(stream, peer, &sink, &origins, &stop));
                match spawned {
                    Ok(t) => clients.push(t),
                    Err(e) => tracing::warn!("live view: {peer} refused: {e}"),
                }
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(POLL * 2),
            Err(e) => {
                tracing::warn!("live view: accept: {e}");
                std::thread::sleep(POLL * 10);
            }
        }
    }
    for t in clients {
        let _ = t.join();
    }
}

/// Why a handshake was refused.
enum Refusal {
    Origin(String),
    Subprotocol(String),
}

fn refuse(status: StatusCode, body: &str) -> ErrorResponse {
    let mut r = ErrorResponse::new(Some(body.to_string()));
    *r.status_mut() = status;
    r
}

/// The WebSocket handshake with the Origin check and subprotocol choice.
fn handshake(
    stream: TcpStream,
    origins: &[String],
) -> Result<WebSocket<TcpStream>, Option<Refusal>> {
    let mut refusal = None;
    // tungstenite's callback type: the refusal is an HTTP response.
    #[allow(clippy::result_large_err)]
    let check = |req: &Request, mut res: Response| {
        if let Some(origin) = req.headers().get("origin") {
            let origin = String::from_utf8_lossy(origin.as_bytes());
            if !origins.iter().any(|o| o == origin.trim()) {
                refusal = Some(Refusal::Origin(origin.into_owned()));
                return Err(refuse(
                    StatusCode::FORBIDDEN,
                    "origin not allowed: see [live] allowed_origins in the site file",
                ));
            }
        }
        let offered: Vec<&str> = req
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .flat_map(|h| h.to_str().unwrap_or_default().split(','))
            .map(str::trim)
            .collect();
        let Some(chosen) = SUBPROTOCOLS.iter().find(|p| offered.contains(p)) else {
            refusal = Some(Refusal::Subprotocol(offered.join(",")));
            return Err(refuse(
                StatusCode::BAD_REQUEST,
                "expected Sec-WebSocket-Protocol foxglove.sdk.v1 or foxglove.websocket.v1",
            ));
        };
        res.headers_mut()
            .insert("sec-websocket-protocol", HeaderValue::from_static(chosen));
        Ok(res)
    };
    match tungstenite::accept_hdr(stream, check) {
        Ok(ws) => Ok(ws),
        Err(e) => {
            // The error holds the callback, which borrows `refusal`.
            drop(e);
            Err(refusal)
        }
    }
}

/// The largest upgrade request head read.
const MAX_REQUEST_HEAD: usize = 8 << 10;

/// Waits until the client's whole request head has arrived, at most `limit` in all (a
/// client that drips it, a byte at a time, must not hold a client slot for longer): the
/// bytes are only peeked, so the handshake then reads them without waiting.
fn request_head_within(stream: &TcpStream, limit: Duration) -> Result<(), String> {
    let until = std::time::Instant::now() + limit;
    let mut buf = vec![0u8; MAX_REQUEST_HEAD];
    loop {
        let left = until.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Err(format!(
                "request head not complete within {} s",
                limit.as_secs()
            ));
        }
        stream
            .set_read_timeout(Some(left))
            .map_err(|e| e.to_string())?;
        let n = match stream.peek(&mut buf) {
            Ok(0) => return Err("closed".into()),
            Ok(n) => n,
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => continue,
            Err(e) => return Err(e.to_string()),
        };
        if buf[..n].windows(4).any(|w| w == b"\r\n\r\n") {
            return Ok(());
        }
        if n == buf.len() {
            return Err(format!("request head over {MAX_REQUEST_HEAD} bytes"));
        }
        // More to come: wait a little rather than spin on the same peeked bytes.
        std::thread::sleep(POLL);
    }
}

fn serve_client(
    stream: TcpStream,
    peer: SocketAddr,
    sink: &Arc<LiveSink>,
    origins: &[String],
    stop: &AtomicBool,
) {
    let setup = stream
        .set_nonblocking(false)
        .and_then(|()| stream.set_read_timeout(Some(HANDSHAKE_TIMEOUT)))
        .and_then(|()| stream.set_write_timeout(Some(WRITE_TIMEOUT)))
        .and_then(|()| stream.set_nodelay(true));
    if let Err(e) = setup {
        tracing::debug!("live view: {peer}: {e}");
        return;
    }
    if let Err(why) = request_head_within(&stream, HANDSHAKE_TIMEOUT) {
        tracing::debug!("live view: {peer}: no WebSocket upgrade: {why}");
        return;
    }
    let mut ws = match handshake(stream, origins) {
        Ok(ws) => ws,
        Err(Some(Refusal::Origin(o))) => {
            tracing::warn!(
                "live view: refused {peer} with Origin {o:?} (not in [live] allowed_origins)"
            );
            return;
        }
        Err(Some(Refusal::Subprotocol(p))) => {
            tracing::warn!("live view: refused {peer}: subprotocols {p:?} not served");
            return;
        }
        Err(None) => {
            tracing::debug!("live view: {peer}: no valid WebSocket upgrade");
            return;
        }
    };
    let (data_tx, data_rx) = sync_channel(QUEUE_MESSAGES);
    let (control_tx, control_rx) = channel();
    let queued = Arc::new(AtomicUsize::new(0));
    let (id, advertise) = sink.register(peer, data_tx, control_tx, queued.clone());
    let info = ServerInfo::new("markhold").to_string();
    let greeted = ws
        .send(Message::text(info))
        .and_then(|()| ws.send(Message::text(advertise)))
        .map_err(|e| e.to_string())
        .and_then(|()| {
            ws.get_mut()
                .set_read_timeout(Some(POLL))
                .map_err(|e| e.to_string())
        });
    match greeted {
        Ok(()) => {
            if let Err(e) = client_loop(&mut ws, id, sink, &data_rx, &control_rx, &queued, stop) {
                tracing::debug!("live view: {peer}: {e}");
            }
        }
        Err(e) => tracing::debug!("live view: {peer}: {e}"),
    }
    sink.unregister(id);
    let _ = ws.close(None);
    let _ = ws.flush();
}

/// Read the client's requests and write what is queued for it until it leaves or the
/// server stops.
fn client_loop(
    ws: &mut WebSocket<TcpStream>,
    id: u64,
    sink: &LiveSink,
    data: &Receiver<Vec<u8>>,
    control: &Receiver<String>,
    queued: &AtomicUsize,
    stop: &AtomicBool,
) -> Result<(), tungstenite::Error> {
    while !stop.load(Ordering::Relaxed) {
        match ws.read() {
            Ok(Message::Text(text)) => match ClientMessage::parse_json(text.as_str()) {
                Ok(msg) => sink.handle(id, msg),
                Err(e) => tracing::debug!("live view: unreadable client message: {e}"),
            },
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(tungstenite::Error::ConnectionClosed) => return Ok(()),
            Err(e) => return Err(e),
        }
        while let Ok(text) = control.try_recv() {
            ws.write(Message::text(text))?;
        }
        while let Ok(bytes) = data.try_recv() {
            queued.fetch_sub(bytes.len(), Ordering::Relaxed);
            ws.write(Message::binary(bytes))?;
        }
        ws.flush()?;
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;
    use tungstenite::client::IntoClientRequest;

    /// A client that subscribes, sees one message, then stops reading: the sender goes on
    /// logging 128 MB, which cannot all fit in its queue and socket, and is never held up
    /// (every `log` returns); what did not fit is counted as dropped.
    #[test]
    fn a_client_that_stops_reading_loses_messages_and_never_blocks_the_sender() {
        let ctx = Context::new();
        let ch = foxglove::ChannelBuilder::new("/big")
            .message_encoding("raw")
            .context(&ctx)
            .build_raw()
            .unwrap();
        let server = LiveServer::start(&ctx, 0, &LiveSection::default()).unwrap();
        let stream = TcpStream::connect(("127.0.0.1", server.port())).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let mut req = format!("ws://127.0.0.1:{}/", server.port())
            .into_client_request()
            .unwrap();
        req.headers_mut().insert(
            "sec-websocket-protocol",
            HeaderValue::from_static("foxglove.sdk.v1"),
        );
        let (mut ws, _) = tungstenite::client(req, stream).unwrap();
        let subscribe = format!(
            r#"{{"op":"subscribe","subscriptions":[{{"id":3,"channelId":{}}}]}}"#,
            u64::from(ch.id())
        );
        ws.send(Message::text(subscribe)).unwrap();
        ws.get_mut()
            .set_read_timeout(Some(Duration::from_millis(50)))
            .unwrap();
        // Log small messages until one arrives: the subscription is in place.
        let mut got = false;
        for _ in 0..500 {
            ch.log(b"x");
            let m = match ws.read() {
                Ok(m) => m,
                Err(tungstenite::Error::Io(e)) if e.kind() == ErrorKind::WouldBlock => continue,
                Err(e) => panic!("{e}"),
            };
            if let Message::Binary(b) = m {
                assert_eq!(b[0], 1, "messageData opcode");
                assert_eq!(&b[1..5], &3u32.to_le_bytes(), "subscription id");
                got = true;
                break;
            }
        }
        assert!(got, "no message reached the subscribed client");
        let big = vec![7u8; 64 << 10];
        for _ in 0..2000 {
            ch.log(&big);
        }
        assert!(
            server.dropped() > 0,
            "nothing was dropped for a stalled client"
        );
        drop(ws);
        drop(server);
    }

    /// Eight clients that drip their upgrade request a byte at a time (every client slot)
    /// hold the view for at most the handshake deadline: a real client gets in after it.
    #[test]
    fn clients_dripping_their_handshake_are_cut_at_the_deadline() {
        use std::io::Write;
        let ctx = Context::new();
        let server = LiveServer::start(&ctx, 0, &LiveSection::default()).unwrap();
        let port = server.port();
        let stop = Arc::new(AtomicBool::new(false));
        let drippers: Vec<_> = (0..MAX_CLIENTS)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
                    let _ = s.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n");
                    for _ in 0..300 {
                        if stop.load(Ordering::Relaxed) || s.write_all(b"X").is_err() {
                            return;
                        }
                        std::thread::sleep(Duration::from_millis(100));
                    }
                })
            })
            .collect();
        std::thread::sleep(Duration::from_millis(300));
        let t0 = std::time::Instant::now();
        let mut served = None;
        while t0.elapsed() < Duration::from_secs(15) {
            let stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
            stream
                .set_read_timeout(Some(Duration::from_secs(5)))
                .unwrap();
            let mut req = format!("ws://127.0.0.1:{port}/")
                .into_client_request()
                .unwrap();
            req.headers_mut().insert(
                "sec-websocket-protocol",
                HeaderValue::from_static("foxglove.sdk.v1"),
            );
            if tungstenite::client(req, stream).is_ok() {
                served = Some(t0.elapsed());
                break;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        stop.store(true, Ordering::Relaxed);
        for d in drippers {
            let _ = d.join();
        }
        let served = served.expect("a real client never got in while others dripped");
        eprintln!(
            "served after {:.1} s of dripping clients",
            served.as_secs_f64()
        );
        assert!(
            served <= HANDSHAKE_TIMEOUT + Duration::from_secs(2),
            "{served:?}"
        );
    }

    #[test]
    fn origins_are_checked_for_their_form() {
        for ok in [
            "https://app.foxglove.dev",
            "http://localhost:8080",
            "http://127.0.0.1:3000",
            "http://[::1]:8080",
            "file://",
            "app://foxglove",
            "null",
        ] {
            assert!(is_origin(ok), "{ok}");
        }
        for bad in [
            "",
            "app.foxglove.dev",
            "https://",
            "https://app.foxglove.dev/",
            "https://app.foxglove.dev/path",
            "https:/host",
            "https://host:99999",
            "https://host:",
            "https://a b",
            "*",
            "https://*.example",
            "HTTPS://host",
            "nul",
        ] {
            assert!(!is_origin(bad), "{bad}");
        }
    }

    #[test]
    fn a_bad_origin_names_the_key_and_value() {
        let live = LiveSection {
            allowed_origins: vec!["https://ok.example".into(), "https://bad.example/".into()],
        };
        let e = live
            .validate()
            .expect_err("a path is not an origin")
            .to_string();
        assert!(e.contains("live.allowed_origins"), "{e}");
        assert!(e.contains("https://bad.example/"), "{e}");
        assert!(LiveSection::default().validate().is_ok());
    }
}
