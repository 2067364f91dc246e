//! WADO-RS retrieval of a study, series or instance as `multipart/related; type="application/dicom"`,
//! streamed from the stored files (one part per instance, each with its Content-Type, Content-Length and
//! Content-Location). The transfer syntax asked for in `Accept` decides which instances are re-encoded
//! (`app::wado::RetrieveSyntax`): explicit VR little endian unless `transfer-syntax=*` asks for the stored
//! one.

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::Response;

use super::super::super::AppState;
use super::super::super::problem::{ApiResult, api_error};
use super::negotiation::{accepted, base_url, not_acceptable, param};
use crate::app::dicomweb::resource_path;
use crate::app::wado::RetrieveSyntax;
use crate::dicom::EXPLICIT_LE;
use crate::error_code::ErrorCode;
use crate::http::files::{Chunks, send_file_range};
use crate::jobs::model::StoredInstance;

/// The syntax a retrieval's `Accept` asks for, or 406.
fn retrieve_syntax(headers: &HeaderMap) -> ApiResult<RetrieveSyntax> {
    for (t, p) in accepted(headers) {
        let dicom = match t.as_str() {
            "*/*" | "multipart/*" => true,
            "multipart/related" => param(&p, "type").is_none_or(|ty| ty == "application/dicom"),
            _ => false,
        };
        if !dicom {
            continue;
        }
        // PS3.18 §8.7.3.5.2: without a transfer-syntax parameter, application/dicom is explicit VR
        // little endian.
        return match param(&p, "transfer-syntax") {
            None => Ok(RetrieveSyntax::ExplicitLe),
            Some("*") => Ok(RetrieveSyntax::Stored),
            Some(EXPLICIT_LE) => Ok(RetrieveSyntax::ExplicitLe),
            Some(other) => Err(api_error(
                ErrorCode::NotAcceptable,
                format!("transfer syntax {other} is not offered: ask for * or {EXPLICIT_LE}"),
            )),
        };
    }
    Err(not_acceptable(
        "multipart/related; type=\"application/dicom\"",
    ))
}

/// Hand the whole file at `path` to `tx` in chunks (see [`send_file_range`]; read to its end, no stat).
fn send_file(path: &std::path::Path, tx: &Chunks) -> bool {
    match std::fs::File::open(path) {
        Ok(f) => send_file_range(f, 0, u64::MAX, tx),
        Err(e) => {
            let _ = tx.blocking_send(Err(e));
            false
        }
    }
}

/// Stream `instances` as one `multipart/related` body: the parts are produced one at a time by a task,
/// files read in chunks of up to 1 MiB through a channel of four, so memory stays flat in the retrieval's
/// size.
async fn retrieve(
    state: AppState,
    headers: HeaderMap,
    instances: Vec<StoredInstance>,
) -> ApiResult<Response> {
    let syntax = retrieve_syntax(&headers)?;
    syntax.check(&instances)?;
    let boundary = uuid::Uuid::new_v4().simple().to_string();
    let base = base_url(&headers);
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    let app = state.app.clone();
    let b = boundary.clone();
    // The first instance is made ready before the answer starts, so that one that cannot be sent in the
    // syntax asked for (a single-instance retrieval above all) is a problem, not a cut-off body.
    let mut first = match instances.first() {
        Some(i) => Some(state.retrieved_instance(i, syntax).await?),
        None => None,
    };
    tokio::spawn(async move {
        for i in instances {
            let ready = match first.take() {
                Some(v) => Ok(v),
                None => app.retrieved_instance(&i, syntax).await,
            };
            let (bytes, ts) = match ready {
                Ok(v) => v,
                Err(e) => {
                    tracing::error!(error = %e, "an instance cannot be sent");
                    let _ = tx
                        .send(Err(std::io::Error::other("instance unreadable")))
                        .await;
                    return;
                }
            };
            let path = app.instance_file(&i);
            let len = match &bytes {
                Some(v) => v.len() as u64,
                None => match tokio::fs::metadata(&path).await {
                    Ok(m) => m.len(),
                    Err(e) => {
                        let _ = tx.send(Err(e)).await;
                        return;
                    }
                },
            };
            let h = &i.instance;
            let head = format!(
                "--{b}\r\nContent-Type: application/dicom; transfer-syntax={ts}\r\nContent-Length: {len}\r\nContent-Location: {base}{}\r\n\r\n",
                resource_path(&h.study_uid, Some(&h.series_uid), Some(&h.sop_instance_uid))
            );
            if tx.send(Ok(Bytes::from(head))).await.is_err() {
                return;
            }
            match bytes {
                Some(v) => {
                    if tx.send(Ok(Bytes::from(v))).await.is_err() {
                        return;
                    }
                }
                None => {
                    let tx = tx.clone();
                    let sent = tokio::task::spawn_blocking(move || send_file(&path, &tx)).await;
                    if !matches!(sent, Ok(true)) {
                        return;
                    }
                }
            }
            if tx.send(Ok(Bytes::from_static(b"\r\n"))).await.is_err() {
                return;
            }
        }
        let _ = tx.send(Ok(Bytes::from(format!("--{b}--\r\n")))).await;
    });
    let stream =
        futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|c| (c, rx)) });
    let mut r = Response::new(Body::from_stream(stream));
    let ct = format!("multipart/related; type=\"application/dicom\"; boundary={boundary}");
    if let Ok(v) = HeaderValue::from_str(&ct) {
        r.headers_mut().insert(header::CONTENT_TYPE, v);
    }
    Ok(r)
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn retrieve_study(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state.wado_instances(&study, None, None).await?;
    retrieve(state, headers, found).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series))]
pub async fn retrieve_series(
    State(state): State<AppState>,
    Path((study, series)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state.wado_instances(&study, Some(&series), None).await?;
    retrieve(state, headers, found).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series, instance = %instance))]
pub async fn retrieve_instance(
    State(state): State<AppState>,
    Path((study, series, instance)): Path<(String, String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state
        .wado_instances(&study, Some(&series), Some(&instance))
        .await?;
    retrieve(state, headers, found).await
}
