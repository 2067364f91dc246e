//! Synthetic CT series written by ctrecon itself from the 3D Shepp–Logan phantom (known geometry), read back
//! through the upload path: shuffled files, a tilted series, a missing slice, two series in one ZIP, an Enhanced
//! multi-frame file, and a non-CT series where CT is required.

use ctrecon::dicom::{
    self, DicomError, ReadLimits, SeriesMeta, ZipLimits, read_upload, unpack, write_ct_series,
    write_enhanced_ct, write_secondary_capture, write_zip,
};
use ctrecon::recon::VolumeGrid;
use ctrecon::recon::control::unattended;
use ctrecon::recon::phantom::{Phantom3, Table3};
use ctrecon::series::{AssemblyOptions, UnevenPolicy};
use ctrecon::volume::{Frame, Volume, WindowPreset};

/// The modified Shepp–Logan phantom (scale 100 mm) on a 40×48×24 grid with anisotropic voxels, mapped to HU
/// as 2000·v − 1000 (background −1000, skull +1000); supersampled, so values are not integers.
fn phantom_volume() -> Volume {
    let grid = VolumeGrid {
        nx: 40,
        ny: 48,
        nz: 24,
        spacing_mm: [5.0, 4.5, 8.0],
        centre_mm: [3.0, -7.0, 120.0],
    };
    let p = Phantom3::from_table(Table3::ModifiedSheppLogan, 100.0);
    let data = p.rasterize(&grid, 2).mapv(|v| 2000.0 * v - 1000.0);
    Volume {
        data,
        frame: Frame::from_grid(&grid),
    }
}

fn meta(description: &str) -> SeriesMeta {
    SeriesMeta {
        study_uid: Some("1.2.826.0.1.3680043.8.498.1".into()),
        patient_id: Some("PHANTOM".into()),
        series_description: description.into(),
        series_number: 7,
        ..Default::default()
    }
}

/// Deterministic shuffle (an LCG permutation).
fn shuffle<T>(v: &mut [T]) {
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    for i in (1..v.len()).rev() {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        v.swap(i, (s >> 33) as usize % (i + 1));
    }
}

/// Largest |a − b| over the volume, and geometry agreement within `tol_mm`.
fn compare(got: &Volume, want: &Volume, tol_mm: f64) -> f32 {
    assert_eq!(got.data.dim(), want.data.dim());
    for c in 0..3 {
        assert!((got.frame.spacing_mm[c] - want.frame.spacing_mm[c]).abs() < tol_mm);
        assert!((got.frame.origin_mm[c] - want.frame.origin_mm[c]).abs() < tol_mm);
        for a in 0..3 {
            assert!((got.frame.direction[a][c] - want.frame.direction[a][c]).abs() < 1e-6);
        }
    }
    got.data
        .iter()
        .zip(want.data.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max)
}

#[test]
fn a_shuffled_series_assembles_to_the_phantom_within_the_int16_step() {
    let vol = phantom_volume();
    let written = write_ct_series(&vol, &meta("shuffled")).unwrap();
    assert_eq!(written.files.len(), 24);
    let mut files = written.files.clone();
    shuffle(&mut files);
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert!(up.rejected.is_empty());
    assert_eq!(up.series.len(), 1);
    let group = up.series.into_iter().next().unwrap();
    let report = group.report();
    assert_eq!(report.series_uid, written.series_uid);
    assert_eq!(
        report.study_uid.as_deref(),
        Some("1.2.826.0.1.3680043.8.498.1")
    );
    assert_eq!(
        (report.instances, report.rows, report.columns),
        (24, 48, 40)
    );
    assert_eq!(report.pixel_spacing_mm, Some([4.5, 5.0]));
    let a = group
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap();
    // Quantisation: half an int16 step of the written rescale slope (HU), plus f32 rounding.
    let step = written.rescale_slope as f32;
    let err = compare(&a.volume, &vol, 1e-6);
    assert!(err <= 0.5 * step + 1e-3, "max error {err} HU, step {step}");
    assert!(a.warnings.is_empty(), "{:?}", a.warnings);
    assert!(a.tilt_deg < 1e-6);
}

#[test]
fn a_tilted_series_keeps_its_sheared_slice_axis() {
    let mut vol = phantom_volume();
    // Gantry tilt of 15° about the x axis: each slice moves 8·tan15° mm posteriorly.
    let t = 15f64.to_radians();
    vol.frame.direction[2] = [0.0, t.sin(), t.cos()];
    vol.frame.spacing_mm[2] = 8.0 / t.cos();
    let written = write_ct_series(&vol, &meta("tilted")).unwrap();
    let up = read_upload(&written.files, &ReadLimits::default(), unattended()).unwrap();
    let a = up
        .series
        .into_iter()
        .next()
        .unwrap()
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap();
    assert!((a.tilt_deg - 15.0).abs() < 1e-3, "tilt {}", a.tilt_deg);
    assert!((a.normal_spacing_mm - 8.0).abs() < 1e-4);
    assert!(a.warnings.iter().any(|w| w.code == "gantry_tilt"));
    // DS values carry ~1e-6 mm relative precision; direction within 1e-6.
    let err = compare(&a.volume, &vol, 1e-4);
    assert!(err <= 0.5 * written.rescale_slope as f32 + 1e-3);
    // The far corner voxel is where the sheared frame puts it.
    let p = a.volume.frame.position(23.0, 47.0, 39.0);
    let q = vol.frame.position(23.0, 47.0, 39.0);
    for c in 0..3 {
        assert!((p[c] - q[c]).abs() < 1e-3);
    }
}

#[test]
fn a_missing_slice_is_refused_with_a_clear_message_or_interpolated() {
    let vol = phantom_volume();
    let mut files = write_ct_series(&vol, &meta("gap")).unwrap().files;
    files.remove(10); // slice k = 10
    let group = read_upload(&files, &ReadLimits::default(), unattended())
        .unwrap()
        .series
        .remove(0);
    let e = group
        .clone()
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap_err();
    assert_eq!(e.code(), "series_missing_slices");
    let msg = e.to_string();
    assert!(
        msg.contains("1 slice(s) missing") && msg.contains("IM00010.dcm"),
        "{msg}"
    );
    let a = group
        .assemble(
            &AssemblyOptions {
                uneven: UnevenPolicy::Resample,
                ..Default::default()
            },
            true,
            unattended(),
        )
        .unwrap();
    assert_eq!(a.volume.data.dim(), (24, 48, 40));
    assert!(
        a.warnings
            .iter()
            .any(|w| w.code == "missing_slices_interpolated")
    );
    // The interpolated slice is the mean of its neighbours; the others are exact up to quantisation.
    let k = 10;
    let (lo, hi) = (
        vol.data.index_axis(ndarray::Axis(0), k - 1),
        vol.data.index_axis(ndarray::Axis(0), k + 1),
    );
    let got = a.volume.data.index_axis(ndarray::Axis(0), k);
    let err = got
        .iter()
        .zip(lo.iter().zip(hi.iter()))
        .map(|(g, (a, b))| (g - 0.5 * (a + b)).abs())
        .fold(0.0f32, f32::max);
    assert!(err < 0.1, "interpolated slice off by {err} HU");
}

#[test]
fn two_series_in_one_zip_are_split_and_reported() {
    let vol = phantom_volume();
    let a = write_ct_series(&vol, &meta("first")).unwrap();
    let mut small = vol.clone();
    small.data = small.data.slice(ndarray::s![..5, .., ..]).to_owned();
    let b = write_enhanced_ct(&small, &meta("second")).unwrap();
    let mut all: Vec<(String, Vec<u8>)> = a
        .files
        .iter()
        .map(|(n, d)| (format!("first/{n}"), d.clone()))
        .collect();
    all.extend(
        b.files
            .iter()
            .map(|(n, d)| (format!("second/{n}"), d.clone())),
    );
    all.push(("README.txt".into(), b"not dicom".to_vec()));
    let zip = write_zip(&all).unwrap();
    let files = unpack("upload.zip", zip, &ZipLimits::default()).unwrap();
    assert_eq!(files.len(), 26);
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert_eq!(up.rejected.len(), 1);
    assert_eq!(up.rejected[0].error.code(), "dicom_not_dicom");
    assert_eq!(up.series.len(), 2);
    let mut reports: Vec<_> = up.series.iter().map(|g| g.report()).collect();
    reports.sort_by_key(|r| r.instances);
    assert_eq!((reports[0].instances, reports[0].frames), (1, 5));
    assert_eq!((reports[1].instances, reports[1].frames), (24, 24));
    assert_eq!(reports[0].description.as_deref(), Some("second"));
    assert_eq!(reports[0].series_uid, b.series_uid);
    assert_eq!(reports[1].series_uid, a.series_uid);
}

#[test]
fn an_enhanced_multi_frame_file_assembles_like_the_classic_series() {
    let vol = phantom_volume();
    let written = write_enhanced_ct(&vol, &meta("enhanced")).unwrap();
    assert_eq!(written.files.len(), 1);
    let up = read_upload(&written.files, &ReadLimits::default(), unattended()).unwrap();
    assert!(up.rejected.is_empty(), "{:?}", up.rejected);
    let a = up
        .series
        .into_iter()
        .next()
        .unwrap()
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap();
    let err = compare(&a.volume, &vol, 1e-6);
    assert!(
        err <= 0.5 * written.rescale_slope as f32 + 1e-3,
        "max error {err}"
    );
}

#[test]
fn a_secondary_capture_is_not_a_ct_series() {
    let vol = phantom_volume();
    let mip = ctrecon::volume::project(
        vol.data.view(),
        ctrecon::volume::Axis::Coronal,
        ctrecon::volume::ProjectionKind::Max,
        None,
    )
    .unwrap();
    let (_, bytes) =
        write_secondary_capture(mip.view(), WindowPreset::Bone.window(), &meta("mip"), None)
            .unwrap();
    let up = read_upload(
        &[("mip.dcm".into(), bytes)],
        &ReadLimits::default(),
        unattended(),
    )
    .unwrap();
    let g = up.series.into_iter().next().unwrap();
    assert_eq!(g.modality.as_deref(), Some("OT"));
    assert_eq!(g.instances[0].slices[0].rows, 24);
    let e = g
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap_err();
    assert_eq!(e.code(), "dicom_not_ct");
    assert!(e.to_string().contains("modality OT"));
}

#[test]
fn hostile_files_are_refused_with_typed_errors() {
    let vol = phantom_volume();
    let good = write_ct_series(&vol, &meta("x")).unwrap().files.remove(0).1;
    let lim = ReadLimits::default();
    // Truncated anywhere: header, mid-element, mid-pixels.
    for cut in [10, 131, 200, 600, good.len() / 2, good.len() - 1] {
        let e = dicom::read_bytes("cut.dcm", &good[..cut], &lim).unwrap_err();
        assert!(
            matches!(
                e.code(),
                "dicom_not_dicom"
                    | "dicom_parse_error"
                    | "dicom_pixel_data_short"
                    | "dicom_no_pixel_data"
            ),
            "cut at {cut}: {e}"
        );
    }
    // Absurd dimensions: Rows = 65535 patched in place (tag (0028,0010) US, explicit VR LE).
    let pos = good
        .windows(6)
        .position(|w| w == [0x28, 0x00, 0x10, 0x00, b'U', b'S'])
        .unwrap();
    let mut big = good.clone();
    big[pos + 8..pos + 10].copy_from_slice(&65535u16.to_le_bytes());
    let e = dicom::read_bytes("big.dcm", &big, &lim).unwrap_err();
    assert_eq!(e.code(), "dicom_too_large", "{e}");
    // Declared 49 rows with pixel data for 48: shorter than declared.
    let mut short = good.clone();
    short[pos + 8..pos + 10].copy_from_slice(&49u16.to_le_bytes());
    let e_short = dicom::read_bytes("short.dcm", &short, &lim).unwrap_err();
    assert_eq!(e_short.code(), "dicom_pixel_data_short", "{e_short}");
    // A pixel data element declaring 4 GB in a small file is refused before anything is allocated for it.
    let px = good
        .windows(6)
        .rposition(|w| w == [0xE0, 0x7F, 0x10, 0x00, b'O', b'W'])
        .unwrap();
    let mut huge = good.clone();
    huge[px + 8..px + 12].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
    let e = dicom::read_bytes("huge.dcm", &huge, &lim).unwrap_err();
    assert_eq!(e.code(), "dicom_parse_error");
    assert!(
        e.to_string()
            .contains("(7FE0,0010) declares 4294967280 bytes"),
        "{e}"
    );
    assert!(matches!(
        e_short,
        DicomError::PixelDataShort {
            expected: 3920,
            got: 3840,
            ..
        }
    ));
}

#[test]
fn zip_bombs_and_hostile_names_are_handled() {
    // 64 MiB of zeros deflates ~1000:1.
    let zeros = vec![0u8; 64 << 20];
    let zip = write_zip(&[("zeros.dcm".into(), zeros)]).unwrap();
    assert!(zip.len() < 1 << 20);
    let e = unpack("bomb.zip", zip.clone(), &ZipLimits::default()).unwrap_err();
    assert_eq!(e.code(), "zip_limits_exceeded", "{e}");
    let e = unpack(
        "bomb.zip",
        zip,
        &ZipLimits {
            max_ratio: 100_000,
            max_total_bytes: 32 << 20,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("bytes once inflated"), "{e}");
    // Names are labels: traversal and absolute paths come back verbatim and are never opened.
    let vol = phantom_volume();
    let f = write_ct_series(&vol, &meta("x")).unwrap().files.remove(0).1;
    let zip = write_zip(&[
        ("../../etc/passwd.dcm".into(), f.clone()),
        ("/abs/x.dcm".into(), f),
    ])
    .unwrap();
    let files = unpack("names.zip", zip, &ZipLimits::default()).unwrap();
    let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["../../etc/passwd.dcm", "/abs/x.dcm"]);
    // The same instance twice: kept once, with a warning.
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert_eq!(up.series[0].instances.len(), 1);
    assert_eq!(up.series[0].warnings[0].code, "duplicate_instance_dropped");
    // Not a ZIP at all, and a broken one.
    assert_eq!(
        unpack("a.dcm", b"DICM".to_vec(), &ZipLimits::default())
            .unwrap()
            .len(),
        1
    );
    let e = unpack(
        "b.zip",
        b"PK\x03\x04garbage".to_vec(),
        &ZipLimits::default(),
    )
    .unwrap_err();
    assert_eq!(e.code(), "zip_invalid");
}

#[test]
fn canceling_stops_decoding_and_assembly() {
    use ctrecon::recon::{Cancel, Control, NoProgress};
    let vol = phantom_volume();
    let files = write_ct_series(&vol, &meta("cancel")).unwrap().files;
    let cancel = Cancel::new();
    cancel.cancel();
    let ctl = Control::new(&cancel, &NoProgress);
    let e = read_upload(&files, &ReadLimits::default(), ctl).unwrap_err();
    assert_eq!(e.code(), "canceled");
    let g = read_upload(&files, &ReadLimits::default(), unattended())
        .unwrap()
        .series
        .remove(0);
    let e = g
        .assemble(&AssemblyOptions::default(), true, ctl)
        .unwrap_err();
    assert_eq!(e.code(), "canceled");
    assert!(!e.is_client_error());
}
