//! WADO-RS `/metadata` of a study, series or instance: each instance's attributes in the DICOM JSON model,
//! with the resource's Content-Location.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::Response;

use super::super::super::AppState;
use super::super::super::problem::ApiResult;
use super::negotiation::{DICOM_JSON, accepts_any, base_url, dicom_json_response, not_acceptable};
use crate::app::dicomweb::resource_path;

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
    let mut r = dicom_json_response(StatusCode::OK, &out.into());
    let location = format!(
        "{}{}/metadata",
        base_url(headers),
        resource_path(study, series, instance)
    );
    if let Ok(v) = HeaderValue::from_str(&location) {
        r.headers_mut().insert(header::CONTENT_LOCATION, v);
    }
    Ok(r)
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
