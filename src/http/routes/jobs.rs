//! `POST /v1/jobs`, `GET /v1/jobs`, `GET /v1/jobs/{id}`, `POST /v1/jobs/{id}/cancel`,
//! `DELETE /v1/jobs/{id}`.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;

use super::super::AppState;
use super::super::extract::{ApiJson, ApiQuery, idempotency_key, job_id};
use super::super::problem::{ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::jobs::model::{KIND_RECONSTRUCTION, now_us, parse_rfc3339, rfc3339};
use crate::jobs::plan::admit_job;
use crate::jobs::{CancelError, IdempotencyKey, Inserted, Job, JobFilter, JobRequest, JobStatus};
use crate::storage::JobId;

const ROUTE_JOBS: &str = "POST /v1/jobs";

/// Links of a job: itself, its events, cancel, and its results once it succeeded.
fn links(job: &Job) -> serde_json::Value {
    let base = format!("/v1/jobs/{}", job.id);
    let mut l = json!({
        "self": base,
        "events": format!("{base}/events"),
        "cancel": format!("{base}/cancel"),
    });
    if job.status == JobStatus::Succeeded {
        let r = format!("{base}/result");
        l["volume"] = json!(format!("{r}/volume.npy"));
        l["slice"] = json!(format!("{r}/slice?axis=axial"));
        l["projection"] = json!(format!("{r}/projection?axis=axial&kind=mip"));
        l["mesh"] = json!(format!("{r}/mesh.stl?iso=<value>"));
        if job.result.as_ref().is_some_and(|r| r.metrics.is_some()) {
            l["metrics"] = json!(format!("{r}/metrics"));
        }
    }
    l
}

/// The JSON view of a job.
pub fn job_view(job: &Job) -> serde_json::Value {
    json!({
        "id": job.id,
        "kind": job.kind,
        "status": job.status,
        "progress": job.progress,
        "stage": job.stage,
        "attempts": job.attempts,
        "created_at": rfc3339(job.created_us),
        "started_at": job.started_us.map(rfc3339),
        "finished_at": job.finished_us.map(rfc3339),
        "input": job.request.input,
        "algorithm": job.request.algorithm,
        "grid": job.request.grid,
        "outputs": job.request.outputs,
        "estimate_bytes": job.estimate_bytes,
        "error": job.error,
        "result": job.result,
        "links": links(job),
    })
}

fn accepted(job: &Job) -> Response {
    let mut r = (StatusCode::ACCEPTED, axum::Json(job_view(job))).into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/jobs/{}", job.id)) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

async fn load(st: &AppState, id: JobId) -> ApiResult<Job> {
    st.db
        .get_job(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::JobNotFound, format!("no job {id}")))
}

fn reused() -> super::super::problem::ApiError {
    api_error(
        ErrorCode::IdempotencyKeyReused,
        "this Idempotency-Key was used with a different request",
    )
}

pub async fn post_job(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: ApiJson<JobRequest>,
) -> ApiResult<Response> {
    let key = idempotency_key(&headers)?;
    if let Some(k) = &key
        && let Some((id, fp)) = st.db.idempotency_lookup(ROUTE_JOBS, k).await?
    {
        if fp != body.fingerprint {
            return Err(reused());
        }
        return Ok(accepted(&load(&st, job_id(&id)?).await?));
    }
    let req = body.value;
    let dataset = st.db.get_dataset(req.input).await?.ok_or_else(|| {
        api_error(
            ErrorCode::DatasetNotFound,
            format!("no dataset {}", req.input),
        )
    })?;
    let estimate = admit_job(&req, &dataset, st.settings.memory_budget_bytes)?;
    let job = Job {
        id: JobId::generate(),
        kind: KIND_RECONSTRUCTION.into(),
        status: JobStatus::Queued,
        progress: 0,
        stage: "queued".into(),
        request: req,
        estimate_bytes: estimate,
        attempts: 0,
        cancel_requested: false,
        error: None,
        result: None,
        created_us: now_us(),
        started_us: None,
        finished_us: None,
    };
    let key = key.map(|key| IdempotencyKey {
        route: ROUTE_JOBS,
        key,
        fingerprint: body.fingerprint.clone(),
    });
    match st.db.insert_job(&job, key.as_ref()).await? {
        Inserted::New => {
            tracing::info!(job_id = %job.id, algorithm = job.request.algorithm.name(), "job queued");
            st.engine.publish(&job);
            st.engine.wake();
            Ok(accepted(&job))
        }
        Inserted::Existing {
            resource_id,
            fingerprint,
        } => {
            if fingerprint != body.fingerprint {
                return Err(reused());
            }
            Ok(accepted(&load(&st, job_id(&resource_id)?).await?))
        }
    }
}

pub async fn get_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let job = load(&st, job_id(&id)?).await?;
    Ok(axum::Json(job_view(&job)).into_response())
}

/// Filters and page of `GET /v1/jobs`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Comma-separated statuses.
    pub status: Option<String>,
    pub kind: Option<String>,
    /// RFC 3339.
    pub created_after: Option<String>,
    pub created_before: Option<String>,
    /// 1–200, default 50.
    pub limit: Option<u32>,
    /// `next_cursor` of the previous page.
    pub cursor: Option<String>,
}

pub async fn list_jobs(
    State(st): State<AppState>,
    ApiQuery(q): ApiQuery<ListQuery>,
) -> ApiResult<Response> {
    let bad = |m: String| api_error(ErrorCode::InvalidQuery, m);
    let mut statuses = Vec::new();
    for s in q.status.iter().flat_map(|s| s.split(',')) {
        let s = s.trim();
        if s.is_empty() {
            continue;
        }
        statuses.push(JobStatus::parse(s).ok_or_else(|| bad(format!("unknown status `{s}`")))?);
    }
    let time = |v: &Option<String>, name: &str| {
        v.as_deref()
            .map(|t| parse_rfc3339(t).ok_or_else(|| bad(format!("`{name}` must be RFC 3339"))))
            .transpose()
    };
    let limit = q.limit.unwrap_or(50);
    if !(1..=200).contains(&limit) {
        return Err(bad("`limit` must be in 1..=200".into()));
    }
    let before_id = q
        .cursor
        .as_deref()
        .map(|c| JobId::parse(c).map_err(|_| bad("`cursor` is not a cursor from this API".into())))
        .transpose()?;
    let filter = JobFilter {
        statuses,
        kind: q.kind.clone(),
        created_after_us: time(&q.created_after, "created_after")?,
        created_before_us: time(&q.created_before, "created_before")?,
        before_id,
        limit: limit + 1,
    };
    let mut jobs = st.db.list_jobs(&filter).await?;
    let next = if jobs.len() > limit as usize {
        jobs.truncate(limit as usize);
        jobs.last().map(|j| j.id.to_string())
    } else {
        None
    };
    let items: Vec<_> = jobs.iter().map(job_view).collect();
    Ok(axum::Json(json!({ "jobs": items, "next_cursor": next })).into_response())
}

pub async fn cancel_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let id = job_id(&id)?;
    match st.engine.cancel(id).await {
        Ok(()) => Ok(accepted(&load(&st, id).await?)),
        Err(CancelError::NotFound) => {
            Err(api_error(ErrorCode::JobNotFound, format!("no job {id}")))
        }
        Err(CancelError::Finished(s)) => Err(api_error(
            ErrorCode::JobAlreadyFinished,
            format!("the job has already {}; it cannot be canceled", s.as_str()),
        )),
        Err(CancelError::Db(e)) => Err(e.into()),
    }
}

pub async fn delete_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let job = load(&st, id).await?;
    if !job.status.is_terminal() || !st.db.delete_finished(id).await? {
        return Err(api_error(
            ErrorCode::JobActive,
            "cancel the job and wait for it to finish before deleting it",
        ));
    }
    st.store.remove_results(id)?;
    tracing::info!(job_id = %id, "job deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}
