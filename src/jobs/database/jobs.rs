//! Job rows: inserted, read, listed, and the transitions outside the lease protocol (progress, hand-back,
//! cancel, recovery after a crash of the process that owns a SQLite database). On a shared database a
//! queued job and a cancel request are announced to the other processes when their transaction commits.

use super::driver::{Row, assembled, query};
use super::rows::{job_from_row, summary_from_row};
use super::{CANCEL_CHANNEL, Database, DbError, QUEUED_CHANNEL};
use crate::error_code::Problem;
use crate::jobs::model::{IdempotencyKey, Inserted, Job, JobFilter, JobStatus, JobSummary, now_us};
use crate::jobs::store::to_json;
use crate::storage::JobId;

impl Database {
    pub async fn insert_job(
        &self,
        j: &Job,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        let mut tx = match self.begin_claimed(key, &j.id.to_string()).await? {
            Ok(tx) => tx,
            Err(existing) => return Ok(existing),
        };
        query(
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
        .execute(&mut tx)
        .await?;
        tx.notify(QUEUED_CHANNEL, &j.id.to_string()).await?;
        tx.commit().await?;
        // A new job changes every list it falls in.
        self.invalidate(j.id);
        Ok(Inserted::New)
    }

    pub async fn get_job(&self, id: JobId) -> Result<Option<Job>, DbError> {
        if let Some(job) = self.cache.as_ref().and_then(|c| c.get(id)) {
            return Ok(Some(job));
        }
        let generation = self.jobs_generation();
        let row = query("SELECT * FROM jobs WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        let job = row.as_ref().map(job_from_row).transpose()?;
        if let (Some(j), Some(cache)) = (&job, &self.cache) {
            cache.fill(j, generation);
        }
        Ok(job)
    }

    /// Jobs matching `f`, newest first, at most `f.limit`.
    pub async fn list_jobs(&self, f: &JobFilter) -> Result<Vec<Job>, DbError> {
        let rows = self.list_rows("*", f).await?;
        rows.iter().map(job_from_row).collect()
    }

    /// The summaries of the jobs matching `f`, newest first, at most `f.limit`: neither the request nor the
    /// result is read, only what the result links need (the database's JSON functions look it up).
    pub async fn list_job_summaries(&self, f: &JobFilter) -> Result<Vec<JobSummary>, DbError> {
        let rows = self.list_rows(self.dialect().summary_columns(), f).await?;
        rows.iter().map(summary_from_row).collect()
    }

    /// The rows of `columns` (a fixed list) of the jobs matching `f`.
    async fn list_rows(&self, columns: &'static str, f: &JobFilter) -> Result<Vec<Row>, DbError> {
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
        let mut q = assembled(sql);
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
        let rows = query(
            "SELECT id, estimate_bytes FROM jobs WHERE status = 'queued' ORDER BY id LIMIT $1",
        )
        .bind(limit as i64)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                let est: i64 = r.try_get("estimate_bytes")?;
                Ok((r.parsed("id", "jobs", JobId::parse)?, est.max(0) as u64))
            })
            .collect()
    }

    /// `running → queued` by a graceful hand-back (the server is stopping): the run is given back, not
    /// spent, so the attempt its claim counted is returned. False when the job was not running, or was asked
    /// to cancel (it then ends canceled).
    pub async fn hand_back(&self, id: JobId, attempt: u32) -> Result<bool, DbError> {
        let mut tx = self.pool.begin().await?;
        let done = query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0, started_us = NULL,
                    attempts = CASE WHEN attempts > 0 THEN attempts - 1 ELSE 0 END, lease_expires_us = NULL
             WHERE id = $1 AND status = 'running' AND cancel_requested = 0 AND attempts = $2",
        )
        .bind(id.to_string())
        .bind(attempt as i64)
        .execute(&mut tx)
        .await?;
        if done.rows_affected() == 1 {
            tx.notify(QUEUED_CHANNEL, &id.to_string()).await?;
        }
        tx.commit().await?;
        self.invalidate(id);
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
        query(
            "UPDATE jobs SET progress = $1, stage = $2 WHERE id = $3 AND status = 'running' AND attempts = $4",
        )
        .bind(progress as i64)
        .bind(stage)
        .bind(id.to_string())
        .bind(attempt as i64)
        .execute(&self.pool)
        .await?;
        self.invalidate(id);
        Ok(())
    }

    /// `queued → canceled`. False when the job was not queued.
    pub async fn cancel_queued(&self, id: JobId) -> Result<bool, DbError> {
        let done = query(
            "UPDATE jobs SET status = 'canceled', stage = 'canceled', finished_us = $1
             WHERE id = $2 AND status = 'queued'",
        )
        .bind(now_us())
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        self.invalidate(id);
        Ok(done.rows_affected() == 1)
    }

    /// Remember that a running job was asked to stop (survives a crash), and tell the process running it
    /// ([`CANCEL_CHANNEL`]); it also learns of it at its next heartbeat.
    pub async fn request_cancel(&self, id: JobId) -> Result<(), DbError> {
        let mut tx = self.pool.begin().await?;
        let done =
            query("UPDATE jobs SET cancel_requested = 1 WHERE id = $1 AND status = 'running'")
                .bind(id.to_string())
                .execute(&mut tx)
                .await?;
        if done.rows_affected() == 1 {
            tx.notify(CANCEL_CHANNEL, &id.to_string()).await?;
        }
        tx.commit().await?;
        self.invalidate(id);
        Ok(())
    }

    /// Delete a finished job. False when it does not exist or is still queued or running.
    pub async fn delete_finished(&self, id: JobId) -> Result<bool, DbError> {
        let done = query(
            "DELETE FROM jobs WHERE id = $1 AND status IN ('succeeded', 'failed', 'canceled')",
        )
        .bind(id.to_string())
        .execute(&self.pool)
        .await?;
        self.invalidate(id);
        Ok(done.rows_affected() == 1)
    }

    /// After a crash of the one process that owns a SQLite database (or a shutdown that did not get to hand a
    /// job back): jobs left `running` go back to `queued`, keeping the attempt their claim counted, except
    /// those asked to cancel (→ canceled) and those already started `max_attempts` times (→ failed).
    /// Returns `(requeued, failed)`. Nothing on a shared database, where the jobs left running belong to
    /// live workers until their leases expire.
    pub async fn recover(&self, max_attempts: u32) -> Result<(u64, u64), DbError> {
        if self.is_shared() {
            return Ok((0, 0));
        }
        let now = now_us();
        query(
            "UPDATE jobs SET status = 'canceled', stage = 'canceled', finished_us = $1
             WHERE status = 'running' AND cancel_requested = 1",
        )
        .bind(now)
        .execute(&self.pool)
        .await?;
        let problem = Problem::new(
            crate::error_code::ErrorCode::AttemptsExhausted,
            format!("the server stopped while running this job {max_attempts} times"),
        );
        let failed = query(
            "UPDATE jobs SET status = 'failed', stage = 'failed', finished_us = $1, error = $2
             WHERE status = 'running' AND attempts >= $3",
        )
        .bind(now)
        .bind(to_json(&problem))
        .bind(max_attempts as i64)
        .execute(&self.pool)
        .await?
        .rows_affected();
        let requeued = query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0
             WHERE status = 'running'",
        )
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok((requeued, failed))
    }

    /// Ids of jobs whose result directories may hold partial files after a crash of the one process that
    /// owns a SQLite database (those not `succeeded`); none on a shared database (another process may be
    /// writing them).
    pub async fn unfinished_ids(&self) -> Result<Vec<JobId>, DbError> {
        if self.is_shared() {
            return Ok(Vec::new());
        }
        let rows = query("SELECT id FROM jobs WHERE status != 'succeeded'")
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| r.parsed("id", "jobs", JobId::parse))
            .collect()
    }

    /// Number of jobs in each status.
    pub async fn counts(&self) -> Result<Vec<(JobStatus, i64)>, DbError> {
        let rows = query("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status")
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
