//! The SQL repository (SQLite through sqlx, runtime-checked queries): datasets, jobs and their state
//! transitions, Idempotency-Key records. Every state change is one guarded `UPDATE … WHERE status = …`,
//! so concurrent transitions cannot both win.

use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow,
    SqliteSynchronous,
};
use sqlx::{AssertSqlSafe, Row};

mod blobs;
mod deliveries;
mod instances;
mod job_store;
mod retention;
mod rows;
mod rules;
mod uploads;

pub use super::model::{IndexScope, IndexedInstance, NewInstance, StoredInstance};
pub use super::store::{Appended, Completed, DbError, Deleted, UploadDeleted};
pub(crate) use super::store::{corrupt, product_indexes, to_json};
use rows::*;

use super::cache::JobCache;
use super::model::{Dataset, Job, JobStatus, JobSummary, now_us};
pub use super::model::{IdempotencyKey, Inserted, JobFilter};
use crate::error_code::Problem;
use crate::storage::{DatasetId, JobId};

#[derive(Clone, Debug)]
pub struct Db {
    pool: SqlitePool,
    cache: std::sync::Arc<JobCache>,
}

impl Db {
    /// A transaction that takes the write lock at its start (`BEGIN IMMEDIATE`). A deferred transaction that
    /// reads and then writes fails at once with `SQLITE_BUSY` when another connection wrote in between (WAL
    /// cannot upgrade a stale read snapshot, and the busy timeout does not apply); an immediate one waits for
    /// the lock within the busy timeout instead. Every transaction of this adapter writes.
    async fn write_tx(&self) -> Result<sqlx::Transaction<'static, sqlx::Sqlite>, sqlx::Error> {
        self.pool.begin_with("BEGIN IMMEDIATE").await
    }

    /// Open (creating if needed) the database file and apply the migrations.
    pub async fn open(path: &Path) -> Result<Self, DbError> {
        let options = SqliteConnectOptions::from_str("sqlite://")?
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(options)
            .await?;
        sqlx::migrate!("./migrations").run(&pool).await?;
        Ok(Self {
            pool,
            cache: Default::default(),
        })
    }

    /// A counter that changes after every write of a job (insert, transition, progress, delete): a value
    /// computed from job rows is current while the counter still has the value read before computing it.
    pub fn jobs_generation(&self) -> u64 {
        self.cache.generation()
    }

    /// The database answers a trivial query.
    pub async fn ping(&self) -> bool {
        sqlx::query("SELECT 1").execute(&self.pool).await.is_ok()
    }

    /// Begin the transaction that creates resource `id`, claiming `key` (if any) in it first; `Err` with the
    /// earlier resource when the key was used before.
    async fn begin_claimed(
        &self,
        key: Option<&IdempotencyKey>,
        id: &str,
    ) -> Result<Result<sqlx::Transaction<'static, sqlx::Sqlite>, Inserted>, DbError> {
        let mut tx = self.write_tx().await?;
        if let Some(key) = key
            && let existing @ Inserted::Existing { .. } = Self::claim_key(&mut tx, key, id).await?
        {
            return Ok(Err(existing));
        }
        Ok(Ok(tx))
    }

    /// Claim `key` for a new resource inside `tx`; `Existing` when the key was used before.
    async fn claim_key(
        tx: &mut sqlx::SqliteConnection,
        key: &IdempotencyKey,
        resource_id: &str,
    ) -> Result<Inserted, DbError> {
        let done = sqlx::query(
            "INSERT INTO idempotency_keys (route, key, fingerprint, resource_id, created_us)
             VALUES (?, ?, ?, ?, ?) ON CONFLICT (route, key) DO NOTHING",
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
        let row = sqlx::query(
            "SELECT resource_id, fingerprint FROM idempotency_keys WHERE route = ? AND key = ?",
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
        let row = sqlx::query(
            "SELECT resource_id, fingerprint FROM idempotency_keys WHERE route = ? AND key = ?",
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
        sqlx::query(
            "INSERT INTO datasets (id, kind, geometry, shape, dtype, bytes, sha256, phantom, noise, scan, created_us)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_dataset(&self, id: DatasetId) -> Result<Option<Dataset>, DbError> {
        let row = sqlx::query("SELECT * FROM datasets WHERE id = ?")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(dataset_from_row).transpose()
    }

    pub async fn insert_job(
        &self,
        j: &Job,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        let mut tx = match self.begin_claimed(key, &j.id.to_string()).await? {
            Ok(tx) => tx,
            Err(existing) => return Ok(existing),
        };
        sqlx::query(
            "INSERT INTO jobs (id, kind, status, progress, stage, spec, dataset_id, estimate_bytes,
                               attempts, created_us)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, 0, ?)",
        )
        .bind(j.id.to_string())
        .bind(&j.kind)
        .bind(j.status.as_str())
        .bind(j.progress as i64)
        .bind(&j.stage)
        .bind(to_json(&j.request))
        .bind(j.request.input_id())
        .bind(j.estimate_bytes as i64)
        .bind(j.created_us)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        // A new job changes every list it falls in.
        self.cache.invalidate(j.id);
        Ok(Inserted::New)
    }

    pub async fn get_job(&self, id: JobId) -> Result<Option<Job>, DbError> {
        if let Some(job) = self.cache.get(id) {
            return Ok(Some(job));
        }
        let generation = self.cache.generation();
        let row = sqlx::query("SELECT * FROM jobs WHERE id = ?")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        let job = row.as_ref().map(job_from_row).transpose()?;
        if let Some(j) = &job {
            self.cache.fill(j, generation);
        }
        Ok(job)
    }

    /// Jobs matching `f`, newest first, at most `f.limit`.
    pub async fn list_jobs(&self, f: &JobFilter) -> Result<Vec<Job>, DbError> {
        let rows = self.list_rows("*", f).await?;
        rows.iter().map(job_from_row).collect()
    }

    /// The summaries of the jobs matching `f`, newest first, at most `f.limit`: neither the request nor the
    /// result is read, only what the result links need (SQLite's JSON functions look it up).
    pub async fn list_job_summaries(&self, f: &JobFilter) -> Result<Vec<JobSummary>, DbError> {
        let rows = self.list_rows(SUMMARY_COLUMNS, f).await?;
        rows.iter().map(summary_from_row).collect()
    }

    /// The rows of `columns` (a fixed list) of the jobs matching `f`.
    async fn list_rows(
        &self,
        columns: &'static str,
        f: &JobFilter,
    ) -> Result<Vec<SqliteRow>, DbError> {
        // Only fixed fragments enter the SQL text; every value is bound.
        let mut sql = format!("SELECT {columns} FROM jobs WHERE 1 = 1");
        if !f.statuses.is_empty() {
            let marks = vec!["?"; f.statuses.len()].join(", ");
            sql.push_str(&format!(" AND status IN ({marks})"));
        }
        if f.kind.is_some() {
            sql.push_str(" AND kind = ?");
        }
        if f.created_after_us.is_some() {
            sql.push_str(" AND created_us > ?");
        }
        if f.created_before_us.is_some() {
            sql.push_str(" AND created_us < ?");
        }
        if f.before_id.is_some() {
            sql.push_str(" AND id < ?");
        }
        sql.push_str(" ORDER BY id DESC LIMIT ?");
        let mut q = sqlx::query(AssertSqlSafe(sql));
        for s in &f.statuses {
            q = q.bind(s.as_str());
        }
        if let Some(k) = &f.kind {
            q = q.bind(k.clone());
        }
        if let Some(t) = f.created_after_us {
            q = q.bind(t);
        }
        if let Some(t) = f.created_before_us {
            q = q.bind(t);
        }
        if let Some(id) = f.before_id {
            q = q.bind(id.to_string());
        }
        q = q.bind(f.limit as i64);
        Ok(q.fetch_all(&self.pool).await?)
    }

    /// Queued jobs in submission order: `(id, estimate bytes)`.
    pub async fn queued(&self, limit: u32) -> Result<Vec<(JobId, u64)>, DbError> {
        let rows = sqlx::query(
            "SELECT id, estimate_bytes FROM jobs WHERE status = 'queued' ORDER BY id LIMIT ?",
        )
        .bind(limit as i64)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let id: String = r.try_get("id")?;
                let est: i64 = r.try_get("estimate_bytes")?;
                Ok((
                    JobId::parse(&id).map_err(|e| corrupt("jobs", e))?,
                    est.max(0) as u64,
                ))
            })
            .collect()
    }

    /// `running → queued` by a graceful hand-back (the server is stopping): the run is given back, not
    /// spent, so the attempt its claim counted is returned. False when the job was not running, or was asked
    /// to cancel (it then ends canceled).
    pub async fn hand_back(&self, id: JobId, attempt: u32) -> Result<bool, DbError> {
        let done = sqlx::query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0, started_us = NULL,
                    attempts = MAX(attempts - 1, 0), lease_expires_us = NULL
             WHERE id = ? AND status = 'running' AND cancel_requested = 0 AND attempts = ?",
        )
        .bind(id.to_string())
        .bind(attempt as i64)
        .execute(&self.pool)
        .await?;
        self.cache.invalidate(id);
        Ok(done.rows_affected() == 1)
    }

    /// Persist the progress of a job running its `attempt` (a stale worker's progress is ignored).
    pub async fn set_progress(
        &self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &str,
    ) -> Result<(), DbError> {
        sqlx::query(
            "UPDATE jobs SET progress = ?, stage = ? WHERE id = ? AND status = 'running' AND attempts = ?",
        )
        .bind(progress as i64)
        .bind(stage)
        .bind(id.to_string())
        .bind(attempt as i64)
            .execute(&self.pool)
            .await?;
        self.cache.invalidate(id);
        Ok(())
    }

    /// `queued → canceled`. False when the job was not queued.
    pub async fn cancel_queued(&self, id: JobId) -> Result<bool, DbError> {
        let done = sqlx::query(
            "UPDATE jobs SET status = 'canceled', stage = 'canceled', finished_us = ?
             WHERE id = ? AND status = 'queued'",
        )
        .bind(now_us())
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        self.cache.invalidate(id);
        Ok(done.rows_affected() == 1)
    }

    /// Remember that a running job was asked to stop (survives a crash).
    pub async fn request_cancel(&self, id: JobId) -> Result<(), DbError> {
        sqlx::query("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND status = 'running'")
            .bind(id.to_string())
            .execute(&self.pool)
            .await?;
        self.cache.invalidate(id);
        Ok(())
    }

    /// After a crash (or a shutdown that did not get to hand a job back): jobs left `running` go back to
    /// `queued`, keeping the attempt their claim counted, except those asked to cancel (→ canceled) and those
    /// already started `max_attempts` times (→ failed). Returns `(requeued, failed)`.
    pub async fn recover(&self, max_attempts: u32) -> Result<(u64, u64), DbError> {
        let now = now_us();
        sqlx::query(
            "UPDATE jobs SET status = 'canceled', stage = 'canceled', finished_us = ?
             WHERE status = 'running' AND cancel_requested = 1",
        )
        .bind(now)
        .execute(&self.pool)
        .await?;
        let problem = Problem::new(
            crate::error_code::ErrorCode::AttemptsExhausted,
            format!("the server stopped while running this job {max_attempts} times"),
        );
        let failed = sqlx::query(
            "UPDATE jobs SET status = 'failed', stage = 'failed', finished_us = ?, error = ?
             WHERE status = 'running' AND attempts >= ?",
        )
        .bind(now)
        .bind(to_json(&problem))
        .bind(max_attempts as i64)
        .execute(&self.pool)
        .await?
        .rows_affected();
        let requeued = sqlx::query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0
             WHERE status = 'running'",
        )
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok((requeued, failed))
    }

    /// Number of jobs in each status.
    pub async fn counts(&self) -> Result<Vec<(JobStatus, i64)>, DbError> {
        let rows = sqlx::query("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status")
            .fetch_all(&self.pool)
            .await?;
        let mut out: Vec<(JobStatus, i64)> = JobStatus::ALL.iter().map(|&s| (s, 0)).collect();
        for r in rows {
            let s: String = r.try_get("status")?;
            let n: i64 = r.try_get("n")?;
            if let Some(slot) = out.iter_mut().find(|(st, _)| st.as_str() == s) {
                slot.1 = n;
            }
        }
        Ok(out)
    }
}
