//! The job database the service runs on: SQLite in the data directory (the default; one process owns it)
//! or PostgreSQL (`database_url = "postgres://…"`; several processes share it). Every front door and the
//! engine hold a [`Database`]; each call goes to the adapter it was opened with, which implement the same
//! operations with the same guards ([`super::repo::Db`], [`super::pg::PgDb`]).
//!
//! The DICOM node's tables (rules, runs, deliveries, the instance index) are dispatched in [`node`], with
//! what they guarantee on a shared database. A table only the SQLite adapter has is reached through
//! [`Database::sqlite`]; its PostgreSQL twin is a migration under `migrations/postgres/` and the same
//! methods on `PgDb`, dispatched here.

use std::collections::HashSet;
use std::path::Path;
use std::time::Duration;

use futures_util::future::BoxFuture;

use super::lifecycle::{JobState, Lease, Outcome};
use super::model::{
    Dataset, IdempotencyKey, Inserted, Job, JobFilter, JobStatus, JobSummary, SeriesRecord,
    UploadRecord,
};
use super::pg::PgDb;
use super::repo::{Appended, Completed, Db, DbError, Deleted, UploadDeleted};
use super::store::{Expired, JobStore, Renewed, StoreResult};
use crate::storage::sweep::BlobKind;
use crate::storage::{DatasetId, JobId, SeriesId, UploadId};

pub mod conformance;
pub mod node;

/// The job database: one adapter or the other.
#[derive(Clone, Debug)]
pub enum Database {
    Sqlite(Db),
    Postgres(PgDb),
}

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
    /// Open the database `url` names (`postgres://…`), or SQLite at `sqlite_path` when there is none, and
    /// apply its migrations. A PostgreSQL server that cannot be reached fails within `connect_timeout`.
    pub async fn open(
        url: Option<&str>,
        sqlite_path: &Path,
        connect_timeout: Duration,
    ) -> Result<Self, DbError> {
        Ok(match url {
            Some(url) => Database::Postgres(PgDb::open(url, connect_timeout).await?),
            None => Database::Sqlite(Db::open(sqlite_path).await?),
        })
    }

    /// Whether other processes may use this database at the same time (PostgreSQL): then a process never
    /// assumes that a running job is its own, and lost workers are found by their leases only.
    pub fn is_shared(&self) -> bool {
        matches!(self, Database::Postgres(_))
    }

    /// The SQLite adapter, for tables that have no PostgreSQL twin yet.
    pub fn sqlite(&self) -> Option<&Db> {
        match self {
            Database::Sqlite(db) => Some(db),
            Database::Postgres(_) => None,
        }
    }

    /// A value that changes after every write of a job (see [`Db::jobs_generation`]); on PostgreSQL it
    /// changes at every call.
    pub fn jobs_generation(&self) -> u64 {
        on!(self, db => db.jobs_generation())
    }

    pub async fn ping(&self) -> bool {
        on!(self, db => db.ping().await)
    }

    pub async fn idempotency_lookup(
        &self,
        route: &str,
        key: &str,
    ) -> Result<Option<(String, String)>, DbError> {
        on!(self, db => db.idempotency_lookup(route, key).await)
    }

    pub async fn insert_dataset(
        &self,
        d: &Dataset,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        on!(self, db => db.insert_dataset(d, key).await)
    }

    pub async fn get_dataset(&self, id: DatasetId) -> Result<Option<Dataset>, DbError> {
        on!(self, db => db.get_dataset(id).await)
    }

    pub async fn insert_job(
        &self,
        j: &Job,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        on!(self, db => db.insert_job(j, key).await)
    }

    pub async fn get_job(&self, id: JobId) -> Result<Option<Job>, DbError> {
        on!(self, db => db.get_job(id).await)
    }

    pub async fn list_jobs(&self, f: &JobFilter) -> Result<Vec<Job>, DbError> {
        on!(self, db => db.list_jobs(f).await)
    }

    pub async fn list_job_summaries(&self, f: &JobFilter) -> Result<Vec<JobSummary>, DbError> {
        on!(self, db => db.list_job_summaries(f).await)
    }

    pub async fn queued(&self, limit: u32) -> Result<Vec<(JobId, u64)>, DbError> {
        on!(self, db => db.queued(limit).await)
    }

    pub async fn cancel_queued(&self, id: JobId) -> Result<bool, DbError> {
        on!(self, db => db.cancel_queued(id).await)
    }

    pub async fn request_cancel(&self, id: JobId) -> Result<(), DbError> {
        on!(self, db => db.request_cancel(id).await)
    }

    /// After a crash of the one process that owns a SQLite database: see [`Db::recover`]. Nothing on a
    /// shared database, where the jobs left running belong to live workers until their leases expire.
    pub async fn recover(&self, max_attempts: u32) -> Result<(u64, u64), DbError> {
        match self {
            Database::Sqlite(db) => db.recover(max_attempts).await,
            Database::Postgres(_) => Ok((0, 0)),
        }
    }

    /// Ids of jobs whose result directories may hold partial files after a crash of the one process that
    /// owns a SQLite database; none on a shared database (another process may be writing them).
    pub async fn unfinished_ids(&self) -> Result<Vec<JobId>, DbError> {
        match self {
            Database::Sqlite(db) => db.unfinished_ids().await,
            Database::Postgres(_) => Ok(Vec::new()),
        }
    }

    pub async fn delete_finished(&self, id: JobId) -> Result<bool, DbError> {
        on!(self, db => db.delete_finished(id).await)
    }

    pub async fn delete_jobs_finished_before(&self, before_us: i64) -> Result<Vec<JobId>, DbError> {
        on!(self, db => db.delete_jobs_finished_before(before_us).await)
    }

    pub async fn delete_datasets_created_before(
        &self,
        before_us: i64,
    ) -> Result<Vec<DatasetId>, DbError> {
        on!(self, db => db.delete_datasets_created_before(before_us).await)
    }

    pub async fn delete_series_created_before(
        &self,
        before_us: i64,
    ) -> Result<Vec<SeriesId>, DbError> {
        on!(self, db => db.delete_series_created_before(before_us).await)
    }

    pub async fn delete_uploads_without_series(
        &self,
        before_us: i64,
    ) -> Result<Vec<UploadId>, DbError> {
        on!(self, db => db.delete_uploads_without_series(before_us).await)
    }

    pub async fn insert_completed_upload(
        &self,
        id: UploadId,
        instances: u32,
        bytes: u64,
        outcome: &serde_json::Value,
        series: &[SeriesRecord],
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        on!(self, db => db.insert_completed_upload(id, instances, bytes, outcome, series, key).await)
    }

    pub async fn insert_open_upload(
        &self,
        id: UploadId,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        on!(self, db => db.insert_open_upload(id, key).await)
    }

    pub async fn get_upload(&self, id: UploadId) -> Result<Option<UploadRecord>, DbError> {
        on!(self, db => db.get_upload(id).await)
    }

    pub async fn append_upload_file(
        &self,
        id: UploadId,
        sha256: &str,
        label: &str,
        bytes: u64,
        series_uid: &str,
        max_bytes: u64,
    ) -> Result<Appended, DbError> {
        on!(self, db => db.append_upload_file(id, sha256, label, bytes, series_uid, max_bytes).await)
    }

    pub async fn delete_open_upload(&self, id: UploadId) -> Result<UploadDeleted, DbError> {
        on!(self, db => db.delete_open_upload(id).await)
    }

    pub async fn upload_files(&self, id: UploadId) -> Result<Vec<(String, String)>, DbError> {
        on!(self, db => db.upload_files(id).await)
    }

    pub async fn complete_upload(
        &self,
        id: UploadId,
        instances: u32,
        outcome: &serde_json::Value,
        series: &[SeriesRecord],
    ) -> Result<Completed, DbError> {
        on!(self, db => db.complete_upload(id, instances, outcome, series).await)
    }

    pub async fn get_series(&self, id: SeriesId) -> Result<Option<SeriesRecord>, DbError> {
        on!(self, db => db.get_series(id).await)
    }

    /// The stored series of Series Instance UID `series_uid`, newest first.
    pub async fn series_with_uid(&self, series_uid: &str) -> Result<Vec<SeriesRecord>, DbError> {
        on!(self, db => db.series_with_uid(series_uid).await)
    }

    pub async fn counts(&self) -> Result<Vec<(JobStatus, i64)>, DbError> {
        on!(self, db => db.counts().await)
    }

    pub async fn blob_missing(&self, kind: BlobKind, id: &str) -> Result<bool, DbError> {
        on!(self, db => db.blob_missing(kind, id).await)
    }

    pub async fn delete_series(&self, id: SeriesId) -> Result<Deleted, DbError> {
        on!(self, db => db.delete_series(id).await)
    }

    pub async fn delete_dataset(&self, id: DatasetId) -> Result<Deleted, DbError> {
        on!(self, db => db.delete_dataset(id).await)
    }

    pub(crate) async fn owner_ids(&self, kind: BlobKind) -> Result<HashSet<String>, DbError> {
        on!(self, db => db.owner_ids(kind).await)
    }

    pub(crate) async fn mark_missing(&self, kind: BlobKind, id: &str) -> Result<(), DbError> {
        on!(self, db => db.mark_missing(kind, id).await)
    }
}

impl JobStore for Database {
    fn insert<'a>(
        &'a self,
        job: &'a Job,
        key: Option<&'a IdempotencyKey>,
    ) -> BoxFuture<'a, StoreResult<Inserted>> {
        on!(self, db => JobStore::insert(db, job, key))
    }

    fn get(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<Job>>> {
        on!(self, db => JobStore::get(db, id))
    }

    fn state(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<JobState>>> {
        on!(self, db => JobStore::state(db, id))
    }

    fn list<'a>(&'a self, filter: &'a JobFilter) -> BoxFuture<'a, StoreResult<Vec<Job>>> {
        on!(self, db => JobStore::list(db, filter))
    }

    fn queued(&self, limit: u32) -> BoxFuture<'_, StoreResult<Vec<(JobId, u64)>>> {
        on!(self, db => JobStore::queued(db, limit))
    }

    fn claim(&self, id: JobId, lease: Lease) -> BoxFuture<'_, StoreResult<u32>> {
        on!(self, db => JobStore::claim(db, id, lease))
    }

    fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        lease: Lease,
    ) -> BoxFuture<'_, StoreResult<Renewed>> {
        on!(self, db => JobStore::heartbeat(db, id, attempt, lease))
    }

    fn set_progress<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &'a str,
    ) -> BoxFuture<'a, StoreResult<()>> {
        on!(self, db => JobStore::set_progress(db, id, attempt, progress, stage))
    }

    fn hand_back(&self, id: JobId, attempt: u32) -> BoxFuture<'_, StoreResult<()>> {
        on!(self, db => JobStore::hand_back(db, id, attempt))
    }

    fn expire_leases(&self, now_us: i64, max_attempts: u32) -> BoxFuture<'_, StoreResult<Expired>> {
        on!(self, db => JobStore::expire_leases(db, now_us, max_attempts))
    }

    fn finish<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        outcome: &'a Outcome,
    ) -> BoxFuture<'a, StoreResult<()>> {
        on!(self, db => JobStore::finish(db, id, attempt, outcome))
    }

    fn cancel_queued(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        on!(self, db => JobStore::cancel_queued(db, id))
    }

    fn request_cancel(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        on!(self, db => JobStore::request_cancel(db, id))
    }

    fn delete_finished(&self, id: JobId) -> BoxFuture<'_, StoreResult<bool>> {
        on!(self, db => JobStore::delete_finished(db, id))
    }
}

impl From<Db> for Database {
    fn from(db: Db) -> Self {
        Database::Sqlite(db)
    }
}

impl From<PgDb> for Database {
    fn from(db: PgDb) -> Self {
        Database::Postgres(db)
    }
}
