//! A pre-parse walk over element headers that mirrors how dicom-rs will read the same bytes: every declared
//! value length must fit in the bytes that remain and sequences may nest only so deep, so a hostile header
//! can neither make the parser allocate far more memory than the file holds nor recurse until the stack
//! overflows.
//!
//! The walk follows dicom-rs 0.10's rules: the file meta group is read while the bytes consumed are below
//! its group length (0002,0000); in explicit VR, the VRs with a 2-byte length are exactly the 21 of PS3.5
//! Table 7.1-2 and every other VR, unknown ones included, has 2 reserved bytes and a 4-byte length; in
//! implicit VR the data dictionary gives the VR; an undefined length opens a sequence, except on Pixel Data
//! where it opens a run of fragments.

use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry};
use dicom_core::{Tag, VR};
use dicom_dictionary_std::StandardDataDictionary;

/// Deepest nesting of sequences accepted. Real files nest a few levels (Enhanced CT: three or four).
pub(super) const MAX_SEQUENCE_DEPTH: usize = 32;

const UNDEFINED: u32 = u32::MAX;

/// What the walk found wrong before the parser saw it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Defect {
    /// Element (group, element) declares more bytes than remain.
    Overrun {
        tag: (u16, u16),
        declared: u64,
        left: usize,
    },
    /// Element (group, element) of a binary VR declares a length that is not a whole number of its values
    /// (`unit` bytes each). dicom-rs reads `len / unit` values but counts `len` bytes as read, so the parser
    /// and the walk would part ways on where the next element starts.
    Misaligned {
        tag: (u16, u16),
        vr: VR,
        declared: u32,
        unit: u32,
    },
    /// Sequences nest deeper than [`MAX_SEQUENCE_DEPTH`] at element (group, element).
    TooDeep { tag: (u16, u16) },
    /// An item inside encapsulated pixel data has an undefined length.
    UndefinedFragment,
    /// A deflated data set is not a valid deflate stream.
    Inflate,
    /// A deflated data set inflates past the limit (bytes).
    InflatesTooFar { limit: usize },
}

impl std::fmt::Display for Defect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Defect::Overrun {
                tag: (g, e),
                declared,
                left,
            } => write!(
                f,
                "element ({g:04X},{e:04X}) declares {declared} bytes but only {left} remain (truncated or corrupt)"
            ),
            Defect::Misaligned {
                tag: (g, e),
                vr,
                declared,
                unit,
            } => write!(
                f,
                "element ({g:04X},{e:04X}) {vr} declares {declared} bytes, not a multiple of its {unit}-byte values"
            ),
            Defect::TooDeep { tag: (g, e) } => write!(
                f,
                "sequence ({g:04X},{e:04X}) nests deeper than {MAX_SEQUENCE_DEPTH} levels"
            ),
            Defect::UndefinedFragment => {
                write!(f, "a pixel data fragment has an undefined length")
            }
            Defect::Inflate => write!(f, "the deflated data set is not a valid deflate stream"),
            Defect::InflatesTooFar { limit } => {
                write!(
                    f,
                    "the deflated data set inflates to more than {limit} bytes"
                )
            }
        }
    }
}

/// How a data set is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Encoding {
    pub explicit: bool,
    pub big_endian: bool,
}

impl Encoding {
    /// The encoding of a transfer syntax; `None` for a deflated data set (walked after inflation, if at all).
    pub fn of(transfer_syntax: &str) -> Option<Self> {
        match transfer_syntax {
            "1.2.840.10008.1.2" => Some(Self {
                explicit: false,
                big_endian: false,
            }),
            "1.2.840.10008.1.2.2" => Some(Self {
                explicit: true,
                big_endian: true,
            }),
            "1.2.840.10008.1.2.1.99" | "1.2.840.10008.1.2.4.95" => None,
            _ => Some(Self {
                explicit: true,
                big_endian: false,
            }),
        }
    }
}

/// The file meta group as dicom-rs reads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Meta {
    /// Offset of the data set (after the meta group) from the start of the walked bytes.
    pub end: usize,
    /// Transfer syntax UID, trimmed of padding.
    pub transfer_syntax: String,
    /// Whether the group opens with its group length (0002,0000), as dicom-rs requires.
    pub group_length: bool,
}

fn u16_at(d: &[u8], p: usize, big: bool) -> Option<u16> {
    let b = [*d.get(p)?, *d.get(p.checked_add(1)?)?];
    Some(if big {
        u16::from_be_bytes(b)
    } else {
        u16::from_le_bytes(b)
    })
}

fn u32_at(d: &[u8], p: usize, big: bool) -> Option<u32> {
    let b = d.get(p..p.checked_add(4)?)?;
    let b = [b[0], b[1], b[2], b[3]];
    Some(if big {
        u32::from_be_bytes(b)
    } else {
        u32::from_le_bytes(b)
    })
}

/// VRs with a 2-byte length in explicit VR encodings (PS3.5 Table 7.1-2), as dicom-rs decodes them.
fn short_length(vr: [u8; 2]) -> bool {
    matches!(
        &vr,
        b"AE"
            | b"AS"
            | b"AT"
            | b"CS"
            | b"DA"
            | b"DS"
            | b"DT"
            | b"FL"
            | b"FD"
            | b"IS"
            | b"LO"
            | b"LT"
            | b"PN"
            | b"SH"
            | b"SL"
            | b"SS"
            | b"ST"
            | b"TM"
            | b"UI"
            | b"UL"
            | b"US"
    )
}

/// Size in bytes of one value of a binary VR, as dicom-rs reads it (`len / unit` values); 1 for the VRs read
/// as whole byte strings (text, OB, UN, unknown VRs).
fn unit(vr: VR) -> u32 {
    match vr {
        VR::US | VR::SS | VR::OW => 2,
        VR::UL | VR::SL | VR::OL | VR::FL | VR::OF | VR::AT => 4,
        VR::FD | VR::OD | VR::SV | VR::UV | VR::OV => 8,
        _ => 1,
    }
}

/// An element header: tag, VR as the parser resolves it, whether it opens a sequence, value length and
/// header size.
struct Header {
    tag: (u16, u16),
    vr: VR,
    sequence: bool,
    len: u32,
    size: usize,
}

/// The header at `p`; `None` when the bytes end inside it.
fn header(d: &[u8], p: usize, enc: Encoding) -> Option<Header> {
    let big = enc.big_endian;
    let tag = (u16_at(d, p, big)?, u16_at(d, p + 2, big)?);
    if tag.0 == 0xFFFE {
        return Some(Header {
            tag,
            vr: VR::UN,
            sequence: false,
            len: u32_at(d, p + 4, big)?,
            size: 8,
        });
    }
    if enc.explicit {
        let code = [*d.get(p + 4)?, *d.get(p + 5)?];
        let vr = VR::from_binary(code).unwrap_or(VR::UN);
        if short_length(code) {
            Some(Header {
                tag,
                vr,
                sequence: false,
                len: u16_at(d, p + 6, big)? as u32,
                size: 8,
            })
        } else {
            Some(Header {
                tag,
                vr,
                sequence: &code == b"SQ",
                len: u32_at(d, p + 8, big)?,
                size: 12,
            })
        }
    } else {
        // Pixel Data and Overlay Data are OW in implicit VR; other tags take the dictionary's VR, else UN.
        let vr = if tag == (0x7FE0, 0x0010) || (tag.0 >> 8 == 0x60 && tag.1 == 0x3000) {
            VR::OW
        } else {
            StandardDataDictionary
                .by_tag(Tag(tag.0, tag.1))
                .map_or(VR::UN, |e| e.vr().relaxed())
        };
        Some(Header {
            tag,
            vr,
            sequence: vr == VR::SQ,
            len: u32_at(d, p + 4, big)?,
            size: 8,
        })
    }
}

/// Walk the file meta group of `d` (the bytes after the `DICM` marker, explicit VR little endian). With a group
/// length (0002,0000) first, as dicom-rs reads it: elements until that many bytes are consumed. Without one:
/// the elements of group 0002.
pub(super) fn meta(d: &[u8]) -> Result<Meta, Defect> {
    let le = Encoding {
        explicit: true,
        big_endian: false,
    };
    let first = header(d, 0, le);
    let group_length = first
        .as_ref()
        .filter(|h| h.tag == (0x0002, 0x0000) && h.len == 4)
        .and_then(|h| u32_at(d, h.size, false));
    let mut p = match (&first, group_length) {
        (Some(h), Some(_)) => h.size + 4,
        _ => 0,
    };
    let mut consumed: u32 = 0;
    let mut transfer_syntax = String::new();
    // Ending inside a header is left to the parser, which reports the truncation.
    while let Some(h) = header(d, p, le) {
        match group_length {
            Some(g) if consumed >= g => break,
            None if h.tag.0 != 0x0002 => break,
            _ => {}
        }
        let left = d.len().saturating_sub(p + h.size);
        if h.len as usize > left {
            return Err(Defect::Overrun {
                tag: h.tag,
                declared: h.len as u64,
                left,
            });
        }
        let value = &d[p + h.size..p + h.size + h.len as usize];
        if h.tag == (0x0002, 0x0010) {
            transfer_syntax = String::from_utf8_lossy(value)
                .trim_end_matches(['\0', ' '])
                .to_string();
        }
        p += h.size + h.len as usize;
        consumed = consumed.saturating_add(h.size as u32).saturating_add(h.len);
    }
    Ok(Meta {
        end: p,
        transfer_syntax,
        group_length: group_length.is_some(),
    })
}

/// The elements of a walked meta group (`d` up to [`Meta::end`]): tag and the element's bytes, header included.
pub(super) fn meta_elements(d: &[u8]) -> Vec<((u16, u16), &[u8])> {
    let le = Encoding {
        explicit: true,
        big_endian: false,
    };
    let mut out = Vec::new();
    let mut p = 0;
    while let Some(h) = header(d, p, le) {
        let Some(end) = (p + h.size)
            .checked_add(h.len as usize)
            .filter(|&e| e <= d.len())
        else {
            break;
        };
        out.push((h.tag, &d[p..end]));
        p = end;
    }
    out
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Open {
    /// A sequence: items come next.
    Sequence,
    /// An item of a sequence: elements come next.
    Item,
    /// Encapsulated pixel data: fragments come next.
    Fragments,
}

/// Walk a data set (elements, sequences, items and fragments) checking every declared length against the bytes
/// that remain and the nesting depth against [`MAX_SEQUENCE_DEPTH`]. Returns how many bytes to parse: all of
/// them, less trailing padding (zero bytes, or Data Set Trailing Padding (FFFC,FFFC)) after the last element
/// of the top level. Stops without a defect where the bytes end inside a header or where the structure is
/// one the parser refuses by itself.
pub(super) fn dataset(d: &[u8], enc: Encoding) -> Result<usize, Defect> {
    walk(d, enc, |_, _| false).map(|w| w.end)
}

/// Top-level elements as [`leading`] finds them: tag and value bytes.
pub(super) type Leading<'a> = Vec<((u16, u16), &'a [u8])>;

/// The top-level elements of defined length of a data set's leading groups (up to and including
/// `last_group`), walked as [`dataset`] walks them: tag and value bytes, in file order. `Ok(None)` when `d`
/// ends before an element past `last_group` (or Pixel Data) is met: `d` may be a prefix of the data set, and
/// whether a longer one would do is the caller's call. A defect found on the way is a defect of the prefix,
/// which may only mean that it was cut (an [`Defect::Overrun`]).
pub(super) fn leading(
    d: &[u8],
    enc: Encoding,
    last_group: u16,
) -> Result<Option<Leading<'_>>, Defect> {
    let mut elements = Vec::new();
    let walked = walk(d, enc, |h, start| {
        if h.tag.0 > last_group || h.tag == (0x7FE0, 0x0010) {
            return true;
        }
        if let Some(value) = (h.len != UNDEFINED && !h.sequence)
            .then(|| d.get(start..start.checked_add(h.len as usize)?))
            .flatten()
        {
            elements.push((h.tag, value));
        }
        false
    })?;
    Ok(walked.stopped.then_some(elements))
}

/// Where a walk ended: the bytes to parse, and whether the visitor stopped it before a top-level element.
struct Walked {
    end: usize,
    stopped: bool,
}

/// The walk of [`dataset`]; `stop` sees the header and value offset of every top-level element before its
/// length is checked, and ends the walk there by answering true.
fn walk(
    d: &[u8],
    enc: Encoding,
    mut stop: impl FnMut(&Header, usize) -> bool,
) -> Result<Walked, Defect> {
    let ran_out = |end| {
        Ok(Walked {
            end,
            stopped: false,
        })
    };
    // Open containers with the offset where a defined length ends them.
    let mut open: Vec<(Open, Option<usize>)> = Vec::new();
    let mut p = 0usize;
    loop {
        while let Some(&(_, Some(end))) = open.last() {
            if p < end {
                break;
            }
            open.pop();
        }
        let top = open.last().map(|o| o.0);
        if top.is_none() && p < d.len() && d[p..].iter().all(|&b| b == 0) {
            return ran_out(p);
        }
        let Some(h) = header(d, p, enc) else {
            return ran_out(d.len());
        };
        if top.is_none() && h.tag == (0xFFFC, 0xFFFC) {
            return ran_out(p);
        }
        let start = p + h.size;
        let left = d.len().saturating_sub(start);
        let defined = h.len != UNDEFINED;
        if top.is_none() && h.tag.0 != 0xFFFE && stop(&h, start) {
            return Ok(Walked {
                end: p,
                stopped: true,
            });
        }
        if defined && h.len as usize > left {
            return Err(Defect::Overrun {
                tag: h.tag,
                declared: h.len as u64,
                left,
            });
        }
        let end = defined.then(|| start + h.len as usize);
        match top {
            Some(Open::Fragments) => match h.tag {
                (0xFFFE, 0xE000) if defined => p = start + h.len as usize,
                (0xFFFE, 0xE000) => return Err(Defect::UndefinedFragment),
                (0xFFFE, 0xE0DD) => {
                    open.pop();
                    p = start;
                }
                _ => return ran_out(d.len()),
            },
            Some(Open::Sequence) => match h.tag {
                (0xFFFE, 0xE000) => {
                    open.push((Open::Item, end));
                    p = start;
                }
                (0xFFFE, 0xE0DD) => {
                    open.pop();
                    p = start;
                }
                _ => return ran_out(d.len()),
            },
            None | Some(Open::Item) => {
                if h.tag == (0xFFFE, 0xE00D) {
                    if top == Some(Open::Item) {
                        open.pop();
                    }
                    p = start;
                    continue;
                }
                // Other item tags here are read by dicom-rs as plain elements (tag and 4-byte length).
                if h.tag == (0x7FE0, 0x0010) && !defined {
                    open.push((Open::Fragments, None));
                    p = start;
                } else if h.sequence || !defined {
                    let depth = open.iter().filter(|o| o.0 == Open::Sequence).count();
                    if depth >= MAX_SEQUENCE_DEPTH {
                        return Err(Defect::TooDeep { tag: h.tag });
                    }
                    open.push((Open::Sequence, end));
                    p = start;
                } else if h.len % unit(h.vr) != 0 {
                    return Err(Defect::Misaligned {
                        tag: h.tag,
                        vr: h.vr,
                        declared: h.len,
                        unit: unit(h.vr),
                    });
                } else {
                    p = start + h.len as usize;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
