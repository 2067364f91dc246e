//! The seed program's fan-beam experiment: the 128³ modified Shepp–Logan phantom on the seed's grid,
//! axial slice 64 (MATLAB's 1-based index, 0-based 63), forward-projected as a pixel image with MATLAB
//! `fanbeam` conventions (D = 250 px, arc sensors at 2°, 1° and 0.25°, 1° rotation steps over 360°) and
//! reconstructed at 128² by fan-beam FBP. Prints the PSNR (true data range of the slice) and the RMSE for
//! each sensor spacing, for the MATLAB-style projection and for ctrecon's Joseph projector.
//!
//! The pixel image is projected MATLAB-style: every pixel split into 2×2 sub-pixels, each projected from
//! the source onto the arc and shared linearly between the two nearest sensors, divided by the width of
//! a sensor's fan at the sub-pixel (so the result is a line integral in mm).
//!
//! Run: `cargo run --release --example fan_seed`.

use ctrecon::recon::algorithm::FbpParams;
use ctrecon::recon::analytic::fbp_2d;
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{MatlabFan, Source2, Views2};
use ctrecon::recon::grid::{ImageGrid, VolumeGrid};
use ctrecon::recon::metrics::{psnr, rmse};
use ctrecon::recon::phantom::{Phantom3, Table3, seed_grid};
use ctrecon::recon::projector::forward_2d;
use ndarray::{Array2, ArrayView2, Axis};

/// The seed's slice: `phantom3d(128)(:, :, 64)` on 1 mm pixels (phantom scale 63.5 mm).
pub fn seed_slice() -> (Array2<f32>, ImageGrid) {
    let full = seed_grid(128, 63.5);
    let grid = VolumeGrid {
        nz: 1,
        centre_mm: [0.0, 0.0, full.z(63)],
        ..full
    };
    let phantom = Phantom3::from_table(Table3::ModifiedSheppLogan, 63.5);
    let slice = phantom.rasterize(&grid, 1).index_axis_move(Axis(0), 0);
    (slice, full.slice_grid())
}

/// Pixel-driven arc fan projection of `image` on `grid` (MATLAB `fanbeam` style, 2×2 sub-pixels).
pub fn project_pixels(image: ArrayView2<'_, f32>, grid: &ImageGrid, views: &Views2) -> Array2<f32> {
    let det = views.detector;
    let n = det.count;
    let mut sino = Array2::<f32>::zeros(views.shape());
    for (view, mut row) in views.views.iter().zip(sino.axis_iter_mut(Axis(0))) {
        let Source2::Point { position: s } = view.source else {
            continue;
        };
        let c = [view.det_centre[0] - s[0], view.det_centre[1] - s[1]];
        let r = c[0].hypot(c[1]);
        let dir = [c[0] / r, c[1] / r];
        let mut acc = vec![0.0f64; n];
        for ((j, i), &v) in image.indexed_iter() {
            if v == 0.0 {
                continue;
            }
            for (oy, ox) in [(-0.25, -0.25), (-0.25, 0.25), (0.25, -0.25), (0.25, 0.25)] {
                let p = [
                    grid.x(i) + ox * grid.dx_mm - s[0],
                    grid.y(j) + oy * grid.dy_mm - s[1],
                ];
                let along = p[0] * dir[0] + p[1] * dir[1];
                let lat = p[0] * view.det_u[0] + p[1] * view.det_u[1];
                let gamma = lat.atan2(along);
                let dist = along.hypot(lat);
                let pos = det.index_of(gamma);
                let k = pos.floor();
                let f = pos - k;
                let w = v as f64 * grid.dx_mm * grid.dy_mm / 4.0 / (dist * det.spacing);
                for (kk, ww) in [(k, 1.0 - f), (k + 1.0, f)] {
                    if kk >= 0.0 && (kk as usize) < n {
                        acc[kk as usize] += w * ww;
                    }
                }
            }
        }
        for (o, a) in row.iter_mut().zip(&acc) {
            *o = *a as f32;
        }
    }
    sino
}

/// How the slice image is forward-projected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Projector {
    /// MATLAB-style pixel-driven (2×2 sub-pixels, linear split between sensors), as the seed's `fanbeam`.
    Pixels,
    /// ctrecon's ray-driven Joseph projector (`projector::forward_2d`).
    Joseph,
}

/// (PSNR in dB with the slice's data range, RMSE) of the fan-beam FBP at sensor spacing `spacing_deg`,
/// with the MATLAB-style pixel-driven projection.
pub fn seed_experiment(spacing_deg: f64) -> (f64, f64) {
    seed_experiment_with(spacing_deg, Projector::Pixels)
}

/// As [`seed_experiment`] with a chosen projector.
pub fn seed_experiment_with(spacing_deg: f64, projector: Projector) -> (f64, f64) {
    let (slice, grid) = seed_slice();
    let fan = MatlabFan::arc(128, 128, 250.0, spacing_deg, 1.0);
    let views = fan
        .to_fan()
        .and_then(|f| f.to_views())
        .expect("the seed geometry is valid");
    let sino = match projector {
        Projector::Pixels => project_pixels(slice.view(), &grid, &views),
        Projector::Joseph => forward_2d(&views, slice.view(), &grid),
    };
    let image = fbp_2d(
        &views,
        sino.view(),
        &grid,
        &FbpParams::default(),
        unattended(),
    )
    .expect("fan-beam FBP of the seed geometry");
    let (lo, hi) = slice
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    let range = (hi - lo) as f64;
    let p = psnr(image.view(), slice.view(), range, None).expect("same shapes");
    let e = rmse(image.view(), slice.view(), None).expect("same shapes");
    (p, e)
}

#[allow(dead_code)]
fn main() {
    ctrecon::config::limit_simd_from_env();
    for projector in [Projector::Pixels, Projector::Joseph] {
        println!("{projector:?} forward projection of the slice:");
        for spacing in [2.0, 1.0, 0.25] {
            let (p, e) = seed_experiment_with(spacing, projector);
            println!("  sensor spacing {spacing:>4}°: PSNR {p:6.2} dB, RMSE {e:.4}");
        }
    }
}
