//! Extractors that answer problems instead of axum's plain-text rejections: JSON bodies (with a
//! canonical fingerprint for Idempotency-Key), query strings, ids and the Idempotency-Key header.

use axum::body::Bytes;
use axum::extract::{FromRequest, FromRequestParts, Query, Request};
use axum::http::{HeaderMap, StatusCode, header, request::Parts};
use serde::de::DeserializeOwned;
use sha2::{Digest, Sha256};

use super::problem::{ApiError, ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::storage::npy::hex;
use crate::storage::{DatasetId, JobId};

/// A JSON body parsed into `T` (unknown fields refused by `T`), with the SHA-256 of its canonical form
/// (object keys sorted, no whitespace): two bodies with the same meaning have the same fingerprint.
pub struct ApiJson<T> {
    pub value: T,
    pub fingerprint: String,
}

/// Canonical JSON text of `v`: keys sorted at every level.
pub fn canonical(v: &serde_json::Value, out: &mut String) {
    match v {
        serde_json::Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            out.push('{');
            for (i, k) in keys.into_iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&serde_json::Value::String(k.clone()).to_string());
                out.push(':');
                canonical(&map[k], out);
            }
            out.push('}');
        }
        serde_json::Value::Array(items) => {
            out.push('[');
            for (i, item) in items.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                canonical(item, out);
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// Fingerprint of a JSON value.
pub fn fingerprint(v: &serde_json::Value) -> String {
    let mut text = String::new();
    canonical(v, &mut text);
    hex(&Sha256::digest(text.as_bytes()))
}

/// Parse a JSON value into `T`, mapping schema errors to `invalid_request`.
pub fn from_value<T: DeserializeOwned>(v: serde_json::Value) -> ApiResult<T> {
    Ok(crate::app::error::parse_body(v)?)
}

/// Parse JSON text: syntax errors are `malformed_json`, schema errors `invalid_request`.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> ApiResult<(T, String)> {
    let v: serde_json::Value = serde_json::from_slice(bytes)
        .map_err(|e| api_error(ErrorCode::MalformedJson, e.to_string()))?;
    let fp = fingerprint(&v);
    Ok((from_value(v)?, fp))
}

/// The media type of the body (lowercase, without parameters); empty when absent.
pub fn media_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .map(|s| s.trim().to_ascii_lowercase())
        .unwrap_or_default()
}

fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .map(|m| {
            let m = m.trim().to_ascii_lowercase();
            m == "application/json" || (m.starts_with("application/") && m.ends_with("+json"))
        })
        .unwrap_or(false)
}

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        if !is_json(req.headers()) {
            return Err(api_error(
                ErrorCode::UnsupportedMediaType,
                "send the body as application/json",
            ));
        }
        let bytes = Bytes::from_request(req, state).await.map_err(|e| {
            if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                api_error(ErrorCode::BodyTooLarge, e.body_text())
            } else {
                api_error(ErrorCode::TruncatedUpload, e.body_text())
            }
        })?;
        let (value, fingerprint) = parse_json(&bytes)?;
        Ok(ApiJson { value, fingerprint })
    }
}

/// A query string parsed into `T`; malformed or unknown parameters are `invalid_query`.
pub struct ApiQuery<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequestParts<S> for ApiQuery<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        Query::<T>::from_request_parts(parts, state)
            .await
            .map(|Query(v)| ApiQuery(v))
            .map_err(|e| api_error(ErrorCode::InvalidQuery, e.body_text()))
    }
}

pub fn job_id(s: &str) -> ApiResult<JobId> {
    JobId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

pub fn dataset_id(s: &str) -> ApiResult<DatasetId> {
    DatasetId::parse(s).map_err(|e| api_error(ErrorCode::InvalidId, e.to_string()))
}

/// The `Idempotency-Key` header: 1–255 visible ASCII characters, if present.
pub fn idempotency_key(headers: &HeaderMap) -> ApiResult<Option<String>> {
    let Some(v) = headers.get("idempotency-key") else {
        return Ok(None);
    };
    let s = v.to_str().unwrap_or("");
    if s.is_empty() || s.len() > 255 || !s.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(api_error(
            ErrorCode::InvalidIdempotencyKey,
            "Idempotency-Key must be 1 to 255 visible ASCII characters",
        ));
    }
    Ok(Some(s.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprints_ignore_key_order_and_whitespace_but_not_values() {
        let a: serde_json::Value =
            serde_json::from_str(r#"{"b": [1, {"y": 2, "x": 1}], "a": "s"}"#).unwrap();
        let b: serde_json::Value =
            serde_json::from_str(r#"{"a":"s","b":[1,{"x":1,"y":2}]}"#).unwrap();
        let c: serde_json::Value =
            serde_json::from_str(r#"{"a":"s","b":[1,{"x":1,"y":3}]}"#).unwrap();
        assert_eq!(fingerprint(&a), fingerprint(&b));
        assert_ne!(fingerprint(&a), fingerprint(&c));
    }
}
