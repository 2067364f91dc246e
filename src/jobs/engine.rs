//! The engine: rayon pools that do all computation (one for each running job or request computation,
//! [`pools`]), a scheduler that starts queued jobs within the concurrency limit and the memory budget,
//! cancellation, progress (broadcast live, persisted at a bounded rate), and crash recovery at start.
//!
//! The async runtime never computes: work goes to a pool and its result comes back through a oneshot
//! channel. Job state lives in the database; the engine keeps in memory only the cancel flags and memory
//! reservations of the jobs it is running.
//!
//! A graceful stop ([`Engine::begin_stop`]) starts no more jobs and asks the running ones to stop; each one
//! that stops is handed back to the queue (`running → queued`) without spending an attempt, so rolling
//! restarts never exhaust a job. Only a crash (the process killed) counts as an attempt.

mod cancel;
mod dispatch;
mod leases;
mod memory;
mod pools;
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
use std::time::Duration;

use serde::{Deserialize, Serialize};

use tokio::sync::{Notify, broadcast, oneshot};

use super::database::Database;
use super::imaging::VolumeInput;
use super::model::VolumeJobRequest;
use super::model::{Dataset, Job, JobRequest, JobStatus};
use super::pull::SeriesPuller;
use super::store::DbError;
use crate::error_code::Problem;
use crate::recon::control::Cancel;
use crate::storage::{BlobStore, JobId};

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
    /// One pool per running job.
    job_pools: pools::Pools,
    /// One pool per computation of a request ([`Engine::compute`]), [`COMPUTE_SLOTS`] at most at once.
    compute_pools: pools::Pools,
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

/// Computations of requests (simulations, renders, assemblies, exports) that run at once; more wait.
pub const COMPUTE_SLOTS: usize = 4;

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
                job_pools: pools::Pools::new(
                    "job",
                    config.worker_threads,
                    config.max_concurrent_jobs,
                ),
                compute_pools: pools::Pools::new("compute", config.worker_threads, COMPUTE_SLOTS),
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

    /// Run `f` on a pool of its own (once one of the [`COMPUTE_SLOTS`] is free) and await its result; a
    /// panic becomes an internal error.
    pub async fn compute<T, F>(&self, f: F) -> Result<T, Problem>
    where
        T: Send + 'static,
        F: FnOnce() -> Result<T, Problem> + Send + 'static,
    {
        let (tx, rx) = oneshot::channel();
        let span = tracing::Span::current();
        let slot = self.inner.compute_pools.slot().await;
        self.inner
            .compute_pools
            .spawn(slot, move || {
                let _g = span.enter();
                let _ = tx.send(std::panic::catch_unwind(AssertUnwindSafe(f)));
            })
            .map_err(|e| {
                tracing::error!(error = %e, "a computation could not start");
                Problem::internal()
            })?;
        match rx.await {
            Ok(Ok(r)) => r,
            _ => {
                tracing::error!("a computation panicked");
                Err(Problem::internal())
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
