//! The streaming validator of uploads: a `.npy` body checked chunk by chunk (header, limits, expected
//! shape, finiteness, exact length) and hashed, so that nothing sized by the header is allocated and a bad
//! upload is refused as soon as its first bad byte arrives.

use sha2::{Digest, Sha256};

use super::header::{Dtype, MAX_HEADER_LEN, NpyError, NpyHeader, malformed, parse_header};
use super::hex;

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
