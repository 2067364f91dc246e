//! The conformance suite of the DICOM node's tables on [`Database`]: what both adapters must do with rules,
//! rule runs, deliveries and the instance index, as async checks that panic on a violation. A test file
//! instantiates all of them for one adapter with one line:
//!
//! ```ignore
//! ctrecon::node_tables_conformance!(async { Database::from(my_adapter().await) });
//! ```
//! (the expression makes a fresh, empty database for each check; `optional` takes a future of an `Option`,
//! `None` making each check return at once, as for `job_store_conformance!`).

use serde_json::json;

use super::Database;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::deliveries::{NewRun, RunState};
use crate::jobs::lifecycle::{Lease, Outcome};
use crate::jobs::model::{Inserted, Job, JobSpec, JobStatus, now_us};
use crate::jobs::rules::{RuleSource, RuleSpec, SeriesFacts};
use crate::jobs::store::JobStore;
use crate::jobs::store::conformance::{sample_job, sample_result};
use crate::storage::{JobId, SeriesId};

mod deliveries;
mod instances;

pub use deliveries::*;
pub use instances::*;

/// A rule named `name` running the lung protocol and sending to `destinations`.
fn rule(name: &str, destinations: &[&str]) -> RuleSpec {
    match serde_json::from_value(json!({
        "name": name, "protocol": "lung", "destinations": destinations,
    })) {
        Ok(r) => r,
        Err(e) => panic!("the sample rule parses: {e}"),
    }
}

/// A volume job (what rules start and what the index holds the results of), queued.
fn volume_job() -> Job {
    let request = match serde_json::from_value(json!({
        "kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
    })) {
        Ok(r) => r,
        Err(e) => panic!("the sample volume request parses: {e}"),
    };
    Job::queued(JobSpec::Volume(request), 1024, now_us())
}

/// Insert `job`, run it and end it with `outcome`; its id.
async fn finished(db: &Database, job: Job, outcome: Outcome) -> JobId {
    assert_eq!(db.insert_job(&job, None).await.ok(), Some(Inserted::New));
    let lease = Lease {
        expires_us: now_us() + 30_000_000,
    };
    assert_eq!(JobStore::claim(db, job.id, lease).await.ok(), Some(1));
    assert!(JobStore::finish(db, job.id, 1, &outcome).await.is_ok());
    job.id
}

fn succeeded() -> Outcome {
    Outcome::Succeeded(Box::new(sample_result()))
}

/// Record a run of rule `rule` for a series with content `hash`; its id, or `None` when it ran already.
async fn run(db: &Database, rule: &str, hash: &str) -> Option<String> {
    let facts = SeriesFacts {
        calling_ae: Some("MODALITY".into()),
        ..SeriesFacts::default()
    };
    let r = NewRun {
        rule_name: rule,
        content_hash: hash,
        series_id: SeriesId::generate(),
        series_uid: "1.2.3.4",
        facts: &facts,
    };
    match db.insert_run(&r).await {
        Ok(id) => id,
        Err(e) => panic!("recording a run: {e}"),
    }
}

/// A rule is created once under its name, read back, replaced, listed by name and deleted.
pub async fn rules_are_created_replaced_listed_and_deleted(db: &Database) {
    let lung = rule("lung", &["PACS"]);
    assert_eq!(
        db.insert_rule(&lung, RuleSource::Api).await.ok(),
        Some(true)
    );
    assert_eq!(
        db.insert_rule(&lung, RuleSource::Api).await.ok(),
        Some(false)
    );
    assert_eq!(
        db.insert_rule(&rule("bone", &[]), RuleSource::Api)
            .await
            .ok(),
        Some(true)
    );
    let back = db
        .get_rule("lung")
        .await
        .ok()
        .flatten()
        .expect("the rule reads back");
    assert_eq!((back.spec, back.source), (lung, RuleSource::Api));
    let changed = rule("lung", &["PACS", "ARCHIVE"]);
    assert_eq!(db.replace_rule(&changed).await.ok(), Some(true));
    assert_eq!(db.replace_rule(&rule("none", &[])).await.ok(), Some(false));
    let listed: Vec<(String, Vec<String>)> = db
        .list_rules()
        .await
        .expect("rules")
        .into_iter()
        .map(|r| (r.spec.name, r.spec.destinations))
        .collect();
    assert_eq!(
        listed,
        vec![
            ("bone".to_string(), vec![]),
            (
                "lung".to_string(),
                vec!["PACS".to_string(), "ARCHIVE".to_string()]
            )
        ]
    );
    assert_eq!(db.delete_rule("lung").await.ok(), Some(true));
    assert_eq!(db.delete_rule("lung").await.ok(), Some(false));
    assert!(matches!(db.get_rule("lung").await, Ok(None)));
}

/// The configuration's rules replace API rules of their names, stay read-only through the API, and go when
/// the configuration drops them; API rules of other names stay.
pub async fn config_rules_are_synced_and_read_only(db: &Database) {
    assert_eq!(
        db.insert_rule(&rule("a", &[]), RuleSource::Api).await.ok(),
        Some(true)
    );
    assert_eq!(
        db.insert_rule(&rule("c", &[]), RuleSource::Api).await.ok(),
        Some(true)
    );
    let a = rule("a", &["PACS"]);
    assert!(
        db.sync_config_rules(&[a.clone(), rule("b", &[])])
            .await
            .is_ok()
    );
    let stored = db.get_rule("a").await.ok().flatten().expect("rule a");
    assert_eq!(
        (stored.spec, stored.source),
        (a.clone(), RuleSource::Config)
    );
    assert_eq!(db.replace_rule(&a).await.ok(), Some(false));
    assert_eq!(db.delete_rule("a").await.ok(), Some(false));
    assert!(db.sync_config_rules(&[rule("b", &[])]).await.is_ok());
    let names: Vec<(String, RuleSource)> = db
        .list_rules()
        .await
        .expect("rules")
        .into_iter()
        .map(|r| (r.spec.name, r.source))
        .collect();
    assert_eq!(
        names,
        vec![
            ("b".to_string(), RuleSource::Config),
            ("c".to_string(), RuleSource::Api)
        ]
    );
}

/// A rule runs once per series content: the same content again records nothing, changed content or another
/// rule records a run; runs are listed newest first, carry their job and state, and go with their rule.
pub async fn a_rule_runs_once_per_series_content(db: &Database) {
    assert_eq!(
        db.insert_rule(&rule("r", &[]), RuleSource::Api).await.ok(),
        Some(true)
    );
    let first = run(db, "r", "h1").await.expect("a first run");
    assert_eq!(run(db, "r", "h1").await, None);
    let second = run(db, "r", "h2").await.expect("changed content runs");
    let other = run(db, "s", "h1").await.expect("another rule runs");
    let of_r: Vec<String> = db
        .list_runs(Some("r"), 10)
        .await
        .expect("runs")
        .into_iter()
        .map(|r| r.id)
        .collect();
    assert_eq!(of_r, vec![second.clone(), first.clone()]);
    assert_eq!(db.list_runs(None, 10).await.expect("runs").len(), 3);
    assert_eq!(db.list_runs(None, 1).await.expect("runs").len(), 1);
    let job = JobId::generate();
    assert!(db.set_run_job(&first, job).await.is_ok());
    let back = db
        .run_of_job(job)
        .await
        .ok()
        .flatten()
        .expect("the run of the job");
    assert_eq!(
        (
            back.id.as_str(),
            back.rule_name.as_str(),
            back.content_hash.as_str(),
            back.state
        ),
        (first.as_str(), "r", "h1", RunState::Running)
    );
    assert_eq!(back.calling_ae.as_deref(), Some("MODALITY"));
    let p = Problem::new(ErrorCode::InvalidRule, "refused");
    assert!(
        db.set_run_state(&other, RunState::Refused, Some(&p))
            .await
            .is_ok()
    );
    let refused = db.list_runs(Some("s"), 10).await.expect("runs").remove(0);
    assert_eq!(refused.state, RunState::Refused);
    assert_eq!(
        refused.error.map(|e| (e.code, e.detail)),
        Some((ErrorCode::InvalidRule, "refused".to_string()))
    );
    assert_eq!(db.delete_rule("r").await.ok(), Some(true));
    assert!(db.list_runs(Some("r"), 10).await.expect("runs").is_empty());
}

/// A run whose job finished is listed until it is completed; completing queues its deliveries once, even
/// when two workers complete it at the same time; a failed job's run records the job's problem.
pub async fn runs_of_finished_jobs_complete_once(db: &Database) {
    let job = sample_job(now_us());
    let id = run(db, "r", "h1").await.expect("a run");
    assert!(db.set_run_job(&id, job.id).await.is_ok());
    assert_eq!(db.insert_job(&job, None).await.ok(), Some(Inserted::New));
    assert!(db.runs_with_finished_jobs().await.expect("runs").is_empty());
    let lease = Lease {
        expires_us: now_us() + 30_000_000,
    };
    assert_eq!(JobStore::claim(db, job.id, lease).await.ok(), Some(1));
    assert!(JobStore::finish(db, job.id, 1, &succeeded()).await.is_ok());
    let listed = db.runs_with_finished_jobs().await.expect("runs");
    assert_eq!(listed.len(), 1);
    assert_eq!(
        (listed[0].0.id.as_str(), listed[0].1),
        (id.as_str(), JobStatus::Succeeded)
    );
    let closing = listed[0].0.clone();
    let dest = ["PACS".to_string(), "ARCHIVE".to_string()];
    let (a, b) = tokio::join!(
        db.complete_run(&closing, job.id, &dest, None),
        db.complete_run(&closing, job.id, &dest, None)
    );
    let (a, b) = (a.expect("complete"), b.expect("complete"));
    let queued = match (a, b) {
        (Some(q), None) | (None, Some(q)) => q,
        other => panic!("exactly one completion queues deliveries: {other:?}"),
    };
    assert_eq!(queued.len(), 2);
    let mut sorted = queued.clone();
    sorted.sort();
    assert_eq!(db.delivery_ids_of_run(&id).await.expect("ids"), sorted);
    assert!(db.runs_with_finished_jobs().await.expect("runs").is_empty());
    assert_eq!(
        db.run_of_job(job.id).await.ok().flatten().map(|r| r.state),
        Some(RunState::Done)
    );
    let d = db
        .get_delivery(&queued[0])
        .await
        .ok()
        .flatten()
        .expect("a delivery");
    assert_eq!(
        (d.run_id.as_deref(), d.rule_name.as_deref(), d.job_id),
        (Some(id.as_str()), Some("r"), job.id)
    );

    let p = Problem::new(ErrorCode::ReconstructionFailed, "no");
    let failed = finished(db, sample_job(now_us()), Outcome::Failed(p.clone())).await;
    let id = run(db, "r", "h2").await.expect("a run");
    assert!(db.set_run_job(&id, failed).await.is_ok());
    let listed = db.runs_with_finished_jobs().await.expect("runs");
    assert_eq!(
        listed
            .iter()
            .map(|(r, s)| (r.id.clone(), *s))
            .collect::<Vec<_>>(),
        vec![(id.clone(), JobStatus::Failed)]
    );
    assert_eq!(
        db.complete_run(&listed[0].0, failed, &[], Some(&p))
            .await
            .ok(),
        Some(Some(vec![]))
    );
    let done = db.run_of_job(failed).await.ok().flatten().expect("the run");
    assert_eq!(
        (done.state, done.error.map(|e| e.code)),
        (RunState::Done, Some(ErrorCode::ReconstructionFailed))
    );
}

/// Instantiate every check as a `#[tokio::test]` for the database `$make` builds (see the module notes).
#[macro_export]
macro_rules! node_tables_conformance {
    (optional $make:expr) => {
        $crate::node_tables_conformance!(@all optional $make);
    };
    (@all $mode:ident $make:expr) => {
        $crate::node_tables_conformance!(@each $mode $make;
            rules_are_created_replaced_listed_and_deleted,
            config_rules_are_synced_and_read_only,
            a_rule_runs_once_per_series_content,
            runs_of_finished_jobs_complete_once,
            deliveries_are_listed_newest_first_and_filtered,
            a_due_delivery_is_claimed_once_and_one_per_destination,
            a_failed_attempt_backs_off_until_due_again,
            instance_statuses_are_recorded_and_retry_resends_the_failed,
            only_expired_claims_are_requeued,
            received_instances_are_indexed_and_read_by_scope,
            a_received_copy_replaces_the_one_indexed_before,
            a_jobs_results_are_indexed_once,
            pending_instances_are_claimed_once_and_settled,
        );
    };
    (@each $mode:ident $make:expr; $($case:ident),* $(,)?) => {
        $( $crate::node_tables_conformance!(@one $mode $make; $case); )*
    };
    (@one plain $make:expr; $case:ident) => {
        #[tokio::test]
        async fn $case() {
            let db = $make.await;
            $crate::jobs::database::conformance::$case(&db).await;
        }
    };
    (@one optional $make:expr; $case:ident) => {
        #[tokio::test]
        async fn $case() {
            let Some(db) = $make.await else {
                return;
            };
            $crate::jobs::database::conformance::$case(&db).await;
        }
    };
    ($make:expr) => {
        $crate::node_tables_conformance!(@all plain $make);
    };
}
