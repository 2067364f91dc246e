//! DICOM in: `POST /v1/series` (a multipart form of files, a ZIP, or one `application/dicom` instance appended
//! to an open upload), `GET /v1/uploads/{id}`, `POST /v1/uploads/{id}/complete`, `GET` and `DELETE
//! /v1/series/{id}`, and `GET /v1/series/{id}/volume.npy`.
//!
//! Bodies and multipart fields stream to temporary files (the size limit enforced while streaming), ZIPs are
//! inflated member by member on disk, files are decoded on the worker pool, split by SeriesInstanceUID and
//! assembled into HU volumes; a file or member that cannot be read is listed as rejected with its reason and
//! the others go on. Instances of an open upload are stored under their SHA-256 as they arrive (so re-sending
//! one is harmless) and assembled on completion; a completion that fails (say, a missing slice) leaves the
//! upload open, so the missing instance can still be sent. Volumes are renamed into place only after their
//! rows are committed.

use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{ApiQuery, idempotency_key, media_type};
use super::super::files::{FileMeta, serve_stored};
use super::super::problem::{ApiResult, api_error};
use super::super::upload::{Spooled, paced, spool, too_large};
use crate::app::Replay;
use crate::app::idempotency::settle;
use crate::app::series::outcome_view;
pub use crate::app::series::series_view;
use crate::dicom::{ReadLimits, UploadFile, read_upload_file};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::{Ingested, Staged, dicom_problem};
use crate::jobs::model::rfc3339;
use crate::jobs::repo::Deleted;
use crate::jobs::{Appended, Completed, IdempotencyKey, SeriesRecord, UploadRecord};
use crate::series::UnevenPolicy;
use crate::storage::npy::hex;
use crate::storage::sweep::BlobKind;
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

/// A file of the upload, streamed to `tmp/`, with the name the client gave it.
struct Received {
    label: String,
    file: Spooled,
}

/// Remove the temporary files of a request.
/// Index the instances of recorded upload `id` (the upload stands whether or not they could be indexed;
/// with a PostgreSQL job database there is no instance index).
async fn index_upload(
    st: &AppState,
    id: UploadId,
    kept: crate::app::instances::StagedInstances,
    records: &[SeriesRecord],
) {
    if let Err(e) = st.index_staged(id, kept, records).await {
        tracing::warn!(upload_id = %id, error = %e, "the upload's instances are not indexed");
    }
}

async fn discard_received(files: Vec<Received>) {
    for f in files {
        f.file.temp.discard().await;
    }
}

/// The whole body, streamed to a temporary file and refused beyond the upload limit.
async fn read_body(st: &AppState, req: Request) -> ApiResult<Spooled> {
    let body = req.into_body().into_data_stream();
    let mut spent = 0;
    spool(&st.store, body, &mut spent, st.settings.max_upload_bytes).await
}

/// Most parts of one form (each is a temporary file while the upload is read).
const MAX_PARTS: usize = 20_000;

/// Every part of a multipart form is a file (a DICOM instance or a ZIP of them), each streamed to its own
/// temporary file; the limit is on the sum.
async fn read_multipart(st: &AppState, req: Request) -> ApiResult<Vec<Received>> {
    let limit = st.settings.max_upload_bytes;
    let bad = |m: String| api_error(ErrorCode::InvalidMultipart, m);
    let mut form = Multipart::from_request(paced(req), st)
        .await
        .map_err(|e| bad(e.body_text()))?;
    let mut files = Vec::new();
    let mut spent = 0u64;
    loop {
        let field = match form.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) => {
                discard_received(files).await;
                return Err(bad(e.body_text()));
            }
        };
        if files.len() >= MAX_PARTS {
            discard_received(files).await;
            return Err(bad(format!(
                "the form has more than {MAX_PARTS} parts; send a ZIP"
            )));
        }
        let name = label(
            field.file_name().or(field.name()),
            format!("part-{}", files.len() + 1),
        );
        match spool(&st.store, field, &mut spent, limit).await {
            Ok(file) => files.push(Received { label: name, file }),
            Err(e) => {
                discard_received(files).await;
                return Err(e);
            }
        }
    }
    if files.is_empty() {
        return Err(bad("the form has no file parts".into()));
    }
    Ok(files)
}

fn created(location: &str, body: Value) -> Response {
    let mut r = (StatusCode::CREATED, axum::Json(body)).into_response();
    if let Ok(loc) = HeaderValue::from_str(location) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

const ROUTE_SERIES: &str = "POST /v1/series";

/// Record an upload completed in one request with its series: `None` when recorded, or the answer of the
/// request that won a race for the same Idempotency-Key.
async fn record_upload(
    st: &AppState,
    id: UploadId,
    (instances, bytes): (u32, u64),
    view: &Value,
    records: &[SeriesRecord],
    key: Option<&IdempotencyKey>,
) -> ApiResult<Option<Response>> {
    let inserted = st
        .db
        .insert_completed_upload(id, instances, bytes, view, records, key)
        .await?;
    match settle(inserted, key)? {
        Replay::New => Ok(None),
        Replay::Existing(id) => {
            let u = load_upload(st, &id).await?;
            Ok(Some(created(
                &format!("/v1/uploads/{}", u.id),
                upload_view(&u),
            )))
        }
    }
}

/// The upload an earlier request with the same Idempotency-Key created (201 with its view), or 422 when that
/// request differed; `None` when the key is new.
async fn replay(st: &AppState, key: &IdempotencyKey) -> ApiResult<Option<Response>> {
    let Replay::Existing(id) = st.replay(Some(key)).await? else {
        return Ok(None);
    };
    let u = load_upload(st, &id).await?;
    Ok(Some(created(
        &format!("/v1/uploads/{}", u.id),
        upload_view(&u),
    )))
}

/// Fingerprint of an upload: the media type, options and the SHA-256 of every file in order.
fn fingerprint(media: &str, q: &SeriesQuery, files: &[Received]) -> String {
    let mut h = Sha256::new();
    h.update(format!("{media}|{:?}|{:?}|", q.upload, q.uneven).as_bytes());
    for f in files {
        h.update(f.file.sha256);
    }
    hex(&h.finalize())
}

/// After the series rows were recorded (`Ok(None)`), move their volumes into place; otherwise (an answer for
/// a lost race, or an error) remove them, so that nothing is left behind.
async fn commit_series(
    st: &AppState,
    staged: Staged,
    recorded: ApiResult<Option<Response>>,
) -> ApiResult<Option<Response>> {
    match recorded {
        Ok(None) => {
            staged.commit(&st.store).await?;
            Ok(None)
        }
        other => {
            staged.discard().await;
            other
        }
    }
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
            vec![Received {
                label: "upload.zip".to_string(),
                file: read_body(&st, req).await?,
            }]
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
    let bytes: u64 = files.iter().map(|f| f.file.bytes).sum();
    let id = UploadId::generate();
    let replayed: ApiResult<Option<Response>> = match &key {
        Some(k) => replay(&st, k).await,
        None => Ok(None),
    };
    let outcome: ApiResult<Result<(Ingested, Staged), Response>> = match replayed {
        Ok(None) => {
            let on_disk = files
                .iter()
                .map(|f| UploadFile {
                    label: f.label.clone(),
                    path: f.file.temp.path().to_path_buf(),
                })
                .collect();
            st.ingest_files(id, on_disk, q.uneven)
                .await
                .map_err(Into::into)
                .map(Ok)
        }
        Ok(Some(r)) => Ok(Err(r)),
        Err(e) => Err(e),
    };
    // Kept aside for the instance index before the received files go; indexed once the upload is recorded.
    let kept = match &outcome {
        Ok(Ok((ingested, _))) if ingested.ready().next().is_some() => {
            let on_disk: Vec<UploadFile> = files
                .iter()
                .map(|f| UploadFile {
                    label: f.label.clone(),
                    path: f.file.temp.path().to_path_buf(),
                })
                .collect();
            st.stage_uploaded(&on_disk, &ingested.rejected).await.ok()
        }
        _ => None,
    };
    discard_received(files).await;
    let (ingested, staged) = match outcome? {
        Ok(done) => done,
        Err(replayed) => return Ok(replayed),
    };
    // Instances (ZIP entries included), not request parts.
    let instances = ingested.files() as u32;
    let records: Vec<SeriesRecord> = ingested.ready().cloned().collect();
    if records.is_empty() {
        staged.discard().await;
        return Err(ingested.failure().into());
    }
    let view = outcome_view(id, instances, bytes, &ingested);
    let recorded = record_upload(&st, id, (instances, bytes), &view, &records, key.as_ref()).await;
    if let Some(r) = commit_series(&st, staged, recorded).await? {
        return Ok(r);
    }
    if let Some(kept) = kept {
        index_upload(&st, id, kept, &records).await;
    }
    st.fire_rules(&ingested, None).await;
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
    let sha = hex(&body.sha256);
    let key = key.map(|key| IdempotencyKey {
        route: ROUTE_SERIES,
        key,
        fingerprint: hex(&Sha256::digest(
            format!("application/dicom|{sha}").as_bytes(),
        )),
    });
    if let Some(k) = &key {
        match replay(st, k).await {
            Ok(None) => {}
            done => {
                body.temp.discard().await;
                return done.and_then(|r| r.ok_or_else(|| Problem::internal().into()));
            }
        }
    }
    // Decode now, so that a broken file is refused at once and never reaches the upload. The instance is
    // labelled in messages by its SOP Instance UID (a body has no file name).
    let decoded = {
        let file = UploadFile {
            label: "the instance".to_string(),
            path: body.temp.path().to_path_buf(),
        };
        st.engine
            .compute(move || {
                read_upload_file(&file, &ReadLimits::default())
                    .map(|inst| {
                        let name = if inst.sop_instance_uid.is_empty() {
                            "an instance without a SOP Instance UID".to_string()
                        } else {
                            inst.sop_instance_uid
                        };
                        (inst.series_uid, name)
                    })
                    .map_err(|e| dicom_problem(&e))
            })
            .await
    };
    let (series_uid, name) = match decoded {
        Ok(v) => v,
        Err(e) => {
            body.temp.discard().await;
            return Err(e.into());
        }
    };
    let (id, new) = match existing {
        Some(id) => (id, false),
        None => {
            let id = UploadId::generate();
            let inserted = st.db.insert_open_upload(id, key.as_ref()).await?;
            if let Replay::Existing(winner) = settle(inserted, key.as_ref())? {
                // Lost a race with the same key: answer the winner.
                let u = load_upload(st, &winner).await?;
                return Ok(created(&format!("/v1/uploads/{}", u.id), upload_view(&u)));
            }
            (id, true)
        }
    };
    // Temporary file → row → rename: a crash between the last two leaves a row the completion reports.
    let path = st.store.upload_file(id, &sha);
    let outcome = st
        .db
        .append_upload_file(
            id,
            &sha,
            &name,
            body.bytes,
            &series_uid,
            st.settings.max_upload_bytes,
        )
        .await;
    let (instances, duplicate) = match outcome {
        Ok(Appended::Added(n)) => {
            body.temp.sync().await?;
            st.store.commit_async(body.temp, path).await?;
            (n, false)
        }
        Ok(Appended::Duplicate(n)) => {
            body.temp.discard().await;
            (n, true)
        }
        Ok(other) => {
            body.temp.discard().await;
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
            body.temp.discard().await;
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
    let mut bytes = 0u64;
    for (sha, name) in listed {
        if sha.len() != 64 || !sha.bytes().all(|b| b.is_ascii_hexdigit()) {
            tracing::error!(upload_id = %id, "an upload file has a malformed hash");
            return Err(Problem::internal().into());
        }
        let path = st.store.upload_file(id, &sha);
        bytes += tokio::fs::metadata(&path).await?.len();
        files.push(UploadFile { label: name, path });
    }
    let (ingested, staged) = st.ingest_files(id, files.clone(), q.uneven).await?;
    let records: Vec<SeriesRecord> = ingested.ready().cloned().collect();
    if records.is_empty() {
        // The upload stays open: a missing instance can still be appended.
        staged.discard().await;
        return Err(ingested.failure().into());
    }
    let view = outcome_view(id, instances, bytes, &ingested);
    let recorded = match st.db.complete_upload(id, instances, &view, &records).await {
        Ok(Completed::Done) => Ok(None),
        Ok(Completed::Changed) => Err(api_error(
            ErrorCode::UploadChanged,
            "instances arrived while the upload was being completed; complete it again",
        )),
        Ok(Completed::Closed) => Err(api_error(
            ErrorCode::UploadClosed,
            format!("upload {id} was completed meanwhile"),
        )),
        Err(e) => Err(e.into()),
    };
    commit_series(&st, staged, recorded).await?;
    if let Ok(kept) = st.stage_uploaded(&files, &ingested.rejected).await {
        index_upload(&st, id, kept, &records).await;
    }
    st.fire_rules(&ingested, None).await;
    let store = st.store.clone();
    let removed = tokio::task::spawn_blocking(move || store.remove_upload(id)).await;
    if let Ok(Err(e)) = removed {
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

/// 410 when the start-up sweep found the series' volume missing.
async fn check_available(st: &AppState, id: SeriesId) -> ApiResult<()> {
    if st
        .db
        .blob_missing(BlobKind::Series, &id.to_string())
        .await?
    {
        return Err(api_error(
            ErrorCode::FileMissing,
            format!("the volume of series {id} was lost; upload the series again"),
        ));
    }
    Ok(())
}

pub async fn get_series(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let r = load_series(&st, &id).await?;
    let missing = st
        .db
        .blob_missing(BlobKind::Series, &r.id.to_string())
        .await?;
    let mut view = series_view(&r);
    view["available"] = json!(!missing);
    Ok(axum::Json(view).into_response())
}

/// `DELETE /v1/series/{id}`: 204, the row and then the volume removed; 409 while a queued or running job
/// reads it.
pub async fn delete_series(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = series_id(&id)?;
    match st.db.delete_series(id).await? {
        Deleted::Done => {
            // A crash before this removal leaves an orphan file, which the start-up sweep removes.
            if let Err(e) = st.store.remove_blob_async(&st.store.series_path(id)).await {
                tracing::warn!(error = %e, series_id = %id, "removing a deleted series' volume failed");
            }
            // Its indexed instances went with its row; their folder goes once no row names it.
            if let Err(e) = st.sweep_instances().await {
                tracing::warn!(error = %e, series_id = %id, "removing a deleted series' instances failed");
            }
            tracing::info!(series_id = %id, "series deleted");
            Ok(StatusCode::NO_CONTENT.into_response())
        }
        Deleted::InUse => Err(api_error(
            ErrorCode::ResourceInUse,
            format!("series {id} is the input of a queued or running job; cancel it or wait"),
        )),
        Deleted::NotFound => Err(api_error(
            ErrorCode::SeriesNotFound,
            format!("no series {id}"),
        )),
    }
}

pub async fn series_volume(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let r = load_series(&st, &id).await?;
    check_available(&st, r.id).await?;
    serve_stored(
        &headers,
        &st.store,
        FileMeta {
            path: st.store.series_path(r.id),
            etag: r.volume.sha256,
            content_type: "application/x-npy",
            filename: Some(format!("{}.npy", r.id)),
        },
    )
    .await
}
