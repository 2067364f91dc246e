//! The start-up sweep that pairs blob files with the rows that own them (temporary file → row → rename leaves
//! at most a row without its file after a crash; anything else on disk without a row is an orphan), on
//! whichever job database the service runs.

use std::collections::HashSet;

use super::database::Database;
use super::store::DbError;
use crate::storage::sweep::{BlobEntry, BlobKind};
use crate::storage::{BlobStore, DatasetId, SeriesId};

/// Counter of files removed by the start-up sweep for want of a row, by kind.
pub const ORPHANS_REMOVED: &str = "ctrecon_startup_orphans_removed_total";
/// Counter of rows whose file the start-up sweep found missing, by kind.
pub const MISSING_FILES: &str = "ctrecon_startup_missing_files_total";

/// What the start-up sweep found, per kind: files removed for want of a row, rows marked for want of a file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SweepReport {
    pub orphans_removed: Vec<(BlobKind, u64)>,
    pub rows_missing_file: Vec<(BlobKind, u64)>,
}

/// Pair blob files with rows: remove every entry of `series/`, `datasets/`, `uploads/` and `results/` without
/// a row (or not named by an id), and mark series and dataset rows whose file is missing. Logged and counted by kind.
/// On a shared job database only entries untouched for [`SHARED_IDLE`](crate::storage::SHARED_IDLE) go,
/// and no row is marked (another process may be between its row and its rename).
pub async fn sweep_blobs(db: &Database, store: &BlobStore) -> Result<SweepReport, DbError> {
    let mut report = SweepReport::default();
    // Processes sharing the job database may share the directory: leave what another one may be writing.
    let idle = if db.is_shared() {
        crate::storage::SHARED_IDLE
    } else {
        std::time::Duration::ZERO
    };
    for kind in BlobKind::ALL {
        // Files first, rows second: a file renamed into place meanwhile already has its row.
        // Each entry with whether another process may still be writing it (read off the async runtime).
        let listing = {
            let store = store.clone();
            tokio::task::spawn_blocking(move || {
                store.list_blobs(kind).map(|entries| {
                    entries
                        .into_iter()
                        .map(|e| {
                            let busy = !idle.is_zero() && !crate::storage::idle_for(&e.path, idle);
                            (e, busy)
                        })
                        .collect::<Vec<_>>()
                })
            })
            .await
        };
        let entries: Vec<(BlobEntry, bool)> =
            match listing.map_err(std::io::Error::other).and_then(|r| r) {
                Ok(e) => e,
                Err(e) => {
                    tracing::error!(error = %e, kind = kind.as_str(), "listing blob files failed");
                    continue;
                }
            };
        let owners = db.owner_ids(kind).await?;
        let mut on_disk = HashSet::new();
        let mut removed = 0u64;
        for (entry, busy) in entries {
            match entry.id.clone().filter(|id| owners.contains(id)) {
                Some(id) => {
                    on_disk.insert(id);
                }
                None if busy => {}
                None => {
                    let path = entry.path.clone();
                    let store = store.clone();
                    match tokio::task::spawn_blocking(move || store.remove_entry(&entry)).await {
                        Ok(Ok(())) => {
                            tracing::warn!(kind = kind.as_str(), path = %path.display(), "removed a file without a database row");
                            removed += 1;
                        }
                        other => {
                            tracing::error!(kind = kind.as_str(), path = %path.display(), outcome = ?other.map(|r| r.err()), "removing an orphan file failed");
                        }
                    }
                }
            }
        }
        let mut missing = 0u64;
        // A shared directory: another process may be between inserting a row and renaming its file into place.
        if kind.row_needs_file() && idle.is_zero() {
            for id in owners.difference(&on_disk) {
                let path = match kind {
                    BlobKind::Series => SeriesId::parse(id).map(|i| store.series_path(i)),
                    _ => DatasetId::parse(id).map(|i| store.dataset_path(i)),
                };
                // A row inserted after the listing may have its file by now.
                // With object storage the data directory is a cache: the object decides (an
                // unanswered request counts as there).
                if let Ok(p) = path
                    && store.exists(&p).await.unwrap_or(true)
                {
                    continue;
                }
                tracing::warn!(kind = kind.as_str(), id = %id, "a row's file is missing; marked unavailable");
                db.mark_missing(kind, id).await?;
                missing += 1;
            }
        }
        metrics::counter!(ORPHANS_REMOVED, "kind" => kind.as_str()).increment(removed);
        if kind.row_needs_file() {
            metrics::counter!(MISSING_FILES, "kind" => kind.as_str()).increment(missing);
        }
        report.orphans_removed.push((kind, removed));
        report.rows_missing_file.push((kind, missing));
    }
    Ok(report)
}
