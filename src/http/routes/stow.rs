//! STOW-RS: `POST /dicom-web/studies[/{study}]` with a `multipart/related; type="application/dicom"` body.
//!
//! The body is parsed as it streams ([`crate::dicom::multipart::Parser`]): each part goes to a temporary file
//! chunk by chunk, refused as soon as it passes the DICOM node's instance limit, and the whole body is
//! refused (413) as soon as it passes the upload limit of `/v1` uploads (at once, unread, when its
//! `Content-Length` is already over it). The parts are then stored through
//! the same receive path as C-STORE ([`crate::app::App::stow`]). The answer is the PS3.18 response in
//! `application/dicom+json`: ReferencedSOPSequence (0008,1199) with a RetrieveURL per stored instance,
//! FailedSOPSequence (0008,1198) with a FailureReason (0008,1197) per refused part, and a `Warning: 299` header
//! field with the catalogue code (`dicom_invalid_uid`, …) of each part refused for what it holds; 200 when all were stored,
//! 202 when some were, 409 when none. A body that is not `multipart/related` of DICOM is 415; a missing or
//! wrong boundary, or a body that is not multipart, is 400; in both cases nothing is stored.

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::Response;
use futures_util::StreamExt;
use serde_json::{Value, json};
use tokio::io::AsyncWriteExt;

use super::super::AppState;
use super::super::problem::{ApiResult, api_error};
use super::super::upload::{declared_length, too_large};
use super::dicomweb::{base_url, dicom_json_response};
use crate::app::dicomweb::resource_path;
use crate::app::stow::{StowOutcome, StowPart, reason};
use crate::dicom::multipart::{Event, Parser, media_type};
use crate::error_code::ErrorCode;
use crate::storage::TempBlob;

/// Longest header block of one part (bytes).
const MAX_PART_HEADERS: usize = 16 << 10;

/// The boundary of a STOW-RS body, or the problem (415 or 400).
fn boundary(headers: &HeaderMap) -> ApiResult<String> {
    let value = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let (essence, params) = media_type(value).ok_or_else(|| {
        api_error(
            ErrorCode::UnsupportedMediaType,
            "send multipart/related; type=\"application/dicom\"",
        )
    })?;
    let param = |n: &str| params.iter().find(|(k, _)| k == n).map(|(_, v)| v.clone());
    if essence != "multipart/related" || param("type").as_deref() != Some("application/dicom") {
        return Err(api_error(
            ErrorCode::UnsupportedMediaType,
            "send multipart/related; type=\"application/dicom\" (application/dicom+json and XML bodies are not accepted)",
        ));
    }
    param("boundary").ok_or_else(|| {
        api_error(
            ErrorCode::InvalidMultipart,
            "the Content-Type has no boundary",
        )
    })
}

/// One part being received.
struct Open {
    temp: Option<(TempBlob, tokio::fs::File)>,
    bytes: u64,
    refused: Option<(u16, String)>,
}

/// Read the body into parts (files under `tmp/`; the temporaries are removed when dropped).
async fn receive(
    state: &AppState,
    body: Body,
    boundary: &str,
) -> ApiResult<(Vec<StowPart>, Vec<TempBlob>)> {
    let mut parser = Parser::new(boundary, MAX_PART_HEADERS)
        .map_err(|e| api_error(ErrorCode::InvalidMultipart, e.to_string()))?;
    let (limit, part_limit) = (
        state.settings.max_upload_bytes,
        state.settings.dicom.max_instance_bytes,
    );
    let mut stream = body.into_data_stream();
    let (mut spent, mut parts, mut temps) = (0u64, Vec::new(), Vec::new());
    let mut open: Option<Open> = None;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| api_error(ErrorCode::TruncatedUpload, e.to_string()))?;
        spent = spent.saturating_add(chunk.len() as u64);
        if spent > limit {
            return Err(too_large(limit));
        }
        let events = parser
            .feed(&chunk)
            .map_err(|e| api_error(ErrorCode::InvalidMultipart, e.to_string()))?;
        for e in events {
            match e {
                Event::Part(h) => {
                    let ct = h.get("content-type").unwrap_or("application/dicom");
                    let dicom = media_type(ct).is_some_and(|(t, _)| t == "application/dicom");
                    let mut o = Open {
                        temp: None,
                        bytes: 0,
                        refused: None,
                    };
                    if dicom {
                        let t = state.store.temp();
                        let f = tokio::fs::File::create(t.path()).await?;
                        o.temp = Some((t, f));
                    } else {
                        o.refused = Some((
                            reason::CANNOT_UNDERSTAND,
                            format!("a part of type {ct} is not application/dicom"),
                        ));
                    }
                    open = Some(o);
                }
                Event::Data(d) => {
                    let Some(o) = open.as_mut() else { continue };
                    o.bytes += d.len() as u64;
                    if o.bytes > part_limit && o.refused.is_none() {
                        o.temp = None; // removes the file
                        o.refused = Some((
                            reason::OUT_OF_RESOURCES,
                            format!("the instance exceeds the limit of {part_limit} bytes"),
                        ));
                    }
                    if let Some((_, f)) = o.temp.as_mut() {
                        f.write_all(&d).await?;
                    }
                }
                Event::PartEnd => {
                    let Some(o) = open.take() else { continue };
                    match (o.refused, o.temp) {
                        (Some((reason, why)), _) => parts.push(StowPart::Refused { reason, why }),
                        (None, Some((t, mut f))) => {
                            f.flush().await?;
                            f.sync_all().await?;
                            parts.push(StowPart::File {
                                path: t.path().to_path_buf(),
                                bytes: o.bytes,
                            });
                            temps.push(t);
                        }
                        (None, None) => {}
                    }
                }
            }
        }
    }
    parser
        .finish()
        .map_err(|e| api_error(ErrorCode::InvalidMultipart, e.to_string()))?;
    if parts.is_empty() {
        return Err(api_error(
            ErrorCode::InvalidMultipart,
            "the body has no part",
        ));
    }
    Ok((parts, temps))
}

/// The PS3.18 response of a STOW-RS request.
fn response_json(outcomes: &[StowOutcome], study: Option<&str>, base: &str) -> Value {
    let uid = |v: &Option<String>| json!({"vr": "UI", "Value": [v.clone().unwrap_or_default()]});
    let (mut referenced, mut failed) = (Vec::new(), Vec::new());
    for o in outcomes {
        match o.failure {
            None => {
                let url = resource_path(
                    o.study_uid.as_deref().unwrap_or_default(),
                    o.series_uid.as_deref(),
                    o.sop_instance_uid.as_deref(),
                );
                referenced.push(json!({
                    "00081150": uid(&o.sop_class_uid),
                    "00081155": uid(&o.sop_instance_uid),
                    "00081190": {"vr": "UR", "Value": [format!("{base}{url}")]},
                }));
            }
            Some(reason) => {
                let mut item = json!({ "00081197": {"vr": "US", "Value": [reason]} });
                if o.sop_class_uid.is_some() {
                    item["00081150"] = uid(&o.sop_class_uid);
                    item["00081155"] = uid(&o.sop_instance_uid);
                }
                failed.push(item);
            }
        }
    }
    let mut body = json!({});
    let study = study.map(str::to_string).or_else(|| {
        let mut studies = outcomes
            .iter()
            .filter(|o| o.failure.is_none())
            .filter_map(|o| o.study_uid.clone());
        let first = studies.next()?;
        studies.all(|s| s == first).then_some(first)
    });
    if let Some(s) = study {
        body["00081190"] =
            json!({"vr": "UR", "Value": [format!("{base}{}", resource_path(&s, None, None))]});
    }
    if !failed.is_empty() {
        body["00081198"] = json!({"vr": "SQ", "Value": failed});
    }
    if !referenced.is_empty() {
        body["00081199"] = json!({"vr": "SQ", "Value": referenced});
    }
    body
}

async fn stow(
    state: AppState,
    headers: HeaderMap,
    study: Option<String>,
    body: Body,
) -> ApiResult<Response> {
    // A body declared over the limit is refused before a byte of it is read.
    let limit = state.settings.max_upload_bytes;
    if declared_length(&headers).is_some_and(|n| n > limit) {
        return Err(too_large(limit));
    }
    let b = boundary(&headers)?;
    if let Some(s) = &study
        && !crate::dicom::is_valid_uid(s)
    {
        return Err(api_error(
            ErrorCode::InvalidId,
            "the study UID is malformed",
        ));
    }
    let (parts, temps) = receive(&state, body, &b).await?;
    let outcomes = state.stow(parts, study.as_deref()).await?;
    drop(temps); // what was not kept
    for o in outcomes.iter().filter(|o| o.failure.is_some()) {
        tracing::warn!(sop_instance_uid = ?o.sop_instance_uid, reason = format!("{:04X}", o.failure.unwrap_or_default()), code = o.code.unwrap_or_default(), why = %o.why, "STOW-RS part refused");
    }
    let stored = outcomes.iter().filter(|o| o.failure.is_none()).count();
    let status = match stored {
        n if n == outcomes.len() => StatusCode::OK,
        0 => StatusCode::CONFLICT,
        _ => StatusCode::ACCEPTED,
    };
    tracing::info!(parts = outcomes.len(), stored, "STOW-RS request answered");
    let json = response_json(&outcomes, study.as_deref(), &base_url(&headers));
    let mut response = dicom_json_response(status, &json);
    for value in warnings(&outcomes) {
        response.headers_mut().append(header::WARNING, value);
    }
    Ok(response)
}

/// Most `Warning` header fields of one answer.
const MAX_WARNINGS: usize = 16;

/// A `Warning` header field (PS3.18 §10.5.3: `299`, a miscellaneous persistent warning) per part refused
/// for what it holds: its catalogue code and why, so that a client sees the code the other doors answer.
fn warnings(outcomes: &[StowOutcome]) -> Vec<HeaderValue> {
    outcomes
        .iter()
        .enumerate()
        .filter_map(|(k, o)| {
            let code = o.code.filter(|_| o.failure.is_some())?;
            let why: String = o
                .why
                .chars()
                .map(|c| match c {
                    '"' | '\\' => '\'',
                    c if c.is_ascii_graphic() || c == ' ' => c,
                    _ => '?',
                })
                .take(300)
                .collect();
            HeaderValue::from_str(&format!("299 ctrecon \"part {}: {code}: {why}\"", k + 1)).ok()
        })
        .take(MAX_WARNINGS)
        .collect()
}

#[tracing::instrument(skip_all)]
pub async fn store_instances(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult<Response> {
    stow(state, headers, None, body).await
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn store_study_instances(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult<Response> {
    stow(state, headers, Some(study), body).await
}
