//! Rows that own blob files: what the start-up sweep ([`crate::jobs::sweep::sweep_blobs`]) reads and
//! marks, and the deletion of series and datasets that no queued or running job uses.

use std::collections::HashSet;

use super::driver::{assembled, query};
use super::{Database, DbError, Deleted};
use crate::jobs::model::now_us;
use crate::storage::sweep::BlobKind;
use crate::storage::{DatasetId, SeriesId};

const ACTIVE_INPUT: &str =
    "EXISTS (SELECT 1 FROM jobs WHERE dataset_id = $1 AND status IN ('queued', 'running'))";

impl Database {
    /// The ids of the rows that own a file of `kind` (for uploads: the open ones; for results: every job).
    pub(crate) async fn owner_ids(&self, kind: BlobKind) -> Result<HashSet<String>, DbError> {
        let sql = match kind {
            BlobKind::Series => "SELECT id FROM series",
            BlobKind::Dataset => "SELECT id FROM datasets",
            BlobKind::Upload => "SELECT id FROM uploads WHERE status = 'open'",
            BlobKind::Results => "SELECT id FROM jobs",
        };
        let rows = query(sql).fetch_all(&self.pool).await?;
        rows.iter()
            .map(|r| r.try_get::<String>("id").map_err(DbError::from))
            .collect()
    }

    /// Record that the file of row `id` is gone.
    pub(crate) async fn mark_missing(&self, kind: BlobKind, id: &str) -> Result<(), DbError> {
        query(
            "INSERT INTO missing_blobs (kind, id, detected_us) VALUES ($1, $2, $3)
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
        let row = query("SELECT 1 FROM missing_blobs WHERE kind = $1 AND id = $2")
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
        let mut tx = self.pool.begin().await?;
        let sql = format!("DELETE FROM {table} WHERE id = $1 AND NOT {ACTIVE_INPUT}");
        let done = assembled(sql).bind(id).execute(&mut tx).await?;
        if done.rows_affected() == 0 {
            let sql = format!("SELECT 1 FROM {table} WHERE id = $1");
            let exists = assembled(sql).bind(id).fetch_optional(&mut tx).await?;
            return Ok(if exists.is_some() {
                Deleted::InUse
            } else {
                Deleted::NotFound
            });
        }
        query("DELETE FROM missing_blobs WHERE kind = $1 AND id = $2")
            .bind(kind.as_str())
            .bind(id)
            .execute(&mut tx)
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
