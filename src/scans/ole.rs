//! Typed reading of the streams of an OLE compound file (Zeiss Xradia `.txrm` / `.xrm`) through the `cfb`
//! crate. Streams are named by their path (`ImageInfo/Angles`; compared without regard to case, as the
//! compound file format does); every value taken is recorded as [`Provenance`] (`file stream`), and every
//! error names the file and the stream. A stream's length is checked before anything sized by it is
//! allocated; values are little-endian.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use cfb::CompoundFile;

use super::{Provenance, ScanError};

/// The first 8 bytes of every OLE compound file.
pub const SIGNATURE: [u8; 8] = [0xD0, 0xCF, 0x11, 0xE0, 0xA1, 0xB1, 0x1A, 0xE1];

/// An open compound file and the values taken from it so far.
pub struct OleFile {
    pub file: PathBuf,
    ole: CompoundFile<File>,
    /// The values read so far, with their origin (`<file name> <stream>`).
    pub taken: Vec<Provenance>,
}

impl OleFile {
    /// Open `file`; a file without the compound file signature is [`ScanError::NotAScan`], one with it that
    /// fails to parse is [`ScanError::Io`].
    pub fn open(file: &Path) -> Result<Self, ScanError> {
        let mut f = File::open(file).map_err(|e| ScanError::io(file, e))?;
        let mut head = [0u8; 8];
        let n = read_up_to(&mut f, &mut head).map_err(|e| ScanError::io(file, e))?;
        if n < head.len() || head != SIGNATURE {
            return Err(ScanError::NotAScan {
                path: file.to_path_buf(),
                why: "not an OLE compound file (a Zeiss .txrm/.xrm starts with D0 CF 11 E0 A1 B1 1A E1)"
                    .into(),
            });
        }
        f.seek(SeekFrom::Start(0))
            .map_err(|e| ScanError::io(file, e))?;
        // The signature is there: a file that then fails to parse is a damaged compound file.
        let ole = CompoundFile::open(f).map_err(|e| {
            ScanError::io(
                file,
                std::io::Error::new(e.kind(), format!("a damaged OLE compound file: {e}")),
            )
        })?;
        Ok(Self {
            file: file.to_path_buf(),
            ole,
            taken: Vec::new(),
        })
    }

    fn origin(&self, stream: &str) -> String {
        let name = self.file.file_name().map_or_else(
            || self.file.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        format!("{name} {stream}")
    }

    /// Whether the file has a storage (folder) of this name.
    pub fn has_storage(&self, name: &str) -> bool {
        self.ole.is_storage(name)
    }

    /// The length of stream `stream` in bytes; `None` when there is no such stream.
    pub fn len(&self, stream: &str) -> Option<u64> {
        if !self.ole.is_stream(stream) {
            return None;
        }
        self.ole.entry(stream).ok().map(|e| e.len())
    }

    pub fn missing(&self, stream: &str) -> ScanError {
        ScanError::Missing {
            file: self.file.clone(),
            key: stream.to_string(),
        }
    }

    /// Record `value` as taken from `stream`.
    pub fn record(&mut self, stream: &str, value: String) {
        let origin = self.origin(stream);
        self.taken.push(Provenance {
            key: stream.to_string(),
            value,
            origin,
        });
    }

    /// Read the first `buf.len()` bytes of `stream` (its length checked by the caller) into `buf`. An I/O
    /// error names the stream.
    pub fn read_into(&mut self, stream: &str, buf: &mut [u8]) -> Result<(), ScanError> {
        let named = |e: std::io::Error| {
            ScanError::io(
                &self.file,
                std::io::Error::new(e.kind(), format!("stream {stream}: {e}")),
            )
        };
        let mut s = self.ole.open_stream(stream).map_err(named)?;
        s.read_exact(buf).map_err(named)
    }

    /// The first 4 bytes of `stream` (a scalar); `None` when the stream is absent. A stream shorter than
    /// 4 bytes is [`ScanError::Invalid`].
    fn first_word(&mut self, stream: &str) -> Result<Option<[u8; 4]>, ScanError> {
        let Some(len) = self.len(stream) else {
            return Ok(None);
        };
        if len < 4 {
            return Err(ScanError::invalid(
                &self.file,
                stream,
                &format!("{len} bytes"),
                "a 4-byte value was expected",
            ));
        }
        let mut word = [0u8; 4];
        self.read_into(stream, &mut word)?;
        Ok(Some(word))
    }

    /// A 32-bit integer (the first value of the stream), recorded; `None` when absent.
    pub fn int(&mut self, stream: &str) -> Result<Option<i64>, ScanError> {
        let Some(w) = self.first_word(stream)? else {
            return Ok(None);
        };
        // Xradia writes counts as int32 or uint32: both agree below 2^31, larger values are refused.
        let v = i64::from(i32::from_le_bytes(w));
        self.record(stream, v.to_string());
        Ok(Some(v))
    }

    /// A required count in `1..=max`.
    pub fn count(&mut self, stream: &str, max: usize) -> Result<usize, ScanError> {
        let v = self.int(stream)?.ok_or_else(|| self.missing(stream))?;
        match usize::try_from(v) {
            Ok(n) if (1..=max).contains(&n) => Ok(n),
            _ => Err(ScanError::invalid(
                &self.file,
                stream,
                &v.to_string(),
                format!("must be between 1 and {max}"),
            )),
        }
    }

    /// A finite 32-bit float (the first value of the stream), recorded; `None` when absent.
    pub fn float(&mut self, stream: &str) -> Result<Option<f64>, ScanError> {
        let Some(w) = self.first_word(stream)? else {
            return Ok(None);
        };
        let v = f64::from(f32::from_le_bytes(w));
        if !v.is_finite() {
            return Err(ScanError::invalid(
                &self.file,
                stream,
                &v.to_string(),
                "not a finite number",
            ));
        }
        self.record(stream, v.to_string());
        Ok(Some(v))
    }

    /// The first `n` of the 32-bit floats of `stream`, which must hold at least `n` and at most `max`
    /// values (a scan stopped early keeps the arrays of the images it planned); `None` when absent. Not
    /// recorded: the caller records a summary.
    pub fn floats(
        &mut self,
        stream: &str,
        n: usize,
        max: usize,
        count_key: &str,
    ) -> Result<Option<Vec<f64>>, ScanError> {
        let Some(len) = self.len(stream) else {
            return Ok(None);
        };
        let values = len / 4;
        if len % 4 != 0 || values < n as u64 || values > max.max(n) as u64 {
            return Err(ScanError::mismatch(
                &self.file,
                count_key,
                format!(
                    "{count_key} = {n}, but {stream} holds {len} bytes ({} 32-bit values{})",
                    values,
                    if max > n {
                        format!("; between {n} and {max} were expected")
                    } else {
                        String::new()
                    }
                ),
            ));
        }
        let mut bytes = vec![0u8; n * 4];
        self.read_into(stream, &mut bytes)?;
        let out: Vec<f64> = bytes
            .chunks_exact(4)
            .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
            .collect();
        if let Some(k) = out.iter().position(|v| !v.is_finite()) {
            return Err(ScanError::invalid(
                &self.file,
                stream,
                &out[k].to_string(),
                format!("value {k} is not a finite number"),
            ));
        }
        Ok(Some(out))
    }

    /// Record a summary of an array taken from `stream`: `n values, first … last`.
    pub fn record_array(&mut self, stream: &str, values: &[f64], unit: &str) {
        let text = match (values.first(), values.last()) {
            (Some(a), Some(b)) => format!("{} values, {a} … {b}{unit}", values.len()),
            _ => "no values".into(),
        };
        self.record(stream, text);
    }
}

/// Read up to `buf.len()` bytes (fewer only at the end of the file).
fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}
