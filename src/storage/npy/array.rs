//! Whole `.npy` files as arrays: decoding to f32 (float64 rounds, uint16 converts exactly) and encoding a
//! float32 array (format 1.0, C order, data aligned to 64 bytes).

use std::io::{self, Write};

use ndarray::{ArrayD, ArrayView, Dimension, IxDyn};
use sha2::{Digest, Sha256};

use super::MAGIC;
use super::header::{NpyError, malformed, parse_header};

/// Decode a whole `.npy` file as an f32 array (float64 rounds, uint16 converts exactly).
pub fn decode_f32(bytes: &[u8]) -> Result<ArrayD<f32>, NpyError> {
    let h = parse_header(bytes)?.ok_or_else(|| malformed("the file ends inside its header"))?;
    let expected = h
        .file_bytes()
        .ok_or_else(|| malformed("the declared size overflows"))?;
    if bytes.len() as u64 != expected {
        return Err(NpyError::Length {
            expected,
            got: bytes.len() as u64,
        });
    }
    let item = h.dtype.item_bytes();
    let values: Vec<f32> = bytes[h.data_offset..]
        .chunks_exact(item)
        .map(|e| h.value(e))
        .collect();
    ArrayD::from_shape_vec(IxDyn(&h.shape), values).map_err(|e| malformed(e.to_string()))
}

/// The header of a little-endian float32 `.npy` of `shape` (format 1.0, C order), padded so that the data
/// start on a 64-byte boundary.
pub fn f32_header(shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|n| n.to_string()).collect();
    let shape = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic (6) + version (2) + length (2) + dict + '\n' is a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// Encode `array` as a little-endian float32 `.npy` (format 1.0, C order).
pub fn encode_f32<D: Dimension>(array: ArrayView<'_, f32, D>) -> Vec<u8> {
    let mut out = f32_header(array.shape());
    out.reserve_exact(array.len() * 4);
    for v in array.iter() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Write `array` as [`encode_f32`] encodes it to `out` through a buffer of 64 KiB (never a second copy of
/// the array in memory); returns the bytes written and their SHA-256 (hex).
pub fn write_f32<D: Dimension>(
    array: ArrayView<'_, f32, D>,
    out: &mut impl Write,
) -> io::Result<(u64, String)> {
    let mut hash = Sha256::new();
    let header = f32_header(array.shape());
    hash.update(&header);
    out.write_all(&header)?;
    let mut written = header.len() as u64;
    let mut buf = Vec::with_capacity(64 << 10);
    for v in array.iter() {
        buf.extend_from_slice(&v.to_le_bytes());
        if buf.len() >= 64 << 10 {
            hash.update(&buf);
            out.write_all(&buf)?;
            written += buf.len() as u64;
            buf.clear();
        }
    }
    hash.update(&buf);
    out.write_all(&buf)?;
    written += buf.len() as u64;
    Ok((written, super::hex(&hash.finalize())))
}
