//! The preprocessing plan: the shape, geometry and record it gives, in its fixed order.

use ndarray::Array2;
use serde_json::json;

use super::plan::PrepPlan;
use crate::recon::geometry::{Angles, ConeBeam, Geometry, Panel};

fn cone() -> Geometry {
    Geometry::Cone(ConeBeam {
        angles: Angles::Uniform {
            count: 10,
            start_deg: 0.0,
            range_deg: None,
            short_scan: false,
        },
        dso_mm: 100.0,
        dsd_mm: 300.0,
        detector: Panel {
            nu: 12,
            nv: 8,
            du_mm: 0.5,
            dv_mm: 0.25,
            offset_u_mm: 1.0,
            offset_v_mm: 0.0,
        },
    })
}

fn plan(v: serde_json::Value) -> PrepPlan {
    serde_json::from_value(v).expect("plan")
}

#[test]
fn the_plan_gives_the_shape_geometry_and_record_of_its_steps() {
    let p = plan(
        json!({"angles": {"start": 1, "step": 3}, "crop": {"u0": 2, "v0": 0, "nu": 8, "nv": 8},
                        "bin": {"u": 2, "v": 2}, "linearise": {"coefficients": [0, 2]},
                        "stripes": {"size": 3}}),
    );
    assert_eq!(p.kept_views(10).unwrap(), vec![1, 4, 7]);
    assert_eq!(p.view_shape(8, 12).unwrap(), (4, 4));
    p.check(10, 8, 12).unwrap();
    let Geometry::Cone(g) = p.geometry(&cone()).unwrap() else {
        panic!("a cone")
    };
    assert_eq!((g.detector.nu, g.detector.nv), (4, 4));
    assert_eq!((g.detector.du_mm, g.detector.dv_mm), (1.0, 0.5));
    // Columns 2..10 have their middle at 5.5, as the panel's 0..12 does: the u offset is kept.
    assert_eq!(g.detector.offset_u_mm, 1.0);
    let Angles::List { degrees } = &g.angles else {
        panic!("the kept angles are listed")
    };
    let want = [36.0, 144.0, 252.0];
    for (a, b) in degrees.iter().zip(want) {
        assert!((a - b).abs() < 1e-9, "{degrees:?}");
    }
    // A view: crop, then 2 × 2 means, then doubled by the polynomial.
    let view = Array2::from_shape_fn((8, 12), |(r, c)| (r * 12 + c) as f32);
    let out = p.apply_view(view.view()).unwrap();
    // Output [0][0] averages rows 0..2, columns 2..4: (2 + 3 + 14 + 15) / 4 = 8.5, doubled.
    assert_eq!(out[[0, 0]], 17.0);
    // [3][3]: rows 6..8, cropped columns 6..8 = columns 8..10: (80 + 81 + 92 + 93) / 4, doubled.
    assert_eq!(out[[3, 3]], 173.0);
    let names: Vec<String> = p
        .steps(10, 3)
        .iter()
        .map(|s| s["step"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(
        names,
        ["angle_subset", "crop", "bin", "linearise", "stripes"]
    );
    assert_eq!(p.steps(10, 3)[0]["views_after"], 3);
}

#[test]
fn plans_that_cannot_apply_are_refused_before_any_work() {
    assert!(PrepPlan::default().is_empty());
    assert!(PrepPlan::default().geometry(&cone()).unwrap() == cone());
    for (v, word) in [
        (json!({"stripes": {"size": 4}}), "size"),
        (
            json!({"crop": {"u0": 10, "v0": 0, "nu": 4, "nv": 4}}),
            "exceeds the panel",
        ),
        (json!({"bin": {"u": 0, "v": 1}}), "at least 1"),
        (json!({"angles": {"start": 10, "step": 1}}), "start"),
        (json!({"linearise": {"coefficients": []}}), "coefficients"),
    ] {
        let e = plan(v.clone()).check(10, 8, 12).unwrap_err().to_string();
        assert!(e.contains(word), "{v}: {e}");
    }
    assert!(serde_json::from_value::<PrepPlan>(json!({"rings": {}})).is_err());
    let parallel: Geometry = serde_json::from_value(
        json!({"type": "parallel", "angles": {"count": 4}, "det_count": 8, "det_spacing_mm": 1}),
    )
    .unwrap();
    assert!(
        plan(json!({"bin": {"u": 2, "v": 1}}))
            .geometry(&parallel)
            .is_err()
    );
    assert!(PrepPlan::stripe_rows(3000, 2000) >= 1);
    assert_eq!(
        PrepPlan::stripe_rows(1, 1),
        super::plan::STRIPE_BLOCK_BYTES / 4
    );
}
