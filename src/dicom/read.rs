//! One DICOM file into an [`Instance`]: attributes and decoded frames as [`Slice`]s.

use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{InMemDicomObject, OpenFileOptions};
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};

use super::error::DicomError;
use super::framing::{self, FramingError};
use super::pixels;
use super::uid::{check_meta_uids, check_uid, check_uids, uid_value};
use crate::series::{Slice, Warning};

/// Limits checked from the header, before any pixel buffer is allocated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Largest number of rows or columns.
    pub max_side: u32,
    pub max_frames: u32,
    /// Largest decoded pixel data (bytes) of one file.
    pub max_pixel_bytes: usize,
}

impl Default for ReadLimits {
    fn default() -> Self {
        Self {
            max_side: 8192,
            max_frames: 4096,
            max_pixel_bytes: 1 << 30,
        }
    }
}

/// Room for the attributes beside the pixel data when a deflated data set is inflated (bytes).
pub(super) const MAX_HEADER_BYTES: usize = 64 << 20;

/// The most a deflated file of `file_len` bytes may inflate to when its attributes alone are read (a
/// header, its DICOM JSON, a re-encoding): four times the file, but at least 16 MiB, since a small file of
/// smooth pixels deflates far more than 4× (a synthetic CT slice of 4.9 kB to 1 kB), and at most 1 GiB.
pub(super) fn header_inflate_limit(file_len: usize) -> usize {
    file_len
        .saturating_mul(4)
        .clamp(MAX_HEADER_BYTES / 4, MAX_HEADER_BYTES.saturating_mul(16))
}

/// A decoded DICOM image file.
#[derive(Debug, Clone, PartialEq)]
pub struct Instance {
    /// Name given by the uploader (file or ZIP entry name): for messages only, never a path.
    pub label: String,
    pub size_bytes: usize,
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub series_uid: String,
    pub study_uid: Option<String>,
    pub frame_of_reference_uid: Option<String>,
    pub modality: Option<String>,
    pub transfer_syntax: String,
    pub photometric: String,
    pub samples_per_pixel: u16,
    pub bits_stored: u16,
    pub signed: bool,
    pub patient_name: Option<String>,
    pub patient_id: Option<String>,
    pub series_description: Option<String>,
    pub instance_number: Option<i64>,
    /// Body Part Examined (0018,0015).
    pub body_part: Option<String>,
    /// Image Type (0008,0008) values.
    pub image_type: Vec<String>,
    /// One slice per frame (stored values; colour images keep all samples interleaved).
    pub slices: Vec<Slice>,
    pub warnings: Vec<Warning>,
}

pub(super) fn text(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let e = obj.get(tag)?;
    let s = e.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

fn floats(obj: &InMemDicomObject, tag: Tag) -> Option<Vec<f64>> {
    obj.get(tag)?.to_multi_float64().ok()
}

pub(super) fn float(obj: &InMemDicomObject, tag: Tag) -> Option<f64> {
    floats(obj, tag)?.first().copied().filter(|v| v.is_finite())
}

pub(super) fn int(obj: &InMemDicomObject, tag: Tag) -> Option<i64> {
    obj.get(tag)?.to_int::<i64>().ok()
}

fn items(obj: &InMemDicomObject, tag: Tag) -> Option<&[InMemDicomObject]> {
    obj.get(tag)?.items()
}

/// The first item of sequence `seq` in `group`, falling back to `shared`.
fn group_item<'a>(
    group: Option<&'a InMemDicomObject>,
    shared: Option<&'a InMemDicomObject>,
    seq: Tag,
) -> Option<&'a InMemDicomObject> {
    group
        .and_then(|g| items(g, seq))
        .and_then(|i| i.first())
        .or_else(|| shared.and_then(|g| items(g, seq)).and_then(|i| i.first()))
}

fn arr<const N: usize>(v: Option<Vec<f64>>) -> Option<[f64; N]> {
    let v = v?;
    (v.len() >= N && v[..N].iter().all(|x| x.is_finite())).then(|| {
        let mut a = [0.0; N];
        a.copy_from_slice(&v[..N]);
        a
    })
}

/// Read one DICOM file from a path (the label is the file name).
pub fn read_path(path: &Path, limits: &ReadLimits) -> Result<Instance, DicomError> {
    let label = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    let bytes = std::fs::read(path).map_err(|e| DicomError::Parse {
        label: label.clone(),
        reason: e.to_string(),
    })?;
    read_bytes(&label, &bytes, limits)
}

/// The fuzz target's entry point (and the regression replay's): [`read_bytes`] under limits of 64 MiB of pixels.
/// Every outcome but a panic is fine.
#[doc(hidden)]
pub fn fuzz_entry(data: &[u8]) {
    let limits = ReadLimits {
        max_pixel_bytes: 64 << 20,
        ..ReadLimits::default()
    };
    let _ = read_bytes("fuzz input", data, &limits);
}

/// A data set that passed framing and the pre-parse walk, parsed (up to `until`, when given).
pub(super) struct Opened<'a> {
    pub obj: dicom_object::FileDicomObject<InMemDicomObject>,
    pub framed: framing::Framed<'a>,
}

/// Frame, walk and parse `bytes` (a deflated data set may inflate to `max_inflated`); stop before `until`.
pub(super) fn open<'a>(
    label: &str,
    bytes: &'a [u8],
    max_inflated: usize,
    until: Option<Tag>,
) -> Result<Opened<'a>, DicomError> {
    let label_s = label.to_string();
    // Framing and the pre-parse walk: no declared length past the end, no runaway nesting.
    let framed = framing::frame(bytes, max_inflated).map_err(|e| match e {
        FramingError::NotDicom => DicomError::NotDicom {
            label: label_s.clone(),
        },
        FramingError::Defect(d) => DicomError::Parse {
            label: label_s.clone(),
            reason: d.to_string(),
        },
    })?;
    // A transfer syntax the registry does not know, or whose data set it cannot decode, is named as such.
    let unsupported_ts = |name: &str| DicomError::UnsupportedTransferSyntax {
        label: label_s.clone(),
        uid: framed.transfer_syntax.clone(),
        name: name.to_string(),
    };
    if framed.transfer_syntax.is_empty() {
        return Err(DicomError::Parse {
            label: label_s,
            reason: "the file meta group ends before its Transfer Syntax UID (0002,0010)".into(),
        });
    }
    let ts_entry = TransferSyntaxRegistry
        .get(&framed.transfer_syntax)
        .ok_or_else(|| unsupported_ts("not a known transfer syntax"))?;
    if !ts_entry.can_decode_dataset() {
        return Err(unsupported_ts(ts_entry.name()));
    }
    // dicom-rs refuses a meta group with a malformed UID as unreadable: name it as the UID it is.
    check_meta_uids(label, &framed.bytes)?;
    let parse = || {
        let options = OpenFileOptions::new().read_preamble(ReadPreamble::Never);
        let options = match until {
            Some(tag) => options.read_until(tag),
            None => options,
        };
        options.from_reader(&framed.bytes[..])
    };
    let obj = match super::contain::contained(parse) {
        Ok(Ok(o)) => o,
        Ok(Err(e)) => {
            return Err(DicomError::Parse {
                label: label_s,
                reason: e.to_string(),
            });
        }
        Err(_) => {
            return Err(DicomError::Parse {
                label: label_s,
                reason: "malformed data set".into(),
            });
        }
    };
    Ok(Opened { obj, framed })
}

/// Read one DICOM file held in memory (Part 10, or a raw data set as pydicom reads with `force=True`). `label` names it
/// in messages.
pub fn read_bytes(label: &str, bytes: &[u8], limits: &ReadLimits) -> Result<Instance, DicomError> {
    let label_s = label.to_string();
    let Opened { obj, framed } = open(
        label,
        bytes,
        limits.max_pixel_bytes.saturating_add(MAX_HEADER_BYTES),
        None,
    )?;
    // As framed: a deflated data set reaches the parser inflated, and keeps its own name.
    let transfer_syntax = framed.transfer_syntax.clone();
    let missing = |what| DicomError::MissingAttribute {
        label: label_s.clone(),
        what,
    };
    // Every UID present is checked before any pixel is decoded: a malformed one refuses the file (an absent
    // one is not required here; a file without a series UID is grouped with the others that lack one).
    check_uids(label, &obj)?;
    let from_meta = |value: &str, attribute| {
        let value = value.trim_end_matches(['\0', ' ']);
        check_uid(label, attribute, (!value.is_empty()).then_some(value))
            .map(|()| value.to_string())
    };
    let sop_class_uid = match uid_value(&obj, tags::SOP_CLASS_UID) {
        Some(uid) => uid,
        None => from_meta(
            obj.meta().media_storage_sop_class_uid(),
            "Media Storage SOP Class UID (0002,0002)",
        )?,
    };
    let sop_instance_uid = match uid_value(&obj, tags::SOP_INSTANCE_UID) {
        Some(uid) => uid,
        None => from_meta(
            obj.meta().media_storage_sop_instance_uid(),
            "Media Storage SOP Instance UID (0002,0003)",
        )?,
    };
    let series_uid = uid_value(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default();

    let pixels = pixels::decode(&obj, &framed, limits, label)?;
    let (rows, columns, frames) = (
        pixels.layout.rows,
        pixels.layout.columns,
        pixels.layout.frames,
    );

    // Placement: classic attributes or Enhanced functional groups.
    let shared = items(&obj, tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE).and_then(|i| i.first());
    let per_frame = items(&obj, tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE);
    if per_frame.is_some_and(|p| p.len() < frames) {
        return Err(missing(
            "Per-frame Functional Groups Sequence (one item per frame)",
        ));
    }
    let padding = float(&obj, tags::PIXEL_PADDING_VALUE)
        .map(|p| (p, float(&obj, tags::PIXEL_PADDING_RANGE_LIMIT).unwrap_or(p)));
    let mut slices = Vec::with_capacity(frames);
    let mut rescale_missing = false;
    for f in 0..frames {
        let g = per_frame.and_then(|p| p.get(f));
        let from_group =
            |seq: Tag, tag: Tag| group_item(g, shared, seq).and_then(|item| floats(item, tag));
        let position = arr::<3>(
            from_group(tags::PLANE_POSITION_SEQUENCE, tags::IMAGE_POSITION_PATIENT)
                .or_else(|| floats(&obj, tags::IMAGE_POSITION_PATIENT)),
        );
        let orientation = arr::<6>(
            from_group(
                tags::PLANE_ORIENTATION_SEQUENCE,
                tags::IMAGE_ORIENTATION_PATIENT,
            )
            .or_else(|| floats(&obj, tags::IMAGE_ORIENTATION_PATIENT)),
        );
        let spacing = arr::<2>(
            from_group(tags::PIXEL_MEASURES_SEQUENCE, tags::PIXEL_SPACING)
                .or_else(|| floats(&obj, tags::PIXEL_SPACING)),
        )
        .filter(|s| s.iter().all(|v| *v > 0.0));
        let thickness = from_group(tags::PIXEL_MEASURES_SEQUENCE, tags::SLICE_THICKNESS)
            .and_then(|v| v.first().copied())
            .or_else(|| float(&obj, tags::SLICE_THICKNESS));
        let stated_slope = from_group(
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_SLOPE,
        )
        .and_then(|v| v.first().copied())
        .or_else(|| float(&obj, tags::RESCALE_SLOPE));
        let stated_intercept = from_group(
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_INTERCEPT,
        )
        .and_then(|v| v.first().copied())
        .or_else(|| float(&obj, tags::RESCALE_INTERCEPT));
        rescale_missing |= stated_slope.is_none() || stated_intercept.is_none();
        let (slope, intercept) = (stated_slope.unwrap_or(1.0), stated_intercept.unwrap_or(0.0));
        let stored = pixels.frame_values(f);
        slices.push(Slice {
            rows,
            columns,
            stored,
            rescale_slope: slope,
            rescale_intercept: intercept,
            position_mm: position,
            orientation,
            pixel_spacing_mm: spacing,
            slice_thickness_mm: thickness,
            padding,
            label: if frames > 1 {
                format!("{label} frame {}", f + 1)
            } else {
                label.to_string()
            },
        });
    }
    let mut warnings = Vec::new();
    let modality = text(&obj, tags::MODALITY);
    if rescale_missing && modality.as_deref() == Some("CT") {
        warnings.push(Warning {
            code: "rescale_assumed",
            message: format!(
                "{label}: no Rescale Slope/Intercept (0028,1053/1052): stored values taken as HU (slope 1, intercept 0)"
            ),
        });
    }
    if series_uid.is_empty() {
        warnings.push(Warning {
            code: "series_uid_missing",
            message: format!(
                "{label}: no Series Instance UID (0020,000E): grouped with the other files that lack one"
            ),
        });
    }
    if framed.raw_dataset {
        warnings.push(Warning {
            code: "transfer_syntax_guessed",
            message: format!(
                "{label}: no preamble, DICM marker or file meta group: read as {} from its first element",
                framed.transfer_syntax
            ),
        });
    }
    if framed.trailing_bytes > 0 {
        warnings.push(Warning {
            code: "trailing_bytes_ignored",
            message: format!(
                "{label}: {} bytes of padding after the data set were ignored",
                framed.trailing_bytes
            ),
        });
    }
    if pixels.layout.photometric == "MONOCHROME1" {
        warnings.push(Warning {
            code: "monochrome1",
            message: format!("{label}: MONOCHROME1 (inverted display); HU values are unaffected"),
        });
    }
    Ok(Instance {
        label: label.to_string(),
        size_bytes: bytes.len(),
        sop_class_uid,
        sop_instance_uid,
        series_uid,
        study_uid: uid_value(&obj, tags::STUDY_INSTANCE_UID),
        frame_of_reference_uid: uid_value(&obj, tags::FRAME_OF_REFERENCE_UID),
        modality,
        transfer_syntax,
        samples_per_pixel: pixels.samples_per_pixel as u16,
        bits_stored: pixels.layout.bits_stored as u16,
        signed: pixels.layout.signed,
        photometric: pixels.layout.photometric,
        patient_name: text(&obj, tags::PATIENT_NAME),
        patient_id: text(&obj, tags::PATIENT_ID),
        series_description: text(&obj, tags::SERIES_DESCRIPTION),
        instance_number: int(&obj, tags::INSTANCE_NUMBER),
        body_part: text(&obj, tags::BODY_PART_EXAMINED),
        image_type: obj
            .get(tags::IMAGE_TYPE)
            .and_then(|e| e.to_multi_str().ok().map(|v| v.to_vec()))
            .unwrap_or_default()
            .into_iter()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
            .collect(),
        slices,
        warnings,
    })
}
