//! Rerun's web viewer (its page, script and wasm) served by us, on a Unix socket behind the
//! viewer port's guard. Rerun's own `WebViewerServer` answers any local process that finds its
//! port; this server listens where only the guard can reach it, answers only requests the guard
//! stamped with the session's secret ([`super::guard::GUARD_HEADER`]), and checks Host itself
//! too. The files are Rerun's
//! (`re_web_viewer_server::WebViewerData`), served by the paths and media types Rerun uses.

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;

use re_web_viewer_server::WebViewerData;

use super::guard::{GUARD_HEADER, is_loopback_host};
use super::web::{WebError, header};

/// The running asset server; dropping it ends its thread.
pub struct ViewerAssets {
    server: Arc<tiny_http::Server>,
    shutdown: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

/// Who may be answered.
#[derive(Debug, Clone)]
struct Admission {
    secret: String,
    loopback_hosts_only: bool,
}

impl ViewerAssets {
    /// Serves the viewer on the Unix socket `socket` (behind the guard).
    pub fn start(
        socket: &Path,
        secret: String,
        loopback_hosts_only: bool,
    ) -> Result<Self, WebError> {
        let data = WebViewerData::load(None).map_err(|e| WebError::Viewer(e.into()))?;
        let server = tiny_http::Server::http_unix(socket).map_err(|reason| WebError::Socket {
            what: "web viewer",
            path: socket.to_path_buf(),
            reason,
        })?;
        let server = Arc::new(server);
        let shutdown = Arc::new(AtomicBool::new(false));
        let admission = Admission {
            secret,
            loopback_hosts_only,
        };
        let (srv, stop) = (server.clone(), shutdown.clone());
        let thread = std::thread::Builder::new()
            .name("gaitscope-viewer-assets".into())
            .spawn(move || serve(&srv, &stop, &data, &admission))
            .map_err(|e| WebError::Viewer(e.into()))?;
        Ok(Self {
            server,
            shutdown,
            thread: Some(thread),
        })
    }
}

impl Drop for ViewerAssets {
    fn drop(&mut self) {
        self.shutdown.store(true, Ordering::Release);
        self.server.unblock();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn serve(
    server: &tiny_http::Server,
    shutdown: &AtomicBool,
    data: &WebViewerData,
    admission: &Admission,
) {
    loop {
        let request = server.recv();
        if shutdown.load(Ordering::Acquire) {
            return;
        }
        // An accept that failed is that connection's loss, not the server's.
        if let Ok(request) = request {
            answer(request, data, admission);
        }
    }
}

fn answer(request: tiny_http::Request, data: &WebViewerData, admission: &Admission) {
    let get = |name: &str| {
        request
            .headers()
            .iter()
            .find(|h| h.field.as_str().as_str().eq_ignore_ascii_case(name))
            .map(|h| h.value.as_str().to_string())
    };
    let verdict = admit(
        get(GUARD_HEADER).as_deref(),
        get("Host").as_deref(),
        admission,
    )
    .and_then(|()| {
        if *request.method() == tiny_http::Method::Get
            || *request.method() == tiny_http::Method::Head
        {
            Ok(())
        } else {
            Err((
                405,
                "the web viewer's files are only read (GET)".to_string(),
            ))
        }
    });
    let response = match verdict.and_then(|()| {
        let path = request.url().split('?').next().unwrap_or("/");
        asset(data, path).ok_or((404, format!("no file {path} in the web viewer")))
    }) {
        Ok((mime, bytes)) => tiny_http::Response::from_data(bytes)
            .with_header(header("Content-Type", mime))
            // Sent chunked (tiny_http does above a size), so the length travels in the
            // header Rerun's index.html reads for its progress bar, as Rerun's server does.
            .with_header(header("rerun-final-length", &bytes.len().to_string())),
        Err((status, reason)) => tiny_http::Response::from_data(reason.into_bytes())
            .with_status_code(status)
            .with_header(header("Content-Type", "text/plain; charset=utf-8")),
    };
    let _ = request.respond(response);
}

/// Whether a request that reached the socket may be answered: only through the guard
/// (its secret), and on a loopback server only for a loopback Host (no DNS rebinding).
fn admit(
    stamp: Option<&str>,
    host: Option<&str>,
    admission: &Admission,
) -> Result<(), (u16, String)> {
    if stamp != Some(admission.secret.as_str()) {
        return Err((
            403,
            "this port is served through the web viewer's public port only".into(),
        ));
    }
    let host = host.unwrap_or_default();
    if admission.loopback_hosts_only && !is_loopback_host(host) {
        return Err((
            403,
            format!("this server is bound to loopback and answers only localhost, not '{host}'"),
        ));
    }
    Ok(())
}

/// The file at `path` and its media type: Rerun's paths (`re_web_viewer_server`).
fn asset<'a>(data: &'a WebViewerData, path: &str) -> Option<(&'static str, &'a [u8])> {
    Some(match path {
        "/" | "/index.html" => ("text/html", data.index_html()),
        "/favicon.ico" => ("image/x-icon", data.favicon()),
        "/apple-touch-icon.png" => ("image/png", data.apple_touch_icon()),
        "/sw.js" => ("text/javascript", data.sw_js()),
        "/re_viewer.js" => ("text/javascript", data.viewer_js()),
        "/re_viewer_bg.wasm" => ("application/wasm", data.viewer_wasm()),
        "/signed-in" => ("text/html", data.signed_in_html()),
        "/signed-out" => ("text/html", data.signed_out_html()),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    fn get(socket: &Path, head: &str) -> String {
        let mut s = std::os::unix::net::UnixStream::connect(socket).unwrap();
        s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .unwrap();
        s.write_all(head.as_bytes()).unwrap();
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out);
        String::from_utf8_lossy(&out).into_owned()
    }

    #[test]
    fn only_stamped_loopback_requests_get_the_viewer() {
        let dir = crate::files::PrivateDir::create("gaitscope-test").unwrap();
        let socket = dir.join("viewer.sock");
        let assets = ViewerAssets::start(&socket, "s3cret".into(), true).unwrap();
        let index = WebViewerData::load(None).unwrap().index_html().len();
        let ok = get(
            &socket,
            "GET /index.html HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Gaitscope-Guard: s3cret\r\nConnection: close\r\n\r\n",
        );
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        assert!(ok.contains("text/html"), "{ok}");
        assert!(ok.contains(&format!("rerun-final-length: {index}")), "{ok}");
        // Refused: without the guard's secret (or with a guessed one); a foreign Host; a path
        // Rerun does not serve; anything but a read.
        for (request, status, says) in [
            (
                "GET /index.html HTTP/1.1\r\nHost: 127.0.0.1\r\n",
                "403",
                "public port only",
            ),
            (
                "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Gaitscope-Guard: guess\r\n",
                "403",
                "",
            ),
            (
                "GET / HTTP/1.1\r\nHost: evil.example\r\nX-Gaitscope-Guard: s3cret\r\n",
                "403",
                "evil.example",
            ),
            (
                "GET /etc/passwd HTTP/1.1\r\nHost: localhost\r\nX-Gaitscope-Guard: s3cret\r\n",
                "404",
                "",
            ),
            (
                "POST / HTTP/1.1\r\nHost: localhost\r\nX-Gaitscope-Guard: s3cret\r\nContent-Length: 0\r\n",
                "405",
                "",
            ),
        ] {
            let answer = get(&socket, &format!("{request}Connection: close\r\n\r\n"));
            assert!(
                answer.starts_with(&format!("HTTP/1.1 {status}")),
                "{answer}"
            );
            assert!(answer.contains(says), "{answer}");
        }
        // Dropping it ends its thread (joined in drop); its folder goes with the PrivateDir.
        drop(assets);
        drop(dir);
        assert!(!socket.exists());
    }

    #[test]
    fn every_path_rerun_serves_is_served() {
        let data = WebViewerData::load(None).unwrap();
        for (path, mime) in [
            ("/", "text/html"),
            ("/re_viewer.js", "text/javascript"),
            ("/re_viewer_bg.wasm", "application/wasm"),
            ("/sw.js", "text/javascript"),
            ("/favicon.ico", "image/x-icon"),
        ] {
            let (m, bytes) = asset(&data, path).unwrap();
            assert_eq!(m, mime);
            assert!(!bytes.is_empty());
        }
        // The wasm is the module itself (its magic number), not a placeholder.
        assert_eq!(
            &asset(&data, "/re_viewer_bg.wasm").unwrap().1[..4],
            b"\0asm"
        );
        assert!(asset(&data, "/../Cargo.toml").is_none());
    }
}
