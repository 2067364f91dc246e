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

/// Parse JSON text: syntax errors are `malformed_json`, schema errors `invalid_request`. A number with no
/// fraction is an integer whatever its spelling (`4.0`, `4e0`), as JSON Schema's `integer` says: counts
/// typed as integers accept it, and the fingerprint does not tell the spellings apart.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> ApiResult<(T, String)> {
    let mut v: serde_json::Value = serde_json::from_slice(bytes)
        .map_err(|e| api_error(ErrorCode::MalformedJson, e.to_string()))?;
    integral_numbers(&mut v);
    let fp = fingerprint(&v);
    Ok((from_value(v)?, fp))
}

/// Write every number whose value is a whole number within the 64-bit integer range as an integer.
pub fn integral_numbers(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Number(n) if n.is_f64() => {
            if let Some(f) = n.as_f64()
                && f.fract() == 0.0
            {
                // Exact bounds: 2^63 and 2^64 are representable, so `<` keeps every cast in range.
                if (0.0..18_446_744_073_709_551_616.0).contains(&f) {
                    *v = serde_json::Value::from(f as u64);
                } else if (-9_223_372_036_854_775_808.0..0.0).contains(&f) {
                    *v = serde_json::Value::from(f as i64);
                }
            }
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(integral_numbers),
        serde_json::Value::Object(map) => map.values_mut().for_each(integral_numbers),
        _ => {}
    }
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

    #[test]
    fn whole_numbers_spelt_as_floats_read_as_integers() {
        let (v, fp): (serde_json::Value, String) = parse_json(
            br#"{"nv": 4.0, "big": 1e3, "neg": -2.0, "half": 0.5, "deep": [{"n": 6E0}]}"#,
        )
        .expect("json");
        assert_eq!(v["nv"].as_u64(), Some(4));
        assert_eq!(v["big"].as_u64(), Some(1000));
        assert_eq!(v["neg"].as_i64(), Some(-2));
        assert_eq!(v["half"].as_f64(), Some(0.5));
        assert!(v["half"].is_f64());
        assert_eq!(v["deep"][0]["n"].as_u64(), Some(6));
        let (_, same): (serde_json::Value, String) =
            parse_json(br#"{"deep": [{"n": 6}], "half": 0.5, "neg": -2, "big": 1000, "nv": 4}"#)
                .expect("json");
        assert_eq!(fp, same);
        // Out of the integer range or not finite as f64: left as they are.
        let (v, _): (serde_json::Value, String) = parse_json(br#"{"x": 1e300}"#).expect("json");
        assert!(v["x"].is_f64());
        #[derive(serde::Deserialize)]
        struct Counts {
            nv: usize,
        }
        let (c, _): (Counts, String) = parse_json(br#"{"nv": 4.0}"#).expect("an integral float");
        assert_eq!(c.nv, 4);
    }
}
