//! Rows that own blob files: the start-up sweep that pairs files with rows (temporary file → row → rename
//! leaves at most a row without its file after a crash; anything else on disk without a row is an orphan),
//! and the deletion of series and datasets that no queued or running job uses.

use std::collections::HashSet;

use sqlx::Row;

use super::{Db, DbError};
use crate::jobs::database::Database;
use crate::jobs::model::now_us;
use crate::storage::sweep::{BlobEntry, BlobKind};
use crate::storage::{BlobStore, DatasetId, SeriesId};

/// Outcome of deleting a series or a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Deleted {
    Done,
    /// A queued or running job reads it.
    InUse,
    NotFound,
}

/// What the start-up sweep found, per kind: files removed for want of a row, rows marked for want of a file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SweepReport {
    pub orphans_removed: Vec<(BlobKind, u64)>,
    pub rows_missing_file: Vec<(BlobKind, u64)>,
}

/// Counter of files removed by the start-up sweep for want of a row, by kind.
pub const ORPHANS_REMOVED: &str = "ctrecon_startup_orphans_removed_total";
/// Counter of rows whose file the start-up sweep found missing, by kind.
pub const MISSING_FILES: &str = "ctrecon_startup_missing_files_total";

const ACTIVE_INPUT: &str =
    "EXISTS (SELECT 1 FROM jobs WHERE dataset_id = ? AND status IN ('queued', 'running'))";

impl Db {
    /// The ids of the rows that own a file of `kind` (for uploads: the open ones; for results: every job).
    pub(crate) async fn owner_ids(&self, kind: BlobKind) -> Result<HashSet<String>, DbError> {
        let sql = match kind {
            BlobKind::Series => "SELECT id FROM series",
            BlobKind::Dataset => "SELECT id FROM datasets",
            BlobKind::Upload => "SELECT id FROM uploads WHERE status = 'open'",
            BlobKind::Results => "SELECT id FROM jobs",
        };
        let rows = sqlx::query(sql).fetch_all(&self.pool).await?;
        rows.iter()
            .map(|r| r.try_get::<String, _>("id").map_err(DbError::from))
            .collect()
    }

    /// Record that the file of row `id` is gone.
    pub(crate) async fn mark_missing(&self, kind: BlobKind, id: &str) -> Result<(), DbError> {
        sqlx::query(
            "INSERT INTO missing_blobs (kind, id, detected_us) VALUES (?, ?, ?)
             ON CONFLICT (kind, id) DO NOTHING",
        )
        .bind(kind.as_str())
        .bind(id)
        .bind(now_us())
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Whether the sweep found the file of this series or dataset missing.
    pub async fn blob_missing(&self, kind: BlobKind, id: &str) -> Result<bool, DbError> {
        let row = sqlx::query("SELECT 1 FROM missing_blobs WHERE kind = ? AND id = ?")
            .bind(kind.as_str())
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.is_some())
    }

    /// Delete a row of `table` unless a queued or running job reads it, in one statement.
    async fn delete_unused(
        &self,
        table: &str,
        kind: BlobKind,
        id: &str,
    ) -> Result<Deleted, DbError> {
        let mut tx = self.write_tx().await?;
        let sql = format!("DELETE FROM {table} WHERE id = ? AND NOT {ACTIVE_INPUT}");
        let done = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(id)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        if done.rows_affected() == 0 {
            let sql = format!("SELECT 1 FROM {table} WHERE id = ?");
            let exists = sqlx::query(sqlx::AssertSqlSafe(sql))
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
            return Ok(if exists.is_some() {
                Deleted::InUse
            } else {
                Deleted::NotFound
            });
        }
        sqlx::query("DELETE FROM missing_blobs WHERE kind = ? AND id = ?")
            .bind(kind.as_str())
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(Deleted::Done)
    }

    /// Delete a series row (its file is the caller's to remove afterwards).
    pub async fn delete_series(&self, id: SeriesId) -> Result<Deleted, DbError> {
        self.delete_unused("series", BlobKind::Series, &id.to_string())
            .await
    }

    /// Delete a dataset row (its file is the caller's to remove afterwards).
    pub async fn delete_dataset(&self, id: DatasetId) -> Result<Deleted, DbError> {
        self.delete_unused("datasets", BlobKind::Dataset, &id.to_string())
            .await
    }
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
