use super::*;
use crate::recon::analytic::fdk_filter::pre_weight;
use crate::recon::analytic::orbit::cone_frames;
use crate::recon::control::unattended;
use crate::recon::geometry::{Angles, ConeBeam, Panel as Detector};
use crate::recon::phantom::{Ellipsoid, Phantom3};

/// Two ellipsoids off centre, so that every part of the backprojection (distance weights, both
/// detector axes, offsets) shapes the image.
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

fn cone(angles: Angles, nu: usize, offset_u_mm: f64, offset_v_mm: f64) -> Views3 {
    ConeBeam {
        angles,
        dso_mm: 200.0,
        dsd_mm: 350.0,
        detector: Detector {
            nu,
            nv: 40,
            du_mm: 1.3,
            dv_mm: 1.1,
            offset_u_mm,
            offset_v_mm,
        },
    }
    .to_views()
    .unwrap()
}

/// FDK with the loop along z (`true`) or along x (`false`) forced.
fn along(views: &Views3, proj: &Array3<f32>, grid: &VolumeGrid, z: bool) -> Array3<f32> {
    let params = FbpParams::default();
    fdk_with(views, proj.view(), grid, &params, unattended(), Some(z)).unwrap()
}

fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 40,
        ny: 36,
        nz: 30,
        spacing_mm: [1.0, 1.1, 0.9],
        centre_mm: [1.0, -2.0, 1.5],
    }
}

/// The loop along z and the loop along x compute the same sums in a different order: full, short and
/// offset scans, a panel shifted vertically, agree to f32 rounding of the largest value.
#[test]
fn the_loops_along_z_and_along_x_agree() {
    let full = Angles::Uniform {
        count: 90,
        start_deg: 10.0,
        range_deg: None,
        short_scan: false,
    };
    let cases = [
        ("full", cone(full.clone(), 64, 0.0, 0.0)),
        ("full, panel shifted", cone(full.clone(), 64, 3.1, -4.3)),
        (
            "short",
            cone(
                Angles::Uniform {
                    count: 70,
                    start_deg: 0.0,
                    range_deg: None,
                    short_scan: true,
                },
                64,
                0.0,
                0.0,
            ),
        ),
        ("offset", cone(full, 40, 20.0, 0.0)),
    ];
    let grid = grid();
    let params = FbpParams::default();
    for (name, views) in cases {
        let proj = phantom().project(&views);
        assert!(lines_along_z(
            &cone_frames(&views).unwrap(),
            &grid,
            &views.detector
        ));
        let z = along(&views, &proj, &grid, true);
        let x = along(&views, &proj, &grid, false);
        let top = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = z
            .iter()
            .zip(&x)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        println!("{name}: largest value {top:.5}, largest difference {worst:.2e}");
        assert!(top > 0.01, "{name}: the image is empty");
        assert!(worst <= 2e-5 * top, "{name}: {worst} against {top}");
        let default = fdk(&views, proj.view(), &grid, &params, unattended()).unwrap();
        assert_eq!(default, z, "{name}: the default is the loop along z");
    }
}

/// A panel rolled about the central ray has rows that are not horizontal: lines along z cross its
/// columns, so the loop along x is taken.
#[test]
fn a_rolled_panel_takes_the_loop_along_x() {
    let mut views = cone(
        Angles::Uniform {
            count: 36,
            start_deg: 0.0,
            range_deg: None,
            short_scan: false,
        },
        48,
        0.0,
        0.0,
    );
    let roll = 3f64.to_radians();
    for v in &mut views.views {
        let (u, w) = (v.det_u, v.det_v);
        v.det_u = std::array::from_fn(|i| u[i] * roll.cos() + w[i] * roll.sin());
        v.det_v = std::array::from_fn(|i| w[i] * roll.cos() - u[i] * roll.sin());
    }
    let grid = grid();
    assert!(!lines_along_z(
        &cone_frames(&views).unwrap(),
        &grid,
        &views.detector
    ));
    let proj = phantom().project(&views);
    let params = FbpParams::default();
    let default = fdk(&views, proj.view(), &grid, &params, unattended()).unwrap();
    let x = along(&views, &proj, &grid, false);
    assert_eq!(default, x);
}

/// The views of a parametric orbit share one table of pre-weights although their frames, computed from
/// rotated vectors, differ in the last bits; every view's own weights agree with the table far below
/// f32 rounding. A view whose panel lies a micrometre farther from the source has weights of its own.
#[test]
fn the_views_of_one_orbit_share_their_pre_weights() {
    let angles = Angles::Uniform {
        count: 90,
        start_deg: 10.0,
        range_deg: None,
        short_scan: false,
    };
    let views = cone(angles, 64, 3.1, -4.3);
    let params = FbpParams::default();
    let setup = Setup::new(&views, &params).unwrap();
    let f0 = setup.frames[0];
    assert!(
        setup
            .frames
            .iter()
            .any(|f| (f.dsd, f.u0, f.v0) != (f0.dsd, f0.u0, f0.v0)),
        "the frames should differ in their last bits, as computed"
    );
    let det = views.detector;
    let table = setup.pre.as_ref().expect("one table for the orbit");
    for f in &setup.frames {
        for r in 0..det.nv {
            for c in 0..det.nu {
                let own = pre_weight(f, &det, r, c);
                assert!((own - table[r * det.nu + c]).abs() <= 1e-12 * own);
            }
        }
    }
    let mut shifted = views.clone();
    let v = &mut shifted.views[7];
    let ray: [f64; 3] = std::array::from_fn(|i| v.det_centre[i] - v.source[i]);
    let length = ray.iter().map(|r| r * r).sum::<f64>().sqrt();
    v.det_centre = std::array::from_fn(|i| v.det_centre[i] + 1e-3 * ray[i] / length);
    assert!(Setup::new(&shifted, &params).unwrap().pre.is_none());
}

/// The back projection alone ([`back_project_voxels`]) of projections that are 1 everywhere: a voxel
/// at distance ρ from the axis of a full turn sums Δβ·D²/lc² over the views, lc = D − ρ·cos(β − φ),
/// which is 2π·(1 − ρ²/D²)^(−3/2) (the integral over the turn; the sum of 180 equal steps of this
/// smooth periodic function equals it far below f32 rounding). Both loops, off-centre grid.
#[test]
fn the_back_projection_alone_of_ones_is_the_integral_of_its_distance_weight() {
    let views = ConeBeam {
        angles: Angles::uniform(180, 360.0),
        dso_mm: 100.0,
        dsd_mm: 180.0,
        detector: Detector {
            nu: 160,
            nv: 120,
            du_mm: 1.0,
            dv_mm: 1.0,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .unwrap();
    let grid = VolumeGrid {
        nx: 20,
        ny: 18,
        nz: 10,
        spacing_mm: [2.0, 2.5, 1.5],
        centre_mm: [3.0, -4.0, 2.0],
    };
    let ones = Array3::<f32>::ones(views.shape());
    let params = FbpParams::default();
    let public = back_project_voxels(&views, ones.view(), &grid, unattended()).unwrap();
    for z in [true, false] {
        let got = run(
            &views,
            ones.view(),
            &grid,
            &params,
            unattended(),
            Some(z),
            false,
        )
        .unwrap();
        assert_eq!(got.shape(), &[10, 18, 20]);
        if z {
            assert_eq!(got, public, "the public call takes the loop along z here");
        }
        let d = 100.0f64;
        let mut worst = 0.0f64;
        for ((k, j, i), v) in got.indexed_iter() {
            let rho2 = grid.x(i).powi(2) + grid.y(j).powi(2);
            let want = 2.0 * std::f64::consts::PI / (1.0 - rho2 / (d * d)).powf(1.5);
            let e = (*v as f64 - want).abs() / want;
            assert!(
                e < 1e-5,
                "along z {z}, voxel ({i}, {j}, {k}): {v} against {want}"
            );
            worst = worst.max(e);
        }
        println!("back projection of ones, along z {z}: largest relative error {worst:.2e}");
    }
}
