//! DICOM round trips: volumes written by ctrecon as CT series (classic and Enhanced), zipped, unpacked, read
//! and assembled give back the same HU values (within half the int16 rescale step) and the same geometry;
//! Secondary Capture and Encapsulated STL instances carry their payload unchanged.

use ctrecon::dicom::{
    ReadLimits, SeriesMeta, ZipLimits, read_bytes, read_upload, unpack, write_ct_series,
    write_encapsulated_stl, write_secondary_capture, write_zip,
};
use ctrecon::mesh::marching_cubes;
use ctrecon::recon::VolumeGrid;
use ctrecon::recon::control::unattended;
use ctrecon::recon::phantom::{Phantom3, Table3};
use ctrecon::series::AssemblyOptions;
use ctrecon::volume::{Frame, MU_WATER_PER_MM, Volume, Window, mu_to_hu};
use dicom_dictionary_std::tags;

fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 32,
        ny: 30,
        nz: 20,
        spacing_mm: [6.5, 7.0, 10.0],
        centre_mm: [-12.25, 40.5, -310.75],
    }
}

/// A μ reconstruction stand-in (the phantom as attenuation, 1/mm) converted to HU, as a job would.
fn hu_volume(frame: Frame) -> Volume {
    let p = Phantom3::from_table(Table3::ModifiedSheppLogan, 100.0);
    let mu = p.rasterize(&grid(), 2).mapv(|v| v * MU_WATER_PER_MM as f32);
    Volume {
        data: mu.mapv(|m| mu_to_hu(m, MU_WATER_PER_MM)),
        frame,
    }
}

fn round_trip(vol: &Volume) -> (Volume, f64, Vec<(String, Vec<u8>)>) {
    let meta = SeriesMeta {
        study_uid: Some("1.2.3.4.5".into()),
        frame_of_reference_uid: Some("1.2.3.4.6".into()),
        series_description: "round trip".into(),
        ..Default::default()
    };
    let written = write_ct_series(vol, &meta).unwrap();
    // Through a ZIP, as a download and re-upload would go.
    let zip = write_zip(&written.files).unwrap();
    let files = unpack("series.zip", zip, &ZipLimits::default()).unwrap();
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert!(up.rejected.is_empty());
    let g = up.series.into_iter().next().unwrap();
    assert_eq!(g.series_uid, written.series_uid);
    assert_eq!(g.study_uid.as_deref(), Some("1.2.3.4.5"));
    assert_eq!(
        g.instances[0].frame_of_reference_uid.as_deref(),
        Some("1.2.3.4.6")
    );
    assert_ne!(
        g.instances[0].sop_instance_uid,
        g.instances[1].sop_instance_uid
    );
    let a = g
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap();
    (a.volume, written.rescale_slope, written.files)
}

fn max_diff(a: &Volume, b: &Volume) -> f32 {
    assert_eq!(a.data.dim(), b.data.dim());
    a.data
        .iter()
        .zip(b.data.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn assert_frames_equal(a: &Frame, b: &Frame, tol: f64) {
    for c in 0..3 {
        assert!(
            (a.spacing_mm[c] - b.spacing_mm[c]).abs() <= tol,
            "{a:?} vs {b:?}"
        );
        assert!(
            (a.origin_mm[c] - b.origin_mm[c]).abs() <= tol,
            "{a:?} vs {b:?}"
        );
        for d in 0..3 {
            assert!(
                (a.direction[d][c] - b.direction[d][c]).abs() <= 1e-9,
                "{a:?} vs {b:?}"
            );
        }
    }
}

#[test]
fn an_axis_aligned_hu_volume_round_trips_within_half_a_step() {
    let vol = hu_volume(Frame::from_grid(&grid()));
    let (back, slope, _) = round_trip(&vol);
    // Half an int16 step plus float rounding of HU ~ 1000 in f32 (1e-4).
    let err = max_diff(&back, &vol);
    assert!(
        err <= 0.5 * slope as f32 + 1e-3,
        "max error {err} HU, step {slope}"
    );
    assert_frames_equal(&back.frame, &vol.frame, 1e-9);
}

#[test]
fn integer_hu_round_trips_exactly_with_unit_slope() {
    let mut vol = hu_volume(Frame::from_grid(&grid()));
    vol.data.mapv_inplace(f32::round);
    let (back, slope, files) = round_trip(&vol);
    assert_eq!(slope, 1.0);
    assert_eq!(max_diff(&back, &vol), 0.0);
    // The stored attributes: CT, int16, rescale to HU, derived.
    let inst = read_bytes(&files[0].0, &files[0].1, &ReadLimits::default()).unwrap();
    assert_eq!(inst.modality.as_deref(), Some("CT"));
    assert!(inst.signed && inst.bits_stored == 16);
    assert_eq!(inst.sop_class_uid, "1.2.840.10008.5.1.4.1.1.2");
    assert_eq!(inst.slices[0].pixel_spacing_mm, Some([7.0, 6.5]));
    assert_eq!(inst.slices[0].slice_thickness_mm, Some(10.0));
}

#[test]
fn an_oblique_volume_round_trips_with_its_orientation() {
    let (s, c) = 30f64.to_radians().sin_cos();
    let frame = Frame {
        spacing_mm: [6.5, 7.0, 10.0],
        origin_mm: [101.125, -57.3, 12.0],
        // Rotated 30° in the axial plane and tipped 20° about the row axis (orthonormal).
        direction: {
            let (st, ct) = 20f64.to_radians().sin_cos();
            let r = [c, s, 0.0];
            let col = [-s * ct, c * ct, st];
            let n = [s * st, -c * st, ct];
            [r, col, n]
        },
    };
    let vol = hu_volume(frame);
    let (back, slope, _) = round_trip(&vol);
    let err = max_diff(&back, &vol);
    assert!(err <= 0.5 * slope as f32 + 1e-3, "max error {err} HU");
    // DS strings hold 16 characters: positions and cosines to ~1e-9.
    assert_frames_equal(&back.frame, &vol.frame, 1e-7);
}

#[test]
fn secondary_capture_and_encapsulated_stl_carry_their_payloads() {
    let vol = hu_volume(Frame::from_grid(&grid()));
    let img = vol.data.index_axis(ndarray::Axis(0), 10).to_owned();
    let window = Window::new(2000.0, 0.0).unwrap();
    let meta = SeriesMeta {
        study_uid: Some("1.2.3.4.5".into()),
        ..Default::default()
    };
    let (sop, bytes) = write_secondary_capture(img.view(), window, &meta, None).unwrap();
    let inst = read_bytes("sc.dcm", &bytes, &ReadLimits::default()).unwrap();
    assert_eq!(inst.sop_instance_uid, sop);
    assert_eq!(inst.sop_class_uid, "1.2.840.10008.5.1.4.1.1.7");
    assert_eq!(inst.study_uid.as_deref(), Some("1.2.3.4.5"));
    // Pixels are the window's 8-bit grey levels, exactly.
    for (got, &hu) in inst.slices[0].stored.iter().zip(img.iter()) {
        assert_eq!(*got, (window.unit(hu) * 255.0).round() as f32);
    }

    let mesh = marching_cubes(vol.data.view(), &vol.frame, 0.0).largest_component();
    let stl = mesh.to_stl_binary();
    let (sop, bytes) = write_encapsulated_stl(&stl, &meta, "skull").unwrap();
    let obj = dicom_object::OpenFileOptions::new()
        .from_reader(&bytes[128..])
        .unwrap();
    let text = |t| {
        obj.element(t)
            .unwrap()
            .to_str()
            .unwrap()
            .trim_end_matches('\0')
            .trim()
            .to_string()
    };
    assert_eq!(text(tags::SOP_CLASS_UID), "1.2.840.10008.5.1.4.1.1.104.3");
    assert_eq!(text(tags::SOP_INSTANCE_UID), sop);
    assert_eq!(text(tags::MODALITY), "M3D");
    assert_eq!(text(tags::MIME_TYPE_OF_ENCAPSULATED_DOCUMENT), "model/stl");
    assert_eq!(
        obj.element(tags::ENCAPSULATED_DOCUMENT_LENGTH)
            .unwrap()
            .to_int::<u32>()
            .unwrap() as usize,
        stl.len()
    );
    let doc = obj
        .element(tags::ENCAPSULATED_DOCUMENT)
        .unwrap()
        .to_bytes()
        .unwrap();
    assert_eq!(&doc[..stl.len()], &stl[..]);
    assert!(doc.len() - stl.len() <= 1);
    // A file with no pixel data is refused by the image reader with a typed error.
    let e = read_bytes("stl.dcm", &bytes, &ReadLimits::default()).unwrap_err();
    assert_eq!(e.code(), "dicom_no_pixel_data");
}
