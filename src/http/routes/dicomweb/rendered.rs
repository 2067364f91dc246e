//! WADO-RS `/rendered` of an instance or one of its frames: a PNG through the window asked for.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::super::super::AppState;
use super::super::super::extract::ApiQuery;
use super::super::super::problem::{ApiResult, api_error};
use super::negotiation::{accepts_any, not_acceptable};
use crate::app::wado::RenderWindow;
use crate::error_code::ErrorCode;

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
