//! Processing rules, deliveries and DICOM peers: `/v1/rules` (create, list, fetch, replace, delete),
//! `/v1/deliveries` (list, fetch, send a job's results by hand, retry) and `/v1/peers` (list, C-ECHO).

use axum::extract::{Path, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::{Value, json};

use super::super::AppState;
use super::super::extract::{ApiJson, ApiQuery, job_id};
use super::super::problem::{ApiResult, api_error};
use crate::app::deliveries::delivery_json;
use crate::app::peers::{peer_json, web_peer_json};
use crate::app::rules::rule_json;
use crate::error_code::ErrorCode;
use crate::jobs::deliveries::{DeliveryFilter, DeliveryState};
use crate::storage::JobId;

/// Runs shown with a rule.
const RULE_RUNS: u32 = 20;

fn with_location(status: StatusCode, location: &str, body: Value) -> Response {
    let mut r = (status, axum::Json(body)).into_response();
    if let Ok(loc) = HeaderValue::from_str(location) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

pub async fn post_rule(State(st): State<AppState>, body: ApiJson<Value>) -> ApiResult<Response> {
    let r = st.create_rule(body.value).await?;
    Ok(with_location(
        StatusCode::CREATED,
        &format!("/v1/rules/{}", r.spec.name),
        rule_json(&r, Some(&[])),
    ))
}

pub async fn list_rules(State(st): State<AppState>) -> ApiResult<Response> {
    let rules = st.list_rules().await?;
    let items: Vec<Value> = rules.iter().map(|r| rule_json(r, None)).collect();
    Ok(axum::Json(json!({ "rules": items })).into_response())
}

pub async fn get_rule(State(st): State<AppState>, Path(name): Path<String>) -> ApiResult<Response> {
    let r = st.get_rule(&name).await?;
    let runs = st.rule_runs(&name, RULE_RUNS).await?;
    Ok(axum::Json(rule_json(&r, Some(&runs))).into_response())
}

pub async fn put_rule(
    State(st): State<AppState>,
    Path(name): Path<String>,
    body: ApiJson<Value>,
) -> ApiResult<Response> {
    let r = st.replace_rule(&name, body.value).await?;
    let runs = st.rule_runs(&name, RULE_RUNS).await?;
    Ok(axum::Json(rule_json(&r, Some(&runs))).into_response())
}

pub async fn delete_rule(
    State(st): State<AppState>,
    Path(name): Path<String>,
) -> ApiResult<Response> {
    st.delete_rule(&name).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// Filters of `GET /v1/deliveries`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeliveryQuery {
    pub state: Option<String>,
    pub job_id: Option<String>,
    pub rule: Option<String>,
    pub limit: Option<u32>,
}

fn delivery_id(s: &str) -> ApiResult<String> {
    JobId::parse(s)
        .map(|id| id.to_string())
        .map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

pub async fn list_deliveries(
    State(st): State<AppState>,
    ApiQuery(q): ApiQuery<DeliveryQuery>,
) -> ApiResult<Response> {
    let state = match q.state.as_deref() {
        None => None,
        Some(s) => Some(DeliveryState::parse(s).ok_or_else(|| {
            api_error(
                ErrorCode::InvalidQuery,
                "`state` is one of queued, sending, succeeded, failed",
            )
        })?),
    };
    let limit = q.limit.unwrap_or(50);
    if !(1..=500).contains(&limit) {
        return Err(api_error(ErrorCode::InvalidQuery, "`limit` is 1–500"));
    }
    let f = DeliveryFilter {
        state,
        job_id: q.job_id.as_deref().map(job_id).transpose()?,
        rule_name: q.rule,
        limit,
    };
    let items: Vec<Value> = st
        .list_deliveries(&f)
        .await?
        .iter()
        .map(|d| delivery_json(d, false))
        .collect();
    Ok(axum::Json(json!({ "deliveries": items })).into_response())
}

pub async fn get_delivery(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let d = st.get_delivery(&delivery_id(&id)?).await?;
    Ok(axum::Json(delivery_json(&d, true)).into_response())
}

/// `POST /v1/deliveries`: send a succeeded job's DICOM results to a peer.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewDelivery {
    pub job_id: JobId,
    pub destination: String,
}

pub async fn post_delivery(
    State(st): State<AppState>,
    body: ApiJson<Value>,
) -> ApiResult<Response> {
    let req: NewDelivery = serde_json::from_value(body.value)
        .map_err(|e| api_error(ErrorCode::InvalidRequest, e.to_string()))?;
    let d = st.create_delivery(req.job_id, &req.destination).await?;
    Ok(with_location(
        StatusCode::ACCEPTED,
        &format!("/v1/deliveries/{}", d.id),
        delivery_json(&d, true),
    ))
}

pub async fn retry_delivery(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let d = st.retry_delivery(&delivery_id(&id)?).await?;
    Ok(with_location(
        StatusCode::ACCEPTED,
        &format!("/v1/deliveries/{}", d.id),
        delivery_json(&d, true),
    ))
}

pub async fn list_peers(State(st): State<AppState>) -> ApiResult<Response> {
    let d = &st.settings.dicom;
    let peers: Vec<Value> = d.peers.iter().map(peer_json).collect();
    let web_peers: Vec<Value> = d.web_peers.iter().map(web_peer_json).collect();
    Ok(
        axum::Json(json!({ "ae_title": d.ae_title, "peers": peers, "web_peers": web_peers }))
            .into_response(),
    )
}

pub async fn echo_peer(
    State(st): State<AppState>,
    Path(ae_title): Path<String>,
) -> ApiResult<Response> {
    let (status, rtt) = st.echo_peer(&ae_title).await?;
    Ok(axum::Json(json!({
        "ae_title": ae_title,
        "status": status,
        "success": status == 0,
        "round_trip_ms": rtt.as_secs_f64() * 1000.0,
    }))
    .into_response())
}
