use super::vectors::{dot3, norm3, sub3};
use super::*;
use crate::recon::phantom::{Ellipsoid, Phantom3};

const JSON: &str = r#"{"type": "helical", "dso_mm": 595.0, "dsd_mm": 1085.6, "pitch": 1.0, "turns": 2.5,
    "views_per_turn": 64, "start_deg": 30.0, "z_start_mm": -20.0, "rotation": "cw",
    "detector": {"nu": 48, "nv": 8, "du_mm": 1.2858, "dv_mm": 1.0947, "shape": "cylindrical"},
    "flying_focal_spot": {"offsets": [{"phi_deg": 0.02, "z_mm": -0.3}, {"phi_deg": -0.02, "z_mm": 0.3}]}}"#;

fn helical(json: &str) -> Result<Views3, String> {
    let g: Geometry = serde_json::from_str(json).map_err(|e| e.to_string())?;
    match g.to_views().map_err(|e| e.to_string())? {
        Views::D3(v) => Ok(v),
        other => Err(format!("not a cone beam: {other:?}")),
    }
}

#[test]
fn the_helical_json_round_trips_and_is_3d() {
    let g: Geometry = serde_json::from_str(JSON).unwrap();
    assert!(g.is_3d());
    assert_eq!(g.dso_mm(), Some(595.0));
    let again: Geometry = serde_json::from_str(&serde_json::to_string(&g).unwrap()).unwrap();
    assert_eq!(g, again);
    let Geometry::Helical(h) = &g else {
        panic!("not helical: {g:?}")
    };
    assert_eq!(h.rotation, Rotation::Cw);
    assert_eq!(h.detector.shape, PanelShape::Cylindrical);
    // 2.5 turns of 64 views.
    assert_eq!(g.to_views().unwrap().data_shape(), vec![160, 8, 48]);
}

/// Pitch 1 moves the table by the detector's height at the rotation axis per turn; the sources lie on
/// the helix of radius DSO, angles fall for a clockwise rotation, and the flying focal spot alternates.
#[test]
fn views_climb_a_helix_of_the_stated_pitch() {
    let v = helical(JSON).unwrap();
    let feed = 8.0 * 1.0947 * 595.0 / 1085.6;
    for (k, view) in v.views.iter().enumerate() {
        let t = k as f64 / 64.0;
        let beta = 30f64.to_radians() - std::f64::consts::TAU * t;
        assert!((view.angle_rad - beta).abs() < 1e-12);
        let (dphi, dz) = if k % 2 == 0 {
            (0.02f64, -0.3)
        } else {
            (-0.02, 0.3)
        };
        let b = beta + dphi.to_radians();
        let want = [595.0 * b.sin(), -595.0 * b.cos(), -20.0 + feed * t + dz];
        assert!(norm3(sub3(view.source, want)) < 1e-9, "view {k}");
        // The detector does not move with the focal spot: its centre is DSD from the nominal source.
        let nominal = [595.0 * beta.sin(), -595.0 * beta.cos(), -20.0 + feed * t];
        assert!((norm3(sub3(view.det_centre, nominal)) - 1085.6).abs() < 1e-9);
        assert_eq!(view.det_v, [0.0, 0.0, 1.0]);
    }
    let feed_json = JSON.replace(r#""pitch": 1.0"#, &format!(r#""feed_mm_per_turn": {feed}"#));
    let by_feed = helical(&feed_json).unwrap();
    for (a, b) in v.views.iter().zip(&by_feed.views) {
        assert!(norm3(sub3(a.source, b.source)) < 1e-9);
    }
}

/// Columns of a cylindrical detector lie on the cylinder of radius DSD about the source's vertical,
/// one arc pitch apart; the central column (odd count) sits where the flat panel's does.
#[test]
fn a_cylindrical_detector_puts_its_columns_on_an_arc_about_the_source() {
    let v = helical(&JSON.replace(r#""nu": 48"#, r#""nu": 49"#)).unwrap();
    let view = &v.views[3];
    let horizontal = |p: Vec3| {
        let d = sub3(p, view.source);
        d[0].hypot(d[1])
    };
    // With the flying focal spot's φ offset the radius is the source's distance from the panel centre.
    let radius = horizontal(view.det_centre);
    assert!((radius - 1085.6).abs() < 0.5);
    for col in 0..49 {
        for row in [0, 7] {
            let e = v.element_position(view, row, col);
            assert!((horizontal(e) - radius).abs() < 1e-9, "column {col}");
            assert!((e[2] - (view.det_centre[2] + v.detector.v(row))).abs() < 1e-9);
        }
    }
    let centre = v.element_position(view, 0, 24);
    assert!((centre[0] - view.det_centre[0]).abs() < 1e-9);
    assert!((centre[1] - view.det_centre[1]).abs() < 1e-9);
    // Neighbouring columns subtend du/DSD at the source.
    let a = sub3(v.element_position(view, 0, 10), view.source);
    let b = sub3(v.element_position(view, 0, 11), view.source);
    let flat = |d: Vec3| [d[0], d[1], 0.0];
    let cos = dot3(flat(a), flat(b)) / (norm3(flat(a)) * norm3(flat(b)));
    assert!((cos.acos() - 1.2858 / radius).abs() < 1e-9);
}

#[test]
fn invalid_helical_scans_are_refused_with_the_field_named() {
    let cases = [
        (r#""pitch": 1.0"#, r#""pitch": 0.0"#, "pitch"),
        (r#""pitch": 1.0"#, r#""pitch": -1.0"#, "pitch"),
        (r#""turns": 2.5"#, r#""turns": 0.0"#, "turns"),
        (r#""turns": 2.5"#, r#""turns": -2.0"#, "turns"),
        (
            r#""views_per_turn": 64"#,
            r#""views_per_turn": 8"#,
            "views_per_turn",
        ),
        (
            r#""dsd_mm": 1085.6"#,
            r#""dsd_mm": 500.0"#,
            "source-to-detector",
        ),
        (
            r#""pitch": 1.0"#,
            r#""pitch": 1.0, "feed_mm_per_turn": 5.0"#,
            "not both",
        ),
        (r#""pitch": 1.0,"#, "", "`pitch`"),
        (r#""nv": 8"#, r#""nv": 0"#, "detector.nv"),
        (
            r#""shape": "cylindrical""#,
            r#""shape": "spherical""#,
            "unknown variant",
        ),
        (
            r#""rotation": "cw""#,
            r#""rotation": "left""#,
            "unknown variant",
        ),
        (
            r#""turns": 2.5"#,
            r#""turns": 2.5, "tilt_deg": 1"#,
            "unknown field",
        ),
        (r#""phi_deg": 0.02"#, r#""phi_deg": 5.0"#, "phi_deg"),
        (
            r#""offsets": [{"#,
            r#""offsets": [], "x": [{"#,
            "unknown field",
        ),
    ];
    for (from, to, needle) in cases {
        let json = JSON.replacen(from, to, 1);
        assert_ne!(json, JSON, "{from}");
        let err = helical(&json).expect_err(to);
        assert!(err.contains(needle), "{to}: {err}");
    }
    let empty = JSON.replace(
        r#"[{"phi_deg": 0.02, "z_mm": -0.3}, {"phi_deg": -0.02, "z_mm": 0.3}]"#,
        "[]",
    );
    assert!(helical(&empty).unwrap_err().contains("offsets"));
}

/// The exact projection of one ball on a helical trajectory is its chord length, 2√(ρ² − d²) for a ray
/// passing at distance d from the centre, on flat and cylindrical detectors alike.
#[test]
fn a_balls_helical_projection_is_its_chord_length() {
    let (rho, c) = (6.0, [5.0, -3.0, 2.0]);
    let scale = 10.0;
    let ball = Phantom3::new(
        vec![Ellipsoid {
            value: 1.0,
            a: rho / scale,
            b: rho / scale,
            c: rho / scale,
            x0: c[0] / scale,
            y0: c[1] / scale,
            z0: c[2] / scale,
            phi_deg: 0.0,
            theta_deg: 0.0,
            psi_deg: 0.0,
        }],
        scale,
    )
    .unwrap();
    for shape in ["flat", "cylindrical"] {
        let json = format!(
            r#"{{"type": "helical", "dso_mm": 100.0, "dsd_mm": 180.0, "pitch": 1.2, "turns": 1.5,
            "views_per_turn": 24, "z_start_mm": -12.0, "detector": {{"nu": 40, "nv": 12, "du_mm": 0.9,
            "dv_mm": 1.1, "shape": "{shape}"}}}}"#
        );
        let v = helical(&json).unwrap();
        let proj = ball.project(&v);
        let mut hit = 0;
        for (k, view) in v.views.iter().enumerate() {
            for r in 0..v.detector.nv {
                for col in 0..v.detector.nu {
                    let ray = v.ray(view, r, col);
                    let w = sub3(c, ray.origin);
                    let along = dot3(w, ray.direction);
                    let d2 = dot3(w, w) - along * along;
                    let chord = 2.0 * (rho * rho - d2).max(0.0).sqrt();
                    let got = proj[[k, r, col]] as f64;
                    assert!(
                        (got - chord).abs() < 1e-4,
                        "{shape} view {k} [{r}][{col}]: {got} vs {chord}"
                    );
                    hit += usize::from(chord > 1.0);
                }
            }
        }
        assert!(hit > 500, "{shape}: the ball was seen by {hit} rays only");
    }
}
