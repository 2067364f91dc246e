//! Admission of HTTP connections before anything is read from them: a cap on the connections open at once
//! and one per client address, each counted by an RAII [`Admitted`] ticket that the connection's task holds
//! (released when the task ends, however it ends: closed, timed out, cut, cancelled or panicked).
//!
//! A connection over a cap gets a canned `503 too_many_connections` problem, written with one non-blocking
//! `try_write` on the accept loop itself (nothing is spawned that a client could hold open), and is closed.
//! The global cap is clamped at start to half the process's open-file limit (the soft `RLIMIT_NOFILE`, read
//! from `/proc/self/limits`) less a reserve for the database, the results being written and the DICOM
//! node: a connection holds its socket and, while it uploads, a temporary file, so connections alone can
//! never make `accept` fail with "too many open files".

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::net::TcpStream;
use tokio::sync::Notify;

use crate::error_code::{ErrorCode, Problem};

/// Descriptors kept out of the connection cap: at least this many, or an eighth of the limit.
const FD_RESERVE_MIN: usize = 256;

/// The caps: connections at once, and per client address (0 = none per address).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Caps {
    pub max: usize,
    pub per_ip: usize,
}

impl Caps {
    /// `max` clamped to half of `open_files` (the soft limit of open descriptors, when known) less the
    /// reserve, and at least 1.
    pub fn clamped(max: usize, per_ip: usize, open_files: Option<u64>) -> Self {
        let max = match open_files {
            Some(limit) => {
                let limit = usize::try_from(limit).unwrap_or(usize::MAX);
                let room = limit.saturating_sub(FD_RESERVE_MIN.max(limit / 8)) / 2;
                max.min(room).max(1)
            }
            None => max.max(1),
        };
        Self { max, per_ip }
    }
}

/// The soft limit of open files of this process, from `/proc/self/limits` (`None` where it cannot be read or
/// is unlimited).
pub fn open_file_limit() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/limits").ok()?;
    parse_open_file_limit(&text)
}

fn parse_open_file_limit(limits: &str) -> Option<u64> {
    let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
    line["Max open files".len()..]
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Which cap refused a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Over {
    Total,
    Address,
}

impl Over {
    fn label(self) -> &'static str {
        match self {
            Over::Total => "total",
            Over::Address => "address",
        }
    }
}

#[derive(Default)]
struct Counts {
    open: usize,
    per_ip: HashMap<IpAddr, usize>,
}

/// The open connections, counted against the caps.
pub struct Admission {
    caps: Caps,
    counts: Mutex<Counts>,
    /// The number open, readable without the lock (metrics, the wait for the last one).
    open: AtomicUsize,
    closed: Notify,
    answers: [Vec<u8>; 2],
}

/// A connection counted against the caps; dropping it releases its place.
pub struct Admitted {
    admission: Arc<Admission>,
    ip: IpAddr,
}

impl Admission {
    pub fn new(caps: Caps) -> Arc<Self> {
        Arc::new(Self {
            caps,
            counts: Mutex::default(),
            open: AtomicUsize::new(0),
            closed: Notify::new(),
            answers: [
                answer("the server has too many open connections; try again shortly"),
                answer("this address has too many open connections; close some, then try again"),
            ],
        })
    }

    pub fn caps(&self) -> Caps {
        self.caps
    }

    fn counts(&self) -> MutexGuard<'_, Counts> {
        // A panic while the lock was held left the counts as they were: keep counting.
        self.counts.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Count a connection from `ip`, or say which cap it is over.
    pub fn admit(self: &Arc<Self>, ip: IpAddr) -> Result<Admitted, Over> {
        let ip = ip.to_canonical();
        let mut c = self.counts();
        if c.open >= self.caps.max {
            return Err(Over::Total);
        }
        let mine = c.per_ip.entry(ip).or_default();
        if self.caps.per_ip > 0 && *mine >= self.caps.per_ip {
            return Err(Over::Address);
        }
        *mine += 1;
        c.open += 1;
        self.open.store(c.open, Ordering::Release);
        metrics::gauge!(crate::telemetry::names::HTTP_CONNECTIONS).set(c.open as f64);
        Ok(Admitted {
            admission: self.clone(),
            ip,
        })
    }

    /// Connections open now.
    pub fn open(&self) -> usize {
        self.open.load(Ordering::Acquire)
    }

    /// Completes once no connection is open.
    pub async fn all_closed(&self) {
        loop {
            let closed = self.closed.notified();
            tokio::pin!(closed);
            closed.as_mut().enable();
            if self.open() == 0 {
                return;
            }
            closed.await;
        }
    }

    /// Answer a refused connection with the 503 problem and close it, without waiting for anything: what
    /// the client already sent is read once (so that closing does not reset the connection before the
    /// client reads the answer), the answer is written once (an empty socket buffer takes it whole).
    pub fn refuse(&self, stream: TcpStream, over: Over) {
        metrics::counter!(crate::telemetry::names::HTTP_CONNECTIONS_REFUSED, "cap" => over.label())
            .increment(1);
        let mut sink = [0u8; 4096];
        let _ = stream.try_read(&mut sink);
        let answer = match over {
            Over::Total => &self.answers[0],
            Over::Address => &self.answers[1],
        };
        let _ = stream.try_write(answer);
        // Dropped here: the descriptor is closed at once.
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let a = &self.admission;
        let mut c = a.counts();
        if let Some(n) = c.per_ip.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                c.per_ip.remove(&self.ip);
            }
        }
        c.open = c.open.saturating_sub(1);
        a.open.store(c.open, Ordering::Release);
        metrics::gauge!(crate::telemetry::names::HTTP_CONNECTIONS).set(c.open as f64);
        if c.open == 0 {
            a.closed.notify_waiters();
        }
    }
}

/// The bytes of a 503 `too_many_connections` response with `detail`, closing the connection.
fn answer(detail: &str) -> Vec<u8> {
    let body = serde_json::to_vec(&Problem::new(ErrorCode::TooManyConnections, detail))
        .unwrap_or_default();
    let mut out = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/problem+json\r\n\
         content-length: {}\r\nconnection: close\r\nretry-after: 1\r\n\r\n",
        body.len()
    )
    .into_bytes();
    out.extend_from_slice(&body);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: &str = "Limit                     Soft Limit           Hard Limit           Units\n\
        Max processes             63704                63704                processes\n\
        Max open files            20000                524288               files\n";

    #[test]
    fn the_soft_open_file_limit_is_read_and_the_cap_kept_below_it() {
        assert_eq!(parse_open_file_limit(LIMITS), Some(20_000));
        assert_eq!(
            parse_open_file_limit("Max open files  unlimited  unlimited  files"),
            None
        );
        assert_eq!(Caps::clamped(2048, 256, Some(20_000)).max, 2048);
        assert_eq!(Caps::clamped(2048, 256, Some(1024)).max, 384);
        assert_eq!(Caps::clamped(2048, 256, Some(4096)).max, 1792);
        assert_eq!(Caps::clamped(2048, 256, Some(65_536)).max, 2048);
        assert_eq!(Caps::clamped(2048, 256, Some(100)).max, 1);
        assert_eq!(Caps::clamped(2048, 256, None).max, 2048);
    }

    #[test]
    fn tickets_count_against_both_caps_and_release_their_place_when_dropped() {
        let a = Admission::new(Caps { max: 3, per_ip: 2 });
        let (x, y): (IpAddr, IpAddr) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let t1 = a.admit(x).unwrap();
        let t2 = a.admit(x).unwrap();
        assert_eq!(a.admit(x).err(), Some(Over::Address));
        let t3 = a.admit(y).unwrap();
        assert_eq!(a.admit(y).err(), Some(Over::Total));
        assert_eq!(a.open(), 3);
        drop(t1);
        assert!(
            a.admit(x).is_ok(),
            "a place of x is free again (the ticket dropped at once)"
        );
        drop((t2, t3));
        assert_eq!(a.open(), 0);
        assert!(a.counts().per_ip.is_empty(), "no address is remembered");
    }

    #[test]
    fn an_ipv4_mapped_address_counts_as_its_ipv4_address() {
        let a = Admission::new(Caps { max: 9, per_ip: 1 });
        let _t = a.admit("10.0.0.1".parse().unwrap()).unwrap();
        let mapped: IpAddr = "::ffff:10.0.0.1".parse().unwrap();
        assert_eq!(a.admit(mapped).err(), Some(Over::Address));
    }

    #[test]
    fn the_canned_answer_is_a_complete_problem_response() {
        let bytes = answer("busy");
        let text = String::from_utf8(bytes).unwrap();
        let (head, body) = text.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 503 "));
        assert!(head.contains(&format!("content-length: {}", body.len())));
        let v: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(
            (v["code"].as_str(), v["status"].as_u64()),
            (Some("too_many_connections"), Some(503))
        );
    }
}
