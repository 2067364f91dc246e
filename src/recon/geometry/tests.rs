use proptest::prelude::*;

use super::vectors::{dot2, norm2, sub2};
use super::*;

fn fan(shape_arc: bool, n: usize, offset: f64) -> FanBeam {
    FanBeam {
        angles: Angles::uniform(8, 360.0),
        dso_mm: 500.0,
        dsd_mm: 900.0,
        detector: if shape_arc {
            FanDetector::Arc {
                count: n,
                spacing_deg: 0.1,
                offset_deg: offset,
            }
        } else {
            FanDetector::Flat {
                count: n,
                spacing_mm: 1.5,
                offset_mm: offset,
            }
        },
        centre_mm: [0.0, 0.0],
    }
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn source_starts_on_negative_y_and_turns_counter_clockwise() {
    let v = fan(true, 11, 0.0).to_views().unwrap();
    let Source2::Point { position } = v.views[0].source else {
        panic!()
    };
    assert!(close(position[0], 0.0, 1e-9) && close(position[1], -500.0, 1e-9));
    // View 2 of 8 is at β = 90°: the source has turned from −y to +x.
    let Source2::Point { position } = v.views[2].source else {
        panic!()
    };
    assert!(
        close(position[0], 500.0, 1e-9) && close(position[1], 0.0, 1e-9),
        "{position:?}"
    );
}

#[test]
fn parallel_detector_coordinate_is_x_cos_plus_y_sin() {
    let g = ParallelBeam {
        angles: Angles::uniform(6, 180.0),
        det_count: 5,
        det_spacing_mm: 2.0,
        det_offset_mm: 0.5,
    };
    let v = g.to_views().unwrap();
    for view in &v.views {
        let t = view.angle_rad;
        for k in 0..5 {
            let ray = v.ray(view, k);
            // Every point of the ray has x cos θ + y sin θ = u_k.
            for s in [-100.0, 0.0, 37.0] {
                let p = [
                    ray.origin[0] + s * ray.direction[0],
                    ray.origin[1] + s * ray.direction[1],
                ];
                let u = p[0] * t.cos() + p[1] * t.sin();
                assert!(close(u, v.detector.coord(k), 1e-9));
            }
        }
    }
    assert_eq!(v.detector.coord(2), 0.5);
}

#[test]
fn short_scan_covers_pi_plus_fan_angle_inclusive() {
    let mut g = fan(true, 101, 0.0);
    g.angles = Angles::short_scan(181);
    let v = g.to_views().unwrap();
    let delta = half_fan_angle(&v.detector, g.dsd_mm);
    let last = v.views.last().unwrap().angle_rad;
    assert!(close(last, std::f64::consts::PI + 2.0 * delta, 1e-12));
    assert!(close(delta.to_degrees(), 5.05, 1e-9));
}

#[test]
fn invalid_geometries_are_refused_with_typed_errors() {
    let mut g = fan(false, 10, 0.0);
    g.dsd_mm = 400.0;
    assert!(matches!(
        g.to_views(),
        Err(GeometryError::DetectorInsideOrbit { .. })
    ));
    let g = fan(false, 0, 0.0);
    assert!(matches!(g.to_views(), Err(GeometryError::Zero { .. })));
    let mut g = fan(true, 10, 0.0);
    g.dso_mm = f64::NAN;
    assert!(matches!(g.to_views(), Err(GeometryError::NonFinite { .. })));
    let g = Geometry::Fan(fan(true, 10, 0.0));
    assert!(matches!(
        g.check_fov(600.0),
        Err(GeometryError::SourceInsideFov { .. })
    ));
    let g = ParallelBeam {
        angles: Angles::List {
            degrees: vec![0.0, 1.0, 1.0],
        },
        det_count: 3,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    };
    assert!(matches!(
        g.to_views(),
        Err(GeometryError::AnglesNotMonotonic { index: 2 })
    ));
    let mut g = fan(true, 10, 0.0);
    g.detector = FanDetector::Arc {
        count: 2001,
        spacing_deg: 0.1,
        offset_deg: 0.0,
    };
    assert!(matches!(
        g.to_views(),
        Err(GeometryError::FanTooWide { .. })
    ));
}

#[test]
fn geometry_json_round_trips_and_rejects_unknown_fields() {
    let json = r#"{"type":"fan","angles":{"count":360},"dso_mm":500,"dsd_mm":900,
        "detector":{"shape":"flat","count":256,"spacing_mm":1.2}}"#;
    let g: Geometry = serde_json::from_str(json).unwrap();
    let back: Geometry = serde_json::from_str(&serde_json::to_string(&g).unwrap()).unwrap();
    assert_eq!(g, back);
    assert_eq!(g.to_views().unwrap().data_shape(), vec![360, 256]);
    let bad = json.replace("\"dso_mm\"", "\"dso\"");
    assert!(serde_json::from_str::<Geometry>(&bad).is_err());
    let cone = r#"{"type":"cone","angles":{"count":90,"short_scan":true},"dso_mm":1000,"dsd_mm":1500,
        "detector":{"nu":64,"nv":48,"du_mm":2,"dv_mm":2}}"#;
    let g: Geometry = serde_json::from_str(cone).unwrap();
    assert_eq!(g.to_views().unwrap().data_shape(), vec![90, 48, 64]);
}

#[test]
fn matlab_fanbeam_reproduces_sensor_counts_and_rotation_angles() {
    // fanbeam(phantom(128), 250, 'FanSensorSpacing', s): 2° → 21, 1° → 43, 0.25° → 175 sensors.
    for (s, n) in [(2.0, 21), (1.0, 43), (0.25, 175)] {
        let m = MatlabFan::arc(128, 128, 250.0, s, 1.0);
        assert_eq!(m.sensor_positions().len(), n, "spacing {s}");
        let v = m.to_fan().unwrap().to_views().unwrap();
        assert_eq!(v.shape(), [360, n]);
    }
    let m = MatlabFan::arc(128, 128, 250.0, 1.0, 1.0);
    assert_eq!(m.rotation_angles_deg()[90], 90.0);
    let v = m.to_fan().unwrap().to_views().unwrap();
    // MATLAB θ = 90° is ctrecon β = −90°; the rotation centre is the pixel at (−0.5, −0.5) mm.
    assert!(close(
        v.views[90].angle_rad,
        -std::f64::consts::FRAC_PI_2,
        1e-12
    ));
    let Source2::Point { position } = v.views[0].source else {
        panic!()
    };
    assert!(close(position[0], -0.5, 1e-9) && close(position[1], -250.5, 1e-9));
}

proptest! {
    #[test]
    fn fan_rays_pass_through_source_and_element(arc in any::<bool>(), n in 1usize..400,
            offset in -3.0f64..3.0, dso in 200.0f64..1000.0, extra in 1.0f64..800.0, beta in -7.0f64..7.0) {
        let g = FanBeam {
            angles: Angles::List { degrees: vec![beta.to_degrees()] },
            dso_mm: dso,
            dsd_mm: dso + extra,
            detector: if arc {
                FanDetector::Arc { count: n, spacing_deg: 0.05, offset_deg: offset }
            } else {
                FanDetector::Flat { count: n, spacing_mm: 0.7, offset_mm: offset }
            },
            centre_mm: [0.0, 0.0],
        };
        let v = g.to_views().unwrap();
        let view = v.views[0];
        let Source2::Point { position: s } = view.source else { panic!() };
        prop_assert!((norm2(s) - dso).abs() < 1e-9 * dso);
        // The u axis is perpendicular to the central ray, and the centre of rotation is on the central ray.
        let central = sub2(view.det_centre, s);
        prop_assert!(dot2(central, view.det_u).abs() < 1e-9 * dso);
        prop_assert!((dot2(sub2([0.0, 0.0], s), central) / norm2(central) - dso).abs() < 1e-6);
        for k in [0, n / 2, n - 1] {
            let e = v.element_position(&view, k);
            let r = v.ray(&view, k);
            let to_e = sub2(e, r.origin);
            let cross = to_e[0] * r.direction[1] - to_e[1] * r.direction[0];
            prop_assert!(cross.abs() < 1e-7 * norm2(to_e));
            prop_assert!((norm2(r.direction) - 1.0).abs() < 1e-12);
            if arc {
                prop_assert!((norm2(to_e) - (dso + extra)).abs() < 1e-7);
                // The angle from the central ray equals the element's coordinate.
                let gamma = (dot2(to_e, view.det_u)).atan2(dot2(to_e, central) / norm2(central));
                prop_assert!((gamma - v.detector.coord(k)).abs() < 1e-9);
            } else {
                prop_assert!((dot2(sub2(e, view.det_centre), view.det_u) - v.detector.coord(k)).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn detector_index_and_coordinate_are_inverse(n in 1usize..5000, spacing in 1e-3f64..10.0, offset in -50.0f64..50.0, k in 0usize..5000) {
        let d = Detector1 { count: n, spacing, offset, shape: DetectorShape::Flat };
        let k = k % n;
        prop_assert!((d.index_of(d.coord(k)) - k as f64).abs() < 1e-6);
    }

    #[test]
    fn cone_views_are_orthonormal_and_the_panel_faces_the_source(beta in -7.0f64..7.0, dso in 100.0f64..2000.0, extra in 1.0f64..1000.0) {
        let g = ConeBeam {
            angles: Angles::List { degrees: vec![beta.to_degrees()] },
            dso_mm: dso,
            dsd_mm: dso + extra,
            detector: Panel { nu: 10, nv: 7, du_mm: 1.0, dv_mm: 2.0, offset_u_mm: 3.0, offset_v_mm: -1.0 },
        };
        let v = g.to_views().unwrap();
        let w = v.views[0];
        let axis = vectors::sub3(w.det_centre, w.source);
        prop_assert!(vectors::dot3(axis, w.det_u).abs() < 1e-9 * dso);
        prop_assert!(vectors::dot3(axis, w.det_v).abs() < 1e-9 * dso);
        prop_assert!((vectors::norm3(axis) - (dso + extra)).abs() < 1e-9 * dso);
        prop_assert!((vectors::norm3(w.source) - dso).abs() < 1e-9 * dso);
    }
}

#[test]
fn matlab_sensors_and_rotations_too_many_to_allocate_are_refused_by_count() {
    // A spacing of 2e-311 px asks for about 10^314 sensors: refused before any is allocated.
    let mut m = MatlabFan::arc(2214, 185, 1.57e308, 1.0, 1.0);
    m.sensors = MatlabSensors::Line {
        sensor_spacing: 2.225073858507e-311,
    };
    assert_eq!(m.sensor_count(), None);
    assert!(m.sensor_positions().is_empty());
    assert!(matches!(
        m.to_fan(),
        Err(GeometryError::TooMany { max: MAX_AXIS, .. })
    ));
    // A rotation increment of 1e-300° is at most MAX_VIEWS angles, never 10^302.
    m.rotation_increment_deg = 1e-300;
    assert_eq!(m.rotation_angles_deg().len(), angles::MAX_VIEWS);
}
