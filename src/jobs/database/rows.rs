//! Rows of the job database as domain values: datasets, jobs and job summaries (JSON columns are text
//! holding the typed API objects).

use super::DbError;
use super::driver::Row;
use crate::error_code::Problem;
use crate::jobs::model::{Dataset, DatasetKind, Job, JobResult, JobSpec, JobStatus, JobSummary};
use crate::jobs::store::{corrupt, product_indexes};
use crate::storage::{DatasetId, JobId};

pub(super) fn json_col<T: serde::de::DeserializeOwned>(
    row: &Row,
    col: &str,
    table: &'static str,
) -> Result<T, DbError> {
    let text: String = row.try_get(col)?;
    serde_json::from_str(&text).map_err(|e| corrupt(table, format!("{col}: {e}")))
}

pub(super) fn opt_json_col<T: serde::de::DeserializeOwned>(
    row: &Row,
    col: &str,
    table: &'static str,
) -> Result<Option<T>, DbError> {
    let text: Option<String> = row.try_get(col)?;
    text.map(|t| serde_json::from_str(&t).map_err(|e| corrupt(table, format!("{col}: {e}"))))
        .transpose()
}

pub(super) fn dataset_from_row(row: &Row) -> Result<Dataset, DbError> {
    let id: String = row.try_get("id")?;
    let kind: String = row.try_get("kind")?;
    let bytes: i64 = row.try_get("bytes")?;
    Ok(Dataset {
        id: DatasetId::parse(&id).map_err(|e| corrupt("datasets", e))?,
        kind: match kind.as_str() {
            "upload" => DatasetKind::Upload,
            "simulation" => DatasetKind::Simulation,
            "scan" => DatasetKind::Scan,
            other => return Err(corrupt("datasets", format!("kind {other}"))),
        },
        geometry: json_col(row, "geometry", "datasets")?,
        shape: json_col(row, "shape", "datasets")?,
        dtype: row.try_get("dtype")?,
        bytes: bytes as u64,
        sha256: row.try_get("sha256")?,
        phantom: opt_json_col(row, "phantom", "datasets")?,
        noise: opt_json_col(row, "noise", "datasets")?,
        scan: opt_json_col(row, "scan", "datasets")?,
        created_us: row.try_get("created_us")?,
    })
}

pub(super) fn job_from_row(row: &Row) -> Result<Job, DbError> {
    let estimate: i64 = row.try_get("estimate_bytes")?;
    let attempts: i64 = row.try_get("attempts")?;
    let cancel: i64 = row.try_get("cancel_requested")?;
    Ok(Job {
        id: row.parsed("id", "jobs", JobId::parse)?,
        kind: row.try_get("kind")?,
        status: status_col(row)?,
        progress: progress_col(row)?,
        stage: row.try_get("stage")?,
        request: json_col::<JobSpec>(row, "spec", "jobs")?,
        estimate_bytes: estimate.max(0) as u64,
        attempts: attempts.max(0) as u32,
        cancel_requested: cancel != 0,
        error: opt_json_col::<Problem>(row, "error", "jobs")?,
        result: opt_json_col::<JobResult>(row, "result", "jobs")?,
        created_us: row.try_get("created_us")?,
        started_us: row.try_get("started_us")?,
        finished_us: row.try_get("finished_us")?,
    })
}

pub(super) fn summary_from_row(row: &Row) -> Result<JobSummary, DbError> {
    let products: Option<String> = row.try_get("product_indexes")?;
    Ok(JobSummary {
        id: row.parsed("id", "jobs", JobId::parse)?,
        kind: row.try_get("kind")?,
        status: status_col(row)?,
        progress: progress_col(row)?,
        stage: row.try_get("stage")?,
        created_us: row.try_get("created_us")?,
        started_us: row.try_get("started_us")?,
        finished_us: row.try_get("finished_us")?,
        has_metrics: row.try_get("has_metrics")?,
        product_indexes: product_indexes(products.as_deref())?,
    })
}

/// A job's `status` column.
fn status_col(row: &Row) -> Result<JobStatus, DbError> {
    let status: String = row.try_get("status")?;
    JobStatus::parse(&status).ok_or_else(|| corrupt("jobs", format!("status {status}")))
}

/// A job's `progress` column, in percent.
fn progress_col(row: &Row) -> Result<u8, DbError> {
    let progress: i64 = row.try_get("progress")?;
    Ok(progress.clamp(0, 100) as u8)
}
