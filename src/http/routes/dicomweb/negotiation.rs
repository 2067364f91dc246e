//! Content negotiation of the DICOMweb routes: the media ranges of `Accept` (with their parameters, `q=0`
//! left out), whether a route's offer is accepted (406 otherwise), the base URL RetrieveURLs and
//! Content-Locations point at, and `application/dicom+json` responses.

use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::super::super::problem::{ApiError, api_error};
use crate::dicom::multipart::media_type;
use crate::error_code::ErrorCode;

pub const DICOM_JSON: &str = "application/dicom+json";

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

pub(super) fn param<'a>(p: &'a [(String, String)], name: &str) -> Option<&'a str> {
    p.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

pub(super) fn not_acceptable(offered: &str) -> ApiError {
    api_error(
        ErrorCode::NotAcceptable,
        format!("this resource is offered as {offered}"),
    )
}

/// Whether `Accept` takes one of `types` (exact, `type/*` or `*/*`).
pub(super) fn accepts_any(headers: &HeaderMap, types: &[&str]) -> bool {
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
