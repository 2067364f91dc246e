use super::plan::*;
use super::*;
use crate::volume::{Frame, series_count, whole_ceil};

fn shape() -> VolumeShape {
    VolumeShape {
        dim: (20, 40, 50),
        frame: Frame {
            spacing_mm: [0.5, 0.5, 2.0],
            origin_mm: [-12.25, -9.75, 100.0],
            direction: Frame::AXIS_ALIGNED,
        },
        max_value: None,
    }
}

fn request(json: &str) -> VolumeJobRequest {
    serde_json::from_str(json).unwrap()
}

#[test]
fn requests_parse_with_tagged_steps_and_products_and_refuse_unknown_fields() {
    let r = request(
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
            "steps": [{"op": "resample", "spacing_mm": 1}, {"op": "gaussian", "sigma_mm": 1}, {"op": "median"}],
            "products": [{"type": "projection", "axis": "coronal", "kind": "minip"},
                         {"type": "mpr", "plane": "sagittal", "slab": {"thickness_mm": 3, "kind": "mip"}, "spacing_mm": 3},
                         {"type": "curved", "points_mm": [[0,0,0],[10,0,0]], "height": 8},
                         {"type": "rotating", "frames": 4},
                         {"type": "mesh", "iso": 300, "smoothing": 5}]}"#,
    );
    assert_eq!(r.steps.len(), 3);
    assert_eq!(r.products.len(), 5);
    assert!(
        matches!(&r.products[4], ProductSpec::Mesh(m) if m.iso == 300.0 && m.largest_component)
    );
    for bad in [
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "colour": 1}"#,
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "steps": [{"op": "blur"}]}"#,
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "products": [{"type": "mesh", "iso": 1, "x": 2}]}"#,
        r#"{"kind": "volume", "input": "../etc/passwd"}"#,
    ] {
        assert!(
            serde_json::from_str::<VolumeJobRequest>(bad).is_err(),
            "{bad}"
        );
    }
}

#[test]
fn planning_follows_the_shape_through_resampling_and_sizes_default_planes_to_the_volume() {
    let r = request(
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
            "steps": [{"op": "resample"}],
            "products": [{"type": "mpr", "plane": "coronal"}, {"type": "mpr", "plane": "axial", "spacing_mm": 4}]}"#,
    );
    let p = plan(&r, shape(), 1 << 30).unwrap();
    // 50 × 0.5 = 24.5 mm span → 50 samples; 40 → 40; z: 19 × 2 mm = 38 mm → 77 samples of 0.5 mm.
    assert_eq!(p.output.dim, (77, 40, 50));
    match &p.products[0] {
        Planned::Mpr { plane, .. } => {
            assert_eq!(plane.size, [50, 77]);
            assert!((plane.u[0] - 1.0).abs() < 1e-12 && (plane.v[2] + 1.0).abs() < 1e-12);
        }
        other => panic!("{other:?}"),
    }
    match &p.products[1] {
        Planned::Mpr { series, .. } => assert_eq!(*series, Some((4.0, 19.0))),
        other => panic!("{other:?}"),
    }
}

#[test]
fn rounding_noise_in_the_frame_changes_no_default_size() {
    // The same patient read from another acquisition: its spacing and origin derived from slice
    // positions, a few ulps off.
    let exact = VolumeShape {
        dim: (10, 14, 18),
        frame: Frame {
            spacing_mm: [0.8, 1.0, 2.0],
            origin_mm: [-7.0, -5.0, 40.0],
            direction: Frame::AXIS_ALIGNED,
        },
        max_value: None,
    };
    let mut noisy = exact;
    noisy.frame.spacing_mm[0] = 0.7999999999999998;
    noisy.frame.origin_mm[0] = -6.999999999999999;
    let r = request(
        r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
            "products": [{"type": "mpr", "plane": "coronal", "centre_mm": [-4.6, -2, 44]},
                         {"type": "mpr", "plane": "sagittal", "centre_mm": [-0.6, 1, 50], "spacing_mm": 0.8}]}"#,
    );
    let (a, b) = (
        plan(&r, exact, 1 << 30).unwrap(),
        plan(&r, noisy, 1 << 30).unwrap(),
    );
    for (x, y) in a.products.iter().zip(&b.products) {
        match (x, y) {
            (
                Planned::Mpr {
                    plane: p,
                    series: s,
                    ..
                },
                Planned::Mpr {
                    plane: q,
                    series: t,
                    ..
                },
            ) => {
                assert_eq!(p.size, q.size);
                let count = |s: &Option<(f64, f64)>| s.map(|(sp, ext)| series_count(sp, ext));
                assert_eq!(count(s), count(t));
            }
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(whole_ceil(36.00000000000001), 36.0);
    assert_eq!(whole_ceil(36.01), 37.0);
    assert_eq!(series_count(0.8, 6.3999999999999995), 17);
}

#[test]
fn bad_parameters_and_jobs_beyond_the_budget_are_refused_before_running() {
    let base = r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "#;
    for (body, code) in [
        (
            r#""steps": [{"op": "resample", "spacing_mm": 0}]}"#,
            "invalid_parameter",
        ),
        (
            r#""steps": [{"op": "resample", "spacing_mm": 0.001}]}"#,
            "invalid_parameter",
        ),
        (
            r#""steps": [{"op": "gaussian", "sigma_mm": -1}]}"#,
            "invalid_parameter",
        ),
        (r#""products": [{"type": "mpr"}]}"#, "invalid_parameter"),
        (
            r#""products": [{"type": "mpr", "plane": "axial", "normal": [0,0,1]}]}"#,
            "invalid_parameter",
        ),
        (
            r#""products": [{"type": "mpr", "normal": [0,0,0]}]}"#,
            "invalid_parameter",
        ),
        (
            r#""products": [{"type": "mpr", "plane": "axial", "size": [0, 10]}]}"#,
            "invalid_parameter",
        ),
        (
            r#""products": [{"type": "projection", "slab": [5, 5]}]}"#,
            "invalid_slab",
        ),
        (
            r#""products": [{"type": "curved", "points_mm": [[0,0,0]], "height": 4}]}"#,
            "invalid_parameter",
        ),
        (
            r#""products": [{"type": "rotating", "frames": 0}]}"#,
            "invalid_parameter",
        ),
        (
            r#""products": [{"type": "mesh", "iso": 1, "smoothing": 100000}]}"#,
            "invalid_mesh_options",
        ),
    ] {
        let r = request(&format!("{base}{body}"));
        let e = plan(&r, shape(), 1 << 30).unwrap_err();
        assert_eq!(e.code.code(), code, "{body}: {e}");
    }
    let r = request(&format!("{base}\"steps\": [{{\"op\": \"median\"}}]}}"));
    let e = plan(&r, shape(), 100_000).unwrap_err();
    assert_eq!(e.code, ErrorCode::JobTooLarge);
}
