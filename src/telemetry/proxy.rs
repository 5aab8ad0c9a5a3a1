//! Rerun's message proxy — the gRPC service a stock viewer reads a live stream from — served on
//! a Unix socket instead of a TCP port, and fed through it.
//!
//! Rerun's own server sink ([`rerun::grpc_server::GrpcServerSink`]) binds TCP only, so any local
//! process could reach it around the guard in front of `live --web`'s gRPC port (and gRPC's
//! HTTP/2 frames carry no header a relay could stamp with a secret). Here the same service
//! (`re_grpc_server::MessageProxy`, with Rerun's CORS rule and grpc-web layer, as Rerun serves
//! it) listens on a socket inside the session's private folder (mode 0700), so only this user's
//! processes — in practice the guard — can connect. The recording reaches it the way Rerun's
//! client sink sends to a proxy: one `WriteMessages` stream, over the same socket. It checks
//! each request's host itself too (HTTP/1's `Host`, HTTP/2's `:authority`), as the guard does.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::thread::JoinHandle;
use std::time::Duration;

use rerun::external::re_grpc_server::{self, MessageProxy};
use rerun::external::re_log_encoding::{Compression, ToTransport as _};
use rerun::log::LogMsg;
use rerun::sink::{LogSink, SinkFlushError};

use re_protos::sdk_comms::v1alpha1::WriteMessagesRequest;
use re_protos::sdk_comms::v1alpha1::message_proxy_service_client::MessageProxyServiceClient;
use re_protos::sdk_comms::v1alpha1::message_proxy_service_server::MessageProxyServiceServer;
use tonic::codegen::http;

/// Messages queued for the proxy before `send` blocks (backpressure, as Rerun's sinks do).
const QUEUE: usize = 1024;

/// How long a dropped sink lets viewers finish reading before the server stops.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(1);

#[derive(Debug, thiserror::Error)]
pub enum ProxyError {
    #[error("cannot listen on the gRPC socket {path}")]
    Bind {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start the gRPC proxy's thread")]
    Thread(#[source] std::io::Error),
}

enum Cmd {
    /// A message, encoded on the sender's thread (not the runtime's, which serves the viewers).
    Msg(Box<WriteMessagesRequest>),
    /// Everything queued before it has been handed to the proxy connection.
    Flush(std::sync::mpsc::Sender<()>),
}

/// A [`LogSink`] that hosts Rerun's message proxy on a Unix socket (and optionally writes an
/// `.rrd` as well, first: a slow or absent viewer must not hold the file back).
pub struct UnixProxySink {
    tx: Option<tokio::sync::mpsc::Sender<Cmd>>,
    thread: Option<JoinHandle<()>>,
    file: Option<rerun::sink::FileSink>,
    /// Why the proxy stopped, once it has.
    failure: Arc<Mutex<Option<String>>>,
}

impl UnixProxySink {
    /// Binds `socket` (its folder must exist and be private) and starts the proxy's thread;
    /// requests whose host `admit` refuses are answered 403.
    pub fn start(
        socket: &Path,
        options: re_grpc_server::ServerOptions,
        file: Option<rerun::sink::FileSink>,
        admit: fn(&str) -> bool,
    ) -> Result<Self, ProxyError> {
        let bind_error = |source| ProxyError::Bind {
            path: socket.to_path_buf(),
            source,
        };
        // Bound here, so a bad path is the caller's error, not a log line from a thread.
        let listener = std::os::unix::net::UnixListener::bind(socket).map_err(bind_error)?;
        listener.set_nonblocking(true).map_err(bind_error)?;
        let (tx, rx) = tokio::sync::mpsc::channel(QUEUE);
        let failure = Arc::new(Mutex::new(None));
        let (path, failed) = (socket.to_path_buf(), failure.clone());
        let thread = std::thread::Builder::new()
            .name("gaitscope-grpc-proxy".into())
            .spawn(move || {
                if let Err(why) = run(listener, &path, options, admit, rx)
                    && let Ok(mut f) = failed.lock()
                {
                    *f = Some(why);
                }
            })
            .map_err(ProxyError::Thread)?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            file,
            failure,
        })
    }

    fn failure(&self) -> Option<String> {
        self.failure.lock().ok().and_then(|f| f.clone())
    }
}

/// The proxy's thread: the server on the socket, and the one connection that feeds it.
fn run(
    listener: std::os::unix::net::UnixListener,
    path: &Path,
    options: re_grpc_server::ServerOptions,
    admit: fn(&str) -> bool,
    mut rx: tokio::sync::mpsc::Receiver<Cmd>,
) -> Result<(), String> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the gRPC proxy's runtime: {e}"))?;
    runtime.block_on(async move {
        let listener = tokio::net::UnixListener::from_std(listener)
            .map_err(|e| format!("cannot listen on {}: {e}", path.display()))?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let cors = re_grpc_server::cors_layer(&options.cors_allowed_origins);
        let proxy = MessageProxyServiceServer::new(MessageProxy::new(options))
            .max_decoding_message_size(re_grpc_server::MAX_DECODING_MESSAGE_SIZE)
            .max_encoding_message_size(re_grpc_server::MAX_ENCODING_MESSAGE_SIZE);
        let server = tonic::transport::Server::builder()
            // grpc-web (the browser viewer) arrives as HTTP/1.1 through the guard.
            .accept_http1(true)
            .layer(HostCheckLayer(admit))
            .layer(cors)
            .layer(tonic_web::GrpcWebLayer::new())
            .add_service(proxy)
            .serve_with_incoming_shutdown(Incoming(listener), async {
                let _ = stopped.await;
            });
        let server = tokio::spawn(server);

        let socket = path.to_path_buf();
        let connector = tower::service_fn(move |_: tonic::transport::Uri| {
            let socket = socket.clone();
            async move {
                let stream = tokio::net::UnixStream::connect(socket).await?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
            }
        });
        // The connector ignores the URI; its host is what the host check reads.
        let channel = tonic::transport::Endpoint::from_static("http://localhost")
            .connect_with_connector(connector)
            .await
            .map_err(|e| format!("cannot connect to the gRPC proxy: {e}"))?;
        let mut client = MessageProxyServiceClient::new(channel)
            .max_encoding_message_size(re_grpc_server::MAX_ENCODING_MESSAGE_SIZE);
        let messages = futures_util::stream::poll_fn(move |cx| {
            loop {
                match rx.poll_recv(cx) {
                    Poll::Ready(Some(Cmd::Msg(request))) => return Poll::Ready(Some(*request)),
                    Poll::Ready(Some(Cmd::Flush(done))) => {
                        let _ = done.send(());
                    }
                    Poll::Ready(None) => return Poll::Ready(None),
                    Poll::Pending => return Poll::Pending,
                }
            }
        });
        // Ends when the sink is dropped (its sender with it).
        let written = client.write_messages(messages).await;
        let _ = stop.send(());
        // Viewers still reading get a moment; then the runtime ends, closing what is left.
        let _ = tokio::time::timeout(SHUTDOWN_GRACE, server).await;
        written
            .map(|_| ())
            .map_err(|e| format!("the gRPC proxy stopped taking the stream: {e}"))
    })
}

/// Answers 403 to a request whose host — HTTP/1's `Host` header, else HTTP/2's `:authority` —
/// is missing or refused by the check, before it reaches the proxy.
#[derive(Clone, Copy)]
struct HostCheckLayer(fn(&str) -> bool);

impl<S> tower::Layer<S> for HostCheckLayer {
    type Service = HostCheck<S>;

    fn layer(&self, inner: S) -> HostCheck<S> {
        HostCheck {
            inner,
            admit: self.0,
        }
    }
}

#[derive(Clone)]
struct HostCheck<S> {
    inner: S,
    admit: fn(&str) -> bool,
}

impl<S, B, R> tower::Service<http::Request<B>> for HostCheck<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    R: Default + Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Self::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let host = match request.headers().get(http::header::HOST) {
            Some(value) => value.to_str().ok().map(str::to_owned),
            None => request.uri().authority().map(|a| a.as_str().to_owned()),
        };
        if host.as_deref().is_some_and(self.admit) {
            return Box::pin(self.inner.call(request));
        }
        let mut refused = http::Response::new(R::default());
        *refused.status_mut() = http::StatusCode::FORBIDDEN;
        Box::pin(std::future::ready(Ok(refused)))
    }
}

/// A Unix listener's connections, as tonic's server takes them.
struct Incoming(tokio::net::UnixListener);

impl futures_util::Stream for Incoming {
    type Item = std::io::Result<tokio::net::UnixStream>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.0
            .poll_accept(cx)
            .map(|accepted| Some(accepted.map(|(stream, _)| stream)))
    }
}

impl LogSink for UnixProxySink {
    fn send(&self, msg: LogMsg) {
        if let Some(file) = &self.file {
            LogSink::send(file, msg.clone());
        }
        // A message that cannot be encoded is dropped, as Rerun's own sinks do.
        if let (Some(tx), Ok(encoded)) = (&self.tx, msg.to_transport(Compression::LZ4)) {
            let request = WriteMessagesRequest {
                log_msg: Some(encoded.into()),
            };
            // Fails only once the proxy has stopped (its failure says why, at the next flush).
            let _ = tx.blocking_send(Cmd::Msg(Box::new(request)));
        }
    }

    fn flush_blocking(&self, timeout: Duration) -> Result<(), SinkFlushError> {
        if let Some(file) = &self.file {
            LogSink::flush_blocking(file, timeout)?;
        }
        let stopped = || {
            SinkFlushError::failed(
                self.failure()
                    .unwrap_or_else(|| "the gRPC proxy stopped".into()),
            )
        };
        let Some(tx) = &self.tx else {
            return Err(stopped());
        };
        let (done, flushed) = std::sync::mpsc::channel();
        if tx.blocking_send(Cmd::Flush(done)).is_err() {
            return Err(stopped());
        }
        match flushed.recv_timeout(timeout) {
            Ok(()) => Ok(()),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => Err(SinkFlushError::Timeout),
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => Err(stopped()),
        }
    }

    fn default_batcher_config(&self) -> rerun::log::ChunkBatcherConfig {
        rerun::log::ChunkBatcherConfig::LOW_LATENCY
    }
}

impl Drop for UnixProxySink {
    fn drop(&mut self) {
        // Closing the queue ends the stream, then the server (after its grace), then the thread.
        self.tx = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_socket_that_cannot_be_bound_is_a_clear_error() {
        let err = UnixProxySink::start(
            Path::new("/nonexistent/gaitscope/grpc.sock"),
            Default::default(),
            None,
            |_| true,
        )
        .err()
        .expect("no such folder");
        assert!(
            err.to_string().contains("/nonexistent/gaitscope/grpc.sock"),
            "{err}"
        );
        assert!(std::error::Error::source(&err).is_some());
    }

    /// The proxy comes up on its socket, takes a flush, and its thread ends when it is dropped
    /// (no viewer attached): nothing outlives the session.
    #[test]
    fn the_proxy_flushes_and_ends_with_its_sink() {
        let dir = crate::files::PrivateDir::create("gaitscope-test").unwrap();
        let socket = dir.join("grpc.sock");
        let sink = UnixProxySink::start(&socket, Default::default(), None, |host| {
            host.starts_with("localhost")
        })
        .unwrap();
        sink.flush_blocking(Duration::from_secs(10)).unwrap();
        assert!(socket.exists());
        // The proxy checks the host itself: a foreign one is refused before the service, a
        // loopback one reaches it (grpc-web's answer to an empty request is not a 403).
        let ask = |host: &str| {
            use std::io::{Read, Write};
            let mut s = std::os::unix::net::UnixStream::connect(&socket).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            let request = format!(
                "POST /rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages HTTP/1.1\r\n\
                 Host: {host}\r\nContent-Type: application/grpc-web+proto\r\n\
                 Content-Length: 0\r\nConnection: close\r\n\r\n"
            );
            s.write_all(request.as_bytes()).unwrap();
            let mut head = [0u8; 12];
            s.read_exact(&mut head).unwrap();
            String::from_utf8_lossy(&head).into_owned()
        };
        assert_eq!(ask("evil.example"), "HTTP/1.1 403");
        assert_eq!(ask("localhost:9876"), "HTTP/1.1 200");
        let thread_id = sink.thread.as_ref().map(|t| t.thread().id());
        assert!(thread_id.is_some());
        let started = std::time::Instant::now();
        drop(sink);
        // Drop joined the thread: bounded by the shutdown grace, not a hang.
        assert!(started.elapsed() < SHUTDOWN_GRACE + Duration::from_secs(5));
    }
}
