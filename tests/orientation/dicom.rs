//! The DICOM outputs: where Secondary Capture images say they lie (Patient Orientation, and Image
//! Position/Orientation (Patient) for planar ones), and derived CT series whose voxels sit at the marker's
//! LPS points.

use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_object::{DefaultDicomObject, OpenFileOptions};
use serde_json::Value;

use super::geometry::{V3, axpy, close, v3};
use super::phantom::{MARKERS, N, O, S, lps};

pub fn open(bytes: &[u8]) -> DefaultDicomObject {
    assert_eq!(&bytes[128..132], b"DICM");
    OpenFileOptions::new().from_reader(&bytes[128..]).unwrap()
}

pub fn strs(obj: &DefaultDicomObject, tag: Tag) -> Option<Vec<String>> {
    let e = obj.element(tag).ok()?;
    Some(
        e.to_multi_str()
            .ok()?
            .iter()
            .map(|s| {
                s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
                    .to_string()
            })
            .collect(),
    )
}

pub fn floats(obj: &DefaultDicomObject, tag: Tag) -> Option<Vec<f64>> {
    strs(obj, tag).map(|v| v.iter().map(|s| s.parse().unwrap()).collect())
}

pub fn int(obj: &DefaultDicomObject, tag: Tag) -> i64 {
    strs(obj, tag).unwrap()[0].parse().unwrap()
}

/// Where an image lies: its first pixel, screen right and down, and Pixel Spacing (rows, columns).
#[derive(Debug, Clone, Copy)]
pub struct Placement {
    pub first: V3,
    pub right: V3,
    pub down: V3,
    pub pixel: [f64; 2],
}

impl Placement {
    pub fn from_json(plane: &Value) -> Self {
        Self {
            first: v3(&plane["first_pixel_mm"]),
            right: v3(&plane["row_direction"]),
            down: v3(&plane["column_direction"]),
            pixel: [
                plane["pixel_mm"][0].as_f64().unwrap(),
                plane["pixel_mm"][1].as_f64().unwrap(),
            ],
        }
    }
}

/// Assert an image's Patient Orientation (absent for `None`: frames that do not share one), and its Image
/// Position/Orientation (Patient) and Pixel Spacing when it is planar (absent otherwise).
pub fn assert_placed(
    obj: &DefaultDicomObject,
    po: Option<[String; 2]>,
    plane: Option<Placement>,
    what: &str,
) {
    assert_eq!(
        strs(obj, tags::PATIENT_ORIENTATION),
        po.map(|p| p.to_vec()),
        "{what}: Patient Orientation"
    );
    let iop = floats(obj, tags::IMAGE_ORIENTATION_PATIENT);
    let ipp = floats(obj, tags::IMAGE_POSITION_PATIENT);
    match plane {
        None => assert!(
            iop.is_none() && ipp.is_none(),
            "{what}: placed at {ipp:?} {iop:?}"
        ),
        Some(p) => {
            let iop = iop.unwrap_or_else(|| panic!("{what}: no Image Orientation (Patient)"));
            let ipp = ipp.unwrap_or_else(|| panic!("{what}: no Image Position (Patient)"));
            let want = [p.right, p.down].concat();
            assert!(
                iop.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6),
                "{what}: Image Orientation (Patient) {iop:?}, want {want:?}"
            );
            assert!(
                close([ipp[0], ipp[1], ipp[2]], p.first, 1e-3),
                "{what}: Image Position (Patient) {ipp:?}, want {:?}",
                p.first
            );
            let ps = floats(obj, tags::PIXEL_SPACING).unwrap();
            assert!(
                (ps[0] - p.pixel[0]).abs() < 1e-6 && (ps[1] - p.pixel[1]).abs() < 1e-6,
                "{what}: Pixel Spacing {ps:?}"
            );
            assert_eq!(
                strs(obj, tags::FRAME_OF_REFERENCE_UID).as_deref(),
                Some(&["1.2.826.0.1.3680043.8.498.78".to_string()][..]),
                "{what}"
            );
        }
    }
}

/// HU of every pixel of a CT image, row by row.
fn hu(obj: &DefaultDicomObject) -> Vec<f64> {
    let slope = floats(obj, tags::RESCALE_SLOPE).map_or(1.0, |v| v[0]);
    let intercept = floats(obj, tags::RESCALE_INTERCEPT).map_or(0.0, |v| v[0]);
    let raw = obj.element(tags::PIXEL_DATA).unwrap().to_bytes().unwrap();
    raw.chunks_exact(2)
        .map(|b| i16::from_le_bytes([b[0], b[1]]) as f64 * slope + intercept)
        .collect()
}

/// A derived CT series of the whole volume (one file a slice, any order): canonical axial images from the
/// inferior end, labelled L/P, whose marker voxels lie at the markers' LPS points.
pub fn assert_volume_series(files: &[Vec<u8>], what: &str) {
    assert_eq!(files.len(), N[2], "{what}: slices");
    let mut voxels: Vec<(V3, f64)> = Vec::new();
    let mut zs = Vec::new();
    for f in files {
        let obj = open(f);
        assert_eq!(
            obj.meta()
                .media_storage_sop_class_uid
                .trim_end_matches('\0'),
            uids::CT_IMAGE_STORAGE,
            "{what}"
        );
        let place = Placement {
            first: {
                let p = floats(&obj, tags::IMAGE_POSITION_PATIENT).unwrap();
                [p[0], p[1], p[2]]
            },
            right: [1.0, 0.0, 0.0],
            down: [0.0, 1.0, 0.0],
            pixel: [S[1], S[0]],
        };
        assert_placed(&obj, Some(["L".into(), "P".into()]), Some(place), what);
        assert!(
            close(place.first, [O[0], O[1], place.first[2]], 1e-3),
            "{what}: {place:?}"
        );
        zs.push(place.first[2]);
        let iop = floats(&obj, tags::IMAGE_ORIENTATION_PATIENT).unwrap();
        let (right, down) = ([iop[0], iop[1], iop[2]], [iop[3], iop[4], iop[5]]);
        let (rows, cols) = (
            int(&obj, tags::ROWS) as usize,
            int(&obj, tags::COLUMNS) as usize,
        );
        assert_eq!((rows, cols), (N[1], N[0]), "{what}");
        for (i, v) in hu(&obj).into_iter().enumerate() {
            let (r, c) = (i / cols, i % cols);
            // Image Position (Patient) + the orientation vectors scaled by Pixel Spacing.
            let p = axpy(
                axpy(place.first, c as f64 * place.pixel[1], right),
                r as f64 * place.pixel[0],
                down,
            );
            voxels.push((p, v));
        }
    }
    zs.sort_by(f64::total_cmp);
    for (k, z) in zs.iter().enumerate() {
        assert!(
            (z - (O[2] + k as f64 * S[2])).abs() < 1e-3,
            "{what}: slice positions {zs:?}"
        );
    }
    for (c, hu) in MARKERS {
        let inside: Vec<V3> = voxels
            .iter()
            .filter(|(_, v)| (v - hu as f64).abs() < 0.5)
            .map(|(p, _)| *p)
            .collect();
        assert_eq!(inside.len(), 27, "{what}: marker {c:?}");
        let mean: V3 = std::array::from_fn(|a| inside.iter().map(|p| p[a]).sum::<f64>() / 27.0);
        let want = lps(c);
        assert!(
            (0..3).all(|a| (mean[a] - want[a]).abs() <= S[a] / 2.0),
            "{what}: marker {c:?} at {mean:?}, want {want:?}"
        );
    }
}

/// The files of a ZIP archive.
pub fn unzip(bytes: &[u8]) -> Vec<Vec<u8>> {
    use std::io::Read;
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).unwrap();
    (0..zip.len())
        .map(|i| {
            let mut f = zip.by_index(i).unwrap();
            let mut b = Vec::new();
            f.read_to_end(&mut b).unwrap();
            b
        })
        .collect()
}
