//! Per-view (vector) geometries: exact round trips with the parametric geometries, refusals that name the
//! view and the number at fault, and reconstructions on a trajectory no parametric geometry describes.

use ndarray::{Array3, ArrayD};

use super::vectors::{norm2, norm3, sub2, sub3};
use super::*;
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid, reconstruct};
use crate::recon::control::unattended;
use crate::recon::grid::{Limits, VolumeGrid};
use crate::recon::phantom::{Ellipsoid, Phantom3};

fn cone(angles: Angles, offset_u_mm: f64, offset_v_mm: f64) -> ConeBeam {
    ConeBeam {
        angles,
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

fn full(count: usize, start_deg: f64) -> Angles {
    Angles::Uniform {
        count,
        start_deg,
        range_deg: None,
        short_scan: false,
    }
}

fn views3(g: &Geometry) -> Views3 {
    match g.to_views() {
        Ok(Views::D3(v)) => v,
        other => panic!("a cone beam, got {other:?}"),
    }
}

/// Every element's position and every source agree to 1e-9 mm; angles agree modulo a turn.
pub(super) fn assert_same_views(a: &Views3, b: &Views3) {
    assert_eq!(a.shape(), b.shape());
    for (k, (va, vb)) in a.views.iter().zip(&b.views).enumerate() {
        assert!(norm3(sub3(va.source, vb.source)) < 1e-9, "view {k} source");
        let turns = (va.angle_rad - vb.angle_rad) / std::f64::consts::TAU;
        assert!((turns - turns.round()).abs() < 1e-12, "view {k} angle");
        for (r, c) in [(0, 0), (0, 47), (35, 0), (35, 47), (17, 30)] {
            let pa = a.element_position(va, r, c);
            let pb = b.element_position(vb, r, c);
            assert!(norm3(sub3(pa, pb)) < 1e-9, "view {k} element [{r}][{c}]");
        }
    }
}

#[test]
fn a_cone_beam_survives_the_trip_through_vectors_and_json() {
    for (angles, ou, ov) in [
        (full(24, 0.0), 0.0, 0.0),
        (full(24, 200.0), 3.1, -4.3),
        (
            Angles::Uniform {
                count: 30,
                start_deg: 15.0,
                range_deg: Some(-300.0),
                short_scan: false,
            },
            20.0,
            0.0,
        ),
    ] {
        let g = Geometry::Cone(cone(angles, ou, ov));
        let a = views3(&g);
        let vectors = Geometry::ConeVectors(cone_vectors(&a));
        let json = serde_json::to_string(&vectors).unwrap();
        assert!(json.starts_with(r#"{"type":"cone_vectors","detector":{"nu":48,"nv":36}"#));
        let back: Geometry = serde_json::from_str(&json).unwrap();
        let b = views3(&back);
        assert_same_views(&a, &b);
        assert_eq!(b.detector.du_mm, 1.3);
        assert!((b.detector.dv_mm - 1.1).abs() < 1e-15);
        // The panel offsets moved into the detector centres.
        assert_eq!((b.detector.offset_u_mm, b.detector.offset_v_mm), (0.0, 0.0));
    }
}

#[test]
fn a_flat_fan_beam_survives_the_trip_through_vectors() {
    let fan = FanBeam {
        angles: full(20, 30.0),
        dso_mm: 500.0,
        dsd_mm: 900.0,
        detector: FanDetector::Flat {
            count: 64,
            spacing_mm: 1.5,
            offset_mm: 7.0,
        },
        centre_mm: [0.0, 0.0],
    };
    let a = fan.to_views().unwrap();
    let v = fan_vectors(&a).unwrap();
    let json = serde_json::to_value(Geometry::FanVectors(v)).unwrap();
    let Ok(Views::D2(b)) = serde_json::from_value::<Geometry>(json).unwrap().to_views() else {
        panic!("a fan beam")
    };
    for (va, vb) in a.views.iter().zip(&b.views) {
        assert_eq!(va.source, vb.source);
        for k in [0, 31, 63] {
            let d = sub2(a.element_position(va, k), b.element_position(vb, k));
            assert!(norm2(d) < 1e-9);
        }
    }
    // An arc detector has no flat-fan vector form.
    let arc = FanBeam {
        detector: FanDetector::Arc {
            count: 10,
            spacing_deg: 0.5,
            offset_deg: 0.0,
        },
        ..fan
    };
    assert!(fan_vectors(&arc.to_views().unwrap()).is_none());
}

fn one_view(row: [f64; 12]) -> Geometry {
    Geometry::ConeVectors(ConeVectors {
        detector: VectorPanel { nu: 4, nv: 4 },
        vectors: vec![
            [
                0.0, -100.0, 0.0, 0.0, 100.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ],
            row,
        ],
    })
}

fn refusal(g: &Geometry) -> String {
    match g.to_views() {
        Err(e) => e.to_string(),
        Ok(_) => panic!("accepted {g:?}"),
    }
}

#[test]
fn vectors_that_ctrecon_cannot_take_are_refused_naming_the_view() {
    let good = [
        100.0, 0.0, 0.0, -100.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0,
    ];
    assert!(one_view(good).to_views().is_ok());
    let mut wider = good;
    wider[7] = 1.5;
    assert!(refusal(&one_view(wider)).contains("`vectors[1]`: the u (column) step is 1.5 mm long"));
    let mut skew = good;
    skew[11] = 0.9;
    skew[10] = 0.435_889_894_354_067_4; // |v| = 1, 25.8° away from ⟂ u
    assert!(refusal(&one_view(skew)).contains("rectangular detector elements"));
    let mut flat_on = good;
    flat_on[0] = -100.0;
    flat_on[1] = 5.0; // on the detector plane x = −100
    assert!(refusal(&one_view(flat_on)).contains("the source lies in the detector's plane"));
    let mut nan = good;
    nan[4] = f64::NAN;
    assert!(refusal(&one_view(nan)).contains("`vectors[1][4]` must be finite"));
    let mut zero = good;
    zero[9..12].copy_from_slice(&[0.0, 0.0, 0.0]);
    assert!(refusal(&one_view(zero)).contains("has length 0"));
    let empty = Geometry::ConeVectors(ConeVectors {
        detector: VectorPanel { nu: 4, nv: 4 },
        vectors: vec![],
    });
    assert!(refusal(&empty).contains("`vectors` must be at least 1"));
    // A row of 11 numbers is refused by the parser.
    let short = r#"{"type": "cone_vectors", "detector": {"nu": 2, "nv": 2}, "vectors": [[1,2,3,4,5,6,7,8,9,10,11]]}"#;
    assert!(serde_json::from_str::<Geometry>(short).is_err());
}

fn phantom() -> Phantom3 {
    let e = |value, a, b, c, x0, y0, z0| Ellipsoid {
        value,
        a,
        b,
        c,
        x0,
        y0,
        z0,
        phi_deg: 20.0,
        theta_deg: 0.0,
        psi_deg: 0.0,
    };
    Phantom3::new(
        vec![
            e(0.02, 0.6, 0.45, 0.5, 0.1, -0.05, 0.05),
            e(0.01, 0.2, 0.3, 0.25, -0.2, 0.15, -0.1),
        ],
        40.0,
    )
    .unwrap()
}

fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 32,
        ny: 32,
        nz: 24,
        spacing_mm: [2.0, 2.0, 2.0],
        centre_mm: [0.0, 0.0, 0.0],
    }
}

fn run(spec: &str, g: &Geometry, proj: &Array3<f32>) -> Result<ArrayD<f32>, String> {
    let spec: AlgorithmSpec = serde_json::from_str(spec).unwrap();
    reconstruct(
        &spec,
        &g.to_views().map_err(|e| e.to_string())?,
        proj.view().into_dyn(),
        &OutputGrid::Volume(grid()),
        &Limits::default(),
        unattended(),
    )
    .map_err(|e| e.to_string())
}

fn rmse(a: &ArrayD<f32>, truth: &Array3<f32>) -> f64 {
    let s: f64 = a
        .iter()
        .zip(truth.iter())
        .map(|(x, y)| f64::from(x - y).powi(2))
        .sum();
    (s / truth.len() as f64).sqrt()
}

/// FDK takes a per-view geometry that describes a circular orbit and gives the parametric geometry's
/// volume, also with an offset (Wang-weighted) panel whose middle is off the central ray.
#[test]
fn fdk_of_a_circular_orbit_given_as_vectors_equals_fdk_of_the_cone_beam() {
    for (ou, ov) in [(0.0, 0.0), (14.0, -2.0)] {
        let g = Geometry::Cone(cone(full(72, 10.0), ou, ov));
        let a = views3(&g);
        let proj = phantom().project(&a);
        let as_vectors = Geometry::ConeVectors(cone_vectors(&a));
        let direct = run(r#"{"name": "fdk"}"#, &g, &proj).unwrap();
        let via = run(r#"{"name": "fdk"}"#, &as_vectors, &proj).unwrap();
        let top = direct.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = direct
            .iter()
            .zip(&via)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(top > 0.01, "empty image");
        assert!(
            worst <= 1e-4 * top,
            "offset ({ou}, {ov}): {worst} against {top}"
        );
    }
}

/// A trajectory with a source-to-axis distance that wobbles by ±8 % and a source that rises and falls by
/// ±6 mm: FDK refuses it with a pointer to the iterative methods; CGLS on the vectors reconstructs the
/// phantom as well as it does from the circular scan (RMSE within 15 %).
#[test]
fn a_non_circular_trajectory_is_refused_by_fdk_and_reconstructed_by_cgls() {
    let circle = views3(&Geometry::Cone(cone(full(60, 0.0), 0.0, 0.0)));
    let mut wobble = cone_vectors(&circle);
    for (k, row) in wobble.vectors.iter_mut().enumerate() {
        let t = k as f64 / 60.0 * std::f64::consts::TAU;
        let r = 1.0 + 0.08 * (3.0 * t).sin();
        let dz = 6.0 * (2.0 * t).cos();
        for i in [0, 1] {
            row[i] *= r;
        }
        row[2] += dz;
        row[5] += dz;
    }
    let wobble = Geometry::ConeVectors(wobble);
    let truth = phantom().rasterize(&grid(), 2);
    let refused = run(r#"{"name": "fdk"}"#, &wobble, &Array3::zeros((60, 36, 48))).unwrap_err();
    assert!(
        refused.contains("circular orbit") && refused.contains("iterative methods"),
        "{refused}"
    );
    let cgls = r#"{"name": "cgls", "iterations": 12}"#;
    let on_circle = run(
        cgls,
        &Geometry::Cone(cone(full(60, 0.0), 0.0, 0.0)),
        &phantom().project(&circle),
    )
    .unwrap();
    let proj = phantom().project(&views3(&wobble));
    let on_wobble = run(cgls, &wobble, &proj).unwrap();
    let (e_circle, e_wobble) = (rmse(&on_circle, &truth), rmse(&on_wobble, &truth));
    let scale = truth.iter().fold(0.0f32, |m, v| m.max(*v)) as f64;
    println!("CGLS RMSE: circle {e_circle:.5}, wobble {e_wobble:.5} (peak {scale})");
    assert!(e_circle < 0.25 * scale, "the circle itself reconstructs");
    assert!(e_wobble < 1.15 * e_circle, "{e_wobble} vs {e_circle}");
    // The wobble matters: the same projections taken as a circle reconstruct far worse.
    let as_circle = run(cgls, &Geometry::Cone(cone(full(60, 0.0), 0.0, 0.0)), &proj).unwrap();
    let e_wrong = rmse(&as_circle, &truth);
    println!("CGLS RMSE of the wobble taken as a circle: {e_wrong:.5}");
    assert!(e_wrong > 1.3 * e_wobble, "{e_wrong} vs {e_wobble}");
}
