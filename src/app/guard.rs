//! The door in front of every port `live --web` serves: a TCP relay that caps connections,
//! times out slow request headers, bounds their size and — on loopback — answers only requests
//! that name a loopback host (no DNS rebinding), before a byte reaches the server behind it
//! (our control page, Rerun's web viewer, Rerun's gRPC stream; none of which does all of this
//! itself). Each server listens on an ephemeral loopback port; the guard owns the public one.
//!
//! A connection that opens with HTTP/2's prior-knowledge preface (a native gRPC client: no
//! browser speaks cleartext HTTP/2, so no rebinding page can) passes without a Host check.
//! Later requests on a kept-alive connection are not re-read: the first decides.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Duration;

/// Limits of one guarded port.
#[derive(Debug, Clone)]
pub struct GuardLimits {
    /// Open connections at most; more are answered 503 and closed.
    pub max_connections: usize,
    /// Time for a connection's first request header to arrive whole.
    pub header_timeout: Duration,
    /// Its size at most.
    pub max_header_bytes: usize,
    /// Answer only requests whose Host is localhost, 127.0.0.1 or `[::1]`.
    pub loopback_hosts_only: bool,
}

impl GuardLimits {
    pub fn new(loopback_hosts_only: bool) -> Self {
        Self {
            max_connections: 64,
            header_timeout: Duration::from_secs(5),
            max_header_bytes: 16 * 1024,
            loopback_hosts_only,
        }
    }
}

/// A running guard; dropping it stops accepting (open relays finish on their own).
pub struct Guard {
    stop: Arc<AtomicBool>,
    open: Arc<AtomicUsize>,
    addr: SocketAddr,
}

impl Guard {
    /// Relays connections accepted on `listener` to `backend` under `limits`.
    pub fn spawn(
        listener: TcpListener,
        backend: SocketAddr,
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

/// Decrements the open-connection count when a relay ends, however it ends.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

fn accept_loop(
    listener: TcpListener,
    backend: SocketAddr,
    limits: GuardLimits,
    stop: Arc<AtomicBool>,
    open: Arc<AtomicUsize>,
) {
    let limits = Arc::new(limits);
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
        if open.fetch_add(1, Ordering::SeqCst) >= limits.max_connections {
            open.fetch_sub(1, Ordering::SeqCst);
            refuse(
                client,
                "503 Service Unavailable",
                "too many open connections",
            );
            continue;
        }
        let slot = Slot(open.clone());
        let limits = limits.clone();
        let spawned = std::thread::Builder::new()
            .name("gaitscope-guard-conn".into())
            .spawn(move || {
                let _slot = slot;
                relay(client, backend, &limits);
            });
        // A thread that cannot start drops its closure, and with it the slot and the client.
        drop(spawned);
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

/// Why a connection's first request is not let through.
#[derive(Debug, PartialEq)]
enum Verdict {
    Pass,
    Refuse(&'static str, String),
}

/// Checks the head of a connection: `head` holds what has arrived (up to the end of the
/// header block, if it has).
fn judge(head: &[u8], limits: &GuardLimits) -> Verdict {
    if head.starts_with(b"PRI * HTTP/2.0") {
        return Verdict::Pass;
    }
    if !limits.loopback_hosts_only {
        return Verdict::Pass;
    }
    let text = String::from_utf8_lossy(head);
    let host = text
        .split("\r\n")
        .skip(1)
        .filter_map(|line| line.split_once(':'))
        .find(|(name, _)| name.trim().eq_ignore_ascii_case("host"))
        .map(|(_, value)| value.trim().to_string())
        .unwrap_or_default();
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
    if matches!(name.as_str(), "127.0.0.1" | "localhost" | "[::1]") {
        Verdict::Pass
    } else {
        Verdict::Refuse(
            "403 Forbidden",
            format!("this server is bound to loopback and answers only localhost, not '{host}'"),
        )
    }
}

fn header_end(buf: &[u8]) -> Option<usize> {
    buf.windows(4).position(|w| w == b"\r\n\r\n").map(|p| p + 4)
}

fn relay(mut client: TcpStream, backend: SocketAddr, limits: &GuardLimits) {
    let _ = client.set_read_timeout(Some(limits.header_timeout));
    let deadline = std::time::Instant::now() + limits.header_timeout;
    let mut head = Vec::with_capacity(1024);
    let mut chunk = [0u8; 4096];
    loop {
        if head.starts_with(b"PRI * HTTP/2.0") || header_end(&head).is_some() {
            break;
        }
        if head.len() > limits.max_header_bytes {
            refuse(
                client,
                "431 Request Header Fields Too Large",
                "request header too large",
            );
            return;
        }
        if std::time::Instant::now() >= deadline {
            refuse(
                client,
                "408 Request Timeout",
                "the request header came too slowly",
            );
            return;
        }
        match client.read(&mut chunk) {
            Ok(0) => return,
            Ok(n) => head.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                refuse(
                    client,
                    "408 Request Timeout",
                    "the request header came too slowly",
                );
                return;
            }
            Err(_) => return,
        }
    }
    if let Verdict::Refuse(status, reason) = judge(&head, limits) {
        refuse(client, status, &reason);
        return;
    }
    let Ok(mut server) = TcpStream::connect_timeout(&backend, Duration::from_secs(2)) else {
        refuse(
            client,
            "502 Bad Gateway",
            "the server behind this port is not up",
        );
        return;
    };
    let _ = client.set_read_timeout(None);
    let _ = server.set_nodelay(true);
    let _ = client.set_nodelay(true);
    if server.write_all(&head).is_err() {
        return;
    }
    let (Ok(mut server_read), Ok(mut client_write)) = (server.try_clone(), client.try_clone())
    else {
        return;
    };
    // Server → client on a thread of its own; client → server here. Either side closing ends
    // both.
    let back = std::thread::Builder::new()
        .name("gaitscope-guard-back".into())
        .spawn(move || {
            let _ = std::io::copy(&mut server_read, &mut client_write);
            let _ = client_write.shutdown(Shutdown::Both);
        });
    let _ = std::io::copy(&mut client, &mut server);
    let _ = server.shutdown(Shutdown::Both);
    if let Ok(back) = back {
        let _ = back.join();
    }
}

/// A free port on loopback for a server behind a guard (bound, read, released).
pub fn free_loopback_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind(("127.0.0.1", 0))?.local_addr()?.port())
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
            assert_eq!(judge(head.as_bytes(), &l), Verdict::Pass, "{host}");
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
            Verdict::Pass
        );
        let open = GuardLimits::new(false);
        assert_eq!(
            judge(b"GET / HTTP/1.1\r\nHost: lab-box:9090\r\n\r\n", &open),
            Verdict::Pass
        );
    }

    /// A backend that answers every request with "ok" (one connection at a time is enough).
    fn echo_backend() -> SocketAddr {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        std::thread::spawn(move || {
            for mut conn in listener.incoming().flatten() {
                std::thread::spawn(move || {
                    let mut buf = [0u8; 4096];
                    if conn.read(&mut buf).unwrap_or(0) > 0 {
                        let _ = conn.write_all(
                            b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nConnection: close\r\n\r\nok",
                        );
                    }
                });
            }
        });
        addr
    }

    fn get(addr: SocketAddr, request: &[u8]) -> String {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        s.write_all(request).unwrap();
        let mut out = String::new();
        let _ = s.read_to_string(&mut out);
        out
    }

    #[test]
    fn the_guard_relays_refuses_and_times_out() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let guard = Guard::spawn(listener, echo_backend(), limits(), "test").unwrap();
        let addr = guard.addr();
        let ok = get(addr, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
        assert!(ok.starts_with("HTTP/1.1 200") && ok.ends_with("ok"), "{ok}");
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
        // Slow headers: held connections fill the cap, the next is refused; after the header
        // timeout they are closed and the slots free again.
        let slow: Vec<TcpStream> = (0..3)
            .map(|_| {
                let mut s = TcpStream::connect(addr).unwrap();
                s.write_all(b"GET / HTTP/1.1\r\n").unwrap();
                s
            })
            .collect();
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!(guard.open_connections(), 3);
        let full = get(addr, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
        assert!(full.starts_with("HTTP/1.1 503"), "{full}");
        for mut s in slow {
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
}
