//! QIDO-RS: `GET /dicom-web/studies`, `…/series`, `…/instances` (at every level of the path), answered in
//! `application/dicom+json` from the instance index.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;

use super::super::super::AppState;
use super::super::super::extract::ApiQuery;
use super::super::super::problem::ApiResult;
use super::negotiation::{DICOM_JSON, accepts_any, base_url, dicom_json_response, not_acceptable};
use crate::app::dicomweb::{QidoPath, found_json, parse_qido};
use crate::app::matching::Level;

type Params = ApiQuery<Vec<(String, String)>>;

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
