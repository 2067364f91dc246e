//! The DICOM node's tables on either database: processing rules and their runs, deliveries with their
//! instances, and the instance index with the received instances pending assembly. Each call goes to the
//! adapter the database was opened with; both write the same rows with the same guards.
//!
//! What holds when several processes share a PostgreSQL database (and, trivially, for the one process that
//! owns a SQLite one):
//! - a rule fires once per series content ([`Database::insert_run`]), and a finished run queues its
//!   deliveries once ([`Database::complete_run`]);
//! - a due delivery is claimed by exactly one process ([`Database::claim_due_delivery`]) and is its own
//!   until the claim ends, which it renews while it sends; only deliveries whose claim ended are queued
//!   again ([`Database::requeue_expired_deliveries`]; at start on SQLite every `sending` one,
//!   [`Database::requeue_interrupted_deliveries`]);
//! - a job's results are indexed once ([`Database::insert_instances`] answers false to the later caller);
//! - the received instances of a series are assembled by one process at a time
//!   ([`Database::claim_pending_instances`]), and settling them twice is harmless.

use super::Database;
use crate::error_code::Problem;
use crate::jobs::deliveries::{
    Delivery, DeliveryFilter, DeliveryInstance, DeliveryState, NewRun, RuleRun, RunState,
};
use crate::jobs::model::JobStatus;
use crate::jobs::model::{IndexScope, NewInstance, ReplacedCopy, StoredInstance, now_us};
use crate::jobs::rules::{RuleSource, RuleSpec, StoredRule};
use crate::jobs::store::DbError;
use crate::storage::{InstanceId, InstanceOwner, JobId, SeriesId, UploadId};

/// The same call on whichever adapter `$self` holds.
macro_rules! on {
    ($self:ident, $db:ident => $call:expr) => {
        match $self {
            Database::Sqlite($db) => $call,
            Database::Postgres($db) => $call,
        }
    };
}

impl Database {
    /// Insert a rule; false when one of that name exists.
    pub async fn insert_rule(&self, spec: &RuleSpec, source: RuleSource) -> Result<bool, DbError> {
        on!(self, db => db.insert_rule(spec, source).await)
    }

    /// Replace an API rule; false when there is no API rule of that name.
    pub async fn replace_rule(&self, spec: &RuleSpec) -> Result<bool, DbError> {
        on!(self, db => db.replace_rule(spec).await)
    }

    /// Delete an API rule and its runs; false when there is no API rule of that name.
    pub async fn delete_rule(&self, name: &str) -> Result<bool, DbError> {
        on!(self, db => db.delete_rule(name).await)
    }

    pub async fn get_rule(&self, name: &str) -> Result<Option<StoredRule>, DbError> {
        on!(self, db => db.get_rule(name).await)
    }

    /// Every rule, by name.
    pub async fn list_rules(&self) -> Result<Vec<StoredRule>, DbError> {
        on!(self, db => db.list_rules().await)
    }

    /// Make the configuration's rules the stored config rules (others removed, these inserted or replaced).
    pub async fn sync_config_rules(&self, specs: &[RuleSpec]) -> Result<(), DbError> {
        on!(self, db => db.sync_config_rules(specs).await)
    }

    /// Record that a rule fires for a series; `None` when it already fired for this content.
    pub async fn insert_run(&self, run: &NewRun<'_>) -> Result<Option<String>, DbError> {
        on!(self, db => db.insert_run(run).await)
    }

    pub async fn set_run_job(&self, run_id: &str, job: JobId) -> Result<(), DbError> {
        on!(self, db => db.set_run_job(run_id, job).await)
    }

    pub async fn set_run_state(
        &self,
        run_id: &str,
        state: RunState,
        error: Option<&Problem>,
    ) -> Result<(), DbError> {
        on!(self, db => db.set_run_state(run_id, state, error).await)
    }

    /// Close a run whose job finished and queue its deliveries, once: `None` when it was closed before.
    pub async fn complete_run(
        &self,
        run: &RuleRun,
        job: JobId,
        destinations: &[String],
        error: Option<&Problem>,
    ) -> Result<Option<Vec<String>>, DbError> {
        on!(self, db => db.complete_run(run, job, destinations, error).await)
    }

    /// Runs whose job has finished but which are not closed yet, with the job's status.
    pub async fn runs_with_finished_jobs(&self) -> Result<Vec<(RuleRun, JobStatus)>, DbError> {
        on!(self, db => db.runs_with_finished_jobs().await)
    }

    /// The newest runs of a rule (all rules when `rule` is `None`).
    pub async fn list_runs(&self, rule: Option<&str>, limit: u32) -> Result<Vec<RuleRun>, DbError> {
        on!(self, db => db.list_runs(rule, limit).await)
    }

    /// The run that started `job`, if a rule did.
    pub async fn run_of_job(&self, job: JobId) -> Result<Option<RuleRun>, DbError> {
        on!(self, db => db.run_of_job(job).await)
    }

    /// Queue a delivery of `job` to `destination`, due now; returns its id.
    pub async fn insert_delivery(
        &self,
        job: JobId,
        run: Option<&RuleRun>,
        destination: &str,
    ) -> Result<String, DbError> {
        on!(self, db => db.insert_delivery(job, run, destination).await)
    }

    /// A delivery with its instances.
    pub async fn get_delivery(&self, id: &str) -> Result<Option<Delivery>, DbError> {
        on!(self, db => db.get_delivery(id).await)
    }

    /// Deliveries matching `f` (without their instances), newest first.
    pub async fn list_deliveries(&self, f: &DeliveryFilter) -> Result<Vec<Delivery>, DbError> {
        on!(self, db => db.list_deliveries(f).await)
    }

    /// Ids of the deliveries of run `run_id`.
    pub async fn delivery_ids_of_run(&self, run_id: &str) -> Result<Vec<String>, DbError> {
        on!(self, db => db.delivery_ids_of_run(run_id).await)
    }

    /// Claim the next due delivery for this process until `claimed_until_us` (see the module notes).
    pub async fn claim_due_delivery(
        &self,
        now: i64,
        claimed_until_us: i64,
    ) -> Result<Option<Delivery>, DbError> {
        on!(self, db => db.claim_due_delivery(now, claimed_until_us).await)
    }

    /// Extend the claim of attempt `attempts` of a sending delivery; false when it lost the claim.
    pub async fn renew_delivery_claim(
        &self,
        id: &str,
        attempts: u32,
        claimed_until_us: i64,
    ) -> Result<bool, DbError> {
        on!(self, db => db.renew_delivery_claim(id, attempts, claimed_until_us).await)
    }

    /// The earliest time a queued delivery is due.
    pub async fn next_delivery_due(&self) -> Result<Option<i64>, DbError> {
        on!(self, db => db.next_delivery_due().await)
    }

    /// At start: deliveries left `sending` go back to `queued`, due now. On SQLite every one (the one
    /// process that owns the database was sending them when it stopped); on a shared database only those
    /// whose claim ended (another live process renews the claims of what it sends).
    pub async fn requeue_interrupted_deliveries(&self) -> Result<u64, DbError> {
        match self {
            Database::Sqlite(db) => db.requeue_sending_deliveries(i64::MAX).await,
            Database::Postgres(db) => db.requeue_sending_deliveries(now_us()).await,
        }
    }

    /// Deliveries `sending` whose claim ended (their process was lost) go back to `queued`, due now.
    pub async fn requeue_expired_deliveries(&self) -> Result<u64, DbError> {
        on!(self, db => db.requeue_sending_deliveries(now_us()).await)
    }

    /// Give a delivery its instances (once, when its job's results were exported).
    pub async fn set_delivery_instances(
        &self,
        id: &str,
        instances: &[DeliveryInstance],
    ) -> Result<(), DbError> {
        on!(self, db => db.set_delivery_instances(id, instances).await)
    }

    /// Record the end of the attempt `d.attempts`; false (nothing written) when it lost its claim.
    pub async fn finish_delivery_attempt(
        &self,
        d: &Delivery,
        state: DeliveryState,
        next_attempt_us: Option<i64>,
        error: Option<&str>,
    ) -> Result<bool, DbError> {
        on!(self, db => db.finish_delivery_attempt(d, state, next_attempt_us, error).await)
    }

    /// Queue a failed delivery again, due now, with its failed instances pending; false unless it was
    /// `failed`.
    pub async fn retry_delivery(&self, id: &str) -> Result<bool, DbError> {
        on!(self, db => db.retry_delivery(id).await)
    }

    /// Index `rows` as belonging to `owner`; for a job, false (nothing written) when its results were
    /// indexed already.
    pub async fn insert_instances(
        &self,
        owner: InstanceOwner,
        rows: &[NewInstance],
    ) -> Result<bool, DbError> {
        on!(self, db => db.insert_instances(owner, rows).await)
    }

    /// Index received `rows` of upload `upload` (pending assembly when `pending`), each replacing the
    /// received copies of its SOP Instance UID indexed before; the copies replaced (their files are the
    /// caller's to remove).
    pub async fn insert_received(
        &self,
        upload: UploadId,
        rows: &[NewInstance],
        pending: bool,
    ) -> Result<Vec<ReplacedCopy>, DbError> {
        on!(self, db => db.insert_received(upload, rows, pending).await)
    }

    /// The received copies of the SOP Instance UIDs `sop_uids`, newest first.
    pub async fn received_copies(
        &self,
        sop_uids: &[String],
    ) -> Result<Vec<StoredInstance>, DbError> {
        on!(self, db => db.received_copies(sop_uids).await)
    }

    /// The indexed instances in `scope`, newest first.
    pub async fn indexed_instances(
        &self,
        scope: &IndexScope,
    ) -> Result<Vec<StoredInstance>, DbError> {
        on!(self, db => db.indexed_instances(scope).await)
    }

    /// Succeeded volume jobs whose DICOM results are not indexed yet, oldest first.
    pub async fn jobs_to_index(&self) -> Result<Vec<JobId>, DbError> {
        on!(self, db => db.jobs_to_index().await)
    }

    /// Whether a job's results were indexed.
    pub async fn job_indexed(&self, id: JobId) -> Result<bool, DbError> {
        on!(self, db => db.job_indexed(id).await)
    }

    /// Mark a job as indexed without instances; false when it was already.
    pub async fn mark_job_indexed(&self, id: JobId) -> Result<bool, DbError> {
        on!(self, db => db.mark_job_indexed(id).await)
    }

    /// Series (UID, study UID) with received instances not yet assembled, oldest first.
    pub async fn pending_series(&self) -> Result<Vec<(String, String)>, DbError> {
        on!(self, db => db.pending_series().await)
    }

    /// Claim the pending instances of series `series_uid` nobody holds, until `claimed_until_us`.
    pub async fn claim_pending_instances(
        &self,
        series_uid: &str,
        now: i64,
        claimed_until_us: i64,
    ) -> Result<Vec<InstanceId>, DbError> {
        on!(self, db => db.claim_pending_instances(series_uid, now, claimed_until_us).await)
    }

    /// At start: on SQLite, release the claims on pending instances (they were this process's, before a
    /// stop); on a shared database nothing (claims of lost processes end by themselves).
    pub async fn release_instance_claims(&self) -> Result<u64, DbError> {
        match self {
            Database::Sqlite(db) => db.release_instance_claims().await,
            Database::Postgres(_) => Ok(0),
        }
    }

    /// Received instances `ids` were assembled: settled, and members of `series` when one was made.
    pub async fn settle_instances(
        &self,
        ids: &[InstanceId],
        series: Option<SeriesId>,
    ) -> Result<(), DbError> {
        on!(self, db => db.settle_instances(ids, series).await)
    }

    /// Uploads that own indexed instances.
    pub async fn uploads_with_instances(&self) -> Result<Vec<UploadId>, DbError> {
        on!(self, db => db.uploads_with_instances().await)
    }
}
