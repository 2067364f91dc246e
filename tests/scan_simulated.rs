//! The simulated Nikon XT H scans `ctrecon phantom --out <name>.xtekct` writes (the README's scan
//! walk-through starts from one): Python's tifffile reads the TIFFs as the turned, 16-bit intensities of the
//! line integrals, and ctrecon's Nikon reader gives back the geometry and the values they were made from.

use std::path::Path;
use std::process::{Command, Stdio};

use ctrecon::recon::geometry::{Angles, ConeBeam, Geometry, Panel, Views};
use ctrecon::scans::{self, simulated};
use ndarray::Array3;

use crate::scan_formats::python;

fn cone(angles: Angles) -> Geometry {
    Geometry::Cone(ConeBeam {
        angles,
        dso_mm: 150.0,
        dsd_mm: 450.0,
        detector: Panel {
            nu: 7,
            nv: 5,
            du_mm: 0.3,
            dv_mm: 0.25,
            offset_u_mm: 0.0,
            offset_v_mm: -0.5,
        },
    })
}

/// Line integrals that differ in every view, row and column.
fn line_integrals(views: usize) -> Array3<f32> {
    Array3::from_shape_fn((views, 5, 7), |(k, r, c)| {
        0.05 * k as f32 + 0.3 * r as f32 + 0.11 * c as f32
    })
}

fn intensity(p: f32) -> u16 {
    (simulated::WHITE_LEVEL * (-f64::from(p)).exp()).round() as u16
}

/// Reads the TIFFs named on stdin with tifffile and prints them as JSON lists.
const READER: &str = r#"
import sys, json, tifffile
print(json.dumps([tifffile.imread(p).tolist() for p in json.load(sys.stdin)]))
"#;

fn tifffile_read(py: &Path, files: &[String]) -> Vec<Vec<Vec<u64>>> {
    let mut child = Command::new(py)
        .args(["-c", READER])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("start python");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin
            .write_all(serde_json::to_string(files).expect("json").as_bytes())
            .expect("write");
    }
    let out = child.wait_with_output().expect("python");
    assert!(out.status.success(), "tifffile failed");
    serde_json::from_slice(&out.stdout).expect("tifffile's JSON")
}

#[test]
fn a_simulated_nikon_scan_reads_back_as_it_was_made() {
    let cases = [
        Angles::Uniform {
            count: 6,
            start_deg: 10.0,
            range_deg: Some(300.0),
            short_scan: false,
        },
        Angles::List {
            degrees: vec![-20.0, 3.0, 50.0, 51.5, 140.0, 330.0],
        },
    ];
    for angles in cases {
        let dir = tempfile::tempdir().expect("tempdir");
        let geometry = cone(angles);
        let p = line_integrals(6);
        let xtekct = dir.path().join("part.xtekct");
        let w = simulated::write_nikon(&xtekct, &geometry, p.view()).expect("write");
        assert_eq!((w.tiffs, w.clipped), (6, 0));
        let mut scan = scans::open(&xtekct).expect("read");
        assert_eq!(scan.format, scans::Format::NikonXtek);
        let (Ok(Views::D3(ours)), Ok(Views::D3(read))) =
            (geometry.to_views(), scan.geometry.to_views())
        else {
            panic!("cone beams")
        };
        for (a, b) in ours.views.iter().zip(&read.views) {
            let turns = (a.angle_rad - b.angle_rad) / std::f64::consts::TAU;
            assert!((turns - turns.round()).abs() < 1e-9, "angles");
            for i in 0..3 {
                assert!((a.source[i] - b.source[i]).abs() < 1e-9, "sources");
                let (ea, eb) = (
                    ours.element_position(a, 4, 6),
                    read.element_position(b, 4, 6),
                );
                assert!((ea[i] - eb[i]).abs() < 1e-9, "corner elements");
            }
        }
        let mut stored = vec![0f32; 35];
        let mut oriented = vec![0f32; 35];
        for k in 0..6 {
            scan.views.read_view(k, &mut stored).expect("view");
            scan.orientation.apply(&stored, 5, 7, &mut oriented);
            for r in 0..5 {
                for c in 0..7 {
                    assert_eq!(
                        oriented[r * 7 + c],
                        f32::from(intensity(p[[k, r, c]])),
                        "view {k} ({r}, {c})"
                    );
                }
            }
        }
    }
}

#[test]
fn tifffile_reads_the_simulated_views_turned_by_180_degrees() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let p = line_integrals(3);
    let geometry = cone(Angles::Uniform {
        count: 3,
        start_deg: 0.0,
        range_deg: None,
        short_scan: false,
    });
    simulated::write_nikon(&dir.path().join("t.xtekct"), &geometry, p.view()).expect("write");
    let files: Vec<String> = (1..=3)
        .map(|k| {
            dir.path()
                .join(format!("t_{k:04}.tif"))
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    let images = tifffile_read(&py, &files);
    for (k, image) in images.iter().enumerate() {
        assert_eq!((image.len(), image[0].len()), (5, 7));
        for r in 0..5 {
            for c in 0..7 {
                // Image row 0 is the panel's top (+v), column 0 its right: ctrecon's [4 − r][6 − c].
                let want = u64::from(intensity(p[[k, 4 - r, 6 - c]]));
                assert_eq!(image[r][c], want, "view {k} image ({r}, {c})");
            }
        }
    }
}

#[test]
fn a_scan_that_is_not_a_circular_cone_is_not_written_as_nikon() {
    let dir = tempfile::tempdir().expect("tempdir");
    let fan: Geometry = serde_json::from_str(
        r#"{"type": "parallel", "angles": {"count": 4}, "det_count": 7, "det_spacing_mm": 1}"#,
    )
    .expect("geometry");
    let e = simulated::write_nikon(
        &dir.path().join("x.xtekct"),
        &fan,
        Array3::zeros((4, 1, 7)).view(),
    )
    .expect_err("refused");
    assert!(
        e.to_string().contains("give a geometry of type cone"),
        "{e}"
    );
    let short = cone(Angles::Uniform {
        count: 6,
        start_deg: 0.0,
        range_deg: None,
        short_scan: true,
    });
    let e = simulated::write_nikon(
        &dir.path().join("y.xtekct"),
        &short,
        line_integrals(6).view(),
    )
    .expect_err("refused");
    assert!(e.to_string().contains("short scan"), "{e}");
    assert!(!dir.path().join("y.xtekct").exists());
}
