//! The `JobStore` conformance suite, run against every adapter: SQLite (the default), PostgreSQL (on a
//! throwaway cluster; skipped with one line where PostgreSQL is not installed, unless
//! `CTRECON_REQUIRE_PEERS=1`) and an in-memory store written here.

use std::collections::HashMap;
use std::sync::Mutex;

use ctrecon::jobs::lifecycle::{IllegalTransition, transition};
use ctrecon::jobs::model::now_us;
use ctrecon::jobs::store::{Expired, Renewed, StoreResult};
use ctrecon::jobs::{
    Db, IdempotencyKey, Inserted, Job, JobFilter, JobState, JobStatus, JobStore, Lease, Outcome,
    StoreError, Transition,
};
use ctrecon::storage::JobId;
use futures_util::FutureExt;
use futures_util::future::BoxFuture;

mod sqlite {
    use super::*;

    /// A fresh database in a directory that lives as long as the test process.
    async fn fresh() -> Db {
        let dir = tempfile::tempdir().expect("temp dir").keep();
        Db::open(&dir.join("ctrecon.sqlite"))
            .await
            .expect("database")
    }

    ctrecon::job_store_conformance!(fresh());
}

use crate::cluster;

mod postgres {
    use super::*;
    use ctrecon::jobs::PgDb;

    /// A fresh database on the throwaway cluster, or `None` (one skip line) without PostgreSQL.
    async fn fresh() -> Option<PgDb> {
        let url = cluster::database_url("job_store::postgres")?;
        Some(
            PgDb::open(&url, std::time::Duration::from_secs(10))
                .await
                .expect("database"),
        )
    }

    ctrecon::job_store_conformance!(optional fresh());
}

mod memory {
    use super::*;

    ctrecon::job_store_conformance!(async { MemoryStore::default() });
}

/// A job store in memory: jobs with their lease, and Idempotency-Key records.
#[derive(Default)]
struct MemoryStore {
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    jobs: HashMap<JobId, (Job, Option<Lease>)>,
    keys: HashMap<(String, String), (String, String)>,
}

impl MemoryStore {
    /// Apply `event` to job `id` under the lock, then `f` to the job moved to its new status.
    fn apply<T>(
        &self,
        id: JobId,
        event: Transition,
        f: impl FnOnce(&mut Job, &mut Option<Lease>) -> T,
    ) -> StoreResult<T> {
        let mut inner = self.inner.lock().expect("lock");
        let Some((job, lease)) = inner.jobs.get_mut(&id) else {
            return Err(IllegalTransition { from: None, event }.into());
        };
        job.status = transition(job.status, event)?;
        Ok(f(job, lease))
    }
}

impl JobStore for MemoryStore {
    fn insert<'a>(
        &'a self,
        job: &'a Job,
        key: Option<&'a IdempotencyKey>,
    ) -> BoxFuture<'a, StoreResult<Inserted>> {
        let inserted = (|| {
            let mut inner = self.inner.lock().expect("lock");
            if let Some(k) = key {
                let slot = (k.route.to_string(), k.key.clone());
                if let Some((resource_id, fingerprint)) = inner.keys.get(&slot) {
                    return Inserted::Existing {
                        resource_id: resource_id.clone(),
                        fingerprint: fingerprint.clone(),
                    };
                }
                inner
                    .keys
                    .insert(slot, (job.id.to_string(), k.fingerprint.clone()));
            }
            inner.jobs.insert(job.id, (job.clone(), None));
            Inserted::New
        })();
        async move { Ok(inserted) }.boxed()
    }

    fn get(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<Job>>> {
        let job = self
            .inner
            .lock()
            .expect("lock")
            .jobs
            .get(&id)
            .map(|(j, _)| j.clone());
        async move { Ok(job) }.boxed()
    }

    fn state(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<JobState>>> {
        let state = self
            .inner
            .lock()
            .expect("lock")
            .jobs
            .get(&id)
            .map(|(j, lease)| match j.status {
                JobStatus::Queued => JobState::Queued,
                JobStatus::Running => JobState::Running {
                    attempt: j.attempts,
                    lease: *lease,
                },
                JobStatus::Succeeded => {
                    JobState::Succeeded(Box::new(j.result.clone().expect("a result")))
                }
                JobStatus::Failed => JobState::Failed(j.error.clone().expect("a problem")),
                JobStatus::Canceled => JobState::Canceled,
            });
        async move { Ok(state) }.boxed()
    }

    fn list<'a>(&'a self, f: &'a JobFilter) -> BoxFuture<'a, StoreResult<Vec<Job>>> {
        let inner = self.inner.lock().expect("lock");
        let mut jobs: Vec<Job> = inner
            .jobs
            .values()
            .map(|(j, _)| j)
            .filter(|j| f.statuses.is_empty() || f.statuses.contains(&j.status))
            .filter(|j| f.kind.as_ref().is_none_or(|k| *k == j.kind))
            .filter(|j| f.created_after_us.is_none_or(|t| j.created_us > t))
            .filter(|j| f.created_before_us.is_none_or(|t| j.created_us < t))
            .filter(|j| f.before_id.is_none_or(|b| j.id.to_string() < b.to_string()))
            .cloned()
            .collect();
        jobs.sort_by_key(|j| std::cmp::Reverse(j.id.to_string()));
        jobs.truncate(f.limit as usize);
        async move { Ok(jobs) }.boxed()
    }

    fn queued(&self, limit: u32) -> BoxFuture<'_, StoreResult<Vec<(JobId, u64)>>> {
        let inner = self.inner.lock().expect("lock");
        let mut q: Vec<&Job> = inner
            .jobs
            .values()
            .map(|(j, _)| j)
            .filter(|j| j.status == JobStatus::Queued)
            .collect();
        q.sort_by_key(|j| j.id.to_string());
        let out: Vec<(JobId, u64)> = q
            .iter()
            .take(limit as usize)
            .map(|j| (j.id, j.estimate_bytes))
            .collect();
        async move { Ok(out) }.boxed()
    }

    fn claim(&self, id: JobId, lease: Lease) -> BoxFuture<'_, StoreResult<u32>> {
        let r = self.apply(id, Transition::Claim, |j, l| {
            j.attempts += 1;
            j.started_us = Some(now_us());
            j.progress = 0;
            j.stage = "starting".into();
            *l = Some(lease);
            j.attempts
        });
        async move { r }.boxed()
    }

    fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        lease: Lease,
    ) -> BoxFuture<'_, StoreResult<Renewed>> {
        let mut inner = self.inner.lock().expect("lock");
        let r = match inner.jobs.get_mut(&id) {
            Some((j, l)) if j.status == JobStatus::Running && j.attempts == attempt => {
                *l = Some(lease);
                Ok(Renewed {
                    cancel_requested: j.cancel_requested,
                })
            }
            _ => Err(StoreError::LeaseLost),
        };
        async move { r }.boxed()
    }

    fn set_progress<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &'a str,
    ) -> BoxFuture<'a, StoreResult<()>> {
        let mut inner = self.inner.lock().expect("lock");
        if let Some((j, _)) = inner.jobs.get_mut(&id)
            && j.status == JobStatus::Running
            && j.attempts == attempt
        {
            j.progress = progress;
            j.stage = stage.to_string();
        }
        async move { Ok(()) }.boxed()
    }

    fn hand_back(&self, id: JobId, attempt: u32) -> BoxFuture<'_, StoreResult<()>> {
        let (asked_to_cancel, stale) =
            self.inner
                .lock()
                .expect("lock")
                .jobs
                .get(&id)
                .map_or((false, false), |(j, _)| {
                    (
                        j.cancel_requested,
                        j.status == JobStatus::Running && j.attempts != attempt,
                    )
                });
        let r = if stale {
            Err(StoreError::LeaseLost)
        } else if asked_to_cancel {
            Err(IllegalTransition {
                from: Some(JobStatus::Running),
                event: Transition::HandBack,
            }
            .into())
        } else {
            self.apply(id, Transition::HandBack, |j, l| {
                j.attempts = j.attempts.saturating_sub(1);
                j.progress = 0;
                j.stage = "requeued".into();
                j.started_us = None;
                *l = None;
            })
        };
        async move { r }.boxed()
    }

    fn expire_leases(&self, now: i64, max_attempts: u32) -> BoxFuture<'_, StoreResult<Expired>> {
        let mut inner = self.inner.lock().expect("lock");
        let mut e = Expired::default();
        for (j, l) in inner.jobs.values_mut() {
            if j.status != JobStatus::Running || l.is_none_or(|l| l.expires_us >= now) {
                continue;
            }
            *l = None;
            if j.attempts >= max_attempts {
                j.status = JobStatus::Failed;
                j.stage = "failed".into();
                j.finished_us = Some(now);
                j.error = Some(ctrecon::error_code::Problem::new(
                    ctrecon::error_code::ErrorCode::AttemptsExhausted,
                    "the job's worker was lost too often",
                ));
                e.failed.push(j.id);
            } else {
                j.status = JobStatus::Queued;
                j.stage = "requeued".into();
                j.progress = 0;
                j.started_us = None;
                e.requeued.push(j.id);
            }
        }
        async move { Ok(e) }.boxed()
    }

    fn finish<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        outcome: &'a Outcome,
    ) -> BoxFuture<'a, StoreResult<()>> {
        let stale = self
            .inner
            .lock()
            .expect("lock")
            .jobs
            .get(&id)
            .is_some_and(|(j, _)| j.status == JobStatus::Running && j.attempts != attempt);
        if stale {
            return async { Err(StoreError::LeaseLost) }.boxed();
        }
        let r = self.apply(id, outcome.transition(), |j, l| {
            *l = None;
            j.stage = j.status.as_str().into();
            j.finished_us = Some(now_us());
            match outcome {
                Outcome::Succeeded(r) => {
                    j.result = Some((**r).clone());
                    j.progress = 100;
                }
                Outcome::Failed(p) => j.error = Some(p.clone()),
                Outcome::Canceled => {}
            }
        });
        async move { r }.boxed()
    }

    fn cancel_queued(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        let running = self
            .inner
            .lock()
            .expect("lock")
            .jobs
            .get(&id)
            .is_some_and(|(j, _)| j.status == JobStatus::Running);
        let r = if running {
            Err(IllegalTransition {
                from: Some(JobStatus::Running),
                event: Transition::Cancel,
            }
            .into())
        } else {
            self.apply(id, Transition::Cancel, |j, _| {
                j.stage = "canceled".into();
                j.finished_us = Some(now_us());
            })
        };
        async move { r }.boxed()
    }

    fn request_cancel(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        if let Some((j, _)) = self.inner.lock().expect("lock").jobs.get_mut(&id)
            && j.status == JobStatus::Running
        {
            j.cancel_requested = true;
        }
        async move { Ok(()) }.boxed()
    }

    fn delete_finished(&self, id: JobId) -> BoxFuture<'_, StoreResult<bool>> {
        let mut inner = self.inner.lock().expect("lock");
        let finished = inner
            .jobs
            .get(&id)
            .is_some_and(|(j, _)| j.status.is_terminal());
        if finished {
            inner.jobs.remove(&id);
        }
        async move { Ok(finished) }.boxed()
    }
}

/// A dataset of kind `scan` (migration 20261211000001 in both dialects) and its import record.
fn scan_dataset() -> ctrecon::jobs::Dataset {
    use ctrecon::jobs::model::{ScanRecord, ScanValue};
    let geometry = serde_json::from_value(common_cone()).expect("geometry");
    ctrecon::jobs::Dataset {
        id: ctrecon::storage::DatasetId::generate(),
        kind: ctrecon::jobs::DatasetKind::Scan,
        geometry,
        shape: vec![4, 5, 7],
        dtype: "float32".into(),
        bytes: 688,
        sha256: "00".repeat(32),
        phantom: None,
        noise: None,
        scan: Some(ScanRecord {
            format: "nikon_xtek".into(),
            provenance: vec![ScanValue {
                key: "SrcToObject".into(),
                value: "100".into(),
                origin: "ball.xtekct [XTekCT] SrcToObject".into(),
            }],
            notes: vec!["a note".into()],
            preprocessing: vec![serde_json::json!({"step": "minus_log", "clamped_pixels": 3})],
            calibration: Some(ctrecon::scans::calibrate::Calibration {
                offset_u_mm: 0.45,
                centre: "read".into(),
                estimate: None,
                note: Some("a note".into()),
            }),
        }),
        created_us: now_us(),
    }
}

fn common_cone() -> serde_json::Value {
    crate::common::cone_geometry(4, 7)
}

#[tokio::test]
async fn a_scan_dataset_reads_back_from_sqlite_and_postgresql() {
    let d = scan_dataset();
    let dir = tempfile::tempdir().expect("temp dir");
    let db = Db::open(&dir.path().join("ctrecon.sqlite"))
        .await
        .expect("database");
    assert!(matches!(
        db.insert_dataset(&d, None).await,
        Ok(Inserted::New)
    ));
    assert_eq!(db.get_dataset(d.id).await.expect("get"), Some(d.clone()));
    if let Some(url) = cluster::database_url("job_store::scan_dataset") {
        let pg = ctrecon::jobs::PgDb::open(&url, std::time::Duration::from_secs(10))
            .await
            .expect("database");
        assert!(matches!(
            pg.insert_dataset(&d, None).await,
            Ok(Inserted::New)
        ));
        assert_eq!(pg.get_dataset(d.id).await.expect("get"), Some(d));
    }
}
