//! The rows of deliveries and their instances. A delivery moves by guarded updates (`… WHERE state = …`).
//! What each operation guarantees on a database that several processes share (PostgreSQL; on SQLite the
//! one process holds the write lock for each transaction, which gives the same):
//! - a claim takes one due `queued` delivery to `sending` under `FOR UPDATE SKIP LOCKED`, so exactly one
//!   process sends it; claims are also serialised by a transaction-level lock ([`Tx::lock`]), so the rule
//!   "one delivery in flight per destination" holds across processes, not only within one;
//! - a claimed delivery belongs to its process until `claimed_until_us`, which that process renews while it
//!   sends ([`Database::renew_delivery_claim`]); [`Database::requeue_sending_deliveries`] queues again only
//!   those whose claim ended, so a process starting (or a round of any process) never takes a delivery another
//!   live process is sending;
//! - the end of an attempt is recorded only by the attempt that holds the claim (`attempts` guard), so a
//!   process whose claim expired and was taken over cannot overwrite the newer attempt.

use super::driver::{Target, assembled, query};
use super::node_rows::{delivery, delivery_instance};
use super::{Database, DbError};
use crate::jobs::deliveries::{Delivery, DeliveryFilter, DeliveryInstance, DeliveryState, RuleRun};
use crate::jobs::model::now_us;
use crate::storage::JobId;

/// The transaction-level lock that serialises delivery claims across processes.
const CLAIM_LOCK: i64 = 0x6374_7265_636f_6e02;

impl Database {
    /// Queue a delivery of `job` to `destination`, due now; returns its id.
    pub async fn insert_delivery(
        &self,
        job: JobId,
        run: Option<&RuleRun>,
        destination: &str,
    ) -> Result<String, DbError> {
        insert_delivery(&self.pool, job, run, destination).await
    }

    /// A delivery with its instances.
    pub async fn get_delivery(&self, id: &str) -> Result<Option<Delivery>, DbError> {
        let row = query("SELECT * FROM deliveries WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        let Some(mut d) = row.as_ref().map(delivery).transpose()? else {
            return Ok(None);
        };
        let rows =
            query("SELECT * FROM delivery_instances WHERE delivery_id = $1 ORDER BY position")
                .bind(id)
                .fetch_all(&self.pool)
                .await?;
        d.instances = rows
            .iter()
            .map(delivery_instance)
            .collect::<Result<_, _>>()?;
        Ok(Some(d))
    }

    /// Deliveries matching `f` (without their instances), newest first.
    pub async fn list_deliveries(&self, f: &DeliveryFilter) -> Result<Vec<Delivery>, DbError> {
        let rows = query(
            "SELECT * FROM deliveries WHERE (CAST($1 AS TEXT) IS NULL OR state = $2)
                 AND (CAST($3 AS TEXT) IS NULL OR job_id = $4) AND (CAST($5 AS TEXT) IS NULL OR rule_name = $6)
             ORDER BY id DESC LIMIT $7",
        )
        .bind(f.state.map(|s| s.as_str()))
        .bind(f.state.map(|s| s.as_str()))
        .bind(f.job_id.map(|j| j.to_string()))
        .bind(f.job_id.map(|j| j.to_string()))
        .bind(f.rule_name.as_deref())
        .bind(f.rule_name.as_deref())
        .bind(f.limit as i64)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(delivery).collect()
    }

    /// Ids of the deliveries of the runs `run_ids`.
    pub async fn delivery_ids_of_run(&self, run_id: &str) -> Result<Vec<String>, DbError> {
        let rows = query("SELECT id FROM deliveries WHERE run_id = $1 ORDER BY id")
            .bind(run_id)
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| Ok(r.try_get::<String>("id")?))
            .collect()
    }

    /// Claim the next due queued delivery (`queued → sending`, one more attempt) to a destination that has
    /// none in flight, for the caller until `claimed_until_us`. The row is taken with `FOR UPDATE SKIP
    /// LOCKED` (on PostgreSQL) and claims are serialised by [`CLAIM_LOCK`], so two processes never claim one
    /// delivery, nor two deliveries to one destination.
    pub async fn claim_due_delivery(
        &self,
        now: i64,
        claimed_until_us: i64,
    ) -> Result<Option<Delivery>, DbError> {
        let mut tx = self.pool.begin().await?;
        tx.lock(CLAIM_LOCK).await?;
        let sql = format!(
            "UPDATE deliveries SET state = 'sending', attempts = attempts + 1, updated_us = $1,
                 claimed_until_us = $2
             WHERE id = (SELECT id FROM deliveries WHERE state = 'queued' AND next_attempt_us <= $3
                           AND destination NOT IN (SELECT destination FROM deliveries WHERE state = 'sending')
                         ORDER BY next_attempt_us, id LIMIT 1{})
               AND state = 'queued'
             RETURNING id",
            self.dialect().skip_locked()
        );
        let row = assembled(sql)
            .bind(now)
            .bind(claimed_until_us)
            .bind(now)
            .fetch_optional(&mut tx)
            .await?;
        tx.commit().await?;
        match row {
            Some(r) => {
                let id: String = r.try_get("id")?;
                self.get_delivery(&id).await
            }
            None => Ok(None),
        }
    }

    /// Extend the claim of the attempt `attempts` of a sending delivery to `claimed_until_us`; false when
    /// that attempt no longer holds it.
    pub async fn renew_delivery_claim(
        &self,
        id: &str,
        attempts: u32,
        claimed_until_us: i64,
    ) -> Result<bool, DbError> {
        let r = query(
            "UPDATE deliveries SET claimed_until_us = $1 WHERE id = $2 AND state = 'sending' AND attempts = $3",
        )
        .bind(claimed_until_us)
        .bind(id)
        .bind(attempts as i64)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    /// The earliest time a queued delivery is due.
    pub async fn next_delivery_due(&self) -> Result<Option<i64>, DbError> {
        let row = query("SELECT MIN(next_attempt_us) AS t FROM deliveries WHERE state = 'queued'")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<Option<i64>>("t")?)
    }

    /// At start: deliveries left `sending` go back to `queued`, due now. On SQLite every one (the one
    /// process that owns the database was sending them when it stopped); on a shared database only those
    /// whose claim ended (another live process renews the claims of what it sends).
    pub async fn requeue_interrupted_deliveries(&self) -> Result<u64, DbError> {
        let before = if self.is_shared() { now_us() } else { i64::MAX };
        self.requeue_sending_deliveries(before).await
    }

    /// Deliveries `sending` whose claim ended (their process was lost) go back to `queued`, due now.
    pub async fn requeue_expired_deliveries(&self) -> Result<u64, DbError> {
        self.requeue_sending_deliveries(now_us()).await
    }

    /// Deliveries `sending` whose claim ended before `expired_before_us` go back to `queued`, due now (the
    /// attempt stays counted).
    pub async fn requeue_sending_deliveries(&self, expired_before_us: i64) -> Result<u64, DbError> {
        let now = now_us();
        let r = query(
            "UPDATE deliveries SET state = 'queued', next_attempt_us = $1, updated_us = $2, claimed_until_us = NULL
             WHERE state = 'sending' AND (claimed_until_us IS NULL OR claimed_until_us < $3)",
        )
        .bind(now)
        .bind(now)
        .bind(expired_before_us)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected())
    }

    /// Give a delivery its instances (once, when its job's results were exported).
    pub async fn set_delivery_instances(
        &self,
        id: &str,
        instances: &[DeliveryInstance],
    ) -> Result<(), DbError> {
        let mut tx = self.pool.begin().await?;
        query("DELETE FROM delivery_instances WHERE delivery_id = $1")
            .bind(id)
            .execute(&mut tx)
            .await?;
        for (k, i) in instances.iter().enumerate() {
            query(
                "INSERT INTO delivery_instances (delivery_id, position, file, sop_class_uid, sop_instance_uid,
                                                 state, status, detail)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
            )
            .bind(id)
            .bind(k as i64)
            .bind(&i.file)
            .bind(&i.sop_class_uid)
            .bind(&i.sop_instance_uid)
            .bind(i.state.as_str())
            .bind(i.status.map(i64::from))
            .bind(i.detail.as_deref())
            .execute(&mut tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Record the end of an attempt of a `sending` delivery: each instance's state, status and detail (in
    /// position order), the delivery's new state, when it is due again (queued) and the error of the
    /// attempt. False (and nothing written) when the attempt `d.attempts` no longer holds the delivery.
    pub async fn finish_delivery_attempt(
        &self,
        d: &Delivery,
        state: DeliveryState,
        next_attempt_us: Option<i64>,
        error: Option<&str>,
    ) -> Result<bool, DbError> {
        let now = now_us();
        let mut tx = self.pool.begin().await?;
        let finished = matches!(state, DeliveryState::Succeeded | DeliveryState::Failed);
        let r = query(
            "UPDATE deliveries SET state = $1, next_attempt_us = $2, last_error = $3, updated_us = $4,
                 finished_us = $5, claimed_until_us = NULL
             WHERE id = $6 AND state = 'sending' AND attempts = $7",
        )
        .bind(state.as_str())
        .bind(next_attempt_us)
        .bind(error)
        .bind(now)
        .bind(finished.then_some(now))
        .bind(&d.id)
        .bind(d.attempts as i64)
        .execute(&mut tx)
        .await?;
        if r.rows_affected() != 1 {
            tx.rollback().await?;
            return Ok(false);
        }
        for (k, i) in d.instances.iter().enumerate() {
            query(
                "UPDATE delivery_instances SET state = $1, status = $2, detail = $3
                 WHERE delivery_id = $4 AND position = $5",
            )
            .bind(i.state.as_str())
            .bind(i.status.map(i64::from))
            .bind(i.detail.as_deref())
            .bind(&d.id)
            .bind(k as i64)
            .execute(&mut tx)
            .await?;
        }
        tx.commit().await?;
        Ok(true)
    }

    /// Queue a failed delivery again, due now, with its failed instances pending; false unless it was
    /// `failed`.
    pub async fn retry_delivery(&self, id: &str) -> Result<bool, DbError> {
        let now = now_us();
        let mut tx = self.pool.begin().await?;
        let r = query(
            "UPDATE deliveries SET state = 'queued', attempts = 0, next_attempt_us = $1, updated_us = $2,
                 finished_us = NULL WHERE id = $3 AND state = 'failed'",
        )
        .bind(now)
        .bind(now)
        .bind(id)
        .execute(&mut tx)
        .await?;
        if r.rows_affected() == 1 {
            query(
                "UPDATE delivery_instances SET state = 'pending', status = NULL, detail = NULL
                 WHERE delivery_id = $1 AND state = 'failed'",
            )
            .bind(id)
            .execute(&mut tx)
            .await?;
        }
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }
}

/// Queue a delivery of `job` to `destination`, due now, on `on` (a transaction's or the pool's); returns
/// its id.
pub(super) async fn insert_delivery<'a>(
    on: impl Into<Target<'a>>,
    job: JobId,
    run: Option<&RuleRun>,
    destination: &str,
) -> Result<String, DbError> {
    let id = JobId::generate().to_string();
    let now = now_us();
    query(
        "INSERT INTO deliveries (id, job_id, run_id, rule_name, destination, state, attempts,
                                 next_attempt_us, created_us, updated_us)
         VALUES ($1, $2, $3, $4, $5, 'queued', 0, $6, $7, $8)",
    )
    .bind(&id)
    .bind(job.to_string())
    .bind(run.map(|r| r.id.clone()))
    .bind(run.map(|r| r.rule_name.clone()))
    .bind(destination)
    .bind(now)
    .bind(now)
    .bind(now)
    .execute(on)
    .await?;
    Ok(id)
}
