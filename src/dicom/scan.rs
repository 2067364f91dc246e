//! A pre-parse walk over element headers: every declared value length must fit in the bytes that remain, so a
//! hostile header cannot make the parser allocate far more memory than the file holds.

/// The first element (group, element, declared length, bytes left) whose value runs past the end of the file.
pub(super) type Overrun = (u16, u16, u64, usize);

const UNDEFINED: u32 = u32::MAX;

/// Walk `data` (a Part 10 stream after the `DICM` marker). `None` when all lengths fit or the stream ends early
/// in a header (the parser reports that), `Some` with the first overrun otherwise. Deflated data sets are not
/// walked.
pub(super) fn overrun(data: &[u8]) -> Option<Overrun> {
    let (start, ts) = match walk_meta(data) {
        Ok(m) => m,
        Err(o) => return Some(o),
    };
    let (explicit, big) = match ts.as_str() {
        "1.2.840.10008.1.2" => (false, false),
        "1.2.840.10008.1.2.2" => (true, true),
        "1.2.840.10008.1.2.1.99" => return None,
        _ => (true, false),
    };
    walk(&data[start..], explicit, big)
}

fn u16_at(d: &[u8], p: usize, big: bool) -> Option<u16> {
    let b = [*d.get(p)?, *d.get(p + 1)?];
    Some(if big {
        u16::from_be_bytes(b)
    } else {
        u16::from_le_bytes(b)
    })
}

fn u32_at(d: &[u8], p: usize, big: bool) -> Option<u32> {
    let b = [*d.get(p)?, *d.get(p + 1)?, *d.get(p + 2)?, *d.get(p + 3)?];
    Some(if big {
        u32::from_be_bytes(b)
    } else {
        u32::from_le_bytes(b)
    })
}

/// VRs with a 4-byte length in explicit VR encodings.
fn long_vr(vr: [u8; 2]) -> bool {
    matches!(
        &vr,
        b"OB"
            | b"OD"
            | b"OF"
            | b"OL"
            | b"OV"
            | b"OW"
            | b"SQ"
            | b"SV"
            | b"UC"
            | b"UN"
            | b"UR"
            | b"UT"
            | b"UV"
    )
}

/// Walk the group 0002 elements (explicit VR little endian); returns where the data set starts and the
/// transfer syntax UID.
fn walk_meta(d: &[u8]) -> Result<(usize, String), Overrun> {
    let mut p = 0;
    let mut ts = String::new();
    while let (Some(group), Some(element)) = (u16_at(d, p, false), u16_at(d, p + 2, false)) {
        if group != 0x0002 {
            break;
        }
        let vr = [
            d.get(p + 4).copied().unwrap_or(0),
            d.get(p + 5).copied().unwrap_or(0),
        ];
        let (len, header) = if long_vr(vr) {
            (u32_at(d, p + 8, false).unwrap_or(0), 12)
        } else {
            (u16_at(d, p + 6, false).unwrap_or(0) as u32, 8)
        };
        let left = d.len().saturating_sub(p + header);
        if len as usize > left {
            return Err((group, element, len as u64, left));
        }
        if element == 0x0010 {
            ts = String::from_utf8_lossy(&d[p + header..p + header + len as usize])
                .trim_end_matches(['\0', ' '])
                .to_string();
        }
        p += header + len as usize;
    }
    Ok((p, ts))
}

fn walk(d: &[u8], explicit: bool, big: bool) -> Option<Overrun> {
    let mut p = 0;
    // Inside encapsulated pixel data, items are opaque fragments.
    let mut in_fragments = false;
    while let (Some(group), Some(element)) = (u16_at(d, p, big), u16_at(d, p + 2, big)) {
        if group == 0xFFFE {
            // Item and delimiters: tag + 4-byte length, no VR.
            let len = u32_at(d, p + 4, big)?;
            p += 8;
            match element {
                0xE000 if in_fragments && len != UNDEFINED => {
                    let left = d.len().saturating_sub(p);
                    if len as usize > left {
                        return Some((group, element, len as u64, left));
                    }
                    p += len as usize;
                }
                0xE0DD => in_fragments = false,
                // Items of sequences: descend into their elements.
                _ => {}
            }
            continue;
        }
        let (len, header, sequence) = if explicit {
            let vr = [*d.get(p + 4)?, *d.get(p + 5)?];
            if long_vr(vr) {
                (u32_at(d, p + 8, big)?, 12, &vr == b"SQ")
            } else {
                (u16_at(d, p + 6, big)? as u32, 8, false)
            }
        } else {
            let len = u32_at(d, p + 4, big)?;
            // Implicit VR: a value that opens with an item tag is a sequence.
            let opens_item =
                u16_at(d, p + 8, big) == Some(0xFFFE) && u16_at(d, p + 10, big) == Some(0xE000);
            (len, 8, opens_item)
        };
        p += header;
        if len == UNDEFINED {
            // Undefined length: a sequence or encapsulated pixel data; walk into it.
            in_fragments = (group, element) == (0x7FE0, 0x0010);
            continue;
        }
        let left = d.len().saturating_sub(p);
        if len as usize > left {
            return Some((group, element, len as u64, left));
        }
        if !sequence {
            p += len as usize;
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_length_past_the_end_is_found_and_a_fitting_one_is_not() {
        // Meta: (0002,0010) UI "1.2.840.10008.1.2.1" padded to 20 bytes.
        let mut d = Vec::new();
        d.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I', 20, 0]);
        d.extend_from_slice(b"1.2.840.10008.1.2.1\0");
        // (0028,0010) US 2 bytes, then (7FE0,0010) OW with 8 bytes.
        d.extend_from_slice(&[0x28, 0x00, 0x10, 0x00, b'U', b'S', 2, 0, 4, 0]);
        d.extend_from_slice(&[0xE0, 0x7F, 0x10, 0x00, b'O', b'W', 0, 0, 8, 0, 0, 0]);
        d.extend_from_slice(&[0u8; 8]);
        assert_eq!(overrun(&d), None);
        let n = d.len();
        d[n - 12..n - 8].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
        assert_eq!(overrun(&d), Some((0x7FE0, 0x0010, 0xFFFF_FFF0, 8)));
    }
}
