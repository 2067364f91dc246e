//! One DICOM file into an [`Instance`]: attributes and decoded frames as [`Slice`]s.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{InMemDicomObject, OpenFileOptions};
use dicom_pixeldata::PixelDecoder;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};

use super::error::DicomError;
use super::framing::{self, FramingError};
use super::{jpeg, jpeg_ls};
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
    let e = obj.element_opt(tag).ok()??;
    let s = e.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

fn floats(obj: &InMemDicomObject, tag: Tag) -> Option<Vec<f64>> {
    obj.element_opt(tag).ok()??.to_multi_float64().ok()
}

pub(super) fn float(obj: &InMemDicomObject, tag: Tag) -> Option<f64> {
    floats(obj, tag)?.first().copied().filter(|v| v.is_finite())
}

pub(super) fn int(obj: &InMemDicomObject, tag: Tag) -> Option<i64> {
    obj.element_opt(tag).ok()??.to_int::<i64>().ok()
}

fn items(obj: &InMemDicomObject, tag: Tag) -> Option<&[InMemDicomObject]> {
    obj.element_opt(tag).ok()??.items()
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
    let parse = || {
        let options = OpenFileOptions::new().read_preamble(ReadPreamble::Never);
        let options = match until {
            Some(tag) => options.read_until(tag),
            None => options,
        };
        options.from_reader(&framed.bytes[..])
    };
    let obj = match catch_unwind(AssertUnwindSafe(parse)) {
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
    let unsupported_ts = |name: &str| DicomError::UnsupportedTransferSyntax {
        label: label_s.clone(),
        uid: framed.transfer_syntax.clone(),
        name: name.to_string(),
    };
    let ts_entry = TransferSyntaxRegistry
        .get(&framed.transfer_syntax)
        .ok_or_else(|| unsupported_ts("not a known transfer syntax"))?;
    // As framed: a deflated data set reaches the parser inflated, and keeps its own name.
    let transfer_syntax = framed.transfer_syntax.clone();
    let missing = |what| DicomError::MissingAttribute {
        label: label_s.clone(),
        what,
    };
    let sop_class_uid = text(&obj, tags::SOP_CLASS_UID)
        .unwrap_or_else(|| obj.meta().media_storage_sop_class_uid().to_string());
    let sop_instance_uid = text(&obj, tags::SOP_INSTANCE_UID)
        .unwrap_or_else(|| obj.meta().media_storage_sop_instance_uid().to_string());
    let series_uid = text(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default();

    // Header checks before any pixel buffer exists.
    let pixel = obj
        .element_opt(tags::PIXEL_DATA)
        .ok()
        .flatten()
        .ok_or_else(|| DicomError::NoPixelData {
            label: label_s.clone(),
        })?;
    let rows = int(&obj, tags::ROWS).ok_or_else(|| missing("Rows (0028,0010)"))?;
    let columns = int(&obj, tags::COLUMNS).ok_or_else(|| missing("Columns (0028,0011)"))?;
    // Absent means one frame; present but unreadable, zero or negative is refused, never taken as one.
    let frames = match obj.element_opt(tags::NUMBER_OF_FRAMES).ok().flatten() {
        None => 1,
        Some(e) => match e.to_int::<i64>() {
            Ok(f) if f >= 1 => f,
            _ => return Err(missing("Number of Frames (0028,0008)")),
        },
    };
    let spp = int(&obj, tags::SAMPLES_PER_PIXEL).unwrap_or(1);
    let bits_allocated =
        int(&obj, tags::BITS_ALLOCATED).ok_or_else(|| missing("Bits Allocated (0028,0100)"))?;
    let bits_stored = int(&obj, tags::BITS_STORED).unwrap_or(bits_allocated);
    let signed = int(&obj, tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1;
    let photometric =
        text(&obj, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_else(|| "MONOCHROME2".into());
    if rows < 1 || columns < 1 {
        return Err(missing("Rows/Columns (non-zero)"));
    }
    let too_large = |detail: String, limit: String| DicomError::TooLarge {
        label: label_s.clone(),
        detail,
        limit,
    };
    if rows > limits.max_side as i64 || columns > limits.max_side as i64 {
        return Err(too_large(
            format!("{rows}×{columns} pixels"),
            format!("{} pixels a side", limits.max_side),
        ));
    }
    if frames > limits.max_frames as i64 {
        return Err(too_large(
            format!("{frames} frames"),
            format!("{} frames", limits.max_frames),
        ));
    }
    if !matches!(bits_allocated, 8 | 16 | 32) || bits_stored < 1 || bits_stored > bits_allocated {
        return Err(DicomError::Unsupported {
            label: label_s.clone(),
            what: format!("pixel layout: {bits_allocated} bits allocated, {bits_stored} stored"),
        });
    }
    if !(1..=4).contains(&spp) {
        return Err(DicomError::Unsupported {
            label: label_s.clone(),
            what: format!("{spp} samples per pixel"),
        });
    }
    let (rows, columns, frames, spp) = (
        rows as usize,
        columns as usize,
        frames as usize,
        spp as usize,
    );
    let expected = rows
        .checked_mul(columns)
        .and_then(|v| v.checked_mul(frames))
        .and_then(|v| v.checked_mul(spp))
        .and_then(|v| v.checked_mul(bits_allocated as usize / 8))
        .filter(|&v| v <= limits.max_pixel_bytes)
        .ok_or_else(|| {
            too_large(
                format!("{rows}×{columns} pixels × {frames} frames × {spp} samples × {bits_allocated} bits"),
                format!("{} bytes", limits.max_pixel_bytes),
            )
        })?;
    let encapsulated = pixel.fragments().is_some();
    // Codecs dicom-pixeldata lacks in this build; JPEG-LS is decoded here (`jpeg_ls`), grey images only.
    if encapsulated && !ts_entry.can_decode_all() && !jpeg_ls::is_jpeg_ls(&transfer_syntax) {
        return Err(unsupported_ts(ts_entry.name()));
    }
    if encapsulated && jpeg_ls::is_jpeg_ls(&transfer_syntax) && spp != 1 {
        return Err(DicomError::Unsupported {
            label: label_s,
            what: format!("colour JPEG-LS ({spp} samples per pixel); grey JPEG-LS is read"),
        });
    }
    if !encapsulated {
        let got = pixel.to_bytes().map(|b| b.len()).unwrap_or(0);
        if got < expected {
            return Err(DicomError::PixelDataShort {
                label: label_s,
                expected,
                got,
            });
        }
    }

    // An RGB JPEG with neither an Adobe nor a JFIF marker nor R, G, B component ids is ambiguous: decoders
    // disagree on whether to undo a YCbCr transform, so it is refused rather than guessed.
    if spp == 3
        && photometric == "RGB"
        && matches!(
            transfer_syntax.as_str(),
            "1.2.840.10008.1.2.4.50" | "1.2.840.10008.1.2.4.51"
        )
        && let Some(frag) = pixel.fragments().and_then(|f| f.first())
        && !jpeg_colour_declared(frag)
    {
        return Err(DicomError::Unsupported {
            label: label_s,
            what: "RGB JPEG without a colour-transform marker (Adobe APP14 or JFIF)".into(),
        });
    }

    // JPEG: dicom-rs copies each decoded frame at the size its frame header declares, so every frame header
    // must declare exactly this image.
    if matches!(
        transfer_syntax.as_str(),
        "1.2.840.10008.1.2.4.50"
            | "1.2.840.10008.1.2.4.51"
            | "1.2.840.10008.1.2.4.57"
            | "1.2.840.10008.1.2.4.70"
    ) {
        let data: Vec<u8> = pixel
            .fragments()
            .into_iter()
            .flatten()
            .flatten()
            .copied()
            .collect();
        if let Err(reason) =
            jpeg::frame_headers_fit(&data, rows, columns, spp, bits_allocated as usize)
        {
            return Err(DicomError::Decode {
                label: label_s,
                transfer_syntax,
                reason,
            });
        }
    }

    // RLE: dicom-rs trusts each fragment's 64-byte header (it allocates by the segment count and slices by
    // the offsets), so the header is checked first.
    if transfer_syntax == "1.2.840.10008.1.2.5"
        && let Some(bad) = pixel
            .fragments()
            .into_iter()
            .flatten()
            .position(|f| !rle_fragment_fits(f, rows * columns))
    {
        return Err(DicomError::Decode {
            label: label_s,
            transfer_syntax,
            reason: format!(
                "RLE fragment {} has a header that does not fit it, or a segment shorter than a plane",
                bad + 1
            ),
        });
    }

    // Decode (codec panics on hostile data become errors).
    let decode_err = |reason: String| DicomError::Decode {
        label: label_s.clone(),
        transfer_syntax: transfer_syntax.clone(),
        reason,
    };
    let jls_data: Vec<u8>;
    let decoded;
    let (data, decoded_spp, decoded_bits): (&[u8], usize, usize) =
        if jpeg_ls::is_jpeg_ls(&transfer_syntax) {
            let fragments: Vec<&[u8]> = pixel
                .fragments()
                .into_iter()
                .flatten()
                .map(|f| f.as_slice())
                .collect();
            jls_data = jpeg_ls::decode_frames(
                &fragments,
                frames,
                rows,
                columns,
                spp,
                bits_allocated as u16,
            )
            .map_err(decode_err)?;
            (&jls_data, 1, bits_allocated as usize)
        } else {
            decoded = match catch_unwind(AssertUnwindSafe(|| obj.decode_pixel_data())) {
                Ok(Ok(d)) => d,
                Ok(Err(e)) => return Err(decode_err(e.to_string())),
                Err(_) => return Err(decode_err("the codec failed on malformed data".into())),
            };
            if decoded.rows() as usize != rows
                || decoded.columns() as usize != columns
                || (decoded.number_of_frames() as usize) < frames
            {
                return Err(decode_err("decoded size differs from the header".into()));
            }
            // Colour images decoded from JPEG may be RGB regardless of the declared photometric
            // interpretation.
            (
                decoded.data(),
                decoded.samples_per_pixel() as usize,
                decoded.bits_allocated() as usize,
            )
        };
    let bytes_per = bits_allocated as usize / 8;
    let frame_len = rows * columns * spp;
    let frame_bytes = frame_len * bytes_per / spp * decoded_spp;
    if data.len() < frame_bytes * frames {
        return Err(DicomError::PixelDataShort {
            label: label_s,
            expected: frame_bytes * frames,
            got: data.len(),
        });
    }
    let big_endian = transfer_syntax == "1.2.840.10008.1.2.2" && !encapsulated;
    if decoded_bits / 8 != bytes_per {
        return Err(decode_err(format!(
            "decoder returned {decoded_bits}-bit samples for {bits_allocated}-bit data"
        )));
    }
    let bs = bits_stored as u32;
    let mask: u64 = if bs >= 64 { u64::MAX } else { (1u64 << bs) - 1 };
    let convert = |raw: u64| -> f32 {
        let v = raw & mask;
        if signed && bs < 64 && (v >> (bs - 1)) & 1 == 1 {
            (v as i64 - (1i64 << bs)) as f32
        } else {
            v as f32
        }
    };

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
        let raw = &data[f * frame_bytes..(f + 1) * frame_bytes];
        let stored: Vec<f32> = match bytes_per {
            1 => raw.iter().map(|&b| convert(b as u64)).collect(),
            2 => raw
                .chunks_exact(2)
                .map(|c| convert(u16::from_le_bytes([c[0], c[1]]) as u64))
                .collect(),
            // Big endian native data arrives as 16-bit words in host order: swap the words of 32-bit samples.
            _ if big_endian => raw
                .chunks_exact(4)
                .map(|c| convert(u32::from_le_bytes([c[2], c[3], c[0], c[1]]) as u64))
                .collect(),
            _ => raw
                .chunks_exact(4)
                .map(|c| convert(u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as u64))
                .collect(),
        };
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
    if photometric == "MONOCHROME1" {
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
        study_uid: text(&obj, tags::STUDY_INSTANCE_UID),
        frame_of_reference_uid: text(&obj, tags::FRAME_OF_REFERENCE_UID),
        modality,
        transfer_syntax,
        photometric,
        samples_per_pixel: decoded_spp as u16,
        bits_stored: bits_stored as u16,
        signed,
        patient_name: text(&obj, tags::PATIENT_NAME),
        patient_id: text(&obj, tags::PATIENT_ID),
        series_description: text(&obj, tags::SERIES_DESCRIPTION),
        instance_number: int(&obj, tags::INSTANCE_NUMBER),
        body_part: text(&obj, tags::BODY_PART_EXAMINED),
        image_type: obj
            .element_opt(tags::IMAGE_TYPE)
            .ok()
            .flatten()
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

/// Whether a JPEG stream says how its three components relate to RGB: an Adobe APP14 or JFIF APP0 marker, or
/// component ids `R`, `G`, `B` in the frame header.
fn jpeg_colour_declared(jpeg: &[u8]) -> bool {
    let header = match jpeg.windows(2).position(|w| w == [0xFF, 0xDA]) {
        Some(end) => &jpeg[..end],
        None => jpeg,
    };
    let has = |needle: &[u8]| header.windows(needle.len()).any(|w| w == needle);
    if has(b"Adobe") || has(b"JFIF") {
        return true;
    }
    header
        .windows(2)
        .position(|w| w[0] == 0xFF && (0xC0..=0xC3).contains(&w[1]))
        .and_then(|sof| {
            let n = *header.get(sof + 9)? as usize;
            let ids: Option<Vec<u8>> = (0..n)
                .map(|c| header.get(sof + 10 + 3 * c).copied())
                .collect();
            ids
        })
        .is_some_and(|ids| ids == b"RGB")
}

/// Whether an RLE Lossless fragment's header (PS3.5 G.5: a segment count of 1 to 15, then 15 offsets) has
/// offsets from the end of the header to the end of the fragment, in order, and every segment unpacks to at
/// least `plane` bytes (dicom-rs indexes a short segment out of bounds).
fn rle_fragment_fits(fragment: &[u8], plane: usize) -> bool {
    let word = |i: usize| {
        fragment
            .get(4 * i..4 * i + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let (Some(n), true) = (word(0), fragment.len() >= 64) else {
        return false;
    };
    if !(1..=15).contains(&n) {
        return false;
    }
    let mut offsets = Vec::with_capacity(n + 1);
    for i in 1..=n {
        match word(i) {
            Some(o) if o >= offsets.last().copied().unwrap_or(64) && o <= fragment.len() => {
                offsets.push(o)
            }
            _ => return false,
        }
    }
    offsets.push(fragment.len());
    offsets
        .windows(2)
        .all(|w| packbits_len(&fragment[w[0]..w[1]], plane) >= plane)
}

/// Bytes a PackBits segment unpacks to, counting up to `enough`.
fn packbits_len(segment: &[u8], enough: usize) -> usize {
    let (mut i, mut out) = (0usize, 0usize);
    while i < segment.len() && out < enough {
        let h = segment[i] as i8;
        i += 1;
        if h >= 0 {
            let n = (h as usize + 1).min(segment.len() - i);
            out += n;
            i += n;
        } else if h != -128 {
            if i >= segment.len() {
                break;
            }
            out += (1 - h as isize) as usize;
            i += 1;
        }
    }
    out
}
