//! Re-encoding a stored instance's data set between the two uncompressed little-endian transfer syntaxes
//! (explicit ↔ implicit VR) for a peer that accepted only the other one: the pixel data is native in both,
//! so only the element headers change.

use std::path::Path;

use super::error::DicomError;
use super::read::{Opened, header_inflate_limit, open};
use super::web::{EXPLICIT_LE, IMPLICIT_LE};

/// Whether a data set stored in `from` can be sent in `to` by [`data_set_as`].
pub fn le_interchangeable(from: &str, to: &str) -> bool {
    let le = |ts: &str| ts == EXPLICIT_LE || ts == IMPLICIT_LE;
    le(from) && le(to)
}

/// The data set (no file meta) of the Part 10 file at `path`, encoded in `ts_uid`, which must be one of the
/// little-endian syntaxes, as must the file's (files over `max_bytes` are refused unread).
pub fn data_set_as(path: &Path, ts_uid: &str, max_bytes: u64) -> Result<Vec<u8>, DicomError> {
    let stored = super::header::read_part10(path)?.transfer_syntax;
    let (label, bytes) = super::header::read_bounded(path, max_bytes)?;
    if !le_interchangeable(&stored, ts_uid) {
        return Err(DicomError::UnsupportedTransferSyntax {
            label,
            uid: stored,
            name: format!("not transcoded to {ts_uid}"),
        });
    }
    let ts = if ts_uid == EXPLICIT_LE {
        dicom_transfer_syntax_registry::entries::EXPLICIT_VR_LITTLE_ENDIAN.erased()
    } else {
        dicom_transfer_syntax_registry::entries::IMPLICIT_VR_LITTLE_ENDIAN.erased()
    };
    let Opened { obj, .. } = open(&label, &bytes, header_inflate_limit(bytes.len()), None)?;
    let mut out = Vec::with_capacity(bytes.len() + 1024);
    obj.write_dataset_with_ts(&mut out, &ts)
        .map_err(|e| DicomError::Write(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dicom::{ReadLimits, SeriesMeta, read_bytes, write_ct_series};
    use crate::volume::{Frame, Volume};

    #[test]
    fn an_explicit_le_instance_re_encoded_as_implicit_le_reads_back_the_same() {
        let vol = Volume {
            data: ndarray::Array3::from_shape_fn((2, 6, 5), |(k, j, i)| {
                (k * 30 + j * 5 + i) as f32 - 20.0
            }),
            frame: Frame {
                origin_mm: [0.0, 0.0, 0.0],
                spacing_mm: [1.0, 1.0, 2.0],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let s = write_ct_series(&vol, &SeriesMeta::default()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.dcm");
        std::fs::write(&path, &s.files[1].1).unwrap();
        assert!(le_interchangeable(EXPLICIT_LE, IMPLICIT_LE));
        assert!(!le_interchangeable(EXPLICIT_LE, "1.2.840.10008.1.2.4.70"));
        let implicit = data_set_as(&path, IMPLICIT_LE, 1 << 20).unwrap();
        // A Part 10 file around the implicit data set reads back to the same slice.
        let p10 = super::super::header::part10_prefix(
            "1.2.840.10008.5.1.4.1.1.2",
            &read_bytes("a", &s.files[1].1, &ReadLimits::default())
                .unwrap()
                .sop_instance_uid,
            IMPLICIT_LE,
        )
        .unwrap();
        let again = read_bytes("b", &[p10, implicit].concat(), &ReadLimits::default()).unwrap();
        let first = read_bytes("a", &s.files[1].1, &ReadLimits::default()).unwrap();
        assert_eq!(again.sop_instance_uid, first.sop_instance_uid);
        assert_eq!(again.transfer_syntax, IMPLICIT_LE);
        assert_eq!(again.slices[0].stored, first.slices[0].stored);
        assert!(matches!(
            data_set_as(&path, "1.2.840.10008.1.2.4.70", 1 << 20),
            Err(DicomError::UnsupportedTransferSyntax { .. })
        ));
    }
}
