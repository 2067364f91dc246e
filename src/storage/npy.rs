//! NumPy `.npy` files: a strict header parser, a streaming validator for uploads, a reader that converts
//! float32/float64/uint16 to f32, and a float32 writer.
//!
//! Accepted: format versions 1–3, C order, dtypes `f4`, `f8`, `u2` in either byte order, any shape.
//! Sizes read from a header are checked against limits before anything is allocated.

use ndarray::{ArrayD, ArrayView, Dimension, IxDyn};
use sha2::{Digest, Sha256};

const MAGIC: &[u8; 6] = b"\x93NUMPY";
/// Largest header (dictionary) length accepted.
pub const MAX_HEADER_LEN: usize = 1 << 16;

/// Element type of an accepted array.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    F32,
    F64,
    U16,
}

impl Dtype {
    /// The API name: `float32`, `float64`, `uint16`.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F32 => "float32",
            Dtype::F64 => "float64",
            Dtype::U16 => "uint16",
        }
    }
    pub fn item_bytes(self) -> usize {
        match self {
            Dtype::F32 => 4,
            Dtype::F64 => 8,
            Dtype::U16 => 2,
        }
    }
}

/// A parsed `.npy` header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyHeader {
    pub dtype: Dtype,
    pub big_endian: bool,
    pub shape: Vec<usize>,
    /// Bytes before the data: magic, version, length field and dictionary.
    pub data_offset: usize,
}

impl NpyHeader {
    /// Number of elements, `None` on overflow.
    pub fn elements(&self) -> Option<u64> {
        self.shape
            .iter()
            .try_fold(1u64, |acc, &n| acc.checked_mul(n as u64))
    }
    /// Size of the whole file the header declares, `None` on overflow.
    pub fn file_bytes(&self) -> Option<u64> {
        self.elements()?
            .checked_mul(self.dtype.item_bytes() as u64)?
            .checked_add(self.data_offset as u64)
    }
    /// Convert one element's bytes to f32.
    fn value(&self, b: &[u8]) -> f32 {
        let be = self.big_endian;
        match self.dtype {
            Dtype::F32 => {
                let a = [b[0], b[1], b[2], b[3]];
                if be {
                    f32::from_be_bytes(a)
                } else {
                    f32::from_le_bytes(a)
                }
            }
            Dtype::F64 => {
                let a = [b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]];
                (if be {
                    f64::from_be_bytes(a)
                } else {
                    f64::from_le_bytes(a)
                }) as f32
            }
            Dtype::U16 => {
                let a = [b[0], b[1]];
                (if be {
                    u16::from_be_bytes(a)
                } else {
                    u16::from_le_bytes(a)
                }) as f32
            }
        }
    }
    /// True when one element's bytes hold a finite value (also after conversion to f32).
    fn finite(&self, b: &[u8]) -> bool {
        self.value(b).is_finite()
    }
}

/// What is wrong with a `.npy` file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NpyError {
    #[error("malformed .npy: {0}")]
    Malformed(String),
    #[error("unsupported dtype `{0}`: use float32 (<f4), float64 (<f8) or uint16 (<u2)")]
    UnsupportedDtype(String),
    #[error(
        "Fortran-ordered arrays are not supported: save a C-ordered array (np.ascontiguousarray)"
    )]
    FortranOrder,
    #[error("the file has {got} bytes, the header declares {expected}")]
    Length { expected: u64, got: u64 },
}

fn malformed(s: impl Into<String>) -> NpyError {
    NpyError::Malformed(s.into())
}

/// Parse a header from the start of `buf`; `Ok(None)` when more bytes are needed.
pub fn parse_header(buf: &[u8]) -> Result<Option<NpyHeader>, NpyError> {
    let n = buf.len().min(MAGIC.len());
    if buf[..n] != MAGIC[..n] {
        return Err(malformed("missing the \\x93NUMPY magic"));
    }
    if buf.len() < 8 {
        return Ok(None);
    }
    let (len_bytes, len) = match buf[6] {
        1 => {
            if buf.len() < 10 {
                return Ok(None);
            }
            (2, u16::from_le_bytes([buf[8], buf[9]]) as usize)
        }
        2 | 3 => {
            if buf.len() < 12 {
                return Ok(None);
            }
            (
                4,
                u32::from_le_bytes([buf[8], buf[9], buf[10], buf[11]]) as usize,
            )
        }
        v => return Err(malformed(format!("unknown format version {v}"))),
    };
    if len > MAX_HEADER_LEN {
        return Err(malformed(format!(
            "header length {len} exceeds {MAX_HEADER_LEN}"
        )));
    }
    let start = 8 + len_bytes;
    if buf.len() < start + len {
        return Ok(None);
    }
    let text = std::str::from_utf8(&buf[start..start + len])
        .map_err(|_| malformed("the header is not text"))?;
    let (descr, fortran, shape) = Dict::new(text).parse()?;
    if fortran {
        return Err(NpyError::FortranOrder);
    }
    let (big_endian, code) = match descr.as_bytes().first() {
        Some(b'<') | Some(b'=') => (false, &descr[1..]),
        Some(b'>') => (true, &descr[1..]),
        Some(b'|') => (false, &descr[1..]),
        _ => (false, descr.as_str()),
    };
    let dtype = match code {
        "f4" => Dtype::F32,
        "f8" => Dtype::F64,
        "u2" => Dtype::U16,
        _ => return Err(NpyError::UnsupportedDtype(descr)),
    };
    Ok(Some(NpyHeader {
        dtype,
        big_endian,
        shape,
        data_offset: start + len,
    }))
}

/// A cursor over the header's Python dictionary literal.
struct Dict<'a> {
    s: &'a [u8],
    i: usize,
}

impl<'a> Dict<'a> {
    fn new(text: &'a str) -> Self {
        Self {
            s: text.as_bytes(),
            i: 0,
        }
    }
    fn ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }
    fn eat(&mut self, c: u8) -> bool {
        self.ws();
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }
    fn expect(&mut self, c: u8) -> Result<(), NpyError> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(malformed(format!(
                "expected `{}` at header byte {}",
                c as char, self.i
            )))
        }
    }
    fn string(&mut self) -> Result<String, NpyError> {
        self.ws();
        let q = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(malformed("expected a quoted string in the header")),
        };
        self.i += 1;
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i] != q {
            self.i += 1;
        }
        if self.i >= self.s.len() {
            return Err(malformed("unterminated string in the header"));
        }
        let out = String::from_utf8_lossy(&self.s[start..self.i]).into_owned();
        self.i += 1;
        Ok(out)
    }
    fn word(&mut self) -> &'a [u8] {
        self.ws();
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i].is_ascii_alphanumeric() {
            self.i += 1;
        }
        &self.s[start..self.i]
    }
    fn shape(&mut self) -> Result<Vec<usize>, NpyError> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        loop {
            if self.eat(b')') {
                return Ok(dims);
            }
            let w = self.word();
            let n = std::str::from_utf8(w)
                .ok()
                .and_then(|t| t.parse::<usize>().ok())
                .ok_or_else(|| malformed("shape entries must be non-negative integers"))?;
            dims.push(n);
            if dims.len() > 32 {
                return Err(malformed("more than 32 dimensions"));
            }
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(dims);
            }
        }
    }
    fn parse(mut self) -> Result<(String, bool, Vec<usize>), NpyError> {
        self.expect(b'{')?;
        let (mut descr, mut fortran, mut shape) = (None, None, None);
        loop {
            if self.eat(b'}') {
                break;
            }
            let key = self.string()?;
            self.expect(b':')?;
            match key.as_str() {
                "descr" if descr.is_none() => descr = Some(self.string()?),
                "fortran_order" if fortran.is_none() => {
                    fortran = Some(match self.word() {
                        b"True" => true,
                        b"False" => false,
                        _ => return Err(malformed("fortran_order must be True or False")),
                    })
                }
                "shape" if shape.is_none() => shape = Some(self.shape()?),
                _ => return Err(malformed(format!("unexpected or repeated key `{key}`"))),
            }
            if !self.eat(b',') {
                self.expect(b'}')?;
                break;
            }
        }
        self.ws();
        if self.i != self.s.len() {
            return Err(malformed("trailing characters after the header dictionary"));
        }
        match (descr, fortran, shape) {
            (Some(d), Some(f), Some(s)) => Ok((d, f, s)),
            _ => Err(malformed(
                "the header needs `descr`, `fortran_order` and `shape`",
            )),
        }
    }
}

/// Limits a streamed upload is checked against as soon as its header is known.
#[derive(Debug, Clone, Copy)]
pub struct StreamLimits {
    /// Most bytes of the whole file.
    pub max_file_bytes: u64,
    /// Most elements (bounds the f32 copy a job makes).
    pub max_elements: u64,
}

/// Why a streamed upload is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StreamError {
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("the array has shape {got:?}, the geometry expects {expected:?}")]
    ShapeMismatch {
        expected: Vec<usize>,
        got: Vec<usize>,
    },
    #[error("the header declares {declared} bytes ({what}), more than the limit of {limit}")]
    TooLarge {
        what: &'static str,
        declared: u64,
        limit: u64,
    },
    #[error("the body has more bytes than the header declares ({expected})")]
    TrailingBytes { expected: u64 },
    #[error("the upload ended after {got} of {expected} bytes")]
    Truncated { expected: u64, got: u64 },
    #[error("the data contain a non-finite value at flat index {index}")]
    NonFinite { index: u64 },
}

/// Validates an upload chunk by chunk: header, limits, expected shape, finiteness, exact length; and
/// hashes it (SHA-256). The caller writes each accepted chunk to disk.
pub struct NpyStream {
    limits: StreamLimits,
    expected_shape: Option<Vec<usize>>,
    head: Vec<u8>,
    header: Option<NpyHeader>,
    total: u64,
    carry: Vec<u8>,
    index: u64,
    sha: Sha256,
}

impl NpyStream {
    pub fn new(limits: StreamLimits, expected_shape: Option<Vec<usize>>) -> Self {
        Self {
            limits,
            expected_shape,
            head: Vec::new(),
            header: None,
            total: 0,
            carry: Vec::new(),
            index: 0,
            sha: Sha256::new(),
        }
    }

    /// The header, once enough bytes have arrived.
    pub fn header(&self) -> Option<&NpyHeader> {
        self.header.as_ref()
    }

    fn accept_header(&mut self, h: &NpyHeader) -> Result<(), StreamError> {
        if let Some(expected) = &self.expected_shape
            && *expected != h.shape
        {
            return Err(StreamError::ShapeMismatch {
                expected: expected.clone(),
                got: h.shape.clone(),
            });
        }
        let elements = h.elements().unwrap_or(u64::MAX);
        if elements > self.limits.max_elements {
            return Err(StreamError::TooLarge {
                what: "elements",
                declared: elements,
                limit: self.limits.max_elements,
            });
        }
        let bytes = h.file_bytes().unwrap_or(u64::MAX);
        if bytes > self.limits.max_file_bytes {
            return Err(StreamError::TooLarge {
                what: "file bytes",
                declared: bytes,
                limit: self.limits.max_file_bytes,
            });
        }
        Ok(())
    }

    fn scan_data(&mut self, mut data: &[u8]) -> Result<(), StreamError> {
        let Some(h) = self.header.clone() else {
            return Ok(());
        };
        let item = h.dtype.item_bytes();
        if h.dtype == Dtype::U16 {
            return Ok(());
        }
        if !self.carry.is_empty() {
            let need = item - self.carry.len();
            let take = need.min(data.len());
            self.carry.extend_from_slice(&data[..take]);
            data = &data[take..];
            if self.carry.len() < item {
                return Ok(());
            }
            if !h.finite(&self.carry) {
                return Err(StreamError::NonFinite { index: self.index });
            }
            self.index += 1;
            self.carry.clear();
        }
        let whole = data.len() / item * item;
        for (k, e) in data[..whole].chunks_exact(item).enumerate() {
            if !h.finite(e) {
                return Err(StreamError::NonFinite {
                    index: self.index + k as u64,
                });
            }
        }
        self.index += (whole / item) as u64;
        self.carry.extend_from_slice(&data[whole..]);
        Ok(())
    }

    /// Take the next chunk of the body.
    pub fn feed(&mut self, chunk: &[u8]) -> Result<(), StreamError> {
        self.total += chunk.len() as u64;
        self.sha.update(chunk);
        match &self.header {
            Some(h) => {
                let expected = h.file_bytes().unwrap_or(u64::MAX);
                if self.total > expected {
                    return Err(StreamError::TrailingBytes { expected });
                }
                self.scan_data(chunk)
            }
            None => {
                self.head.extend_from_slice(chunk);
                match parse_header(&self.head)? {
                    None => {
                        if self.head.len() > MAX_HEADER_LEN + 12 {
                            return Err(malformed("header too long").into());
                        }
                        Ok(())
                    }
                    Some(h) => {
                        self.accept_header(&h)?;
                        let expected = h.file_bytes().unwrap_or(u64::MAX);
                        if self.total > expected {
                            return Err(StreamError::TrailingBytes { expected });
                        }
                        let rest = std::mem::take(&mut self.head);
                        let offset = h.data_offset;
                        self.header = Some(h);
                        self.scan_data(&rest[offset..])
                    }
                }
            }
        }
    }

    /// Check the upload is complete: `(header, total bytes, sha256 hex)`.
    pub fn finish(self) -> Result<(NpyHeader, u64, String), StreamError> {
        let Some(h) = self.header else {
            return Err(if self.total == 0 {
                malformed("empty body").into()
            } else {
                StreamError::Truncated {
                    expected: 0,
                    got: self.total,
                }
            });
        };
        let expected = h.file_bytes().unwrap_or(u64::MAX);
        if self.total < expected {
            return Err(StreamError::Truncated {
                expected,
                got: self.total,
            });
        }
        Ok((h, self.total, hex(&self.sha.finalize())))
    }
}

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

/// Encode `array` as a little-endian float32 `.npy` (format 1.0, C order).
pub fn encode_f32<D: Dimension>(array: ArrayView<'_, f32, D>) -> Vec<u8> {
    let dims: Vec<String> = array.shape().iter().map(|n| n.to_string()).collect();
    let shape = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic (6) + version (2) + length (2) + dict + '\n' is a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len() + array.len() * 4);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    for v in array.iter() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use ndarray::Array3;

    use super::*;

    fn npy(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
        let dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}\n");
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        out.extend_from_slice(dict.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn limits() -> StreamLimits {
        StreamLimits {
            max_file_bytes: 1 << 20,
            max_elements: 1 << 16,
        }
    }

    #[test]
    fn an_encoded_array_decodes_to_the_same_values_and_aligns_its_data() {
        let a = Array3::from_shape_fn((2, 3, 5), |(i, j, k)| (i * 100 + j * 10 + k) as f32 - 7.5);
        let bytes = encode_f32(a.view());
        let h = parse_header(&bytes).unwrap().unwrap();
        assert_eq!(h.data_offset % 64, 0);
        assert_eq!(h.shape, [2, 3, 5]);
        assert_eq!(decode_f32(&bytes).unwrap(), a.into_dyn());
    }

    #[test]
    fn float64_and_big_endian_uint16_convert_to_f32() {
        let d: Vec<u8> = [1.5f64, -2.25]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let a = decode_f32(&npy("<f8", "(2,)", &d)).unwrap();
        assert_eq!(a.as_slice().unwrap(), &[1.5, -2.25]);
        let d: Vec<u8> = [300u16, 7].iter().flat_map(|v| v.to_be_bytes()).collect();
        let a = decode_f32(&npy(">u2", "(1, 2)", &d)).unwrap();
        assert_eq!(a.as_slice().unwrap(), &[300.0, 7.0]);
    }

    #[test]
    fn malformed_and_unsupported_headers_are_named() {
        assert!(matches!(
            parse_header(b"NUMPY\x01\x00"),
            Err(NpyError::Malformed(_))
        ));
        assert!(matches!(
            parse_header(&npy("<i8", "(2,)", &[0; 16])),
            Err(NpyError::UnsupportedDtype(d)) if d == "<i8"
        ));
        let f = npy("<f4", "(2,)", &[0; 8]);
        let at = f
            .windows(5)
            .position(|w| w == b"False")
            .expect("the header names fortran_order");
        let mut fortran = f.clone();
        fortran[at..at + 5].copy_from_slice(b"True ");
        assert_eq!(parse_header(&fortran), Err(NpyError::FortranOrder));
        assert!(matches!(
            parse_header(&npy("<f4", "(2, -1)", &[])),
            Err(NpyError::Malformed(_))
        ));
        assert_eq!(parse_header(&f[..20]), Ok(None));
    }

    #[test]
    fn a_stream_checks_shape_size_finiteness_and_length_across_chunk_boundaries() {
        let values = [1.0f32, 2.0, f32::NAN, 4.0];
        let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let file = npy("<f4", "(2, 2)", &data);
        // NaN at flat index 2 is found even when chunks split elements.
        let mut s = NpyStream::new(limits(), Some(vec![2, 2]));
        let err = file.chunks(3).try_for_each(|c| s.feed(c));
        assert_eq!(err, Err(StreamError::NonFinite { index: 2 }));

        let good: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let file = npy("<f4", "(2, 2)", &good);
        let mut s = NpyStream::new(limits(), Some(vec![2, 2]));
        file.chunks(5).try_for_each(|c| s.feed(c)).unwrap();
        let (h, n, sha) = s.finish().unwrap();
        assert_eq!((h.shape, n, sha.len()), (vec![2, 2], file.len() as u64, 64));

        let mut s = NpyStream::new(limits(), Some(vec![4]));
        assert!(matches!(
            s.feed(&file),
            Err(StreamError::ShapeMismatch { .. })
        ));
        let mut s = NpyStream::new(limits(), None);
        s.feed(&file[..file.len() - 1]).unwrap();
        assert!(matches!(s.finish(), Err(StreamError::Truncated { .. })));
        let mut s = NpyStream::new(limits(), None);
        let mut long = file.clone();
        long.push(0);
        assert!(matches!(
            s.feed(&long),
            Err(StreamError::TrailingBytes { .. })
        ));
        let huge = npy("<f4", "(100000, 100000)", &[]);
        let mut s = NpyStream::new(limits(), None);
        assert!(matches!(s.feed(&huge), Err(StreamError::TooLarge { .. })));
    }
}
