//! The rows of rules, rule runs and deliveries (SQLite; plain runtime queries, so that another adapter can
//! repeat them). State changes of a delivery are guarded updates (`… WHERE state = ?`), so two workers
//! never both claim one.

use sqlx::Row;
use sqlx::sqlite::SqliteRow;

use super::{Db, DbError, corrupt, json_col, opt_json_col, to_json};
use crate::error_code::Problem;
use crate::jobs::deliveries::{
    Delivery, DeliveryFilter, DeliveryInstance, DeliveryState, InstanceState, NewRun, RuleRun,
    RunState,
};
use crate::jobs::model::{JobStatus, now_us};
use crate::jobs::rules::{RuleSource, RuleSpec, StoredRule};
use crate::storage::{JobId, SeriesId};

fn rule_from_row(row: &SqliteRow) -> Result<StoredRule, DbError> {
    let source: String = row.try_get("source")?;
    Ok(StoredRule {
        spec: json_col(row, "spec", "rules")?,
        source: match source.as_str() {
            "api" => RuleSource::Api,
            "config" => RuleSource::Config,
            other => return Err(corrupt("rules", format!("source {other}"))),
        },
        created_us: row.try_get("created_us")?,
        updated_us: row.try_get("updated_us")?,
    })
}

fn run_from_row(row: &SqliteRow) -> Result<RuleRun, DbError> {
    let state: String = row.try_get("state")?;
    let series: String = row.try_get("series_id")?;
    let job: Option<String> = row.try_get("job_id")?;
    Ok(RuleRun {
        id: row.try_get("id")?,
        rule_name: row.try_get("rule_name")?,
        content_hash: row.try_get("content_hash")?,
        series_id: SeriesId::parse(&series).map_err(|e| corrupt("rule_runs", e))?,
        series_uid: row.try_get("series_uid")?,
        calling_ae: row.try_get("calling_ae")?,
        job_id: job
            .map(|j| JobId::parse(&j).map_err(|e| corrupt("rule_runs", e)))
            .transpose()?,
        state: RunState::parse(&state).ok_or_else(|| corrupt("rule_runs", state))?,
        error: opt_json_col::<Problem>(row, "error", "rule_runs")?,
        created_us: row.try_get("created_us")?,
    })
}

fn delivery_from_row(row: &SqliteRow) -> Result<Delivery, DbError> {
    let state: String = row.try_get("state")?;
    let job: String = row.try_get("job_id")?;
    let attempts: i64 = row.try_get("attempts")?;
    Ok(Delivery {
        id: row.try_get("id")?,
        job_id: JobId::parse(&job).map_err(|e| corrupt("deliveries", e))?,
        run_id: row.try_get("run_id")?,
        rule_name: row.try_get("rule_name")?,
        destination: row.try_get("destination")?,
        state: DeliveryState::parse(&state).ok_or_else(|| corrupt("deliveries", state))?,
        attempts: attempts.max(0) as u32,
        next_attempt_us: row.try_get("next_attempt_us")?,
        last_error: row.try_get("last_error")?,
        created_us: row.try_get("created_us")?,
        updated_us: row.try_get("updated_us")?,
        finished_us: row.try_get("finished_us")?,
        instances: Vec::new(),
    })
}

fn instance_from_row(row: &SqliteRow) -> Result<DeliveryInstance, DbError> {
    let state: String = row.try_get("state")?;
    let status: Option<i64> = row.try_get("status")?;
    Ok(DeliveryInstance {
        file: row.try_get("file")?,
        sop_class_uid: row.try_get("sop_class_uid")?,
        sop_instance_uid: row.try_get("sop_instance_uid")?,
        state: InstanceState::parse(&state).ok_or_else(|| corrupt("delivery_instances", state))?,
        status: status.map(|s| s.clamp(0, 0xFFFF) as u16),
        detail: row.try_get("detail")?,
    })
}

impl Db {
    /// Insert a rule; false when one of that name exists.
    pub async fn insert_rule(&self, spec: &RuleSpec, source: RuleSource) -> Result<bool, DbError> {
        let now = now_us();
        let r = sqlx::query(
            "INSERT INTO rules (name, source, spec, created_us, updated_us) VALUES (?, ?, ?, ?, ?)
             ON CONFLICT (name) DO NOTHING",
        )
        .bind(&spec.name)
        .bind(source.as_str())
        .bind(to_json(spec))
        .bind(now)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Replace an API rule; false when there is no API rule of that name.
    pub async fn replace_rule(&self, spec: &RuleSpec) -> Result<bool, DbError> {
        let r = sqlx::query(
            "UPDATE rules SET spec = ?, updated_us = ? WHERE name = ? AND source = 'api'",
        )
        .bind(to_json(spec))
        .bind(now_us())
        .bind(&spec.name)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Delete an API rule and its runs (so a rule made again under the name starts afresh); false when
    /// there is no API rule of that name.
    pub async fn delete_rule(&self, name: &str) -> Result<bool, DbError> {
        let mut tx = self.write_tx().await?;
        let r = sqlx::query("DELETE FROM rules WHERE name = ? AND source = 'api'")
            .bind(name)
            .execute(&mut *tx)
            .await?;
        if r.rows_affected() == 1 {
            sqlx::query("DELETE FROM rule_runs WHERE rule_name = ?")
                .bind(name)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }

    pub async fn get_rule(&self, name: &str) -> Result<Option<StoredRule>, DbError> {
        let row = sqlx::query("SELECT * FROM rules WHERE name = ?")
            .bind(name)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(rule_from_row).transpose()
    }

    /// Every rule, by name.
    pub async fn list_rules(&self) -> Result<Vec<StoredRule>, DbError> {
        let rows = sqlx::query("SELECT * FROM rules ORDER BY name")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(rule_from_row).collect()
    }

    /// Make the configuration's rules the stored config rules: others removed, these inserted or
    /// replaced (a config rule replaces an API rule of the same name).
    pub async fn sync_config_rules(&self, specs: &[RuleSpec]) -> Result<(), DbError> {
        let now = now_us();
        let mut tx = self.write_tx().await?;
        let names = to_json(&specs.iter().map(|s| &s.name).collect::<Vec<_>>());
        sqlx::query(
            "DELETE FROM rules WHERE source = 'config' AND name NOT IN (SELECT value FROM json_each(?))",
        )
        .bind(names)
        .execute(&mut *tx)
        .await?;
        for s in specs {
            sqlx::query(
                "INSERT INTO rules (name, source, spec, created_us, updated_us) VALUES (?, 'config', ?, ?, ?)
                 ON CONFLICT (name) DO UPDATE SET source = 'config', spec = excluded.spec,
                     updated_us = excluded.updated_us
                 WHERE rules.spec <> excluded.spec OR rules.source <> 'config'",
            )
            .bind(&s.name)
            .bind(to_json(s))
            .bind(now)
            .bind(now)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Record that a rule fires for a series; `None` when it already fired for this content.
    pub async fn insert_run(&self, run: &NewRun<'_>) -> Result<Option<String>, DbError> {
        let id = JobId::generate().to_string();
        let r = sqlx::query(
            "INSERT INTO rule_runs (id, rule_name, content_hash, series_id, series_uid, calling_ae, state,
                                    created_us)
             VALUES (?, ?, ?, ?, ?, ?, 'running', ?) ON CONFLICT (rule_name, content_hash) DO NOTHING",
        )
        .bind(&id)
        .bind(run.rule_name)
        .bind(run.content_hash)
        .bind(run.series_id.to_string())
        .bind(run.series_uid)
        .bind(run.facts.calling_ae.as_deref())
        .bind(now_us())
        .execute(&self.pool)
        .await?;
        Ok((r.rows_affected() == 1).then_some(id))
    }

    pub async fn set_run_job(&self, run_id: &str, job: JobId) -> Result<(), DbError> {
        sqlx::query("UPDATE rule_runs SET job_id = ? WHERE id = ?")
            .bind(job.to_string())
            .bind(run_id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    pub async fn set_run_state(
        &self,
        run_id: &str,
        state: RunState,
        error: Option<&Problem>,
    ) -> Result<(), DbError> {
        sqlx::query("UPDATE rule_runs SET state = ?, error = COALESCE(?, error) WHERE id = ?")
            .bind(state.as_str())
            .bind(error.map(to_json))
            .bind(run_id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Runs whose job has finished but whose deliveries were not made yet, with the job's status.
    pub async fn runs_with_finished_jobs(&self) -> Result<Vec<(RuleRun, JobStatus)>, DbError> {
        let rows = sqlx::query(
            "SELECT r.*, j.status AS job_status FROM rule_runs r JOIN jobs j ON j.id = r.job_id
             WHERE r.state = 'running' AND j.status IN ('succeeded', 'failed', 'canceled')
             ORDER BY r.created_us LIMIT 100",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|row| {
                let s: String = row.try_get("job_status")?;
                let status = JobStatus::parse(&s).ok_or_else(|| corrupt("jobs", s))?;
                Ok((run_from_row(row)?, status))
            })
            .collect()
    }

    /// The newest runs of a rule (all rules when `rule` is `None`).
    pub async fn list_runs(&self, rule: Option<&str>, limit: u32) -> Result<Vec<RuleRun>, DbError> {
        let rows = sqlx::query(
            "SELECT * FROM rule_runs WHERE (? IS NULL OR rule_name = ?) ORDER BY created_us DESC, id DESC
             LIMIT ?",
        )
        .bind(rule)
        .bind(rule)
        .bind(limit as i64)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(run_from_row).collect()
    }

    /// The run that started `job`, if a rule did.
    pub async fn run_of_job(&self, job: JobId) -> Result<Option<RuleRun>, DbError> {
        let row = sqlx::query("SELECT * FROM rule_runs WHERE job_id = ?")
            .bind(job.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(run_from_row).transpose()
    }

    /// Queue a delivery of `job` to `destination`, due now; returns its id.
    pub async fn insert_delivery(
        &self,
        job: JobId,
        run: Option<&RuleRun>,
        destination: &str,
    ) -> Result<String, DbError> {
        let id = JobId::generate().to_string();
        let now = now_us();
        sqlx::query(
            "INSERT INTO deliveries (id, job_id, run_id, rule_name, destination, state, attempts,
                                     next_attempt_us, created_us, updated_us)
             VALUES (?, ?, ?, ?, ?, 'queued', 0, ?, ?, ?)",
        )
        .bind(&id)
        .bind(job.to_string())
        .bind(run.map(|r| r.id.clone()))
        .bind(run.map(|r| r.rule_name.clone()))
        .bind(destination)
        .bind(now)
        .bind(now)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(id)
    }

    /// A delivery with its instances.
    pub async fn get_delivery(&self, id: &str) -> Result<Option<Delivery>, DbError> {
        let row = sqlx::query("SELECT * FROM deliveries WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        let Some(mut d) = row.as_ref().map(delivery_from_row).transpose()? else {
            return Ok(None);
        };
        let rows =
            sqlx::query("SELECT * FROM delivery_instances WHERE delivery_id = ? ORDER BY position")
                .bind(id)
                .fetch_all(&self.pool)
                .await?;
        d.instances = rows
            .iter()
            .map(instance_from_row)
            .collect::<Result<_, _>>()?;
        Ok(Some(d))
    }

    /// Deliveries matching `f` (without their instances), newest first.
    pub async fn list_deliveries(&self, f: &DeliveryFilter) -> Result<Vec<Delivery>, DbError> {
        let rows = sqlx::query(
            "SELECT * FROM deliveries WHERE (? IS NULL OR state = ?) AND (? IS NULL OR job_id = ?)
                 AND (? IS NULL OR rule_name = ?)
             ORDER BY id DESC LIMIT ?",
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
        rows.iter().map(delivery_from_row).collect()
    }

    /// Ids of the deliveries of the runs `run_ids`.
    pub async fn delivery_ids_of_run(&self, run_id: &str) -> Result<Vec<String>, DbError> {
        let rows = sqlx::query("SELECT id FROM deliveries WHERE run_id = ? ORDER BY id")
            .bind(run_id)
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| Ok(r.try_get::<String, _>("id")?))
            .collect()
    }

    /// Claim the next due queued delivery (`queued → sending`, one more attempt) to a destination that has
    /// none in flight.
    pub async fn claim_due_delivery(&self, now: i64) -> Result<Option<Delivery>, DbError> {
        let row = sqlx::query(
            "UPDATE deliveries SET state = 'sending', attempts = attempts + 1, updated_us = ?
             WHERE id = (SELECT id FROM deliveries WHERE state = 'queued' AND next_attempt_us <= ?
                           AND destination NOT IN (SELECT destination FROM deliveries WHERE state = 'sending')
                         ORDER BY next_attempt_us, id LIMIT 1)
               AND state = 'queued'
             RETURNING id",
        )
        .bind(now)
        .bind(now)
        .fetch_optional(&self.pool)
        .await?;
        match row {
            Some(r) => {
                let id: String = r.try_get("id")?;
                self.get_delivery(&id).await
            }
            None => Ok(None),
        }
    }

    /// The earliest time a queued delivery is due.
    pub async fn next_delivery_due(&self) -> Result<Option<i64>, DbError> {
        let row =
            sqlx::query("SELECT MIN(next_attempt_us) AS t FROM deliveries WHERE state = 'queued'")
                .fetch_one(&self.pool)
                .await?;
        Ok(row.try_get::<Option<i64>, _>("t")?)
    }

    /// Deliveries left `sending` by a stop go back to `queued`, due now (the attempt stays counted).
    pub async fn requeue_sending_deliveries(&self) -> Result<u64, DbError> {
        let now = now_us();
        let r = sqlx::query(
            "UPDATE deliveries SET state = 'queued', next_attempt_us = ?, updated_us = ? WHERE state = 'sending'",
        )
        .bind(now)
        .bind(now)
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
        let mut tx = self.write_tx().await?;
        sqlx::query("DELETE FROM delivery_instances WHERE delivery_id = ?")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        for (k, i) in instances.iter().enumerate() {
            sqlx::query(
                "INSERT INTO delivery_instances (delivery_id, position, file, sop_class_uid, sop_instance_uid,
                                                 state, status, detail)
                 VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            )
            .bind(id)
            .bind(k as i64)
            .bind(&i.file)
            .bind(&i.sop_class_uid)
            .bind(&i.sop_instance_uid)
            .bind(i.state.as_str())
            .bind(i.status.map(i64::from))
            .bind(i.detail.as_deref())
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Record the end of an attempt of a `sending` delivery: each instance's state, status and detail (in
    /// position order), the delivery's new state, when it is due again (queued) and the error of the
    /// attempt.
    pub async fn finish_delivery_attempt(
        &self,
        d: &Delivery,
        state: DeliveryState,
        next_attempt_us: Option<i64>,
        error: Option<&str>,
    ) -> Result<bool, DbError> {
        let now = now_us();
        let mut tx = self.write_tx().await?;
        for (k, i) in d.instances.iter().enumerate() {
            sqlx::query(
                "UPDATE delivery_instances SET state = ?, status = ?, detail = ?
                 WHERE delivery_id = ? AND position = ?",
            )
            .bind(i.state.as_str())
            .bind(i.status.map(i64::from))
            .bind(i.detail.as_deref())
            .bind(&d.id)
            .bind(k as i64)
            .execute(&mut *tx)
            .await?;
        }
        let finished = matches!(state, DeliveryState::Succeeded | DeliveryState::Failed);
        let r = sqlx::query(
            "UPDATE deliveries SET state = ?, next_attempt_us = ?, last_error = ?, updated_us = ?,
                 finished_us = ? WHERE id = ? AND state = 'sending'",
        )
        .bind(state.as_str())
        .bind(next_attempt_us)
        .bind(error)
        .bind(now)
        .bind(finished.then_some(now))
        .bind(&d.id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }

    /// Queue a failed delivery again, due now, with its failed instances pending; false unless it was
    /// `failed`.
    pub async fn retry_delivery(&self, id: &str) -> Result<bool, DbError> {
        let now = now_us();
        let mut tx = self.write_tx().await?;
        let r = sqlx::query(
            "UPDATE deliveries SET state = 'queued', attempts = 0, next_attempt_us = ?, updated_us = ?,
                 finished_us = NULL WHERE id = ? AND state = 'failed'",
        )
        .bind(now)
        .bind(now)
        .bind(id)
        .execute(&mut *tx)
        .await?;
        if r.rows_affected() == 1 {
            sqlx::query(
                "UPDATE delivery_instances SET state = 'pending', status = NULL, detail = NULL
                 WHERE delivery_id = ? AND state = 'failed'",
            )
            .bind(id)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }
}
