//! The job database: one SQL adapter for both databases the service runs on, SQLite in the data directory
//! (the default; one process owns it) or PostgreSQL (`database_url = "postgres://…"`; several processes
//! share it). Every statement is written once (runtime-checked queries with `$n` parameters, which both
//! read) and runs on the pool the database was opened with ([`driver`]); what really differs is a fragment
//! of the [`Dialect`] or one branch on [`Database::is_shared`]. Every state change is one guarded `UPDATE …
//! WHERE status = …`, so concurrent transitions cannot both win.
//!
//! Files: this one (opening, Idempotency-Key records, datasets), `jobs` (job rows), `job_store` (the
//! [`JobStore`](super::store::JobStore) port), `uploads` (uploads and series), `blobs` and `retention`
//! (deletions), `rules`, `deliveries` and `instances` (the DICOM node's tables, with what they guarantee
//! on a shared database), `rows` (rows as domain values), `listen` (`LISTEN/NOTIFY` wake-ups, PostgreSQL
//! only), `open` (connecting, and the typed handles [`Db`] and [`PgDb`]).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

mod blobs;
pub mod conformance;
mod deliveries;
pub mod dialect;
mod driver;
mod instances;
mod job_store;
mod jobs;
pub mod listen;
mod node_rows;
mod open;
mod retention;
mod rows;
mod rules;
mod uploads;

pub use dialect::Dialect;
pub use open::{Db, Opened, PgDb, Postgres, Sqlite};

use self::driver::{Pool, Tx, query};
use self::rows::dataset_from_row;
use super::cache::JobCache;
use super::model::{Dataset, IdempotencyKey, Inserted, now_us};
use super::store::to_json;
pub use super::store::{Appended, Completed, DbError, Deleted, UploadDeleted};
use crate::storage::{DatasetId, JobId};

/// The channel on which a new or re-queued job is announced (payload: the job id).
pub const QUEUED_CHANNEL: &str = "ctrecon_queued";
/// The channel on which a request to cancel a running job is announced (payload: the job id).
pub const CANCEL_CHANNEL: &str = "ctrecon_cancel";
/// The channel on which each process relays its job events to the others (payload: JSON, see
/// `jobs::engine::relay`).
pub const EVENTS_CHANNEL: &str = "ctrecon_job_events";

/// The job database (a cheap handle: clones share the pool).
#[derive(Clone, Debug)]
pub struct Database {
    pool: Pool,
    /// The URL a shared database was opened with (for its listener connection).
    url: Option<Arc<str>>,
    /// Job rows cached by this process: only on a database it owns; another process may write any row of a
    /// shared one at any time.
    cache: Option<Arc<JobCache>>,
    /// Changes on every read of [`Database::jobs_generation`] on a shared database, so that nothing
    /// computed from job rows is ever reused there.
    generation: Arc<AtomicU64>,
}

impl Database {
    fn new(pool: Pool, url: Option<&str>) -> Self {
        let shared = pool.dialect().is_shared();
        Self {
            pool,
            url: url.map(Arc::from),
            cache: (!shared).then(Default::default),
            generation: Default::default(),
        }
    }

    /// The dialect of the database this one was opened on.
    pub fn dialect(&self) -> Dialect {
        self.pool.dialect()
    }

    /// Whether other processes may use this database at the same time (PostgreSQL): then a process never
    /// assumes that a running job is its own, and lost workers are found by their leases only.
    pub fn is_shared(&self) -> bool {
        self.dialect().is_shared()
    }

    /// A value that changes after every write of a job (insert, transition, progress, delete): a value
    /// computed from job rows is current while it still has the value read before computing it. On a shared
    /// database it changes at every call (another process may have written any job since).
    pub fn jobs_generation(&self) -> u64 {
        match &self.cache {
            Some(cache) => cache.generation(),
            None => self.generation.fetch_add(1, Ordering::Relaxed),
        }
    }

    /// Forget the cached row of job `id` (after every write of it).
    fn invalidate(&self, id: JobId) {
        if let Some(cache) = &self.cache {
            cache.invalidate(id);
        }
    }

    /// Send `payload` on [`EVENTS_CHANNEL`] (PostgreSQL refuses payloads of 8000 bytes or more); nothing on
    /// a database no other process uses.
    pub async fn notify_event(&self, payload: &str) -> Result<(), DbError> {
        driver::notify(&self.pool, EVENTS_CHANNEL, payload).await?;
        Ok(())
    }

    /// The database answers a trivial query.
    pub async fn ping(&self) -> bool {
        query("SELECT 1").execute(&self.pool).await.is_ok()
    }

    /// Begin the transaction that creates resource `id`, claiming `key` (if any) in it first; `Err` with the
    /// earlier resource when the key was used before.
    async fn begin_claimed(
        &self,
        key: Option<&IdempotencyKey>,
        id: &str,
    ) -> Result<Result<Tx, Inserted>, DbError> {
        let mut tx = self.pool.begin().await?;
        if let Some(key) = key
            && let existing @ Inserted::Existing { .. } = Self::claim_key(&mut tx, key, id).await?
        {
            return Ok(Err(existing));
        }
        Ok(Ok(tx))
    }

    /// Claim `key` for a new resource inside `tx`; `Existing` when the key was used before.
    async fn claim_key(
        tx: &mut Tx,
        key: &IdempotencyKey,
        resource_id: &str,
    ) -> Result<Inserted, DbError> {
        let done = query(
            "INSERT INTO idempotency_keys (route, key, fingerprint, resource_id, created_us)
             VALUES ($1, $2, $3, $4, $5) ON CONFLICT (route, key) DO NOTHING",
        )
        .bind(key.route)
        .bind(&key.key)
        .bind(&key.fingerprint)
        .bind(resource_id)
        .bind(now_us())
        .execute(&mut *tx)
        .await?;
        if done.rows_affected() == 1 {
            return Ok(Inserted::New);
        }
        let row = query(
            "SELECT resource_id, fingerprint FROM idempotency_keys WHERE route = $1 AND key = $2",
        )
        .bind(key.route)
        .bind(&key.key)
        .fetch_one(&mut *tx)
        .await?;
        Ok(Inserted::Existing {
            resource_id: row.try_get("resource_id")?,
            fingerprint: row.try_get("fingerprint")?,
        })
    }

    /// The resource an Idempotency-Key names, if the key was used: `(resource id, fingerprint)`.
    pub async fn idempotency_lookup(
        &self,
        route: &str,
        key: &str,
    ) -> Result<Option<(String, String)>, DbError> {
        let row = query(
            "SELECT resource_id, fingerprint FROM idempotency_keys WHERE route = $1 AND key = $2",
        )
        .bind(route)
        .bind(key)
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| Ok((r.try_get("resource_id")?, r.try_get("fingerprint")?)))
            .transpose()
    }

    pub async fn insert_dataset(
        &self,
        d: &Dataset,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        let mut tx = match self.begin_claimed(key, &d.id.to_string()).await? {
            Ok(tx) => tx,
            Err(existing) => return Ok(existing),
        };
        query(
            "INSERT INTO datasets (id, kind, geometry, shape, dtype, bytes, sha256, phantom, noise, scan, created_us)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11)",
        )
        .bind(d.id.to_string())
        .bind(d.kind.as_str())
        .bind(to_json(&d.geometry))
        .bind(to_json(&d.shape))
        .bind(&d.dtype)
        .bind(d.bytes as i64)
        .bind(&d.sha256)
        .bind(d.phantom.as_ref().map(to_json))
        .bind(d.noise.as_ref().map(to_json))
        .bind(d.scan.as_ref().map(to_json))
        .bind(d.created_us)
        .execute(&mut tx)
        .await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_dataset(&self, id: DatasetId) -> Result<Option<Dataset>, DbError> {
        let row = query("SELECT * FROM datasets WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(dataset_from_row).transpose()
    }
}
