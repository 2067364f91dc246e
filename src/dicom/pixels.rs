//! The pixel data of one DICOM file: the image layout checked against the limits before any buffer exists,
//! the compressed streams checked where codecs trust their headers (JPEG frame headers, RLE segment tables,
//! RGB JPEG colour markers), then decoded (JPEG-LS and 12-bit JPEG Extended here, every other codec by dicom-pixeldata,
//! whose panics on hostile data become errors), and each frame's samples read as stored values.

use dicom_dictionary_std::tags;
use dicom_object::FileDicomObject;
use dicom_object::InMemDicomObject;
use dicom_pixeldata::{DecodedPixelData, PixelDecoder};
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};

use super::error::DicomError;
use super::framing::Framed;
use super::read::{ReadLimits, int, text};
use super::{jpeg, jpeg_ls, jpeg12};

/// The image layout the header declares, checked against the limits.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Layout {
    pub rows: usize,
    pub columns: usize,
    pub frames: usize,
    pub bits_allocated: i64,
    pub bits_stored: i64,
    pub signed: bool,
    pub photometric: String,
}

/// Decoded pixel data: the bytes of every frame, as the codec (or the file) gives them.
pub(super) struct Decoded<'a> {
    pub layout: Layout,
    /// Samples per pixel after decoding (JPEG colour may come back as RGB whatever the header says).
    pub samples_per_pixel: usize,
    /// Bytes of one frame in [`Decoded::bytes`].
    pub frame_bytes: usize,
    /// Photometric Interpretation of the decoded samples: the declared one, except colour decoded from a
    /// compressed stream, which is RGB.
    pub photometric_out: String,
    /// Planar Configuration of the decoded samples (0: interleaved, as every codec gives them).
    pub planar_out: u16,
    big_endian: bool,
    data: Data<'a>,
}

enum Data<'a> {
    /// Decoded here (JPEG-LS, 12-bit JPEG Extended): little-endian samples.
    Own(Vec<u8>),
    Codec(DecodedPixelData<'a>),
}

impl Decoded<'_> {
    pub fn bytes(&self) -> &[u8] {
        match &self.data {
            Data::Own(v) => v,
            Data::Codec(d) => d.data(),
        }
    }

    /// The decoded frames as native little-endian pixel data (every frame, no more): what a Pixel Data
    /// element of an uncompressed little-endian data set holds.
    pub fn native_le(&self) -> Vec<u8> {
        let all = &self.bytes()[..self.frame_bytes * self.layout.frames];
        if self.big_endian && self.layout.bits_allocated == 32 {
            // 16-bit words in host order: swap the words of each 32-bit sample, as `frame_values` does.
            all.chunks_exact(4)
                .flat_map(|c| [c[2], c[3], c[0], c[1]])
                .collect()
        } else {
            all.to_vec()
        }
    }

    /// The stored values of frame `f` (all samples interleaved), sign-extended from Bits Stored.
    pub fn frame_values(&self, f: usize) -> Vec<f32> {
        let (bits_stored, signed) = (self.layout.bits_stored, self.layout.signed);
        let bytes_per = self.layout.bits_allocated as usize / 8;
        let big_endian = self.big_endian;
        let raw = &self.bytes()[f * self.frame_bytes..(f + 1) * self.frame_bytes];
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

        match bytes_per {
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
        }
    }
}

/// Check the layout and the compressed streams of `obj`'s pixel data, then decode it.
pub(super) fn decode<'a>(
    obj: &'a FileDicomObject<InMemDicomObject>,
    framed: &Framed<'_>,
    limits: &ReadLimits,
    label: &str,
) -> Result<Decoded<'a>, DicomError> {
    let label_s = label.to_string();
    let transfer_syntax = framed.transfer_syntax.clone();
    let unsupported_ts = |name: &str| DicomError::UnsupportedTransferSyntax {
        label: label_s.clone(),
        uid: transfer_syntax.clone(),
        name: name.to_string(),
    };
    let ts_entry = TransferSyntaxRegistry
        .get(&transfer_syntax)
        .ok_or_else(|| unsupported_ts("not a known transfer syntax"))?;
    let missing = |what| DicomError::MissingAttribute {
        label: label_s.clone(),
        what,
    };
    // Header checks before any pixel buffer exists.
    let pixel = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| DicomError::NoPixelData {
            label: label_s.clone(),
        })?;
    let rows = int(obj, tags::ROWS).ok_or_else(|| missing("Rows (0028,0010)"))?;
    let columns = int(obj, tags::COLUMNS).ok_or_else(|| missing("Columns (0028,0011)"))?;
    // Absent means one frame; present but unreadable, zero or negative is refused, never taken as one.
    let frames = match obj.get(tags::NUMBER_OF_FRAMES) {
        None => 1,
        Some(e) => match e.to_int::<i64>() {
            Ok(f) if f >= 1 => f,
            _ => return Err(missing("Number of Frames (0028,0008)")),
        },
    };
    let spp = int(obj, tags::SAMPLES_PER_PIXEL).unwrap_or(1);
    let bits_allocated =
        int(obj, tags::BITS_ALLOCATED).ok_or_else(|| missing("Bits Allocated (0028,0100)"))?;
    let bits_stored = int(obj, tags::BITS_STORED).unwrap_or(bits_allocated);
    let signed = int(obj, tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1;
    let photometric =
        text(obj, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_else(|| "MONOCHROME2".into());
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
    // The fragments, for the decoders of this module.
    let fragments: Vec<&[u8]> = pixel
        .fragments()
        .into_iter()
        .flatten()
        .map(|f| f.as_slice())
        .collect();
    let twelve_bit = transfer_syntax == jpeg12::EXTENDED
        && fragments.first().is_some_and(|f| jpeg12::is_12bit_dct(f));
    let (data, decoded_spp, decoded_bits, decoded_colour) = if twelve_bit {
        if spp != 1 || bits_allocated != 16 {
            return Err(DicomError::Unsupported {
                label: label_s.clone(),
                what: format!(
                    "12-bit JPEG of {spp} samples per pixel and {bits_allocated} bits allocated; grey 16-bit images are read"
                ),
            });
        }
        // ctrecon's own decoder: not contained, so that the fuzzer sees any panic in it.
        let decoded =
            jpeg12::decode_frames(&fragments, frames, rows, columns).map_err(decode_err)?;
        (Data::Own(decoded), 1, 16, None)
    } else if jpeg_ls::is_jpeg_ls(&transfer_syntax) {
        let jls = jpeg_ls::decode_frames(
            &fragments,
            frames,
            rows,
            columns,
            spp,
            bits_allocated as u16,
        )
        .map_err(decode_err)?;
        (Data::Own(jls), 1, bits_allocated as usize, None)
    } else {
        let decoded = match super::contain::contained(|| obj.decode_pixel_data()) {
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
        let (spp, bits) = (
            decoded.samples_per_pixel() as usize,
            decoded.bits_allocated() as usize,
        );
        let colour = (
            decoded.photometric_interpretation().to_string(),
            match decoded.planar_configuration() {
                dicom_pixeldata::PlanarConfiguration::Standard => 0,
                _ => 1,
            },
        );
        (Data::Codec(decoded), spp, bits, Some(colour))
    };
    let bytes_per = bits_allocated as usize / 8;
    let frame_len = rows * columns * spp;
    let frame_bytes = frame_len * bytes_per / spp * decoded_spp;
    let len = match &data {
        Data::Own(v) => v.len(),
        Data::Codec(d) => d.data().len(),
    };
    if len < frame_bytes * frames {
        return Err(DicomError::PixelDataShort {
            label: label_s,
            expected: frame_bytes * frames,
            got: len,
        });
    }
    let big_endian = transfer_syntax == "1.2.840.10008.1.2.2" && !encapsulated;
    if decoded_bits / 8 != bytes_per {
        return Err(decode_err(format!(
            "decoder returned {decoded_bits}-bit samples for {bits_allocated}-bit data"
        )));
    }
    let (photometric_out, planar_out) = match decoded_colour {
        Some((pi, planar)) => (pi, planar),
        None => (photometric.clone(), 0),
    };
    Ok(Decoded {
        layout: Layout {
            rows,
            columns,
            frames,
            bits_allocated,
            bits_stored,
            signed,
            photometric,
        },
        samples_per_pixel: decoded_spp,
        frame_bytes,
        photometric_out,
        planar_out,
        big_endian,
        data,
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
