//! The engine: a dedicated rayon pool that does all computation, a scheduler that starts queued jobs
//! within the concurrency limit and the memory budget, cancellation, progress (broadcast live, persisted
//! at a bounded rate), and crash recovery at start.
//!
//! The async runtime never computes: work goes to the pool and its result comes back through a oneshot
//! channel. Job state lives in the database; the engine keeps in memory only the cancel flags and memory
//! reservations of the jobs it is running.
//!
//! A graceful stop ([`Engine::begin_stop`]) starts no more jobs and asks the running ones to stop; each one
//! that stops is handed back to the queue (`running → queued`) without spending an attempt, so rolling
//! restarts never exhaust a job. Only a crash (the process killed) counts as an attempt.

mod cancel;
mod leases;
mod memory;
mod progress;
mod pulled;
mod relay;
mod wakeups;

pub use leases::{LEASE, expiry_interval, heartbeat_interval};
pub use memory::Reservation;
pub use relay::Remote;

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use progress::{Latest, Sink};
use tokio::sync::{Notify, broadcast, oneshot};
use tracing::Instrument;

use super::database::Database;
use super::imaging::{VolumeInput, VolumeJobRequest, execute_volume, resolve_input};
use super::lifecycle::Outcome;
use super::model::{Dataset, Job, JobRequest, JobSpec, JobStatus};
use super::pull::{PULL_SHARE, Scaled, SeriesPuller};
use super::repo::DbError;
use super::run::{RunError, execute};
use super::store::{JobStore, StoreError};
use super::volume_spec::VolumeSource;
use crate::error_code::{ErrorCode, Problem};
use crate::recon::control::{Cancel, Control};
use crate::recon::grid::Limits;
use crate::storage::{BlobStore, JobId};
use crate::telemetry::names;

/// A change of a job's status, progress or stage, as sent to event subscribers: the one progress type that
/// the core's [`Progress`] reports become (SSE `progress` events; the CLI bar reads the same reports).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobEvent {
    pub id: JobId,
    pub status: JobStatus,
    /// 0–100 (never 100 while running).
    pub progress: u8,
    pub stage: String,
    /// The iteration an iterative algorithm is at, when it reports one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub iteration: Option<usize>,
    /// The residual of that iteration (‖Ax − b‖ / ‖b‖), when the algorithm reports one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual: Option<f64>,
}

impl JobEvent {
    /// The event of a job as it is stored (no iteration or residual).
    pub fn of(job: &Job) -> Self {
        JobEvent {
            id: job.id,
            status: job.status,
            progress: job.progress,
            stage: job.stage.clone(),
            iteration: None,
            residual: None,
        }
    }
}

/// Engine limits.
#[derive(Debug, Clone, Copy)]
pub struct EngineConfig {
    pub worker_threads: usize,
    pub max_concurrent_jobs: usize,
    pub memory_budget_bytes: u64,
    pub max_attempts: u32,
    pub progress_interval: Duration,
    /// How long a claim holds a job without a heartbeat ([`LEASE`] by default); heartbeats come every
    /// [`heartbeat_interval`], expired leases are looked for every [`expiry_interval`].
    pub lease: Duration,
    /// μ of water (/mm): HU values of rendering requests on μ volumes convert through it (`mu_water_per_mm`).
    pub mu_water_per_mm: f64,
}

struct Running {
    cancel: Cancel,
    estimate: u64,
}

struct Inner {
    db: Database,
    store: BlobStore,
    pool: rayon::ThreadPool,
    config: EngineConfig,
    running: Mutex<HashMap<JobId, Running>>,
    wake: Notify,
    events: broadcast::Sender<JobEvent>,
    /// Set by a graceful stop: no job starts any more, running ones are handed back.
    stopping: AtomicBool,
    /// Bytes of the budget held outside jobs (`memory::Reservation`).
    reserved: AtomicU64,
    /// Notified each time a running job is released.
    released: Notify,
    /// Pulls series from PACS peers for jobs whose input is one; installed by the DICOM node.
    puller: OnceLock<Arc<dyn SeriesPuller>>,
    /// Job events to and from other processes on a shared database (`None` on SQLite).
    relay: Option<relay::Relay>,
    /// What other processes announced besides job events.
    remote: broadcast::Sender<relay::Remote>,
}

/// What a job run does, with its input resolved (one per running job: its size does not matter).
#[allow(clippy::large_enum_variant)]
enum Work {
    Reconstruct(JobRequest, Dataset),
    Volume(VolumeJobRequest, VolumeInput),
}

/// Handle to the engine; cheap to clone.
#[derive(Clone)]
pub struct Engine {
    inner: Arc<Inner>,
}

impl Engine {
    /// Build the pool, recover from a crash (re-queue or fail jobs left running, remove partial results)
    /// and start the scheduler on the current runtime.
    pub async fn start(
        db: Database,
        store: BlobStore,
        config: EngineConfig,
    ) -> Result<Self, StartError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.worker_threads)
            .thread_name(|i| format!("ctrecon-worker-{i}"))
            .build()
            .map_err(|e| StartError::Pool(e.to_string()))?;
        let (requeued, failed) = db.recover(config.max_attempts).await?;
        if requeued + failed > 0 {
            tracing::warn!(
                requeued,
                failed,
                "recovered jobs left running by a previous process"
            );
        }
        for id in db.unfinished_ids().await? {
            store
                .remove_results(id)
                .map_err(|e| StartError::Pool(format!("removing partial results: {e}")))?;
        }
        let (events, _) = broadcast::channel(1024);
        let (remote, _) = broadcast::channel(256);
        let relay = relay::Relay::start(&db);
        let engine = Engine {
            inner: Arc::new(Inner {
                db,
                store,
                pool,
                config,
                running: Mutex::new(HashMap::new()),
                wake: Notify::new(),
                events,
                stopping: AtomicBool::new(false),
                reserved: AtomicU64::new(0),
                released: Notify::new(),
                puller: OnceLock::new(),
                relay,
                remote,
            }),
        };
        let scheduler = engine.clone();
        tokio::spawn(async move { scheduler.schedule().await });
        let expiry = engine.clone();
        tokio::spawn(async move { expiry.expire_leases_periodically().await });
        if engine.inner.db.is_shared() {
            let listener = engine.clone();
            tokio::spawn(async move { listener.listen_for_wakeups().await });
        }
        Ok(engine)
    }

    /// Subscribe to job events (status, progress, stage changes of every job).
    pub fn subscribe(&self) -> broadcast::Receiver<JobEvent> {
        self.inner.events.subscribe()
    }

    /// Tell the scheduler that a job was queued.
    pub fn wake(&self) {
        self.inner.wake.notify_one();
    }

    /// Begin a graceful stop: start no more jobs and ask the running ones to stop at their next check;
    /// each one that stops is handed back to the queue without spending an attempt.
    pub fn begin_stop(&self) {
        self.inner.stopping.store(true, Ordering::SeqCst);
        let flags: Vec<Cancel> = match self.inner.running.lock() {
            Ok(r) => r.values().map(|x| x.cancel.clone()).collect(),
            Err(_) => Vec::new(),
        };
        for flag in flags {
            flag.cancel();
        }
        self.inner.wake.notify_one();
    }

    /// The cancel flag of a job this engine runs.
    fn cancel_flag(&self, id: JobId) -> Option<Cancel> {
        self.inner
            .running
            .lock()
            .ok()
            .and_then(|r| r.get(&id).map(|x| x.cancel.clone()))
    }

    fn is_stopping(&self) -> bool {
        self.inner.stopping.load(Ordering::SeqCst)
    }

    /// Wait until no job runs, or until `deadline`; returns the number still running then (they stay
    /// `running` in the database and are recovered at the next start, as after a crash; on a shared database,
    /// by another process once their lease expires).
    pub async fn stopped(&self, deadline: tokio::time::Instant) -> usize {
        loop {
            let released = self.inner.released.notified();
            if self.running_count() == 0 {
                return 0;
            }
            tokio::select! {
                _ = released => {}
                _ = tokio::time::sleep_until(deadline) => return self.running_count(),
            }
        }
    }

    /// Number of jobs running now.
    pub fn running_count(&self) -> usize {
        self.inner.running.lock().map(|r| r.len()).unwrap_or(0)
    }

    /// Tell subscribers here, and the other processes on a shared database, that `job` changed.
    pub fn publish(&self, job: &Job) {
        let event = JobEvent::of(job);
        self.relay(relay::Relayed::Job {
            event: event.clone(),
        });
        let _ = self.inner.events.send(event);
    }

    /// Run `f` on the worker pool and await its result; a panic becomes an internal error.
    pub async fn compute<T, F>(&self, f: F) -> Result<T, Problem>
    where
        T: Send + 'static,
        F: FnOnce() -> Result<T, Problem> + Send + 'static,
    {
        let (tx, rx) = oneshot::channel();
        let span = tracing::Span::current();
        self.inner.pool.spawn(move || {
            let _g = span.enter();
            let _ = tx.send(std::panic::catch_unwind(AssertUnwindSafe(f)));
        });
        match rx.await {
            Ok(Ok(r)) => r,
            _ => {
                tracing::error!("a computation panicked");
                Err(Problem::internal())
            }
        }
    }

    async fn schedule(self) {
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
        self.inner.pool.spawn(move || {
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

/// Why the engine could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error(transparent)]
    Db(#[from] DbError),
    #[error("{0}")]
    Pool(String),
}

/// Why a cancel was refused.
#[derive(Debug, thiserror::Error)]
pub enum CancelError {
    #[error("no such job")]
    NotFound,
    #[error("the job has already {}", .0.as_str())]
    Finished(JobStatus),
    #[error(transparent)]
    Db(#[from] DbError),
}
