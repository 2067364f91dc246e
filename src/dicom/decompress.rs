//! A stored instance as a Part 10 file in explicit VR little endian, whatever syntax it is stored in: the
//! default and the asked-for transfer syntax of WADO-RS (PS3.18 §8.7.3.5.2).
//!
//! An instance stored in explicit VR little endian is sent as it is; one stored in another uncompressed
//! syntax (implicit VR, deflated, big endian) is re-encoded; one stored compressed (JPEG baseline, extended
//! and lossless, JPEG 2000, RLE, JPEG-LS) has its pixel data decoded by the reader's own decoders
//! ([`super::pixels`]: the same header and codec checks as every upload, the JPEG-LS decoder of
//! [`super::jpeg_ls`]) and written native. Decoding may change what the pixels are: colour decoded from
//! JPEG or JPEG 2000 is RGB whatever the stream's YBR interpretation, so Photometric Interpretation (and
//! Planar Configuration, interleaved) are set to what the decoded samples are, and the encapsulation's
//! offset tables go. Lossy Image Compression (0028,2110) and its ratio stay as the stored instance says.
//!
//! One instance at a time: the file, its decoded pixels and the written result are held together, no more.

use std::path::Path;

use dicom_core::value::PrimitiveValue;
use dicom_core::{DataElement, Tag, VR};
use dicom_dictionary_std::tags;
use dicom_transfer_syntax_registry::entries::EXPLICIT_VR_LITTLE_ENDIAN;

use super::error::DicomError;
use super::read::{MAX_HEADER_BYTES, Opened, ReadLimits, open};
use super::web::{EXPLICIT_LE, IMPLICIT_LE};

/// Extended Offset Table (7FE0,0001) and its lengths (7FE0,0002): only meaningful for encapsulated pixels.
const EXTENDED_OFFSET_TABLE: Tag = Tag(0x7FE0, 0x0001);
const EXTENDED_OFFSET_TABLE_LENGTHS: Tag = Tag(0x7FE0, 0x0002);

/// Whether an instance stored in `ts` can be sent in explicit VR little endian: every syntax whose data
/// set and pixel data the reader decodes.
pub fn transcodable_to_explicit_le(ts: &str) -> bool {
    super::header::decodable_transfer_syntaxes().contains(&ts)
}

/// Whether re-encoding an instance stored in `ts` in explicit VR little endian changes only its element
/// headers: its pixel data is native and little endian (implicit VR, or deflated explicit VR). Big endian
/// pixel data goes through the decoder, which gives its samples in little-endian order.
fn headers_only(ts: &str) -> bool {
    matches!(ts, EXPLICIT_LE | IMPLICIT_LE | "1.2.840.10008.1.2.1.99")
}

/// The instance at `path` as a Part 10 file in explicit VR little endian with native pixel data (files over
/// `max_bytes` are refused unread; decoded pixels over `limits` are refused before they are allocated).
pub fn explicit_le_bytes(
    path: &Path,
    max_bytes: u64,
    limits: &ReadLimits,
) -> Result<Vec<u8>, DicomError> {
    let ts = super::header::read_part10(path)?.transfer_syntax;
    let (label, bytes) = super::header::read_bounded(path, max_bytes)?;
    if ts == EXPLICIT_LE {
        return Ok(bytes);
    }
    let Opened { mut obj, framed } = open(
        &label,
        &bytes,
        limits.max_pixel_bytes.saturating_add(MAX_HEADER_BYTES),
        None,
    )?;
    let has_pixels = obj.get(tags::PIXEL_DATA).is_some();
    if has_pixels && !headers_only(&framed.transfer_syntax) {
        let decoded = super::pixels::decode(&obj, &framed, limits, &label)?;
        let (samples, photometric, planar, bits) = (
            decoded.samples_per_pixel,
            decoded.photometric_out.clone(),
            decoded.planar_out,
            decoded.layout.bits_allocated,
        );
        let mut pixels = decoded.native_le();
        drop(decoded);
        if pixels.len() % 2 == 1 {
            pixels.push(0);
        }
        // Samples over 8 bits are words (OW); the little-endian bytes are written as they are.
        let vr = if bits > 8 { VR::OW } else { VR::OB };
        let value = DataElement::new(tags::PIXEL_DATA, vr, PrimitiveValue::U8(pixels.into()));
        obj.put(value);
        obj.remove_element(EXTENDED_OFFSET_TABLE);
        obj.remove_element(EXTENDED_OFFSET_TABLE_LENGTHS);
        obj.put(DataElement::new(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            PrimitiveValue::from(photometric.as_str()),
        ));
        obj.put(DataElement::new(
            tags::SAMPLES_PER_PIXEL,
            VR::US,
            PrimitiveValue::from(samples as u16),
        ));
        if samples > 1 {
            obj.put(DataElement::new(
                tags::PLANAR_CONFIGURATION,
                VR::US,
                PrimitiveValue::from(planar),
            ));
        } else {
            obj.remove_element(tags::PLANAR_CONFIGURATION);
        }
    }
    obj.meta_mut()
        .set_transfer_syntax(&EXPLICIT_VR_LITTLE_ENDIAN);
    let mut out = Vec::with_capacity(bytes.len().saturating_add(1024));
    obj.write_all(&mut out)
        .map_err(|e| DicomError::Write(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dicom::{SeriesMeta, read_bytes, write_ct_series};
    use crate::volume::{Frame, Volume};

    fn slice_file() -> Vec<u8> {
        let vol = Volume {
            data: ndarray::Array3::from_shape_fn((2, 6, 5), |(k, j, i)| {
                (k * 30 + j * 5 + i) as f32 - 20.0
            }),
            frame: Frame {
                origin_mm: [0.0, 0.0, 0.0],
                spacing_mm: [1.0, 1.0, 2.0],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let s = write_ct_series(&vol, &SeriesMeta::default()).unwrap();
        s.files[1].1.clone()
    }

    #[test]
    fn every_syntax_the_reader_decodes_is_sent_in_explicit_vr_little_endian() {
        for ts in [
            EXPLICIT_LE,
            IMPLICIT_LE,
            "1.2.840.10008.1.2.1.99",
            "1.2.840.10008.1.2.4.50",
            "1.2.840.10008.1.2.4.70",
            "1.2.840.10008.1.2.4.80",
            "1.2.840.10008.1.2.4.90",
            "1.2.840.10008.1.2.5",
        ] {
            assert!(transcodable_to_explicit_le(ts), "{ts}");
        }
        assert!(!transcodable_to_explicit_le("1.2.840.10008.1.2.4.100"));
    }

    #[test]
    fn an_implicit_vr_instance_reads_back_the_same_in_explicit_vr() {
        let file = slice_file();
        let first = read_bytes("a", &file, &ReadLimits::default()).unwrap();
        let mut obj = dicom_object::from_reader(std::io::Cursor::new(&file[128..])).unwrap();
        obj.meta_mut().set_transfer_syntax(
            &dicom_transfer_syntax_registry::entries::IMPLICIT_VR_LITTLE_ENDIAN,
        );
        let mut implicit = Vec::new();
        obj.write_all(&mut implicit).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.dcm");
        std::fs::write(&path, &implicit).unwrap();
        let out = explicit_le_bytes(&path, 1 << 20, &ReadLimits::default()).unwrap();
        let again = read_bytes("b", &out, &ReadLimits::default()).unwrap();
        assert_eq!(again.transfer_syntax, EXPLICIT_LE);
        assert_eq!(again.slices[0].stored, first.slices[0].stored);
        // Stored in explicit VR little endian: the file itself.
        std::fs::write(&path, &file).unwrap();
        assert_eq!(
            explicit_le_bytes(&path, 1 << 20, &ReadLimits::default()).unwrap(),
            file
        );
    }

    #[test]
    fn an_rle_instance_is_decoded_to_the_same_stored_values() {
        // RLE Lossless of the slice written by hand (PS3.5 G: one segment per byte plane, high byte first),
        // each segment a literal run per row.
        let file = slice_file();
        let first = read_bytes("a", &file, &ReadLimits::default()).unwrap();
        let mut obj = dicom_object::from_reader(std::io::Cursor::new(&file[128..])).unwrap();
        let raw = obj
            .element(tags::PIXEL_DATA)
            .unwrap()
            .to_bytes()
            .unwrap()
            .to_vec();
        let (rows, cols) = (6usize, 5usize);
        let mut segments: Vec<Vec<u8>> = vec![Vec::new(), Vec::new()];
        for (s, seg) in segments.iter_mut().enumerate() {
            for r in 0..rows {
                seg.push((cols - 1) as u8);
                for c in 0..cols {
                    let px = &raw[2 * (r * cols + c)..2 * (r * cols + c) + 2];
                    seg.push(if s == 0 { px[1] } else { px[0] });
                }
            }
            if seg.len() % 2 == 1 {
                seg.push(0x80); // no-op run, keeps segments even
            }
        }
        let mut fragment = vec![0u8; 64];
        fragment[0..4].copy_from_slice(&2u32.to_le_bytes());
        fragment[4..8].copy_from_slice(&64u32.to_le_bytes());
        fragment[8..12].copy_from_slice(&(64 + segments[0].len() as u32).to_le_bytes());
        fragment.extend_from_slice(&segments[0]);
        fragment.extend_from_slice(&segments[1]);
        obj.put(DataElement::new(
            tags::PIXEL_DATA,
            VR::OB,
            dicom_core::value::Value::PixelSequence(dicom_core::value::PixelFragmentSequence::new(
                vec![],
                vec![fragment],
            )),
        ));
        obj.meta_mut()
            .set_transfer_syntax(&dicom_transfer_syntax_registry::entries::RLE_LOSSLESS);
        let mut rle = Vec::new();
        obj.write_all(&mut rle).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rle.dcm");
        std::fs::write(&path, &rle).unwrap();
        let stored = read_bytes("rle", &rle, &ReadLimits::default()).unwrap();
        assert_eq!(stored.transfer_syntax, "1.2.840.10008.1.2.5");
        let out = explicit_le_bytes(&path, 1 << 20, &ReadLimits::default()).unwrap();
        let again = read_bytes("b", &out, &ReadLimits::default()).unwrap();
        assert_eq!(again.transfer_syntax, EXPLICIT_LE);
        assert_eq!(again.photometric, "MONOCHROME2");
        assert_eq!(again.slices[0].stored, first.slices[0].stored);
        let native = dicom_object::from_reader(std::io::Cursor::new(&out[128..])).unwrap();
        assert_eq!(native.element(tags::PIXEL_DATA).unwrap().vr(), VR::OW);
        assert_eq!(
            native
                .element(tags::PIXEL_DATA)
                .unwrap()
                .to_bytes()
                .unwrap()
                .len(),
            raw.len()
        );
    }
}
