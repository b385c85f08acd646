//! The web page (`run --web ADDR:PORT`, `hil --web ADDR:PORT`; the BlueOS extension
//! serves it on 0.0.0.0:8780): the loop's status (engagement, marker, exposure, position
//! error, link, failsafes), the camera with its detections, the site file with its
//! `params check` errors in place, recording start / stop, and where the Foxglove live
//! view is. BlueOS lists it in its sidebar (`GET /register_service`) and Cockpit offers
//! it as a widget (`GET /cockpit_extras.json`): docs/blueos-extension.md.
//!
//! The server never holds the loop up: it runs on its own threads (one accepting, a few
//! serving), reads the loop's state from a [`StatusBoard`] (newest wins, the loop never
//! waits), hands accepted connections over a bounded queue (full: the connection is
//! closed), and gives every connection a deadline and bounded request sizes. The JPEG
//! of a frame is made here, at most once per frame the loop handed over, and those come
//! at most `--web-snapshot-hz` times per second of frame time.
//!
//! Every URL the page uses is relative, so it works at `/` and behind BlueOS's proxy at
//! `/extensionv2/markhold/`.

mod http;
pub mod site;

use std::io::ErrorKind;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::observe::status::{Snapshot, Status};
use crate::observe::StatusBoard;
use crate::record::{RecordControl, RecordingState};
use http::{Request, Response};

const INDEX_HTML: &str = include_str!("page/index.html");
const APP_JS: &str = include_str!("page/app.js");
const STYLE_CSS: &str = include_str!("page/style.css");
const ICON_SVG: &str = include_str!("page/icon.svg");

/// Threads serving requests (one more accepts).
const WORKERS: usize = 3;
/// Accepted connections waiting for a worker; beyond, they are closed at once.
const QUEUE: usize = 16;
/// A connection's whole request must arrive within this.
const REQUEST_DEADLINE: Duration = Duration::from_secs(3);
/// One write may block this long before the client is dropped.
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// How often the threads look for a stop.
const POLL: Duration = Duration::from_millis(20);
/// The port the BlueOS extension serves the page on.
pub const EXTENSION_PORT: u16 = 8780;

/// The page's camera view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WebOptions {
    /// Camera frames handed to the page per second of frame time (each is copied on the
    /// loop's thread into a buffer made at start and encoded as JPEG on the page's).
    pub snapshot_hz: f64,
    /// JPEG quality of the camera view, 1..100.
    pub jpeg_quality: u8,
}

impl Default for WebOptions {
    fn default() -> Self {
        Self {
            snapshot_hz: 5.0,
            jpeg_quality: 75,
        }
    }
}

impl WebOptions {
    /// The range a command line's `--web-snapshot-hz` must be in.
    pub const SNAPSHOT_HZ: std::ops::RangeInclusive<f64> = 0.1..=30.0;
}

/// `--web` and `--web-snapshot-hz` of `run` and `hil`.
#[derive(clap::Args, Debug, Clone)]
pub struct WebArgs {
    /// Serve the web page (status, camera view, site file, recording) on this address:
    /// 127.0.0.1:8780 for this machine alone, 0.0.0.0:8780 for the network (the BlueOS
    /// extension's); port 0 takes any free port.
    #[arg(long, value_name = "ADDR:PORT")]
    pub web: Option<SocketAddr>,
    /// Camera frames handed to the web page per second of frame time, 0.1..30.
    #[arg(long, value_name = "HZ", default_value_t = 5.0)]
    pub web_snapshot_hz: f64,
}

impl Default for WebArgs {
    fn default() -> Self {
        Self {
            web: None,
            web_snapshot_hz: WebOptions::default().snapshot_hz,
        }
    }
}

/// Why the page did not start.
#[derive(Debug, thiserror::Error)]
pub enum WebError {
    #[error("--web-snapshot-hz {0}: expected 0.1..30 frames per second")]
    SnapshotHz(f64),
    #[error("--web {addr}: cannot listen there: {source}")]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
}

/// Serve the page for `site` as `args` ask and attach its status observer to `list`.
/// Returns the board (a runner with pilot engagement sets it every frame) and the
/// address served; nothing when `--web` was not given.
pub fn attach(
    site: &crate::params::LoadedSite,
    args: &WebArgs,
    runner: &'static str,
    record: Option<RecordControl>,
    live: Option<LiveInfo>,
    list: &mut crate::pipeline::Observers,
) -> Result<Option<(StatusBoard, SocketAddr)>, WebError> {
    let Some(addr) = args.web else {
        return Ok(None);
    };
    let hz = args.web_snapshot_hz;
    if !WebOptions::SNAPSHOT_HZ.contains(&hz) {
        return Err(WebError::SnapshotHz(hz));
    }
    let board = StatusBoard::new(site.calibration.width, site.calibration.height);
    let cfg = WebConfig {
        addr,
        site_path: site.path.clone(),
        site_name: site.site.site.name.clone(),
        runner,
        live,
        options: WebOptions {
            snapshot_hz: hz,
            ..WebOptions::default()
        },
        allowed_origins: site.site.live.allowed_origins.clone(),
    };
    let server = WebServer::start(cfg, board.clone(), record)
        .map_err(|source| WebError::Bind { addr, source })?;
    let served = server.addr();
    eprintln!("markhold: web page on http://{served}/");
    list.push(crate::observe::StatusObserver::new(site, board.clone(), hz).keeping(server));
    Ok(Some((board, served)))
}

/// What the page says about the Foxglove live view.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LiveInfo {
    pub port: u16,
    /// Bound to loopback only: the topside cannot reach it.
    pub loopback: bool,
}

/// How the page is served.
#[derive(Debug, Clone)]
pub struct WebConfig {
    pub addr: SocketAddr,
    /// The site file the page shows, checks and saves.
    pub site_path: PathBuf,
    /// The site's name, for the page's title.
    pub site_name: String,
    /// `run` or `hil`.
    pub runner: &'static str,
    pub live: Option<LiveInfo>,
    pub options: WebOptions,
    /// Origins besides the page's own whose pages may use the buttons (the site's
    /// `[live] allowed_origins`); a request without an `Origin` (not a browser page) may.
    pub allowed_origins: Vec<String>,
}

/// The running page; stops when dropped.
pub struct WebServer {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl WebServer {
    /// Listen on `cfg.addr` and serve `board`'s status (and `record`'s controls, when
    /// the run records to a file).
    pub fn start(
        cfg: WebConfig,
        board: StatusBoard,
        record: Option<RecordControl>,
    ) -> std::io::Result<Self> {
        let listener = TcpListener::bind(cfg.addr)?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let app = Arc::new(App {
            frame: Mutex::new(Jpeg::new(cfg.options.jpeg_quality, board.spare_snapshot())),
            cfg,
            board,
            record,
            seen: Mutex::new(None),
        });
        let (tx, rx) = sync_channel::<TcpStream>(QUEUE);
        let rx = Arc::new(Mutex::new(rx));
        let mut threads = Vec::with_capacity(WORKERS + 1);
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new().name(name.into()).spawn(f)
        };
        for _ in 0..WORKERS {
            let (app, rx, s) = (app.clone(), rx.clone(), stop.clone());
            match spawn("markhold-web", Box::new(move || worker(&app, &rx, &s))) {
                Ok(t) => threads.push(t),
                Err(e) => {
                    stop.store(true, Ordering::Relaxed);
                    return Err(e);
                }
            }
        }
        let s = stop.clone();
        let accept = spawn(
            "markhold-web-accept",
            Box::new(move || accept_loop(&listener, &tx, &s)),
        );
        match accept {
            Ok(t) => threads.push(t),
            Err(e) => {
                stop.store(true, Ordering::Relaxed);
                return Err(e);
            }
        }
        Ok(Self {
            addr,
            stop,
            threads,
        })
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for WebServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

fn accept_loop(
    listener: &TcpListener,
    queue: &std::sync::mpsc::SyncSender<TcpStream>,
    stop: &AtomicBool,
) {
    while !stop.load(Ordering::Relaxed) {
        match listener.accept() {
            Ok((stream, peer)) => match queue.try_send(stream) {
                Ok(()) => {}
                Err(TrySendError::Full(_)) => {
                    tracing::debug!("web: {peer} closed: {QUEUE} connections already wait");
                }
                Err(TrySendError::Disconnected(_)) => return,
            },
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(POLL),
            Err(e) => {
                tracing::warn!("web: accept: {e}");
                std::thread::sleep(POLL * 10);
            }
        }
    }
}

fn worker(app: &App, queue: &Mutex<Receiver<TcpStream>>, stop: &AtomicBool) {
    while !stop.load(Ordering::Relaxed) {
        let next = {
            let rx = queue.lock().unwrap_or_else(|e| e.into_inner());
            rx.recv_timeout(POLL * 5)
        };
        match next {
            Ok(stream) => serve(app, stream),
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return,
        }
    }
}

fn serve(app: &App, mut stream: TcpStream) {
    let ready = stream
        .set_nonblocking(false)
        .and_then(|()| stream.set_write_timeout(Some(WRITE_TIMEOUT)))
        .and_then(|()| stream.set_nodelay(true));
    if ready.is_err() {
        return;
    }
    let deadline = Instant::now() + REQUEST_DEADLINE;
    let response = match http::read_request(&mut stream, deadline, max_body) {
        Ok(req) => {
            let head = req.method == "HEAD";
            let r = app.route(&req);
            let _ = http::write_response(&mut stream, &r, head);
            return;
        }
        Err(http::ReadError::Closed) => return,
        Err(http::ReadError::Io(e)) => {
            tracing::debug!("web: reading a request: {e}");
            return;
        }
        Err(http::ReadError::Timeout) => Response::text(408, "the request did not arrive in time"),
        Err(http::ReadError::Bad(why)) => Response::text(400, why),
        Err(http::ReadError::TooLarge(why)) => Response::text(413, why),
    };
    let _ = http::write_response(&mut stream, &response, false);
}

/// Body bytes a route takes.
fn max_body(method: &str, path: &str) -> usize {
    match (method, path) {
        ("POST", "/site" | "/site/check") => site::MAX_SITE_BYTES,
        ("POST", _) => 1024,
        _ => 0,
    }
}

/// The camera view: the newest frame handed over, encoded once.
struct Jpeg {
    frame: Snapshot,
    /// Sequence number of the frame `bytes` holds.
    seq: Option<u64>,
    bytes: Vec<u8>,
    params: opencv::core::Vector<i32>,
}

impl Jpeg {
    fn new(quality: u8, frame: Snapshot) -> Self {
        Self {
            frame,
            seq: None,
            bytes: Vec::new(),
            params: opencv::core::Vector::from_slice(&[
                opencv::imgcodecs::IMWRITE_JPEG_QUALITY,
                i32::from(quality),
            ]),
        }
    }

    /// Encode the newest frame if one came since the last time.
    fn refresh(&mut self, board: &StatusBoard) -> Result<(), opencv::Error> {
        if board.take_snapshot(&mut self.frame) {
            self.bytes = draw(&self.frame, &self.params)?;
            self.seq = Some(self.frame.seq);
        }
        Ok(())
    }
}

/// The frame in colour with the tracked marker (green) and the metered region (yellow).
fn draw(f: &Snapshot, params: &opencv::core::Vector<i32>) -> Result<Vec<u8>, opencv::Error> {
    use opencv::core::{Point, Rect, Scalar, Vector};
    use opencv::imgproc;
    let n = f.width as usize * f.height as usize;
    let pixels = f.data.get(..n).ok_or_else(|| {
        opencv::Error::new(opencv::core::StsBadArg, "frame shorter than its size")
    })?;
    let grey =
        opencv::core::Mat::new_rows_cols_with_data::<u8>(f.height as i32, f.width as i32, pixels)?;
    let mut bgr = opencv::core::Mat::default();
    imgproc::cvt_color(&grey, &mut bgr, imgproc::COLOR_GRAY2BGR, 0)?;
    let thick = (f.width as i32 / 320).max(2);
    if let Some(roi) = f.roi {
        let r = Rect::new(
            roi.x as i32,
            roi.y as i32,
            roi.width as i32,
            roi.height as i32,
        );
        imgproc::rectangle(
            &mut bgr,
            r,
            Scalar::new(0.0, 215.0, 255.0, 0.0),
            thick,
            imgproc::LINE_AA,
            0,
        )?;
    }
    if let Some(c) = f.corners {
        let pts: Vector<Point> = c
            .iter()
            .map(|[x, y]| Point::new(x.round() as i32, y.round() as i32))
            .collect();
        let polys: Vector<Vector<Point>> = std::iter::once(pts).collect();
        imgproc::polylines(
            &mut bgr,
            &polys,
            true,
            Scalar::new(40.0, 230.0, 25.0, 0.0),
            thick,
            imgproc::LINE_AA,
            0,
        )?;
    }
    let mut out = Vector::<u8>::new();
    opencv::imgcodecs::imencode(".jpg", &bgr, &mut out, params)?;
    Ok(out.as_slice().to_vec())
}

struct App {
    cfg: WebConfig,
    board: StatusBoard,
    record: Option<RecordControl>,
    frame: Mutex<Jpeg>,
    /// The last frame the page saw and when (wall clock, the page's own): a loop that
    /// stopped stepping shows as stale.
    seen: Mutex<Option<(u64, Instant)>>,
}

/// `GET status.json`.
#[derive(Serialize)]
struct StatusReply<'a> {
    version: &'static str,
    runner: &'static str,
    site: &'a str,
    status: Status,
    /// Seconds since a new frame last reached the page (wall clock); none before one.
    stale_s: Option<f64>,
    /// None: the run does not record to a file.
    recording: Option<RecordingState>,
    live: Option<LiveInfo>,
    /// Camera frames handed to the page per second of frame time.
    snapshot_hz: f64,
}

/// `GET register_service`: what BlueOS's helper reads to list the page in its sidebar
/// (core/services/helper/main.py, `ServiceMetadata` and `Helper.detect_service`).
#[derive(Serialize)]
struct RegisterService {
    name: &'static str,
    description: &'static str,
    icon: &'static str,
    company: &'static str,
    version: &'static str,
    webpage: &'static str,
    api: &'static str,
    /// Served behind BlueOS's proxy at /extensionv2/markhold/ (every URL is relative).
    works_in_relative_paths: bool,
    extras: Extras,
}

#[derive(Serialize)]
struct Extras {
    cockpit: &'static str,
}

impl App {
    fn route(&self, req: &Request) -> Response {
        let get = matches!(req.method.as_str(), "GET" | "HEAD");
        let post = req.method == "POST";
        match (req.path.as_str(), get, post) {
            ("/" | "/index.html", true, _) => page(INDEX_HTML, "text/html; charset=utf-8"),
            ("/app.js", true, _) => page(APP_JS, "text/javascript; charset=utf-8"),
            ("/style.css", true, _) => page(STYLE_CSS, "text/css; charset=utf-8"),
            ("/icon.svg", true, _) => page(ICON_SVG, "image/svg+xml"),
            ("/register_service", true, _) => Response::json(200, &register_service()),
            ("/cockpit_extras.json", true, _) => Response::json(200, &cockpit_extras()),
            ("/status.json", true, _) => self.status(),
            ("/snapshot.jpg", true, _) => self.snapshot(),
            ("/site.json", true, _) => Response::json(200, &site::read(&self.cfg.site_path)),
            ("/site/check" | "/site" | "/record/start" | "/record/stop", _, true) => {
                if !self.origin_allowed(req) {
                    return Response::text(
                        403,
                        "origin not allowed: use the page markhold serves (or add the origin \
                         to [live] allowed_origins)",
                    );
                }
                self.post(req)
            }
            (
                "/"
                | "/index.html"
                | "/app.js"
                | "/style.css"
                | "/icon.svg"
                | "/register_service"
                | "/cockpit_extras.json"
                | "/status.json"
                | "/snapshot.jpg"
                | "/site.json"
                | "/site/check"
                | "/site"
                | "/record/start"
                | "/record/stop",
                _,
                _,
            ) => Response::text(
                405,
                format!("{} is not served for {}", req.method, req.path),
            ),
            _ => Response::text(404, format!("{}: no such page", req.path)),
        }
    }

    fn post(&self, req: &Request) -> Response {
        let text = || String::from_utf8_lossy(&req.body).into_owned();
        match req.path.as_str() {
            "/site/check" => Response::json(200, &site::check(&self.cfg.site_path, &text())),
            "/site" => match site::save(&self.cfg.site_path, &text()) {
                Ok(check) => {
                    tracing::warn!(
                        "web: site file {} saved from the page; it takes effect when markhold \
                         starts again",
                        self.cfg.site_path.display()
                    );
                    Response::json(200, &check)
                }
                Err(site::SaveError::Invalid(check)) => Response::json(422, &check),
                Err(e) => Response::text(500, e.to_string()),
            },
            path => {
                let Some(rec) = &self.record else {
                    return Response::text(
                        409,
                        "this run does not record to a file (start markhold with --record)",
                    );
                };
                if path == "/record/start" {
                    rec.start();
                } else {
                    rec.stop();
                }
                Response::json(200, &rec.state())
            }
        }
    }

    fn status(&self) -> Response {
        let status = self.board.status();
        let stale_s = {
            let mut seen = self.seen.lock().unwrap_or_else(|e| e.into_inner());
            match *seen {
                _ if status.frames == 0 => None,
                Some((seq, at)) if seq == status.seq => Some(at.elapsed().as_secs_f64()),
                _ => {
                    *seen = Some((status.seq, Instant::now()));
                    Some(0.0)
                }
            }
        };
        Response::json(
            200,
            &StatusReply {
                version: env!("CARGO_PKG_VERSION"),
                runner: self.cfg.runner,
                site: &self.cfg.site_name,
                status,
                stale_s,
                recording: self.record.as_ref().map(RecordControl::state),
                live: self.cfg.live,
                snapshot_hz: self.cfg.options.snapshot_hz,
            },
        )
    }

    fn snapshot(&self) -> Response {
        let mut jpeg = self.frame.lock().unwrap_or_else(|e| e.into_inner());
        if let Err(e) = jpeg.refresh(&self.board) {
            return Response::text(500, format!("encoding the camera view: {e}"));
        }
        match jpeg.seq {
            None => Response::text(503, "no camera frame yet"),
            Some(seq) => Response::new(200, "image/jpeg", jpeg.bytes.clone())
                .with_header("X-Markhold-Seq", seq.to_string()),
        }
    }

    /// A browser page may press the buttons only from the page's own origin or an
    /// allowed one (no other site's page may save the site file or stop the recording).
    fn origin_allowed(&self, req: &Request) -> bool {
        let Some(origin) = req.header("origin") else {
            return true;
        };
        let origin = origin.trim();
        if self.cfg.allowed_origins.iter().any(|o| o == origin) {
            return true;
        }
        let Some(host) = req.header("host") else {
            return false;
        };
        let authority = origin
            .strip_prefix("http://")
            .map(|a| (a, ":80"))
            .or_else(|| origin.strip_prefix("https://").map(|a| (a, ":443")));
        authority.is_some_and(|(a, default_port)| {
            a == host
                || a.strip_suffix(default_port) == Some(host)
                || host.strip_suffix(default_port) == Some(a)
        })
    }
}

fn page(body: &'static str, content_type: &'static str) -> Response {
    Response::new(200, content_type, body.as_bytes())
}

fn register_service() -> RegisterService {
    RegisterService {
        name: "markhold",
        description:
            "Station keeping in front of a fiducial marker: status, camera, site file, recording",
        icon: "mdi-crosshairs-gps",
        company: "markhold",
        version: env!("CARGO_PKG_VERSION"),
        webpage: "",
        api: "",
        works_in_relative_paths: true,
        extras: Extras {
            cockpit: "/cockpit_extras.json",
        },
    }
}

/// Cockpit's extras (bluerobotics/cockpit src/libs/blueos/schemas.ts `ExtrasJsonSchema`):
/// one iframe widget, the page's compact view.
fn cockpit_extras() -> serde_json::Value {
    serde_json::json!({
        "targetSystem": "Cockpit",
        "targetCockpitApiVersion": "1.0.0",
        "widgets": [{
            "name": "markhold",
            "iframeUrl": "/?view=widget",
            "iconUrl": "/icon.svg",
            "version": env!("CARGO_PKG_VERSION"),
            "useExtensionPathAsBaseUrl": true
        }],
        "actions": []
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;

    fn app(origins: &[&str]) -> App {
        App {
            cfg: WebConfig {
                addr: "127.0.0.1:0".parse().unwrap(),
                site_path: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../params/pool.toml"),
                site_name: "pool".into(),
                runner: "hil",
                live: None,
                options: WebOptions::default(),
                allowed_origins: origins.iter().map(|s| s.to_string()).collect(),
            },
            board: StatusBoard::new(4, 4),
            record: None,
            frame: Mutex::new(Jpeg::new(75, Snapshot::default())),
            seen: Mutex::new(None),
        }
    }

    fn post(path: &str, origin: Option<&str>, host: &str) -> Request {
        let mut headers = vec![("host".to_string(), host.to_string())];
        if let Some(o) = origin {
            headers.push(("origin".into(), o.into()));
        }
        Request {
            method: "POST".into(),
            path: path.into(),
            headers,
            ..Request::default()
        }
    }

    #[test]
    fn buttons_answer_only_the_pages_own_origin_or_an_allowed_one() {
        let a = app(&["https://ok.example"]);
        let ok = |r: &Request| a.origin_allowed(r);
        assert!(ok(&post("/record/stop", None, "x")), "not a browser page");
        assert!(ok(&post(
            "/record/stop",
            Some("http://192.168.2.2:8780"),
            "192.168.2.2:8780"
        )));
        // Behind BlueOS's proxy: Host without the port, the page at port 80.
        assert!(ok(&post(
            "/record/stop",
            Some("http://blueos.local"),
            "blueos.local"
        )));
        assert!(ok(&post(
            "/record/stop",
            Some("https://ok.example"),
            "blueos.local"
        )));
        assert!(!ok(&post(
            "/record/stop",
            Some("http://evil.example"),
            "blueos.local"
        )));
        assert!(!ok(&post("/record/stop", Some("null"), "blueos.local")));
        let r = a.route(&post(
            "/record/stop",
            Some("http://evil.example"),
            "blueos.local",
        ));
        assert_eq!(r.status, 403);
        // No file recording in this run: the buttons say so.
        assert_eq!(a.route(&post("/record/stop", None, "x")).status, 409);
    }

    #[test]
    fn blueos_and_cockpit_find_what_they_read() {
        let a = app(&[]);
        let get = |p: &str| {
            a.route(&Request {
                method: "GET".into(),
                path: p.into(),
                ..Request::default()
            })
        };
        let index = get("/");
        assert_eq!(index.status, 200);
        assert!(String::from_utf8_lossy(&index.body).contains("<title>markhold</title>"));
        let reg: serde_json::Value =
            serde_json::from_slice(&get("/register_service").body).unwrap();
        // BlueOS's ServiceMetadata: these are required strings.
        for k in [
            "name",
            "description",
            "icon",
            "company",
            "version",
            "webpage",
            "api",
        ] {
            assert!(reg[k].is_string(), "{k}: {reg}");
        }
        assert_eq!(reg["works_in_relative_paths"], true);
        let extras: serde_json::Value =
            serde_json::from_slice(&get(reg["extras"]["cockpit"].as_str().unwrap()).body).unwrap();
        assert!(extras["targetCockpitApiVersion"].is_string());
        assert!(extras["widgets"][0]["iframeUrl"]
            .as_str()
            .unwrap()
            .starts_with('/'));
        assert_eq!(get("/snapshot.jpg").status, 503, "no frame yet");
        assert_eq!(get("/nope").status, 404);
        let mut del = Request {
            method: "DELETE".into(),
            path: "/site".into(),
            ..Request::default()
        };
        assert_eq!(a.route(&del).status, 405);
        del.method = "GET".into();
        del.path = "/site.json".into();
        let site: serde_json::Value = serde_json::from_slice(&a.route(&del).body).unwrap();
        assert_eq!(site["check"]["ok"], true, "{site}");
    }
}
