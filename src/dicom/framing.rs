//! How the bytes of one upload are framed as DICOM, checked and put in the one shape the parser reads:
//! `DICM`, a file meta group that starts with its group length, then the data set, nothing after it.
//!
//! Peers (pydicom, DCMTK, Orthanc) read more than the strict Part 10 layout, and so does this:
//! - the 128-byte preamble is optional (`DICM` first);
//! - a file meta group without its group length (0002,0000) is given one;
//! - a raw data set (no preamble, no `DICM`, no meta group, as pydicom reads with `force=True`) has its
//!   encoding guessed from its first element (explicit VR when bytes 4–5 are a known VR, big endian when
//!   the first group reads smaller that way) and a meta group naming that transfer syntax;
//! - zero bytes or Data Set Trailing Padding (FFFC,FFFC) after the data set are dropped.
//!
//! A deflated data set is inflated here, up to a limit, walked like any other and handed to the parser as
//! explicit VR little endian (the instance still reports the deflated transfer syntax).
//!
//! Every framing goes through [`scan`]'s walk first, so no declared length that overruns the file and no
//! nesting deeper than [`scan::MAX_SEQUENCE_DEPTH`] reaches the parser.

use std::borrow::Cow;

use dicom_core::VR;

use super::scan::{self, Defect, Encoding};

/// What went wrong before parsing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum FramingError {
    /// Neither a Part 10 file nor a plausible raw data set.
    NotDicom,
    /// A length, depth or structure defect found by the walk.
    Defect(Defect),
}

impl From<Defect> for FramingError {
    fn from(d: Defect) -> Self {
        FramingError::Defect(d)
    }
}

/// The bytes to parse, starting at `DICM`, and how they were reframed (for warnings).
#[derive(Debug)]
pub(super) struct Framed<'a> {
    pub bytes: Cow<'a, [u8]>,
    /// The transfer syntax written in (or guessed for) the meta group.
    pub transfer_syntax: String,
    /// The file had no `DICM` marker: its encoding was guessed.
    pub raw_dataset: bool,
    /// Bytes dropped after the data set.
    pub trailing_bytes: usize,
}

const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
const EXPLICIT_BE: &str = "1.2.840.10008.1.2.2";

const DEFLATED: &str = "1.2.840.10008.1.2.1.99";

/// Frame `bytes` for the parser; a deflated data set may inflate to at most `max_inflated` bytes.
pub(super) fn frame(bytes: &[u8], max_inflated: usize) -> Result<Framed<'_>, FramingError> {
    if bytes.len() >= 132 && &bytes[128..132] == b"DICM" {
        part10(&bytes[128..], max_inflated)
    } else if bytes.len() >= 4 && &bytes[..4] == b"DICM" {
        part10(bytes, max_inflated)
    } else {
        raw(bytes, max_inflated)
    }
}

/// `d` starts at `DICM`.
fn part10(d: &[u8], max_inflated: usize) -> Result<Framed<'_>, FramingError> {
    let after = &d[4..];
    let meta = scan::meta(after)?;
    let data = after.get(meta.end..).unwrap_or_default();
    if meta.transfer_syntax == DEFLATED {
        return deflated(&after[..meta.end], data, max_inflated);
    }
    let kept = match Encoding::of(&meta.transfer_syntax) {
        Some(enc) => scan::dataset(data, enc)?,
        None => data.len(),
    };
    let trailing_bytes = data.len() - kept;
    let bytes = if meta.group_length {
        Cow::Borrowed(&d[..4 + meta.end + kept])
    } else {
        let mut out = Vec::with_capacity(16 + meta.end + kept);
        out.extend_from_slice(b"DICM");
        push_group_length(&mut out, meta.end);
        out.extend_from_slice(&after[..meta.end + kept]);
        Cow::Owned(out)
    };
    Ok(Framed {
        bytes,
        transfer_syntax: meta.transfer_syntax,
        raw_dataset: false,
        trailing_bytes,
    })
}

/// (0002,0000) UL, explicit VR little endian.
fn push_group_length(out: &mut Vec<u8>, len: usize) {
    out.extend_from_slice(&[0x02, 0x00, 0x00, 0x00, b'U', b'L', 4, 0]);
    out.extend_from_slice(&(len as u32).to_le_bytes());
}

/// A data set with no marker: a meta group alone (group 0002 first) or a bare data set whose encoding is
/// guessed from its first element.
fn raw(d: &[u8], max_inflated: usize) -> Result<Framed<'_>, FramingError> {
    if d.len() < 8 {
        return Err(FramingError::NotDicom);
    }
    let (le, be) = (
        u16::from_le_bytes([d[0], d[1]]),
        u16::from_be_bytes([d[0], d[1]]),
    );
    if le == 0x0002 {
        let mut with_marker = Vec::with_capacity(4 + d.len());
        with_marker.extend_from_slice(b"DICM");
        with_marker.extend_from_slice(d);
        let f = part10(&with_marker, max_inflated)?;
        return Ok(Framed {
            bytes: Cow::Owned(f.bytes.into_owned()),
            transfer_syntax: f.transfer_syntax,
            raw_dataset: false,
            trailing_bytes: f.trailing_bytes,
        });
    }
    let big = be < le;
    let group = le.min(be);
    // A data set opens with a low, even, public group (0008 in practice); anything else is not DICOM.
    if !(0x0004..=0x0028).contains(&group) || group % 2 != 0 {
        return Err(FramingError::NotDicom);
    }
    let explicit = VR::from_binary([d[4], d[5]]).is_some();
    let (ts, enc) = match (explicit, big) {
        (true, false) => (EXPLICIT_LE, Encoding::of(EXPLICIT_LE)),
        (false, false) => (IMPLICIT_LE, Encoding::of(IMPLICIT_LE)),
        (true, true) => (EXPLICIT_BE, Encoding::of(EXPLICIT_BE)),
        // Implicit VR big endian was never a transfer syntax.
        (false, true) => return Err(FramingError::NotDicom),
    };
    let enc = enc.ok_or(FramingError::NotDicom)?;
    let kept = scan::dataset(d, enc)?;
    let mut uid = ts.as_bytes().to_vec();
    if uid.len() % 2 == 1 {
        uid.push(0);
    }
    let meta_len = 8 + uid.len();
    let mut out = Vec::with_capacity(4 + 12 + meta_len + kept);
    out.extend_from_slice(b"DICM");
    push_group_length(&mut out, meta_len);
    out.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I']);
    out.extend_from_slice(&(uid.len() as u16).to_le_bytes());
    out.extend_from_slice(&uid);
    out.extend_from_slice(&d[..kept]);
    Ok(Framed {
        bytes: Cow::Owned(out),
        transfer_syntax: ts.to_string(),
        raw_dataset: true,
        trailing_bytes: d.len() - kept,
    })
}

/// Inflate a deflated data set (raw deflate, PS3.5 A.5) up to `max_inflated` bytes, walk it, and frame it with
/// the meta group's elements and an explicit VR little endian transfer syntax. A first pass only counts the
/// inflated bytes (through a small scratch buffer, stopping one past the limit); the second inflates straight
/// into a framed buffer of exactly that size. Memory never holds more than the inflated data set and the meta
/// group, and nothing at all is allocated for a stream that inflates past the limit.
fn deflated(
    meta: &[u8],
    data: &[u8],
    max_inflated: usize,
) -> Result<Framed<'static>, FramingError> {
    use std::io::Read;
    let inflater = || flate2::read::DeflateDecoder::new(data).take(max_inflated as u64 + 1);
    let inflated = std::io::copy(&mut inflater(), &mut std::io::sink())
        .map_err(|_| FramingError::Defect(Defect::Inflate))?;
    if inflated > max_inflated as u64 {
        return Err(FramingError::Defect(Defect::InflatesTooFar {
            limit: max_inflated,
        }));
    }
    let inflated = inflated as usize;
    let mut elements = scan::meta_elements(meta)
        .into_iter()
        .filter(|&(tag, _)| tag != (0x0002, 0x0000) && tag != (0x0002, 0x0010))
        .flat_map(|(_, bytes)| bytes.to_vec())
        .collect::<Vec<u8>>();
    let mut uid = EXPLICIT_LE.as_bytes().to_vec();
    uid.push(0);
    elements.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I']);
    elements.extend_from_slice(&(uid.len() as u16).to_le_bytes());
    elements.extend_from_slice(&uid);
    let start = 16 + elements.len();
    let mut out = vec![0u8; start + inflated];
    out[..4].copy_from_slice(b"DICM");
    out[4..12].copy_from_slice(&[0x02, 0x00, 0x00, 0x00, b'U', b'L', 4, 0]);
    out[12..16].copy_from_slice(&(elements.len() as u32).to_le_bytes());
    out[16..start].copy_from_slice(&elements);
    drop(elements);
    inflater()
        .read_exact(&mut out[start..])
        .map_err(|_| FramingError::Defect(Defect::Inflate))?;
    let enc = Encoding {
        explicit: true,
        big_endian: false,
    };
    let kept = scan::dataset(&out[start..], enc)?;
    out.truncate(start + kept);
    Ok(Framed {
        bytes: Cow::Owned(out),
        transfer_syntax: DEFLATED.to_string(),
        raw_dataset: false,
        trailing_bytes: inflated - kept,
    })
}
