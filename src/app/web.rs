//! `gaitscope live --web`: the live session in a browser, for machines without a display.
//!
//! ```text
//!  control page ──POST /command (JSON) ──▶ WebRequest → Command ──▶ sim thread (as the panel)
//!        ▲                                                            │
//!        └──── GET /events (server-sent events: the Snapshot, ≤ 20 Hz) ◀┘
//!  Rerun web viewer (its files, served by us) ◀── Rerun gRPC server ◀── the same stream
//! ```
//! The page is a front-end like the egui panel: it only sends [`Command`]s (through
//! [`commands`], which checks each request against the snapshot first) and reads
//! [`Snapshot`]s. Every server binds the address asked for, loopback by default.

use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpListener};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Deserialize;
use serde_json::{Value, json};

use super::{Breakpoint, Command, LiveCondition, MAX_SPEED, MIN_SPEED, SimHandle, Slot, Snapshot};
use crate::damage::{Edit, JointState, Push};
use crate::policy::ActionMode;

/// The control page: static HTML and JS, no build step.
const PAGE: &str = include_str!("web/control.html");
/// How often the event stream looks for a new snapshot (it sends only changes).
const EVENT_PERIOD: Duration = Duration::from_millis(50);
/// A comment line this often keeps idle connections (and proxies) open.
const KEEP_ALIVE: Duration = Duration::from_secs(5);
const MAX_BODY_BYTES: u64 = 256 * 1024;
const MAX_EVENT_CLIENTS: usize = 16;
/// Most single steps one request may ask for.
pub const MAX_STEPS_PER_REQUEST: usize = 1000;
/// Command requests whose bodies are being read at once; more wait for a free slot (503).
const MAX_POSTS_IN_FLIGHT: usize = 8;
/// A command request's body must arrive within this; a slower one loses its slot (its thread
/// finishes or not on its own, but answers nothing the sim acts on).
const BODY_TIMEOUT: Duration = Duration::from_secs(5);

/// Damage edits one request may carry (each may name every joint).
pub const MAX_EDITS_PER_REQUEST: usize = 64;

/// Where the three servers listen.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WebOptions {
    pub bind: IpAddr,
    /// The control page.
    pub port: u16,
    /// Rerun's web viewer (HTML + wasm).
    pub viewer_port: u16,
    /// The gRPC server the web viewer reads the stream from.
    pub grpc_port: u16,
}

impl WebOptions {
    /// Rerun's own defaults for the viewer and gRPC ports, the control page beside them.
    pub const DEFAULT_PORT: u16 = 9080;
    pub const DEFAULT_VIEWER_PORT: u16 = 9090;
    pub const DEFAULT_GRPC_PORT: u16 = 9876;

    /// The host a browser on this machine (or at the end of an `ssh -L`) uses.
    fn host(&self) -> String {
        match self.bind {
            IpAddr::V4(ip) if ip.is_unspecified() => "127.0.0.1".into(),
            IpAddr::V6(ip) if ip.is_unspecified() => "[::1]".into(),
            IpAddr::V4(ip) => ip.to_string(),
            IpAddr::V6(ip) => format!("[{ip}]"),
        }
    }

    pub fn control_url(&self) -> String {
        format!("http://{}:{}/", self.host(), self.port)
    }

    pub fn grpc_url(&self) -> String {
        format!("rerun+http://{}:{}/proxy", self.host(), self.grpc_port)
    }

    /// The web viewer, told where the stream is.
    pub fn viewer_url(&self) -> String {
        format!(
            "http://{}:{}/?url={}",
            self.host(),
            self.viewer_port,
            percent_encode(&self.grpc_url())
        )
    }

    /// The tunnel that serves all three to a laptop: `ssh -L … user@this-machine`.
    pub fn ssh_tunnel(&self) -> String {
        let forward = |p: u16| format!("-L {p}:{}:{p}", self.host());
        format!(
            "ssh {} {} {} USER@THIS-MACHINE",
            forward(self.port),
            forward(self.viewer_port),
            forward(self.grpc_port)
        )
    }

    pub fn is_loopback(&self) -> bool {
        self.bind.is_loopback()
    }

    /// Each port free on the bind address, before anything starts (Rerun's gRPC server
    /// binds on its own thread and would only log a failure).
    pub fn check_ports(&self) -> Result<(), WebError> {
        let ports = [
            ("control page", self.port),
            ("web viewer", self.viewer_port),
            ("gRPC stream", self.grpc_port),
        ];
        // A port given twice is a usage error, whatever is listening on it.
        for (i, (_, port)) in ports.iter().enumerate() {
            if ports[..i].iter().any(|(_, p)| p == port) {
                return Err(WebError::SamePort { port: *port });
            }
        }
        for (what, port) in ports {
            let addr = SocketAddr::new(self.bind, port);
            TcpListener::bind(addr).map_err(|e| WebError::Bind {
                what,
                addr,
                reason: e.into(),
            })?;
        }
        Ok(())
    }
}

fn percent_encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

#[derive(Debug, thiserror::Error)]
pub enum WebError {
    #[error("cannot listen for the {what} on {addr}: {reason} (pick another port)")]
    Bind {
        what: &'static str,
        addr: SocketAddr,
        #[source]
        reason: crate::Cause,
    },
    #[error("port {port} is given twice: the control page, web viewer and gRPC need one each")]
    SamePort { port: u16 },
    #[error("starting Rerun's web viewer: {0}")]
    Viewer(#[source] crate::Cause),
    #[error("cannot listen for the {what} on the socket {path}")]
    Socket {
        what: &'static str,
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("cannot create a private folder for the servers' sockets under {}", std::env::temp_dir().display())]
    SocketDir(#[source] std::io::Error),
}

/// The public ports, each behind a [`super::guard::Guard`] (connection cap, header timeout
/// and size, Host check on loopback), and the Unix sockets of the servers behind them, in a
/// private folder: only the guards (this user's processes) can reach a server.
pub struct Front {
    guards: Vec<super::guard::Guard>,
    /// What the control page's and the web viewer's guards stamp on every request they relay
    /// ([`super::guard::GUARD_HEADER`]); the servers behind them refuse a request without it.
    secret: String,
    pub control_backend: PathBuf,
    pub viewer_backend: PathBuf,
    pub grpc_backend: PathBuf,
    /// Declared last: removed (with the sockets) after the guards stop.
    _sockets: crate::files::PrivateDir,
}

impl Front {
    /// Binds the three public ports (a taken one is a clear error) and starts their guards;
    /// the servers come up behind them after.
    pub fn bind(options: &WebOptions) -> Result<Self, WebError> {
        use super::guard::{Guard, GuardLimits};
        let limits = GuardLimits::new(options.is_loopback());
        let sockets =
            crate::files::PrivateDir::create("gaitscope-web").map_err(WebError::SocketDir)?;
        // 128 bits from the OS-seeded generator: this user's other processes, which can reach
        // the sockets, cannot guess it.
        let secret = format!("{:032x}", rand::random::<u128>());
        let control_backend = sockets.join("control.sock");
        let viewer_backend = sockets.join("viewer.sock");
        let grpc_backend = sockets.join("grpc.sock");
        let mut guards = Vec::new();
        // Our control and viewer servers require the secret too; the gRPC proxy takes none
        // (HTTP/2 frames carry no header the relay could add), its socket is its only door.
        for (what, port, stamped, backend) in [
            ("control page", options.port, true, &control_backend),
            ("web viewer", options.viewer_port, true, &viewer_backend),
            ("gRPC stream", options.grpc_port, false, &grpc_backend),
        ] {
            let addr = SocketAddr::new(options.bind, port);
            let bind_error = |e: std::io::Error| WebError::Bind {
                what,
                addr,
                reason: e.into(),
            };
            let listener = TcpListener::bind(addr).map_err(bind_error)?;
            let limits = GuardLimits {
                secret: stamped.then(|| secret.clone()),
                ..limits.clone()
            };
            guards.push(Guard::spawn(listener, backend.clone(), limits, what).map_err(bind_error)?);
        }
        Ok(Self {
            guards,
            secret,
            control_backend,
            viewer_backend,
            grpc_backend,
            _sockets: sockets,
        })
    }

    /// Connections open on each public port (control page, web viewer, gRPC).
    pub fn open_connections(&self) -> Vec<usize> {
        self.guards.iter().map(|g| g.open_connections()).collect()
    }
}

/// The running web front-end: Rerun's web viewer (its files, served by us) and the control
/// page's HTTP server, on loopback behind the [`Front`]'s guards.
pub struct WebServer {
    options: WebOptions,
    control: tiny_http::Server,
    _viewer: super::viewer_assets::ViewerAssets,
    front: Front,
    /// Checkpoint folders the page may open (the page never names an arbitrary path).
    checkpoints: Vec<PathBuf>,
    /// A search folder's findings (`live --search DIR`), for the page's "next failure".
    findings: Vec<crate::search::Finding>,
    /// How the stream reaches the web viewer ([`crate::telemetry::web_stream_batch`]), read
    /// once: the page shows it.
    viewer_batch: std::time::Duration,
}

/// What the control server did, for the end-of-session report.
#[derive(Debug, Clone, Default)]
pub struct WebStats {
    pub seconds: f64,
    pub requests: u64,
    pub commands: u64,
    pub refused: u64,
}

impl WebServer {
    /// Starts the web viewer and the control page behind `front` (the gRPC server is the
    /// stream's sink, started on `front.grpc_backend`).
    pub fn start(
        options: WebOptions,
        front: Front,
        checkpoints: Vec<PathBuf>,
        findings: Vec<crate::search::Finding>,
    ) -> Result<Self, WebError> {
        let viewer = super::viewer_assets::ViewerAssets::start(
            &front.viewer_backend,
            front.secret.clone(),
            options.is_loopback(),
        )?;
        // tiny_http's error is already a boxed error: the cause as it is.
        let control = tiny_http::Server::http_unix(&front.control_backend).map_err(|reason| {
            WebError::Socket {
                what: "control page",
                path: front.control_backend.clone(),
                reason,
            }
        })?;
        Ok(Self {
            options,
            control,
            _viewer: viewer,
            front,
            checkpoints,
            findings,
            viewer_batch: crate::telemetry::web_stream_batch(),
        })
    }

    pub fn options(&self) -> &WebOptions {
        &self.options
    }

    /// Answers requests until the sim stops (the page's Quit) or `deadline` passes.
    /// Serves until Quit, the deadline, or `stop` (set by the SIGINT/SIGTERM handler): the
    /// caller then shuts the sim down, which flushes `--save` and yields the session report.
    pub fn serve(
        &self,
        sim: &SimHandle,
        deadline: Option<Instant>,
        stop: &std::sync::atomic::AtomicBool,
    ) -> WebStats {
        let started = Instant::now();
        let mut stats = WebStats::default();
        let clients = Arc::new(AtomicUsize::new(0));
        let posts = Posts::default();
        loop {
            posts.expire();
            if sim.snapshot().stopped
                || deadline.is_some_and(|d| Instant::now() >= d)
                || stop.load(std::sync::atomic::Ordering::Relaxed)
            {
                break;
            }
            let request = match self.control.recv_timeout(Duration::from_millis(100)) {
                Ok(Some(request)) => request,
                Ok(None) => continue,
                Err(_) => break,
            };
            stats.requests += 1;
            match self.route(request, sim, &clients, &posts) {
                Routed::Command => stats.commands += 1,
                Routed::Refused => stats.refused += 1,
                Routed::Other => {}
            }
        }
        stats.seconds = started.elapsed().as_secs_f64();
        stats
    }

    fn route(
        &self,
        request: tiny_http::Request,
        sim: &SimHandle,
        clients: &Arc<AtomicUsize>,
        posts: &Posts,
    ) -> Routed {
        if let Err(reason) = self.check_origin(&request) {
            respond(request, 403, &json!({ "error": reason }));
            return Routed::Refused;
        }
        let path = request.url().split('?').next().unwrap_or("/").to_string();
        match (request.method(), path.as_str()) {
            (tiny_http::Method::Get, "/") => {
                // The page arrives with the state inside it, so it never shows an empty
                // "connecting…" before the first event (a screenshot, a slow stream).
                let first = self.snapshot_json(&sim.snapshot(), posts);
                let response = tiny_http::Response::from_string(page_with(&first))
                    .with_header(header("Content-Type", "text/html; charset=utf-8"));
                let _ = request.respond(response);
                Routed::Other
            }
            (tiny_http::Method::Get, "/state") => {
                let body = self.snapshot_json(&sim.snapshot(), posts);
                respond(request, 200, &body);
                Routed::Other
            }
            (tiny_http::Method::Get, "/scenario.json") => {
                let scenario = sim.snapshot().recorded_scenario.unwrap_or(Value::Null);
                let text = serde_json::to_string_pretty(&scenario).unwrap_or_default();
                let response = tiny_http::Response::from_string(format!("{text}\n"))
                    .with_header(header("Content-Type", "application/json"))
                    .with_header(header(
                        "Content-Disposition",
                        "attachment; filename=\"live-session.json\"",
                    ));
                let _ = request.respond(response);
                Routed::Other
            }
            (tiny_http::Method::Get, "/saved-state.json") => {
                let Some(state) = sim.snapshot().saved_state else {
                    respond(request, 409, &json!({ "error": "no model is loaded" }));
                    return Routed::Refused;
                };
                let name = format!("gaitscope-state-step{}.json", state.env.step);
                let response = tiny_http::Response::from_string(state.to_json())
                    .with_header(header("Content-Type", "application/json"))
                    .with_header(header(
                        "Content-Disposition",
                        &format!("attachment; filename=\"{name}\""),
                    ));
                let _ = request.respond(response);
                Routed::Other
            }
            (tiny_http::Method::Get, "/events") => {
                if clients.load(Ordering::SeqCst) >= MAX_EVENT_CLIENTS {
                    respond(request, 503, &json!({ "error": "too many open pages" }));
                    return Routed::Refused;
                }
                self.stream_events(request, sim, clients.clone(), posts.clone());
                Routed::Other
            }
            (tiny_http::Method::Post, "/command") => self.post_command(request, sim, posts),
            _ => {
                respond(
                    request,
                    404,
                    &json!({ "error": format!("no such page: {path}") }),
                );
                Routed::Refused
            }
        }
    }

    /// Loopback servers answer only pages that name a loopback host (no DNS rebinding), and
    /// commands only as JSON (a cross-site form post cannot send that without permission).
    fn check_origin(&self, request: &tiny_http::Request) -> Result<(), String> {
        let get = |name: &'static str| {
            request
                .headers()
                .iter()
                .find(|h| h.field.equiv(name))
                .map(|h| h.value.as_str().to_string())
        };
        // Only what came through the guard (this user's other processes can reach its socket too).
        if get(super::guard::GUARD_HEADER).as_deref() != Some(self.front.secret.as_str()) {
            return Err("this port is served through the control page's public port only".into());
        }
        if self.options.is_loopback() {
            let host = get("Host").unwrap_or_default();
            if !super::guard::is_loopback_host(&host) {
                return Err(format!(
                    "this server is bound to loopback and answers only localhost, not '{host}'"
                ));
            }
        }
        if *request.method() == tiny_http::Method::Post {
            // The media type itself, parameters (`; charset=utf-8`) aside: not a prefix
            // (`application/jsonx` is not JSON).
            let kind = get("Content-Type").unwrap_or_default();
            let media = kind.split(';').next().unwrap_or_default().trim();
            if !media.eq_ignore_ascii_case("application/json") {
                return Err("commands must be sent as application/json".into());
            }
            // A browser names the page that sends a command; only this server's own may.
            if let Some(origin) = get("Origin") {
                let host = get("Host").unwrap_or_default();
                if !origin.eq_ignore_ascii_case(&format!("http://{host}")) {
                    return Err(format!(
                        "commands come only from this server's own page (http://{host}), not from '{origin}'"
                    ));
                }
            }
        }
        Ok(())
    }

    /// A command request, read and applied on a thread of its own so that a client that
    /// stalls mid-body holds only its slot, never the serving loop (GET /state, Quit and
    /// `--exit-after` go on). Applied in the order bodies complete.
    fn post_command(&self, request: tiny_http::Request, sim: &SimHandle, posts: &Posts) -> Routed {
        let Some(slot) = posts.take_slot() else {
            respond(
                request,
                503,
                &json!({ "error": format!("{MAX_POSTS_IN_FLIGHT} command requests are still being read; try again") }),
            );
            return Routed::Refused;
        };
        let (tx, shared, checkpoints) = (
            sim.sender(),
            sim.shared_snapshot(),
            self.checkpoints.clone(),
        );
        let mine = posts.clone();
        let spawned = std::thread::Builder::new()
            .name("gaitscope-web-command".into())
            .spawn(move || {
                let mut request = request;
                let body = read_body(&mut request);
                // Past its time the slot was given back and the request answers nothing.
                if !mine.release(slot) {
                    respond(
                        request,
                        408,
                        &json!({ "error": "the request body came too slowly" }),
                    );
                    return;
                }
                let snapshot = lock_snapshot(&shared);
                let parsed = body.and_then(|body| {
                    let request = WebRequest::parse(&body)?;
                    let what = request.describe();
                    Ok((what, commands(request, &snapshot, &checkpoints)?))
                });
                match parsed {
                    Ok((what, commands)) => {
                        // The page is the sim's only sender: its command has been applied once
                        // the snapshot's `commands_handled` reaches this receipt.
                        let mut sent = mine.sent.lock().unwrap_or_else(|e| e.into_inner());
                        let n = commands.len() as u64;
                        let sent_at = Instant::now();
                        if !commands.into_iter().all(|c| tx.send(c).is_ok()) {
                            respond(request, 503, &json!({ "error": "the simulation stopped" }));
                            return;
                        }
                        *sent += n;
                        if n > 0 {
                            *mine.latest.lock().unwrap_or_else(|e| e.into_inner()) = Some(Posted {
                                receipt: *sent,
                                what,
                                sent_at,
                            });
                        }
                        respond(request, 200, &json!({ "ok": true, "receipt": *sent }));
                    }
                    Err(error) => {
                        respond(request, 400, &json!({ "error": without_backtrace(&error) }))
                    }
                }
            });
        if spawned.is_err() {
            posts.release(slot);
            return Routed::Refused;
        }
        Routed::Command
    }

    /// Server-sent events on their own thread: a snapshot whenever it changed, until the
    /// page goes away or the sim stops.
    fn stream_events(
        &self,
        request: tiny_http::Request,
        sim: &SimHandle,
        clients: Arc<AtomicUsize>,
        posts: Posts,
    ) {
        let shared = sim.shared_snapshot();
        let statics = self.statics();
        clients.fetch_add(1, Ordering::SeqCst);
        let open = clients.clone();
        let spawned = std::thread::Builder::new()
            .name("gaitscope-web-events".into())
            .spawn(move || {
                // Our own framing on the raw socket: tiny_http's chunked writer would hold
                // events back until 8 KiB had gathered.
                let mut out = request.into_writer();
                let _ = event_loop(&mut out, &shared, &statics, &posts);
                open.fetch_sub(1, Ordering::SeqCst);
            });
        if spawned.is_err() {
            clients.fetch_sub(1, Ordering::SeqCst);
        }
    }

    /// What never changes during a session: offered checkpoints and bundled scenarios.
    fn statics(&self) -> Value {
        json!({
            "checkpoints": self.checkpoints.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
            "scenarios": crate::damage::scenario::OOD_SUITE.iter().map(|(n, _)| *n).collect::<Vec<_>>(),
            "viewer_url": self.options.viewer_url(),
            "viewer_batch_ms": self.viewer_batch.as_millis() as u64,
            "findings": self.findings,
            "limits": { "min_speed": MIN_SPEED, "max_speed": MAX_SPEED, "max_steps": MAX_STEPS_PER_REQUEST },
        })
    }

    fn snapshot_json(&self, snapshot: &Snapshot, posts: &Posts) -> Value {
        let mut value = snapshot_json(snapshot);
        value["last_command"] = last_command_json(posts, snapshot);
        value["session"] = self.statics();
        value
    }
}

enum Routed {
    Command,
    Refused,
    Other,
}

fn event_loop(
    out: &mut dyn Write,
    shared: &Arc<Mutex<Snapshot>>,
    statics: &Value,
    posts: &Posts,
) -> std::io::Result<()> {
    out.write_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-cache\r\n\
          Connection: close\r\n\r\n",
    )?;
    let mut last: Option<(Snapshot, Value)> = None;
    let mut last_write = Instant::now();
    loop {
        let snapshot = shared
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .clone();
        // A command's timing can land after the snapshot that applied it (a paused sim sends
        // no other): either changing sends an event.
        let command = last_command_json(posts, &snapshot);
        if last.as_ref() != Some(&(snapshot.clone(), command.clone())) {
            let mut value = snapshot_json(&snapshot);
            value["session"] = statics.clone();
            value["last_command"] = command.clone();
            write!(out, "data: {value}\n\n")?;
            out.flush()?;
            last_write = Instant::now();
            if snapshot.stopped {
                return Ok(());
            }
            last = Some((snapshot, command));
        } else if last_write.elapsed() >= KEEP_ALIVE {
            out.write_all(b": keep-alive\n\n")?;
            out.flush()?;
            last_write = Instant::now();
        }
        std::thread::sleep(EVENT_PERIOD);
    }
}

pub(super) fn header(name: &str, value: &str) -> tiny_http::Header {
    // Both are ASCII of ours (literals, numbers): this cannot fail.
    tiny_http::Header::from_bytes(name.as_bytes(), value.as_bytes())
        .unwrap_or_else(|_| unreachable!("ASCII header {name}"))
}

fn respond(request: tiny_http::Request, status: u16, body: &Value) {
    let response = tiny_http::Response::from_string(body.to_string())
        .with_status_code(status)
        .with_header(header("Content-Type", "application/json"))
        .with_header(header("Cache-Control", "no-store"));
    let _ = request.respond(response);
}

/// The body of a command request, at most [`MAX_BODY_BYTES`].
fn read_body(request: &mut tiny_http::Request) -> Result<String, String> {
    let mut body = String::new();
    request
        .as_reader()
        .take(MAX_BODY_BYTES + 1)
        .read_to_string(&mut body)
        .map_err(|e| format!("reading the request: {e}"))?;
    if body.len() as u64 > MAX_BODY_BYTES {
        return Err(format!("request larger than {MAX_BODY_BYTES} bytes"));
    }
    Ok(body)
}

fn lock_snapshot(shared: &Arc<std::sync::Mutex<Snapshot>>) -> Snapshot {
    shared.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

/// Command requests in flight: their slots (by when their reading began) and the receipt
/// counter the sim's `commands_handled` is compared with.
#[derive(Clone, Default)]
struct Posts {
    slots: Arc<std::sync::Mutex<Vec<(u64, Instant)>>>,
    next: Arc<std::sync::atomic::AtomicU64>,
    sent: Arc<std::sync::Mutex<u64>>,
    /// The latest request that sent commands, from the page or any other client.
    latest: Arc<std::sync::Mutex<Option<Posted>>>,
}

/// A request whose commands went to the sim: its receipt, what it asked, when it was sent.
#[derive(Debug, Clone)]
struct Posted {
    receipt: u64,
    what: String,
    sent_at: Instant,
}

/// The latest request's timing as the page shows it: from the server sending its commands to
/// the sim taking the last of them (any client's, the API's as well as the page's own clicks).
/// `null` until one was sent; `applied_in_ms` null while the sim has not taken it yet.
fn last_command_json(posts: &Posts, snapshot: &Snapshot) -> Value {
    let latest = posts
        .latest
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .clone();
    let Some(posted) = latest else {
        return Value::Null;
    };
    // The sim's `last_command_at` is this request's last command only while no later one has
    // been taken; otherwise the page shows the request without a time.
    let applied_in_ms = match snapshot.last_command_at {
        Some(at) if snapshot.commands_handled == posted.receipt => {
            Some(at.saturating_duration_since(posted.sent_at).as_secs_f64() * 1e3)
        }
        _ => None,
    };
    json!({
        "receipt": posted.receipt,
        "command": posted.what,
        "applied": snapshot.commands_handled >= posted.receipt,
        "applied_in_ms": applied_in_ms,
    })
}

impl Posts {
    fn take_slot(&self) -> Option<u64> {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        if slots.len() >= MAX_POSTS_IN_FLIGHT {
            return None;
        }
        let id = self.next.fetch_add(1, Ordering::SeqCst);
        slots.push((id, Instant::now()));
        Some(id)
    }

    /// Gives the slot back; false if it had already expired.
    fn release(&self, id: u64) -> bool {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        let before = slots.len();
        slots.retain(|(i, _)| *i != id);
        slots.len() < before
    }

    /// Frees the slots of bodies slower than [`BODY_TIMEOUT`].
    fn expire(&self) {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        slots.retain(|(_, started)| started.elapsed() < BODY_TIMEOUT);
    }
}

/// What the page may ask, one JSON object each: `{"command": "pause"}`,
/// `{"command": "edit", "edit": "fail:ankle_3"}`, `{"command": "step", "count": 5}`…
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "command", rename_all = "snake_case", deny_unknown_fields)]
pub enum WebRequest {
    Pause,
    Resume,
    Step {
        #[serde(default = "one")]
        count: usize,
    },
    Speed {
        value: f64,
    },
    Reset,
    Condition {
        value: String,
    },
    Seed {
        value: u64,
    },
    StepLimit {
        value: usize,
    },
    /// Edits in the CLI's syntax (`fail:ankle_3`, `scale:hip_1=0.4`, `heal:all`,
    /// `push:torso=0,40,0@5`).
    Edit {
        edit: String,
    },
    /// The attribution view (why z moved) on or off.
    Attribution {
        on: bool,
    },
    /// An external force (newtons, world frame) on a body for `steps` env steps.
    Push {
        body: String,
        force: [f64; 3],
        #[serde(default = "one")]
        steps: usize,
    },
    Sampled {
        on: bool,
    },
    Compare {
        on: bool,
    },
    /// Open one of the offered checkpoint folders in `slot` (`main` or `compare`).
    Load {
        slot: String,
        dir: String,
    },
    BreakOn {
        list: String,
    },
    Rewind {
        step: usize,
    },
    Fork {
        edits: String,
    },
    EndFork,
    /// A bundled scenario by `name`, an uploaded scenario file's `json`, or neither: none.
    Scenario {
        #[serde(default)]
        name: Option<String>,
        #[serde(default)]
        json: Option<String>,
    },
    Quit,
}

/// An error for the page: what it says, without a backtrace some libraries append (candle's
/// errors carry one when RUST_BACKTRACE is set) — no source paths reach a browser.
fn without_backtrace(text: &str) -> String {
    let cut = ["\nstack backtrace:", "\nStack backtrace:", "\n   0: "]
        .iter()
        .filter_map(|m| text.find(m))
        .min()
        .unwrap_or(text.len());
    text[..cut].trim_end().to_string()
}

fn one() -> usize {
    1
}

impl WebRequest {
    /// One request body: JSON with no key given twice, one known command with exactly its
    /// fields (serde's `deny_unknown_fields` lets extra keys through on a command without
    /// fields, so those are checked here).
    pub fn parse(body: &str) -> Result<Self, String> {
        let malformed = |e: &dyn std::fmt::Display| format!("malformed request: {e}");
        let value = crate::damage::scenario::strict_json(body).map_err(|e| malformed(&e))?;
        let request: WebRequest =
            serde_json::from_value(value.clone()).map_err(|e| malformed(&e))?;
        let bare = matches!(
            request,
            Self::Pause | Self::Resume | Self::Reset | Self::EndFork | Self::Quit
        );
        if bare
            && let Some(extra) = value
                .as_object()
                .and_then(|o| o.keys().find(|k| k.as_str() != "command"))
        {
            return Err(malformed(&format!(
                "unknown field `{extra}`: this command takes none"
            )));
        }
        Ok(request)
    }

    /// A few words for the page's "last command" line.
    fn describe(&self) -> String {
        match self {
            Self::Pause => "pause".into(),
            Self::Resume => "resume".into(),
            Self::Step { count } => format!("step {count}"),
            Self::Speed { value } => format!("speed {value}×"),
            Self::Reset => "reset".into(),
            Self::Condition { value } => format!("condition {value}"),
            Self::Seed { value } => format!("seed {value}"),
            Self::StepLimit { value } => format!("step limit {value}"),
            Self::Edit { edit } => format!("edit {edit}"),
            Self::Attribution { on } => format!("attribution {}", on_off(*on)),
            Self::Push { body, steps, .. } => format!("push {body} for {steps} steps"),
            Self::Sampled { on } => format!("sampled actions {}", on_off(*on)),
            Self::Compare { on } => format!("compare {}", on_off(*on)),
            Self::Load { slot, dir } => format!("load {dir} as {slot}"),
            Self::BreakOn { list } => format!("break on {list}"),
            Self::Rewind { step } => format!("rewind to step {step}"),
            Self::Fork { edits } => format!("fork {edits}"),
            Self::EndFork => "end fork".into(),
            Self::Scenario {
                name: Some(name), ..
            } => format!("scenario {name}"),
            Self::Scenario { json: Some(_), .. } => "scenario (uploaded)".into(),
            Self::Scenario { .. } => "no scenario".into(),
            Self::Quit => "quit".into(),
        }
    }
}

fn on_off(on: bool) -> &'static str {
    if on { "on" } else { "off" }
}

/// The control page with `first` (the state when it was asked for) inside it. `<` is escaped so
/// that no string in the state can close the script element.
fn page_with(first: &Value) -> String {
    let json = first.to_string().replace('<', "\\u003c");
    PAGE.replacen("/*FIRST_SNAPSHOT*/null", &json, 1)
}

/// The commands a request stands for, or why it changes nothing. Checked here against the
/// snapshot so that the page hears at once; the sim thread checks again as it applies them.
pub fn commands(
    request: WebRequest,
    snapshot: &Snapshot,
    checkpoints: &[PathBuf],
) -> Result<Vec<Command>, String> {
    let joint_names = || {
        snapshot
            .lanes
            .first()
            .map(|l| l.joint_names.clone())
            .ok_or_else(|| "no model is loaded".to_string())
    };
    let check_body = |push: &Push| -> Result<(), String> {
        let bodies = snapshot
            .lanes
            .first()
            .map(|l| l.body_names.clone())
            .ok_or_else(|| "no model is loaded".to_string())?;
        if bodies.contains(&push.body) {
            Ok(())
        } else {
            // The env's own refusal, as the sim thread would give it.
            Err(crate::env::EnvError::NoSuchBody {
                name: push.body.clone(),
                known: bodies.join(", "),
            }
            .to_string())
        }
    };
    // An edit list, its joints and bodies checked by name: the parser and resolver the CLI uses.
    let parse_edits = |text: &str| -> Result<Vec<Edit>, String> {
        let names = joint_names()?;
        let edits = Edit::parse_list(text).map_err(|e| e.to_string())?;
        if edits.len() > MAX_EDITS_PER_REQUEST {
            return Err(format!(
                "{} edits in one request; at most {MAX_EDITS_PER_REQUEST}",
                edits.len()
            ));
        }
        for edit in &edits {
            match edit {
                Edit::Joint(e) => e
                    .target
                    .resolve(&names)
                    .map(|_| ())
                    .map_err(|e| e.to_string())?,
                Edit::Push(p) => check_body(p)?,
            }
        }
        Ok(edits)
    };
    Ok(match request {
        WebRequest::Pause => vec![Command::Pause],
        WebRequest::Resume => vec![Command::Resume],
        WebRequest::Step { count } => {
            if !(1..=MAX_STEPS_PER_REQUEST).contains(&count) {
                return Err(format!(
                    "step count must be 1 to {MAX_STEPS_PER_REQUEST}, got {count}"
                ));
            }
            vec![Command::StepOnce; count]
        }
        WebRequest::Speed { value } => {
            if !(value.is_finite() && (MIN_SPEED..=MAX_SPEED).contains(&value)) {
                return Err(format!(
                    "speed must be between {MIN_SPEED}× and {MAX_SPEED}× real time, got {value}"
                ));
            }
            vec![Command::SetSpeed(value)]
        }
        WebRequest::Reset => vec![Command::Reset],
        WebRequest::Condition { value } => {
            vec![Command::SetCondition(value.parse::<LiveCondition>()?)]
        }
        WebRequest::Seed { value } => vec![Command::SetSeed(value)],
        WebRequest::StepLimit { value } => {
            if value == 0 {
                return Err("the step limit must be at least 1".into());
            }
            vec![Command::SetStepLimit(value)]
        }
        WebRequest::Edit { edit } => {
            let names = joint_names()?;
            let mut commands = Vec::new();
            for edit in parse_edits(&edit)? {
                match edit {
                    Edit::Joint(edit) => {
                        let actuators = edit.target.resolve(&names).map_err(|e| e.to_string())?;
                        commands.extend(actuators.into_iter().map(|actuator| Command::Override {
                            actuator,
                            change: edit.change,
                        }));
                    }
                    Edit::Push(push) => commands.push(Command::Push(push)),
                }
            }
            commands
        }
        WebRequest::Attribution { on } => vec![Command::SetAttribution(on)],
        WebRequest::Push { body, force, steps } => {
            let push = Push::new(&body, force, steps).map_err(|e| e.to_string())?;
            check_body(&push)?;
            vec![Command::Push(push)]
        }
        WebRequest::Sampled { on } => vec![Command::SetActionMode(if on {
            ActionMode::Sampled
        } else {
            ActionMode::Deterministic
        })],
        WebRequest::Compare { on } => {
            if on && snapshot.compare_checkpoint.is_none() {
                return Err("load a second model first".into());
            }
            vec![Command::SetCompare(on)]
        }
        WebRequest::Load { slot, dir } => {
            let slot = match slot.as_str() {
                "main" => Slot::Main,
                "compare" => Slot::Compare,
                other => return Err(format!("unknown slot '{other}' (main or compare)")),
            };
            let Some(dir) = checkpoints.iter().find(|p| p.display().to_string() == dir) else {
                return Err(format!(
                    "'{dir}' is not one of the offered checkpoints ({})",
                    checkpoints
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            };
            vec![Command::Load {
                slot,
                dir: dir.clone(),
            }]
        }
        WebRequest::BreakOn { list } => {
            let list = Breakpoint::parse_list(&list).map_err(|e| e.to_string())?;
            let names = joint_names()?;
            for b in &list {
                b.validate(&names, snapshot.has_probe)
                    .map_err(|e| e.to_string())?;
            }
            vec![Command::SetBreakpoints(list)]
        }
        WebRequest::Rewind { step } => {
            if step > snapshot.rewindable {
                return Err(format!(
                    "can rewind to steps 0 to {} of this episode, not {step}",
                    snapshot.rewindable
                ));
            }
            vec![Command::Rewind(step)]
        }
        WebRequest::Fork { edits } => vec![Command::Fork(parse_edits(&edits)?)],
        WebRequest::EndFork => vec![Command::EndFork],
        WebRequest::Scenario { name, json } => {
            let scenario = match (name, json) {
                (Some(_), Some(_)) => {
                    return Err("give a scenario's name or its JSON, not both".into());
                }
                (Some(name), None) => {
                    if !crate::damage::scenario::OOD_SUITE
                        .iter()
                        .any(|(n, _)| *n == name)
                    {
                        return Err(format!(
                            "no bundled scenario '{name}' (bundled: {}; or upload a file)",
                            crate::damage::scenario::OOD_SUITE
                                .map(|(n, _)| n)
                                .join(", ")
                        ));
                    }
                    Some(
                        crate::damage::scenario::Scenario::load(&name)
                            .map_err(|e| e.to_string())?,
                    )
                }
                (None, Some(text)) => Some(
                    crate::damage::scenario::Scenario::from_json(&text, "uploaded file")
                        .map_err(|e| e.to_string())?,
                ),
                (None, None) => None,
            };
            vec![Command::SetScenario(scenario)]
        }
        WebRequest::Quit => vec![Command::Quit],
    })
}

fn state_name(state: JointState) -> &'static str {
    match state {
        JointState::Healthy => "healthy",
        JointState::Triggered => "triggered",
        JointState::Manual => "manual",
        JointState::Dead => "dead",
    }
}

/// The snapshot as the page reads it.
pub fn snapshot_json(s: &Snapshot) -> Value {
    let lanes: Vec<Value> = s
        .lanes
        .iter()
        .map(|l| {
            let joints: Vec<Value> = (0..l.joint_names.len())
                .map(|i| {
                    // What the joint has lost, in the words and colour of every view.
                    let torque = crate::palette::Torque::of(l.scale[i], l.states[i]);
                    let [r, g, b] = torque.rgb();
                    json!({
                        "name": l.joint_names[i],
                        "torque": torque.describe(),
                        "torque_lost": torque.lost(),
                        "cause": l.causes[i],
                        "color": format!("#{r:02x}{g:02x}{b:02x}"),
                        "leg": l.joint_legs[i],
                        "fatigue": l.fatigue[i],
                        "state": state_name(l.states[i]),
                        "scale": l.scale[i],
                        "damaged": l.damaged[i],
                        "probe": l.probe.map(|p| p[i]),
                        "commanded": l.commanded[i],
                        "applied": l.applied[i],
                    })
                })
                .collect();
            json!({
                "label": l.label,
                "root": l.root,
                "encoder": l.encoder,
                "bodies": l.body_names,
                "checkpoint": l.checkpoint.as_ref().map(|p| p.display().to_string()),
                "step": l.step,
                "distance": l.distance,
                "success": l.success,
                "done": l.done,
                "ending": l.ending,
                "threshold": l.threshold,
                "fatigue_triggers": l.fatigue_triggers,
                "joints": joints,
                "events": l.events,
                "last_event": l.last_event,
                "event_log": l.event_log.iter().map(|e| json!({"step": e.step, "kind": e.kind, "text": e.text})).collect::<Vec<_>>(),
                "fork_of": l.fork_of,
            })
        })
        .collect();
    json!({
        "paused": s.paused,
        "speed": s.speed,
        "condition": s.condition.name(),
        "world": s.world,
        "condition_meanings": LiveCondition::ALL
            .iter()
            .zip(&s.condition_meanings)
            .map(|(c, m)| (c.name().to_string(), Value::from(m.as_str())))
            .collect::<serde_json::Map<String, Value>>(),
        "seed": s.seed,
        "step_limit": s.step_limit,
        "sampled": s.mode == ActionMode::Sampled,
        "compare": s.compare,
        "attribution": s.attribution,
        "compare_checkpoint": s.compare_checkpoint.as_ref().map(|p| p.display().to_string()),
        "episode_seed": s.episode_seed,
        "episodes": s.episodes,
        "global_step": s.global_step,
        "steps_per_s": s.steps_per_s,
        "target_steps_per_s": s.target_steps_per_s,
        "message": s.message.as_deref().map(without_backtrace),
        "breakpoints": s.breakpoints.iter().map(|b| b.to_string()).collect::<Vec<_>>(),
        "break_hit": s.break_hit.as_ref().map(|b| b.to_string()),
        "rewindable": s.rewindable,
        "branches": s.branches,
        "has_probe": s.has_probe,
        "scenario": s.scenario,
        "has_recorded_overrides": s.recorded_scenario.as_ref()
            .and_then(|v| v.get("edits")).and_then(|e| e.as_array()).is_some_and(|e| !e.is_empty()),
        "commands_handled": s.commands_handled,
        "stopped": s.stopped,
        "lanes": lanes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_name_loopback_and_encode_the_stream_address() {
        let options = WebOptions {
            bind: "127.0.0.1".parse().unwrap(),
            port: 9080,
            viewer_port: 9090,
            grpc_port: 9876,
        };
        assert_eq!(options.control_url(), "http://127.0.0.1:9080/");
        assert_eq!(
            options.viewer_url(),
            "http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy"
        );
        assert!(options.ssh_tunnel().contains("-L 9876:127.0.0.1:9876"));
        let same = WebOptions {
            grpc_port: 9080,
            ..options
        };
        assert!(matches!(
            same.check_ports(),
            Err(WebError::SamePort { port: 9080 })
        ));
    }

    #[test]
    fn requests_parse_with_defaults_and_refuse_unknown_fields() {
        let step: WebRequest = serde_json::from_str(r#"{"command":"step"}"#).unwrap();
        assert_eq!(step, WebRequest::Step { count: 1 });
        // A misspelt field is an error, not a silent default.
        assert!(serde_json::from_str::<WebRequest>(r#"{"command":"step","cout":5}"#).is_err());
        assert!(serde_json::from_str::<WebRequest>(r#"{"command":"explode"}"#).is_err());
        // A command without fields takes none; no key twice.
        assert!(WebRequest::parse(r#"{"command":"pause"}"#).is_ok());
        let err = WebRequest::parse(r#"{"command":"pause","now":true}"#).unwrap_err();
        assert!(err.contains("unknown field `now`"), "{err}");
        let err = WebRequest::parse(r#"{"command":"step","count":1,"count":9}"#).unwrap_err();
        assert!(err.contains("duplicate key"), "{err}");
    }

    #[test]
    fn page_errors_carry_no_backtrace() {
        let candle_like = "cannot load x: shape mismatch\nStack backtrace:\n   0: candle_core::error::Error::bt\n             at /root/.cargo/registry/src/candle-core/src/error.rs:264:25";
        assert_eq!(
            without_backtrace(candle_like),
            "cannot load x: shape mismatch"
        );
        assert_eq!(without_backtrace("plain"), "plain");
    }
}
