//! Query identifiers (the data sets of C-FIND and C-MOVE requests and responses): read a request's keys as
//! `(tag, VR, text)` and write a response from the same, in the presentation context's transfer syntax.
//! Only top-level elements are keys; a sequence key is read with an empty value (sequence matching is not
//! supported) and echoed empty.

use dicom_core::header::Header as _;
use dicom_core::value::{DataSetSequence, Value};
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_object::InMemDicomObject;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};

use super::error::DicomError;

/// The largest identifier read (bytes); real ones are a few hundred.
pub const MAX_IDENTIFIER_BYTES: usize = 256 << 10;

/// One element of an identifier.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IdentifierElement {
    /// `(group << 16) | element`.
    pub tag: u32,
    /// The two-letter VR (`UI`, `DA`, `PN`, …).
    pub vr: String,
    /// Its value as text (multiple values joined by `\`); empty for a universal key or a sequence.
    pub value: String,
}

fn label() -> String {
    "the identifier".to_string()
}

/// Read the elements of an identifier encoded in transfer syntax `ts_uid`.
pub fn read_identifier(bytes: &[u8], ts_uid: &str) -> Result<Vec<IdentifierElement>, DicomError> {
    let parse = |reason: String| DicomError::Parse {
        label: label(),
        reason,
    };
    if bytes.len() > MAX_IDENTIFIER_BYTES {
        return Err(parse(format!("{} bytes", bytes.len())));
    }
    let ts = TransferSyntaxRegistry
        .get(ts_uid.trim_end_matches('\0'))
        .ok_or_else(|| parse(format!("unknown transfer syntax {ts_uid}")))?;
    let obj =
        InMemDicomObject::read_dataset_with_ts(bytes, ts).map_err(|e| parse(e.to_string()))?;
    let mut out = Vec::new();
    for e in obj.iter() {
        let tag = e.tag();
        let vr = e.vr();
        let value = if vr == VR::SQ {
            String::new()
        } else {
            e.to_str()
                .map(|s| s.trim_matches(|c: char| c == ' ' || c == '\0').to_string())
                .unwrap_or_default()
        };
        out.push(IdentifierElement {
            tag: ((tag.group() as u32) << 16) | tag.element() as u32,
            vr: vr.to_string().to_string(),
            value,
        });
    }
    Ok(out)
}

/// Write an identifier in transfer syntax `ts_uid`; string values are padded to even length, values of
/// binary VRs and sequences are written empty.
pub fn write_identifier(
    elements: &[IdentifierElement],
    ts_uid: &str,
) -> Result<Vec<u8>, DicomError> {
    let write = |reason: String| DicomError::Write(reason);
    let ts = TransferSyntaxRegistry
        .get(ts_uid.trim_end_matches('\0'))
        .ok_or_else(|| write(format!("unknown transfer syntax {ts_uid}")))?;
    let mut obj = InMemDicomObject::new_empty();
    for el in elements {
        let tag = Tag((el.tag >> 16) as u16, (el.tag & 0xFFFF) as u16);
        let vr = el.vr.parse::<VR>().unwrap_or(VR::UN);
        let value: Value<InMemDicomObject> = match vr {
            VR::SQ => Value::Sequence(DataSetSequence::empty()),
            VR::AE
            | VR::AS
            | VR::CS
            | VR::DA
            | VR::DS
            | VR::DT
            | VR::IS
            | VR::LO
            | VR::LT
            | VR::PN
            | VR::SH
            | VR::ST
            | VR::TM
            | VR::UC
            | VR::UI
            | VR::UR
            | VR::UT => {
                let mut s = el.value.clone();
                if s.len() % 2 == 1 {
                    s.push(if vr == VR::UI { '\0' } else { ' ' });
                }
                if s.is_empty() {
                    PrimitiveValue::Empty.into()
                } else {
                    PrimitiveValue::from(s).into()
                }
            }
            _ => PrimitiveValue::Empty.into(),
        };
        obj.put(DataElement::new(tag, vr, value));
    }
    let mut out = Vec::with_capacity(512);
    obj.write_dataset_with_ts(&mut out, ts)
        .map_err(|e| write(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn el(tag: u32, vr: &str, value: &str) -> IdentifierElement {
        IdentifierElement {
            tag,
            vr: vr.into(),
            value: value.into(),
        }
    }

    #[test]
    fn an_identifier_reads_back_in_both_little_endian_syntaxes() {
        let elements = vec![
            el(0x0008_0052, "CS", "SERIES"),
            el(0x0010_0010, "PN", "DOE^J*"),
            el(0x0020_000D, "UI", "1.2.3"),
            el(0x0020_000E, "UI", ""),
            el(0x0028_0010, "US", ""),
        ];
        for ts in ["1.2.840.10008.1.2", "1.2.840.10008.1.2.1"] {
            let bytes = write_identifier(&elements, ts).unwrap();
            let back = read_identifier(&bytes, ts).unwrap();
            let values: Vec<(u32, &str)> = back.iter().map(|e| (e.tag, e.value.as_str())).collect();
            assert_eq!(
                values,
                vec![
                    (0x0008_0052, "SERIES"),
                    (0x0010_0010, "DOE^J*"),
                    (0x0020_000D, "1.2.3"),
                    (0x0020_000E, ""),
                    (0x0028_0010, ""),
                ],
                "{ts}"
            );
        }
        // (0010,0010) PN declaring 100 bytes, of which 2 follow.
        let cut = [0x10, 0x00, 0x10, 0x00, b'P', b'N', 100, 0, b'a', b'b'];
        assert!(read_identifier(&cut, "1.2.840.10008.1.2.1").is_err());
        assert!(read_identifier(&[], "1.2.3.4").is_err());
    }
}
