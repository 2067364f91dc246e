//! Admission of TCP callers before association negotiation, so that sockets that never negotiate can hold
//! neither association slots nor file descriptors.
//!
//! A connection is *pending* from `accept` until its whole A-ASSOCIATE-RQ has arrived; the request is read
//! with `peek` ([`read_opening`]), so its bytes stay on the socket for `dicom-ul`'s negotiation. Pending
//! connections hold no association slot: the node takes one only for a complete request whose calling AE may
//! call from the connection's address. They are bounded ([`Pending`]) per address and node-wide; a newcomer
//! over either cap closes the *oldest* pending connection of that address (or of the node) — a real caller
//! sends its request within milliseconds of connecting, so the oldest pending socket is the idlest — and a
//! pending connection is closed at the negotiation timeout. The listener accepts a connection only while
//! pending connections hold at most the node-wide cap of sockets ([`Pending::room`]).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::net::IpAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use dicom_ul::pdu::{
    AbortRQServiceProviderReason, AbortRQSource, AssociationRJ, AssociationRJResult,
    AssociationRJServiceProviderPresentationReason, AssociationRJSource, Pdu,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::{Notify, oneshot};

/// The longest A-ASSOCIATE-RQ the node reads (bytes, header included); a longer one is aborted unread.
/// DCMTK's `storescu` proposing 128 presentation contexts sends about 16 KiB.
pub const MAX_REQUEST_BYTES: usize = 64 << 10;

/// PDU header: type, reserved, 4-byte big-endian length.
const HEADER: usize = 6;
/// The fixed part of an A-ASSOCIATE-RQ after its header (PS3.8 §9.3.2): version, reserved, called AE,
/// calling AE, reserved.
const FIXED: usize = 2 + 2 + 16 + 16 + 32;

/// The connections waiting for their A-ASSOCIATE-RQ, by address, oldest first.
pub struct Pending {
    per_address: usize,
    total: usize,
    state: Mutex<State>,
    /// Told when a ticket is dropped (its connection's task ended or got its request).
    freed: Notify,
}

#[derive(Default)]
struct State {
    next: u64,
    /// Entry number → address and the sender that closes the connection.
    entries: BTreeMap<u64, (IpAddr, oneshot::Sender<()>)>,
    by_address: HashMap<IpAddr, BTreeSet<u64>>,
    /// Tickets not yet dropped: the entries, and connections closed for a newer one whose task has not yet
    /// ended (each still holds its socket).
    live: usize,
}

impl State {
    fn remove(&mut self, seq: u64) -> Option<oneshot::Sender<()>> {
        let (ip, close) = self.entries.remove(&seq)?;
        if let Some(set) = self.by_address.get_mut(&ip) {
            set.remove(&seq);
            if set.is_empty() {
                self.by_address.remove(&ip);
            }
        }
        Some(close)
    }
}

/// One pending connection's place; dropping it frees the place. `closed` fires when a newer connection took
/// the place.
pub struct Ticket {
    pending: Arc<Pending>,
    seq: u64,
    pub closed: oneshot::Receiver<()>,
}

impl Drop for Ticket {
    fn drop(&mut self) {
        let mut state = self.pending.lock();
        state.remove(self.seq);
        state.live = state.live.saturating_sub(1);
        drop(state);
        self.pending.freed.notify_one();
    }
}

impl Pending {
    /// At most `per_address` pending connections from one address and `total` from all (each at least 1).
    pub fn new(per_address: usize, total: usize) -> Self {
        Self {
            per_address: per_address.max(1),
            total: total.max(1),
            state: Mutex::new(State::default()),
            freed: Notify::new(),
        }
    }

    /// Wait until one more connection may be accepted: until at most `total` pending connections hold a
    /// socket, those closed for a newer one and not yet ended included. So pending connections never hold
    /// more than `total + 1` descriptors however fast they arrive (the listener's backlog holds the rest).
    pub async fn room(&self) {
        while self.lock().live > self.total {
            // `notify_one` keeps a wake-up given between the check and the wait.
            self.freed.notified().await;
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves the maps consistent (every change is one call).
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A place for a new connection from `ip`, closing the oldest pending connection of `ip` (or of the
    /// node) when it is over its cap; returns the ticket and how many connections were closed for it.
    pub fn enter(self: &Arc<Self>, ip: IpAddr) -> (Ticket, usize) {
        let ip = canonical(ip);
        let mut state = self.lock();
        let mut closed = 0;
        let oldest_here = state
            .by_address
            .get(&ip)
            .filter(|set| set.len() >= self.per_address)
            .and_then(|set| set.first().copied());
        if let Some(seq) = oldest_here {
            closed += close(state.remove(seq));
        }
        while state.entries.len() >= self.total {
            let Some(seq) = state.entries.keys().next().copied() else {
                break;
            };
            closed += close(state.remove(seq));
        }
        let seq = state.next;
        state.next += 1;
        let (tx, rx) = oneshot::channel();
        state.entries.insert(seq, (ip, tx));
        state.by_address.entry(ip).or_default().insert(seq);
        state.live += 1;
        let ticket = Ticket {
            pending: self.clone(),
            seq,
            closed: rx,
        };
        (ticket, closed)
    }

    /// Close the oldest pending connection, if any (to free a descriptor when the process ran out).
    pub fn close_oldest(&self) -> bool {
        let mut state = self.lock();
        let oldest = state.entries.keys().next().copied();
        oldest.is_some_and(|seq| close(state.remove(seq)) > 0)
    }

    /// Pending connections now: from all addresses, and from `ip`.
    pub fn count(&self, ip: IpAddr) -> (usize, usize) {
        let state = self.lock();
        let here = state.by_address.get(&canonical(ip)).map_or(0, |s| s.len());
        (state.entries.len(), here)
    }
}

fn close(sender: Option<oneshot::Sender<()>>) -> usize {
    match sender {
        Some(tx) => {
            // The connection's task may have ended already; then there is nothing to close.
            let _ = tx.send(());
            1
        }
        None => 0,
    }
}

/// An IPv4 address mapped into IPv6 counts as the IPv4 address.
pub fn canonical(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => v6
            .to_ipv4_mapped()
            .map(IpAddr::V4)
            .unwrap_or(IpAddr::V6(v6)),
        v4 => v4,
    }
}

/// What a caller sent first.
#[derive(Debug, PartialEq, Eq)]
pub enum Opening {
    /// A whole A-ASSOCIATE-RQ of `len` bytes (header included), still unread on the socket.
    Request {
        called: String,
        calling: String,
        len: usize,
    },
    /// Bytes that are no A-ASSOCIATE-RQ, or one longer than [`MAX_REQUEST_BYTES`]: to be aborted.
    NotARequest(&'static str),
    /// The caller closed the connection (or it failed) before a whole request.
    Closed,
}

/// Wait until `socket` holds a whole A-ASSOCIATE-RQ (or shows it will not), leaving every byte unread. The
/// caller bounds the wait; while a request arrives in pieces the socket is peeked again after pauses of 1 ms
/// doubling to 50 ms (a caller's request usually arrives in one segment, so this rarely runs).
pub async fn read_opening(socket: &TcpStream) -> Opening {
    let mut buf = vec![0u8; HEADER];
    let (mut seen, mut pause) = (0, Duration::from_millis(1));
    loop {
        let n = match socket.peek(&mut buf).await {
            Ok(0) | Err(_) => return Opening::Closed,
            Ok(n) => n,
        };
        if buf[0] != 0x01 {
            return Opening::NotARequest("not an A-ASSOCIATE-RQ");
        }
        if n == buf.len() {
            if buf.len() == HEADER {
                let len = u32::from_be_bytes([buf[2], buf[3], buf[4], buf[5]]) as usize;
                if len < FIXED {
                    return Opening::NotARequest("A-ASSOCIATE-RQ shorter than its fixed fields");
                }
                if len > MAX_REQUEST_BYTES - HEADER {
                    return Opening::NotARequest("A-ASSOCIATE-RQ over the longest the node reads");
                }
                buf.resize(HEADER + len, 0);
                continue;
            }
            return parse(&buf);
        }
        if n > seen {
            (seen, pause) = (n, Duration::from_millis(1));
        } else {
            pause = (pause * 2).min(Duration::from_millis(50));
        }
        tokio::time::sleep(pause).await;
    }
}

fn parse(bytes: &[u8]) -> Opening {
    match dicom_ul::pdu::read_pdu(bytes, dicom_ul::pdu::MAXIMUM_PDU_SIZE, false) {
        Ok(Some(Pdu::AssociationRQ(rq))) => Opening::Request {
            called: rq.called_ae_title,
            calling: rq.calling_ae_title,
            len: bytes.len(),
        },
        _ => Opening::NotARequest("malformed A-ASSOCIATE-RQ"),
    }
}

/// The A-ASSOCIATE-RJ of a known caller over the association cap: transient, service provider
/// (presentation), local limit exceeded.
pub fn busy_pdu() -> Vec<u8> {
    encode(&Pdu::AssociationRJ(AssociationRJ {
        result: AssociationRJResult::Transient,
        source: AssociationRJSource::ServiceProviderPresentation(
            AssociationRJServiceProviderPresentationReason::LocalLimitExceeded,
        ),
    }))
}

fn encode(pdu: &Pdu) -> Vec<u8> {
    let mut buf = Vec::new();
    // Writing these fixed PDUs into memory cannot fail; an empty answer would only close the connection.
    let _ = dicom_ul::pdu::write_pdu(&mut buf, pdu);
    buf
}

/// Answer a whole request of `len` bytes with `answer` and close: the request is consumed first, so that
/// the close is orderly (a socket closed with unread bytes sends a reset, which may overtake the answer).
pub async fn answer_request(mut socket: TcpStream, len: usize, answer: &[u8]) {
    let mut sink = vec![0u8; len];
    let _ = tokio::time::timeout(Duration::from_secs(1), socket.read_exact(&mut sink)).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), async {
        socket.write_all(answer).await?;
        socket.shutdown().await
    })
    .await;
}

/// Answer bytes that are no A-ASSOCIATE-RQ with an A-ABORT (service provider, unrecognised PDU) and close.
pub async fn abort(mut socket: TcpStream) {
    let pdu = encode(&Pdu::AbortRQ {
        source: AbortRQSource::ServiceProvider(AbortRQServiceProviderReason::UnrecognizedPdu),
    });
    let _ = tokio::time::timeout(Duration::from_secs(1), socket.write_all(&pdu)).await;
}

/// A log line at most once per period for an event a remote host can repeat at will.
pub struct Throttle {
    period: Duration,
    state: Mutex<(Option<Instant>, u64)>,
}

impl Throttle {
    pub const fn new(period: Duration) -> Self {
        Self {
            period,
            state: Mutex::new((None, 0)),
        }
    }

    /// Count one event; `Some(n)` when a line is due, `n` the events since the last line (this one included).
    pub fn tick(&self) -> Option<u64> {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.1 += 1;
        let now = Instant::now();
        if s.0
            .is_some_and(|last| now.duration_since(last) < self.period)
        {
            return None;
        }
        let n = s.1;
        *s = (Some(now), 0);
        Some(n)
    }
}

#[cfg(test)]
mod tests;
