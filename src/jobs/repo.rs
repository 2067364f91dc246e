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

use super::model::{Dataset, DatasetKind, Job, JobResult, JobStatus, now_us};
use crate::error_code::Problem;
use crate::storage::{DatasetId, JobId};

/// A database failure (logged; answered as a 500 without detail).
#[derive(Debug, thiserror::Error)]
pub enum DbError {
    #[error(transparent)]
    Sql(#[from] sqlx::Error),
    #[error(transparent)]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("corrupt row in {table}: {reason}")]
    Corrupt { table: &'static str, reason: String },
}

/// An Idempotency-Key record to insert with a new resource.
#[derive(Debug, Clone)]
pub struct IdempotencyKey {
    pub route: &'static str,
    pub key: String,
    pub fingerprint: String,
}

/// Outcome of an insert guarded by an Idempotency-Key.
#[derive(Debug, Clone, PartialEq)]
pub enum Inserted {
    New,
    /// The key was already used: the earlier resource id and request fingerprint.
    Existing {
        resource_id: String,
        fingerprint: String,
    },
}

/// Filters of `GET /v1/jobs`.
#[derive(Debug, Clone, Default)]
pub struct JobFilter {
    pub statuses: Vec<JobStatus>,
    pub kind: Option<String>,
    pub created_after_us: Option<i64>,
    pub created_before_us: Option<i64>,
    /// Return jobs older than this one (ids are time-ordered).
    pub before_id: Option<JobId>,
    pub limit: u32,
}

#[derive(Clone, Debug)]
pub struct Db {
    pool: SqlitePool,
}

fn corrupt(table: &'static str, reason: impl ToString) -> DbError {
    DbError::Corrupt {
        table,
        reason: reason.to_string(),
    }
}

fn json_col<T: serde::de::DeserializeOwned>(
    row: &SqliteRow,
    col: &str,
    table: &'static str,
) -> Result<T, DbError> {
    let text: String = row.try_get(col)?;
    serde_json::from_str(&text).map_err(|e| corrupt(table, format!("{col}: {e}")))
}

fn opt_json_col<T: serde::de::DeserializeOwned>(
    row: &SqliteRow,
    col: &str,
    table: &'static str,
) -> Result<Option<T>, DbError> {
    let text: Option<String> = row.try_get(col)?;
    text.map(|t| serde_json::from_str(&t).map_err(|e| corrupt(table, format!("{col}: {e}"))))
        .transpose()
}

fn to_json<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "null".into())
}

fn dataset_from_row(row: &SqliteRow) -> Result<Dataset, DbError> {
    let id: String = row.try_get("id")?;
    let kind: String = row.try_get("kind")?;
    let bytes: i64 = row.try_get("bytes")?;
    Ok(Dataset {
        id: DatasetId::parse(&id).map_err(|e| corrupt("datasets", e))?,
        kind: match kind.as_str() {
            "upload" => DatasetKind::Upload,
            "simulation" => DatasetKind::Simulation,
            other => return Err(corrupt("datasets", format!("kind {other}"))),
        },
        geometry: json_col(row, "geometry", "datasets")?,
        shape: json_col(row, "shape", "datasets")?,
        dtype: row.try_get("dtype")?,
        bytes: bytes as u64,
        sha256: row.try_get("sha256")?,
        phantom: opt_json_col(row, "phantom", "datasets")?,
        noise: opt_json_col(row, "noise", "datasets")?,
        created_us: row.try_get("created_us")?,
    })
}

fn job_from_row(row: &SqliteRow) -> Result<Job, DbError> {
    let id: String = row.try_get("id")?;
    let status: String = row.try_get("status")?;
    let progress: i64 = row.try_get("progress")?;
    let estimate: i64 = row.try_get("estimate_bytes")?;
    let attempts: i64 = row.try_get("attempts")?;
    let cancel: i64 = row.try_get("cancel_requested")?;
    Ok(Job {
        id: JobId::parse(&id).map_err(|e| corrupt("jobs", e))?,
        kind: row.try_get("kind")?,
        status: JobStatus::parse(&status)
            .ok_or_else(|| corrupt("jobs", format!("status {status}")))?,
        progress: progress.clamp(0, 100) as u8,
        stage: row.try_get("stage")?,
        request: json_col(row, "spec", "jobs")?,
        estimate_bytes: estimate.max(0) as u64,
        attempts: attempts.max(0) as u32,
        cancel_requested: cancel != 0,
        error: opt_json_col::<Problem>(row, "error", "jobs")?,
        result: opt_json_col::<JobResult>(row, "result", "jobs")?,
        created_us: row.try_get("created_us")?,
        started_us: row.try_get("started_us")?,
        finished_us: row.try_get("finished_us")?,
    })
}

impl Db {
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
        Ok(Self { pool })
    }

    /// The database answers a trivial query.
    pub async fn ping(&self) -> bool {
        sqlx::query("SELECT 1").execute(&self.pool).await.is_ok()
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
        let mut tx = self.pool.begin().await?;
        if let Some(key) = key
            && let existing @ Inserted::Existing { .. } =
                Self::claim_key(&mut tx, key, &d.id.to_string()).await?
        {
            return Ok(existing);
        }
        sqlx::query(
            "INSERT INTO datasets (id, kind, geometry, shape, dtype, bytes, sha256, phantom, noise, created_us)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
        let mut tx = self.pool.begin().await?;
        if let Some(key) = key
            && let existing @ Inserted::Existing { .. } =
                Self::claim_key(&mut tx, key, &j.id.to_string()).await?
        {
            return Ok(existing);
        }
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
        .bind(j.request.input.to_string())
        .bind(j.estimate_bytes as i64)
        .bind(j.created_us)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_job(&self, id: JobId) -> Result<Option<Job>, DbError> {
        let row = sqlx::query("SELECT * FROM jobs WHERE id = ?")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(job_from_row).transpose()
    }

    /// Jobs matching `f`, newest first, at most `f.limit`.
    pub async fn list_jobs(&self, f: &JobFilter) -> Result<Vec<Job>, DbError> {
        // Only fixed fragments enter the SQL text; every value is bound.
        let mut sql = String::from("SELECT * FROM jobs WHERE 1 = 1");
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
        let rows = q.fetch_all(&self.pool).await?;
        rows.iter().map(job_from_row).collect()
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

    /// `queued → running`, counting the attempt. False when the job was not queued.
    pub async fn claim(&self, id: JobId) -> Result<bool, DbError> {
        let done = sqlx::query(
            "UPDATE jobs SET status = 'running', attempts = attempts + 1, started_us = ?,
                    progress = 0, stage = 'starting'
             WHERE id = ? AND status = 'queued'",
        )
        .bind(now_us())
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
    }

    /// Persist the progress of a running job.
    pub async fn set_progress(&self, id: JobId, progress: u8, stage: &str) -> Result<(), DbError> {
        sqlx::query("UPDATE jobs SET progress = ?, stage = ? WHERE id = ? AND status = 'running'")
            .bind(progress as i64)
            .bind(stage)
            .bind(id.to_string())
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// `running → succeeded | failed | canceled`. False when the job was not running.
    pub async fn finish(
        &self,
        id: JobId,
        status: JobStatus,
        error: Option<&Problem>,
        result: Option<&JobResult>,
    ) -> Result<bool, DbError> {
        let progress = if status == JobStatus::Succeeded {
            100
        } else {
            0
        };
        let done = sqlx::query(
            "UPDATE jobs SET status = ?, stage = ?, error = ?, result = ?, finished_us = ?,
                    progress = CASE WHEN ? = 100 THEN 100 ELSE progress END
             WHERE id = ? AND status = 'running'",
        )
        .bind(status.as_str())
        .bind(status.as_str())
        .bind(error.map(to_json))
        .bind(result.map(to_json))
        .bind(now_us())
        .bind(progress)
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
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
        Ok(done.rows_affected() == 1)
    }

    /// Remember that a running job was asked to stop (survives a crash).
    pub async fn request_cancel(&self, id: JobId) -> Result<(), DbError> {
        sqlx::query("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND status = 'running'")
            .bind(id.to_string())
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// After a crash: jobs left `running` go back to `queued`, except those asked to cancel (→ canceled)
    /// and those already started `max_attempts` times (→ failed). Returns `(requeued, failed)`.
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

    /// Delete a finished job. False when it does not exist or is still queued or running.
    pub async fn delete_finished(&self, id: JobId) -> Result<bool, DbError> {
        let done = sqlx::query(
            "DELETE FROM jobs WHERE id = ? AND status IN ('succeeded', 'failed', 'canceled')",
        )
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
    }

    /// Ids of jobs that are not `succeeded` (their result directories may hold partial files).
    pub async fn unfinished_ids(&self) -> Result<Vec<JobId>, DbError> {
        let rows = sqlx::query("SELECT id FROM jobs WHERE status != 'succeeded'")
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| {
                let id: String = r.try_get("id")?;
                JobId::parse(&id).map_err(|e| corrupt("jobs", e))
            })
            .collect()
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
