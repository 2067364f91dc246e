//! Retention: finished jobs, datasets and series older than their configured age are removed — the rows
//! first (one transaction each), then their files — at start and periodically. An input of a queued or
//! running job (a dataset, a series or a succeeded job's volume) is never removed; a completed upload goes
//! with the last of its series. Also: the bytes the data directory holds, by kind, for `/metrics`.
//!
//! A job admitted just before a sweep removes its input fails with `dataset_not_found` when it starts, as
//! it would after a manual delete.

use std::fs;
use std::io;
use std::path::Path;
use std::time::Duration;

use tokio::sync::watch;

use super::database::Database;
use super::model::now_us;
use super::store::DbError;
use crate::storage::BlobStore;
use crate::telemetry::names;

/// How long each kind is kept (`None`: forever).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Retention {
    /// Jobs, counted from when they finished (their results go with them).
    pub finished_jobs: Option<Duration>,
    /// Projection datasets, counted from their creation.
    pub datasets: Option<Duration>,
    /// Assembled CT series, counted from their creation.
    pub series: Option<Duration>,
}

impl Retention {
    /// From ages in seconds, 0 meaning forever.
    pub fn from_secs(finished_jobs: u64, datasets: u64, series: u64) -> Self {
        let age = |s: u64| (s > 0).then(|| Duration::from_secs(s));
        Self {
            finished_jobs: age(finished_jobs),
            datasets: age(datasets),
            series: age(series),
        }
    }

    pub fn is_off(&self) -> bool {
        *self == Self::default()
    }
}

/// What one sweep removed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Swept {
    pub jobs: usize,
    pub datasets: usize,
    pub series: usize,
    pub uploads: usize,
}

/// Remove what has aged out under `retention`, now.
pub async fn sweep(
    db: &Database,
    store: &BlobStore,
    retention: &Retention,
) -> Result<Swept, DbError> {
    let now = now_us();
    let before =
        |age: Duration| now.saturating_sub(i64::try_from(age.as_micros()).unwrap_or(i64::MAX));
    let (mut jobs, mut datasets, mut series, mut uploads) = (vec![], vec![], vec![], vec![]);
    if let Some(age) = retention.finished_jobs {
        jobs = db.delete_jobs_finished_before(before(age)).await?;
    }
    if let Some(age) = retention.datasets {
        datasets = db.delete_datasets_created_before(before(age)).await?;
    }
    if let Some(age) = retention.series {
        series = db.delete_series_created_before(before(age)).await?;
        uploads = db.delete_uploads_without_series(before(age)).await?;
    }
    let swept = Swept {
        jobs: jobs.len(),
        datasets: datasets.len(),
        series: series.len(),
        uploads: uploads.len(),
    };
    // The rows are gone: nothing serves these files any more. A file that cannot be removed is logged and
    // counted by the storage gauge; it never comes back as a resource.
    let store = store.clone();
    let removed = tokio::task::spawn_blocking(move || {
        let mut failures = 0usize;
        let mut check = |r: io::Result<()>| {
            if let Err(e) = r {
                tracing::warn!(error = %e, "retention: removing a file failed");
                failures += 1;
            }
        };
        for id in jobs {
            check(store.delete_results(id));
        }
        for id in datasets {
            check(store.remove_blob(&store.dataset_path(id)));
        }
        for id in series {
            check(store.remove_blob(&store.series_path(id)));
        }
        for id in uploads {
            check(store.remove_upload(id));
            // Its indexed instances' rows went with it.
            check(store.remove_instances(id));
        }
        failures
    })
    .await;
    if !matches!(removed, Ok(0)) {
        tracing::warn!("retention: some files could not be removed");
    }
    for (kind, n) in [
        ("jobs", swept.jobs),
        ("datasets", swept.datasets),
        ("series", swept.series),
        ("uploads", swept.uploads),
    ] {
        metrics::counter!(names::RETENTION_REMOVED, "kind" => kind).increment(n as u64);
    }
    Ok(swept)
}

/// Sweep every `every` until `shutdown` turns true (the sweep at start is the caller's).
pub fn spawn(
    db: Database,
    store: BlobStore,
    retention: Retention,
    every: Duration,
    mut shutdown: watch::Receiver<bool>,
) {
    if retention.is_off() {
        return;
    }
    tokio::spawn(async move {
        loop {
            tokio::select! {
                _ = tokio::time::sleep(every) => {}
                _ = shutdown.changed() => return,
            }
            match sweep(&db, &store, &retention).await {
                Ok(s) if s != Swept::default() => tracing::info!(
                    jobs = s.jobs,
                    datasets = s.datasets,
                    series = s.series,
                    uploads = s.uploads,
                    "retention: removed"
                ),
                Ok(_) => {}
                Err(e) => tracing::error!(error = %e, "retention sweep failed"),
            }
        }
    });
}

/// Bytes of the files under `dir`, recursively (missing is 0).
fn tree_bytes(dir: &Path) -> u64 {
    let Ok(entries) = fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => tree_bytes(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map(|m| m.len()).unwrap_or(0),
            _ => 0,
        })
        .sum()
}

/// The bytes the data directory holds, by kind: `datasets`, `series`, `results`, `uploads`, `instances`
/// (received instances kept in the instance index; a job's indexed results count under `results`).
pub fn storage_bytes(store: &BlobStore) -> [(&'static str, u64); 5] {
    ["datasets", "series", "results", "uploads", "instances"]
        .map(|k| (k, tree_bytes(&store.root().join(k))))
}
