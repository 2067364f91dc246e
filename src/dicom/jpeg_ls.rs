//! JPEG-LS pixel data (ITU-T T.87): transfer syntaxes 1.2.840.10008.1.2.4.80 (lossless) and
//! 1.2.840.10008.1.2.4.81 (near-lossless), as scanners and archives store CT.
//!
//! dicom-rs decodes JPEG-LS only through CharLS (a C++ library built with CMake), so ctrecon decodes it
//! with the `pure_jpegls` crate (library `jpegls`), a pure-Rust T.87 decoder checked against CharLS fixtures. It reads one component per
//! scan, which is what CT, MR and other grey images use; colour JPEG-LS is refused by name. The decoder
//! checks the frame size against the DICOM header, NEAR, MAXVAL and the LSE thresholds before it
//! allocates, and ctrecon catches a panic inside it as a decode error.

pub const LOSSLESS: &str = "1.2.840.10008.1.2.4.80";
pub const NEAR_LOSSLESS: &str = "1.2.840.10008.1.2.4.81";

pub fn is_jpeg_ls(transfer_syntax: &str) -> bool {
    transfer_syntax == LOSSLESS || transfer_syntax == NEAR_LOSSLESS
}

/// The fragments of each frame (JPEG-LS and 12-bit JPEG): one frame per fragment, or (PS3.5 A.4) a frame over several fragments,
/// each frame starting in a fragment that begins with SOI.
pub(super) fn frame_streams(fragments: &[&[u8]], frames: usize) -> Result<Vec<Vec<u8>>, String> {
    if fragments.len() == frames {
        return Ok(fragments.iter().map(|f| f.to_vec()).collect());
    }
    if frames == 1 {
        return Ok(vec![fragments.concat()]);
    }
    let mut out: Vec<Vec<u8>> = Vec::new();
    for f in fragments {
        if f.starts_with(&[0xFF, 0xD8]) || out.is_empty() {
            if out.len() == frames {
                return Err(format!(
                    "more JPEG-LS frames in the pixel data than the {frames} declared"
                ));
            }
            out.push(Vec::new());
        }
        if let Some(last) = out.last_mut() {
            last.extend_from_slice(f);
        }
    }
    if out.len() != frames {
        return Err(format!(
            "{} JPEG-LS frames found in {} fragments, {frames} declared",
            out.len(),
            fragments.len()
        ));
    }
    Ok(out)
}

/// The stream without the fill bytes (0xFF, T.81 B.1.1.2, which T.87 keeps) between the end of its scan and
/// its EOI marker. CharLS, and DCMTK through it, ends a scan whose last data byte is a full byte with one
/// such fill byte; the decoder reads the first 0xFF after the scan as the marker's start and refuses the
/// stream. A 0xFF data byte is always followed by a byte below 0x80, so a 0xFF followed by 0xFF is fill.
fn without_fill_before_eoi(stream: &[u8]) -> std::borrow::Cow<'_, [u8]> {
    // The last EOI, before any padding after it (fragments are padded to even length).
    let Some(eoi) = stream.windows(2).rposition(|w| w == [0xFF, 0xD9]) else {
        return stream.into();
    };
    let fill = stream[..eoi]
        .iter()
        .rev()
        .take_while(|&&b| b == 0xFF)
        .count();
    if fill == 0 {
        return stream.into();
    }
    let mut out = Vec::with_capacity(stream.len() - fill);
    out.extend_from_slice(&stream[..eoi - fill]);
    out.extend_from_slice(&stream[eoi..]);
    out.into()
}

/// Decode `frames` frames of `rows` × `columns` single-sample pixels into little-endian samples of
/// `bits_allocated` (8 or 16) bits, frame after frame.
pub fn decode_frames(
    fragments: &[&[u8]],
    frames: usize,
    rows: usize,
    columns: usize,
    samples_per_pixel: usize,
    bits_allocated: u16,
) -> Result<Vec<u8>, String> {
    if samples_per_pixel != 1 {
        return Err(format!(
            "colour JPEG-LS ({samples_per_pixel} samples per pixel) is not supported; grey images are"
        ));
    }
    let bytes_per = match bits_allocated {
        8 => 1,
        16 => 2,
        other => return Err(format!("JPEG-LS with {other} bits allocated")),
    };
    let (w, h) = (
        u32::try_from(columns).map_err(|_| "image too wide".to_string())?,
        u32::try_from(rows).map_err(|_| "image too tall".to_string())?,
    );
    let streams = frame_streams(fragments, frames)?;
    let mut out = Vec::with_capacity(frames * rows * columns * bytes_per);
    for (i, stream) in streams.iter().enumerate() {
        let stream = without_fill_before_eoi(stream);
        let decoded = super::contain::contained(|| jpegls::decode(&stream, w, h))
            .map_err(|_| {
                format!(
                    "frame {}: the JPEG-LS decoder failed on malformed data",
                    i + 1
                )
            })?
            .map_err(|e| format!("frame {}: {e}", i + 1))?;
        let (pixels, dw, dh) = decoded;
        if (dw, dh) != (w, h) || pixels.len() != rows * columns {
            return Err(format!(
                "frame {}: decoded {dw}×{dh}, the header says {w}×{h}",
                i + 1
            ));
        }
        if bytes_per == 1 {
            if let Some(big) = pixels.iter().find(|&&p| p > 255) {
                return Err(format!(
                    "frame {}: sample {big} does not fit 8 bits allocated",
                    i + 1
                ));
            }
            out.extend(pixels.iter().map(|&p| p as u8));
        } else {
            out.extend(pixels.iter().flat_map(|p| p.to_le_bytes()));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize, max: u16) -> Vec<u16> {
        (0..w * h)
            .map(|i| (((i % w) * 37 + (i / w) * 11) % (max as usize + 1)) as u16)
            .collect()
    }

    fn encode(px: &[u16], w: u32, h: u32, near: u8) -> Vec<u8> {
        let mut o = jpegls::EncodeOptions::default();
        o.near = near;
        o.precision = Some(12);
        let mut out = Vec::new();
        jpegls::encode_with_options(px, w, h, &o, &mut out).expect("encode");
        out
    }

    #[test]
    fn lossless_frames_decode_exactly_and_near_lossless_within_near() {
        let (w, h) = (33usize, 17usize);
        let a = ramp(w, h, 4095);
        let b: Vec<u16> = a.iter().map(|v| 4095 - v).collect();
        let (fa, fb) = (encode(&a, 33, 17, 0), encode(&b, 33, 17, 0));
        let out = decode_frames(&[&fa, &fb], 2, h, w, 1, 16).expect("decode");
        let got: Vec<u16> = out
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        assert_eq!(&got[..w * h], &a[..]);
        assert_eq!(&got[w * h..], &b[..]);

        let near = encode(&a, 33, 17, 3);
        let out = decode_frames(&[&near], 1, h, w, 1, 16).expect("decode");
        let worst = out
            .chunks_exact(2)
            .zip(&a)
            .map(|(c, &v)| (u16::from_le_bytes([c[0], c[1]]) as i32 - v as i32).abs())
            .max();
        assert!(worst.is_some_and(|e| e <= 3), "{worst:?}");
    }

    #[test]
    fn fill_bytes_before_the_end_of_image_are_skipped() {
        let (w, h) = (16usize, 9usize);
        let a = ramp(w, h, 4095);
        let f = encode(&a, 16, 9, 0);
        assert_eq!(&f[f.len() - 2..], &[0xFF, 0xD9]);
        for fill in [1, 3] {
            // Fill bytes before EOI, and the zero that pads a DICOM fragment to even length after it.
            let mut filled = f[..f.len() - 2].to_vec();
            filled.extend(std::iter::repeat_n(0xFF, fill));
            filled.extend_from_slice(&[0xFF, 0xD9]);
            if filled.len() % 2 == 1 {
                filled.push(0);
            }
            assert!(jpegls::decode(&filled, 16, 9).is_err(), "the decoder alone");
            let out = decode_frames(&[&filled], 1, h, w, 1, 16).expect("decode");
            let got: Vec<u16> = out
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect();
            assert_eq!(got, a, "{fill} fill bytes");
        }
        assert_eq!(without_fill_before_eoi(&f), &f[..]);
        assert_eq!(without_fill_before_eoi(&[0xFF, 0xFF]), &[0xFF, 0xFF][..]);
    }

    #[test]
    fn a_frame_split_over_fragments_is_joined_at_each_start_of_image() {
        let (w, h) = (8usize, 8usize);
        let a = ramp(w, h, 4095);
        let f = encode(&a, 8, 8, 0);
        let (x, y) = f.split_at(f.len() / 2);
        let out = decode_frames(&[x, y, x, y], 2, h, w, 1, 16).expect("decode");
        assert_eq!(out.len(), 2 * w * h * 2);
        assert_eq!(out[..w * h * 2], out[w * h * 2..]);
    }

    #[test]
    fn wrong_sizes_colour_and_garbage_are_named_refusals() {
        let a = ramp(8, 8, 4095);
        let f = encode(&a, 8, 8, 0);
        let e = decode_frames(&[&f], 1, 9, 8, 1, 16).expect_err("size differs");
        assert!(e.contains("frame 1"), "{e}");
        assert!(
            decode_frames(&[&f], 1, 8, 8, 3, 16)
                .expect_err("colour")
                .contains("colour")
        );
        assert!(decode_frames(&[&f, &f], 3, 8, 8, 1, 16).is_err());
        let mut cut = f.clone();
        cut.truncate(f.len() / 3);
        assert!(decode_frames(&[&cut], 1, 8, 8, 1, 16).is_err());
        let twelve_bit = decode_frames(&[&f], 1, 8, 8, 1, 8).expect_err("8-bit overflow");
        assert!(twelve_bit.contains("8 bits"), "{twelve_bit}");
        let mut flipped = f.clone();
        for b in flipped.iter_mut().skip(20).step_by(7) {
            *b ^= 0x5A;
        }
        let _ = decode_frames(&[&flipped], 1, 8, 8, 1, 16); // an error or some pixels, never a panic
    }
}
