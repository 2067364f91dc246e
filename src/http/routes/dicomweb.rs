//! DICOMweb (PS3.18) under `/dicom-web`: QIDO-RS (`GET …/studies`, `…/series`, `…/instances`) answered in
//! `application/dicom+json`; WADO-RS retrieval of a study, series or instance as `multipart/related;
//! type="application/dicom"` streamed from the stored files (one part per instance, each with its
//! Content-Type, Content-Length and Content-Location), `/metadata` in `application/dicom+json`, and
//! `/rendered` frames as PNG. STOW-RS is in [`super::stow`].
//!
//! `Accept` is honoured: a request that accepts none of what a route offers gets 406. On retrieval,
//! `transfer-syntax=*` sends each instance in its stored syntax, `transfer-syntax=1.2.840.10008.1.2.1`
//! (explicit VR little endian) re-encodes those stored in implicit VR little endian and refuses (406)
//! compressed ones; without the parameter, implicit VR little endian is re-encoded and the others go as
//! stored. RetrieveURLs and Content-Locations are absolute, on the host the request named.

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tokio::io::AsyncReadExt;

use super::super::AppState;
use super::super::extract::ApiQuery;
use super::super::problem::{ApiResult, api_error};
use crate::app::App;
use crate::app::dicomweb::{QidoPath, found_json, parse_qido, resource_path};
use crate::app::matching::Level;
use crate::app::wado::RenderWindow;
use crate::dicom::multipart::media_type;
use crate::dicom::{EXPLICIT_LE, transcodable_to_explicit_le};
use crate::error_code::ErrorCode;
use crate::jobs::repo::StoredInstance;

pub const DICOM_JSON: &str = "application/dicom+json";

type Params = ApiQuery<Vec<(String, String)>>;

/// The media ranges of `Accept` (essence and parameters), those with `q=0` left out; `*/*` when absent.
pub fn accepted(headers: &HeaderMap) -> Vec<(String, Vec<(String, String)>)> {
    let all: Vec<_> = headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(split_ranges)
        .filter_map(|r| media_type(&r))
        .filter(|(_, p)| {
            !p.iter()
                .any(|(k, v)| k == "q" && v.parse::<f64>().is_ok_and(|q| q <= 0.0))
        })
        .collect();
    if all.is_empty() {
        vec![("*/*".into(), vec![])]
    } else {
        all
    }
}

/// Split an Accept value at the commas outside quotes.
fn split_ranges(v: &str) -> Vec<String> {
    let (mut out, mut cur, mut quoted) = (Vec::new(), String::new(), false);
    for c in v.chars() {
        match c {
            '"' => {
                quoted = !quoted;
                cur.push(c);
            }
            ',' if !quoted => out.push(std::mem::take(&mut cur)),
            c => cur.push(c),
        }
    }
    out.push(cur);
    out.into_iter().filter(|s| !s.trim().is_empty()).collect()
}

fn param<'a>(p: &'a [(String, String)], name: &str) -> Option<&'a str> {
    p.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

fn not_acceptable(offered: &str) -> super::super::problem::ApiError {
    api_error(
        ErrorCode::NotAcceptable,
        format!("this resource is offered as {offered}"),
    )
}

/// Whether `Accept` takes one of `types` (exact, `type/*` or `*/*`).
fn accepts_any(headers: &HeaderMap, types: &[&str]) -> bool {
    accepted(headers).iter().any(|(t, _)| {
        t == "*/*"
            || types.iter().any(|o| {
                t == o
                    || t.strip_suffix("/*")
                        .is_some_and(|m| o.starts_with(&format!("{m}/")))
            })
    })
}

/// `http://host` of the request (RetrieveURLs point back at ctrecon as the client reached it).
pub fn base_url(headers: &HeaderMap) -> String {
    let host = headers
        .get(header::HOST)
        .and_then(|v| v.to_str().ok())
        .filter(|h| {
            !h.is_empty()
                && h.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b".-:[]".contains(&b))
        })
        .unwrap_or("localhost");
    let proto = match headers
        .get("x-forwarded-proto")
        .and_then(|v| v.to_str().ok())
    {
        Some("https") => "https",
        _ => "http",
    };
    format!("{proto}://{host}")
}

pub fn dicom_json_response(status: StatusCode, body: &serde_json::Value) -> Response {
    let mut r = (status, serde_json::to_vec(body).unwrap_or_default()).into_response();
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(DICOM_JSON));
    r
}

async fn qido(
    state: &AppState,
    headers: &HeaderMap,
    level: Level,
    path: QidoPath,
    params: Vec<(String, String)>,
) -> ApiResult<Response> {
    if !accepts_any(headers, &[DICOM_JSON, "application/json"]) {
        return Err(not_acceptable(DICOM_JSON));
    }
    let q = parse_qido(level, path, &params)?;
    let found = state.qido(&q).await?;
    let base = base_url(headers);
    let body: Vec<serde_json::Value> = found.iter().map(|f| found_json(&q, f, &base)).collect();
    Ok(dicom_json_response(StatusCode::OK, &body.into()))
}

#[tracing::instrument(skip_all)]
pub async fn search_studies(
    State(state): State<AppState>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    qido(&state, &headers, Level::Study, QidoPath::default(), p).await
}

#[tracing::instrument(skip_all)]
pub async fn search_all_series(
    State(state): State<AppState>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    qido(&state, &headers, Level::Series, QidoPath::default(), p).await
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn search_series(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    let path = QidoPath {
        study: Some(study),
        series: None,
    };
    qido(&state, &headers, Level::Series, path, p).await
}

#[tracing::instrument(skip_all)]
pub async fn search_all_instances(
    State(state): State<AppState>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    qido(&state, &headers, Level::Image, QidoPath::default(), p).await
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn search_study_instances(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    let path = QidoPath {
        study: Some(study),
        series: None,
    };
    qido(&state, &headers, Level::Image, path, p).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series))]
pub async fn search_instances(
    State(state): State<AppState>,
    Path((study, series)): Path<(String, String)>,
    headers: HeaderMap,
    ApiQuery(p): Params,
) -> ApiResult<Response> {
    let path = QidoPath {
        study: Some(study),
        series: Some(series),
    };
    qido(&state, &headers, Level::Image, path, p).await
}

/// How each instance of a retrieval is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Syntax {
    /// As stored, except implicit VR little endian, re-encoded (no parameter).
    Default,
    /// As stored (`transfer-syntax=*`).
    Stored,
    /// Explicit VR little endian, or refused.
    ExplicitLe,
}

/// The syntax a retrieval's `Accept` asks for, or 406.
fn retrieve_syntax(headers: &HeaderMap) -> ApiResult<Syntax> {
    for (t, p) in accepted(headers) {
        let dicom = match t.as_str() {
            "*/*" | "multipart/*" => true,
            "multipart/related" => param(&p, "type").is_none_or(|ty| ty == "application/dicom"),
            _ => false,
        };
        if !dicom {
            continue;
        }
        return match param(&p, "transfer-syntax") {
            None => Ok(Syntax::Default),
            Some("*") => Ok(Syntax::Stored),
            Some(EXPLICIT_LE) => Ok(Syntax::ExplicitLe),
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

/// The bytes and the transfer syntax one instance is sent with (`None`: its file, streamed).
async fn instance_body(
    app: &App,
    i: &StoredInstance,
    syntax: Syntax,
) -> ApiResult<(Option<Vec<u8>>, String)> {
    let ts = i.instance.transfer_syntax.as_str();
    let transcode = match syntax {
        Syntax::Stored => false,
        Syntax::Default => transcodable_to_explicit_le(ts) && ts != EXPLICIT_LE,
        Syntax::ExplicitLe => ts != EXPLICIT_LE,
    };
    if transcode {
        Ok((Some(app.instance_explicit_le(i).await?), EXPLICIT_LE.into()))
    } else {
        Ok((None, ts.to_string()))
    }
}

/// Stream `instances` as one `multipart/related` body: the parts are produced one at a time by a task,
/// files read in 256 KiB chunks through a channel of four, so memory stays flat in the retrieval's size.
async fn retrieve(
    state: AppState,
    headers: HeaderMap,
    instances: Vec<StoredInstance>,
) -> ApiResult<Response> {
    let syntax = retrieve_syntax(&headers)?;
    if syntax == Syntax::ExplicitLe
        && let Some(i) = instances
            .iter()
            .find(|i| !transcodable_to_explicit_le(&i.instance.transfer_syntax))
    {
        return Err(api_error(
            ErrorCode::NotAcceptable,
            format!(
                "instance {} is stored in {}, which is not re-encoded: ask for transfer-syntax=*",
                i.instance.sop_instance_uid, i.instance.transfer_syntax
            ),
        ));
    }
    let boundary = uuid::Uuid::new_v4().simple().to_string();
    let base = base_url(&headers);
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    let app = state.app.clone();
    let b = boundary.clone();
    tokio::spawn(async move {
        for i in instances {
            let (bytes, ts) = match instance_body(&app, &i, syntax).await {
                Ok(v) => v,
                Err(e) => {
                    tracing::error!(error = ?e.0, "an instance cannot be sent");
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
                    let mut f = match tokio::fs::File::open(&path).await {
                        Ok(f) => f,
                        Err(e) => {
                            let _ = tx.send(Err(e)).await;
                            return;
                        }
                    };
                    loop {
                        let mut buf = vec![0u8; 256 << 10];
                        match f.read(&mut buf).await {
                            Ok(0) => break,
                            Ok(n) => {
                                buf.truncate(n);
                                if tx.send(Ok(Bytes::from(buf))).await.is_err() {
                                    return;
                                }
                            }
                            Err(e) => {
                                let _ = tx.send(Err(e)).await;
                                return;
                            }
                        }
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

async fn metadata(
    state: &AppState,
    headers: &HeaderMap,
    study: &str,
    series: Option<&str>,
    instance: Option<&str>,
) -> ApiResult<Response> {
    if !accepts_any(headers, &[DICOM_JSON, "application/json"]) {
        return Err(not_acceptable(DICOM_JSON));
    }
    let found = state.wado_instances(study, series, instance).await?;
    let mut out = Vec::with_capacity(found.len());
    for i in &found {
        out.push(state.instance_metadata(i).await?);
    }
    Ok(dicom_json_response(StatusCode::OK, &out.into()))
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn study_metadata(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    metadata(&state, &headers, &study, None, None).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series))]
pub async fn series_metadata(
    State(state): State<AppState>,
    Path((study, series)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    metadata(&state, &headers, &study, Some(&series), None).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series, instance = %instance))]
pub async fn instance_metadata(
    State(state): State<AppState>,
    Path((study, series, instance)): Path<(String, String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    metadata(&state, &headers, &study, Some(&series), Some(&instance)).await
}

/// Query of `/rendered`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderedQuery {
    /// `center,width[,linear]`.
    pub window: Option<String>,
}

async fn rendered(
    state: &AppState,
    headers: &HeaderMap,
    ids: (String, String, String),
    frame: usize,
    q: RenderedQuery,
) -> ApiResult<Response> {
    if !accepts_any(headers, &["image/png"]) {
        return Err(not_acceptable("image/png"));
    }
    let window = q.window.as_deref().map(RenderWindow::parse).transpose()?;
    let found = state
        .wado_instances(&ids.0, Some(&ids.1), Some(&ids.2))
        .await?;
    let png = state.render_instance(&found[0], frame, window).await?;
    let mut r = (StatusCode::OK, png).into_response();
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    Ok(r)
}

#[tracing::instrument(skip_all, fields(instance = %ids.2))]
pub async fn instance_rendered(
    State(state): State<AppState>,
    Path(ids): Path<(String, String, String)>,
    headers: HeaderMap,
    ApiQuery(q): ApiQuery<RenderedQuery>,
) -> ApiResult<Response> {
    rendered(&state, &headers, ids, 1, q).await
}

#[tracing::instrument(skip_all, fields(instance = %ids.2, frame = %ids.3))]
pub async fn frame_rendered(
    State(state): State<AppState>,
    Path(ids): Path<(String, String, String, String)>,
    headers: HeaderMap,
    ApiQuery(q): ApiQuery<RenderedQuery>,
) -> ApiResult<Response> {
    let frame: usize = ids
        .3
        .parse()
        .ok()
        .filter(|f| *f >= 1)
        .ok_or_else(|| api_error(ErrorCode::InvalidId, "a frame number is 1 or more"))?;
    rendered(&state, &headers, (ids.0, ids.1, ids.2), frame, q).await
}
