//! Helpers of the DICOMweb tests: a ctrecon with a token, synthetic series, STOW-RS bodies and answers,
//! multipart answers and DICOM JSON values.
#![allow(dead_code)]

use std::collections::BTreeSet;

use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::volume::{Frame, Volume};
use serde_json::Value;

use super::common::{TestApp, spawn_app_with};

pub const TOKEN: &str = "dicomweb-test-token-0123456789";
pub const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
pub const BOUNDARY: &str = "ctrecon-test-boundary-7f3a";

/// A ctrecon with a bearer token, its DICOM node on, series stable after a second and room for uploads.
pub async fn ctrecon() -> (TestApp, reqwest::Client) {
    let app = spawn_app_with(|s| {
        s.api_tokens = vec![TOKEN.to_string()];
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = 1;
        s.max_upload_bytes = 64 << 20;
    })
    .await;
    let mut h = reqwest::header::HeaderMap::new();
    h.insert(
        reqwest::header::AUTHORIZATION,
        format!("Bearer {TOKEN}").parse().unwrap(),
    );
    let client = reqwest::Client::builder()
        .default_headers(h)
        .build()
        .unwrap();
    (app, client)
}

/// A synthetic CT series of `nz` slices of 48 × 40 (1 × 1 × 2 mm): soft tissue with a 400 HU block, in
/// `study` (a new one when `None`); the Part 10 files in instance order.
pub fn synthetic(nz: usize, study: Option<&str>, patient: &str) -> (String, String, Vec<Vec<u8>>) {
    let data = ndarray::Array3::from_shape_fn((nz, 40, 48), |(k, j, i)| {
        let bone = (8..32).contains(&i) && (10..30).contains(&j) && (2..nz - 2).contains(&k);
        if bone {
            400.0
        } else {
            40.0 + (i + 2 * j + 3 * k) as f32
        }
    });
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-24.0, -20.0, 10.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let study = study.map_or_else(ctrecon::dicom::new_uid, str::to_string);
    let meta = SeriesMeta {
        study_uid: Some(study.clone()),
        frame_of_reference_uid: Some(ctrecon::dicom::new_uid()),
        patient_id: Some(patient.into()),
        patient_name: Some("WEB^DICOM".into()),
        series_description: "L-SPINE bone".into(),
        series_number: 2,
        ..Default::default()
    };
    let s = write_ct_series(&vol, &meta).unwrap();
    (
        study,
        s.series_uid,
        s.files.into_iter().map(|(_, b)| b).collect(),
    )
}

/// A STOW-RS body of `parts` (content type, bytes).
pub fn multipart(parts: &[(&str, &[u8])]) -> Vec<u8> {
    let mut b = Vec::new();
    for (ct, data) in parts {
        b.extend_from_slice(format!("--{BOUNDARY}\r\nContent-Type: {ct}\r\n\r\n").as_bytes());
        b.extend_from_slice(data);
        b.extend_from_slice(b"\r\n");
    }
    b.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    b
}

pub const STOW_TYPE: &str =
    "multipart/related; type=\"application/dicom\"; boundary=ctrecon-test-boundary-7f3a";

pub async fn stow(client: &reqwest::Client, url: String, body: Vec<u8>) -> (u16, Value) {
    let r = client
        .post(url)
        .header("content-type", STOW_TYPE)
        .header("accept", "application/dicom+json")
        .body(body)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// The values of `tag` in the items of sequence `seq` of a STOW-RS answer.
pub fn seq_values(v: &Value, seq: &str, tag: &str) -> BTreeSet<String> {
    v[seq]["Value"]
        .as_array()
        .map(|items| {
            items
                .iter()
                .map(|i| match &i[tag]["Value"][0] {
                    Value::String(s) => s.clone(),
                    other => other.to_string(),
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The parts of a multipart body: (headers, lower-case names; bytes).
pub type Part = (Vec<(String, String)>, Vec<u8>);

pub fn parts(content_type: &str, body: &[u8]) -> Vec<Part> {
    let b = content_type
        .split(';')
        .find_map(|p| p.trim().strip_prefix("boundary="))
        .expect("a boundary")
        .trim_matches('"')
        .to_string();
    let delim = format!("--{b}");
    let mut out = Vec::new();
    let mut rest = body;
    let find = |h: &[u8], n: &[u8]| h.windows(n.len()).position(|w| w == n);
    let start = find(rest, delim.as_bytes()).expect("first delimiter");
    rest = &rest[start + delim.len()..];
    while !rest.starts_with(b"--") {
        rest = &rest[2..]; // CRLF
        let end = find(rest, b"\r\n\r\n").expect("end of headers");
        let headers: Vec<(String, String)> = String::from_utf8_lossy(&rest[..end])
            .split("\r\n")
            .filter_map(|l| l.split_once(':'))
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        rest = &rest[end + 4..];
        let next = find(rest, format!("\r\n{delim}").as_bytes()).expect("next delimiter");
        out.push((headers, rest[..next].to_vec()));
        rest = &rest[next + 2 + delim.len()..];
    }
    out
}

pub fn header<'a>(h: &'a [(String, String)], name: &str) -> Option<&'a str> {
    h.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

/// The string or number value of `tag` in a DICOM JSON data set (or in the form Orthanc's DICOMweb client
/// gives answers in: one value, not an array).
pub fn value(d: &Value, tag: &str) -> Option<String> {
    if let Value::String(s) = &d[tag]["Value"] {
        return Some(s.clone());
    }
    match &d[tag]["Value"][0] {
        Value::String(s) => Some(s.clone()),
        Value::Number(n) => Some(n.to_string()),
        Value::Object(o) => o
            .get("Alphabetic")
            .and_then(|a| a.as_str())
            .map(str::to_string),
        _ => None,
    }
}
