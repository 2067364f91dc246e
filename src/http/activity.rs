//! What one HTTP connection is doing, and when it has been quiet too long — the deadlines of a connection,
//! the same for HTTP/1 and HTTP/2:
//! - **header**: until its first request head is complete, a connection gets `header_read_timeout_ms` from
//!   the accept (a client that connects and sends nothing, or a partial request line, is closed then);
//! - **idle**: with no request in flight after its first one, `idle_timeout_ms` from the end of the last
//!   response (keep-alive connections left open);
//! - **send**: while a response is in flight, none — the request and upload timeouts bound handlers, and the
//!   upload progress rule bounds bodies — except that a connection whose writes have been blocked for
//!   `idle_timeout_ms` (a client that reads none of its response) is closed (nginx's `send_timeout`).
//!
//! The connection's service marks requests in flight ([`Activity::begin`], released when the response body
//! is dropped), its socket marks blocked writes ([`Watched`]), and its task races [`Activity::expired`]
//! against the connection.

use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::Notify;
use tokio::time::Instant;

/// The header and idle timeouts of a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Timeouts {
    pub header: Duration,
    pub idle: Duration,
}

/// Which deadline closed a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Expired {
    Header,
    Idle,
    Send,
}

impl Expired {
    pub fn label(self) -> &'static str {
        match self {
            Expired::Header => "header",
            Expired::Idle => "idle",
            Expired::Send => "send",
        }
    }
}

#[derive(Debug)]
struct State {
    in_flight: usize,
    requests: u64,
    idle_since: Instant,
    blocked_since: Option<Instant>,
}

/// The activity of one connection (shared by its socket, its service and its task).
#[derive(Debug)]
pub struct Activity {
    accepted: Instant,
    timeouts: Timeouts,
    state: Mutex<State>,
    changed: Notify,
}

/// A request in flight; dropping it (with the response body) ends it.
#[derive(Debug)]
pub struct Busy(Arc<Activity>);

impl Activity {
    pub fn new(timeouts: Timeouts) -> Arc<Self> {
        let now = Instant::now();
        Arc::new(Self {
            accepted: now,
            timeouts,
            state: Mutex::new(State {
                in_flight: 0,
                requests: 0,
                idle_since: now,
                blocked_since: None,
            }),
            changed: Notify::new(),
        })
    }

    fn state(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A request head arrived: no deadline but the send one until its response is dropped.
    pub fn begin(self: &Arc<Self>) -> Busy {
        {
            let mut s = self.state();
            s.in_flight += 1;
            s.requests += 1;
        }
        self.changed.notify_one();
        Busy(self.clone())
    }

    /// The deadline now and what it is for; `None` while requests are in flight and writes move.
    fn deadline(&self) -> Option<(Instant, Expired)> {
        let s = self.state();
        let t = self.timeouts;
        if let Some(at) = s.blocked_since {
            Some((at + t.idle, Expired::Send))
        } else if s.in_flight > 0 {
            None
        } else if s.requests == 0 {
            Some((self.accepted + t.header, Expired::Header))
        } else {
            Some((s.idle_since + t.idle, Expired::Idle))
        }
    }

    /// Completes when a deadline has passed (checked again after every change).
    pub async fn expired(&self) -> Expired {
        loop {
            let changed = self.changed.notified();
            tokio::pin!(changed);
            changed.as_mut().enable();
            match self.deadline() {
                None => changed.await,
                Some((at, why)) if at <= Instant::now() => return why,
                Some((at, _)) => {
                    tokio::select! {
                        () = changed => {}
                        () = tokio::time::sleep_until(at) => {}
                    }
                }
            }
        }
    }

    fn set_blocked(&self, blocked: bool) {
        self.state().blocked_since = blocked.then(Instant::now);
        if blocked {
            self.changed.notify_one();
        }
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        {
            let mut s = self.0.state();
            s.in_flight = s.in_flight.saturating_sub(1);
            s.idle_since = Instant::now();
        }
        self.0.changed.notify_one();
    }
}

/// A connection's socket that tells its [`Activity`] when writes block and when they move again.
pub struct Watched<T> {
    io: T,
    activity: Arc<Activity>,
    blocked: bool,
}

impl<T> Watched<T> {
    pub fn new(io: T, activity: Arc<Activity>) -> Self {
        Self {
            io,
            activity,
            blocked: false,
        }
    }

    fn note<R>(&mut self, r: &Poll<R>) {
        let blocked = r.is_pending();
        if blocked != self.blocked {
            self.blocked = blocked;
            self.activity.set_blocked(blocked);
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Watched<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Watched<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.io).poll_write(cx, buf);
        this.note(&r);
        r
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.io).poll_write_vectored(cx, bufs);
        this.note(&r);
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: Timeouts = Timeouts {
        header: Duration::from_millis(100),
        idle: Duration::from_millis(250),
    };

    fn within(took: Duration, expected: Duration) -> bool {
        took >= expected && took < expected + Duration::from_millis(200)
    }

    #[tokio::test]
    async fn a_connection_without_a_request_expires_at_the_header_timeout() {
        let a = Activity::new(T);
        let t0 = Instant::now();
        assert_eq!(a.expired().await, Expired::Header);
        assert!(within(t0.elapsed(), T.header), "{:?}", t0.elapsed());
    }

    #[tokio::test]
    async fn requests_in_flight_hold_it_open_and_idleness_after_them_expires_it() {
        let a = Activity::new(T);
        let busy = a.begin();
        let waited = tokio::time::timeout(T.idle * 2, a.expired()).await;
        assert!(waited.is_err(), "no deadline while a request is in flight");
        let t0 = Instant::now();
        drop(busy);
        assert_eq!(a.expired().await, Expired::Idle);
        assert!(within(t0.elapsed(), T.idle), "{:?}", t0.elapsed());
    }

    #[tokio::test]
    async fn a_write_blocked_for_the_idle_timeout_expires_a_busy_connection() {
        let a = Activity::new(T);
        let _busy = a.begin();
        a.set_blocked(true);
        tokio::time::sleep(T.idle / 2).await;
        a.set_blocked(false);
        let t0 = Instant::now();
        a.set_blocked(true);
        assert_eq!(a.expired().await, Expired::Send);
        assert!(
            within(t0.elapsed(), T.idle),
            "moving writes restart it: {:?}",
            t0.elapsed()
        );
    }
}
