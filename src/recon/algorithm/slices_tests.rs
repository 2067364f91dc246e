//! The 3D parallel beam against the 2D machinery it runs slice by slice, and against analytic truth.

use ndarray::{Array2, Array3, Axis, s};

use super::{AlgorithmSpec, OutputGrid, estimate_bytes, reconstruct};
use crate::recon::analytic;
use crate::recon::control::unattended;
use crate::recon::geometry::{Geometry, Parallel3d, ParallelBeam, Views};
use crate::recon::grid::{ImageGrid, Limits, VolumeGrid};
use crate::recon::metrics::rmse;
use crate::recon::phantom::{Ellipsoid, Phantom2, Phantom3, Table2};

const SCALE_MM: f64 = 20.0;

fn spec(json: &str) -> AlgorithmSpec {
    serde_json::from_str(json).unwrap()
}

fn parallel3d(views: usize, nu: usize, nv: usize, du: f64, dv: f64) -> Parallel3d {
    serde_json::from_value(serde_json::json!({
        "type": "parallel3d", "angles": {"count": views},
        "detector": {"nu": nu, "nv": nv, "du_mm": du, "dv_mm": dv}
    }))
    .map(|g: Geometry| match g {
        Geometry::Parallel3d(p) => p,
        other => panic!("{other:?}"),
    })
    .unwrap()
}

/// The 2D modified Shepp–Logan extruded along z: ellipsoids with the ellipses' axes and c = 1000 phantom
/// units, so that every plane |z| ≤ a few mm cuts the 2D phantom (to a relative 10⁻⁸).
fn tall_shepp_logan() -> (Phantom2, Phantom3) {
    let flat = Phantom2::from_table(Table2::ModifiedSheppLogan, SCALE_MM);
    let tall = flat
        .ellipses
        .iter()
        .map(|e| {
            // The 3D centre is stated in the rotated frame (Ellipsoid's docs); θ = ψ = 0 turns by −φ about z.
            let (sn, cs) = e.phi_deg.to_radians().sin_cos();
            Ellipsoid {
                value: e.value,
                a: e.a,
                b: e.b,
                c: 1000.0,
                x0: cs * e.x0 + sn * e.y0,
                y0: -sn * e.x0 + cs * e.y0,
                z0: 0.0,
                phi_deg: e.phi_deg,
                theta_deg: 0.0,
                psi_deg: 0.0,
            }
        })
        .collect();
    (flat, Phantom3::new(tall, SCALE_MM).unwrap())
}

fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 64,
        ny: 64,
        nz: 4,
        spacing_mm: [0.625, 0.625, 0.8],
        // z = −1.45, −0.65, 0.15, 0.95 mm: between detector rows (1 mm apart, at ±0.5, ±1.5, …).
        centre_mm: [0.0, 0.0, -0.25],
    }
}

#[test]
fn the_extruded_phantom_cuts_the_2d_phantom_in_every_plane() {
    let (flat, tall) = tall_shepp_logan();
    for k in 0..400 {
        let (x, y) = ((k % 20) as f64 - 9.5, (k / 20) as f64 - 9.5);
        let (x, y) = (x * 1.9, y * 1.9);
        assert_eq!(
            flat.value_at(x, y),
            tall.value_at([x, y, 1.5]),
            "({x}, {y})"
        );
    }
}

#[test]
fn fbp_of_a_tall_shepp_logan_slice_by_slice_equals_2d_fbp_of_the_matching_slice() {
    let (flat, tall) = tall_shepp_logan();
    let g3 = parallel3d(180, 96, 6, 0.5, 1.0);
    let views = Views::Slices(g3.to_views().unwrap());
    let Views::Slices(sv) = &views else {
        unreachable!()
    };
    let data = tall.project_parallel(sv);
    let grid = grid();
    let volume = reconstruct(
        &spec(r#"{"name": "fdk"}"#),
        &views,
        data.view().into_dyn(),
        &OutputGrid::Volume(grid),
        &Limits::default(),
        unattended(),
    )
    .unwrap()
    .into_dimensionality::<ndarray::Ix3>()
    .unwrap();
    let g2 = ParallelBeam {
        angles: g3.angles.clone(),
        det_count: 96,
        det_spacing_mm: 0.5,
        det_offset_mm: 0.0,
    }
    .to_views()
    .unwrap();
    let sinogram = flat.project(&g2);
    let image = analytic::fbp_2d(
        &g2,
        sinogram.view(),
        &grid.slice_grid(),
        &Default::default(),
        unattended(),
    )
    .unwrap();
    let truth = flat.rasterize(&grid.slice_grid(), 4);
    for (k, slice) in volume.axis_iter(Axis(0)).enumerate() {
        let diff = (&slice - &image)
            .mapv(f32::abs)
            .fold(0f32, |a, &b| a.max(b));
        assert!(diff < 1e-5, "slice {k}: max |3D − 2D| = {diff}");
        let e = rmse(slice, truth.view(), None).unwrap();
        eprintln!("slice {k}: max |3D − 2D| {diff:.2e}, RMSE {e:.4}");
        // The 2D FBP of this sampling (64² pixels of 0.625 mm, 180 views, 0.5 mm detector): 0.0357.
        assert!(e < 0.04, "slice {k}: RMSE {e}");
    }
    let e3 = rmse(
        volume.view(),
        tall.rasterize(&grid, 2).view(),
        None::<ndarray::ArrayView3<'_, bool>>,
    )
    .unwrap();
    eprintln!("volume RMSE {e3:.4}");
    // 0.0442 against the 3D raster (supersample 2, so sharper edges than the 2D raster's 4).
    assert!(
        e3 < 0.05,
        "volume RMSE against the rasterised 3D phantom: {e3}"
    );
}

#[test]
fn an_off_centre_point_lands_on_the_detector_pixel_of_its_u_and_z() {
    // A ball of radius 0.4 mm at (6, −3, 2.25) mm: at β it projects to u = x cos β + y sin β, v = z.
    let ball = Phantom3::new(
        vec![Ellipsoid {
            value: 1.0,
            a: 0.02,
            b: 0.02,
            c: 0.02,
            x0: 0.3,
            y0: -0.15,
            z0: 0.1125,
            phi_deg: 0.0,
            theta_deg: 0.0,
            psi_deg: 0.0,
        }],
        SCALE_MM,
    )
    .unwrap();
    let sv = parallel3d(8, 64, 16, 0.5, 0.5).to_views().unwrap();
    let data = ball.project_parallel(&sv);
    for (i, view) in data.axis_iter(Axis(0)).enumerate() {
        let b = sv.rows.views[i].angle_rad;
        let u = 6.0 * b.cos() - 3.0 * b.sin();
        let (r, c) = argmax(&view.to_owned());
        assert_eq!(
            r, 12,
            "view {i}: row of z = 2.25 mm (rows at −3.75 + 0.5 r)"
        );
        let col = sv.rows.detector.index_of(u);
        assert!(
            (c as f64 - col).abs() <= 0.5,
            "view {i}: column {c}, expected {col:.2}"
        );
        assert_eq!(r as f64, sv.row_of(2.25));
    }
}

fn argmax(a: &Array2<f32>) -> (usize, usize) {
    let mut best = ((0, 0), f32::MIN);
    for ((r, c), &v) in a.indexed_iter() {
        if v > best.1 {
            best = ((r, c), v);
        }
    }
    best.0
}

#[test]
fn sirt_and_cgls_on_parallel3d_converge_slice_by_slice_as_in_2d() {
    let (_, tall) = tall_shepp_logan();
    let views = Views::Slices(parallel3d(90, 64, 4, 0.75, 1.0).to_views().unwrap());
    let Views::Slices(sv) = &views else {
        unreachable!()
    };
    let data = tall.project_parallel(sv);
    let grid = VolumeGrid {
        nx: 48,
        ny: 48,
        nz: 2,
        spacing_mm: [0.85, 0.85, 1.0],
        centre_mm: [0.0; 3],
    };
    let truth = tall.rasterize(&grid, 2);
    let run = |json: &str| -> Array3<f32> {
        reconstruct(
            &spec(json),
            &views,
            data.view().into_dyn(),
            &OutputGrid::Volume(grid),
            &Limits::default(),
            unattended(),
        )
        .unwrap()
        .into_dimensionality()
        .unwrap()
    };
    let err = |v: &Array3<f32>| rmse(v.view(), truth.view(), None).unwrap();
    for (method, bound) in [("sirt", 0.12), ("cgls", 0.13)] {
        let few = run(&format!(r#"{{"name": "{method}", "iterations": 2}}"#));
        let many = run(&format!(r#"{{"name": "{method}", "iterations": 40}}"#));
        let (e_few, e_many) = (err(&few), err(&many));
        eprintln!("{method}: RMSE {e_few:.4} after 2, {e_many:.4} after 40 iterations");
        assert!(
            e_many < bound,
            "{method}: RMSE {e_many} after 40 iterations"
        );
        // Slice 0 sits at z = −0.5 mm, on detector row 1: its 2D run on that row's sinogram, whose data
        // residual ‖Ax − b‖ falls.
        let row = data.slice(s![.., 1, ..]).to_owned();
        let residuals = std::sync::Mutex::new(Vec::new());
        let progress = |_: &str, _: f64, _: Option<usize>, r: Option<f64>| {
            residuals.lock().unwrap().extend(r);
        };
        let cancel = crate::recon::control::Cancel::new();
        let image = reconstruct(
            &spec(&format!(r#"{{"name": "{method}", "iterations": 40}}"#)),
            &Views::D2(sv.rows.clone()),
            row.view().into_dyn(),
            &OutputGrid::Image(grid.slice_grid()),
            &Limits::default(),
            crate::recon::control::Control::new(&cancel, &progress),
        )
        .unwrap();
        let r = residuals.into_inner().unwrap();
        let (first, last) = (r[0], r[r.len() - 1]);
        eprintln!(
            "{method}: residual {first:.4} → {last:.4} over {} reports",
            r.len()
        );
        assert!(last < 0.5 * first, "{method}: residual {first} → {last}");
        assert!(
            r.windows(2).all(|w| w[1] <= w[0] * (1.0 + 1e-6)),
            "{method}: the residual rose: {r:?}"
        );
        let diff = (&many.index_axis(Axis(0), 0).into_dyn() - &image)
            .mapv(f32::abs)
            .fold(0f32, |a, &b| a.max(b));
        assert!(diff < 1e-5, "{method}: slice 0 differs from 2D by {diff}");
    }
}

#[test]
fn a_slice_beyond_the_detector_is_zero_and_between_rows_is_interpolated() {
    let sv = parallel3d(4, 3, 2, 1.0, 2.0).to_views().unwrap();
    // Rows at z = −1 and +1 mm.
    let mut data = Array3::<f32>::zeros((4, 2, 3));
    data.slice_mut(s![.., 0, ..]).fill(1.0);
    data.slice_mut(s![.., 1, ..]).fill(3.0);
    assert_eq!(sv.sinogram_at(data.view(), -1.0)[[0, 0]], 1.0);
    assert_eq!(sv.sinogram_at(data.view(), 0.5)[[2, 1]], 2.5);
    // Half a row pitch beyond the last row: half of it; a whole pitch beyond: nothing.
    assert_eq!(sv.sinogram_at(data.view(), 2.0)[[1, 2]], 1.5);
    assert_eq!(sv.sinogram_at(data.view(), 3.0)[[1, 2]], 0.0);
    assert!(sv.covers(2.9) && !sv.covers(3.0) && !sv.covers(-3.0));
}

#[test]
fn bad_parallel3d_geometries_are_refused_naming_the_field() {
    let bad = |detector: serde_json::Value, angles: serde_json::Value| {
        let g: Geometry = serde_json::from_value(serde_json::json!({
            "type": "parallel3d", "angles": angles, "detector": detector
        }))
        .unwrap();
        g.to_views().unwrap_err().to_string()
    };
    let count = serde_json::json!({"count": 10});
    let e = bad(
        serde_json::json!({"nu": 0, "nv": 4, "du_mm": 1, "dv_mm": 1}),
        count.clone(),
    );
    assert!(e.contains("detector.nu"), "{e}");
    let e = bad(
        serde_json::json!({"nu": 4, "nv": 4, "du_mm": 1, "dv_mm": -1}),
        count.clone(),
    );
    assert!(e.contains("detector.dv_mm"), "{e}");
    let e = bad(
        serde_json::json!({"nu": 4, "nv": 4, "du_mm": 1, "dv_mm": 1}),
        serde_json::json!({"count": 10, "short_scan": true}),
    );
    assert!(e.contains("short scan"), "{e}");
    let e = bad(
        serde_json::json!({"nu": 4, "nv": 4, "du_mm": 1, "dv_mm": 1}),
        serde_json::json!({"count": 0}),
    );
    assert!(e.contains("count"), "{e}");
    assert!(
        serde_json::from_str::<Geometry>(
            r#"{"type": "parallel3d", "angles": {"count": 2}, "dso_mm": 5,
                "detector": {"nu": 4, "nv": 4, "du_mm": 1, "dv_mm": 1}}"#
        )
        .is_err()
    );
}

#[test]
fn a_3d_parallel_beam_needs_a_volume_grid_and_counts_its_slices_memory() {
    let views = Views::Slices(parallel3d(180, 256, 64, 0.5, 0.5).to_views().unwrap());
    let image = OutputGrid::Image(ImageGrid::square(64, 1.0));
    assert!(super::check_grid(&views, &image).is_err());
    let grid = VolumeGrid::cube(256, 0.5);
    let volume = OutputGrid::Volume(grid);
    let fbp = estimate_bytes(&spec(r#"{"name": "fbp"}"#), &views, &volume);
    let threads = rayon::current_num_threads().clamp(1, 256) as u64;
    // The volume, and per running slice at least its sinogram and its 2D image.
    let floor = 4 * (256u64 * 256 * 256 + threads * (180 * 256 + 256 * 256));
    assert!(fbp >= floor, "{fbp} < {floor}");
    let cgls = estimate_bytes(&spec(r#"{"name": "cgls"}"#), &views, &volume);
    assert!(cgls > fbp, "CGLS keeps more per slice: {cgls} vs {fbp}");
    let tight = Limits { max_bytes: fbp - 1 };
    let data = Array3::<f32>::zeros((180, 64, 256));
    let err = reconstruct(
        &spec(r#"{"name": "fbp"}"#),
        &views,
        data.view().into_dyn(),
        &volume,
        &tight,
        unattended(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("bytes"), "{err}");
    let voxel = spec(r#"{"name": "cgls", "back_projector": "voxel"}"#);
    assert!(crate::recon::iterative::check_views(&voxel, &views).is_err());
}
