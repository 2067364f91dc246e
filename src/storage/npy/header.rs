//! The `.npy` header: the magic, the format version (1–3), the length field and the dictionary, parsed
//! strictly into an [`NpyHeader`] (dtype `f4`, `f8` or `u2` in either byte order, C order, any shape);
//! and the conversion of one element's bytes to f32.

use super::MAGIC;
use super::literal::Dict;

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
    pub(super) fn value(&self, b: &[u8]) -> f32 {
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
    pub(super) fn finite(&self, b: &[u8]) -> bool {
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

pub(super) fn malformed(s: impl Into<String>) -> NpyError {
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
