//! NumPy `.npy` files: a strict header parser, a streaming validator for uploads, a reader that converts
//! float32/float64/uint16 to f32, and a float32 writer.
//!
//! Accepted: format versions 1–3, C order, dtypes `f4`, `f8`, `u2` in either byte order, any shape.
//! Sizes read from a header are checked against limits before anything is allocated.

mod array;
mod header;
mod literal;
mod stream;

pub use array::{decode_f32, encode_f32, f32_header, write_f32};
pub use header::{Dtype, MAX_HEADER_LEN, NpyError, NpyHeader, parse_header};
pub use stream::{NpyStream, StreamError, StreamLimits};

const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Lowercase hexadecimal of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The fuzz targets' entry point (and the regression replay's): a whole-file decode, then the streamed
/// validator fed in 7-byte chunks under 64 MiB limits. Every outcome but a panic is fine.
#[doc(hidden)]
pub fn fuzz_entry(data: &[u8]) {
    let _ = decode_f32(data);
    let mut s = NpyStream::new(
        StreamLimits {
            max_file_bytes: 64 << 20,
            max_elements: 16 << 20,
        },
        None,
    );
    for chunk in data.chunks(7) {
        if s.feed(chunk).is_err() {
            return;
        }
    }
    let _ = s.finish();
}

#[cfg(test)]
mod tests;
