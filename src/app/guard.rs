//! The door in front of every port `live --web` serves: a TCP relay that caps connections,
//! times out slow request headers, bounds their size and — on loopback — answers only requests
//! that name a loopback host (no DNS rebinding), before a byte reaches the server behind it
//! (our control page, Rerun's web viewer, Rerun's gRPC stream; none of which does all of this
//! itself). Each server listens on a Unix socket in the session's private folder (mode 0700), so
//! no other user's process reaches it around the guard; the guard owns the public port.
//!
//! Every HTTP/1 request on a connection is judged, not only the first: the guard reads each
//! request's head (bounded, timed from its first byte), checks it, relays it and exactly its
//! `Content-Length` body, and closes a kept-alive connection that stays quiet both ways for the
//! idle timeout. A connection that opens with HTTP/2's prior-knowledge preface (a native gRPC
//! client: no browser speaks cleartext HTTP/2, so no rebinding page can) must send the whole
//! preface in time, then passes without a Host check. When every slot is taken, a newcomer
//! evicts the connection that has been quiet longest — one still sending its head, or one with
//! nothing moving either way for a second — so held-open connections cannot lock others out;
//! only when every connection is busy is the newcomer answered 503.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Limits of one guarded port.
#[derive(Debug, Clone)]
pub struct GuardLimits {
    /// Open connections at most; more evict the quietest, or are answered 503 and closed.
    pub max_connections: usize,
    /// Time for a request header to arrive whole, from its first byte (a connection's first
    /// request: from the connection).
    pub header_timeout: Duration,
    /// Its size at most.
    pub max_header_bytes: usize,
    /// A request body (`Content-Length`) at most; chunked request bodies are refused.
    pub max_body_bytes: u64,
    /// A connection with no byte moving either way for this long is closed between requests.
    pub idle_timeout: Duration,
    /// Answer only requests whose Host is localhost, 127.0.0.1 or `[::1]`.
    pub loopback_hosts_only: bool,
    /// A per-session secret the guard adds to every HTTP/1 request it relays, as the header
    /// [`GUARD_HEADER`] (after dropping any the client sent), so the server behind it can refuse
    /// whatever reached its socket some other way.
    pub secret: Option<String>,
}

/// The header that carries [`GuardLimits::secret`] to the server behind the guard.
pub const GUARD_HEADER: &str = "X-Gaitscope-Guard";

impl GuardLimits {
    pub fn new(loopback_hosts_only: bool) -> Self {
        Self {
            max_connections: 64,
            header_timeout: Duration::from_secs(5),
            max_header_bytes: 16 * 1024,
            max_body_bytes: 1024 * 1024,
            idle_timeout: Duration::from_secs(15),
            loopback_hosts_only,
            secret: None,
        }
    }
}

/// The HTTP/2 client connection preface (RFC 9113 §3.4).
const H2_PREFACE: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// A connection quiet this long may be evicted for a newcomer when the guard is full.
const EVICTABLE_AFTER: Duration = Duration::from_secs(1);

/// A running guard; dropping it stops accepting (open relays finish on their own).
pub struct Guard {
    stop: Arc<AtomicBool>,
    open: Arc<AtomicUsize>,
    addr: SocketAddr,
}

impl Guard {
    /// Relays connections accepted on `listener` to the Unix socket `backend` under `limits`.
    pub fn spawn(
        listener: TcpListener,
        backend: PathBuf,
        limits: GuardLimits,
        name: &str,
    ) -> std::io::Result<Self> {
        let addr = listener.local_addr()?;
        // Non-blocking accept, so that the thread sees `stop`.
        listener.set_nonblocking(true)?;
        let stop = Arc::new(AtomicBool::new(false));
        let open = Arc::new(AtomicUsize::new(0));
        let (stop_flag, counter) = (stop.clone(), open.clone());
        std::thread::Builder::new()
            .name(format!("gaitscope-guard-{name}"))
            .spawn(move || accept_loop(listener, backend, limits, stop_flag, counter))?;
        Ok(Self { stop, open, addr })
    }

    /// Connections open now.
    pub fn open_connections(&self) -> usize {
        self.open.load(Ordering::SeqCst)
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for Guard {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

/// Where a connection stands, for eviction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
enum Phase {
    /// Its request head is still arriving: always evictable when the guard is full.
    Head = 0,
    /// Relaying: evictable once nothing has moved either way for [`EVICTABLE_AFTER`].
    Relaying = 1,
}

/// What the accept loop and a connection's threads share about it.
struct Activity {
    id: u64,
    epoch: Instant,
    phase: AtomicU8,
    /// Milliseconds since `epoch` of the last byte either way.
    last_ms: AtomicU64,
    /// A clone of the client socket, so the accept loop can evict the connection.
    client: TcpStream,
}

impl Activity {
    fn touch(&self) {
        self.last_ms
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::SeqCst);
    }
    fn quiet_for(&self) -> Duration {
        let now = self.epoch.elapsed().as_millis() as u64;
        Duration::from_millis(now.saturating_sub(self.last_ms.load(Ordering::SeqCst)))
    }
    fn set_phase(&self, phase: Phase) {
        self.phase.store(phase as u8, Ordering::SeqCst);
    }
    fn evictable(&self) -> bool {
        self.phase.load(Ordering::SeqCst) == Phase::Head as u8
            || self.quiet_for() >= EVICTABLE_AFTER
    }
}

type Registry = Arc<Mutex<Vec<Arc<Activity>>>>;

/// Ends a relay's bookkeeping however it ends: the open count and the registry entry.
struct Slot {
    open: Arc<AtomicUsize>,
    registry: Registry,
    id: u64,
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.open.fetch_sub(1, Ordering::SeqCst);
        if let Ok(mut conns) = self.registry.lock() {
            conns.retain(|c| c.id != self.id);
        }
    }
}

fn accept_loop(
    listener: TcpListener,
    backend: PathBuf,
    limits: GuardLimits,
    stop: Arc<AtomicBool>,
    open: Arc<AtomicUsize>,
) {
    let limits = Arc::new(limits);
    let registry: Registry = Arc::default();
    let epoch = Instant::now();
    let mut next_id = 0u64;
    while !stop.load(Ordering::SeqCst) {
        let client = match listener.accept() {
            Ok((client, _)) => client,
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(20));
                continue;
            }
            Err(_) => continue,
        };
        let _ = client.set_nonblocking(false);
        if open.load(Ordering::SeqCst) >= limits.max_connections && !evict_quietest(&registry) {
            refuse(
                client,
                "503 Service Unavailable",
                "too many open connections",
            );
            continue;
        }
        let Ok(handle) = client.try_clone() else {
            continue;
        };
        next_id += 1;
        let activity = Arc::new(Activity {
            id: next_id,
            epoch,
            phase: AtomicU8::new(Phase::Head as u8),
            last_ms: AtomicU64::new(0),
            client: handle,
        });
        activity.touch();
        open.fetch_add(1, Ordering::SeqCst);
        if let Ok(mut conns) = registry.lock() {
            conns.push(activity.clone());
        }
        let slot = Slot {
            open: open.clone(),
            registry: registry.clone(),
            id: next_id,
        };
        let (limits, backend) = (limits.clone(), backend.clone());
        let spawned = std::thread::Builder::new()
            .name("gaitscope-guard-conn".into())
            .spawn(move || {
                let _slot = slot;
                relay(client, &backend, &limits, &activity);
            });
        // A thread that cannot start drops its closure, and with it the slot and the client.
        drop(spawned);
    }
}

/// Closes the evictable connection that has been quiet longest; false if none is.
fn evict_quietest(registry: &Registry) -> bool {
    let Ok(mut conns) = registry.lock() else {
        return false;
    };
    let victim = conns
        .iter()
        .enumerate()
        .filter(|(_, c)| c.evictable())
        .max_by_key(|(_, c)| c.quiet_for())
        .map(|(i, _)| i);
    match victim {
        Some(i) => {
            // Its relay sees the socket close and ends, dropping its slot; the newcomer takes
            // the place now (the count runs one over for that moment).
            let _ = conns[i].client.shutdown(Shutdown::Both);
            conns.remove(i);
            true
        }
        None => false,
    }
}

/// Answers `status` with a one-line body and closes.
fn refuse(mut client: TcpStream, status: &str, reason: &str) {
    let _ = client.set_write_timeout(Some(Duration::from_secs(1)));
    let body = format!("{{\"error\": \"{reason}\"}}\n");
    let _ = write!(
        client,
        "HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = client.shutdown(Shutdown::Both);
}

/// Why a request is not let through.
#[derive(Debug, PartialEq)]
enum Verdict {
    /// An HTTP/1 request, with its body's length.
    Pass {
        body: u64,
    },
    /// HTTP/2 prior knowledge: relayed blind from here on.
    Http2,
    Refuse(&'static str, String),
}

/// The value of header `name` in a request head, if it has one.
fn header<'a>(text: &'a str, name: &str) -> Option<&'a str> {
    text.split("\r\n")
        .skip(1)
        .filter_map(|line| line.split_once(':'))
        .find(|(n, _)| n.trim().eq_ignore_ascii_case(name))
        .map(|(_, value)| value.trim())
}

/// Checks a whole request head (through its blank line) or the HTTP/2 preface.
fn judge(head: &[u8], limits: &GuardLimits) -> Verdict {
    if head.starts_with(H2_PREFACE) {
        return Verdict::Http2;
    }
    let text = String::from_utf8_lossy(head);
    if header(&text, "transfer-encoding").is_some() {
        return Verdict::Refuse(
            "501 Not Implemented",
            "chunked request bodies are not accepted; send Content-Length".into(),
        );
    }
    let body = match header(&text, "content-length") {
        None => 0,
        Some(v) => match v.parse::<u64>() {
            Ok(n) if n <= limits.max_body_bytes => n,
            Ok(n) => {
                return Verdict::Refuse(
                    "413 Content Too Large",
                    format!(
                        "a request body of {n} bytes; at most {}",
                        limits.max_body_bytes
                    ),
                );
            }
            Err(_) => {
                return Verdict::Refuse("400 Bad Request", "an unreadable Content-Length".into());
            }
        },
    };
    if !limits.loopback_hosts_only {
        return Verdict::Pass { body };
    }
    let host = header(&text, "host").unwrap_or_default();
    if is_loopback_host(host) {
        Verdict::Pass { body }
    } else {
        Verdict::Refuse(
            "403 Forbidden",
            format!("this server is bound to loopback and answers only localhost, not '{host}'"),
        )
    }
}

/// Whether a `Host` header's value names this machine's loopback (any port).
pub fn is_loopback_host(host: &str) -> bool {
    let name = match host.strip_prefix('[') {
        Some(v6) => v6
            .split(']')
            .next()
            .map(|h| format!("[{h}]"))
            .unwrap_or_default(),
        None => host
            .split(':')
            .next()
            .unwrap_or_default()
            .to_ascii_lowercase(),
    };
    matches!(name.as_str(), "127.0.0.1" | "localhost" | "[::1]")
}

/// A request head as relayed: any [`GUARD_HEADER`] the client sent dropped, the session's
/// added after the request line.
fn stamped<'a>(head: &'a [u8], secret: Option<&str>) -> std::borrow::Cow<'a, [u8]> {
    let Some(secret) = secret else {
        return head.into();
    };
    let mut lines = head.split_inclusive(|&b| b == b'\n');
    let mut out = Vec::with_capacity(head.len() + 64);
    if let Some(request_line) = lines.next() {
        out.extend_from_slice(request_line);
    }
    out.extend_from_slice(format!("{GUARD_HEADER}: {secret}\r\n").as_bytes());
    for line in lines {
        let name = line.split(|&b| b == b':').next().unwrap_or_default();
        if !name
            .trim_ascii()
            .eq_ignore_ascii_case(GUARD_HEADER.as_bytes())
        {
            out.extend_from_slice(line);
        }
    }
    out.into()
}

fn header_end(buf: &[u8]) -> Option<usize> {
    buf.windows(4).position(|w| w == b"\r\n\r\n").map(|p| p + 4)
}

/// Why reading a request head stopped.
enum Head {
    /// A whole head (or the HTTP/2 preface) is at the front of the buffer; its length.
    Whole(usize),
    /// The connection closed, or stayed idle between requests: end quietly.
    Gone,
    /// Answer this and close.
    Refuse(&'static str, &'static str),
}

/// Reads the next request head into `buf` (which may already hold its start). The first byte
/// may take up to `first_byte` (while `server_quiet` says the other direction is quiet too);
/// from it, the head has `limits.header_timeout`.
fn read_head(
    client: &mut TcpStream,
    buf: &mut Vec<u8>,
    limits: &GuardLimits,
    first_byte: Duration,
    activity: &Activity,
) -> Head {
    let mut chunk = [0u8; 4096];
    let mut deadline = (!buf.is_empty()).then(|| Instant::now() + limits.header_timeout);
    let waiting_since = Instant::now();
    loop {
        if buf.starts_with(H2_PREFACE) {
            return Head::Whole(H2_PREFACE.len());
        }
        let h2_so_far =
            buf.len() < H2_PREFACE.len() && H2_PREFACE.starts_with(buf) && !buf.is_empty();
        // A head that arrived whole in one read is measured too, not only one still coming.
        let whole = header_end(buf).filter(|_| !h2_so_far);
        if buf.len().min(whole.unwrap_or(usize::MAX)) > limits.max_header_bytes {
            return Head::Refuse(
                "431 Request Header Fields Too Large",
                "request header too large",
            );
        }
        if let Some(end) = whole {
            return Head::Whole(end);
        }
        let wait = match deadline {
            Some(d) => match d.checked_duration_since(Instant::now()) {
                Some(left) if !left.is_zero() => left,
                _ => {
                    return Head::Refuse(
                        "408 Request Timeout",
                        "the request header came too slowly",
                    );
                }
            },
            None => {
                // Between requests: idle only while nothing moves the other way either.
                let quiet = activity.quiet_for().min(waiting_since.elapsed());
                match first_byte.checked_sub(quiet) {
                    Some(left) if !left.is_zero() => left,
                    _ => return Head::Gone,
                }
            }
        };
        let _ = client.set_read_timeout(Some(wait.min(Duration::from_millis(500))));
        match client.read(&mut chunk) {
            Ok(0) => return Head::Gone,
            Ok(n) => {
                activity.touch();
                activity.set_phase(Phase::Head);
                buf.extend_from_slice(&chunk[..n]);
                deadline.get_or_insert_with(|| Instant::now() + limits.header_timeout);
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return Head::Gone,
        }
    }
}

/// A stream socket the relay reads under a timeout: the client's TCP one, the server's Unix one.
trait Socket: Read + Write {
    fn read_timeout(&self, timeout: Option<Duration>);
}

impl Socket for TcpStream {
    fn read_timeout(&self, timeout: Option<Duration>) {
        let _ = self.set_read_timeout(timeout);
    }
}

impl Socket for UnixStream {
    fn read_timeout(&self, timeout: Option<Duration>) {
        let _ = self.set_read_timeout(timeout);
    }
}

/// Copies `from` to `to` until either closes, marking activity; `limit` bytes at most (then
/// returns true: the count was reached), or to the end (`None`).
fn pump(
    from: &mut impl Socket,
    to: &mut impl Write,
    limit: Option<u64>,
    activity: &Activity,
    idle: Duration,
) -> bool {
    let mut chunk = [0u8; 16 * 1024];
    let mut left = limit.unwrap_or(u64::MAX);
    from.read_timeout(limit.map(|_| idle));
    while left > 0 {
        let want = chunk.len().min(usize::try_from(left).unwrap_or(usize::MAX));
        match from.read(&mut chunk[..want]) {
            Ok(0) | Err(_) => return false,
            Ok(n) => {
                activity.touch();
                if to.write_all(&chunk[..n]).is_err() {
                    return false;
                }
                left -= n as u64;
            }
        }
    }
    true
}

fn relay(mut client: TcpStream, backend: &Path, limits: &GuardLimits, activity: &Activity) {
    let mut buf = Vec::with_capacity(1024);
    // The first request's head must arrive within the header timeout of the connection.
    let end = match read_head(
        &mut client,
        &mut buf,
        limits,
        limits.header_timeout,
        activity,
    ) {
        Head::Whole(end) => end,
        Head::Gone if buf.is_empty() => {
            return refuse(
                client,
                "408 Request Timeout",
                "the request header came too slowly",
            );
        }
        Head::Gone => return,
        Head::Refuse(status, reason) => return refuse(client, status, reason),
    };
    let body = match judge(&buf[..end], limits) {
        Verdict::Refuse(status, reason) => return refuse(client, status, &reason),
        Verdict::Http2 => None,
        Verdict::Pass { body } => Some(body),
    };
    let Ok(mut server) = UnixStream::connect(backend) else {
        return refuse(
            client,
            "502 Bad Gateway",
            "the server behind this port is not up",
        );
    };
    let _ = client.set_nodelay(true);
    activity.set_phase(Phase::Relaying);
    let (Ok(mut server_read), Ok(mut client_write)) = (server.try_clone(), client.try_clone())
    else {
        return;
    };
    // Server → client on a thread of its own (responses are not parsed); client → server here.
    // Either side closing ends both.
    let refusing = AtomicBool::new(false);
    std::thread::scope(|scope| {
        let back = std::thread::Builder::new()
            .name("gaitscope-guard-back".into())
            .spawn_scoped(scope, || {
                pump(
                    &mut server_read,
                    &mut client_write,
                    None,
                    activity,
                    limits.idle_timeout,
                );
                // A refusal still has to reach the client: the other side closes it then.
                if !refusing.load(Ordering::SeqCst) {
                    let _ = client_write.shutdown(Shutdown::Both);
                }
            });
        if back.is_err() {
            return;
        }
        let refusal = forward_requests(&mut client, &mut server, buf, end, body, limits, activity);
        refusing.store(refusal.is_some(), Ordering::SeqCst);
        let _ = server.shutdown(Shutdown::Both);
        if let Some((status, reason)) = refusal {
            // The response in flight (if any) ends with the server's side; then the refusal.
            if let Ok(back) = back {
                let _ = back.join();
            }
            refuse(client, status, &reason);
        } else {
            let _ = client.shutdown(Shutdown::Both);
        }
    });
}

/// Relays requests client → server: the first (its head `buf[..end]`, body `body` bytes, or the
/// rest of the connection blind for HTTP/2), then every later one judged as it arrives. Returns
/// the refusal that ended it, if one did.
fn forward_requests(
    client: &mut TcpStream,
    server: &mut UnixStream,
    mut buf: Vec<u8>,
    mut end: usize,
    mut body: Option<u64>,
    limits: &GuardLimits,
    activity: &Activity,
) -> Option<(&'static str, String)> {
    loop {
        let Some(body_len) = body else {
            // HTTP/2: the preface and whatever followed it, then blind.
            if server.write_all(&buf).is_err() {
                return None;
            }
            pump(client, server, None, activity, limits.idle_timeout);
            return None;
        };
        // The head, then as much of the body as already arrived with it.
        let in_buf = (buf.len() - end).min(usize::try_from(body_len).unwrap_or(usize::MAX));
        let head = stamped(&buf[..end], limits.secret.as_deref());
        if server.write_all(&head).is_err() || server.write_all(&buf[end..end + in_buf]).is_err() {
            return None;
        }
        buf.drain(..end + in_buf);
        let rest = body_len - in_buf as u64;
        if rest > 0 && !pump(client, server, Some(rest), activity, limits.idle_timeout) {
            return None;
        }
        activity.set_phase(Phase::Relaying);
        end = match read_head(client, &mut buf, limits, limits.idle_timeout, activity) {
            Head::Whole(end) => end,
            Head::Gone => return None,
            Head::Refuse(status, reason) => return Some((status, reason.to_string())),
        };
        body = match judge(&buf[..end], limits) {
            Verdict::Pass { body } => Some(body),
            Verdict::Http2 => {
                return Some(("400 Bad Request", "HTTP/2 preface inside HTTP/1".into()));
            }
            Verdict::Refuse(status, reason) => return Some((status, reason)),
        };
        activity.set_phase(Phase::Relaying);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> GuardLimits {
        GuardLimits {
            header_timeout: Duration::from_millis(300),
            max_connections: 3,
            ..GuardLimits::new(true)
        }
    }

    #[test]
    fn only_loopback_hosts_pass_on_loopback() {
        let l = limits();
        for host in ["127.0.0.1:9090", "localhost", "[::1]:9876", "LOCALHOST:1"] {
            // Header names and host names are case-insensitive.
            let head = format!("GET / HTTP/1.1\r\nhost: {host}\r\n\r\n");
            assert_eq!(
                judge(head.as_bytes(), &l),
                Verdict::Pass { body: 0 },
                "{host}"
            );
        }
        for head in [
            "GET / HTTP/1.1\r\nHost: evil.example:9090\r\n\r\n",
            "GET / HTTP/1.1\r\nHost: 127.0.0.1.evil.example\r\n\r\n",
            "GET / HTTP/1.1\r\n\r\n",
        ] {
            assert!(matches!(
                judge(head.as_bytes(), &l),
                Verdict::Refuse("403 Forbidden", _)
            ));
        }
        // HTTP/2 prior knowledge (no browser) passes; off loopback every Host does.
        assert_eq!(
            judge(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n", &l),
            Verdict::Http2
        );
        let open = GuardLimits::new(false);
        assert_eq!(
            judge(
                b"POST / HTTP/1.1\r\nHost: lab-box:9090\r\nContent-length: 12\r\n\r\n",
                &open
            ),
            Verdict::Pass { body: 12 }
        );
    }

    /// A backend that keeps connections alive and answers each request with "ok N", N the
    /// body's length as it arrived.
    fn echo_backend() -> (crate::files::PrivateDir, PathBuf) {
        let dir = crate::files::PrivateDir::create("gaitscope-test").unwrap();
        let path = dir.join("echo.sock");
        let listener = std::os::unix::net::UnixListener::bind(&path).unwrap();
        std::thread::spawn(move || {
            for mut conn in listener.incoming().flatten() {
                std::thread::spawn(move || {
                    let mut buf = Vec::new();
                    let mut chunk = [0u8; 4096];
                    loop {
                        while header_end(&buf).is_none() {
                            match conn.read(&mut chunk) {
                                Ok(0) | Err(_) => return,
                                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                            }
                        }
                        let end = header_end(&buf).unwrap();
                        let text = String::from_utf8_lossy(&buf[..end]).to_string();
                        let len: usize =
                            header(&text, "content-length").map_or(0, |v| v.parse().unwrap());
                        while buf.len() < end + len {
                            match conn.read(&mut chunk) {
                                Ok(0) | Err(_) => return,
                                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                            }
                        }
                        buf.drain(..end + len);
                        let mut body = format!("ok {len}");
                        for line in text.split("\r\n").skip(1) {
                            if let Some((name, value)) = line.split_once(':')
                                && name.eq_ignore_ascii_case(GUARD_HEADER)
                            {
                                body.push_str(&format!(" guard={}", value.trim()));
                            }
                        }
                        let reply = format!(
                            "HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n{body}",
                            body.len()
                        );
                        if conn.write_all(reply.as_bytes()).is_err() {
                            return;
                        }
                    }
                });
            }
        });
        (dir, path)
    }

    /// One response from a kept-alive connection: its status line and body.
    fn response(s: &mut TcpStream) -> (String, String) {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut buf = Vec::new();
        let mut byte = [0u8; 1];
        while header_end(&buf).is_none() {
            match s.read(&mut byte) {
                Ok(1) => buf.push(byte[0]),
                _ => return (String::from_utf8_lossy(&buf).to_string(), String::new()),
            }
        }
        let text = String::from_utf8_lossy(&buf).to_string();
        let len: usize = header(&text, "content-length").map_or(0, |v| v.parse().unwrap());
        let mut body = vec![0u8; len];
        s.read_exact(&mut body).unwrap();
        let status = text.lines().next().unwrap_or_default().to_string();
        (status, String::from_utf8_lossy(&body).to_string())
    }

    /// Whether the guard closed `s` (within 5 s), reading past anything it still sends.
    fn closed(s: &mut TcpStream) -> bool {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut sink = Vec::new();
        match s.read_to_end(&mut sink) {
            Ok(_) => true,
            // A reset is closed too; a timeout is not.
            Err(e) => !matches!(
                e.kind(),
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
            ),
        }
    }

    fn get(addr: SocketAddr, request: &[u8]) -> String {
        let mut s = TcpStream::connect(addr).unwrap();
        s.write_all(request).unwrap();
        let (status, body) = response(&mut s);
        format!("{status}\n{body}")
    }

    #[test]
    fn the_guard_relays_refuses_and_times_out() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let (_dir, backend) = echo_backend();
        let guard = Guard::spawn(listener, backend, limits(), "test").unwrap();
        let addr = guard.addr();
        let ok = get(addr, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
        assert!(
            ok.starts_with("HTTP/1.1 200") && ok.ends_with("ok 0"),
            "{ok}"
        );
        let evil = get(addr, b"GET / HTTP/1.1\r\nHost: evil.example\r\n\r\n");
        assert!(evil.starts_with("HTTP/1.1 403"), "{evil}");
        // A header line larger than the bound.
        let mut big = b"GET / HTTP/1.1\r\nX-Long: ".to_vec();
        big.extend(std::iter::repeat_n(b'a', 40_000));
        let mut s = TcpStream::connect(addr).unwrap();
        let _ = s.write_all(&big);
        let mut out = String::new();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = s.read_to_string(&mut out);
        assert!(out.starts_with("HTTP/1.1 431"), "{out}");
        // A whole head just over the bound, in one write (the red team's 17,408 bytes passed:
        // only a head still arriving was measured).
        let mut whole = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Long: ".to_vec();
        whole.extend(std::iter::repeat_n(b'a', 17_408));
        whole.extend(b"\r\n\r\n");
        let over = get(addr, &whole);
        assert!(over.starts_with("HTTP/1.1 431"), "{over}");
        // Exactly at the bound passes.
        let mut at = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Long: ".to_vec();
        let room = limits().max_header_bytes - at.len() - 4;
        at.extend(std::iter::repeat_n(b'a', room));
        at.extend(b"\r\n\r\n");
        assert_eq!(at.len(), limits().max_header_bytes);
        let ok = get(addr, &at);
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        // Slow headers fill the cap; a newcomer evicts the oldest of them (still sending its
        // head) instead of being refused; the others get 408 at the header timeout and their
        // slots free again.
        let mut slow: Vec<TcpStream> = (0..3)
            .map(|_| {
                let mut s = TcpStream::connect(addr).unwrap();
                s.write_all(b"GET / HTTP/1.1\r\n").unwrap();
                std::thread::sleep(Duration::from_millis(20));
                s
            })
            .collect();
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(guard.open_connections(), 3);
        let newcomer = get(addr, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
        assert!(newcomer.starts_with("HTTP/1.1 200"), "{newcomer}");
        let mut evicted = String::new();
        slow[0]
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        let _ = slow[0].read_to_string(&mut evicted);
        assert_eq!(
            evicted, "",
            "the oldest slow head was closed without an answer"
        );
        for s in &mut slow[1..] {
            let mut out = String::new();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            let _ = s.read_to_string(&mut out);
            assert!(out.starts_with("HTTP/1.1 408"), "{out}");
        }
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!(guard.open_connections(), 0);
        let again = get(addr, b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n");
        assert!(again.starts_with("HTTP/1.1 200"), "{again}");
    }

    /// Issue 49: the guard read only a connection's first request, so a kept-alive connection
    /// could follow a good request with any Host, size or body.
    #[test]
    fn every_request_on_a_kept_alive_connection_is_judged() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let (_dir, backend) = echo_backend();
        let guard = Guard::spawn(listener, backend, limits(), "test").unwrap();
        let mut s = TcpStream::connect(guard.addr()).unwrap();
        // Two requests in one write (the second's head arrives with the first), then a POST
        // whose body comes in two pieces: each reaches the server whole, and only once.
        s.write_all(
            b"GET /a HTTP/1.1\r\nHost: localhost\r\n\r\nGET /b HTTP/1.1\r\nHost: localhost\r\n\r\n",
        )
        .unwrap();
        assert_eq!(response(&mut s), ("HTTP/1.1 200 OK".into(), "ok 0".into()));
        assert_eq!(response(&mut s), ("HTTP/1.1 200 OK".into(), "ok 0".into()));
        s.write_all(b"POST /c HTTP/1.1\r\nHost: localhost\r\nContent-Length: 10\r\n\r\n01234")
            .unwrap();
        std::thread::sleep(Duration::from_millis(30));
        s.write_all(b"56789").unwrap();
        assert_eq!(response(&mut s), ("HTTP/1.1 200 OK".into(), "ok 10".into()));
        // Then a foreign Host on the same connection: refused, and the connection closed.
        s.write_all(b"GET / HTTP/1.1\r\nHost: evil.example\r\n\r\n")
            .unwrap();
        let (status, body) = response(&mut s);
        assert!(status.starts_with("HTTP/1.1 403"), "{status}");
        assert!(body.contains("evil.example"), "{body}");
        assert!(closed(&mut s));
        // Bodies: chunked ones and ones over the bound are refused before a byte is relayed.
        let chunked = get(
            guard.addr(),
            b"POST / HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n",
        );
        assert!(chunked.starts_with("HTTP/1.1 501"), "{chunked}");
        let huge = get(
            guard.addr(),
            b"POST / HTTP/1.1\r\nHost: localhost\r\nContent-Length: 99999999999\r\n\r\n",
        );
        assert!(huge.starts_with("HTTP/1.1 413"), "{huge}");
    }

    /// Issue 49: 64 kept-alive connections that sent one good request and went quiet, or 64
    /// that sent the first 14 bytes of HTTP/2's preface and stalled, held every slot forever.
    #[test]
    fn quiet_connections_are_closed_or_evicted_and_a_stalled_preface_times_out() {
        let (_dir, backend) = echo_backend();
        // Idle keep-alives close after the idle timeout.
        let short = GuardLimits {
            idle_timeout: Duration::from_millis(300),
            ..limits()
        };
        let guard = Guard::spawn(
            TcpListener::bind("127.0.0.1:0").unwrap(),
            backend.clone(),
            short,
            "t",
        )
        .unwrap();
        let mut idle: Vec<TcpStream> = (0..3)
            .map(|_| {
                let mut s = TcpStream::connect(guard.addr()).unwrap();
                s.write_all(b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n")
                    .unwrap();
                assert_eq!(response(&mut s).1, "ok 0");
                s
            })
            .collect();
        assert_eq!(guard.open_connections(), 3);
        // Busy a moment ago: not evictable yet, so a newcomer is refused.
        let full = get(guard.addr(), b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n");
        assert!(full.starts_with("HTTP/1.1 503"), "{full}");
        for s in &mut idle {
            assert!(
                closed(s),
                "an idle keep-alive is closed at the idle timeout"
            );
        }
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!(guard.open_connections(), 0);

        // With a long idle timeout, a connection quiet for a second is evicted for a newcomer.
        let guard = Guard::spawn(
            TcpListener::bind("127.0.0.1:0").unwrap(),
            backend,
            limits(),
            "t",
        )
        .unwrap();
        let mut held: Vec<TcpStream> = (0..3)
            .map(|_| {
                let mut s = TcpStream::connect(guard.addr()).unwrap();
                s.write_all(b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n")
                    .unwrap();
                assert_eq!(response(&mut s).1, "ok 0");
                s
            })
            .collect();
        std::thread::sleep(EVICTABLE_AFTER + Duration::from_millis(200));
        let newcomer = get(guard.addr(), b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n");
        assert!(newcomer.starts_with("HTTP/1.1 200"), "{newcomer}");
        assert!(
            closed(&mut held[0]),
            "the quietest held connection was evicted"
        );

        // A stalled HTTP/2 preface: 408 at the header timeout, like any slow head.
        let mut h2 = TcpStream::connect(guard.addr()).unwrap();
        h2.write_all(b"PRI * HTTP/2.0").unwrap();
        let mut out = String::new();
        h2.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = h2.read_to_string(&mut out);
        assert!(out.starts_with("HTTP/1.1 408"), "{out}");
    }

    /// Issue 49: the servers behind the guards answered whoever found their loopback ports.
    /// The guard now stamps every request with the session's secret (and drops a client's
    /// attempt at one), which the control server requires.
    #[test]
    fn the_guard_stamps_every_request_with_the_session_secret() {
        let stamping = GuardLimits {
            secret: Some("s3cret".into()),
            ..limits()
        };
        let (_dir, backend) = echo_backend();
        let guard = Guard::spawn(
            TcpListener::bind("127.0.0.1:0").unwrap(),
            backend,
            stamping,
            "t",
        )
        .unwrap();
        let mut s = TcpStream::connect(guard.addr()).unwrap();
        s.write_all(b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n")
            .unwrap();
        assert_eq!(response(&mut s).1, "ok 0 guard=s3cret");
        // A forged header, in any case, is dropped: the server sees the session's alone.
        s.write_all(b"POST / HTTP/1.1\r\nx-gaitscope-guard: forged\r\nHost: localhost\r\nContent-Length: 2\r\n\r\nhi")
            .unwrap();
        assert_eq!(response(&mut s).1, "ok 2 guard=s3cret");
        assert!(is_loopback_host("LocalHost:8080") && !is_loopback_host("localhost.evil"));
    }
}
