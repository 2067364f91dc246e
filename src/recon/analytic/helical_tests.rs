//! Accuracy of the helical weighted FBP against the exact phantoms, beside circular FDK.

use ndarray::{Array3, ArrayD, s};

use crate::recon::algorithm::{AlgorithmSpec, FbpParams, OutputGrid, reconstruct};
use crate::recon::control::unattended;
use crate::recon::geometry::{Geometry, Views, Views3};
use crate::recon::grid::{Limits, VolumeGrid};
use crate::recon::phantom::{Phantom3, Table3};

/// The modified 3D Shepp–Logan stretched to twice its height (semi-axes and centres along z × 2),
/// values × 0.02 /mm, 25 mm per phantom unit: 17 mm in radius, 81 mm tall.
fn tall_shepp_logan() -> Phantom3 {
    let mut p = Phantom3::from_table(Table3::ModifiedSheppLogan, 25.0);
    for e in &mut p.ellipsoids {
        e.c *= 2.0;
        e.z0 *= 2.0;
        e.value *= 0.02;
    }
    p
}

const DETECTOR: &str = r#""detector": {"nu": 96, "nv": 16, "du_mm": 1.0, "dv_mm": 2.0}"#;

/// A helical scan at `pitch` with the test detector (16 rows of 1 mm at the rotation axis).
fn helix(pitch: f64, turns: f64, z_start_mm: f64) -> Views3 {
    let json = format!(
        r#"{{"type": "helical", "dso_mm": 200.0, "dsd_mm": 400.0, "pitch": {pitch}, "turns": {turns},
        "views_per_turn": 240, "z_start_mm": {z_start_mm}, {DETECTOR}}}"#
    );
    views(&json)
}

/// The same scan with a cylindrical detector of the same pitches (1 mm along the arc).
fn cylindrical_helix(pitch: f64, turns: f64, z_start_mm: f64) -> Views3 {
    let detector = DETECTOR.replace(r#""dv_mm": 2.0"#, r#""dv_mm": 2.0, "shape": "cylindrical""#);
    let json = format!(
        r#"{{"type": "helical", "dso_mm": 200.0, "dsd_mm": 400.0, "pitch": {pitch}, "turns": {turns},
        "views_per_turn": 240, "z_start_mm": {z_start_mm}, {detector}}}"#
    );
    views(&json)
}

fn views(json: &str) -> Views3 {
    let g: Geometry = serde_json::from_str(json).unwrap();
    match g.to_views().unwrap() {
        Views::D3(v) => v,
        other => panic!("not a cone beam: {other:?}"),
    }
}

fn grid(nz: usize, z_mm: f64) -> VolumeGrid {
    VolumeGrid {
        nx: 64,
        ny: 64,
        nz,
        spacing_mm: [0.6, 0.6, 1.0],
        centre_mm: [0.0, 0.0, z_mm],
    }
}

fn fdk(views: &Views3, proj: &Array3<f32>, grid: &VolumeGrid) -> Array3<f32> {
    let spec = AlgorithmSpec::Fdk(FbpParams::default());
    reconstruct(
        &spec,
        &crate::recon::geometry::Views::D3(views.clone()),
        proj.view().into_dyn(),
        &OutputGrid::Volume(*grid),
        &Limits::default(),
        unattended(),
    )
    .unwrap()
    .into_dimensionality()
    .unwrap()
}

/// RMSE over the voxels within `radius_mm` of the axis, slices `zs`.
fn central_rmse(
    image: &Array3<f32>,
    truth: &Array3<f32>,
    grid: &VolumeGrid,
    zs: std::ops::Range<usize>,
    radius_mm: f64,
) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for z in zs {
        for y in 0..grid.ny {
            for x in 0..grid.nx {
                if grid.x(x).hypot(grid.y(y)) <= radius_mm {
                    sum += f64::from(image[[z, y, x]] - truth[[z, y, x]]).powi(2);
                    n += 1;
                }
            }
        }
    }
    (sum / n as f64).sqrt()
}

/// Pitch 1, three turns through the middle of a phantom taller than the detector's coverage: on the
/// central slices (|z| ≤ 4 mm, within 12 mm of the axis) the helical FBP's RMSE against the phantom is
/// within 1.3× that of circular FDK from one turn at z = 0 with the same detector, views per turn and
/// grid.
#[test]
fn helical_fbp_at_pitch_one_is_as_accurate_as_circular_fdk_on_the_central_slices() {
    let phantom = tall_shepp_logan();
    let g = grid(9, 0.0);
    let truth = phantom.rasterize(&g, 2);
    let circle = views(&format!(
        r#"{{"type": "cone", "angles": {{"count": 240}}, "dso_mm": 200.0, "dsd_mm": 400.0, {DETECTOR}}}"#
    ));
    let circular = fdk(&circle, &phantom.project(&circle), &g);
    let spiral = helix(1.0, 3.0, -24.0);
    let helical = fdk(&spiral, &phantom.project(&spiral), &g);
    let e_circle = central_rmse(&circular, &truth, &g, 0..9, 12.0);
    let e_helix = central_rmse(&helical, &truth, &g, 0..9, 12.0);
    println!(
        "central RMSE (1/mm): helical {e_helix:.6}, circular {e_circle:.6}, ratio {:.3}",
        e_helix / e_circle
    );
    assert!(
        e_circle < 0.1 * 0.02,
        "circular FDK itself reconstructs: {e_circle}"
    );
    assert!(e_helix <= 1.3 * e_circle, "{e_helix} vs {e_circle}");
    // A cylindrical detector, rebinned onto a flat panel before filtering, does as well.
    let arc = cylindrical_helix(1.0, 3.0, -24.0);
    let on_arc = fdk(&arc, &phantom.project(&arc), &g);
    let e_arc = central_rmse(&on_arc, &truth, &g, 0..9, 12.0);
    println!(
        "central RMSE (1/mm), cylindrical detector: {e_arc:.6}, ratio {:.3}",
        e_arc / e_circle
    );
    assert!(e_arc <= 1.3 * e_circle, "{e_arc} vs {e_circle}");
}

/// The phantom is 81 mm tall, the sources climb 48 mm: slices beyond the data's z coverage are exactly 0
/// (no partial sums), every slice of the grid is finite, and the slices well inside keep their accuracy.
#[test]
fn slices_beyond_the_helixs_z_coverage_are_zero_and_those_inside_stay_accurate() {
    let phantom = tall_shepp_logan();
    let g = grid(90, 0.0);
    let spiral = helix(1.0, 3.0, -24.0);
    let image = fdk(&spiral, &phantom.project(&spiral), &g);
    let truth = phantom.rasterize(&g, 2);
    assert!(image.iter().all(|v| v.is_finite()));
    // Sources from z = −24 to +24 mm, 8 mm of beam each side at the axis: nothing is complete beyond
    // |z| = 32 mm, everything within 18 mm of the middle is.
    for (iz, z) in (0..g.nz).map(|iz| (iz, g.z(iz))) {
        let slice = image.slice(s![iz, .., ..]);
        let nonzero = slice.iter().filter(|v| **v != 0.0).count();
        if z.abs() > 32.0 {
            assert_eq!(nonzero, 0, "slice z = {z} mm");
        }
    }
    let inside: Vec<usize> = (0..g.nz).filter(|&iz| g.z(iz).abs() <= 18.0).collect();
    let zs = inside[0]..inside[inside.len() - 1] + 1;
    let e = central_rmse(&image, &truth, &g, zs.clone(), 12.0);
    let covered = (0..g.nz)
        .filter(|&iz| image.slice(s![iz, 32, ..]).iter().any(|v| *v != 0.0))
        .count();
    println!(
        "inside RMSE {e:.6} over slices {zs:?}; {covered} of {} slices hold values",
        g.nz
    );
    assert!(e < 0.1 * 0.02, "{e}");
    for iz in zs {
        let line = image.slice(s![iz, 32, ..]);
        assert!(
            line.iter().filter(|v| **v != 0.0).count() > 40,
            "slice {iz} was emptied"
        );
    }
}

/// A uniform tall cylinder of μ = 0.02 /mm reconstructs to μ in its interior (the scaling check of every
/// FBP), at pitch 0.75 and 1.4, within 1.5 %.
#[test]
fn a_uniform_cylinder_reconstructs_to_its_value_at_several_pitches() {
    let cylinder = Phantom3::new(
        vec![crate::recon::phantom::Ellipsoid {
            value: 0.02,
            a: 0.6,
            b: 0.6,
            c: 20.0,
            x0: 0.0,
            y0: 0.0,
            z0: 0.0,
            phi_deg: 0.0,
            theta_deg: 0.0,
            psi_deg: 0.0,
        }],
        25.0,
    )
    .unwrap();
    for pitch in [0.75, 1.4] {
        let spiral = helix(pitch, 3.0, -20.0);
        let g = grid(5, 0.0);
        let image = fdk(&spiral, &cylinder.project(&spiral), &g);
        let mut values = Vec::new();
        for y in 0..g.ny {
            for x in 0..g.nx {
                if g.x(x).hypot(g.y(y)) < 10.0 {
                    values.extend((0..g.nz).map(|z| image[[z, y, x]]));
                }
            }
        }
        let mean = values.iter().map(|v| f64::from(*v)).sum::<f64>() / values.len() as f64;
        println!("pitch {pitch}: mean {mean:.6} over {} voxels", values.len());
        assert!((mean - 0.02).abs() < 0.015 * 0.02, "pitch {pitch}: {mean}");
    }
}

/// SIRT and CGLS take a helical scan through the per-view form and approach the phantom.
#[test]
fn sirt_and_cgls_reconstruct_a_small_helical_scan() {
    let phantom = tall_shepp_logan();
    let json = r#"{"type": "helical", "dso_mm": 200.0, "dsd_mm": 400.0, "pitch": 1.0, "turns": 2.0,
        "views_per_turn": 48, "z_start_mm": -8.0, "detector": {"nu": 48, "nv": 8, "du_mm": 2.0, "dv_mm": 4.0}}"#;
    let v = views(json);
    let proj = phantom.project(&v);
    let g = VolumeGrid {
        nx: 24,
        ny: 24,
        nz: 8,
        spacing_mm: [1.6, 1.6, 2.0],
        centre_mm: [0.0, 0.0, 0.0],
    };
    let truth = phantom.rasterize(&g, 2);
    let zero = Array3::<f32>::zeros(g.shape());
    let e0 = central_rmse(&zero, &truth, &g, 0..g.nz, 12.0);
    for spec in [
        r#"{"name": "sirt", "iterations": 30}"#,
        r#"{"name": "cgls", "iterations": 10}"#,
    ] {
        let spec: AlgorithmSpec = serde_json::from_str(spec).unwrap();
        let out: ArrayD<f32> = reconstruct(
            &spec,
            &Views::D3(v.clone()),
            proj.view().into_dyn(),
            &OutputGrid::Volume(g),
            &Limits::default(),
            unattended(),
        )
        .unwrap();
        let out: Array3<f32> = out.into_dimensionality().unwrap();
        let e = central_rmse(&out, &truth, &g, 0..g.nz, 12.0);
        println!("{spec:?}: RMSE {e:.6} (zero image {e0:.6})");
        assert!(e < 0.5 * e0, "{spec:?}: {e} vs {e0}");
    }
    // The ray-driven projectors read flat panels: a cylindrical detector is refused, pointing to fdk.
    let arc = views(&json.replace(r#""dv_mm": 4.0"#, r#""dv_mm": 4.0, "shape": "cylindrical""#));
    let spec: AlgorithmSpec = serde_json::from_str(r#"{"name": "sirt", "iterations": 2}"#).unwrap();
    let refused = reconstruct(
        &spec,
        &Views::D3(arc.clone()),
        phantom.project(&arc).view().into_dyn(),
        &OutputGrid::Volume(g),
        &Limits::default(),
        unattended(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        refused.contains("cylindrical") && refused.contains("fdk"),
        "{refused}"
    );
}
