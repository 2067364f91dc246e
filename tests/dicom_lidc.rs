//! LIDC-IDRI-0001 (The Cancer Imaging Archive, CC BY 3.0): 133 axial CT slices of 512², 0.703125 mm pixels,
//! 2.5 mm slices. Fetched by `scripts/fetch-test-data.sh` into `.testdata/lidc`; without it these tests print a
//! skip notice, unless `CTRECON_REQUIRE_TEST_DATA=1`, when they fail.

use std::path::{Path, PathBuf};

use ctrecon::dicom::{ReadLimits, read_upload};
use ctrecon::mesh::marching_cubes;
use ctrecon::recon::control::unattended;
use ctrecon::series::{Assembled, AssemblyOptions};
use ctrecon::volume::{Axis, BitDepth, ProjectionKind, WindowPreset, encode_png, project};

fn data_dir(sub: &str) -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(".testdata")
        .join(sub);
    if d.is_dir() {
        return Some(d);
    }
    if std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() == Ok("1") {
        panic!(
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
            d.display()
        );
    }
    eprintln!(
        "SKIPPED: {} is missing (run scripts/fetch-test-data.sh)",
        d.display()
    );
    None
}

fn lidc() -> Option<(ctrecon::dicom::SeriesReport, Assembled)> {
    let dir = data_dir("lidc")?;
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect();
    files.sort();
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert!(up.rejected.is_empty(), "{:?}", up.rejected);
    assert_eq!(up.series.len(), 1);
    let g = up.series.into_iter().next().unwrap();
    let report = g.report();
    let a = g
        .assemble(&AssemblyOptions::default(), true, unattended())
        .unwrap();
    Some((report, a))
}

#[test]
fn lidc_geometry_hu_mesh_and_mip() {
    let Some((report, a)) = lidc() else { return };
    println!("report: {}", serde_json::to_string(&report).unwrap());
    // Geometry, exactly as the headers give it.
    assert_eq!(
        (report.instances, report.rows, report.columns),
        (133, 512, 512)
    );
    assert_eq!(report.modality.as_deref(), Some("CT"));
    assert_eq!(report.pixel_spacing_mm, Some([0.703125, 0.703125]));
    assert_eq!(report.slice_thickness_mm, Some(2.5));
    let v = &a.volume;
    assert_eq!(v.data.dim(), (133, 512, 512));
    assert_eq!(v.frame.spacing_mm[0], 0.703125);
    assert_eq!(v.frame.spacing_mm[1], 0.703125);
    assert!((v.frame.spacing_mm[2] - 2.5).abs() < 1e-9, "{:?}", v.frame);
    assert_eq!(
        v.frame.direction,
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    );
    assert!(a.tilt_deg < 1e-9);
    // Image Position (Patient) of the most inferior slice, as written (DS "-166.000000\\-171.699997\\-340.000000").
    assert_eq!(v.frame.origin_mm, [-166.0, -171.699997, -340.0]);
    println!("frame: {:?}, warnings: {:?}", v.frame, a.warnings);

    // HU: air ≈ −1000 (the mode of values below −500), bone present, no wrap-around.
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    let mut hist = vec![0usize; 100]; // 10 HU bins over [−1500, −500)
    for &x in v.data.iter() {
        lo = lo.min(x);
        hi = hi.max(x);
        if (-1500.0..-500.0).contains(&x) {
            hist[((x + 1500.0) / 10.0) as usize] += 1;
        }
    }
    let mode = hist
        .iter()
        .enumerate()
        .max_by_key(|(_, n)| **n)
        .map(|(i, _)| -1500.0 + 10.0 * i as f32 + 5.0)
        .unwrap();
    println!("HU range [{lo}, {hi}], air mode {mode} HU");
    assert!((-1050.0..=-950.0).contains(&mode), "air at {mode} HU");
    assert!(lo >= -3100.0, "min {lo} HU: wrap-around or bad padding");
    assert!((1000.0..=4100.0).contains(&hi), "max {hi} HU");

    // Bone mesh at 300 HU: closed, plausible size (a chest CT's ribs, spine, sternum, scapulae over 33 cm).
    let mesh = marching_cubes(v.data.view(), &v.frame, 300.0).largest_component();
    let (tri, area, vol) = (mesh.triangle_count(), mesh.area_mm2(), mesh.volume_mm3());
    println!(
        "bone mesh: {tri} triangles, area {:.0} cm², volume {:.0} cm³, closed {}",
        area / 100.0,
        vol / 1000.0,
        mesh.is_closed()
    );
    assert!(mesh.is_closed());
    assert!(tri > 100_000, "{tri} triangles");
    // Bone surface of a chest over 33 cm: 0.1–1.5 m²; bone volume 0.2–3 litres.
    assert!((1.0e5..1.5e6).contains(&area), "area {area} mm²");
    assert!((2.0e5..3.0e6).contains(&vol), "volume {vol} mm³");

    // Coronal MIP: the chest fills the middle of the image, bone bright.
    let mip = project(v.data.view(), Axis::Coronal, ProjectionKind::Max, None).unwrap();
    assert_eq!(mip.dim(), (133, 512));
    let bright = mip.iter().filter(|&&x| x > 300.0).count() as f64 / mip.len() as f64;
    let centre = mip[[66, 256]];
    println!(
        "MIP: {:.0}% of pixels above 300 HU, centre {centre} HU",
        100.0 * bright
    );
    assert!((0.2..0.95).contains(&bright), "bright fraction {bright}");
    assert!(centre > 300.0, "centre {centre} HU");
    let png = encode_png(mip.view(), WindowPreset::Bone.window(), BitDepth::Eight).unwrap();
    let path = std::env::temp_dir().join("ctrecon_lidc_mip_coronal.png");
    std::fs::write(&path, png).unwrap();
    println!("wrote {}", path.display());
}
