//! The [`JobStore`] port on the job database. Each transition is one `UPDATE … WHERE status IN (…)` whose
//! guard comes from the lifecycle table ([`sources`]); when it matches no row, the job's current status
//! says why, as an [`IllegalTransition`]. On PostgreSQL a claim skips a row another worker is claiming at
//! the same moment (`FOR UPDATE SKIP LOCKED`, [`Dialect::skip_locked`](super::Dialect::skip_locked))
//! instead of waiting for it; on SQLite the claim's transaction holds the one write lock.

use super::driver::{Row, assembled, query};
use super::{Database, DbError, QUEUED_CHANNEL};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::lifecycle::{
    IllegalTransition, JobState, Lease, Outcome, Transition, sources, transition,
};
use crate::jobs::model::{IdempotencyKey, Inserted, Job, JobFilter, JobStatus, now_us};
use crate::jobs::store::{Expired, JobStore, Renewed, StoreError, StoreResult};
use crate::jobs::store::{corrupt, to_json};
use crate::storage::JobId;
use futures_util::FutureExt;
use futures_util::future::BoxFuture;

/// `status IN ('…', …)` for the statuses `event` is legal from (fixed words from the lifecycle table).
fn guard(event: Transition) -> String {
    let list: Vec<String> = sources(event)
        .map(|s| format!("'{}'", s.as_str()))
        .collect();
    format!("status IN ({})", list.join(", "))
}

impl From<DbError> for StoreError {
    fn from(e: DbError) -> Self {
        StoreError::Backend(Box::new(e))
    }
}

impl Database {
    /// The status of job `id` now, for explaining a guarded update that matched nothing.
    async fn illegal(&self, id: JobId, event: Transition) -> StoreError {
        let from = match self.get_job(id).await {
            Ok(j) => j.map(|j| j.status),
            Err(e) => return e.into(),
        };
        StoreError::Illegal(IllegalTransition { from, event })
    }

    /// The guarded `queued → running` update: the attempt number, or `None` when the job was not queued.
    async fn claim_row(&self, id: JobId, lease: Option<Lease>) -> Result<Option<u32>, DbError> {
        let sql = format!(
            "UPDATE jobs SET status = 'running', attempts = attempts + 1, started_us = $1,
                    progress = 0, stage = 'starting', lease_expires_us = $2
             WHERE id = (SELECT id FROM jobs WHERE id = $3 AND {}{})
             RETURNING attempts",
            guard(Transition::Claim),
            self.dialect().skip_locked()
        );
        let row = assembled(sql)
            .bind(now_us())
            .bind(lease.map(|l| l.expires_us))
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        self.invalidate(id);
        row.map(|r| {
            let n: i64 = r.try_get("attempts")?;
            Ok(n.max(0) as u32)
        })
        .transpose()
    }

    /// `queued → running` without a lease (a single process owns the database: a crash is found at the next
    /// start, not by a lease). False when the job was not queued.
    pub async fn claim(&self, id: JobId) -> Result<bool, DbError> {
        Ok(self.claim_row(id, None).await?.is_some())
    }

    async fn claim_leased(&self, id: JobId, lease: Option<Lease>) -> StoreResult<u32> {
        match self.claim_row(id, lease).await? {
            Some(attempt) => Ok(attempt),
            None => Err(self.illegal(id, Transition::Claim).await),
        }
    }

    async fn lease_of(&self, id: JobId) -> Result<Option<Lease>, DbError> {
        let row = query("SELECT lease_expires_us FROM jobs WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        let expires: Option<i64> = match row {
            Some(r) => r.try_get("lease_expires_us")?,
            None => None,
        };
        Ok(expires.map(|expires_us| Lease { expires_us }))
    }

    async fn state_of(&self, id: JobId) -> Result<Option<JobState>, DbError> {
        let Some(job) = self.get_job(id).await? else {
            return Ok(None);
        };
        Ok(Some(match job.status {
            JobStatus::Queued => JobState::Queued,
            JobStatus::Running => JobState::Running {
                attempt: job.attempts,
                lease: self.lease_of(id).await?,
            },
            JobStatus::Succeeded => match job.result {
                Some(r) => JobState::Succeeded(Box::new(r)),
                None => return Err(corrupt("jobs", format!("{id}: succeeded without a result"))),
            },
            JobStatus::Failed => JobState::Failed(job.error.unwrap_or_else(Problem::internal)),
            JobStatus::Canceled => JobState::Canceled,
        }))
    }

    async fn heartbeat_row(&self, id: JobId, attempt: u32, lease: Lease) -> StoreResult<Renewed> {
        let row = query(
            "UPDATE jobs SET lease_expires_us = $1 WHERE id = $2 AND status = 'running' AND attempts = $3
             RETURNING cancel_requested",
        )
        .bind(lease.expires_us)
        .bind(id.to_string())
        .bind(attempt as i64)
        .fetch_optional(&self.pool)
        .await
        .map_err(DbError::from)?;
        match row {
            Some(r) => {
                let cancel: i64 = r.try_get("cancel_requested").map_err(DbError::from)?;
                Ok(Renewed {
                    cancel_requested: cancel != 0,
                })
            }
            None => Err(StoreError::LeaseLost),
        }
    }

    /// Why a guarded update of `attempt` matched nothing: the job runs another attempt (this worker's
    /// lease was lost), or its status forbids `event`.
    async fn refused(&self, id: JobId, attempt: u32, event: Transition) -> StoreError {
        match self.get_job(id).await {
            Ok(Some(j)) if j.status == JobStatus::Running && j.attempts != attempt => {
                StoreError::LeaseLost
            }
            Ok(j) => StoreError::Illegal(IllegalTransition {
                from: j.map(|j| j.status),
                event,
            }),
            Err(e) => e.into(),
        }
    }

    async fn expire(&self, now: i64, max_attempts: u32) -> Result<Expired, DbError> {
        let problem = Problem::new(
            ErrorCode::AttemptsExhausted,
            format!("the job's worker was lost while running it {max_attempts} times"),
        );
        let ids = |rows: Vec<Row>| {
            rows.iter()
                .map(|r| r.parsed("id", "jobs", JobId::parse))
                .collect::<Result<Vec<_>, DbError>>()
        };
        let mut tx = self.pool.begin().await?;
        let failed = query(
            "UPDATE jobs SET status = 'failed', stage = 'failed', finished_us = $1, error = $2,
                    lease_expires_us = NULL
             WHERE status = 'running' AND lease_expires_us < $3 AND attempts >= $4 RETURNING id",
        )
        .bind(now)
        .bind(to_json(&problem))
        .bind(now)
        .bind(max_attempts as i64)
        .fetch_all(&mut tx)
        .await?;
        let requeued: Vec<Row> = query(
            "UPDATE jobs SET status = 'queued', stage = 'requeued', progress = 0, started_us = NULL,
                    lease_expires_us = NULL
             WHERE status = 'running' AND lease_expires_us < $1 RETURNING id",
        )
        .bind(now)
        .fetch_all(&mut tx)
        .await?;
        for r in &requeued {
            let id: String = r.try_get("id")?;
            tx.notify(QUEUED_CHANNEL, &id).await?;
        }
        tx.commit().await?;
        let e = Expired {
            requeued: ids(requeued)?,
            failed: ids(failed)?,
        };
        for id in e.requeued.iter().chain(&e.failed) {
            self.invalidate(*id);
        }
        Ok(e)
    }

    /// `running → succeeded | failed | canceled` for the run of `attempt`.
    async fn finish_row(&self, id: JobId, attempt: u32, outcome: &Outcome) -> StoreResult<()> {
        let event = outcome.transition();
        // The outcome's own status must be where the lifecycle takes a running job by its event.
        transition(JobStatus::Running, event)?;
        let (error, result) = match outcome {
            Outcome::Succeeded(r) => (None, Some(to_json(r))),
            Outcome::Failed(p) => (Some(to_json(p)), None),
            Outcome::Canceled => (None, None),
        };
        let status = outcome.status();
        let done = query(
            "UPDATE jobs SET status = $1, stage = $2, error = $3, result = $4, finished_us = $5,
                    progress = CASE WHEN $6 THEN 100 ELSE progress END, lease_expires_us = NULL
             WHERE id = $7 AND status = 'running' AND attempts = $8",
        )
        .bind(status.as_str())
        .bind(status.as_str())
        .bind(error)
        .bind(result)
        .bind(now_us())
        .bind(status == JobStatus::Succeeded)
        .bind(id.to_string())
        .bind(attempt as i64)
        .execute(&self.pool)
        .await
        .map_err(DbError::from)?;
        self.invalidate(id);
        if done.rows_affected() == 1 {
            Ok(())
        } else {
            Err(self.refused(id, attempt, event).await)
        }
    }

    /// A transition method of the inherent API that answers whether it applied, as a port result.
    async fn applied(
        &self,
        id: JobId,
        event: Transition,
        done: Result<bool, DbError>,
    ) -> StoreResult<()> {
        if done? {
            Ok(())
        } else {
            Err(self.illegal(id, event).await)
        }
    }
}

impl JobStore for Database {
    fn insert<'a>(
        &'a self,
        job: &'a Job,
        key: Option<&'a IdempotencyKey>,
    ) -> BoxFuture<'a, StoreResult<Inserted>> {
        async move { Ok(self.insert_job(job, key).await?) }.boxed()
    }

    fn get(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<Job>>> {
        async move { Ok(self.get_job(id).await?) }.boxed()
    }

    fn state(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<JobState>>> {
        async move { Ok(self.state_of(id).await?) }.boxed()
    }

    fn list<'a>(&'a self, filter: &'a JobFilter) -> BoxFuture<'a, StoreResult<Vec<Job>>> {
        async move { Ok(self.list_jobs(filter).await?) }.boxed()
    }

    fn queued(&self, limit: u32) -> BoxFuture<'_, StoreResult<Vec<(JobId, u64)>>> {
        async move { Ok(Database::queued(self, limit).await?) }.boxed()
    }

    fn claim(&self, id: JobId, lease: Lease) -> BoxFuture<'_, StoreResult<u32>> {
        self.claim_leased(id, Some(lease)).boxed()
    }

    fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        lease: Lease,
    ) -> BoxFuture<'_, StoreResult<Renewed>> {
        self.heartbeat_row(id, attempt, lease).boxed()
    }

    fn set_progress<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &'a str,
    ) -> BoxFuture<'a, StoreResult<()>> {
        async move { Ok(Database::set_progress(self, id, attempt, progress, stage).await?) }.boxed()
    }

    fn hand_back(&self, id: JobId, attempt: u32) -> BoxFuture<'_, StoreResult<()>> {
        async move {
            if Database::hand_back(self, id, attempt).await? {
                Ok(())
            } else {
                Err(self.refused(id, attempt, Transition::HandBack).await)
            }
        }
        .boxed()
    }

    fn expire_leases(&self, now_us: i64, max_attempts: u32) -> BoxFuture<'_, StoreResult<Expired>> {
        async move { Ok(self.expire(now_us, max_attempts).await?) }.boxed()
    }

    fn finish<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        outcome: &'a Outcome,
    ) -> BoxFuture<'a, StoreResult<()>> {
        self.finish_row(id, attempt, outcome).boxed()
    }

    fn cancel_queued(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        async move {
            let done = Database::cancel_queued(self, id).await;
            self.applied(id, Transition::Cancel, done).await
        }
        .boxed()
    }

    fn request_cancel(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        async move { Ok(Database::request_cancel(self, id).await?) }.boxed()
    }

    fn delete_finished(&self, id: JobId) -> BoxFuture<'_, StoreResult<bool>> {
        async move { Ok(Database::delete_finished(self, id).await?) }.boxed()
    }
}
