//! What DICOMweb needs from a stored instance: its attributes in the DICOM JSON model (PS3.18 §F.2); its
//! bytes in explicit VR little endian are [`super::decompress`]'s.
//!
//! The JSON model: every attribute of the data set but the pixel data (retrieved with the instance), keyed by
//! its tag as eight upper-case hex digits, with its VR and its values: strings for text VRs, numbers for IS,
//! DS and the binary numeric VRs, `{"Alphabetic": …}` objects for PN, nested data sets for SQ, and
//! `InlineBinary` (base64) for OB, OW, UN and the other byte VRs up to [`MAX_INLINE_BINARY`] bytes (longer
//! ones are left out). Text is decoded by dicom-rs (Specific Character Set honoured), so the JSON is UTF-8.

use std::path::Path;

use dicom_core::VR;
use dicom_core::header::Header as _;
use dicom_dictionary_std::tags;
use dicom_object::InMemDicomObject;
use serde_json::{Map, Value, json};

use super::error::DicomError;
use super::read::{Opened, header_inflate_limit, open};

/// Explicit VR little endian.
pub const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
/// Implicit VR little endian.
pub const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
/// Longest binary value written inline in the JSON model (bytes).
pub const MAX_INLINE_BINARY: usize = 64 << 10;

/// The DICOM JSON model of the instance at `path` (files over `max_bytes` are refused unread).
pub fn instance_json(path: &Path, max_bytes: u64) -> Result<Value, DicomError> {
    let (label, bytes) = super::header::read_bounded(path, max_bytes)?;
    let Opened { obj, .. } = open(
        &label,
        &bytes,
        header_inflate_limit(bytes.len()),
        Some(tags::PIXEL_DATA),
    )?;
    Ok(Value::Object(data_set_json(&obj)))
}

fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                out.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn number(v: f64) -> Value {
    serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number)
}

/// One data set as a JSON object (tags in ascending order, as dicom-rs keeps them).
fn data_set_json(obj: &InMemDicomObject) -> Map<String, Value> {
    let mut out = Map::new();
    for e in obj.iter() {
        let tag = e.tag();
        // Group lengths and the pixel data are not part of the model.
        if tag.element() == 0 || tag == tags::PIXEL_DATA {
            continue;
        }
        let vr = e.vr();
        let key = format!("{:04X}{:04X}", tag.group(), tag.element());
        let mut attr = Map::new();
        attr.insert("vr".into(), json!(vr.to_string()));
        let strings = || -> Vec<String> {
            e.to_multi_str()
                .map(|v| {
                    v.iter()
                        .map(|s| s.trim_matches(|c: char| c == ' ' || c == '\0').to_string())
                        .collect()
                })
                .unwrap_or_default()
        };
        let value: Option<Value> = match vr {
            VR::SQ => e.items().map(|items| {
                Value::Array(
                    items
                        .iter()
                        .map(|i| Value::Object(data_set_json(i)))
                        .collect(),
                )
            }),
            VR::PN => Some(Value::Array(
                strings()
                    .into_iter()
                    .map(|s| {
                        if s.is_empty() {
                            Value::Null
                        } else {
                            json!({ "Alphabetic": s })
                        }
                    })
                    .collect(),
            )),
            VR::IS | VR::SS | VR::US | VR::SL | VR::UL | VR::SV | VR::UV => {
                e.to_multi_int::<i64>().ok().map(|v| json!(v))
            }
            VR::DS | VR::FL | VR::FD => e
                .to_multi_float64()
                .ok()
                .map(|v| Value::Array(v.into_iter().map(number).collect())),
            VR::AT => e.to_multi_str().ok().map(|v| json!(v.to_vec())),
            VR::OB | VR::OD | VR::OF | VR::OL | VR::OV | VR::OW | VR::UN => match e.to_bytes() {
                Ok(b) if b.len() <= MAX_INLINE_BINARY => {
                    attr.insert("InlineBinary".into(), json!(base64(&b)));
                    None
                }
                _ => continue,
            },
            _ => Some(Value::Array(
                strings()
                    .into_iter()
                    .map(|s| if s.is_empty() { Value::Null } else { json!(s) })
                    .collect(),
            )),
        };
        if let Some(v) = value.filter(|v| v.as_array().is_none_or(|a| !a.is_empty())) {
            attr.insert("Value".into(), v);
        }
        out.insert(key, Value::Object(attr));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_follows_rfc_4648() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
    }
}
