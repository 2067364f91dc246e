//! The rows of rules and rule runs. With several processes on one (PostgreSQL) database: a run is unique per rule and series content (`ON CONFLICT DO NOTHING`), so a series
//! assembled by two processes starts one job; a run is closed and its deliveries queued by one guarded
//! update in one transaction, so two delivery workers queue them once; the configuration's rules are
//! written under a transaction-level advisory lock, so processes starting together do not interleave.

use super::driver::{Row, assembled, query};
use super::rows::{json_col, opt_json_col};
use super::{Database, DbError};
use crate::error_code::Problem;
use crate::jobs::deliveries::{NewRun, RuleRun, RunState};
use crate::jobs::model::{JobStatus, now_us};
use crate::jobs::rules::{RuleSource, RuleSpec, StoredRule};
use crate::jobs::store::{corrupt, to_json};
use crate::storage::{JobId, SeriesId};

/// The transaction-level lock that serialises writing the configuration's rules.
const CONFIG_RULES_LOCK: i64 = 0x6374_7265_636f_6e01;

fn rule_from_row(row: &Row) -> Result<StoredRule, DbError> {
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

fn run_from_row(row: &Row) -> Result<RuleRun, DbError> {
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

impl Database {
    /// Insert a rule; false when one of that name exists.
    pub async fn insert_rule(&self, spec: &RuleSpec, source: RuleSource) -> Result<bool, DbError> {
        let now = now_us();
        let r = query(
            "INSERT INTO rules (name, source, spec, created_us, updated_us) VALUES ($1, $2, $3, $4, $5)
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
        let r =
            query("UPDATE rules SET spec = $1, updated_us = $2 WHERE name = $3 AND source = 'api'")
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
        let mut tx = self.pool.begin().await?;
        let r = query("DELETE FROM rules WHERE name = $1 AND source = 'api'")
            .bind(name)
            .execute(&mut tx)
            .await?;
        if r.rows_affected() == 1 {
            query("DELETE FROM rule_runs WHERE rule_name = $1")
                .bind(name)
                .execute(&mut tx)
                .await?;
        }
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }

    pub async fn get_rule(&self, name: &str) -> Result<Option<StoredRule>, DbError> {
        let row = query("SELECT * FROM rules WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(rule_from_row).transpose()
    }

    /// Every rule, by name.
    pub async fn list_rules(&self) -> Result<Vec<StoredRule>, DbError> {
        let rows = query("SELECT * FROM rules ORDER BY name")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(rule_from_row).collect()
    }

    /// Make the configuration's rules the stored config rules: others removed, these inserted or
    /// replaced (a config rule replaces an API rule of the same name).
    pub async fn sync_config_rules(&self, specs: &[RuleSpec]) -> Result<(), DbError> {
        let now = now_us();
        let mut tx = self.pool.begin().await?;
        tx.lock(CONFIG_RULES_LOCK).await?;
        let names = to_json(&specs.iter().map(|s| &s.name).collect::<Vec<_>>());
        let sql = format!(
            "DELETE FROM rules WHERE source = 'config' AND name NOT IN {}",
            self.dialect().json_strings(1)
        );
        assembled(sql).bind(names).execute(&mut tx).await?;
        for s in specs {
            query(
                "INSERT INTO rules (name, source, spec, created_us, updated_us) VALUES ($1, 'config', $2, $3, $4)
                 ON CONFLICT (name) DO UPDATE SET source = 'config', spec = excluded.spec,
                     updated_us = excluded.updated_us
                 WHERE rules.spec <> excluded.spec OR rules.source <> 'config'",
            )
            .bind(&s.name)
            .bind(to_json(s))
            .bind(now)
            .bind(now)
            .execute(&mut tx)
            .await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Record that a rule fires for a series; `None` when it already fired for this content.
    pub async fn insert_run(&self, run: &NewRun<'_>) -> Result<Option<String>, DbError> {
        let id = JobId::generate().to_string();
        let r = query(
            "INSERT INTO rule_runs (id, rule_name, content_hash, series_id, series_uid, calling_ae, state,
                                    created_us)
             VALUES ($1, $2, $3, $4, $5, $6, 'running', $7) ON CONFLICT (rule_name, content_hash) DO NOTHING",
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
        query("UPDATE rule_runs SET job_id = $1 WHERE id = $2")
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
        query("UPDATE rule_runs SET state = $1, error = COALESCE($2, error) WHERE id = $3")
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
        let mut tx = self.pool.begin().await?;
        let r = query(
            "UPDATE rule_runs SET state = 'done', error = COALESCE($1, error) WHERE id = $2 AND state = 'running'",
        )
        .bind(error.map(to_json))
        .bind(&run.id)
        .execute(&mut tx)
        .await?;
        if r.rows_affected() != 1 {
            tx.rollback().await?;
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
        let rows = query(
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
        let rows = query(
            "SELECT * FROM rule_runs WHERE (CAST($1 AS TEXT) IS NULL OR rule_name = $2) ORDER BY created_us DESC, id DESC
             LIMIT $3",
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
        let row = query("SELECT * FROM rule_runs WHERE job_id = $1")
            .bind(job.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(run_from_row).transpose()
    }
}
