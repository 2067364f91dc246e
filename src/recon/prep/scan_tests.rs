//! Simulated cone-beam scans for the calibration tests (exact projections of the 3D modified Shepp–Logan
//! phantom on a 128² panel), and the tests of the panel roll and of applying an estimate.

use ndarray::{Array3, s};

use super::*;
use crate::recon::algorithm::FbpParams;
use crate::recon::analytic;
use crate::recon::control::unattended;
use crate::recon::geometry::vectors::{cross3, dot3, sub3};
use crate::recon::geometry::{Angles, ConeBeam, Panel, Vec3, Views3};
use crate::recon::grid::VolumeGrid;
use crate::recon::metrics::rmse;
use crate::recon::phantom::{Phantom3, Table3};

pub(super) const DU_MM: f64 = 1.3;

/// A circular cone beam, DSO 200 mm, DSD 350 mm, `nu` × 128 pixels of 1.3 mm, offset by `offset_px`.
pub(super) fn cone(angles: Angles, nu: usize, offset_px: f64) -> ConeBeam {
    ConeBeam {
        angles,
        dso_mm: 200.0,
        dsd_mm: 350.0,
        detector: Panel {
            nu,
            nv: 128,
            du_mm: DU_MM,
            dv_mm: DU_MM,
            offset_u_mm: offset_px * DU_MM,
            offset_v_mm: 0.0,
        },
    }
}

pub(super) fn phantom() -> Phantom3 {
    Phantom3::from_table(Table3::ModifiedSheppLogan, 40.0)
}

/// The canonical views of `cone` rolled by `tilt_deg`, and the phantom's exact projections through them.
pub(super) fn scan(cone: &ConeBeam, tilt_deg: f64) -> (Views3, Array3<f32>) {
    let mut views = cone.to_views().unwrap();
    roll_views(&mut views, tilt_deg);
    let proj = phantom().project(&views);
    (views, proj)
}

/// Eight slices 6 mm apart through the phantom (z from −21 to 21 mm), 96² voxels of 0.85 mm.
pub(super) fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 96,
        ny: 96,
        nz: 8,
        spacing_mm: [0.85, 0.85, 6.0],
        centre_mm: [0.0; 3],
    }
}

/// RMSE of the FDK image of `proj` reconstructed on `views` against the phantom.
pub(super) fn fdk_rmse(views: &Views3, proj: &Array3<f32>) -> f64 {
    let g = grid();
    let truth = phantom().rasterize(&g, 2);
    let image = analytic::fdk(views, proj.view(), &g, &FbpParams::default(), unattended()).unwrap();
    rmse(image.view(), truth.view(), None).unwrap()
}

/// Where the point `x` falls on the panel of view `k`: `(u, v)` in mm.
fn panel_uv(views: &Views3, k: usize, x: Vec3) -> (f64, f64) {
    let v = &views.views[k];
    let w = cross3(v.det_u, v.det_v);
    let d = sub3(x, v.source);
    let t = dot3(sub3(v.det_centre, v.source), w) / dot3(d, w);
    let p: Vec3 = std::array::from_fn(|i| v.source[i] + t * d[i] - v.det_centre[i]);
    (dot3(p, v.det_u), dot3(p, v.det_v))
}

#[test]
fn a_rolled_panel_sees_the_rotation_axis_on_the_line_u_equals_v_tan_theta() {
    let mut views = cone(Angles::uniform(8, 360.0), 64, 0.0).to_views().unwrap();
    roll_views(&mut views, 0.4);
    let tan = 0.4f64.to_radians().tan();
    for k in 0..8 {
        for z in [-30.0, -5.0, 12.0, 40.0] {
            let (u, v) = panel_uv(&views, k, [0.0, 0.0, z]);
            assert!((u - v * tan).abs() < 1e-9, "view {k}, z {z}: u {u}, v {v}");
            // Seen from the source with u to the right and v up, the roll turns u toward v: a point of
            // the axis above the mid-plane (v > 0) lands right of the column of the central ray.
            assert!(z <= 0.0 || u > 0.0);
        }
    }
}

#[test]
fn applying_an_estimate_sets_the_offset_and_rolls_the_panel() {
    let est = CentreEstimate {
        offset_u_px: 7.3,
        offset_u_mm: 7.3 * DU_MM,
        tilt_deg: Some(0.4),
        residual: 0.0,
        method: CentreMethod::OppositeViews,
        views_used: 1,
    };
    let truth = cone(Angles::uniform(16, 360.0), 64, 7.3);
    let mut want = truth.to_views().unwrap();
    roll_views(&mut want, 0.4);
    let mut nominal = cone(Angles::uniform(16, 360.0), 64, 0.0);
    let got = apply_to_cone(&mut nominal, &est).unwrap();
    assert_eq!(nominal.detector.offset_u_mm, 7.3 * DU_MM);
    assert_eq!(got, want);
    let mut views = cone(Angles::uniform(16, 360.0), 64, 0.0)
        .to_views()
        .unwrap();
    apply_to_views(&mut views, &est);
    assert_eq!(views, want);
    let json = serde_json::to_string(&est).unwrap();
    assert_eq!(serde_json::from_str::<CentreEstimate>(&json).unwrap(), est);
}

/// The simulation helpers reconstruct: FDK with the true geometry of a centred scan is close to the
/// phantom, and the first and last slices hold the phantom.
#[test]
fn the_simulated_centred_scan_reconstructs() {
    let c = cone(Angles::uniform(360, 360.0), 128, 0.0);
    let (views, proj) = scan(&c, 0.0);
    let e = fdk_rmse(&views, &proj);
    let truth = phantom().rasterize(&grid(), 2);
    let top = truth
        .slice(s![0, .., ..])
        .iter()
        .fold(0f32, |m, &x| m.max(x));
    println!("centred scan: FDK RMSE {e:.4}, phantom top slice max {top}");
    assert!(top > 0.5 && e < 0.1);
}
