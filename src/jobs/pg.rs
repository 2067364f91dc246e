//! The PostgreSQL adapter of the job database (sqlx, runtime-checked queries), for a database shared by
//! several ctrecon processes: the same tables and the same guarded updates as the SQLite adapter
//! ([`super::repo::Db`]), written for PostgreSQL (`$n` parameters, `FOR UPDATE SKIP LOCKED` claims,
//! `LISTEN/NOTIFY` wake-ups in [`listen`]). Its migrations are `migrations/postgres/`.
//!
//! Unlike the SQLite adapter it keeps no cache of job rows: another process may write any row at any time.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use sqlx::Connection;
use sqlx::postgres::{PgConnection, PgPool, PgPoolOptions, PgRow};
use sqlx::{AssertSqlSafe, Row};

mod blobs;
mod deliveries;
mod instances;
mod job_store;
pub mod listen;
mod retention;
mod rows;
mod rules;
mod uploads;

use rows::{
    SUMMARY_COLUMNS, dataset_from_row, job_from_row, json_col, opt_json_col, summary_from_row,
};

use super::model::{Dataset, Job, JobStatus, JobSummary, now_us};
pub use super::model::{IdempotencyKey, Inserted, JobFilter};
pub use super::store::{Appended, Completed, DbError, UploadDeleted};
use super::store::{corrupt, to_json};
use crate::storage::{DatasetId, JobId};

/// The channel on which a new or re-queued job is announced (payload: the job id).
pub const QUEUED_CHANNEL: &str = "ctrecon_queued";
/// The channel on which a request to cancel a running job is announced (payload: the job id).
pub const CANCEL_CHANNEL: &str = "ctrecon_cancel";
/// The channel on which each process relays its job events to the others (payload: JSON, see
/// `jobs::engine::relay`).
pub const EVENTS_CHANNEL: &str = "ctrecon_job_events";

/// Connections each process keeps at most.
const MAX_CONNECTIONS: u32 = 8;

#[derive(Clone, Debug)]
pub struct PgDb {
    pool: PgPool,
    url: Arc<str>,
    /// Changes on every read of [`PgDb::jobs_generation`]: another process may write any job at any time,
    /// so nothing computed from job rows is ever reused.
    generation: Arc<AtomicU64>,
}

impl PgDb {
    /// Connect to the database at `url` (`postgres://…`) and apply the migrations (concurrent starts are
    /// serialised by sqlx's advisory lock). Fails within `connect_timeout` when the server cannot be
    /// reached.
    pub async fn open(url: &str, connect_timeout: Duration) -> Result<Self, DbError> {
        // One connection first, to say why the server cannot be reached (the pool only times out).
        let unreachable = |reason: String| DbError::Unreachable {
            target: redacted(url),
            reason,
        };
        match tokio::time::timeout(connect_timeout, PgConnection::connect(url)).await {
            Ok(Ok(c)) => {
                let _ = c.close().await;
            }
            Ok(Err(e)) => return Err(unreachable(e.to_string())),
            Err(_) => {
                return Err(unreachable(format!(
                    "no answer within {} s",
                    connect_timeout.as_secs()
                )));
            }
        }
        let pool = PgPoolOptions::new()
            .max_connections(MAX_CONNECTIONS)
            .acquire_timeout(connect_timeout)
            .connect(url)
            .await?;
        sqlx::migrate!("./migrations/postgres").run(&pool).await?;
        Ok(Self {
            pool,
            url: url.into(),
            generation: Default::default(),
        })
    }

    /// The URL this database was opened with (for its listener connection).
    pub(crate) fn url(&self) -> &str {
        &self.url
    }

    /// A value that never repeats: another process may have written any job since the last call, so a
    /// value computed from job rows is never reused.
    pub fn jobs_generation(&self) -> u64 {
        self.generation.fetch_add(1, Ordering::Relaxed)
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
    ) -> Result<Result<sqlx::Transaction<'static, sqlx::Postgres>, Inserted>, DbError> {
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
        tx: &mut sqlx::PgConnection,
        key: &IdempotencyKey,
        resource_id: &str,
    ) -> Result<Inserted, DbError> {
        let done = sqlx::query(
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
        let row = sqlx::query(
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
        let row = sqlx::query(
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
        sqlx::query(
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
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_dataset(&self, id: DatasetId) -> Result<Option<Dataset>, DbError> {
        let row = sqlx::query("SELECT * FROM datasets WHERE id = $1")
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
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, 0, $9)",
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
        notify(&mut tx, QUEUED_CHANNEL, j.id).await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_job(&self, id: JobId) -> Result<Option<Job>, DbError> {
        let row = sqlx::query("SELECT * FROM jobs WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(job_from_row).transpose()
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
    async fn list_rows(&self, columns: &'static str, f: &JobFilter) -> Result<Vec<PgRow>, DbError> {
        // Only fixed fragments enter the SQL text; every value is bound.
        let mut sql = format!("SELECT {columns} FROM jobs WHERE 1 = 1");
        let mut n = 0;
        let mut mark = || {
            n += 1;
            format!("${n}")
        };
        if !f.statuses.is_empty() {
            let marks: Vec<String> = f.statuses.iter().map(|_| mark()).collect();
            sql.push_str(&format!(" AND status IN ({})", marks.join(", ")));
        }
        if f.kind.is_some() {
            sql.push_str(&format!(" AND kind = {}", mark()));
        }
        if f.created_after_us.is_some() {
            sql.push_str(&format!(" AND created_us > {}", mark()));
        }
        if f.created_before_us.is_some() {
            sql.push_str(&format!(" AND created_us < {}", mark()));
        }
        if f.before_id.is_some() {
            sql.push_str(&format!(" AND id < {}", mark()));
        }
        sql.push_str(&format!(" ORDER BY id DESC LIMIT {}", mark()));
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
            "SELECT id, estimate_bytes FROM jobs WHERE status = 'queued' ORDER BY id LIMIT $1",
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
        let mut tx = self.pool.begin().await?;
        let done = sqlx::query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0, started_us = NULL,
                    attempts = GREATEST(attempts - 1, 0), lease_expires_us = NULL
             WHERE id = $1 AND status = 'running' AND cancel_requested = 0 AND attempts = $2",
        )
        .bind(id.to_string())
        .bind(attempt as i64)
        .execute(&mut *tx)
        .await?;
        if done.rows_affected() == 1 {
            notify(&mut tx, QUEUED_CHANNEL, id).await?;
        }
        tx.commit().await?;
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
            "UPDATE jobs SET progress = $1, stage = $2 WHERE id = $3 AND status = 'running' AND attempts = $4",
        )
        .bind(progress as i64)
        .bind(stage)
        .bind(id.to_string())
        .bind(attempt as i64)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// `queued → canceled`. False when the job was not queued.
    pub async fn cancel_queued(&self, id: JobId) -> Result<bool, DbError> {
        let done = sqlx::query(
            "UPDATE jobs SET status = 'canceled', stage = 'canceled', finished_us = $1
             WHERE id = $2 AND status = 'queued'",
        )
        .bind(now_us())
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
    }

    /// Remember that a running job was asked to stop (survives a crash), and tell the process running it
    /// ([`CANCEL_CHANNEL`]); it also learns of it at its next heartbeat.
    pub async fn request_cancel(&self, id: JobId) -> Result<(), DbError> {
        let mut tx = self.pool.begin().await?;
        let done = sqlx::query(
            "UPDATE jobs SET cancel_requested = 1 WHERE id = $1 AND status = 'running'",
        )
        .bind(id.to_string())
        .execute(&mut *tx)
        .await?;
        if done.rows_affected() == 1 {
            notify(&mut tx, CANCEL_CHANNEL, id).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Delete a finished job. False when it does not exist or is still queued or running.
    pub async fn delete_finished(&self, id: JobId) -> Result<bool, DbError> {
        let done = sqlx::query(
            "DELETE FROM jobs WHERE id = $1 AND status IN ('succeeded', 'failed', 'canceled')",
        )
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
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

/// `url` without its password, for messages.
fn redacted(url: &str) -> String {
    let Some(scheme_end) = url.find("://").map(|i| i + 3) else {
        return "the configured database_url".into();
    };
    let rest = &url[scheme_end..];
    match (rest.find('@'), rest.find(':')) {
        (Some(at), Some(colon)) if colon < at => {
            format!(
                "{}{}:***{}",
                &url[..scheme_end],
                &rest[..colon],
                &rest[at..]
            )
        }
        _ => url.to_string(),
    }
}

/// Announce `id` on `channel` when `tx` commits (a notification is delivered only if its transaction
/// commits, and only once).
impl PgDb {
    /// Send `payload` on [`EVENTS_CHANNEL`] (PostgreSQL refuses payloads of 8000 bytes or more).
    pub async fn notify_event(&self, payload: &str) -> Result<(), DbError> {
        sqlx::query("SELECT pg_notify($1, $2)")
            .bind(EVENTS_CHANNEL)
            .bind(payload)
            .execute(&self.pool)
            .await?;
        Ok(())
    }
}

async fn notify(tx: &mut sqlx::PgConnection, channel: &str, id: JobId) -> Result<(), DbError> {
    sqlx::query("SELECT pg_notify($1, $2)")
        .bind(channel)
        .bind(id.to_string())
        .execute(&mut *tx)
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_password_never_reaches_a_message() {
        assert_eq!(
            super::redacted("postgres://ctrecon:s3cret@db:5432/ctrecon"),
            "postgres://ctrecon:***@db:5432/ctrecon"
        );
        assert_eq!(
            super::redacted("postgres://ctrecon@db/ctrecon"),
            "postgres://ctrecon@db/ctrecon"
        );
    }
}
