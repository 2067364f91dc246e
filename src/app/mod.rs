//! The application layer: the commands and queries every front door calls (the HTTP routes, the CLI, and
//! later the DIMSE listener and `ctrecon worker`) — submit, cancel, list, fetch and delete jobs; the
//! Idempotency-Key rule — over the job store, the blob store and the engine.
//!
//! It imports no web framework: answers are domain values or an [`AppError`], which each front door maps
//! to its own wire form (the HTTP layer to problem+json, in one place).

pub mod arrivals;
mod decoding;
pub mod deliveries;
pub mod dicom_caller;
pub mod dicomweb;
pub mod error;
pub mod feed;
mod hints;
pub mod idempotency;
pub mod instances;
pub mod jobs;
pub mod limits;
pub mod local;
pub mod matching;
pub mod peers;
pub mod protocols;
pub mod query;
pub mod recognised;
pub mod rules;
pub mod scans;
pub mod series;
pub mod stow;
pub mod stow_client;
pub mod stow_series;
pub mod uploads;
pub mod wado;

use std::time::Duration;

use tokio::sync::watch;

use crate::config::{ConfigError, Settings};
use crate::jobs::retention::{self, Retention};
use crate::jobs::{Database, DbError, Engine, EngineConfig, StartError};
use crate::storage::BlobStore;

pub use error::{AppError, AppResult};
pub use idempotency::{Fingerprinted, Replay};
pub use jobs::{Page, Submitted};

/// How long opening waits for a PostgreSQL server before it gives up with an error.
const DATABASE_CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// Why the application could not open.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("data directory: {0}")]
    DataDir(std::io::Error),
    #[error("object storage: {0}")]
    Storage(String),
    #[error("database: {0}")]
    Db(#[from] DbError),
    #[error("engine: {0}")]
    Engine(#[from] StartError),
}

/// The application: the job database, the blob store, the engine and the settings (limits). Cheap to
/// clone (every part is a handle).
#[derive(Clone)]
pub struct App {
    pub db: Database,
    pub store: BlobStore,
    pub engine: Engine,
    pub settings: Settings,
    /// Every job's creation, status, progress and deletion, for `GET /v1/events`.
    pub feed: feed::Feed,
    retention: Retention,
    outbound: deliveries::Outbound,
    /// Series arriving by STOW-RS, assembled once stable.
    stow_series: std::sync::Arc<stow_series::StowSeries>,
}

impl App {
    /// Validate the settings, open the data directory and the database, pair blob files with their rows,
    /// apply retention once, recover jobs left running and start the engine.
    pub async fn open(settings: Settings) -> Result<Self, OpenError> {
        settings.validate()?;
        let dir = settings.data_dir.clone();
        tokio::fs::create_dir_all(&dir)
            .await
            .map_err(OpenError::DataDir)?;
        let db = Database::open(
            settings.database_url.as_deref(),
            &settings.data_dir.join("ctrecon.sqlite"),
            DATABASE_CONNECT_TIMEOUT,
        )
        .await?;
        // On a shared job database other processes may be writing into the same data directory.
        let idle = if db.is_shared() {
            crate::storage::SHARED_IDLE
        } else {
            Duration::ZERO
        };
        let store = tokio::task::spawn_blocking(move || BlobStore::open_shared(&dir, idle))
            .await
            .map_err(|e| OpenError::DataDir(std::io::Error::other(e)))?
            .map_err(OpenError::DataDir)?;
        // Checked before anything is swept or claimed: a store that cannot be reached takes no job.
        let store = match &settings.storage.url {
            None => store,
            Some(url) => store.with_mirror(open_object_storage(&settings, url).await?),
        };
        let swept = crate::jobs::sweep::sweep_blobs(&db, &store).await?;
        tracing::info!(?swept, "blob files paired with their rows");
        let retention = Retention::from_secs(
            settings.retain_finished_jobs_secs,
            settings.retain_datasets_secs,
            settings.retain_series_secs,
        );
        if !retention.is_off() {
            let s = retention::sweep(&db, &store, &retention).await?;
            tracing::info!(
                jobs = s.jobs,
                datasets = s.datasets,
                series = s.series,
                uploads = s.uploads,
                "retention at start: removed"
            );
        }
        let engine = Engine::start(
            db.clone(),
            store.clone(),
            EngineConfig {
                worker_threads: settings.resolved_worker_threads(),
                max_concurrent_jobs: settings.max_concurrent_jobs,
                memory_budget_bytes: settings.memory_budget_bytes,
                max_attempts: settings.max_attempts,
                progress_interval: Duration::from_millis(settings.progress_interval_ms.max(10)),
                lease: Duration::from_secs(settings.lease_secs),
                mu_water_per_mm: settings.mu_water_per_mm,
            },
        )
        .await?;
        let stable_age = settings.dicom.stable_age();
        let feed = feed::Feed::new();
        feed.spawn_forwarder(engine.subscribe());
        feed.spawn_remote_forwarder(engine.subscribe_remote());
        let app = Self {
            db,
            store,
            engine,
            settings,
            feed,
            retention,
            outbound: deliveries::Outbound::default(),
            stow_series: stow_series::StowSeries::new(stable_age),
        };
        match app.sweep_instances().await {
            Ok(n) => tracing::info!(removed = n, "instance folders paired with their rows"),
            Err(e) => {
                tracing::warn!(error = %e, "pairing instance folders with their rows failed")
            }
        }
        app.load_config_rules().await?;
        Ok(app)
    }

    /// Start the periodic retention sweep; it ends when `shutdown` turns true.
    pub fn spawn_retention(&self, shutdown: watch::Receiver<bool>) {
        retention::spawn(
            self.db.clone(),
            self.store.clone(),
            self.retention,
            Duration::from_secs(self.settings.retention_sweep_secs),
            shutdown,
        );
    }
}

/// The object store of `storage.url`, checked: reachable, the bucket there, the credentials accepted.
#[cfg(feature = "s3")]
async fn open_object_storage(
    settings: &Settings,
    url: &str,
) -> Result<crate::storage::mirror::Mirror, OpenError> {
    use crate::storage::object::{ObjectBlobs, S3Location};
    let s = &settings.storage;
    let mut location = S3Location::parse(url).map_err(OpenError::Storage)?;
    location.endpoint = s.endpoint.clone();
    location.region = s.region.clone();
    location.access_key_id = s.access_key_id.clone();
    location.secret_access_key = s.secret_access_key.clone();
    let blobs = ObjectBlobs::s3(&location, &settings.data_dir.join("tmp"))
        .map_err(|e| OpenError::Storage(format!("{url}: {e}")))?;
    if let Err(e) = blobs.check().await {
        let hint = match e.kind() {
            std::io::ErrorKind::PermissionDenied => {
                "the server refused the credentials (storage.access_key_id / storage.secret_access_key \
                 or AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY)"
            }
            std::io::ErrorKind::NotFound => "the bucket does not exist",
            _ => {
                "the server could not be used (storage.endpoint or AWS_ENDPOINT_URL, the bucket, the credentials)"
            }
        };
        return Err(OpenError::Storage(format!("{url}: {hint}: {e}")));
    }
    tracing::info!(url, endpoint = ?location.endpoint, "datasets, series and results kept in object storage");
    Ok(crate::storage::mirror::Mirror::new(
        std::sync::Arc::new(blobs),
        tokio::runtime::Handle::current(),
        url,
    ))
}

#[cfg(not(feature = "s3"))]
async fn open_object_storage(
    _settings: &Settings,
    url: &str,
) -> Result<crate::storage::mirror::Mirror, OpenError> {
    Err(OpenError::Storage(format!(
        "{url}: this build has no object storage (the `s3` cargo feature is off)"
    )))
}
