//! WADO-RS `/rendered` of an instance or one of its frames: a PNG, or a JPEG when `Accept` prefers it, through
//! the window asked for, fitted to the viewport asked for.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::super::super::AppState;
use super::super::super::extract::ApiQuery;
use super::super::super::problem::{ApiResult, api_error};
use super::negotiation::{accepted, base_url, not_acceptable, param};
use crate::app::dicomweb::resource_path;
use crate::app::wado::{
    DEFAULT_JPEG_QUALITY, RenderWindow, RenderedMedia, Rendering, Viewport, parse_quality,
};
use crate::error_code::ErrorCode;

/// Query of `/rendered`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderedQuery {
    /// `center,width[,linear]`.
    pub window: Option<String>,
    /// 1–100, for JPEG (ignored for PNG, which is lossless).
    pub quality: Option<String>,
    /// `vw,vh`.
    pub viewport: Option<String>,
}

/// The media type `Accept` prefers among PNG and JPEG (by `q`, then by order; `image/*` and `*/*` take
/// PNG), or 406.
fn media(headers: &HeaderMap, quality: u8) -> ApiResult<RenderedMedia> {
    let mut ranges: Vec<(f64, String)> = accepted(headers)
        .into_iter()
        .map(|(t, p)| {
            let q = param(&p, "q")
                .and_then(|q| q.parse::<f64>().ok())
                .unwrap_or(1.0);
            (q, t)
        })
        .collect();
    ranges.sort_by(|a, b| b.0.total_cmp(&a.0));
    for (_, t) in ranges {
        match t.as_str() {
            "image/jpeg" => return Ok(RenderedMedia::Jpeg { quality }),
            "image/png" | "image/*" | "*/*" => return Ok(RenderedMedia::Png),
            _ => {}
        }
    }
    Err(not_acceptable("image/png or image/jpeg"))
}

async fn rendered(
    state: &AppState,
    headers: &HeaderMap,
    ids: (String, String, String),
    frame: Option<usize>,
    q: RenderedQuery,
) -> ApiResult<Response> {
    let quality = q
        .quality
        .as_deref()
        .map(parse_quality)
        .transpose()?
        .unwrap_or(DEFAULT_JPEG_QUALITY);
    let how = Rendering {
        media: media(headers, quality)?,
        window: q.window.as_deref().map(RenderWindow::parse).transpose()?,
        viewport: q.viewport.as_deref().map(Viewport::parse).transpose()?,
    };
    let found = state
        .wado_instances(&ids.0, Some(&ids.1), Some(&ids.2))
        .await?;
    let picture = state
        .render_instance(&found[0], frame.unwrap_or(1), how)
        .await?;
    let mut r = (StatusCode::OK, picture).into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(how.media.content_type()),
    );
    let mut location = format!(
        "{}{}",
        base_url(headers),
        resource_path(&ids.0, Some(&ids.1), Some(&ids.2))
    );
    if let Some(f) = frame {
        location.push_str(&format!("/frames/{f}"));
    }
    location.push_str("/rendered");
    if let Ok(v) = HeaderValue::from_str(&location) {
        r.headers_mut().insert(header::CONTENT_LOCATION, v);
    }
    Ok(r)
}

#[tracing::instrument(skip_all, fields(instance = %ids.2))]
pub async fn instance_rendered(
    State(state): State<AppState>,
    Path(ids): Path<(String, String, String)>,
    headers: HeaderMap,
    ApiQuery(q): ApiQuery<RenderedQuery>,
) -> ApiResult<Response> {
    rendered(&state, &headers, ids, None, q).await
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
    rendered(&state, &headers, (ids.0, ids.1, ids.2), Some(frame), q).await
}
