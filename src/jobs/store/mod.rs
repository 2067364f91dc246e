//! The `JobStore` port: where jobs live, how they are queued, claimed under a lease, moved through their
//! lifecycle and listed. The SQL adapter is [`super::Database`], one for SQLite (the default) and PostgreSQL
//! (also reached as [`super::Db`] and [`super::PgDb`], a database opened on one of them); tests hold an
//! in-memory one. [`conformance`] is the suite every adapter must pass.
//!
//! Every transition is checked against [`lifecycle::transition`](super::lifecycle::transition) and applied by
//! the adapter as one guarded update, so two racing transitions cannot both win; an illegal one is an
//! [`StoreError::Illegal`] error and changes nothing. Methods return boxed futures so a front door can hold
//! any adapter as `Arc<dyn JobStore>`.

pub mod conformance;
mod records;

pub use records::*;

use futures_util::future::BoxFuture;

use super::lifecycle::{IllegalTransition, JobState, Lease, Outcome};
use super::model::{IdempotencyKey, Inserted, Job, JobFilter};
use crate::storage::JobId;

/// Why a store operation failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The lifecycle forbids the transition from the job's current status (nothing was changed).
    #[error(transparent)]
    Illegal(#[from] IllegalTransition),
    /// A heartbeat, progress or finish for an attempt that no longer holds the job (its lease expired and
    /// it was re-queued or claimed again, or it finished): the worker must stop, and its outcome is not
    /// recorded.
    #[error("the job's lease was lost")]
    LeaseLost,
    /// The backend failed (logged; answered as an internal error).
    #[error("job store backend: {0}")]
    Backend(Box<dyn std::error::Error + Send + Sync>),
}

pub type StoreResult<T> = Result<T, StoreError>;

/// Jobs re-queued or failed by [`JobStore::expire_leases`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Expired {
    /// Back to `queued`, keeping the attempt the lost run spent.
    pub requeued: Vec<JobId>,
    /// `failed` (`attempts_exhausted`): they had been claimed `max_attempts` times.
    pub failed: Vec<JobId>,
}

/// The answer to a heartbeat.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Renewed {
    /// A client asked to cancel the job: the worker should stop it.
    pub cancel_requested: bool,
}

/// The job store port.
pub trait JobStore: Send + Sync {
    /// Insert a new `queued` job, claiming `key` (if any) in the same transaction; `Existing` when the key
    /// was used before (nothing is inserted).
    fn insert<'a>(
        &'a self,
        job: &'a Job,
        key: Option<&'a IdempotencyKey>,
    ) -> BoxFuture<'a, StoreResult<Inserted>>;

    fn get(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<Job>>>;

    /// The typed state of a job (with its attempt and lease when running).
    fn state(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<JobState>>>;

    /// Jobs matching `filter`, newest first, at most `filter.limit`.
    fn list<'a>(&'a self, filter: &'a JobFilter) -> BoxFuture<'a, StoreResult<Vec<Job>>>;

    /// Queued jobs in submission order (oldest first): `(id, memory estimate in bytes)`.
    fn queued(&self, limit: u32) -> BoxFuture<'_, StoreResult<Vec<(JobId, u64)>>>;

    /// `queued → running`: counts an attempt and takes `lease`. Returns the attempt number (1-based).
    fn claim(&self, id: JobId, lease: Lease) -> BoxFuture<'_, StoreResult<u32>>;

    /// Renew the lease of a running job's `attempt` (a worker proving it is alive); the answer says whether
    /// a client asked to cancel the job (possibly through another process). [`StoreError::LeaseLost`] when
    /// the job is no longer running that attempt (its lease expired and another worker claimed it, or it
    /// finished).
    fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        lease: Lease,
    ) -> BoxFuture<'_, StoreResult<Renewed>>;

    /// Persist the progress (0–99) and stage of a job running its `attempt`; ignored otherwise (a stale
    /// worker's progress never overwrites the current run's).
    fn set_progress<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &'a str,
    ) -> BoxFuture<'a, StoreResult<()>>;

    /// `running → queued` for a graceful stop of the run of `attempt`: the attempt is returned. Illegal when
    /// the job is not running or a client asked to cancel it (it then ends `canceled`);
    /// [`StoreError::LeaseLost`] when it runs another attempt.
    fn hand_back(&self, id: JobId, attempt: u32) -> BoxFuture<'_, StoreResult<()>>;

    /// `running → queued` for every job whose lease expired before `now_us` (its attempt kept), or
    /// `running → failed` for those already claimed `max_attempts` times.
    fn expire_leases(&self, now_us: i64, max_attempts: u32) -> BoxFuture<'_, StoreResult<Expired>>;

    /// `running → succeeded | failed | canceled` for the run of `attempt`, recording the outcome. Illegal
    /// when the job is not running; [`StoreError::LeaseLost`] when it runs another attempt (this worker's
    /// lease expired and the job was claimed again): nothing is recorded.
    fn finish<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        outcome: &'a Outcome,
    ) -> BoxFuture<'a, StoreResult<()>>;

    /// `queued → canceled`.
    fn cancel_queued(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>>;

    /// Remember that a running job was asked to stop (survives a crash); no effect on other states.
    fn request_cancel(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>>;

    /// Delete a finished job; false when there is no such job or it is queued or running.
    fn delete_finished(&self, id: JobId) -> BoxFuture<'_, StoreResult<bool>>;
}
