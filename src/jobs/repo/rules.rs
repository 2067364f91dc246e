//! The rows of rules and rule runs (SQLite; plain runtime queries, so that another adapter can repeat
//! them). A run is unique per rule and series content, and is closed (its deliveries queued) by one guarded
//! update, so it fires and delivers once.

use sqlx::Row;
use sqlx::sqlite::SqliteRow;

use super::{Db, DbError, corrupt, json_col, opt_json_col, to_json};
use crate::error_code::Problem;
use crate::jobs::deliveries::{NewRun, RuleRun, RunState};
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

    /// Close run `run`, whose job `job` finished: `running → done` (with `error`, the job's problem when it
    /// did not succeed) and, in the same transaction, a delivery of the job to each of `destinations`, due
    /// now. `None` when the run was not running any more (closed before, by this or another worker): then
    /// nothing is queued, so a run's deliveries are queued once.
    pub async fn complete_run(
        &self,
        run: &RuleRun,
        job: JobId,
        destinations: &[String],
        error: Option<&Problem>,
    ) -> Result<Option<Vec<String>>, DbError> {
        let mut tx = self.write_tx().await?;
        let r = sqlx::query(
            "UPDATE rule_runs SET state = 'done', error = COALESCE(?, error) WHERE id = ? AND state = 'running'",
        )
        .bind(error.map(to_json))
        .bind(&run.id)
        .execute(&mut *tx)
        .await?;
        if r.rows_affected() != 1 {
            return Ok(None);
        }
        let mut ids = Vec::with_capacity(destinations.len());
        for d in destinations {
            ids.push(super::deliveries::insert_delivery(&mut tx, job, Some(run), d).await?);
        }
        tx.commit().await?;
        Ok(Some(ids))
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
}
