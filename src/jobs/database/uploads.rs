//! Uploads and the series assembled from them: an upload completed in one request with its series, an open
//! upload that instances are appended to and that is completed later, and the series records.

use super::driver::{Tx, assembled, query};
use super::rows::{json_col, opt_json_col};
use super::{Appended, Completed, Database, DbError, UploadDeleted};
use crate::jobs::model::{IdempotencyKey, Inserted, SeriesRecord, UploadRecord, now_us};
use crate::jobs::store::to_json;
use crate::storage::{SeriesId, UploadId};

impl Database {
    async fn insert_series(tx: &mut Tx, series: &[SeriesRecord]) -> Result<(), DbError> {
        for r in series {
            query(
                "INSERT INTO series (id, upload_id, series_uid, record, created_us) VALUES ($1, $2, $3, $4, $5)",
            )
            .bind(r.id.to_string())
            .bind(r.upload_id.to_string())
            .bind(&r.series_uid)
            .bind(to_json(r))
            .bind(r.created_us)
            .execute(&mut *tx)
            .await?;
        }
        Ok(())
    }

    /// Record an upload completed in one request, with its series, under an optional Idempotency-Key.
    pub async fn insert_completed_upload(
        &self,
        id: UploadId,
        instances: u32,
        bytes: u64,
        outcome: &serde_json::Value,
        series: &[SeriesRecord],
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        let mut tx = match self.begin_claimed(key, &id.to_string()).await? {
            Ok(tx) => tx,
            Err(existing) => return Ok(existing),
        };
        let now = now_us();
        query(
            "INSERT INTO uploads (id, status, instances, bytes, outcome, created_us, completed_us)
             VALUES ($1, 'completed', $2, $3, $4, $5, $6)",
        )
        .bind(id.to_string())
        .bind(instances as i64)
        .bind(bytes as i64)
        .bind(outcome.to_string())
        .bind(now)
        .bind(now)
        .execute(&mut tx)
        .await?;
        Self::insert_series(&mut tx, series).await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    /// Open a new upload, under an optional Idempotency-Key.
    pub async fn insert_open_upload(
        &self,
        id: UploadId,
        key: Option<&IdempotencyKey>,
    ) -> Result<Inserted, DbError> {
        let mut tx = match self.begin_claimed(key, &id.to_string()).await? {
            Ok(tx) => tx,
            Err(existing) => return Ok(existing),
        };
        query("INSERT INTO uploads (id, status, created_us) VALUES ($1, 'open', $2)")
            .bind(id.to_string())
            .bind(now_us())
            .execute(&mut tx)
            .await?;
        tx.commit().await?;
        Ok(Inserted::New)
    }

    pub async fn get_upload(&self, id: UploadId) -> Result<Option<UploadRecord>, DbError> {
        let row = query("SELECT * FROM uploads WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| {
            let status: String = row.try_get("status")?;
            let instances: i64 = row.try_get("instances")?;
            let bytes: i64 = row.try_get("bytes")?;
            Ok(UploadRecord {
                id,
                open: status == "open",
                instances: instances.max(0) as u32,
                bytes: bytes.max(0) as u64,
                outcome: opt_json_col(&row, "outcome", "uploads")?,
                created_us: row.try_get("created_us")?,
            })
        })
        .transpose()
    }

    /// Append an instance (already stored under its SHA-256) to an open upload of at most `max_bytes`.
    pub async fn append_upload_file(
        &self,
        id: UploadId,
        sha256: &str,
        label: &str,
        bytes: u64,
        series_uid: &str,
        max_bytes: u64,
    ) -> Result<Appended, DbError> {
        let mut tx = self.pool.begin().await?;
        // The row stays locked to the end (on SQLite the transaction holds the one write lock): an append and a completion through two processes take turns, so
        // the completion either sees this instance counted (and refuses a changed upload) or this append
        // sees the upload closed; an instance is never acknowledged into an upload already assembled.
        let sql = format!(
            "SELECT status, instances, bytes FROM uploads WHERE id = $1{}",
            self.dialect().for_update()
        );
        let Some(row) = assembled(sql)
            .bind(id.to_string())
            .fetch_optional(&mut tx)
            .await?
        else {
            return Ok(Appended::NotFound);
        };
        let status: String = row.try_get("status")?;
        let instances: i64 = row.try_get("instances")?;
        let total: i64 = row.try_get("bytes")?;
        if status != "open" {
            return Ok(Appended::Closed);
        }
        let known = query("SELECT 1 FROM upload_files WHERE upload_id = $1 AND sha256 = $2")
            .bind(id.to_string())
            .bind(sha256)
            .fetch_optional(&mut tx)
            .await?;
        if known.is_some() {
            return Ok(Appended::Duplicate(instances.max(0) as u32));
        }
        if (total.max(0) as u64).saturating_add(bytes) > max_bytes {
            return Ok(Appended::TooLarge(max_bytes));
        }
        query(
            "INSERT INTO upload_files (upload_id, sha256, label, bytes, series_uid, created_us)
             VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(id.to_string())
        .bind(sha256)
        .bind(label)
        .bind(bytes as i64)
        .bind(series_uid)
        .bind(now_us())
        .execute(&mut tx)
        .await?;
        query(
            "UPDATE uploads SET instances = instances + 1, bytes = bytes + $1
             WHERE id = $2 AND status = 'open'",
        )
        .bind(bytes as i64)
        .bind(id.to_string())
        .execute(&mut tx)
        .await?;
        tx.commit().await?;
        Ok(Appended::Added(instances.max(0) as u32 + 1))
    }

    /// Delete the open upload `id` with its instance rows (a completed upload goes with its series).
    pub async fn delete_open_upload(&self, id: UploadId) -> Result<UploadDeleted, DbError> {
        let gone = query("DELETE FROM uploads WHERE id = $1 AND status = 'open'")
            .bind(id.to_string())
            .execute(&self.pool)
            .await?;
        if gone.rows_affected() > 0 {
            return Ok(UploadDeleted::Done);
        }
        let known = query("SELECT 1 FROM uploads WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        Ok(if known.is_some() {
            UploadDeleted::Completed
        } else {
            UploadDeleted::NotFound
        })
    }

    /// The instances of an upload: `(sha256, label)` in order of arrival.
    pub async fn upload_files(&self, id: UploadId) -> Result<Vec<(String, String)>, DbError> {
        let sql = format!(
            "SELECT sha256, label FROM upload_files WHERE upload_id = $1 ORDER BY created_us, {}",
            self.dialect().insertion_order()
        );
        let rows = assembled(sql)
            .bind(id.to_string())
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("sha256")?, r.try_get("label")?)))
            .collect()
    }

    /// Complete an open upload that still holds `instances` instances, recording its outcome and series.
    pub async fn complete_upload(
        &self,
        id: UploadId,
        instances: u32,
        outcome: &serde_json::Value,
        series: &[SeriesRecord],
    ) -> Result<Completed, DbError> {
        let mut tx = self.pool.begin().await?;
        let done = query(
            "UPDATE uploads SET status = 'completed', outcome = $1, completed_us = $2
             WHERE id = $3 AND status = 'open' AND instances = $4",
        )
        .bind(outcome.to_string())
        .bind(now_us())
        .bind(id.to_string())
        .bind(instances as i64)
        .execute(&mut tx)
        .await?;
        if done.rows_affected() == 0 {
            let open = query("SELECT 1 FROM uploads WHERE id = $1 AND status = 'open'")
                .bind(id.to_string())
                .fetch_optional(&mut tx)
                .await?;
            return Ok(if open.is_some() {
                Completed::Changed
            } else {
                Completed::Closed
            });
        }
        Self::insert_series(&mut tx, series).await?;
        tx.commit().await?;
        Ok(Completed::Done)
    }

    pub async fn get_series(&self, id: SeriesId) -> Result<Option<SeriesRecord>, DbError> {
        let row = query("SELECT record, created_us FROM series WHERE id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| {
            let mut r: SeriesRecord = json_col(&row, "record", "series")?;
            r.created_us = row.try_get("created_us")?;
            Ok(r)
        })
        .transpose()
    }

    /// The stored series of Series Instance UID `series_uid`, newest first.
    pub async fn series_with_uid(&self, series_uid: &str) -> Result<Vec<SeriesRecord>, DbError> {
        let rows = query(
            "SELECT record, created_us FROM series WHERE series_uid = $1 ORDER BY created_us DESC, id DESC",
        )
        .bind(series_uid)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|row| {
                let mut r: SeriesRecord = json_col(row, "record", "series")?;
                r.created_us = row.try_get("created_us")?;
                Ok(r)
            })
            .collect()
    }
}
