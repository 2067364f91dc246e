//! The HTTP server loop: accept, admit, serve each connection on a task of its own (HTTP/1.1, and HTTP/2
//! with prior knowledge where the build has it), and shut down gracefully.
//!
//! Before anything is read, a connection is counted against the caps ([`connections`]: over a cap it gets a
//! canned 503 and is closed); its task then serves it through hyper until it ends, until one of its
//! deadlines passes ([`activity`]: header, idle, send) or until the drain cuts it ([`drain`]). An accept
//! error never ends the loop: errors of one connection are skipped, errors of the process (out of
//! descriptors, buffers or memory) are logged at most once a second and retried after a short pause, so the
//! loop serves again as soon as descriptors are free.
//!
//! At the shutdown signal the listener is closed, idle connections close, open requests finish and the
//! serve future completes when the last connection has closed (bounded by the drain in
//! [`super::Application::run_until`]).
//!
//! [`connections`]: super::connections
//! [`activity`]: super::activity
//! [`drain`]: super::drain

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::Router;
use axum::body::{Body, Bytes};
use hyper::body::{Body as HttpBody, Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;
use tower::ServiceExt;

use super::activity::{Activity, Busy, Timeouts, Watched};
use super::connections::{Admission, Admitted, Caps, open_file_limit};
use super::drain::Cuttable;
use crate::config::Settings;
use crate::telemetry::names;

/// The pause after an accept error of the process (descriptors, buffers, memory) before the next accept.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(20);

/// The most one warning a second says about accept errors or refused connections.
const LOG_EVERY: Duration = Duration::from_secs(1);

/// How connections are admitted and timed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Options {
    pub caps: Caps,
    pub timeouts: Timeouts,
}

impl Options {
    /// From the settings, the global cap clamped below this process's open-file limit.
    pub fn from_settings(s: &Settings) -> Self {
        let open_files = open_file_limit();
        let caps = Caps::clamped(s.max_connections, s.max_connections_per_ip, open_files);
        if caps.max < s.max_connections {
            tracing::warn!(
                max_connections = s.max_connections,
                open_files,
                used = caps.max,
                "max_connections lowered below the open-file limit (raise `ulimit -n` for more)"
            );
        }
        Self {
            caps,
            timeouts: Timeouts {
                header: Duration::from_millis(s.header_read_timeout_ms),
                idle: Duration::from_millis(s.idle_timeout_ms),
            },
        }
    }
}

/// What every connection task shares.
struct Shared {
    router: Router,
    builder: auto::Builder<TokioExecutor>,
    timeouts: Timeouts,
    /// Cancelled at the shutdown signal: connections finish what is open and close.
    graceful: CancellationToken,
    /// Cancelled at the drain deadline: every read and write fails.
    cut: CancellationToken,
}

/// Serve `router` on `listener` until `signal` completes and every connection has closed.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    options: Options,
    cut: CancellationToken,
    signal: impl Future<Output = ()> + Send,
) -> io::Result<()> {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    // The deadlines are the connection task's (`activity`), the same for both protocols.
    builder.http1().header_read_timeout(None);
    builder.http2().enable_connect_protocol();
    let shared = Arc::new(Shared {
        router,
        builder,
        timeouts: options.timeouts,
        graceful: CancellationToken::new(),
        cut,
    });
    let admission = Admission::new(options.caps);
    tracing::info!(
        max_connections = options.caps.max,
        max_connections_per_ip = options.caps.per_ip,
        header_read_timeout_ms = options.timeouts.header.as_millis() as u64,
        idle_timeout_ms = options.timeouts.idle.as_millis() as u64,
        "accepting connections"
    );
    let mut signal = std::pin::pin!(signal);
    let mut errors = Throttled::default();
    let mut refusals = Throttled::default();
    loop {
        let accepted = tokio::select! {
            biased;
            () = &mut signal => break,
            a = listener.accept() => a,
        };
        match accepted {
            Ok((stream, peer)) => match admission.admit(peer.ip()) {
                Ok(ticket) => spawn_connection(stream, peer, ticket, &shared),
                Err(over) => {
                    refusals.warn(|suppressed| {
                        tracing::warn!(%peer, cap = ?over, suppressed, open = admission.open(),
                            "connection refused: too many open connections")
                    });
                    admission.refuse(stream, over);
                }
            },
            Err(e) if of_one_connection(&e) => {}
            Err(e) => {
                errors.warn(|suppressed| {
                    tracing::warn!(error = %e, suppressed, open = admission.open(), "accept failed; retrying")
                });
                tokio::select! {
                    biased;
                    () = &mut signal => break,
                    () = tokio::time::sleep(ACCEPT_BACKOFF) => {}
                }
            }
        }
    }
    drop(listener);
    shared.graceful.cancel();
    admission.all_closed().await;
    Ok(())
}

/// An accept error that concerns only the connection being accepted (the loop goes on at once).
fn of_one_connection(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionRefused
            | io::ErrorKind::Interrupted
            | io::ErrorKind::WouldBlock
    )
}

/// A warning said at most once every [`LOG_EVERY`], with the number of those left unsaid since.
#[derive(Default)]
struct Throttled {
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttled {
    fn warn(&mut self, say: impl FnOnce(u64)) {
        if self.last.is_some_and(|t| t.elapsed() < LOG_EVERY) {
            self.suppressed += 1;
            return;
        }
        say(self.suppressed);
        self.last = Some(Instant::now());
        self.suppressed = 0;
    }
}

/// Serve one admitted connection on a task of its own, which holds its ticket until it ends.
fn spawn_connection(stream: TcpStream, peer: SocketAddr, ticket: Admitted, shared: &Arc<Shared>) {
    let shared = shared.clone();
    tokio::spawn(async move {
        let _ticket = ticket;
        let activity = Activity::new(shared.timeouts);
        let io = TokioIo::new(Watched::new(
            Cuttable::new(stream, shared.cut.clone()),
            activity.clone(),
        ));
        let (router, marks) = (shared.router.clone(), activity.clone());
        let service = hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
            let busy = marks.begin();
            let call = router.clone().oneshot(req.map(Body::new));
            async move {
                let response = call.await?;
                Ok::<_, std::convert::Infallible>(
                    response.map(|body| InFlight { body, _busy: busy }),
                )
            }
        });
        let conn = shared.builder.serve_connection_with_upgrades(io, service);
        tokio::pin!(conn);
        let mut draining = false;
        loop {
            tokio::select! {
                served = conn.as_mut() => {
                    if let Err(e) = served {
                        tracing::debug!(%peer, error = %e, "connection ended with an error");
                    }
                    break;
                }
                why = activity.expired() => {
                    metrics::counter!(names::HTTP_CONNECTIONS_TIMED_OUT, "timeout" => why.label()).increment(1);
                    tracing::debug!(%peer, timeout = why.label(), "connection closed by its timeout");
                    break;
                }
                () = shared.graceful.cancelled(), if !draining => {
                    draining = true;
                    conn.as_mut().graceful_shutdown();
                }
            }
        }
    });
}

/// A response body that keeps its request in flight until it is dropped.
struct InFlight {
    body: Body,
    _busy: Busy,
}

impl HttpBody for InFlight {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

/// Completes on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = term => {}
    }
}
