//! Processing rules: create, replace, delete, fetch and list them (rules of the configuration file are
//! read again at every start and are read-only here), and fire them on series as they are assembled —
//! whether received by C-STORE or uploaded over HTTP — once per rule and series content.

use serde_json::{Value, json};

use super::error::{AppError, AppResult, refused};
use super::{App, OpenError};
use crate::config::ConfigError;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::deliveries::{Delivery, DeliveryFilter, NewRun, RuleRun, RunState};
use crate::jobs::ingest::Ingested;
use crate::jobs::model::rfc3339;
use crate::jobs::rules::{
    RuleProblem, RuleSource, RuleSpec, SeriesFacts, StoredRule, content_hash,
};
use crate::storage::JobId;

fn rule_problem(p: RuleProblem) -> AppError {
    match p {
        RuleProblem::Invalid(m) => refused(ErrorCode::InvalidRule, m),
        RuleProblem::BadPattern(m) => refused(ErrorCode::InvalidPattern, m),
        RuleProblem::UnknownPeer(m) => refused(ErrorCode::UnknownPeer, m),
    }
}

fn not_found(name: &str) -> AppError {
    refused(
        ErrorCode::RuleNotFound,
        format!("no rule {:?}", name.chars().take(80).collect::<String>()),
    )
}

/// The JSON representation of a rule, with its recent runs (each with its delivery ids) when given.
pub fn rule_json(r: &StoredRule, runs: Option<&[(RuleRun, Vec<String>)]>) -> Value {
    let mut v = serde_json::to_value(&r.spec).unwrap_or_default();
    if let Some(m) = v.as_object_mut() {
        m.insert("source".into(), json!(r.source));
        m.insert("created_at".into(), json!(rfc3339(r.created_us)));
        m.insert("updated_at".into(), json!(rfc3339(r.updated_us)));
        m.insert(
            "links".into(),
            json!({"self": format!("/v1/rules/{}", r.spec.name),
                   "deliveries": format!("/v1/deliveries?rule={}", r.spec.name)}),
        );
        if let Some(runs) = runs {
            m.insert(
                "runs".into(),
                runs.iter().map(|(run, d)| run_json(run, d)).collect(),
            );
        }
    }
    v
}

/// A rule run: the series it fired for, the job it started and the deliveries of its results.
pub fn run_json(r: &RuleRun, deliveries: &[String]) -> Value {
    let mut v = json!({
        "id": r.id,
        "series_id": r.series_id,
        "series_uid": r.series_uid,
        "content_hash": r.content_hash,
        "state": r.state,
        "created_at": rfc3339(r.created_us),
        "deliveries": deliveries,
    });
    if let Some(ae) = &r.calling_ae {
        v["calling_ae"] = json!(ae);
    }
    if let Some(j) = r.job_id {
        v["job_id"] = json!(j);
    }
    if let Some(e) = &r.error {
        v["error"] = json!(e);
    }
    v
}

/// The parts of a job's view that say what made it and where its results went: `rule` (the rule run that
/// made it, with its source series) and `deliveries` (each with its destination and state), and their links.
pub fn job_origin_json(run: Option<&RuleRun>, deliveries: &[Delivery]) -> Value {
    let mut v = json!({
        "deliveries": deliveries
            .iter()
            .map(|d| json!({
                "id": d.id,
                "destination": d.destination,
                "state": d.state,
                "links": {"self": format!("/v1/deliveries/{}", d.id)},
            }))
            .collect::<Vec<_>>(),
    });
    if let Some(r) = run {
        v["rule"] = json!({
            "name": r.rule_name,
            "run_id": r.id,
            "state": r.state,
            "series_id": r.series_id,
            "series_uid": r.series_uid,
            "links": {
                "self": format!("/v1/rules/{}", r.rule_name),
                "series": format!("/v1/series/{}", r.series_id),
            },
        });
        if let Some(ae) = &r.calling_ae {
            v["rule"]["calling_ae"] = json!(ae);
        }
    }
    v
}

impl App {
    /// The rule run that made job `id` and the job's deliveries (none of either for a job no rule made and
    /// that was never sent).
    pub async fn job_origin(&self, id: JobId) -> AppResult<(Option<RuleRun>, Vec<Delivery>)> {
        let run = self.db.run_of_job(id).await?;
        let deliveries = self
            .db
            .list_deliveries(&DeliveryFilter {
                job_id: Some(id),
                limit: 200,
                ..DeliveryFilter::default()
            })
            .await?;
        Ok((run, deliveries))
    }

    fn parse_rule(&self, body: Value) -> AppResult<RuleSpec> {
        let spec: RuleSpec = super::error::parse_body(body)?;
        spec.validate_at(|ae| self.settings.dicom.is_destination(ae))
            .map_err(|(p, at)| match rule_problem(p) {
                AppError::Refused(p) => AppError::Refused(p.at(at)),
                other => other,
            })?;
        Ok(spec)
    }

    /// Store the configuration file's rules as the config rules (called at start).
    pub(super) async fn load_config_rules(&self) -> Result<(), OpenError> {
        let mut specs = Vec::new();
        for (i, v) in self.settings.dicom.rules.iter().enumerate() {
            let invalid = |reason: String| {
                OpenError::Config(ConfigError::Invalid {
                    name: "dicom.rules",
                    reason: format!("rule {i}: {reason}"),
                })
            };
            let spec = self.parse_rule(v.clone()).map_err(|e| match e {
                AppError::Refused(p) => invalid(p.detail),
                other => invalid(other.to_string()),
            })?;
            specs.push(spec);
        }
        self.db.sync_config_rules(&specs).await?;
        if !specs.is_empty() {
            tracing::info!(
                rules = specs.len(),
                "rules of the configuration file loaded"
            );
        }
        Ok(())
    }

    /// Create a rule (`POST /v1/rules`).
    pub async fn create_rule(&self, body: Value) -> AppResult<StoredRule> {
        let spec = self.parse_rule(body)?;
        if !self.db.insert_rule(&spec, RuleSource::Api).await? {
            return Err(refused(
                ErrorCode::RuleExists,
                format!("a rule named {:?} exists", spec.name),
            ));
        }
        tracing::info!(rule = %spec.name, "rule created");
        self.get_rule(&spec.name).await
    }

    /// Replace an API rule (`PUT /v1/rules/{name}`); the body's name must be `name`.
    pub async fn replace_rule(&self, name: &str, body: Value) -> AppResult<StoredRule> {
        let spec = self.parse_rule(body)?;
        if spec.name != name {
            return Err(refused(
                ErrorCode::InvalidRule,
                "the body's `name` differs from the rule's name in the path",
            ));
        }
        self.writable(name).await?;
        if !self.db.replace_rule(&spec).await? {
            return Err(not_found(name));
        }
        self.get_rule(name).await
    }

    /// Delete an API rule and its runs (its deliveries stay).
    pub async fn delete_rule(&self, name: &str) -> AppResult<()> {
        self.writable(name).await?;
        if !self.db.delete_rule(name).await? {
            return Err(not_found(name));
        }
        tracing::info!(rule = %name, "rule deleted");
        Ok(())
    }

    async fn writable(&self, name: &str) -> AppResult<()> {
        match self.db.get_rule(name).await? {
            None => Err(not_found(name)),
            Some(r) if r.source == RuleSource::Config => Err(refused(
                ErrorCode::RuleReadOnly,
                format!(
                    "rule {name:?} comes from the configuration file (`dicom.rules`); change it there"
                ),
            )),
            Some(_) => Ok(()),
        }
    }

    pub async fn get_rule(&self, name: &str) -> AppResult<StoredRule> {
        self.db.get_rule(name).await?.ok_or_else(|| not_found(name))
    }

    pub async fn list_rules(&self) -> AppResult<Vec<StoredRule>> {
        Ok(self.db.list_rules().await?)
    }

    /// The newest runs of a rule, each with its delivery ids.
    pub async fn rule_runs(
        &self,
        name: &str,
        limit: u32,
    ) -> AppResult<Vec<(RuleRun, Vec<String>)>> {
        let mut out = Vec::new();
        for run in self.db.list_runs(Some(name), limit).await? {
            let d = self.db.delivery_ids_of_run(&run.id).await?;
            out.push((run, d));
        }
        Ok(out)
    }

    /// Fire the enabled rules on the series an ingestion assembled (`calling_ae`: who sent them by
    /// C-STORE; `None` for an HTTP upload). A rule runs once per series content; failures are logged, never
    /// returned: the series are recorded whatever the rules do.
    pub async fn fire_rules(&self, ingested: &Ingested, calling_ae: Option<&str>) {
        if let Err(e) = self.fire_rules_inner(ingested, calling_ae).await {
            tracing::error!(error = %e, "processing rules could not run");
        }
    }

    async fn fire_rules_inner(
        &self,
        ingested: &Ingested,
        calling_ae: Option<&str>,
    ) -> AppResult<()> {
        let rules: Vec<RuleSpec> = self
            .db
            .list_rules()
            .await?
            .into_iter()
            .map(|r| r.spec)
            .filter(|r| r.enabled)
            .collect();
        if rules.is_empty() {
            return Ok(());
        }
        for outcome in &ingested.series {
            let Some(series) = &outcome.series else {
                continue;
            };
            let rep = &outcome.report;
            let facts = SeriesFacts {
                modality: rep.modality.clone(),
                body_part: rep.body_part.clone(),
                series_description: rep.description.clone(),
                image_type: rep.image_type.clone(),
                slice_thickness_mm: rep.slice_thickness_mm,
                instances: rep.instances,
                calling_ae: calling_ae.map(str::to_string),
            };
            let hash = content_hash(series);
            for rule in rules.iter().filter(|r| r.matches(&facts)) {
                let run = NewRun {
                    rule_name: &rule.name,
                    content_hash: &hash,
                    series_id: series.id,
                    series_uid: &series.series_uid,
                    facts: &facts,
                };
                let Some(run_id) = self.db.insert_run(&run).await? else {
                    tracing::info!(rule = %rule.name, series_uid = %series.series_uid, "rule already ran on this series content");
                    continue;
                };
                let t = rule.template();
                let body = json!({"kind": "volume", "input": series.id, "steps": t.steps,
                                  "products": t.products});
                match self.submit_job(body, None).await {
                    Ok(s) => {
                        self.db.set_run_job(&run_id, s.job.id).await?;
                        tracing::info!(rule = %rule.name, series_uid = %series.series_uid, job_id = %s.job.id, "rule fired");
                    }
                    Err(AppError::Refused(p)) => {
                        tracing::warn!(rule = %rule.name, code = p.code.code(), detail = %p.detail, "rule's job refused");
                        self.db
                            .set_run_state(&run_id, RunState::Refused, Some(&p))
                            .await?;
                    }
                    Err(e) => {
                        self.db
                            .set_run_state(&run_id, RunState::Refused, Some(&Problem::internal()))
                            .await?;
                        return Err(e);
                    }
                }
            }
        }
        Ok(())
    }
}
