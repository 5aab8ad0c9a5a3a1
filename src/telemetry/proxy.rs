//! Rerun's message proxy — the gRPC service a stock viewer reads a live stream from — served on
//! a Unix socket instead of a TCP port, and fed through it.
//!
//! Rerun's own server sink ([`rerun::grpc_server::GrpcServerSink`]) binds TCP only, so any local
//! process could reach it around the guard in front of `live --web`'s gRPC port (and gRPC's
//! HTTP/2 frames carry no header a relay could stamp with a secret). Here the same service
//! (`re_grpc_server::MessageProxy`, with Rerun's CORS rule and grpc-web layer, as Rerun serves
//! it) listens on a socket inside the session's private folder (mode 0700), so only this user's
//! processes — in practice the guard — can connect. The recording reaches it the way Rerun's
//! client sink sends to a proxy: one `WriteMessages` stream, over the same socket.

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
    Msg(Box<LogMsg>),
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
    /// Binds `socket` (its folder must exist and be private) and starts the proxy's thread.
    pub fn start(
        socket: &Path,
        options: re_grpc_server::ServerOptions,
        file: Option<rerun::sink::FileSink>,
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
                if let Err(why) = run(listener, &path, options, rx)
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
        // The URI only names the stream to tonic; the connector ignores it.
        let channel = tonic::transport::Endpoint::from_static("http://gaitscope.proxy")
            .connect_with_connector(connector)
            .await
            .map_err(|e| format!("cannot connect to the gRPC proxy: {e}"))?;
        let mut client = MessageProxyServiceClient::new(channel)
            .max_encoding_message_size(re_grpc_server::MAX_ENCODING_MESSAGE_SIZE);
        let messages = futures_util::stream::poll_fn(move |cx| {
            loop {
                match rx.poll_recv(cx) {
                    Poll::Ready(Some(Cmd::Msg(msg))) => match msg.to_transport(Compression::LZ4) {
                        Ok(msg) => {
                            return Poll::Ready(Some(WriteMessagesRequest {
                                log_msg: Some(msg.into()),
                            }));
                        }
                        // A message that cannot be encoded is dropped, as Rerun's own sinks do.
                        Err(_) => continue,
                    },
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
        if let Some(tx) = &self.tx {
            // Fails only once the proxy has stopped (its failure says why, at the next flush).
            let _ = tx.blocking_send(Cmd::Msg(Box::new(msg)));
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
        let sink = UnixProxySink::start(&socket, Default::default(), None).unwrap();
        sink.flush_blocking(Duration::from_secs(10)).unwrap();
        assert!(socket.exists());
        let thread_id = sink.thread.as_ref().map(|t| t.thread().id());
        assert!(thread_id.is_some());
        let started = std::time::Instant::now();
        drop(sink);
        // Drop joined the thread: bounded by the shutdown grace, not a hang.
        assert!(started.elapsed() < SHUTDOWN_GRACE + Duration::from_secs(5));
    }
}
