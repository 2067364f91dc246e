//! Stored series: `GET` and `DELETE /v1/series/{id}`, and `GET /v1/series/{id}/volume.npy` (strong ETag,
//! conditional GETs and byte ranges). Series are made by uploads ([`super::uploads`]).

use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::super::AppState;
use super::super::files::{FileMeta, serve_stored};
use super::super::problem::{ApiResult, api_error};
use crate::app::series::series_json;
use crate::error_code::ErrorCode;
use crate::storage::SeriesId;

fn series_id(s: &str) -> ApiResult<SeriesId> {
    SeriesId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

pub async fn get_series(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let s = st.get_series(series_id(&id)?).await?;
    let mut view = series_json(&s.record);
    view["available"] = json!(s.available);
    Ok(axum::Json(view).into_response())
}

/// `DELETE /v1/series/{id}`: 204, the row and then the volume removed; 409 while a queued or running job
/// reads it.
pub async fn delete_series(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    st.delete_series(series_id(&id)?).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

pub async fn series_volume(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let r = st.series_with_volume(series_id(&id)?).await?;
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
