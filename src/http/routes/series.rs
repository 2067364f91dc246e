//! DICOM in: `POST /v1/series` (a multipart form of files, a ZIP, or one `application/dicom` instance appended
//! to an open upload), `GET /v1/uploads/{id}`, `POST /v1/uploads/{id}/complete`, `GET /v1/series/{id}` and
//! `GET /v1/series/{id}/volume.npy`.
//!
//! Files are held in memory up to the upload limit, decoded on the worker pool, split by SeriesInstanceUID and
//! assembled into HU volumes. Instances of an open upload are stored under their SHA-256 as they arrive (so
//! re-sending one is harmless) and assembled on completion; a completion that fails (say, a missing slice)
//! leaves the upload open, so the missing instance can still be sent.

use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{ApiQuery, idempotency_key, media_type};
use super::super::files::{FileMeta, serve_file};
use super::super::problem::{ApiError, ApiResult, api_error};
use crate::dicom::{ReadLimits, ZipLimits, read_bytes};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::{IngestOptions, Ingested, dicom_problem, ingest};
use crate::jobs::model::rfc3339;
use crate::jobs::{Appended, Completed, IdempotencyKey, Inserted, SeriesRecord, UploadRecord};
use crate::recon::control::{Cancel, Control, NoProgress};
use crate::series::UnevenPolicy;
use crate::storage::npy::hex;
use crate::storage::{SeriesId, UploadId};

/// Query of `POST /v1/series` and `POST /v1/uploads/{id}/complete`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeriesQuery {
    /// Append an `application/dicom` body to this open upload.
    pub upload: Option<String>,
    /// Missing slices or uneven spacing: `refuse` (default) or `resample` (with a warning).
    pub uneven: Option<UnevenPolicy>,
}

fn upload_id(s: &str) -> ApiResult<UploadId> {
    UploadId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

fn series_id(s: &str) -> ApiResult<SeriesId> {
    SeriesId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

/// A client-supplied file name, made safe for messages (it is never a path).
fn label(name: Option<&str>, fallback: String) -> String {
    match name {
        Some(n) if !n.trim().is_empty() => n
            .chars()
            .map(|c| if c.is_control() { '?' } else { c })
            .take(200)
            .collect(),
        _ => fallback,
    }
}

fn too_large(limit: u64) -> ApiError {
    api_error(
        ErrorCode::BodyTooLarge,
        format!("the upload exceeds the limit of {limit} bytes"),
    )
}

fn check_length(st: &AppState, headers: &HeaderMap) -> ApiResult<()> {
    let limit = st.settings.max_upload_bytes;
    match headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
    {
        Some(n) if n > limit.saturating_add(64 << 10) => Err(too_large(limit)),
        _ => Ok(()),
    }
}

/// The whole body, refused beyond the upload limit.
async fn read_body(st: &AppState, req: Request) -> ApiResult<Vec<u8>> {
    let limit = st.settings.max_upload_bytes;
    let mut out = Vec::new();
    let mut body = req.into_body().into_data_stream();
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| api_error(ErrorCode::TruncatedUpload, e.to_string()))?;
        if out.len() as u64 + chunk.len() as u64 > limit {
            return Err(too_large(limit));
        }
        out.extend_from_slice(&chunk);
    }
    Ok(out)
}

/// Every part of a multipart form is a file (a DICOM instance or a ZIP of them).
async fn read_multipart(st: &AppState, req: Request) -> ApiResult<Vec<(String, Vec<u8>)>> {
    let limit = st.settings.max_upload_bytes;
    let bad = |m: String| api_error(ErrorCode::InvalidMultipart, m);
    let mut form = Multipart::from_request(req, st)
        .await
        .map_err(|e| bad(e.body_text()))?;
    let mut files = Vec::new();
    let mut total = 0u64;
    while let Some(mut field) = form.next_field().await.map_err(|e| bad(e.body_text()))? {
        let name = label(
            field.file_name().or(field.name()),
            format!("part-{}", files.len() + 1),
        );
        let mut bytes = Vec::new();
        while let Some(chunk) = field
            .chunk()
            .await
            .map_err(|e| api_error(ErrorCode::TruncatedUpload, e.body_text()))?
        {
            total += chunk.len() as u64;
            if total > limit {
                return Err(too_large(limit));
            }
            bytes.extend_from_slice(&chunk);
        }
        files.push((name, bytes));
    }
    if files.is_empty() {
        return Err(bad("the form has no file parts".into()));
    }
    Ok(files)
}

fn ingest_options(st: &AppState, uneven: Option<UnevenPolicy>) -> IngestOptions {
    let budget = st.settings.memory_budget_bytes;
    IngestOptions {
        uneven: uneven.unwrap_or_default(),
        read: ReadLimits::default(),
        zip: ZipLimits {
            max_total_bytes: budget.min(ZipLimits::default().max_total_bytes),
            ..ZipLimits::default()
        },
        // Stored slices and the f32 volume both live in memory while assembling.
        max_voxels: usize::try_from(budget / 8).unwrap_or(usize::MAX),
    }
}

/// The JSON view of a stored series.
pub fn series_view(r: &SeriesRecord) -> Value {
    let mut v = serde_json::to_value(r).unwrap_or_default();
    if let Some(m) = v.as_object_mut() {
        m.insert("created_at".into(), rfc3339(r.created_us).into());
        m.insert(
            "links".into(),
            json!({
                "self": format!("/v1/series/{}", r.id),
                "volume": format!("/v1/series/{}/volume.npy", r.id),
                "upload": format!("/v1/uploads/{}", r.upload_id),
            }),
        );
    }
    v
}

/// The JSON of a completed upload: the upload, each series (with links when stored) and the refused files.
fn outcome_view(id: UploadId, instances: u32, bytes: u64, ingested: &Ingested) -> Value {
    let series: Vec<Value> = ingested
        .series
        .iter()
        .map(|s| {
            let mut v = json!({ "status": s.status, "report": s.report });
            if let Some(r) = &s.series {
                v["series"] = series_view(r);
            }
            if let Some(e) = &s.error {
                v["error"] = json!(e);
            }
            v
        })
        .collect();
    json!({
        "upload": {"id": id, "status": "completed", "instances": instances, "bytes": bytes,
                   "links": {"self": format!("/v1/uploads/{id}")}},
        "series": series,
        "rejected": ingested.rejected,
    })
}

fn created(location: &str, body: Value) -> Response {
    let mut r = (StatusCode::CREATED, axum::Json(body)).into_response();
    if let Ok(loc) = HeaderValue::from_str(location) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

/// Remove the volumes of series that were assembled but will not be recorded.
fn discard(st: &AppState, ingested: &Ingested) {
    for r in ingested.ready() {
        let _ = std::fs::remove_file(st.store.series_path(r.id));
    }
}

/// Decode and assemble `files` on the pool.
async fn run_ingest(
    st: &AppState,
    id: UploadId,
    files: Vec<(String, Vec<u8>)>,
    uneven: Option<UnevenPolicy>,
) -> ApiResult<Ingested> {
    let store = st.store.clone();
    let opts = ingest_options(st, uneven);
    Ok(st
        .engine
        .compute(move || {
            let cancel = Cancel::new();
            ingest(&store, id, files, &opts, Control::new(&cancel, &NoProgress))
        })
        .await?)
}

const ROUTE_SERIES: &str = "POST /v1/series";

/// The upload an earlier request with the same Idempotency-Key created (201 with its view), or 422 when that
/// request differed; `None` when the key is new.
async fn replay(st: &AppState, key: &IdempotencyKey) -> ApiResult<Option<Response>> {
    let Some((id, fingerprint)) = st.db.idempotency_lookup(key.route, &key.key).await? else {
        return Ok(None);
    };
    if fingerprint != key.fingerprint {
        return Err(api_error(
            ErrorCode::IdempotencyKeyReused,
            "this Idempotency-Key was used with a different request",
        ));
    }
    let u = load_upload(st, &id).await?;
    Ok(Some(created(
        &format!("/v1/uploads/{}", u.id),
        upload_view(&u),
    )))
}

/// Fingerprint of an upload: the media type, options and the SHA-256 of every file in order.
fn fingerprint(media: &str, q: &SeriesQuery, files: &[(String, Vec<u8>)]) -> String {
    let mut h = Sha256::new();
    h.update(format!("{media}|{:?}|{:?}|", q.upload, q.uneven).as_bytes());
    for (_, bytes) in files {
        h.update(Sha256::digest(bytes));
    }
    hex(&h.finalize())
}

pub async fn post_series(
    State(st): State<AppState>,
    ApiQuery(q): ApiQuery<SeriesQuery>,
    req: Request,
) -> ApiResult<Response> {
    check_length(&st, req.headers())?;
    let key = idempotency_key(req.headers())?;
    let media = media_type(req.headers());
    let files = match media.as_str() {
        "application/dicom" => return append(&st, q, key, req).await,
        _ if q.upload.is_some() => {
            return Err(api_error(
                ErrorCode::InvalidQuery,
                "`upload` appends one application/dicom instance; send forms and ZIPs without it",
            ));
        }
        "multipart/form-data" => read_multipart(&st, req).await?,
        "application/zip" | "application/x-zip-compressed" | "application/octet-stream" => {
            vec![("upload.zip".to_string(), read_body(&st, req).await?)]
        }
        _ => {
            return Err(api_error(
                ErrorCode::UnsupportedMediaType,
                "send multipart/form-data (one part per file or ZIP), application/zip, or one \
                 application/dicom instance",
            ));
        }
    };
    let key = key.map(|key| IdempotencyKey {
        route: ROUTE_SERIES,
        key,
        fingerprint: fingerprint(&media, &q, &files),
    });
    if let Some(k) = &key
        && let Some(r) = replay(&st, k).await?
    {
        return Ok(r);
    }
    let bytes: u64 = files.iter().map(|(_, b)| b.len() as u64).sum();
    let id = UploadId::generate();
    let ingested = run_ingest(&st, id, files, q.uneven).await?;
    // Instances (ZIP entries included), not request parts.
    let instances = ingested.files() as u32;
    let records: Vec<SeriesRecord> = ingested.ready().cloned().collect();
    if records.is_empty() {
        return Err(ingested.failure().into());
    }
    let view = outcome_view(id, instances, bytes, &ingested);
    match st
        .db
        .insert_completed_upload(id, instances, bytes, &view, &records, key.as_ref())
        .await
    {
        Ok(Inserted::New) => {}
        Ok(Inserted::Existing { .. }) => {
            // Lost a race with the same key: answer the winner.
            discard(&st, &ingested);
            if let Some(k) = &key
                && let Some(r) = replay(&st, k).await?
            {
                return Ok(r);
            }
            return Err(Problem::internal().into());
        }
        Err(e) => {
            discard(&st, &ingested);
            return Err(e.into());
        }
    }
    tracing::info!(upload_id = %id, series = records.len(), rejected = ingested.rejected.len(), "upload completed");
    Ok(created(&format!("/v1/uploads/{id}"), view))
}

fn upload_view(u: &UploadRecord) -> Value {
    if let Some(outcome) = &u.outcome {
        return outcome.clone();
    }
    json!({
        "upload": {
            "id": u.id,
            "status": if u.open { "open" } else { "completed" },
            "instances": u.instances,
            "bytes": u.bytes,
            "created_at": rfc3339(u.created_us),
            "links": {
                "self": format!("/v1/uploads/{}", u.id),
                "append": format!("/v1/series?upload={}", u.id),
                "complete": format!("/v1/uploads/{}/complete", u.id),
            }
        }
    })
}

/// Append one `application/dicom` instance to the open upload `q.upload`, or to a new one.
async fn append(
    st: &AppState,
    q: SeriesQuery,
    key: Option<String>,
    req: Request,
) -> ApiResult<Response> {
    if q.uneven.is_some() {
        return Err(api_error(
            ErrorCode::InvalidQuery,
            "`uneven` applies on completion (POST /v1/uploads/{id}/complete)",
        ));
    }
    let existing = q.upload.as_deref().map(upload_id).transpose()?;
    if let Some(id) = existing {
        match st.db.get_upload(id).await? {
            None => {
                return Err(api_error(
                    ErrorCode::UploadNotFound,
                    format!("no upload {id}"),
                ));
            }
            Some(u) if !u.open => {
                return Err(api_error(
                    ErrorCode::UploadClosed,
                    format!("upload {id} is completed; start a new one"),
                ));
            }
            Some(_) => {}
        }
    }
    if key.is_some() && existing.is_some() {
        return Err(api_error(
            ErrorCode::InvalidRequest,
            "appends are idempotent by content; an Idempotency-Key applies to the request that opens an upload",
        ));
    }
    let body = read_body(st, req).await?;
    let sha = hex(&Sha256::digest(&body));
    let key = key.map(|key| IdempotencyKey {
        route: ROUTE_SERIES,
        key,
        fingerprint: hex(&Sha256::digest(
            format!("application/dicom|{sha}").as_bytes(),
        )),
    });
    if let Some(k) = &key
        && let Some(r) = replay(st, k).await?
    {
        return Ok(r);
    }
    // Decode now, so that a broken file is refused at once and never reaches the upload. The instance is
    // labelled in messages by its SOP Instance UID (a body has no file name).
    let (body, series_uid, name) = st
        .engine
        .compute(move || {
            let inst = read_bytes("the instance", &body, &ReadLimits::default())
                .map_err(|e| dicom_problem(&e))?;
            let name = if inst.sop_instance_uid.is_empty() {
                "an instance without a SOP Instance UID".to_string()
            } else {
                inst.sop_instance_uid
            };
            Ok((body, inst.series_uid, name))
        })
        .await?;
    let (id, new) = match existing {
        Some(id) => (id, false),
        None => {
            let id = UploadId::generate();
            if let Inserted::Existing { .. } = st.db.insert_open_upload(id, key.as_ref()).await? {
                // Lost a race with the same key: answer the winner.
                if let Some(k) = &key
                    && let Some(r) = replay(st, k).await?
                {
                    return Ok(r);
                }
                return Err(Problem::internal().into());
            }
            (id, true)
        }
    };
    let path = st.store.upload_file(id, &sha);
    st.store.write_atomic(&path, &body)?;
    let outcome = st
        .db
        .append_upload_file(
            id,
            &sha,
            &name,
            body.len() as u64,
            &series_uid,
            st.settings.max_upload_bytes,
        )
        .await;
    let (instances, duplicate) = match outcome {
        Ok(Appended::Added(n)) => (n, false),
        Ok(Appended::Duplicate(n)) => (n, true),
        Ok(other) => {
            let _ = std::fs::remove_file(&path);
            return Err(match other {
                Appended::Closed => api_error(
                    ErrorCode::UploadClosed,
                    format!("upload {id} was completed meanwhile"),
                ),
                Appended::TooLarge(limit) => api_error(
                    ErrorCode::BodyTooLarge,
                    format!("the upload would exceed its limit of {limit} bytes"),
                ),
                _ => api_error(ErrorCode::UploadNotFound, format!("no upload {id}")),
            });
        }
        Err(e) => {
            let _ = std::fs::remove_file(&path);
            return Err(e.into());
        }
    };
    tracing::info!(upload_id = %id, instances, duplicate, "instance appended");
    let u = st
        .db
        .get_upload(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::UploadNotFound, format!("no upload {id}")))?;
    let mut view = upload_view(&u);
    view["appended"] = json!({"file": name, "series_uid": series_uid, "duplicate": duplicate});
    if new {
        Ok(created(&format!("/v1/uploads/{id}"), view))
    } else {
        Ok(axum::Json(view).into_response())
    }
}

async fn load_upload(st: &AppState, id: &str) -> ApiResult<UploadRecord> {
    let id = upload_id(id)?;
    st.db
        .get_upload(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::UploadNotFound, format!("no upload {id}")))
}

pub async fn get_upload(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let u = load_upload(&st, &id).await?;
    Ok(axum::Json(upload_view(&u)).into_response())
}

/// Query of `POST /v1/uploads/{id}/complete`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompleteQuery {
    pub uneven: Option<UnevenPolicy>,
}

pub async fn complete_upload(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<CompleteQuery>,
) -> ApiResult<Response> {
    let u = load_upload(&st, &id).await?;
    let id = u.id;
    if !u.open {
        return Err(api_error(
            ErrorCode::UploadClosed,
            format!("upload {id} is already completed"),
        ));
    }
    let listed = st.db.upload_files(id).await?;
    let instances = listed.len() as u32;
    let mut files = Vec::with_capacity(listed.len());
    for (sha, name) in listed {
        if sha.len() != 64 || !sha.bytes().all(|b| b.is_ascii_hexdigit()) {
            tracing::error!(upload_id = %id, "an upload file has a malformed hash");
            return Err(Problem::internal().into());
        }
        files.push((name, tokio::fs::read(st.store.upload_file(id, &sha)).await?));
    }
    let bytes: u64 = files.iter().map(|(_, b)| b.len() as u64).sum();
    let ingested = run_ingest(&st, id, files, q.uneven).await?;
    let records: Vec<SeriesRecord> = ingested.ready().cloned().collect();
    if records.is_empty() {
        // The upload stays open: a missing instance can still be appended.
        return Err(ingested.failure().into());
    }
    let view = outcome_view(id, instances, bytes, &ingested);
    match st.db.complete_upload(id, instances, &view, &records).await {
        Ok(Completed::Done) => {}
        Ok(other) => {
            discard(&st, &ingested);
            return Err(match other {
                Completed::Changed => api_error(
                    ErrorCode::UploadChanged,
                    "instances arrived while the upload was being completed; complete it again",
                ),
                _ => api_error(
                    ErrorCode::UploadClosed,
                    format!("upload {id} was completed meanwhile"),
                ),
            });
        }
        Err(e) => {
            discard(&st, &ingested);
            return Err(e.into());
        }
    }
    if let Err(e) = st.store.remove_upload(id) {
        tracing::warn!(error = %e, upload_id = %id, "removing the instances of a completed upload failed");
    }
    tracing::info!(upload_id = %id, series = records.len(), "upload completed");
    Ok(created(&format!("/v1/uploads/{id}"), view))
}

async fn load_series(st: &AppState, id: &str) -> ApiResult<SeriesRecord> {
    let id = series_id(id)?;
    st.db
        .get_series(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::SeriesNotFound, format!("no series {id}")))
}

pub async fn get_series(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let r = load_series(&st, &id).await?;
    Ok(axum::Json(series_view(&r)).into_response())
}

pub async fn series_volume(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let r = load_series(&st, &id).await?;
    serve_file(
        &headers,
        FileMeta {
            path: st.store.series_path(r.id),
            etag: r.volume.sha256,
            content_type: "application/x-npy",
            filename: Some(format!("{}.npy", r.id)),
        },
    )
    .await
}
