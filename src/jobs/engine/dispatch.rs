//! Scheduling: queued jobs are started oldest first while the concurrency limit and the memory budget allow,
//! each supervised on the worker pool (its lease renewed, its cancel flag watched) until it reaches a final
//! state or is handed back.

use crate::error_code::{ErrorCode, Problem};
use crate::jobs::imaging::{execute_volume, resolve_input};
use crate::jobs::lifecycle::Outcome;
use crate::jobs::model::JobSpec;
use crate::jobs::model::VolumeSource;
use crate::jobs::pull::{PULL_SHARE, Scaled};
use crate::jobs::run::{RunError, execute};
use crate::jobs::store::DbError;
use crate::jobs::store::{JobStore, StoreError};
use crate::recon::control::{Cancel, Control};
use crate::recon::grid::Limits;
use crate::storage::JobId;
use crate::telemetry::names;
use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::oneshot;
use tracing::Instrument;

use super::progress::{Latest, Sink};
use super::{Engine, Running, Work, heartbeat_interval};

impl Engine {
    pub(super) async fn schedule(self) {
        while !self.is_stopping() {
            if let Err(e) = self.dispatch().await {
                tracing::error!(error = %e, "scheduling failed");
            }
            tokio::select! {
                _ = self.inner.wake.notified() => {}
                _ = tokio::time::sleep(Duration::from_secs(2)) => {}
            }
        }
    }

    /// Start queued jobs, oldest first, while the concurrency limit and the memory budget allow.
    async fn dispatch(&self) -> Result<(), DbError> {
        let cfg = self.inner.config;
        for (id, estimate) in self.inner.db.queued(64).await? {
            {
                let Ok(mut running) = self.inner.running.lock() else {
                    return Ok(());
                };
                // Checked under the lock that `begin_stop` takes to flag the running jobs: a job is either
                // flagged by it or never registered.
                if self.is_stopping() {
                    return Ok(());
                }
                if running.contains_key(&id) {
                    continue;
                }
                let used = self.memory_in_use(running.values().map(|r| r.estimate).sum());
                if running.len() >= cfg.max_concurrent_jobs
                    || used.saturating_add(estimate) > cfg.memory_budget_bytes
                {
                    // First come, first served: the head of the queue waits for room.
                    return Ok(());
                }
                running.insert(
                    id,
                    Running {
                        cancel: Cancel::new(),
                        estimate,
                    },
                );
            }
            match JobStore::claim(&self.inner.db, id, self.lease_from_now()).await {
                Ok(attempt) => {
                    let engine = self.clone();
                    let span = tracing::info_span!("job", job_id = %id, attempt);
                    tokio::spawn(
                        async move { engine.supervise(id, attempt).await }.instrument(span),
                    );
                }
                // Claimed or canceled by someone else since it was listed.
                Err(StoreError::Illegal(_) | StoreError::LeaseLost) => self.release(id),
                Err(StoreError::Backend(e)) => {
                    self.release(id);
                    tracing::error!(error = %e, "claiming a job failed");
                    return Ok(());
                }
            }
        }
        Ok(())
    }

    fn release(&self, id: JobId) {
        if let Ok(mut r) = self.inner.running.lock() {
            r.remove(&id);
        }
        self.inner.wake.notify_one();
        self.inner.released.notify_waiters();
    }

    async fn supervise(self, id: JobId, attempt: u32) {
        /// Counts the job in [`names::RUNNING_HERE`] until supervision ends, whichever way it ends.
        struct Here;
        impl Drop for Here {
            fn drop(&mut self) {
                metrics::gauge!(names::RUNNING_HERE).decrement(1.0);
            }
        }
        metrics::gauge!(names::RUNNING_HERE).increment(1.0);
        let _here = Here;
        let started = Instant::now();
        let outcome = self.run(id, attempt).await;
        let db = &self.inner.db;
        if outcome == Outcome::Canceled && self.is_stopping() {
            // Stopped by a graceful stop, unless a client asked to cancel it (that ends canceled).
            match JobStore::hand_back(db, id, attempt).await {
                Ok(()) => {
                    tracing::info!("job handed back to the queue");
                    self.release(id);
                    if let Ok(Some(job)) = db.get_job(id).await {
                        self.publish(&job);
                    }
                    return;
                }
                Err(StoreError::Illegal(_) | StoreError::LeaseLost) => {}
                Err(StoreError::Backend(e)) => {
                    // Left running: the next start recovers it (counting the attempt, as after a crash).
                    tracing::error!(error = %e, "handing a job back failed");
                    self.release(id);
                    return;
                }
            }
        }
        let status = outcome.status();
        let recorded = match JobStore::finish(db, id, attempt, &outcome).await {
            Err(StoreError::LeaseLost) => {
                // This worker's lease expired and another attempt holds the job: its outcome is not ours.
                tracing::warn!("the job's lease was lost: its outcome is not recorded");
                Err(StoreError::LeaseLost)
            }
            r => {
                r.inspect_err(|e| tracing::error!(error = %e, "recording the end of a job failed"))
            }
        };
        self.release(id);
        if recorded.is_ok() {
            tracing::info!(status = status.as_str(), "job finished");
            metrics::counter!(names::JOBS_FINISHED, "status" => status.as_str()).increment(1);
            metrics::histogram!(names::JOB_DURATION, "status" => status.as_str())
                .record(started.elapsed().as_secs_f64());
        }
        match db.get_job(id).await {
            Ok(Some(job)) => self.publish(&job),
            Ok(None) => {}
            Err(e) => tracing::error!(error = %e, "reading a finished job failed"),
        }
    }

    async fn run(&self, id: JobId, attempt: u32) -> Outcome {
        let failed = Outcome::Failed;
        let db = &self.inner.db;
        let job = match db.get_job(id).await {
            Ok(Some(j)) => j,
            Ok(None) => return failed(Problem::internal()),
            Err(e) => {
                tracing::error!(error = %e, "loading a job failed");
                return failed(Problem::internal());
            }
        };
        self.publish(&job);
        let cancel = self
            .inner
            .running
            .lock()
            .ok()
            .and_then(|r| r.get(&id).map(|x| x.cancel.clone()))
            .unwrap_or_default();
        if job.cancel_requested {
            cancel.cancel();
        }
        let latest = Arc::new(Mutex::new(Latest::default()));
        let sink = Sink {
            id,
            latest: latest.clone(),
            engine: self.clone(),
        };
        // A series pulled from a PACS takes the first part of the progress bar.
        let mut pulled = false;
        let work = match &job.request {
            JobSpec::Reconstruction(req) => match db.get_dataset(req.input).await {
                Ok(Some(d)) => Work::Reconstruct(req.clone(), d),
                Ok(None) => {
                    return failed(Problem::new(
                        ErrorCode::DatasetNotFound,
                        "the input dataset no longer exists",
                    ));
                }
                Err(e) => {
                    tracing::error!(error = %e, "loading a dataset failed");
                    return failed(Problem::internal());
                }
            },
            JobSpec::Volume(req) => {
                let stored = match &req.input {
                    VolumeSource::Stored(input) => *input,
                    VolumeSource::Pacs(source) => {
                        pulled = true;
                        match self
                            .pull_input(id, attempt, source, &cancel, &sink, &latest)
                            .await
                        {
                            Ok(series) => match crate::storage::AnyId::parse(&series.to_string()) {
                                Ok(any) => any,
                                Err(_) => return failed(Problem::internal()),
                            },
                            Err(RunError::Canceled) => return Outcome::Canceled,
                            Err(RunError::Failed(p)) => return failed(p),
                        }
                    }
                };
                match resolve_input(db, &self.inner.store, stored).await {
                    Ok(input) => Work::Volume(req.clone(), input),
                    Err(p) => return failed(p),
                }
            }
        };
        let cancel_flag = cancel.clone();
        let store = self.inner.store.clone();
        let limits = Limits {
            max_bytes: self.inner.config.memory_budget_bytes,
        };
        let mu_water = self.inner.config.mu_water_per_mm;
        let (tx, mut rx) = oneshot::channel();
        let span = tracing::Span::current();
        let spawned = self.inner.job_pools.spawn(None, move || {
            let _g = span.enter();
            let after_pull = Scaled {
                inner: &sink,
                start: PULL_SHARE,
                span: 1.0 - PULL_SHARE,
            };
            let progress: &dyn crate::recon::control::Progress =
                if pulled { &after_pull } else { &sink };
            let r = std::panic::catch_unwind(AssertUnwindSafe(|| match &work {
                Work::Reconstruct(req, dataset) => execute(
                    &store,
                    &job,
                    req,
                    dataset,
                    &limits,
                    Control::new(&cancel, progress),
                ),
                Work::Volume(req, input) => execute_volume(
                    &store,
                    &job,
                    req,
                    input,
                    limits.max_bytes,
                    mu_water,
                    Control::new(&cancel, progress),
                ),
            }));
            let _ = tx.send(r);
        });
        if let Err(e) = spawned {
            tracing::error!(error = %e, "a job could not start");
            return failed(Problem::internal());
        }
        let mut tick = tokio::time::interval(self.inner.config.progress_interval);
        let mut heartbeat = tokio::time::interval(heartbeat_interval(self.inner.config.lease));
        let outcome = loop {
            tokio::select! {
                r = &mut rx => break r,
                _ = tick.tick() => self.persist_progress(id, attempt, &latest).await,
                _ = heartbeat.tick() => self.renew(id, attempt, &cancel_flag).await,
            }
        };
        match outcome {
            Ok(Ok(Ok(result))) => Outcome::Succeeded(Box::new(result)),
            Ok(Ok(Err(RunError::Canceled))) => Outcome::Canceled,
            Ok(Ok(Err(RunError::Failed(p)))) => failed(p),
            _ => {
                tracing::error!("a job panicked");
                failed(Problem::internal())
            }
        }
    }
}
