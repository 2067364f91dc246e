//! DICOM UIDs (PS3.5 §9.1): the one check every door applies to the UIDs of an instance it receives, and
//! the refusal it answers, which names a hostile value only as a short, escaped summary.
//!
//! A well-formed UID is 1 to 64 characters of digits and dots, with no empty component and no leading zero
//! in a component of more than one digit; such a UID is safe as a file name. The reader trims the padding
//! of a value (a trailing NUL or space) before the check; a NUL or any other character inside is refused.

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::InMemDicomObject;

use std::borrow::Cow;

use super::error::DicomError;
use super::write::{SeriesMeta, new_uid};

/// The longest UID (PS3.5 §9.1).
pub const MAX_UID_CHARS: usize = 64;

/// Characters of a refused value shown in a message; the rest is counted.
const SHOWN_CHARS: usize = 24;

/// Why `uid` is not a well-formed UID, or `None` when it is.
pub fn uid_defect(uid: &str) -> Option<&'static str> {
    if uid.is_empty() {
        return Some("it is empty");
    }
    if uid.len() > MAX_UID_CHARS {
        return Some("it is longer than 64 characters");
    }
    if !uid.bytes().all(|b| b.is_ascii_digit() || b == b'.') {
        return Some("it holds a character other than digits and dots");
    }
    for c in uid.split('.') {
        if c.is_empty() {
            return Some("it has an empty component");
        }
        if c.len() > 1 && c.starts_with('0') {
            return Some("a component has a leading zero");
        }
    }
    None
}

/// Whether `uid` is a well-formed DICOM UID: 1 to 64 characters of digits and dots, no empty component, no
/// leading zero in a component of more than one digit (PS3.5 §9.1). Such a UID is safe as a file name.
pub fn is_valid_uid(uid: &str) -> bool {
    uid_defect(uid).is_none()
}

/// A value as a message may show it: its first characters, quoted, with control and non-ASCII characters
/// escaped (`\u{0}`), and the count of the characters left out.
pub fn value_summary(value: &str) -> String {
    let shown: String = value
        .chars()
        .take(SHOWN_CHARS)
        .flat_map(char::escape_default)
        .collect();
    let total = value.chars().count();
    if total > SHOWN_CHARS {
        format!("\"{shown}\"… ({total} characters)")
    } else {
        format!("\"{shown}\"")
    }
}

/// `Ok` when `value` is absent or a well-formed UID; otherwise the refusal naming `attribute` in the file
/// labelled `label`.
pub fn check_uid(
    label: &str,
    attribute: &'static str,
    value: Option<&str>,
) -> Result<(), DicomError> {
    let Some(value) = value else { return Ok(()) };
    match uid_defect(value) {
        None => Ok(()),
        Some(reason) => Err(DicomError::InvalidUid {
            label: label.to_string(),
            attribute,
            value_summary: value_summary(value),
            reason,
        }),
    }
}

/// The UID attributes every door checks when present, with their names in messages.
pub(super) const CHECKED_UIDS: &[(Tag, &str)] = &[
    (tags::SOP_CLASS_UID, "SOP Class UID (0008,0016)"),
    (tags::SOP_INSTANCE_UID, "SOP Instance UID (0008,0018)"),
    (tags::STUDY_INSTANCE_UID, "Study Instance UID (0020,000D)"),
    (tags::SERIES_INSTANCE_UID, "Series Instance UID (0020,000E)"),
    (
        tags::FRAME_OF_REFERENCE_UID,
        "Frame of Reference UID (0020,0052)",
    ),
];

/// The value of UID attribute `tag` without its padding (trailing NULs and spaces); `None` when absent or
/// empty. Nothing else is trimmed, so a value that is not a UID stays what it is.
pub(super) fn uid_value(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let e = obj.get(tag)?;
    let s = e.to_str().ok()?;
    let s = s.trim_end_matches(['\0', ' ']);
    (!s.is_empty()).then(|| s.to_string())
}

/// Check every attribute of [`CHECKED_UIDS`] that `obj` holds.
pub(super) fn check_uids(label: &str, obj: &InMemDicomObject) -> Result<(), DicomError> {
    for (tag, attribute) in CHECKED_UIDS {
        check_uid(label, attribute, uid_value(obj, *tag).as_deref())?;
    }
    Ok(())
}

/// Check the SOP Class and SOP Instance UIDs of the file meta group of `framed` (a framed file: `DICM`, then
/// the group opening with its group length), which dicom-rs would refuse as an unreadable group.
pub(super) fn check_meta_uids(label: &str, framed: &[u8]) -> Result<(), DicomError> {
    let Some(len) = framed.get(12..16) else {
        return Ok(());
    };
    let end = 16usize.saturating_add(u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize);
    let group = framed.get(4..end.min(framed.len())).unwrap_or_default();
    for (tag, element) in super::scan::meta_elements(group) {
        let attribute = match tag {
            (0x0002, 0x0002) => "Media Storage SOP Class UID (0002,0002)",
            (0x0002, 0x0003) => "Media Storage SOP Instance UID (0002,0003)",
            _ => continue,
        };
        let value = String::from_utf8_lossy(element.get(8..).unwrap_or_default());
        let value = value.trim_end_matches(['\0', ' ']);
        check_uid(label, attribute, (!value.is_empty()).then_some(value))?;
    }
    Ok(())
}

/// `meta` as a derived series may carry it: a malformed study or frame of reference UID (a series stored before
/// every door checked UIDs) is replaced by a new one and a malformed source series is not referenced, each
/// with a warning; `meta` itself when every UID it holds is well-formed.
pub(super) fn valid_meta(meta: &SeriesMeta) -> Cow<'_, SeriesMeta> {
    let bad = |uid: &Option<String>| uid.as_deref().is_some_and(|u| !is_valid_uid(u));
    if !bad(&meta.study_uid) && !bad(&meta.frame_of_reference_uid) && !bad(&meta.source_series_uid)
    {
        return Cow::Borrowed(meta);
    }
    let mut fixed = meta.clone();
    for (attribute, uid) in [
        ("Study Instance UID", &mut fixed.study_uid),
        ("Frame of Reference UID", &mut fixed.frame_of_reference_uid),
    ] {
        if bad(uid) {
            let summary = uid.as_deref().map(value_summary).unwrap_or_default();
            tracing::warn!(attribute, value = %summary, "a malformed source UID is replaced by a new one in a derived series");
            *uid = Some(new_uid());
        }
    }
    if bad(&fixed.source_series_uid) {
        tracing::warn!(
            "a malformed source Series Instance UID is not referenced by a derived series"
        );
        fixed.source_series_uid = None;
    }
    Cow::Owned(fixed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uids_are_digits_and_dots_without_leading_zeros() {
        assert!(is_valid_uid("1.2.840.10008.5.1.4.1.1.2"));
        assert!(is_valid_uid("1.2.0.3"));
        assert!(is_valid_uid(&"1".repeat(64)));
        for (bad, why) in [
            ("", "it is empty"),
            ("1..2", "it has an empty component"),
            ("1.2.", "it has an empty component"),
            (".1", "it has an empty component"),
            ("1.02", "a component has a leading zero"),
            ("1.2a", "it holds a character other than digits and dots"),
            (
                "1.2.3\0.4",
                "it holds a character other than digits and dots",
            ),
            ("../etc", "it holds a character other than digits and dots"),
            (&"1".repeat(65), "it is longer than 64 characters"),
        ] {
            assert_eq!(uid_defect(bad), Some(why), "{bad:?}");
        }
    }

    #[test]
    fn a_refused_value_is_shown_short_and_escaped() {
        assert_eq!(value_summary("1.2.3\0"), "\"1.2.3\\u{0}\"");
        assert_eq!(value_summary("../../x"), "\"../../x\"");
        let long = value_summary(&"9".repeat(10_001));
        assert_eq!(long, format!("\"{}\"… (10001 characters)", "9".repeat(24)));
        let e = check_uid("f.dcm", "SOP Instance UID (0008,0018)", Some("1.2\n3")).unwrap_err();
        assert_eq!(e.code(), "dicom_invalid_uid");
        assert!(!e.to_string().contains('\n'), "{e}");
        assert!(check_uid("f.dcm", "x", None).is_ok());
    }

    #[test]
    fn a_derived_series_never_carries_a_malformed_source_uid() {
        let good = SeriesMeta {
            study_uid: Some("1.2.3".into()),
            frame_of_reference_uid: Some("1.2.4".into()),
            source_series_uid: Some("1.2.5".into()),
            ..SeriesMeta::default()
        };
        assert!(matches!(valid_meta(&good), Cow::Borrowed(_)));
        let hostile = SeriesMeta {
            study_uid: Some("../../../tmp/pwned".into()),
            frame_of_reference_uid: Some("1.02".into()),
            source_series_uid: Some("1.2.3\0".into()),
            ..good
        };
        let fixed = valid_meta(&hostile);
        let study = fixed.study_uid.as_deref().unwrap_or_default();
        assert!(is_valid_uid(study) && study.starts_with("2.25."), "{study}");
        assert!(
            fixed
                .frame_of_reference_uid
                .as_deref()
                .is_some_and(is_valid_uid)
        );
        assert_eq!(fixed.source_series_uid, None);
        // Written out, the series carries the new study.
        let vol = crate::volume::Volume {
            data: ndarray::Array3::zeros((1, 2, 2)),
            frame: crate::volume::Frame {
                origin_mm: [0.0; 3],
                spacing_mm: [1.0; 3],
                direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            },
        };
        let written = super::super::write_ct_series(&vol, &hostile).unwrap();
        assert!(is_valid_uid(&written.study_uid), "{}", written.study_uid);
        assert!(is_valid_uid(&written.frame_of_reference_uid));

        // A malformed UID in the file meta group is refused as such, not as an unreadable group.
        let good = &written.files[0].1;
        let mut obj = dicom_object::from_reader(&good[128..]).unwrap();
        obj.meta_mut().media_storage_sop_instance_uid = "../../../tmp/pwned".into();
        obj.meta_mut().update_information_group_length();
        let mut bad = Vec::new();
        obj.write_all(&mut bad).unwrap();
        let e = super::super::read_bytes("x.dcm", &bad, &Default::default()).unwrap_err();
        assert!(
            matches!(e, DicomError::InvalidUid { attribute, .. } if attribute.contains("(0002,0003)")),
            "{e:?}"
        );
        let e = super::super::header_of("x.dcm", &bad).unwrap_err();
        assert_eq!(e.code(), "dicom_invalid_uid", "{e:?}");
    }
}
