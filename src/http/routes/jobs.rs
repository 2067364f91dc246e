//! `POST /v1/jobs`, `GET /v1/jobs`, `GET /v1/jobs/{id}`, `POST /v1/jobs/{id}/cancel`,
//! `DELETE /v1/jobs/{id}`.

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;

use super::super::AppState;
use super::super::extract::{ApiJson, ApiQuery, idempotency_key, job_id};
use super::super::problem::{ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::jobs::model::{parse_rfc3339, rfc3339};
use crate::jobs::{IdempotencyKey, Job, JobFilter, JobStatus, JobSummary};
use crate::storage::JobId;

const ROUTE_JOBS: &str = "POST /v1/jobs";

/// Links of a job: itself, its events, cancel, and its results once it succeeded.
fn links(job: &JobSummary) -> serde_json::Value {
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
        l["series"] = json!(format!("{r}/series.zip"));
        if job.has_metrics {
            l["metrics"] = json!(format!("{r}/metrics"));
        }
        if !job.product_indexes.is_empty() {
            l["products"] = json!(
                job.product_indexes
                    .iter()
                    .map(|i| format!("{r}/products/{i}"))
                    .collect::<Vec<_>>()
            );
        }
    }
    l
}

/// A field of a job's JSON representation. `request` stands for the request's own fields (`input`, `algorithm`,
/// `grid`, `outputs`; or `input`, `steps`, `products`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Field {
    Id,
    Kind,
    Status,
    Progress,
    Stage,
    CreatedAt,
    StartedAt,
    FinishedAt,
    Links,
    Attempts,
    EstimateBytes,
    Error,
    Result,
    Request,
}

/// Every field with its name in the API, in the order `?fields=` documents them.
const FIELDS: [(&str, Field); 14] = [
    ("id", Field::Id),
    ("kind", Field::Kind),
    ("status", Field::Status),
    ("progress", Field::Progress),
    ("stage", Field::Stage),
    ("created_at", Field::CreatedAt),
    ("started_at", Field::StartedAt),
    ("finished_at", Field::FinishedAt),
    ("links", Field::Links),
    ("attempts", Field::Attempts),
    ("estimate_bytes", Field::EstimateBytes),
    ("error", Field::Error),
    ("result", Field::Result),
    ("request", Field::Request),
];

/// A set of fields of a job's view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldSet(u16);

impl FieldSet {
    /// What `GET /v1/jobs` returns by default: id, kind, status, progress, stage, timestamps, links.
    pub const SUMMARY: FieldSet = FieldSet(0b1_1111_1111);
    /// The whole job, as `GET /v1/jobs/{id}` returns it.
    pub const ALL: FieldSet = FieldSet((1 << FIELDS.len()) - 1);

    fn bit(f: Field) -> u16 {
        1 << (f as u16)
    }

    fn has(self, f: Field) -> bool {
        self.0 & Self::bit(f) != 0
    }

    /// Every field of `self` is in `other`.
    fn within(self, other: FieldSet) -> bool {
        self.0 & !other.0 == 0
    }

    /// The fields named in a comma-separated list (`all` names every field); `Err` names an unknown one.
    fn parse(list: &str) -> Result<FieldSet, String> {
        let mut set = FieldSet(0);
        for name in list.split(',').map(str::trim).filter(|n| !n.is_empty()) {
            if name == "all" {
                set = Self::ALL;
                continue;
            }
            let (_, f) = FIELDS.iter().find(|(n, _)| *n == name).ok_or_else(|| {
                format!(
                    "unknown field `{}`",
                    name.chars().take(64).collect::<String>()
                )
            })?;
            set.0 |= Self::bit(*f);
        }
        Ok(set)
    }

    /// The representation `GET /v1/jobs` answers for `fields` (exactly these, and the id) and `expand` (the summary
    /// and these); both absent: the summary.
    pub fn of_query(fields: Option<&str>, expand: Option<&str>) -> Result<FieldSet, String> {
        let base = match fields {
            Some(f) => FieldSet(Self::parse(f)?.0 | Self::bit(Field::Id)),
            None => Self::SUMMARY,
        };
        let more = expand.map(Self::parse).transpose()?.unwrap_or(FieldSet(0));
        Ok(FieldSet(base.0 | more.0))
    }
}

/// The JSON representation of a job.
pub fn job_json(job: &Job) -> serde_json::Value {
    job_fields(job, FieldSet::ALL)
}

/// The fields `set` of a job's JSON representation (only those are computed).
pub fn job_fields(job: &Job, set: FieldSet) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    summary_fields(&mut m, &JobSummary::of(job), set);
    let mut put = |f: Field, name: &str, v: &dyn Fn() -> serde_json::Value| {
        if set.has(f) {
            m.insert(name.to_string(), v());
        }
    };
    put(Field::Attempts, "attempts", &|| json!(job.attempts));
    put(Field::EstimateBytes, "estimate_bytes", &|| {
        json!(job.estimate_bytes)
    });
    put(Field::Error, "error", &|| json!(job.error));
    put(Field::Result, "result", &|| json!(job.result));
    // The request's own fields (input, algorithm, grid, outputs; or input, steps, products).
    if set.has(Field::Request)
        && let Ok(serde_json::Value::Object(req)) = serde_json::to_value(&job.request)
    {
        for (k, x) in req {
            if k != "kind" {
                m.insert(k, x);
            }
        }
    }
    serde_json::Value::Object(m)
}

/// The summary representation of a job, as `GET /v1/jobs` lists it.
pub fn summary_json(job: &JobSummary) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    summary_fields(&mut m, job, FieldSet::SUMMARY);
    serde_json::Value::Object(m)
}

/// The fields of `set` that a summary holds.
fn summary_fields(
    m: &mut serde_json::Map<String, serde_json::Value>,
    job: &JobSummary,
    set: FieldSet,
) {
    let mut put = |f: Field, name: &str, v: &dyn Fn() -> serde_json::Value| {
        if set.has(f) {
            m.insert(name.to_string(), v());
        }
    };
    put(Field::Id, "id", &|| json!(job.id));
    put(Field::Kind, "kind", &|| json!(job.kind));
    put(Field::Status, "status", &|| json!(job.status));
    put(Field::Progress, "progress", &|| json!(job.progress));
    put(Field::Stage, "stage", &|| json!(job.stage));
    put(Field::CreatedAt, "created_at", &|| {
        json!(rfc3339(job.created_us))
    });
    put(Field::StartedAt, "started_at", &|| {
        json!(job.started_us.map(rfc3339))
    });
    put(Field::FinishedAt, "finished_at", &|| {
        json!(job.finished_us.map(rfc3339))
    });
    put(Field::Links, "links", &|| links(job));
}

fn accepted(job: &Job) -> Response {
    let mut r = (StatusCode::ACCEPTED, axum::Json(job_json(job))).into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/jobs/{}", job.id)) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

pub async fn post_job(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: ApiJson<serde_json::Value>,
) -> ApiResult<Response> {
    let key = idempotency_key(&headers)?.map(|key| IdempotencyKey {
        route: ROUTE_JOBS,
        key,
        fingerprint: body.fingerprint.clone(),
    });
    let submitted = st.submit_job(body.value, key).await?;
    Ok(accepted(&submitted.job))
}

/// A job, with the rule run that made it and its deliveries when it has any.
pub async fn get_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let job = st.get_job(id).await?;
    let mut v = job_json(&job);
    let (run, deliveries) = st.job_origin(id).await?;
    if run.is_some() || !deliveries.is_empty() {
        let origin = crate::app::rules::job_origin_json(run.as_ref(), &deliveries);
        if let Some(r) = origin.get("rule") {
            v["rule"] = r.clone();
            v["links"]["rule"] = r["links"]["self"].clone();
            v["links"]["source_series"] = r["links"]["series"].clone();
        }
        v["deliveries"] = origin["deliveries"].clone();
        v["links"]["deliveries"] = json!(format!("/v1/deliveries?job_id={id}"));
    }
    Ok(axum::Json(v).into_response())
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
    /// Comma-separated: exactly these fields of each job (and its id).
    pub fields: Option<String>,
    /// Comma-separated: the summary and these fields (`all`: the whole job).
    pub expand: Option<String>,
}

pub async fn list_jobs(
    State(st): State<AppState>,
    RawQuery(raw): RawQuery,
    ApiQuery(q): ApiQuery<ListQuery>,
) -> ApiResult<Response> {
    // Read before the rows: a page is reused only while no job was written since.
    let generation = st.db.jobs_generation();
    let key = raw.unwrap_or_default();
    if let Some(body) = st.lists.get(&key, generation) {
        return Ok(json_bytes(body));
    }
    let bad = |m: String| api_error(ErrorCode::InvalidQuery, m);
    let mut statuses = Vec::new();
    for s in q.status.iter().flat_map(|s| s.split(',')) {
        let s = s.trim();
        if s.is_empty() {
            continue;
        }
        statuses.push(JobStatus::parse(s).ok_or_else(|| bad(format!("unknown status `{s}`")))?);
    }
    if let Some(k) = q
        .kind
        .as_deref()
        .filter(|k| !matches!(*k, "reconstruction" | "volume"))
    {
        let k: String = k.chars().take(64).collect();
        return Err(bad(format!("unknown kind `{k}`: reconstruction or volume")));
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
    let view = FieldSet::of_query(q.fields.as_deref(), q.expand.as_deref()).map_err(|e| {
        bad(format!(
            "{e}; the fields are {} (or `all`)",
            FIELDS.map(|(n, _)| n).join(", ")
        ))
    })?;
    let filter = JobFilter {
        statuses,
        kind: q.kind.clone(),
        created_after_us: time(&q.created_after, "created_after")?,
        created_before_us: time(&q.created_before, "created_before")?,
        before_id,
        limit,
    };
    // A summary reads neither requests nor results (most lists: status polls).
    let (items, next) = if view.within(FieldSet::SUMMARY) {
        let page = st.list_job_summaries(&filter).await?;
        let items: Vec<_> = page
            .items
            .iter()
            .map(|j| {
                let mut m = serde_json::Map::new();
                summary_fields(&mut m, j, view);
                serde_json::Value::Object(m)
            })
            .collect();
        (items, page.next)
    } else {
        let page = st.list_jobs(&filter).await?;
        let items: Vec<_> = page.items.iter().map(|j| job_fields(j, view)).collect();
        (items, page.next)
    };
    let next = next.map(|id| id.to_string());
    let body = Bytes::from(
        serde_json::to_vec(&json!({ "jobs": items, "next_cursor": next })).unwrap_or_default(),
    );
    st.lists.put(&key, generation, body.clone());
    Ok(json_bytes(body))
}

fn json_bytes(body: Bytes) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

pub async fn cancel_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let job = st.cancel_job(job_id(&id)?).await?;
    Ok(accepted(&job))
}

pub async fn delete_job(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    st.delete_job(job_id(&id)?).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}
