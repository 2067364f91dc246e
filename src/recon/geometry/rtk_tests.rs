//! RTK geometry XML: round trips through ctrecon's per-view form, a file as itk-rtk 2.7 writes it, and
//! files that are refused with the element at fault named.

use super::per_view_tests::assert_same_views;
use super::rtk::{from_rtk_xml, parse_rtk_xml, to_rtk_xml};
use super::*;

fn cone(offset_u_mm: f64, offset_v_mm: f64) -> ConeBeam {
    ConeBeam {
        angles: Angles::Uniform {
            count: 24,
            start_deg: 200.0,
            range_deg: Some(-300.0),
            short_scan: false,
        },
        dso_mm: 200.0,
        dsd_mm: 350.0,
        detector: Panel {
            nu: 48,
            nv: 36,
            du_mm: 1.3,
            dv_mm: 1.1,
            offset_u_mm,
            offset_v_mm,
        },
    }
}

fn back(xml: &str) -> Views3 {
    let g = from_rtk_xml(xml, VectorPanel { nu: 48, nv: 36 }, [1.3, 1.1]).unwrap();
    g.to_views().unwrap()
}

#[test]
fn a_cone_beam_survives_the_trip_through_rtk_xml() {
    let a = cone(3.1, -4.3).to_views().unwrap();
    let xml = to_rtk_xml(&a).unwrap();
    assert_eq!(xml.matches("<Projection>").count(), 24);
    let p = parse_rtk_xml(&xml).unwrap();
    // RTK's gantry angle is ctrecon's view angle, in [0°, 360°); the panel offsets are projection offsets.
    assert!(
        (p[0].gantry_deg - 200.0).abs() < 1e-9,
        "{}",
        p[0].gantry_deg
    );
    assert!(
        (p[1].gantry_deg - 187.5).abs() < 1e-9,
        "{}",
        p[1].gantry_deg
    );
    assert!((p[0].sid - 200.0).abs() < 1e-9 && (p[0].sdd - 350.0).abs() < 1e-9);
    assert!((p[0].projection_offset[0] - 3.1).abs() < 1e-9);
    assert!((p[0].projection_offset[1] + 4.3).abs() < 1e-9);
    assert!(p[0].out_of_plane_deg.abs() < 1e-9 && p[0].in_plane_deg.abs() < 1e-9);
    assert_same_views(&a, &back(&xml));
}

/// A trajectory with a tilted, rolled panel and a source off the central plane: all nine RTK numbers
/// are used, and the views come back.
#[test]
fn a_general_trajectory_survives_the_trip_through_rtk_xml() {
    let circle = cone(0.0, 0.0).to_views().unwrap();
    let mut g = cone_vectors(&circle);
    for (k, r) in g.vectors.iter_mut().enumerate() {
        let t = k as f64 * 0.37;
        // Roll the panel about its normal by t/10 rad and lift the source.
        let (s, c) = (t / 10.0).sin_cos();
        let u = [r[6], r[7], r[8]];
        let v = [r[9], r[10], r[11]];
        let (du, dv) = (1.3, 1.1);
        let eu = [u[0] / du, u[1] / du, u[2] / du];
        let ev = [v[0] / dv, v[1] / dv, v[2] / dv];
        for i in 0..3 {
            r[6 + i] = du * (c * eu[i] + s * ev[i]);
            r[9 + i] = dv * (-s * eu[i] + c * ev[i]);
        }
        r[2] += 5.0 * t.sin();
        r[3] += 2.0;
    }
    let a = g.to_views().unwrap();
    let xml = to_rtk_xml(&a).unwrap();
    let p = parse_rtk_xml(&xml).unwrap();
    assert!(p.iter().any(|q| q.in_plane_deg.abs() > 10.0));
    assert!(p.iter().any(|q| q.source_offset[1].abs() > 1.0));
    assert_same_views(&a, &back(&xml));
}

/// Written by itk-rtk 2.7.0.post1 (`ThreeDCircularProjectionGeometryXMLFileWriter`) for
/// `AddProjection(200, 350, 30, 3, -4)` and `AddProjection(200, 350, 120, 3, -4, 2, 5, 1.5, -0.5)`; RTK's
/// `GetSourcePosition` gave (100, 0, 173.20508076) and (172.3195308, −7.34703929, −101.26450671).
const FROM_RTK: &str = r#"<?xml version="1.0"?>
<!DOCTYPE RTKGEOMETRY>
<RTKThreeDCircularGeometry version="3">
    <SourceToIsocenterDistance>200</SourceToIsocenterDistance>
    <SourceToDetectorDistance>350</SourceToDetectorDistance>
    <ProjectionOffsetX>3</ProjectionOffsetX>
    <ProjectionOffsetY>-4</ProjectionOffsetY>
  <Projection>
    <GantryAngle>30</GantryAngle>
    <SourceOffsetX>0</SourceOffsetX>
    <SourceOffsetY>0</SourceOffsetY>
    <InPlaneAngle>0</InPlaneAngle>
    <OutOfPlaneAngle>0</OutOfPlaneAngle>
    <Matrix>
        -304.608891324554                   0    172.401923788647                 600
                        2                -350    3.46410161513775                -800
                      0.5                   0   0.866025403784439                -200
    </Matrix>
  </Projection>
  <Projection>
    <GantryAngle>120</GantryAngle>
    <SourceOffsetX>1.5</SourceOffsetX>
    <SourceOffsetY>-0.5</SourceOffsetY>
    <InPlaneAngle>5</InPlaneAngle>
    <OutOfPlaneAngle>2</OutOfPlaneAngle>
    <Matrix>
         172.113861643814   -30.4335781933622    303.237309624661                 825
        -22.7611064714516   -348.577893357741   -22.0824431274013                -875
        0.865497844507677  -0.034899496702501  -0.499695413509548                -200
    </Matrix>
  </Projection>
</RTKThreeDCircularGeometry>
"#;

#[test]
fn a_file_written_by_rtk_reads_with_rtk_source_positions() {
    let v = back(FROM_RTK);
    let rtk = [
        [100.0, 0.0, 173.205_080_76],
        [172.319_530_8, -7.347_039_29, -101.264_506_71],
    ];
    for (w, r) in v.views.iter().zip(rtk) {
        // RTK (x, y, z) is ctrecon (x, −z, y).
        let want = [r[0], -r[2], r[1]];
        for i in 0..3 {
            assert!(
                (w.source[i] - want[i]).abs() < 1e-6,
                "{:?} vs {want:?}",
                w.source
            );
        }
    }
    // View 0 is a plain circular view at β = 30° with the panel shifted by (3, −4) mm.
    let (s, c) = 30f64.to_radians().sin_cos();
    let foot = [200.0 * s - 350.0 * s, -200.0 * c + 350.0 * c, 0.0];
    let d = v.views[0].det_centre;
    let want = [foot[0] + 3.0 * c, foot[1] + 3.0 * s, -4.0];
    for i in 0..3 {
        assert!((d[i] - want[i]).abs() < 1e-9, "{d:?} vs {want:?}");
    }
    // Written back, the second projection keeps RTK's numbers.
    let again = parse_rtk_xml(&to_rtk_xml(&v).unwrap()).unwrap();
    let q = again[1];
    for (got, want) in [
        (q.gantry_deg, 120.0),
        (q.out_of_plane_deg, 2.0),
        (q.in_plane_deg, 5.0),
        (q.source_offset[0], 1.5),
        (q.source_offset[1], -0.5),
        (q.projection_offset[0], 3.0),
        (q.projection_offset[1], -4.0),
        (q.sdd, 350.0),
    ] {
        assert!((got - want).abs() < 1e-9, "{q:?}");
    }
}

fn refused(xml: &str) -> String {
    match from_rtk_xml(xml, VectorPanel { nu: 4, nv: 4 }, [1.0, 1.0]) {
        Err(e) => e.to_string(),
        Ok(g) => panic!("accepted {g:?}"),
    }
}

#[test]
fn files_that_are_not_sound_rtk_geometries_are_refused() {
    let wrong = FROM_RTK.replacen("-200\n    </Matrix>", "-200.5\n    </Matrix>", 1);
    assert!(refused(&wrong).contains("<Projection> 0: <Matrix> entry [2][3] is -200.5"));
    let no_sid = FROM_RTK.replace(
        "<SourceToIsocenterDistance>200</SourceToIsocenterDistance>",
        "",
    );
    assert!(refused(&no_sid).contains("<SourceToIsocenterDistance> is missing"));
    let cyl = FROM_RTK.replace(
        "<GantryAngle>30</GantryAngle>",
        "<GantryAngle>30</GantryAngle><RadiusCylindricalDetector>900</RadiusCylindricalDetector>",
    );
    assert!(refused(&cyl).contains("flat panels only"));
    let odd = FROM_RTK.replace("<InPlaneAngle>0</InPlaneAngle>", "<Wobble>1</Wobble>");
    assert!(refused(&odd).contains("<Wobble>: not an element"));
    let nan = FROM_RTK.replace(
        "<GantryAngle>30</GantryAngle>",
        "<GantryAngle>x</GantryAngle>",
    );
    assert!(refused(&nan).contains("<GantryAngle>: \"x\" is not a finite number"));
    assert!(refused("<svg></svg>").contains("unexpected element <svg>"));
    assert!(
        refused("<RTKThreeDCircularGeometry version=\"3\"></RTKThreeDCircularGeometry>")
            .contains("no <Projection>")
    );
    let cut = &FROM_RTK[..FROM_RTK.find("</Matrix>").unwrap_or(0)];
    let e = refused(cut);
    assert!(
        e.contains("ends inside") || e.contains("not well-formed"),
        "{e}"
    );
}
