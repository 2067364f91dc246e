//! JPEG frame headers (SOF) checked against the DICOM image before dicom-rs decodes the fragments.
//!
//! dicom-rs sizes its output from the DICOM header (rows × columns × samples × frames) but copies each decoded
//! frame at the size its JPEG frame header declares, and the decoder allocates that size first: a 256 × 256
//! image whose JPEG says 768 × 256 indexes past the buffer, and one that says 65535 × 65535 allocates
//! gigabytes. Its decoder starts a frame at any SOI marker (FF D8) of the concatenated fragments and finds
//! the next marker by skipping bytes up to an FF, so every SOI is walked here the same way to its frame
//! header, which must declare exactly the DICOM image.

/// SOFn markers (C0–CF but DHT C4, JPG C8 and DAC CC): the frame header of a baseline, extended,
/// progressive or lossless stream.
pub(super) fn is_frame_header(marker: u8) -> bool {
    (0xC0..=0xCF).contains(&marker) && !matches!(marker, 0xC4 | 0xC8 | 0xCC)
}

/// Markers without a length field: SOI, EOI, TEM and RST0–7.
fn standalone(marker: u8) -> bool {
    matches!(marker, 0xD8 | 0xD9 | 0x01 | 0xD0..=0xD7)
}

/// The next marker at or after `p`, as the decoder reads it: bytes up to an FF skipped, fill FFs skipped, an
/// FF 00 (stuffed byte) not a marker. Returns the marker and the offset after it.
pub(super) fn next_marker(d: &[u8], mut p: usize) -> Option<(u8, usize)> {
    loop {
        while *d.get(p)? != 0xFF {
            p += 1;
        }
        while *d.get(p)? == 0xFF {
            p += 1;
        }
        let m = *d.get(p)?;
        p += 1;
        if m != 0x00 {
            return Some((m, p));
        }
    }
}

/// The frame header of the stream whose SOI ends at `p`: (precision, rows, columns, components). `None`
/// where the bytes end or a scan starts first (the decoder then fails by itself).
fn frame_header(d: &[u8], mut p: usize) -> Option<(u8, u16, u16, u8)> {
    loop {
        let (m, after) = next_marker(d, p)?;
        if standalone(m) {
            p = after;
            continue;
        }
        if m == 0xDA {
            return None;
        }
        let len = u16::from_be_bytes([*d.get(after)?, *d.get(after + 1)?]) as usize;
        if is_frame_header(m) {
            let h = d.get(after + 2..after + 8)?;
            return Some((
                h[0],
                u16::from_be_bytes([h[1], h[2]]),
                u16::from_be_bytes([h[3], h[4]]),
                h[5],
            ));
        }
        p = after + len.max(2);
    }
}

/// Check every JPEG stream in `data` (the fragments of the pixel data, concatenated) against an image of
/// `rows` × `columns` × `samples` with `bits_allocated` bits per sample. `Err` names the first mismatch.
pub(super) fn frame_headers_fit(
    data: &[u8],
    rows: usize,
    columns: usize,
    samples: usize,
    bits_allocated: usize,
) -> Result<(), String> {
    let soi = data
        .windows(2)
        .enumerate()
        .filter(|(_, w)| *w == [0xFF, 0xD8])
        .map(|(i, _)| i + 2);
    for (n, p) in soi.enumerate() {
        let Some((precision, h, w, nc)) = frame_header(data, p) else {
            continue;
        };
        let bytes = if precision > 8 { 2 } else { 1 };
        if h as usize != rows
            || w as usize != columns
            || nc as usize != samples
            || bytes * 8 > bits_allocated
        {
            return Err(format!(
                "JPEG stream {} declares {h}×{w} pixels × {nc} components of {precision} bits, but the image \
                 is {rows}×{columns} × {samples} samples of {bits_allocated} bits",
                n + 1
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SOI, an APP0 segment, a SOF0 of `h` × `w` × `nc` at 8 bits, SOS.
    fn stream(h: u16, w: u16, nc: u8) -> Vec<u8> {
        let mut d = vec![0xFF, 0xD8, 0xFF, 0xE0, 0, 6, b'J', b'F', b'I', b'F'];
        d.extend_from_slice(&[0xFF, 0xC0, 0, 8 + 3 * nc, 8]);
        d.extend_from_slice(&h.to_be_bytes());
        d.extend_from_slice(&w.to_be_bytes());
        d.push(nc);
        for c in 0..nc {
            d.extend_from_slice(&[c + 1, 0x11, 0]);
        }
        d.extend_from_slice(&[0xFF, 0xDA, 0, 2, 0xFF, 0xD9]);
        d
    }

    #[test]
    fn a_frame_header_that_matches_the_image_passes() {
        assert_eq!(
            frame_headers_fit(&stream(256, 256, 3), 256, 256, 3, 8),
            Ok(())
        );
        let two = [stream(4, 5, 1), stream(4, 5, 1)].concat();
        assert_eq!(frame_headers_fit(&two, 4, 5, 1, 16), Ok(()));
    }

    #[test]
    fn a_frame_header_larger_than_the_image_is_refused_in_any_stream() {
        let e = frame_headers_fit(&stream(768, 256, 3), 256, 256, 3, 8).unwrap_err();
        assert!(e.contains("768×256"), "{e}");
        // The second stream, after garbage the decoder would skip.
        let d = [stream(4, 5, 1), vec![1, 2, 3], stream(4, 6, 1)].concat();
        assert!(
            frame_headers_fit(&d, 4, 5, 1, 8)
                .unwrap_err()
                .contains("stream 2")
        );
        // Fill bytes before the marker, as the decoder skips them.
        let mut filled = stream(9, 9, 1);
        filled.splice(10..10, [0xFF, 0xFF]);
        assert!(frame_headers_fit(&filled, 4, 4, 1, 8).is_err());
    }
}
