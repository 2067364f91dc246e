//! Deliveries of DICOM results to DIMSE peers and DICOMweb origins, and the peers themselves.
//!
//! The application owns what a delivery is and how it moves (queued → sending → succeeded | failed, back
//! to queued with exponential backoff while the peer is unreachable); the wire is a port,
//! [`DicomCaller`], that the DICOM front door installs ([`App::start_deliveries`]), so that the
//! application imports no front door. One worker task makes the deliveries of finished rule jobs and
//! starts whatever is due, up to [`PARALLEL_DELIVERIES`] at once and one per destination at a time, so a
//! slow or silent peer holds up only its own deliveries; deliveries left `sending` by a stop are queued
//! again at start (on a shared PostgreSQL database, only those whose claim ended: see
//! [`crate::jobs::database::node`]). A destination
//! that names a DICOMweb origin (`dicom.web_peers`) is sent to by STOW-RS instead
//! ([`stow_client`](super::stow_client)), with the same states, per-instance outcomes and backoff.

use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tokio::sync::{Notify, Semaphore};

use super::App;
use super::error::{AppError, AppResult, refused};
use crate::config::dicom::Peer;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::deliveries::{
    Delivery, DeliveryFilter, DeliveryInstance, DeliveryState, InstanceState, RuleRun, backoff_us,
};
use crate::jobs::export::{ExportOptions, ExportedFile, export_dir, export_job};
use crate::jobs::model::{JobStatus, now_us, rfc3339};
use crate::storage::JobId;

mod claim;

pub use super::dicom_caller::{CallError, CallFuture, DicomCaller, SentInstance};
pub use claim::DELIVERY_CLAIM;

/// Deliveries sent at once (each to a different destination).
pub const PARALLEL_DELIVERIES: usize = 4;

/// The installed caller, the worker's wake-up and the slots of deliveries in flight.
#[derive(Clone)]
pub struct Outbound {
    caller: Arc<OnceLock<Arc<dyn DicomCaller>>>,
    wake: Arc<Notify>,
    slots: Arc<Semaphore>,
    /// The HTTP client of STOW-RS deliveries, made at the first one.
    #[cfg(feature = "dicomweb-client")]
    pub(super) web: Arc<OnceLock<super::stow_client::StowClient>>,
}

impl Default for Outbound {
    fn default() -> Self {
        Self {
            caller: Arc::default(),
            wake: Arc::default(),
            slots: Arc::new(Semaphore::new(PARALLEL_DELIVERIES)),
            #[cfg(feature = "dicomweb-client")]
            web: Arc::default(),
        }
    }
}

impl std::fmt::Debug for Outbound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Outbound")
            .field("installed", &self.caller.get().is_some())
            .finish()
    }
}

/// The JSON representation of a delivery (with its instances when they were loaded).
pub fn delivery_json(d: &Delivery, with_instances: bool) -> Value {
    let mut v = json!({
        "id": d.id,
        "job_id": d.job_id,
        "destination": d.destination,
        "state": d.state,
        "attempts": d.attempts,
        "created_at": rfc3339(d.created_us),
        "updated_at": rfc3339(d.updated_us),
        "links": {"self": format!("/v1/deliveries/{}", d.id), "job": format!("/v1/jobs/{}", d.job_id)},
    });
    if let Some(r) = &d.rule_name {
        v["rule"] = json!(r);
        v["links"]["rule"] = json!(format!("/v1/rules/{r}"));
    }
    if let Some(r) = &d.run_id {
        v["run_id"] = json!(r);
    }
    if let (DeliveryState::Queued, Some(t)) = (d.state, d.next_attempt_us) {
        v["next_attempt_at"] = json!(rfc3339(t));
    }
    if let Some(e) = &d.last_error {
        v["last_error"] = json!(e);
    }
    if let Some(t) = d.finished_us {
        v["finished_at"] = json!(rfc3339(t));
    }
    if with_instances {
        let count = |s: InstanceState| d.instances.iter().filter(|i| i.state == s).count();
        v["counts"] = json!({
            "total": d.instances.len(),
            "succeeded": count(InstanceState::Succeeded),
            "failed": count(InstanceState::Failed),
            "pending": count(InstanceState::Pending),
        });
        v["instances"] = json!(d.instances);
    }
    v
}

fn delivery_not_found(id: &str) -> AppError {
    refused(
        ErrorCode::DeliveryNotFound,
        format!("no delivery {:?}", id.chars().take(80).collect::<String>()),
    )
}

impl App {
    fn caller(&self) -> AppResult<Arc<dyn DicomCaller>> {
        self.outbound.caller.get().cloned().ok_or_else(|| {
            refused(
                ErrorCode::DimseUnavailable,
                "this process has no DICOM front door to call peers with",
            )
        })
    }

    /// Install the DICOM caller and start the delivery worker (once; later calls do nothing).
    pub fn start_deliveries(&self, caller: Arc<dyn DicomCaller>) {
        if self.outbound.caller.set(caller).is_err() {
            return;
        }
        let app = self.clone();
        tokio::spawn(async move { app.delivery_loop().await });
    }

    /// The configured peer called `ae_title`.
    pub fn peer(&self, ae_title: &str) -> AppResult<&Peer> {
        self.settings.dicom.peer(ae_title).ok_or_else(|| {
            refused(
                ErrorCode::PeerNotFound,
                format!(
                    "no DICOM peer {:?} is configured (`dicom.peers`)",
                    ae_title.chars().take(80).collect::<String>()
                ),
            )
        })
    }

    /// C-ECHO a configured peer: its status and the round trip (association, echo, release).
    pub async fn echo_peer(&self, ae_title: &str) -> AppResult<(u16, Duration)> {
        let peer = self.peer(ae_title)?.clone();
        let caller = self.caller()?;
        let t0 = Instant::now();
        match caller.echo(&peer).await {
            Ok(status) => Ok((status, t0.elapsed())),
            Err(CallError(reason)) => Err(refused(
                ErrorCode::PeerUnreachable,
                format!("C-ECHO to {}: {reason}", peer.ae_title),
            )),
        }
    }

    /// Queue a delivery of a succeeded job's DICOM results to a configured peer.
    pub async fn create_delivery(&self, job: JobId, destination: &str) -> AppResult<Delivery> {
        if !self.settings.dicom.is_destination(destination) {
            return Err(refused(
                ErrorCode::UnknownPeer,
                format!(
                    "destination {:?} is not a configured DICOM peer (`dicom.peers`) or DICOMweb \
                     origin (`dicom.web_peers`)",
                    destination.chars().take(80).collect::<String>()
                ),
            ));
        }
        let j = self.get_job(job).await?;
        if j.status != JobStatus::Succeeded {
            return Err(refused(
                ErrorCode::JobNotSucceeded,
                format!(
                    "the job is {}; only a succeeded job's results can be sent",
                    j.status.as_str()
                ),
            ));
        }
        let run = self.db.run_of_job(job).await?;
        let id = self
            .db
            .insert_delivery(job, run.as_ref(), destination)
            .await?;
        self.outbound.wake.notify_one();
        self.get_delivery(&id).await
    }

    pub async fn get_delivery(&self, id: &str) -> AppResult<Delivery> {
        self.db
            .get_delivery(id)
            .await?
            .ok_or_else(|| delivery_not_found(id))
    }

    pub async fn list_deliveries(&self, f: &DeliveryFilter) -> AppResult<Vec<Delivery>> {
        Ok(self.db.list_deliveries(f).await?)
    }

    /// Queue a failed delivery again: its failed instances are sent again, now.
    pub async fn retry_delivery(&self, id: &str) -> AppResult<Delivery> {
        let d = self.get_delivery(id).await?;
        if !self.db.retry_delivery(id).await? {
            return Err(refused(
                ErrorCode::DeliveryNotRetryable,
                format!(
                    "the delivery is {}; only a failed delivery can be retried",
                    d.state.as_str()
                ),
            ));
        }
        self.outbound.wake.notify_one();
        self.get_delivery(id).await
    }

    async fn delivery_loop(self) {
        match self.db.requeue_interrupted_deliveries().await {
            Ok(0) => {}
            Ok(n) => tracing::info!(
                deliveries = n,
                "deliveries interrupted by a stop queued again"
            ),
            Err(e) => tracing::error!(error = %e, "cannot queue interrupted deliveries again"),
        }
        loop {
            if let Err(e) = self.delivery_round().await {
                tracing::error!(error = %e, "delivery round failed");
            }
            let wait = match self.db.next_delivery_due().await {
                Ok(Some(t)) => Duration::from_micros((t - now_us()).clamp(10_000, 500_000) as u64),
                _ => Duration::from_millis(500),
            };
            tokio::select! {
                _ = self.outbound.wake.notified() => {}
                _ = tokio::time::sleep(wait) => {}
            }
        }
    }

    /// Make the deliveries of finished rule jobs, then send every due delivery.
    async fn delivery_round(&self) -> AppResult<()> {
        // On a shared database another process may have been lost while sending: its claims end.
        if self.db.is_shared() {
            let n = self.db.requeue_expired_deliveries().await?;
            if n > 0 {
                tracing::warn!(
                    deliveries = n,
                    "deliveries whose sender was lost queued again"
                );
            }
        }
        for (run, status) in self.db.runs_with_finished_jobs().await? {
            self.settle_run(&run, status).await?;
        }
        // Each attempt runs on its own task holding a slot; the claim skips destinations with one in flight.
        while let Ok(slot) = self.outbound.slots.clone().try_acquire_owned() {
            let now = now_us();
            let until = now.saturating_add(DELIVERY_CLAIM.as_micros() as i64);
            let Some(d) = self.db.claim_due_delivery(now, until).await? else {
                break;
            };
            let span = tracing::info_span!("delivery", delivery_id = %d.id, job_id = %d.job_id, destination = %d.destination);
            let app = self.clone();
            tokio::spawn(tracing::Instrument::instrument(
                async move {
                    if let Err(e) = app.attempt(d).await {
                        tracing::error!(error = %e, "recording a delivery attempt failed");
                    }
                    drop(slot);
                    app.outbound.wake.notify_one();
                },
                span,
            ));
        }
        Ok(())
    }

    /// Close a run whose job finished: its deliveries queued (once, whichever worker closes it first), or
    /// the job's error recorded.
    async fn settle_run(&self, run: &RuleRun, status: JobStatus) -> AppResult<()> {
        let Some(job) = run.job_id else {
            return Ok(());
        };
        let (destinations, error) = if status == JobStatus::Succeeded {
            let destinations = match self.db.get_rule(&run.rule_name).await? {
                Some(r) => r.spec.destinations,
                None => Vec::new(),
            };
            (destinations, None)
        } else {
            (
                Vec::new(),
                self.db.get_job(job).await?.and_then(|j| j.error),
            )
        };
        let queued = self
            .db
            .complete_run(run, job, &destinations, error.as_ref())
            .await?;
        for (id, d) in queued.iter().flatten().zip(&destinations) {
            tracing::info!(delivery_id = %id, rule = %run.rule_name, %job, destination = %d, "delivery queued");
        }
        Ok(())
    }

    /// One attempt of a claimed (`sending`) delivery.
    pub(super) async fn attempt_claimed(&self, mut d: Delivery) -> AppResult<()> {
        let fail = |d: &Delivery, why: String| (d.clone(), DeliveryState::Failed, None, Some(why));
        let (d, state, next, error) = match self.prepare(&mut d).await {
            Err(p) => fail(&d, p.detail),
            Ok(()) => self.send(d).await,
        };
        if let Some(e) = &error {
            tracing::warn!(state = state.as_str(), attempts = d.attempts, error = %e, "delivery attempt ended");
        } else {
            tracing::info!(instances = d.instances.len(), "delivery succeeded");
        }
        if !self
            .db
            .finish_delivery_attempt(&d, state, next, error.as_deref())
            .await?
        {
            tracing::warn!(
                "the delivery was claimed again by another attempt; this attempt's end is not recorded"
            );
        }
        Ok(())
    }

    /// The DICOM results of succeeded job `job`, exported now unless they already were, with the options of
    /// the rule that made the job (if any) — the same files, and so the same UIDs, for every delivery and
    /// for the instance index.
    pub(crate) async fn export_results(&self, job_id: JobId) -> Result<Vec<ExportedFile>, Problem> {
        let job = match self.db.get_job(job_id).await {
            Ok(Some(j)) => j,
            Ok(None) => return Err(Problem::new(ErrorCode::JobNotFound, "the job was deleted")),
            Err(e) => return Err(AppError::from(e).into_problem()),
        };
        let Some(result) = job
            .result
            .clone()
            .filter(|_| job.status == JobStatus::Succeeded)
        else {
            return Err(Problem::new(
                ErrorCode::JobNotSucceeded,
                "the job has no results",
            ));
        };
        let rule = match self.db.run_of_job(job_id).await.ok().flatten() {
            Some(run) => self.db.get_rule(&run.rule_name).await.ok().flatten(),
            None => None,
        };
        let source = match result.source_series {
            Some(id) => self.db.get_series(id).await.ok().flatten(),
            None => None,
        };
        let opts = ExportOptions {
            window: rule.as_ref().and_then(|r| r.spec.result_window()),
            send_volume: rule.as_ref().is_some_and(|r| r.spec.send_volume),
            mu_water: self.settings.mu_water_per_mm,
        };
        let store = self.store.clone();
        let spec = job.request.clone();
        self.engine
            .compute(move || export_job(&store, job_id, &spec, &result, source.as_ref(), &opts))
            .await
    }

    /// Export the job's results (once) and give the delivery its instances.
    async fn prepare(&self, d: &mut Delivery) -> Result<(), Problem> {
        if !d.instances.is_empty() {
            return Ok(());
        }
        let files = self.export_results(d.job_id).await?;
        d.instances = files
            .into_iter()
            .map(|f| DeliveryInstance {
                file: f.file,
                sop_class_uid: f.sop_class_uid,
                sop_instance_uid: f.sop_instance_uid,
                state: InstanceState::Pending,
                status: None,
                detail: None,
            })
            .collect();
        self.db
            .set_delivery_instances(&d.id, &d.instances)
            .await
            .map_err(|e| AppError::from(e).into_problem())?;
        Ok(())
    }

    /// Send the instances not yet stored; the new state, next attempt and error.
    async fn send(
        &self,
        mut d: Delivery,
    ) -> (Delivery, DeliveryState, Option<i64>, Option<String>) {
        if let Some(web) = self.settings.dicom.web_peer(&d.destination).cloned() {
            #[cfg(feature = "dicomweb-client")]
            return self.send_web(d, &web).await;
            #[cfg(not(feature = "dicomweb-client"))]
            {
                let why = format!(
                    "{} is a DICOMweb peer and this build has no DICOMweb client",
                    web.name
                );
                return (d, DeliveryState::Failed, None, Some(why));
            }
        }
        let Some(peer) = self.settings.dicom.peer(&d.destination).cloned() else {
            let why = format!("{} is no longer a configured peer", d.destination);
            return (d, DeliveryState::Failed, None, Some(why));
        };
        let caller = match self.caller() {
            Ok(c) => c,
            Err(e) => return (d, DeliveryState::Failed, None, Some(e.to_string())),
        };
        let dir = export_dir(&self.store, d.job_id);
        let todo: Vec<usize> = (0..d.instances.len())
            .filter(|&k| d.instances[k].state != InstanceState::Succeeded)
            .collect();
        let files = todo
            .iter()
            .map(|&k| dir.join(&d.instances[k].file))
            .collect();
        match caller.store(&peer, files).await {
            Ok(sent) => {
                for (&k, s) in todo.iter().zip(sent) {
                    let i = &mut d.instances[k];
                    i.status = s.status;
                    i.detail = s.detail;
                    i.state = if s.stored {
                        InstanceState::Succeeded
                    } else {
                        InstanceState::Failed
                    };
                }
                let failed = d
                    .instances
                    .iter()
                    .filter(|i| i.state != InstanceState::Succeeded)
                    .count();
                if failed == 0 {
                    (d, DeliveryState::Succeeded, None, None)
                } else {
                    let why = format!(
                        "{failed} of {} instances were not stored by {}",
                        d.instances.len(),
                        peer.ae_title
                    );
                    (d, DeliveryState::Failed, None, Some(why))
                }
            }
            Err(CallError(reason)) => self.unreachable(d, reason),
        }
    }

    /// The peer could not be reached: queued again after the backoff, or failed once the attempts are
    /// spent.
    pub(super) fn unreachable(
        &self,
        d: Delivery,
        reason: String,
    ) -> (Delivery, DeliveryState, Option<i64>, Option<String>) {
        let s = &self.settings.dicom;
        if d.attempts >= s.delivery_max_attempts {
            let why = format!("{reason} (gave up after {} attempts)", d.attempts);
            (d, DeliveryState::Failed, None, Some(why))
        } else {
            let next = now_us()
                + backoff_us(
                    d.attempts,
                    s.delivery_retry_base_ms,
                    s.delivery_retry_max_ms,
                );
            (d, DeliveryState::Queued, Some(next), Some(reason))
        }
    }
}
