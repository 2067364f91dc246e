//! What a file's pixels will cost before a byte of them is decoded: the image layout its header declares
//! (rows × columns × frames × samples × bits allocated), read from the first bytes of the file — inflated,
//! for a deflated data set, only as far as the attributes before the pixel data.
//!
//! The memory a DICOM file takes once decoded is a property of its header, not of its size on disk: a
//! deflated, RLE or JPEG-LS slice of 8192² zeros is a few hundred bytes. Whoever decodes files (uploads, the
//! DICOM node's series, DICOMweb renderings) reserves what [`Declared`] says first, and refuses what can
//! never fit, so that compressed input cannot escape the memory budget.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use super::error::DicomError;
use super::read::ReadLimits;
use super::scan::{self, Encoding};
use super::unzip::may_be_dicom;

/// The most bytes of a data set read (or inflated) to find its image attributes, from 64 KiB doubled as
/// needed. Real headers before the pixel data are a few kilobytes; an Enhanced CT's functional groups come
/// after group 0028.
pub const MAX_LEADING_BYTES: usize = 8 << 20;

const DEFLATED: &str = "1.2.840.10008.1.2.1.99";

/// The first read: the preamble, the meta group and, in real files, every attribute before the pixel data.
const FIRST_READ: usize = 64 << 10;

/// The cost of one file's pixels, as its header declares them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Declared {
    /// Bytes of the file on disk.
    pub file_bytes: u64,
    /// Samples of every frame: rows × columns × frames × samples per pixel (0 without an image).
    pub samples: u64,
    /// Bytes of the decoded pixel data: `samples` × bits allocated / 8.
    pub decoded_bytes: u64,
    /// Whether the data set itself is deflated (it is inflated whole before parsing).
    pub deflated: bool,
    /// Series Instance UID (0020,000E), when the leading attributes hold one.
    pub series_uid: Option<String>,
}

impl Declared {
    /// Peak bytes held while the file is read and decoded, beyond the stored values that are kept: the file,
    /// the inflated data set, the parsed pixel element and the decoded buffer (each at most the decoded
    /// size or the file).
    pub fn decoding_bytes(&self) -> u64 {
        let inflated = if self.deflated { self.decoded_bytes } else { 0 };
        self.file_bytes
            .saturating_mul(2)
            .saturating_add(inflated)
            .saturating_add(self.decoded_bytes.saturating_mul(2))
    }

    /// Bytes of the stored values kept once decoded (`f32` per sample).
    pub fn kept_bytes(&self) -> u64 {
        self.samples.saturating_mul(4)
    }
}

fn parse_error(label: &str, reason: impl Into<String>) -> DicomError {
    DicomError::Parse {
        label: label.to_string(),
        reason: reason.into(),
    }
}

/// The layout the file at `path` declares, checked against `limits` as the decoder checks it (sides, frames,
/// decoded bytes), so that a file over them is refused here, before anything is decoded. A data set
/// without a file meta group (the reader guesses its encoding) holds native pixels: its decoded size is
/// bounded by the file.
pub fn declared(path: &Path, label: &str, limits: &ReadLimits) -> Result<Declared, DicomError> {
    let io = |e: std::io::Error| DicomError::Write(format!("reading {label}: {e}"));
    let mut file = File::open(path).map_err(io)?;
    let file_bytes = file.metadata().map_err(io)?.len();
    let mut head = Vec::new();
    (&mut file)
        .take(FIRST_READ as u64)
        .read_to_end(&mut head)
        .map_err(io)?;
    let meta_at = if head.len() >= 132 && &head[128..132] == b"DICM" {
        Some(132)
    } else if head.starts_with(b"DICM") {
        Some(4)
    } else if head.len() >= 8 && head[..2] == [0x02, 0x00] {
        Some(0)
    } else {
        None
    };
    let bare = Declared {
        file_bytes,
        samples: file_bytes,
        decoded_bytes: file_bytes,
        deflated: false,
        series_uid: None,
    };
    // No file meta group: a bare data set holds native pixels, at most the file; anything else is no DICOM.
    let Some(meta_at) = meta_at else {
        if !may_be_dicom(&head, file_bytes) {
            return Err(DicomError::NotDicom {
                label: label.to_string(),
            });
        }
        return Ok(bare);
    };
    let meta = scan::meta(&head[meta_at..]).map_err(|d| parse_error(label, d.to_string()))?;
    let data_at = (meta_at + meta.end) as u64;
    let deflated = meta.transfer_syntax == DEFLATED;
    let enc = if deflated {
        Encoding {
            explicit: true,
            big_endian: false,
        }
    } else {
        match Encoding::of(&meta.transfer_syntax) {
            Some(e) => e,
            // A data set deflated by a scheme the reader does not know: the decoder refuses it.
            None => return Ok(bare),
        }
    };
    file.seek(SeekFrom::Start(data_at)).map_err(io)?;
    let buffered = std::io::BufReader::new(file);
    let mut data_set: Box<dyn Read> = if deflated {
        Box::new(flate2::read::DeflateDecoder::new(buffered))
    } else {
        Box::new(buffered)
    };
    // Read (or inflate) as far as the image attributes, doubling from 64 KiB up to MAX_LEADING_BYTES.
    let mut data = Vec::new();
    let mut cap = FIRST_READ;
    loop {
        let want = cap - data.len();
        let got = (&mut data_set)
            .take(want as u64)
            .read_to_end(&mut data)
            .map_err(|_| {
                parse_error(label, "the deflated data set is not a valid deflate stream")
            })?;
        let whole = got < want;
        let elements = match scan::leading(&data, enc, 0x0028) {
            Ok(Some(e)) => e,
            // The data set ends before any image attribute or pixel data: nothing to decode.
            Ok(None) if whole => Vec::new(),
            Ok(None) | Err(scan::Defect::Overrun { .. }) if !whole && cap < MAX_LEADING_BYTES => {
                cap = (cap * 2).min(MAX_LEADING_BYTES);
                continue;
            }
            // Still cut at the cap: the header is larger than anything real.
            Ok(None) | Err(scan::Defect::Overrun { .. }) if !whole => {
                return Err(DicomError::TooLarge {
                    label: label.to_string(),
                    detail: "attributes before the pixel data".into(),
                    limit: format!("{MAX_LEADING_BYTES} bytes"),
                });
            }
            Ok(None) => Vec::new(),
            Err(d) => return Err(parse_error(label, d.to_string())),
        };
        let (samples, decoded_bytes, series_uid) =
            layout(label, &elements, enc.big_endian, limits)?;
        return Ok(Declared {
            file_bytes,
            samples,
            decoded_bytes,
            deflated,
            series_uid,
        });
    }
}

fn text(v: &[u8]) -> String {
    String::from_utf8_lossy(v)
        .trim_matches(|c: char| c.is_whitespace() || c == '\0')
        .to_string()
}

/// Samples, decoded bytes and series UID from the leading elements, under the decoder's limits.
fn layout(
    label: &str,
    elements: &[((u16, u16), &[u8])],
    big_endian: bool,
    limits: &ReadLimits,
) -> Result<(u64, u64, Option<String>), DicomError> {
    let find = |tag: (u16, u16)| elements.iter().find(|(t, _)| *t == tag).map(|(_, v)| *v);
    let us = |tag| {
        find(tag).and_then(|v| {
            let b: [u8; 2] = v.get(..2)?.try_into().ok()?;
            Some(i64::from(if big_endian {
                u16::from_be_bytes(b)
            } else {
                u16::from_le_bytes(b)
            }))
        })
    };
    let series_uid = find((0x0020, 0x000E)).map(text).filter(|s| !s.is_empty());
    let (Some(rows), Some(columns)) = (us((0x0028, 0x0010)), us((0x0028, 0x0011))) else {
        // No image declared: nothing to decode (the reader refuses the file for its own reasons).
        return Ok((0, 0, series_uid));
    };
    let frames = match find((0x0028, 0x0008)) {
        None => 1,
        Some(v) => text(v).parse::<i64>().unwrap_or(0),
    };
    let spp = us((0x0028, 0x0002)).unwrap_or(1).max(1);
    let bits = us((0x0028, 0x0100)).unwrap_or(16);
    let too_large = |detail: String, limit: String| DicomError::TooLarge {
        label: label.to_string(),
        detail,
        limit,
    };
    if rows > i64::from(limits.max_side) || columns > i64::from(limits.max_side) {
        return Err(too_large(
            format!("{rows}×{columns} pixels"),
            format!("{} pixels a side", limits.max_side),
        ));
    }
    if frames > i64::from(limits.max_frames) {
        return Err(too_large(
            format!("{frames} frames"),
            format!("{} frames", limits.max_frames),
        ));
    }
    // Zero or negative sizes, odd depths and sample counts are the decoder's to refuse; they cost nothing.
    let (rows, columns, frames, spp) = (
        rows.max(0) as u64,
        columns.max(0) as u64,
        frames.max(0) as u64,
        spp.clamp(1, 4) as u64,
    );
    let samples = rows * columns * frames * spp;
    let decoded = samples * (bits.clamp(8, 32) as u64).div_ceil(8);
    if decoded > limits.max_pixel_bytes as u64 {
        return Err(too_large(
            format!("{rows}×{columns} pixels × {frames} frames × {spp} samples × {bits} bits"),
            format!("{} bytes", limits.max_pixel_bytes),
        ));
    }
    Ok((samples, decoded, series_uid))
}
