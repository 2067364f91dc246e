//! The attributes of one instance that a DICOM node files it by (study, series, patient, SOP class), read
//! without decoding pixels: what the network receiver checks before it keeps a file, and what queries match.
//!
//! The file goes through the same framing and pre-parse walk as every upload, so a declared length that
//! overruns the file or a runaway nesting is refused here too; any SOP class is read (Secondary Capture and
//! Encapsulated STL have no CT image).

use std::path::Path;

use dicom_dictionary_std::tags;
use serde::Serialize;

use super::error::DicomError;
use super::read::{Opened, float, header_inflate_limit, int, open, text};
use super::uid::{check_uids, uid_value};

/// SOP classes a DICOM node of ctrecon stores: CT Image, Enhanced CT Image, Secondary Capture Image and
/// Encapsulated STL.
pub const STORABLE_SOP_CLASSES: &[&str] = &[
    "1.2.840.10008.5.1.4.1.1.2",
    "1.2.840.10008.5.1.4.1.1.2.1",
    "1.2.840.10008.5.1.4.1.1.7",
    "1.2.840.10008.5.1.4.1.1.104.3",
];

/// Transfer syntaxes whose data sets and pixel data the reader decodes: what the codec registry of this
/// build decodes (native and deflated encodings, JPEG baseline/extended/lossless, RLE, JPEG 2000) and
/// JPEG-LS lossless and near-lossless, which the reader decodes itself (grey images).
pub fn decodable_transfer_syntaxes() -> Vec<&'static str> {
    use dicom_transfer_syntax_registry::TransferSyntaxRegistry;
    let mut uids: Vec<&'static str> = TransferSyntaxRegistry
        .iter()
        .filter(|ts| ts.can_decode_all())
        .map(|ts| ts.uid())
        .chain([super::jpeg_ls::LOSSLESS, super::jpeg_ls::NEAR_LOSSLESS])
        .collect();
    uids.sort_unstable();
    uids.dedup();
    uids
}

/// Identity and filing attributes of one instance.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InstanceHeader {
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub study_uid: String,
    pub series_uid: String,
    pub transfer_syntax: String,
    pub modality: Option<String>,
    pub patient_id: Option<String>,
    pub patient_name: Option<String>,
    pub study_date: Option<String>,
    pub study_description: Option<String>,
    pub accession_number: Option<String>,
    pub series_description: Option<String>,
    pub series_number: Option<i64>,
    pub instance_number: Option<i64>,
    pub body_part: Option<String>,
    /// Image Type values, e.g. `["ORIGINAL", "PRIMARY", "AXIAL"]`.
    pub image_type: Vec<String>,
    pub slice_thickness_mm: Option<f64>,
    pub frame_of_reference_uid: Option<String>,
    pub patient_birth_date: Option<String>,
    pub patient_sex: Option<String>,
    pub study_time: Option<String>,
    pub referring_physician: Option<String>,
    pub study_id: Option<String>,
}

/// Read the header of the file at `path`; files over `max_bytes` are refused unread.
pub fn read_header(path: &Path, max_bytes: u64) -> Result<InstanceHeader, DicomError> {
    let (label, bytes) = read_bounded(path, max_bytes)?;
    header_of(&label, &bytes)
}

/// The file at `path` whole, labelled by its name; files over `max_bytes` are refused unread.
pub fn read_bounded(path: &Path, max_bytes: u64) -> Result<(String, Vec<u8>), DicomError> {
    let label = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    let io = |e: std::io::Error| DicomError::Parse {
        label: label.clone(),
        reason: e.to_string(),
    };
    let size = std::fs::metadata(path).map_err(io)?.len();
    if size > max_bytes {
        return Err(DicomError::TooLarge {
            label,
            detail: format!("{size} bytes"),
            limit: format!("{max_bytes} bytes"),
        });
    }
    let bytes = std::fs::read(path).map_err(io)?;
    Ok((label, bytes))
}

/// Read the header of a file held in memory.
pub fn header_of(label: &str, bytes: &[u8]) -> Result<InstanceHeader, DicomError> {
    let Opened { obj, framed } = open(
        label,
        bytes,
        header_inflate_limit(bytes.len()),
        Some(tags::PIXEL_DATA),
    )?;
    // A malformed UID is refused as such, wherever it is; an absent required one as missing.
    check_uids(label, &obj)?;
    let uid = |tag, what| {
        uid_value(&obj, tag).ok_or_else(|| DicomError::MissingAttribute {
            label: label.to_string(),
            what,
        })
    };
    let sop_class_uid = uid(tags::SOP_CLASS_UID, "SOP Class UID (0008,0016)")?;
    let sop_instance_uid = uid(tags::SOP_INSTANCE_UID, "SOP Instance UID (0008,0018)")?;
    let study_uid = uid(tags::STUDY_INSTANCE_UID, "Study Instance UID (0020,000D)")?;
    let series_uid = uid(tags::SERIES_INSTANCE_UID, "Series Instance UID (0020,000E)")?;
    let image_type = obj
        .get(tags::IMAGE_TYPE)
        .and_then(|e| e.to_multi_str().ok().map(|v| v.to_vec()))
        .unwrap_or_default()
        .into_iter()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .collect();
    Ok(InstanceHeader {
        sop_class_uid,
        sop_instance_uid,
        study_uid,
        series_uid,
        transfer_syntax: framed.transfer_syntax.clone(),
        modality: text(&obj, tags::MODALITY),
        patient_id: text(&obj, tags::PATIENT_ID),
        patient_name: text(&obj, tags::PATIENT_NAME),
        study_date: text(&obj, tags::STUDY_DATE),
        study_description: text(&obj, tags::STUDY_DESCRIPTION),
        accession_number: text(&obj, tags::ACCESSION_NUMBER),
        series_description: text(&obj, tags::SERIES_DESCRIPTION),
        series_number: int(&obj, tags::SERIES_NUMBER),
        instance_number: int(&obj, tags::INSTANCE_NUMBER),
        body_part: text(&obj, tags::BODY_PART_EXAMINED),
        image_type,
        slice_thickness_mm: float(&obj, tags::SLICE_THICKNESS),
        frame_of_reference_uid: uid_value(&obj, tags::FRAME_OF_REFERENCE_UID),
        patient_birth_date: text(&obj, tags::PATIENT_BIRTH_DATE),
        patient_sex: text(&obj, tags::PATIENT_SEX),
        study_time: text(&obj, tags::STUDY_TIME),
        referring_physician: text(&obj, tags::REFERRING_PHYSICIAN_NAME),
        study_id: text(&obj, tags::STUDY_ID),
    })
}

/// The Part 10 prefix of a received data set: 128-byte preamble, `DICM` and a file meta group naming the
/// SOP class and instance and the transfer syntax the data set is encoded in. The data set bytes, exactly as
/// they came over the network, follow it.
pub fn part10_prefix(
    sop_class_uid: &str,
    sop_instance_uid: &str,
    transfer_syntax: &str,
) -> Result<Vec<u8>, DicomError> {
    let meta = dicom_object::FileMetaTableBuilder::new()
        .media_storage_sop_class_uid(sop_class_uid)
        .media_storage_sop_instance_uid(sop_instance_uid)
        .transfer_syntax(transfer_syntax)
        .implementation_class_uid(IMPLEMENTATION_CLASS_UID)
        .implementation_version_name(IMPLEMENTATION_VERSION)
        .build()
        .map_err(|e| DicomError::Write(e.to_string()))?;
    let mut out = vec![0u8; 128];
    out.extend_from_slice(b"DICM");
    meta.write(&mut out)
        .map_err(|e| DicomError::Write(e.to_string()))?;
    Ok(out)
}

/// ctrecon's Implementation Class UID (file meta and association negotiation), a fixed UID under the UUID
/// root `2.25`.
pub const IMPLEMENTATION_CLASS_UID: &str = "2.25.268532774380291215664569591702426317033";
/// ctrecon's Implementation Version Name (16 characters at most).
pub const IMPLEMENTATION_VERSION: &str = "CTRECON_0_1";

/// Where the data set of a Part 10 file starts, and what it is: what a sender needs to send the file's data
/// set as it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Part10 {
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub transfer_syntax: String,
    /// Byte offset of the data set in the file.
    pub dataset_offset: u64,
}

/// Read the file meta group of the Part 10 file at `path` (its first 64 KiB at most).
pub fn read_part10(path: &Path) -> Result<Part10, DicomError> {
    use std::io::Read;
    let label = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    let parse = |reason: String| DicomError::Parse {
        label: label.clone(),
        reason,
    };
    let mut head = Vec::with_capacity(4096);
    std::fs::File::open(path)
        .map_err(|e| parse(e.to_string()))?
        .take(64 << 10)
        .read_to_end(&mut head)
        .map_err(|e| parse(e.to_string()))?;
    if head.len() < 132 || &head[128..132] != b"DICM" {
        return Err(DicomError::NotDicom { label });
    }
    // (0002,0000) UL, explicit VR little endian: tag 4, VR 2, length 2, value 4.
    let group = &head[132..];
    if group.len() < 12 || group[..4] != [2, 0, 0, 0] || &group[4..6] != b"UL" {
        return Err(parse(
            "the file meta group does not start with its group length".into(),
        ));
    }
    let group_len = u32::from_le_bytes([group[8], group[9], group[10], group[11]]) as u64;
    let meta =
        dicom_object::FileMetaTable::from_reader(&head[128..]).map_err(|e| parse(e.to_string()))?;
    let uid = |s: &str| s.trim_end_matches(['\0', ' ']).to_string();
    Ok(Part10 {
        sop_class_uid: uid(meta.media_storage_sop_class_uid()),
        sop_instance_uid: uid(meta.media_storage_sop_instance_uid()),
        transfer_syntax: uid(meta.transfer_syntax()),
        dataset_offset: 132 + 12 + group_len,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_prefix_and_a_data_set_read_back_as_a_file() {
        let prefix = part10_prefix(
            "1.2.840.10008.5.1.4.1.1.7",
            "1.2.3.4",
            "1.2.840.10008.1.2.1",
        )
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.dcm");
        std::fs::write(&path, &prefix).unwrap();
        let p = read_part10(&path).unwrap();
        assert_eq!(p.sop_class_uid, "1.2.840.10008.5.1.4.1.1.7");
        assert_eq!(p.sop_instance_uid, "1.2.3.4");
        assert_eq!(p.transfer_syntax, "1.2.840.10008.1.2.1");
        assert_eq!(p.dataset_offset, prefix.len() as u64);
    }

    #[test]
    fn the_decodable_syntaxes_are_the_ones_the_reader_reads() {
        let uids = decodable_transfer_syntaxes();
        for uid in [
            "1.2.840.10008.1.2",
            "1.2.840.10008.1.2.1",
            "1.2.840.10008.1.2.1.99",
            "1.2.840.10008.1.2.4.50",
            "1.2.840.10008.1.2.4.70",
            "1.2.840.10008.1.2.4.90",
            "1.2.840.10008.1.2.5",
        ] {
            assert!(uids.contains(&uid), "{uid} missing from {uids:?}");
        }
        // JPEG-LS lossless and near-lossless, decoded by the reader itself.
        assert!(uids.contains(&"1.2.840.10008.1.2.4.80"));
        assert!(uids.contains(&"1.2.840.10008.1.2.4.81"));
    }
}
