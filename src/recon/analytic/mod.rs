//! Analytic reconstruction: ramp filters and windows, parallel and fan-beam FBP (with Parker short-scan
//! and Wang offset-detector weights) and FDK (Parker and Wang weights), with voxel-driven backprojectors.
//!
//! - [`filter`]: Kak–Slaney spatial ramp kernels (flat and equiangular), windows, cut-off, zero padding.
//! - [`weights`]: which redundancy weighting a scan needs, Parker and Wang weights.
//! - `fbp2d` / `fdk`: the algorithms ([`fbp_2d`], [`fdk`]); `backproject` (rows along x) and `column`
//!   (cone-beam lines along z): the hot kernels.
//! - [`check`]: what the algorithms would refuse about a geometry and parameters, checked before any data.
//!
//! Every algorithm reads only the canonical per-view geometry; divergent beams must come from a planar
//! circular orbit with a detector facing the rotation centre (every parametric geometry of ctrecon
//! does), or from a helix (`helix`, `helical`: the helical weighted FBP). Unsupported combinations (parallel beams over less than 180°, short scans with an offset
//! detector, more than one turn, a detector that misses the central ray) are typed errors, never a silently
//! wrong image. Filtering runs in f64, backprojection in f32. Cancel is checked once per view while
//! filtering and once per image row / view batch while backprojecting; progress is reported per view.

mod admit;
mod backproject;
#[cfg(target_arch = "x86_64")]
mod backproject_x86;
mod column;
#[cfg(target_arch = "x86_64")]
mod column_x86;
mod fbp2d;
mod fdk;
mod fdk_filter;
pub mod filter;
mod helical;
mod helix;
mod orbit;
mod progress;
pub mod weights;

use ndarray::{Array2, Array3, ArrayView2, ArrayView3};

use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Views, Views2, Views3};
use crate::recon::grid::{ImageGrid, VolumeGrid};

pub use admit::check;
pub use fbp2d::ARC_OVERSAMPLING;

/// Filtered backprojection of a 2D sinogram `[view][u]` (parallel or fan beam) onto `grid`; the result is
/// `[y][x]` in the units of the data per mm (μ in 1/mm for line integrals in mm·(1/mm)).
pub fn fbp_2d(
    views: &Views2,
    sinogram: ArrayView2<'_, f32>,
    grid: &ImageGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array2<f32>, ReconError> {
    fbp2d::fbp_2d(views, sinogram, grid, params, ctl)
}

/// FDK reconstruction of a cone-beam projection stack `[view][v][u]` onto `grid` (`[z][y][x]`): circular
/// FDK where the sources lie in one plane, the helical weighted FBP (Stierstorfer-style weights over
/// conjugate views, voxels beyond the data's z coverage set to 0; see `helical`) where they climb a helix.
pub fn fdk(
    views: &Views3,
    projections: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    if orbit::is_planar(views) {
        fdk::fdk(views, projections, grid, params, ctl)
    } else {
        helical::helical_fbp(views, projections, grid, params, ctl)
    }
}

/// The checks every cone-beam analytic method makes first: a valid grid and parameters, and a projection
/// stack of the geometry's shape.
fn check_stack(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
) -> Result<(), ReconError> {
    grid.validate()?;
    params.validate()?;
    let expected = views.shape();
    if proj.shape() != expected {
        return Err(ReconError::ShapeMismatch {
            expected: expected.to_vec(),
            got: proj.shape().to_vec(),
        });
    }
    Ok(())
}

pub use fdk::back_project_voxels;

/// Bytes [`back_project_voxels`] allocates besides its input: those of FDK with default parameters.
pub fn back_project_voxels_bytes(views: &Views3, grid: &VolumeGrid) -> u64 {
    fdk::estimate_bytes(views, grid, &FbpParams::default())
}

/// Bytes FBP or FDK allocates besides its input: the output, the filtered views (2D) or one filtered
/// projection per thread (FDK), and per-thread filter buffers. Grids of the wrong dimensionality count
/// zero (the dispatcher refuses them), and so do 3D parallel beams: the dispatcher runs and counts them
/// slice by slice ([`crate::recon::algorithm::estimate_bytes`]).
pub fn estimate_bytes(
    views: &Views,
    grid: &crate::recon::algorithm::OutputGrid,
    params: &FbpParams,
) -> u64 {
    use crate::recon::algorithm::OutputGrid;
    match (views, grid) {
        (Views::D2(v), OutputGrid::Image(g)) => fbp2d::estimate_bytes(v, g, params),
        (Views::D3(v), OutputGrid::Volume(g)) if !orbit::is_planar(v) => {
            helical::estimate_bytes(v, g, params)
        }
        (Views::D3(v), OutputGrid::Volume(g)) => fdk::estimate_bytes(v, g, params),
        (Views::Slices(_), _) => 0,
        _ => 0,
    }
}

#[cfg(test)]
mod helical_tests;
