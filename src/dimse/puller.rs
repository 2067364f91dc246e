//! Pulling a volume job's series from a PACS (the engine's [`SeriesPuller`] port): C-FIND the series on
//! the peer (its study and instance count), C-MOVE it to this node's own AE title, wait while the peer's
//! C-STOREs arrive (they are filed like any others, but the series is claimed: its stable age does not seal
//! it and no rule fires on it), then assemble it exactly like an uploaded series and index its instances.
//!
//! A peer that cannot be reached, answers a failure, holds no such series or goes silent for the DIMSE
//! timeout ends the pull with a problem naming the peer's status and sub-operation counts; a cancel aborts
//! the C-MOVE association. What arrived of a pull that did not finish is removed.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tracing::Instrument as _;

use super::command::{SubOperations, status};
use super::feed::instance_files;
use super::pull::{self, MoveOutcome};
use super::scu::Caller;
use super::tracker::Tracker;
use crate::app::{App, AppError};
use crate::config::dicom::Peer;
use crate::dicom::IdentifierElement;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::PacsSeries;
use crate::jobs::pull::{PullFuture, SeriesPuller};
use crate::jobs::run::RunError;
use crate::recon::control::{Cancel, Progress};
use crate::storage::SeriesId;

const QUERY_RETRIEVE_LEVEL: u32 = 0x0008_0052;
const STUDY_UID: u32 = 0x0020_000D;
const SERIES_UID: u32 = 0x0020_000E;
const MODALITY: u32 = 0x0008_0060;
const SERIES_INSTANCES: u32 = 0x0020_1209;

/// How often a waiting pull looks at arrivals and its cancel flag.
const POLL: Duration = Duration::from_millis(200);

/// ctrecon's node pulling series from its peers.
pub struct NodePuller {
    app: App,
    caller: Caller,
    tracker: Arc<Tracker>,
}

impl NodePuller {
    /// A puller moving series to this node (`app`'s DICOM settings: its AE title is the move destination)
    /// whose instances are filed by `tracker`.
    pub fn new(app: App, tracker: Arc<Tracker>) -> Self {
        let s = &app.settings.dicom;
        let caller = Caller {
            ae_title: s.ae_title.clone(),
            timeout: s.dimse_timeout(),
            max_pdu_length: s.max_pdu_length,
        };
        Self {
            app,
            caller,
            tracker,
        }
    }
}

impl SeriesPuller for NodePuller {
    fn pull<'a>(
        &'a self,
        source: &'a PacsSeries,
        cancel: &'a Cancel,
        progress: &'a dyn Progress,
    ) -> PullFuture<'a> {
        let span = tracing::info_span!("pull", peer = %source.pacs, series_uid = %source.series_instance_uid);
        Box::pin(self.run(source, cancel, progress).instrument(span))
    }
}

fn element(tag: u32, vr: &str, value: &str) -> IdentifierElement {
    IdentifierElement {
        tag,
        vr: vr.into(),
        value: value.into(),
    }
}

fn value_of(found: &[IdentifierElement], tag: u32) -> &str {
    found
        .iter()
        .find(|e| e.tag == tag)
        .map(|e| e.value.trim())
        .unwrap_or("")
}

fn failed(code: ErrorCode, detail: String) -> RunError {
    RunError::Failed(Problem::new(code, detail))
}

/// A DIMSE status with its meaning (PS3.4 C.4.2.1.5).
fn describe(code: u16) -> String {
    let meaning = match code {
        status::SUCCESS => "success",
        status::CANCEL => "canceled",
        status::SUB_OPERATIONS_FAILED => "sub-operations complete, one or more failures",
        status::MOVE_DESTINATION_UNKNOWN => "move destination unknown",
        0xA701 => "out of resources: unable to calculate number of matches",
        status::SUB_OPERATIONS_IMPOSSIBLE => "out of resources: unable to perform sub-operations",
        0xA900 => "identifier does not match SOP class",
        0xC000..=0xCFFF => "unable to process",
        _ => "failure",
    };
    format!("{code:04X} ({meaning})")
}

fn counts(s: &SubOperations) -> String {
    format!(
        "{} completed, {} failed, {} warning, {} remaining",
        s.completed, s.failed, s.warning, s.remaining
    )
}

/// `fut`, or `None` as soon as `cancel` is set (the future is dropped, closing its association).
async fn unless_canceled<T>(
    cancel: &Cancel,
    fut: impl std::future::Future<Output = T>,
) -> Option<T> {
    tokio::select! {
        r = fut => Some(r),
        _ = async { while !cancel.is_canceled() { tokio::time::sleep(POLL).await } } => None,
    }
}

/// The claim of a series being pulled: released when dropped, removing what arrived unless it was taken.
struct Claim {
    tracker: Arc<Tracker>,
    uid: String,
    taken: bool,
}

impl Drop for Claim {
    fn drop(&mut self) {
        let (tracker, uid, taken) = (self.tracker.clone(), self.uid.clone(), self.taken);
        let release = move || {
            if !taken && let Err(e) = tracker.discard(&uid) {
                tracing::warn!(series_uid = %uid, error = %e, "what arrived of an unfinished pull was not removed");
            }
            tracker.unclaim(&uid);
        };
        match tokio::runtime::Handle::try_current() {
            Ok(h) => {
                h.spawn_blocking(release);
            }
            Err(_) => release(),
        }
    }
}

impl NodePuller {
    async fn run(
        &self,
        source: &PacsSeries,
        cancel: &Cancel,
        progress: &dyn Progress,
    ) -> Result<SeriesId, RunError> {
        let peer = self
            .app
            .settings
            .dicom
            .peer(&source.pacs)
            .cloned()
            .ok_or_else(|| {
                failed(
                    ErrorCode::UnknownPeer,
                    format!("`{}` is no longer a configured DICOM peer", source.pacs),
                )
            })?;
        let uid = source.series_instance_uid.as_str();
        progress.report("querying the PACS", 0.0, None, None);
        let (study_uid, expected) = self.find(&peer, uid, cancel).await?;
        let mut claim = self.claim(uid, cancel).await?;
        let outcome = self
            .retrieve(&peer, uid, &study_uid, expected, cancel, progress)
            .await?;
        let want = usize::from(outcome.sub_operations.completed)
            + usize::from(outcome.sub_operations.warning);
        let good = matches!(
            outcome.status,
            status::SUCCESS | status::SUB_OPERATIONS_FAILED
        );
        if !good || want == 0 {
            return Err(failed(
                ErrorCode::PullFailed,
                format!(
                    "{} ended the C-MOVE of series {uid} with status {}; sub-operations: {}",
                    peer.ae_title,
                    describe(outcome.status),
                    counts(&outcome.sub_operations)
                ),
            ));
        }
        // Each C-STORE is filed before it is answered, so every completed sub-operation is here already;
        // waiting covers a peer that answers the C-MOVE before its last C-STORE association ends.
        let deadline = Instant::now() + self.caller.timeout;
        while self.tracker.arrived(uid) < want {
            if cancel.is_canceled() {
                return Err(RunError::Canceled);
            }
            if Instant::now() >= deadline {
                return Err(failed(
                    ErrorCode::PullFailed,
                    format!(
                        "{} reported {want} instances of series {uid} sent, but {} arrived within {:?}",
                        peer.ae_title,
                        self.tracker.arrived(uid),
                        self.caller.timeout
                    ),
                ));
            }
            tokio::time::sleep(POLL).await;
        }
        progress.report("assembling the pulled series", 0.95, None, None);
        let tracker = self.tracker.clone();
        let owned = uid.to_string();
        let taken = tokio::task::spawn_blocking(move || tracker.take(&owned))
            .await
            .map_err(|e| internal("taking a pulled series failed", &e))?
            .map_err(|e| internal("sealing a pulled series failed", &e))?;
        claim.taken = true;
        let Some(done) = taken else {
            return Err(failed(
                ErrorCode::PullFailed,
                format!("no instance of series {uid} arrived from {}", peer.ae_title),
            ));
        };
        tracing::info!(instances = done.instances, bytes = done.bytes, sub_operations = %counts(&outcome.sub_operations), "pulled series arrived");
        self.assemble(uid, done).await
    }

    /// C-FIND the series: its study and, when the peer says, its number of instances.
    async fn find(
        &self,
        peer: &Peer,
        uid: &str,
        cancel: &Cancel,
    ) -> Result<(String, Option<usize>), RunError> {
        let keys = [
            element(QUERY_RETRIEVE_LEVEL, "CS", "SERIES"),
            element(STUDY_UID, "UI", ""),
            element(SERIES_UID, "UI", uid),
            element(MODALITY, "CS", ""),
            element(SERIES_INSTANCES, "IS", ""),
        ];
        let found = unless_canceled(cancel, pull::find(&self.caller, peer, &keys))
            .await
            .ok_or(RunError::Canceled)?
            .map_err(|e| {
                failed(
                    ErrorCode::PullFailed,
                    format!("C-FIND of series {uid} on {} failed: {e}", peer.ae_title),
                )
            })?;
        let Some(m) = found.iter().find(|m| value_of(m, SERIES_UID) == uid) else {
            return Err(failed(
                ErrorCode::PullSeriesNotFound,
                format!(
                    "{} holds no series {uid} (C-FIND at SERIES level: {} matches)",
                    peer.ae_title,
                    found.len()
                ),
            ));
        };
        let expected = value_of(m, SERIES_INSTANCES).parse().ok();
        tracing::info!(
            study_uid = value_of(m, STUDY_UID),
            modality = value_of(m, MODALITY),
            ?expected,
            "series found on the PACS"
        );
        Ok((value_of(m, STUDY_UID).to_string(), expected))
    }

    /// Claim the series, waiting (up to the DIMSE timeout) while another pull holds it.
    async fn claim(&self, uid: &str, cancel: &Cancel) -> Result<Claim, RunError> {
        let deadline = Instant::now() + self.caller.timeout;
        while !self.tracker.claim(uid) {
            if cancel.is_canceled() {
                return Err(RunError::Canceled);
            }
            if Instant::now() >= deadline {
                return Err(failed(
                    ErrorCode::PullFailed,
                    format!(
                        "another job kept pulling series {uid} for {:?}",
                        self.caller.timeout
                    ),
                ));
            }
            tokio::time::sleep(POLL).await;
        }
        Ok(Claim {
            tracker: self.tracker.clone(),
            uid: uid.to_string(),
            taken: false,
        })
    }

    /// C-MOVE the series to this node, reporting arrivals against the expected count.
    async fn retrieve(
        &self,
        peer: &Peer,
        uid: &str,
        study_uid: &str,
        expected: Option<usize>,
        cancel: &Cancel,
        progress: &dyn Progress,
    ) -> Result<MoveOutcome, RunError> {
        let mut keys = vec![element(QUERY_RETRIEVE_LEVEL, "CS", "SERIES")];
        if !study_uid.is_empty() {
            keys.push(element(STUDY_UID, "UI", study_uid));
        }
        keys.push(element(SERIES_UID, "UI", uid));
        let latest: Mutex<Option<SubOperations>> = Mutex::new(None);
        let on_pending = |s: SubOperations| {
            if let Ok(mut l) = latest.lock() {
                *l = Some(s);
            }
        };
        let destination = self.caller.ae_title.clone();
        let moving =
            pull::retrieve_watched(&self.caller, peer, &destination, &keys, cancel, &on_pending);
        tokio::pin!(moving);
        let mut tick = tokio::time::interval(POLL);
        let result = loop {
            tokio::select! {
                r = &mut moving => break r,
                _ = tick.tick() => {
                    let total = latest
                        .lock()
                        .ok()
                        .and_then(|l| l.map(|s| usize::from(s.remaining) + usize::from(s.completed)
                            + usize::from(s.failed) + usize::from(s.warning)))
                        .filter(|&n| n > 0)
                        .or(expected);
                    let arrived = self.tracker.arrived(uid);
                    let fraction = total.map_or(0.0, |n| arrived as f64 / n.max(1) as f64);
                    let stage = match total {
                        Some(n) => format!("retrieving from {}: {arrived} of {n} instances", peer.ae_title),
                        None => format!("retrieving from {}: {arrived} instances", peer.ae_title),
                    };
                    progress.report(&stage, 0.05 + 0.85 * fraction.min(1.0), None, None);
                }
            }
        };
        match result {
            Ok(Some(outcome)) => Ok(outcome),
            Ok(None) => Err(RunError::Canceled),
            Err(e) => Err(failed(
                ErrorCode::PullFailed,
                format!(
                    "C-MOVE of series {uid} from {} failed: {}",
                    peer.ae_title, e
                ),
            )),
        }
    }

    /// Assemble the instances of a taken series like an upload and index them; the stored series whose UID
    /// was pulled.
    async fn assemble(
        &self,
        uid: &str,
        done: super::tracker::CompletedSeries,
    ) -> Result<SeriesId, RunError> {
        let folder = done.folder.clone();
        let listed = {
            let f = folder.clone();
            tokio::task::spawn_blocking(move || instance_files(&f)).await
        };
        let files = listed
            .map_err(|e| internal("listing a pulled series failed", &e))?
            .map_err(|e| internal("listing a pulled series failed", &e))?;
        let paths: Vec<_> = files.iter().map(|f| f.path.clone()).collect();
        let recorded = self.app.record_received(files, done.bytes).await;
        let outcome = match recorded {
            Ok(r) => {
                let records: Vec<_> = r.ingested.ready().cloned().collect();
                if let Err(e) = self.app.index_received(r.upload_id, paths, &records).await {
                    tracing::error!(upload_id = %r.upload_id, error = %e, "pulled instances not indexed");
                }
                match records.iter().find(|s| s.series_uid == uid) {
                    Some(s) => {
                        tracing::info!(series_id = %s.id, upload_id = %r.upload_id, "pulled series stored");
                        Ok(s.id)
                    }
                    None => Err(RunError::Failed(r.ingested.failure())),
                }
            }
            Err(AppError::Refused(p)) => Err(RunError::Failed(p)),
            Err(e) => Err(internal("recording a pulled series failed", &e)),
        };
        let _ = tokio::fs::remove_dir_all(&folder).await;
        outcome
    }
}

fn internal(what: &str, e: &dyn std::fmt::Display) -> RunError {
    tracing::error!(error = %e, "{what}");
    RunError::Failed(Problem::internal())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statuses_are_named_with_their_meaning() {
        assert_eq!(describe(0xA801), "A801 (move destination unknown)");
        assert_eq!(describe(0xC000), "C000 (unable to process)");
        assert_eq!(
            describe(0xB000),
            "B000 (sub-operations complete, one or more failures)"
        );
        let s = SubOperations {
            remaining: 0,
            completed: 3,
            failed: 1,
            warning: 0,
        };
        assert_eq!(counts(&s), "3 completed, 1 failed, 0 warning, 0 remaining");
    }
}
