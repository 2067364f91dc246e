//! DICOM in: `POST /v1/series` (a multipart form of files, a ZIP, or one `application/dicom` instance appended
//! to an open upload), `GET /v1/uploads/{id}`, `POST /v1/uploads/{id}/complete` and `DELETE /v1/uploads/{id}`.
//!
//! Bodies and multipart fields stream to temporary files (the size limit enforced while streaming); what
//! becomes of them — decoding, assembling, recording, indexing — is the application's (`app::uploads`).

use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::Value;
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{ApiQuery, idempotency_key, media_type};
use super::super::problem::{ApiResult, api_error};
use super::super::upload::{Spooled, declared_length, paced, spool, too_large};
use crate::app::uploads::{AppendAnswer, ReceivedFile, UploadAnswer, upload_json};
use crate::error_code::ErrorCode;
use crate::jobs::{IdempotencyKey, UploadRecord};
use crate::series::UnevenPolicy;
use crate::storage::UploadId;
use crate::storage::npy::hex;

const ROUTE_SERIES: &str = "POST /v1/series";

/// Most parts of one form (each is a temporary file while the upload is read).
const MAX_PARTS: usize = 20_000;

/// Query of `POST /v1/series` and `POST /v1/uploads/{id}/complete`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeriesQuery {
    /// Append an `application/dicom` body to this open upload.
    pub upload: Option<String>,
    /// Missing slices or uneven spacing: `refuse` (default) or `resample` (with a warning).
    pub uneven: Option<UnevenPolicy>,
}

/// Query of `POST /v1/uploads/{id}/complete`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompleteQuery {
    pub uneven: Option<UnevenPolicy>,
}

fn upload_id(s: &str) -> ApiResult<UploadId> {
    UploadId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
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

pub(super) fn check_length(st: &AppState, headers: &HeaderMap) -> ApiResult<()> {
    let limit = st.settings.max_upload_bytes;
    match declared_length(headers) {
        Some(n) if n > limit.saturating_add(64 << 10) => Err(too_large(limit)),
        _ => Ok(()),
    }
}

/// A file of the upload, streamed to `tmp/`, with the name the client gave it.
pub(super) struct Received {
    pub(super) label: String,
    pub(super) file: Spooled,
}

/// Remove the temporary files of a request.
async fn discard_received(files: Vec<Received>) {
    for f in files {
        f.file.temp.discard().await;
    }
}

/// The whole body, streamed to a temporary file and refused beyond the upload limit.
pub(super) async fn read_body(st: &AppState, req: Request) -> ApiResult<Spooled> {
    let body = req.into_body().into_data_stream();
    let mut spent = 0;
    spool(&st.store, body, &mut spent, st.settings.max_upload_bytes).await
}

/// Every part of a multipart form is a file (a DICOM instance or a ZIP of them), each streamed to its own
/// temporary file; the limit is on the sum.
pub(super) async fn read_multipart(st: &AppState, req: Request) -> ApiResult<Vec<Received>> {
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

/// 201 with the representation of an upload an earlier request created.
fn replayed(u: &UploadRecord) -> Response {
    created(&format!("/v1/uploads/{}", u.id), upload_json(u))
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
            let file = read_body(&st, req).await?;
            if media != "application/octet-stream" {
                st.check_zip(file.temp.path()).await?;
            }
            vec![Received {
                label: "upload.zip".to_string(),
                file,
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
    let files = files
        .into_iter()
        .map(|f| ReceivedFile {
            label: f.label,
            temp: f.file.temp,
        })
        .collect();
    match st.upload_files(files, bytes, q.uneven, key).await? {
        UploadAnswer::Created { id, view } => Ok(created(&format!("/v1/uploads/{id}"), view)),
        UploadAnswer::Replayed(u) => Ok(replayed(&u)),
    }
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
        st.check_open_upload(id).await?;
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
    match st
        .append_instance(existing, key, body.temp, &sha, body.bytes)
        .await?
    {
        AppendAnswer::Appended {
            id,
            view,
            opened: true,
        } => Ok(created(&format!("/v1/uploads/{id}"), view)),
        AppendAnswer::Appended { view, .. } => Ok(axum::Json(view).into_response()),
        AppendAnswer::Replayed(u) => Ok(replayed(&u)),
    }
}

pub async fn get_upload(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let u = st.upload(upload_id(&id)?).await?;
    Ok(axum::Json(upload_json(&u)).into_response())
}

pub async fn complete_upload(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<CompleteQuery>,
) -> ApiResult<Response> {
    let id = upload_id(&id)?;
    let view = st.complete_upload(id, q.uneven).await?;
    Ok(created(&format!("/v1/uploads/{id}"), view))
}

/// `DELETE /v1/uploads/{id}`: 204, an open upload and its instances removed; 409 `upload_closed` for a
/// completed one (it goes with its series).
pub async fn delete_upload(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    st.delete_upload(upload_id(&id)?).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}
