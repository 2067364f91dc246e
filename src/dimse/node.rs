//! The listener: accepts TCP connections, admits them ([`admission`]: a connection holds an association
//! slot only once a caller on the allow-list sent its whole A-ASSOCIATE-RQ; until then it is pending, capped
//! per address and node-wide, and closed at the negotiation timeout), negotiates associations (allow-list,
//! SOP classes and transfer syntaxes the reader decodes, PDU size, timeouts, a cap on concurrent
//! associations), serves each on its own task, and seals series whose stable age passed.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use dicom_ul::association::Association as _;
use dicom_ul::association::server::ServerAssociationOptions;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tracing::Instrument as _;

use super::admission::{self, Opening, Pending, Throttle, Ticket};
use super::allow_list::{Gate, Peers};
use super::association::{self, Grant};
use super::command::VERIFICATION;
use super::inbox::Inbox;
use super::query::{QUERY_RETRIEVE_SOP_CLASSES, Retrieval};
use super::scu::Caller;
use super::tracker::{CompletedSeries, Tracker, count};
use crate::config::dicom::NodeSettings;
use crate::dicom::{STORABLE_SOP_CLASSES, decodable_transfer_syntaxes};

/// Why the node could not start.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("DICOM node settings: {0}")]
    Settings(String),
    #[error("DICOM node: {0}")]
    Io(#[from] std::io::Error),
}

/// A running DICOM node. Dropping it stops the listener.
pub struct DicomNode {
    addr: SocketAddr,
    completed: mpsc::UnboundedReceiver<CompletedSeries>,
    tracker: Arc<Tracker>,
    _stop: watch::Sender<bool>,
}

impl std::fmt::Debug for DicomNode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DicomNode")
            .field("addr", &self.addr)
            .finish()
    }
}

impl DicomNode {
    /// Start the node described by `settings` (its `port` must be set), keeping instances under
    /// `data_dir/dimse/`; C-ECHO and C-STORE only.
    pub async fn start(
        settings: &NodeSettings,
        data_dir: &std::path::Path,
    ) -> Result<Self, NodeError> {
        Self::start_with(settings, data_dir, None).await
    }

    /// [`start`](Self::start), also providing C-FIND and C-MOVE over `app`'s instance index when given.
    pub async fn start_with(
        settings: &NodeSettings,
        data_dir: &std::path::Path,
        app: Option<crate::app::App>,
    ) -> Result<Self, NodeError> {
        if let Some(p) = settings.problem() {
            return Err(NodeError::Settings(p));
        }
        let port = settings
            .port
            .ok_or_else(|| NodeError::Settings("no port".into()))?;
        let inbox = Inbox::open(data_dir)?;
        let leftovers = inbox.leftover_complete()?;
        let tracker = Arc::new(Tracker::new(inbox, settings.stable_age())?);
        let listener = TcpListener::bind((settings.host, port)).await?;
        let addr = listener.local_addr()?;
        let (tx, completed) = mpsc::unbounded_channel();
        for folder in leftovers {
            let (instances, bytes) = count(&folder)?;
            let _ = tx.send(CompletedSeries {
                series_uid: String::new(),
                study_uid: String::new(),
                folder,
                instances,
                bytes,
                calling_ae: String::new(),
            });
        }
        let (stop, stopped) = watch::channel(false);
        let peers = Arc::new(Peers::resolve(settings.clone()).await);
        let retrieval = app.map(|app| Retrieval {
            app,
            caller: Caller {
                ae_title: settings.ae_title.clone(),
                timeout: settings.dimse_timeout(),
                max_pdu_length: settings.max_pdu_length,
            },
            peers: settings.peers.clone(),
        });
        tokio::spawn(accept_loop(
            listener,
            peers,
            tracker.clone(),
            retrieval,
            stopped.clone(),
        ));
        tokio::spawn(seal_loop(
            tracker.clone(),
            settings.stable_age(),
            tx,
            stopped,
        ));
        tracing::info!(%addr, ae_title = %settings.ae_title, "DICOM node listening");
        Ok(Self {
            addr,
            completed,
            tracker,
            _stop: stop,
        })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The next series that stopped arriving (waits for it).
    pub async fn next_completed(&mut self) -> Option<CompletedSeries> {
        self.completed.recv().await
    }

    /// Series arriving now: (series UID, instances so far).
    pub fn arriving(&self) -> Vec<(String, usize)> {
        self.tracker.arriving()
    }

    /// The node's series tracker (where received instances are filed), for pulls that wait for a series.
    pub fn tracker(&self) -> Arc<Tracker> {
        self.tracker.clone()
    }
}

async fn seal_loop(
    tracker: Arc<Tracker>,
    stable_age: Duration,
    tx: mpsc::UnboundedSender<CompletedSeries>,
    mut stopped: watch::Receiver<bool>,
) {
    let tick = (stable_age / 4).clamp(Duration::from_millis(100), Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = tokio::time::sleep(tick) => {}
            _ = stopped.changed() => return,
        }
        let t = tracker.clone();
        match tokio::task::spawn_blocking(move || t.seal_due(Instant::now())).await {
            Ok(Ok(done)) => {
                for s in done {
                    if tx.send(s).is_err() {
                        return;
                    }
                }
            }
            Ok(Err(e)) => tracing::error!(error = %e, "cannot seal a complete series"),
            Err(e) => tracing::error!(error = %e, "series sealing failed"),
        }
    }
}

async fn accept_loop(
    listener: TcpListener,
    peers: Arc<Peers>,
    tracker: Arc<Tracker>,
    retrieval: Option<Retrieval>,
    mut stopped: watch::Receiver<bool>,
) {
    let s = &peers.settings;
    let slots = Arc::new(Semaphore::new(s.max_associations));
    let pending = Arc::new(Pending::new(s.max_pending_per_address, s.pending_cap()));
    let noise = Arc::new(Noise::default());
    let mut backoff = Duration::ZERO;
    loop {
        tokio::select! {
            _ = pending.room() => {}
            _ = stopped.changed() => return,
        }
        let (socket, remote) = tokio::select! {
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    use std::io::ErrorKind::{ConnectionAborted, ConnectionReset, Interrupted};
                    if matches!(e.kind(), ConnectionAborted | ConnectionReset | Interrupted) {
                        continue;
                    }
                    // Out of descriptors (EMFILE, ENFILE) or buffers: free one by closing the oldest
                    // connection still without a request, wait (longer while it lasts), keep listening.
                    let freed = pending.close_oldest();
                    backoff = (backoff * 2).clamp(Duration::from_millis(10), Duration::from_secs(1));
                    if let Some(n) = noise.accept_failed.tick() {
                        tracing::warn!(error = %e, failures = n, freed, retry_in = ?backoff,
                            "DICOM accept failed");
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => continue,
                        _ = stopped.changed() => return,
                    }
                }
            },
            _ = stopped.changed() => return,
        };
        backoff = Duration::ZERO;
        let _ = socket.set_nodelay(true);
        let (ticket, closed) = pending.enter(remote.ip());
        if closed > 0
            && let Some(n) = noise.crowded.tick()
        {
            let (total, here) = pending.count(remote.ip());
            tracing::warn!(%remote, closed = n, pending = total, pending_here = here,
                "too many connections without an A-ASSOCIATE-RQ: the oldest closed");
        }
        let (peers, tracker, retrieval) = (peers.clone(), tracker.clone(), retrieval.clone());
        let (slots, noise) = (slots.clone(), noise.clone());
        let span = tracing::info_span!("association", %remote);
        tokio::spawn(
            async move {
                let accepted = Instant::now();
                let Some((socket, slot)) =
                    admit(socket, remote, ticket, &peers, &slots, &noise).await
                else {
                    return;
                };
                // The request is on the socket already: what is left of the association timeout (at
                // least 1 s) is for answering it.
                let left = peers
                    .settings
                    .association_timeout()
                    .saturating_sub(accepted.elapsed());
                handle(
                    socket,
                    remote,
                    &peers,
                    tracker,
                    retrieval,
                    left.max(Duration::from_secs(1)),
                )
                .await;
                drop(slot);
            }
            .instrument(span),
        );
    }
}

/// Log lines for events a remote host can repeat at will, at most one per kind every 10 s.
struct Noise {
    accept_failed: Throttle,
    crowded: Throttle,
    silent: Throttle,
    not_a_request: Throttle,
    busy: Throttle,
}

impl Default for Noise {
    fn default() -> Self {
        let t = || Throttle::new(Duration::from_secs(10));
        Self {
            accept_failed: t(),
            crowded: t(),
            silent: t(),
            not_a_request: t(),
            busy: t(),
        }
    }
}

/// Wait (as a pending connection, within the negotiation timeout) for the caller's whole A-ASSOCIATE-RQ,
/// then decide: a caller that may call from its address takes an association slot, or is refused
/// transiently when none is free; any other is negotiated without a slot (and so rejected by the
/// negotiation). `None`: the connection was answered and closed here.
async fn admit(
    socket: TcpStream,
    remote: SocketAddr,
    mut ticket: Ticket,
    peers: &Peers,
    slots: &Arc<Semaphore>,
    noise: &Noise,
) -> Option<(TcpStream, Option<OwnedSemaphorePermit>)> {
    let s = &peers.settings;
    let opening = tokio::select! {
        o = tokio::time::timeout(s.negotiation_timeout(), admission::read_opening(&socket)) => o,
        _ = &mut ticket.closed => return None,
    };
    drop(ticket);
    match opening {
        Ok(Opening::Request {
            called,
            calling,
            len,
        }) => {
            if !peers.may_call(remote.ip(), &called, &calling) {
                return Some((socket, None));
            }
            match slots.clone().try_acquire_owned() {
                Ok(slot) => Some((socket, Some(slot))),
                Err(_) => {
                    if let Some(n) = noise.busy.tick() {
                        tracing::warn!(calling_ae = %calling.trim(), refused = n,
                            "association refused: too many at once");
                    }
                    admission::answer_request(socket, len, &admission::busy_pdu()).await;
                    None
                }
            }
        }
        Ok(Opening::NotARequest(why)) => {
            if let Some(n) = noise.not_a_request.tick() {
                tracing::warn!(%remote, why, aborted = n, "connection aborted before negotiation");
            }
            admission::abort(socket).await;
            None
        }
        Ok(Opening::Closed) => None,
        Err(_) => {
            if let Some(n) = noise.silent.tick() {
                tracing::warn!(%remote, closed = n, "no A-ASSOCIATE-RQ within the negotiation timeout");
            }
            None
        }
    }
}

async fn handle(
    socket: TcpStream,
    remote: SocketAddr,
    peers: &Peers,
    tracker: Arc<Tracker>,
    retrieval: Option<Retrieval>,
    negotiation: Duration,
) {
    let s = &peers.settings;
    let mut options = ServerAssociationOptions::new()
        .ae_access_control(Gate {
            allowed: peers.allowed_from(remote.ip()),
        })
        .ae_title(s.ae_title.clone())
        .max_pdu_length(s.max_pdu_length)
        .read_timeout(s.dimse_timeout())
        .write_timeout(s.dimse_timeout())
        .with_abstract_syntax(VERIFICATION);
    for uid in STORABLE_SOP_CLASSES {
        options = options.with_abstract_syntax(*uid);
    }
    if retrieval.is_some() {
        for uid in QUERY_RETRIEVE_SOP_CLASSES {
            options = options.with_abstract_syntax(*uid);
        }
    }
    for ts in decodable_transfer_syntaxes() {
        options = options.with_transfer_syntax(ts);
    }
    let assoc = match tokio::time::timeout(negotiation, options.establish_async(socket)).await {
        Ok(Ok(a)) => a,
        Ok(Err(e)) => {
            tracing::warn!(%remote, error = %e, "association refused");
            return;
        }
        Err(_) => {
            tracing::warn!(%remote, "association negotiation timed out");
            return;
        }
    };
    let calling_ae = assoc.peer_ae_title().trim().to_string();
    let may = |f: fn(&crate::config::dicom::Peer) -> bool| {
        s.peers.is_empty() || s.peer(&calling_ae).is_some_and(f)
    };
    let grant = Grant {
        calling_ae: calling_ae.clone(),
        may_store: may(|p| p.store),
        may_query: may(|p| p.query),
        may_retrieve: may(|p| p.retrieve),
        max_instance_bytes: s.max_instance_bytes,
        dimse_timeout: s.dimse_timeout(),
    };
    tracing::info!(%remote, calling_ae = %calling_ae, "association accepted");
    match association::serve(assoc, grant, tracker, retrieval).await {
        Ok(stored) => {
            tracing::info!(%remote, calling_ae = %calling_ae, stored, "association released")
        }
        Err(e) => {
            tracing::warn!(%remote, calling_ae = %calling_ae, error = %e, "association ended")
        }
    }
}
