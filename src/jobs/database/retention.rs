//! Retention: deleting what is older than its retention period, except the inputs of queued
//! and running jobs, with the Idempotency-Key records that name what is deleted.

use super::driver::query;
use super::{Database, DbError};
use crate::jobs::store::corrupt;
use crate::storage::{DatasetId, JobId, SeriesId, UploadId};

/// The inputs (datasets, series, jobs) of queued and running jobs: never removed.
macro_rules! active_inputs {
    () => {
        "SELECT dataset_id FROM jobs WHERE status IN ('queued', 'running')"
    };
}

impl Database {
    /// Delete the rows that `sql` (a `DELETE … WHERE … < ? … RETURNING id`) selects with `before_us`, and
    /// the Idempotency-Key records that name them, in one transaction; returns the ids deleted.
    async fn delete_returning(
        &self,
        sql: &'static str,
        before_us: i64,
    ) -> Result<Vec<String>, DbError> {
        let mut tx = self.pool.begin().await?;
        let rows = query(sql).bind(before_us).fetch_all(&mut tx).await?;
        let ids = rows
            .iter()
            .map(|r| r.try_get::<String>("id"))
            .collect::<Result<Vec<_>, _>>()?;
        for id in &ids {
            query("DELETE FROM idempotency_keys WHERE resource_id = $1")
                .bind(id)
                .execute(&mut tx)
                .await?;
        }
        tx.commit().await?;
        Ok(ids)
    }

    /// Retention: delete the jobs that finished before `before_us`, except those a queued or running job
    /// takes as input; returns their ids (their result files are the caller's to remove).
    pub async fn delete_jobs_finished_before(&self, before_us: i64) -> Result<Vec<JobId>, DbError> {
        let ids = self
            .delete_returning(
                concat!(
                    "DELETE FROM jobs WHERE status IN ('succeeded', 'failed', 'canceled') AND finished_us < $1
                     AND id NOT IN (",
                    active_inputs!(),
                    ") RETURNING id"
                ),
                before_us,
            )
            .await?;
        let ids = ids
            .iter()
            .map(|id| JobId::parse(id).map_err(|e| corrupt("jobs", e)))
            .collect::<Result<Vec<_>, _>>()?;
        for id in &ids {
            self.invalidate(*id);
        }
        Ok(ids)
    }

    /// Retention: delete the datasets created before `before_us` that no queued or running job uses.
    pub async fn delete_datasets_created_before(
        &self,
        before_us: i64,
    ) -> Result<Vec<DatasetId>, DbError> {
        let ids = self
            .delete_returning(
                concat!(
                    "DELETE FROM datasets WHERE created_us < $1 AND id NOT IN (",
                    active_inputs!(),
                    ") RETURNING id"
                ),
                before_us,
            )
            .await?;
        ids.iter()
            .map(|id| DatasetId::parse(id).map_err(|e| corrupt("datasets", e)))
            .collect()
    }

    /// Retention: delete the series created before `before_us` that no queued or running job uses.
    pub async fn delete_series_created_before(
        &self,
        before_us: i64,
    ) -> Result<Vec<SeriesId>, DbError> {
        let ids = self
            .delete_returning(
                concat!(
                    "DELETE FROM series WHERE created_us < $1 AND id NOT IN (",
                    active_inputs!(),
                    ") RETURNING id"
                ),
                before_us,
            )
            .await?;
        ids.iter()
            .map(|id| SeriesId::parse(id).map_err(|e| corrupt("series", e)))
            .collect()
    }

    /// Retention: delete the uploads completed before `before_us` that no series comes from any more and that
    /// own no indexed instance (a STOW-RS request's instances belong to its upload, their series to another).
    pub async fn delete_uploads_without_series(
        &self,
        before_us: i64,
    ) -> Result<Vec<UploadId>, DbError> {
        let ids = self
            .delete_returning(
                "DELETE FROM uploads WHERE status = 'completed' AND completed_us < $1
                 AND id NOT IN (SELECT upload_id FROM series)
                 AND NOT EXISTS (SELECT 1 FROM instances i WHERE i.upload_id = uploads.id) RETURNING id",
                before_us,
            )
            .await?;
        ids.iter()
            .map(|id| UploadId::parse(id).map_err(|e| corrupt("uploads", e)))
            .collect()
    }
}
