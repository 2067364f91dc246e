//! 3D phantom tests: exact cone-beam projections against closed forms and a numeric line integral,
//! voxelisation against the analytic volume, the seed's grid.

use super::*;
use crate::recon::geometry::vectors::{add3, scale3};
use crate::recon::geometry::{Angles, ConeBeam, Panel, Views3};
use crate::recon::grid::VolumeGrid;

fn cone(views: usize, n: usize, d: f64, off_u: f64, off_v: f64) -> Views3 {
    ConeBeam {
        angles: Angles::uniform(views, 360.0),
        dso_mm: 400.0,
        dsd_mm: 600.0,
        detector: Panel {
            nu: n,
            nv: n,
            du_mm: d,
            dv_mm: d,
            offset_u_mm: off_u,
            offset_v_mm: off_v,
        },
    }
    .to_views()
    .unwrap()
}

fn sphere(value: f64, r: f64, c: [f64; 3]) -> Ellipsoid {
    Ellipsoid {
        value,
        a: r,
        b: r,
        c: r,
        x0: c[0],
        y0: c[1],
        z0: c[2],
        phi_deg: 0.0,
        theta_deg: 0.0,
        psi_deg: 0.0,
    }
}

#[test]
fn a_sphere_projects_to_its_closed_form_chord_on_every_panel_element() {
    // Sphere of radius 0.5 (50 mm at scale 100) centred at the origin: chord 2·√(R² − d²) where d is the
    // distance of the ray from the centre.
    let ph = Phantom3::new(vec![sphere(0.02, 0.5, [0.0; 3])], 100.0).unwrap();
    let v = cone(8, 33, 4.0, 1.5, -2.5);
    let p = ph.project(&v);
    assert_eq!(p.shape(), &[8, 33, 33]);
    let mut checked = 0;
    for (k, view) in v.views.iter().enumerate() {
        for r in 0..33 {
            for c in 0..33 {
                let ray = v.ray(view, r, c);
                let s = ray.origin;
                let t =
                    -(s[0] * ray.direction[0] + s[1] * ray.direction[1] + s[2] * ray.direction[2]);
                let closest = add3(s, scale3(ray.direction, t));
                let d2 = closest.iter().map(|x| x * x).sum::<f64>();
                let chord = 2.0 * (2500.0 - d2).max(0.0).sqrt();
                let got = p[[k, r, c]] as f64;
                assert!(
                    (got - 0.02 * chord).abs() < 1e-4,
                    "view {k} [{r}][{c}]: {got} vs {}",
                    0.02 * chord
                );
                checked += usize::from(chord > 0.0);
            }
        }
    }
    assert!(checked > 1000, "only {checked} rays hit the sphere");
}

#[test]
fn rotated_off_centre_ellipsoids_match_a_numeric_line_integral() {
    let e = Ellipsoid {
        value: 0.03,
        a: 0.4,
        b: 0.2,
        c: 0.3,
        x0: 0.1,
        y0: -0.15,
        z0: 0.05,
        phi_deg: 25.0,
        theta_deg: 40.0,
        psi_deg: -15.0,
    };
    let ph = Phantom3::new(vec![e, sphere(-0.01, 0.1, [0.0, 0.1, 0.0])], 100.0).unwrap();
    let v = cone(5, 9, 12.0, 0.0, 0.0);
    let p = ph.project(&v);
    for (k, view) in v.views.iter().enumerate() {
        for r in 0..9 {
            for c in 0..9 {
                let ray = v.ray(view, r, c);
                // Midpoint rule from 250 mm before the isocentre to 250 mm past it, 0.01 mm steps.
                let (t0, t1, n) = (400.0 - 150.0, 400.0 + 150.0, 30_000);
                let h = (t1 - t0) / n as f64;
                let sum: f64 = (0..n)
                    .map(|i| {
                        let t = t0 + (i as f64 + 0.5) * h;
                        ph.value_at(add3(ray.origin, scale3(ray.direction, t)))
                    })
                    .sum::<f64>()
                    * h;
                let got = p[[k, r, c]] as f64;
                assert!(
                    (got - sum).abs() < 2e-3 * 0.03 * 80.0 + 1e-5,
                    "view {k} [{r}][{c}]: {got} vs {sum}"
                );
            }
        }
    }
}

#[test]
fn voxelised_volume_approaches_the_analytic_volume() {
    // ρ·(4/3)πabc·scale³ (mm³) against the voxel sum times the voxel volume.
    let e = Ellipsoid {
        value: 1.0,
        a: 0.6,
        b: 0.45,
        c: 0.35,
        x0: 0.05,
        y0: 0.0,
        z0: -0.1,
        phi_deg: 30.0,
        theta_deg: 20.0,
        psi_deg: 10.0,
    };
    let ph = Phantom3::new(vec![e], 32.0).unwrap();
    let grid = VolumeGrid::cube(64, 1.0);
    let want = 4.0 / 3.0 * std::f64::consts::PI * e.a * e.b * e.c * 32f64.powi(3);
    let err = |s| {
        let vol = ph.rasterize(&grid, s);
        assert_eq!(vol.shape(), &[64, 64, 64]);
        (vol.iter().map(|&v| v as f64).sum::<f64>() - want).abs() / want
    };
    let (e1, e3) = (err(1), err(3));
    assert!(e1 < 5e-3, "supersample 1: {e1}");
    assert!(e3 < 2e-3, "supersample 3: {e3}");
}

#[test]
fn the_seed_grid_samples_both_ends_and_the_modified_table_has_its_known_values() {
    let g = seed_grid(128, 100.0);
    assert!((g.spacing_mm[0] - 200.0 / 127.0).abs() < 1e-12);
    let ph = Phantom3::from_table(Table3::ModifiedSheppLogan, 100.0);
    // Centre: outer 1 − 0.8 (skull interior) = 0.2; the seed's 3D modified table adds nothing at the origin.
    let centre = ph.value_at([0.0, 0.0, 0.0]);
    assert!((centre - 0.2).abs() < 1e-12, "centre {centre}");
    // Outside the head.
    assert_eq!(ph.value_at([0.0, 0.0, 99.0]), 0.0);
    let vol = ph.rasterize(&g, 1);
    // The seed's volume has 128³ samples and both grid ends at ±scale.
    assert_eq!(vol.shape(), &[128, 128, 128]);
    assert_eq!(vol[[0, 64, 64]], 0.0);
    assert!(
        (vol[[64, 64, 64]] - 0.2).abs() < 1e-6,
        "near-centre voxel {}",
        vol[[64, 64, 64]]
    );
}

/// A canceled flag stops the rasterisation with `Canceled`; an unset one gives the plain raster.
#[test]
fn rasterising_checks_the_cancel_flag() {
    use crate::recon::control::{Cancel, Control, NoProgress};
    let ph = Phantom3::from_table(Table3::ModifiedSheppLogan, 30.0);
    let grid = VolumeGrid::cube(24, 2.5);
    let cancel = Cancel::new();
    let ctl = Control::new(&cancel, &NoProgress);
    let vol = ph.rasterize_cancelable(&grid, 2, ctl).unwrap();
    assert_eq!(vol, ph.rasterize(&grid, 2));
    cancel.cancel();
    assert!(matches!(
        ph.rasterize_cancelable(&grid, 2, ctl),
        Err(ReconError::Canceled)
    ));
}
