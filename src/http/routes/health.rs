//! `/healthz` (the process answers), `/readyz` (database, data directory and object storage usable),
//! `/metrics` (Prometheus text), `/openapi.yaml` (the contract).

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::super::AppState;
use super::super::problem::{ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::telemetry::names;

pub async fn healthz() -> Response {
    axum::Json(json!({ "status": "ok" })).into_response()
}

pub async fn readyz(State(st): State<AppState>) -> ApiResult<Response> {
    let db = st.db.ping().await;
    let store = st.store.clone();
    let disk = tokio::task::spawn_blocking(move || store.probe())
        .await
        .unwrap_or(false);
    // With object storage: a listing of the bucket, answered within a few seconds.
    let objects = match st.store.mirror() {
        None => None,
        Some(m) => Some(match m.check().await {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!(error = %e, store = m.name(), "readiness: object storage unavailable");
                false
            }
        }),
    };
    let word = |ok: bool| if ok { "ok" } else { "unavailable" };
    if db && disk && objects != Some(false) {
        let mut body = json!({ "status": "ready", "database": "ok", "data_dir": "ok" });
        if objects.is_some() {
            body["object_storage"] = json!("ok");
        }
        Ok(axum::Json(body).into_response())
    } else {
        let mut detail = format!("database {}, data directory {}", word(db), word(disk));
        if let Some(ok) = objects {
            detail.push_str(&format!(", object storage {}", word(ok)));
        }
        Err(api_error(ErrorCode::Unavailable, detail))
    }
}

pub async fn metrics(State(st): State<AppState>) -> ApiResult<Response> {
    let store = st.store.clone();
    if let Ok(held) =
        tokio::task::spawn_blocking(move || crate::jobs::retention::storage_bytes(&store)).await
    {
        for (kind, bytes) in held {
            metrics::gauge!(names::STORAGE_BYTES, "kind" => kind).set(bytes as f64);
        }
    }
    for (status, n) in st.db.counts().await? {
        metrics::gauge!(names::JOBS, "status" => status.as_str()).set(n as f64);
        if status == crate::jobs::JobStatus::Queued {
            metrics::gauge!(names::QUEUE_DEPTH).set(n as f64);
        }
    }
    Ok((
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        st.metrics.render(),
    )
        .into_response())
}

/// The OpenAPI 3.1 description of this API.
pub const OPENAPI_YAML: &str = include_str!("../../../openapi.yaml");

pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}
