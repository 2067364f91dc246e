//! 12-bit JPEG Extended (ITU-T T.81 sequential DCT with Huffman coding, 12-bit samples, SOF1) of grey
//! images: what CT archives and scanners store under 1.2.840.10008.1.2.4.51. The build's JPEG decoder reads
//! 8-bit DCT streams only, so 12-bit ones are decoded here.
//!
//! The inverse DCT is the integer one of the IJG library (`jidctint.c`, "islow", with the 12-bit scaling),
//! which DCMTK, GDCM and most archives decode with, followed by the IJG range limiting: the samples equal
//! those of DCMTK's `dcmdjpeg` bit for bit. One component per frame, one scan, restart intervals; the frame
//! size must be the DICOM image's, checked before anything is allocated. Progressive, lossless,
//! arithmetic-coded, hierarchical and colour streams are refused by name; a scan header with other spectral
//! or approximation values than a sequential scan's is read as sequential, as IJG does.

/// JPEG Extended (Process 2 & 4): 8- or 12-bit sequential DCT.
pub const EXTENDED: &str = "1.2.840.10008.1.2.4.51";

mod idct;
mod scan;
#[cfg(test)]
mod tests;

use scan::{Bits, Huffman, scan};

/// Start of a sequential DCT frame with extended (12-bit) precision.
const SOF1: u8 = 0xC1;

/// Whether `stream` (one frame's JPEG data) is a 12-bit sequential DCT frame: its first frame header is SOF1
/// with a precision of 12.
pub fn is_12bit_dct(stream: &[u8]) -> bool {
    let mut r = Reader { d: stream, p: 0 };
    if r.marker() != Some(0xD8) {
        return false;
    }
    while let Some(m) = r.marker() {
        match m {
            m if super::jpeg::is_frame_header(m) => {
                return m == SOF1 && r.d.get(r.p + 2) == Some(&12);
            }
            0xD9 | 0xDA => return false,
            0xD0..=0xD7 | 0x01 => {}
            _ => {
                if r.skip_segment().is_none() {
                    return false;
                }
            }
        }
    }
    false
}

/// Decode `frames` frames of `rows` × `columns` 12-bit grey samples into little-endian 16-bit samples,
/// frame after frame. `fragments` are the pixel data's fragments (a frame per fragment, or frames over
/// several fragments, each starting with SOI).
pub fn decode_frames(
    fragments: &[&[u8]],
    frames: usize,
    rows: usize,
    columns: usize,
) -> Result<Vec<u8>, String> {
    let streams = super::jpeg_ls::frame_streams(fragments, frames)?;
    let mut out = Vec::with_capacity(frames.saturating_mul(rows * columns * 2));
    for (i, s) in streams.iter().enumerate() {
        let samples = decode(s, rows, columns).map_err(|e| format!("frame {}: {e}", i + 1))?;
        out.extend(samples.iter().flat_map(|v| v.to_le_bytes()));
    }
    Ok(out)
}

/// Decode one 12-bit grey frame of `rows` × `columns` samples.
pub fn decode(stream: &[u8], rows: usize, columns: usize) -> Result<Vec<u16>, String> {
    let mut r = Reader { d: stream, p: 0 };
    if r.marker() != Some(0xD8) {
        return Err("no start of image".into());
    }
    let mut quant: [Option<[u16; 64]>; 4] = [None; 4];
    let mut dc: [Option<Huffman>; 4] = Default::default();
    let mut ac: [Option<Huffman>; 4] = Default::default();
    let mut frame: Option<(u8, usize)> = None; // (component id, quantisation table)
    let mut restart = 0usize;
    let mut image: Option<Vec<u16>> = None;
    loop {
        let m = r
            .marker()
            .ok_or("the stream ends before its end of image")?;
        match m {
            0xD9 => break,
            0xD0..=0xD7 | 0x01 => {}
            0xDB => {
                let seg = r.segment()?;
                let mut p = 0;
                while p < seg.len() {
                    let (pq, tq) = (seg[p] >> 4, (seg[p] & 15) as usize);
                    p += 1;
                    if tq > 3 || pq > 1 {
                        return Err("a quantisation table of an unknown kind".into());
                    }
                    let size = if pq == 0 { 64 } else { 128 };
                    let t = seg
                        .get(p..p + size)
                        .ok_or("a quantisation table is cut short")?;
                    let mut q = [0u16; 64];
                    for (k, v) in q.iter_mut().enumerate() {
                        *v = if pq == 0 {
                            u16::from(t[k])
                        } else {
                            u16::from_be_bytes([t[2 * k], t[2 * k + 1]])
                        };
                    }
                    quant[tq] = Some(q);
                    p += size;
                }
            }
            0xC4 => {
                let seg = r.segment()?;
                let mut p = 0;
                while p < seg.len() {
                    let (tc, th) = (seg[p] >> 4, (seg[p] & 15) as usize);
                    let counts = seg
                        .get(p + 1..p + 17)
                        .ok_or("a Huffman table is cut short")?;
                    let n: usize = counts.iter().map(|&c| c as usize).sum();
                    let values = seg
                        .get(p + 17..p + 17 + n)
                        .ok_or("a Huffman table is cut short")?;
                    if th > 3 || tc > 1 {
                        return Err("a Huffman table of an unknown kind".into());
                    }
                    let t = Huffman::new(counts, values)?;
                    if tc == 0 {
                        dc[th] = Some(t);
                    } else {
                        ac[th] = Some(t);
                    }
                    p += 17 + n;
                }
            }
            0xDD => {
                let seg = r.segment()?;
                let ri = seg.get(..2).ok_or("a restart interval is cut short")?;
                restart = usize::from(u16::from_be_bytes([ri[0], ri[1]]));
            }
            SOF1 => {
                if frame.is_some() {
                    return Err("more than one frame header".into());
                }
                let seg = r.segment()?;
                let h = seg.get(..6).ok_or("the frame header is cut short")?;
                let precision = h[0];
                let y = usize::from(u16::from_be_bytes([h[1], h[2]]));
                let x = usize::from(u16::from_be_bytes([h[3], h[4]]));
                let nf = h[5];
                if precision != 12 {
                    return Err(format!("{precision}-bit samples in a 12-bit decoder"));
                }
                if nf != 1 {
                    return Err(format!(
                        "{nf} components: colour 12-bit JPEG is not supported, grey images are"
                    ));
                }
                if (y, x) != (rows, columns) {
                    return Err(format!(
                        "the JPEG frame is {x}×{y}, the DICOM image {columns}×{rows}"
                    ));
                }
                let c = seg.get(6..9).ok_or("the frame header is cut short")?;
                let tq = usize::from(c[2]);
                if tq > 3 {
                    return Err("a component names no quantisation table".into());
                }
                frame = Some((c[0], tq));
            }
            0xC0 | 0xC2 | 0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF => {
                return Err(format!(
                    "a frame of kind SOF{} (only 12-bit sequential DCT, SOF1, is decoded here)",
                    m - 0xC0
                ));
            }
            0xDA => {
                let (id, tq) = frame.ok_or("a scan before the frame header")?;
                if image.is_some() {
                    return Err("more than one scan (progressive or multi-scan data)".into());
                }
                let seg = r.segment()?;
                let ns = *seg.first().ok_or("the scan header is cut short")?;
                let s = seg.get(1..6).ok_or("the scan header is cut short")?;
                if ns != 1 || s[0] != id {
                    return Err("the scan does not code the frame's one component".into());
                }
                let (td, ta) = (usize::from(s[1] >> 4), usize::from(s[1] & 15));
                // Ss, Se, Ah and Al are 0, 63, 0, 0 in a sequential scan; other values are decoded as
                // sequential all the same, as the IJG library (and DCMTK with it) does after a warning.
                let q = quant
                    .get(tq)
                    .copied()
                    .flatten()
                    .ok_or("the quantisation table of the frame is missing")?;
                let dct = dc
                    .get(td)
                    .and_then(|t| t.as_ref())
                    .ok_or("the scan's DC Huffman table is missing")?;
                let act = ac
                    .get(ta)
                    .and_then(|t| t.as_ref())
                    .ok_or("the scan's AC Huffman table is missing")?;
                let mut bits = Bits::new(&r.d[r.p..]);
                let img = scan(&mut bits, rows, columns, &q, dct, act, restart)?;
                r.p += bits.consumed_bytes();
                image = Some(img);
            }
            // DAC (arithmetic conditioning), DHP, EXP, DNL: features this decoder does not have.
            0xCC | 0xDC | 0xDE | 0xDF => {
                return Err(format!("marker FF{m:02X} is not supported"));
            }
            _ => {
                r.segment()?;
            }
        }
    }
    image.ok_or_else(|| "no scan".into())
}

/// Markers and segments of a JPEG stream.
struct Reader<'a> {
    d: &'a [u8],
    p: usize,
}

impl<'a> Reader<'a> {
    /// The next marker: bytes up to an FF skipped, fill FFs skipped, a stuffed FF 00 not a marker.
    fn marker(&mut self) -> Option<u8> {
        let (m, p) = super::jpeg::next_marker(self.d, self.p)?;
        self.p = p;
        Some(m)
    }

    /// The segment after a marker with a length field, without the length.
    fn segment(&mut self) -> Result<&'a [u8], String> {
        let l = self
            .d
            .get(self.p..self.p + 2)
            .ok_or("a marker segment is cut short")?;
        let len = usize::from(u16::from_be_bytes([l[0], l[1]]));
        if len < 2 {
            return Err("a marker segment shorter than its length field".into());
        }
        let seg = self
            .d
            .get(self.p + 2..self.p + len)
            .ok_or("a marker segment is cut short")?;
        self.p += len;
        Ok(seg)
    }

    fn skip_segment(&mut self) -> Option<()> {
        self.segment().ok().map(|_| ())
    }
}
