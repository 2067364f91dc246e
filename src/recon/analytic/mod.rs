//! Analytic reconstruction: ramp filters and windows, parallel and fan-beam FBP (with Parker short-scan
//! weights) and FDK (Parker and Wang weights), with voxel-driven backprojectors.

use ndarray::{Array2, Array3, ArrayView2, ArrayView3};

use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Views2, Views3};
use crate::recon::grid::{ImageGrid, VolumeGrid};

/// Filtered backprojection of a 2D sinogram `[view][u]` (parallel or fan beam) onto `grid`.
pub fn fbp_2d(
    _views: &Views2,
    _sinogram: ArrayView2<'_, f32>,
    _grid: &ImageGrid,
    _params: &FbpParams,
    _ctl: Control<'_>,
) -> Result<Array2<f32>, ReconError> {
    Err(ReconError::param("algorithm", "FBP is not implemented yet"))
}

/// FDK reconstruction of a cone-beam projection stack `[view][v][u]` onto `grid`.
pub fn fdk(
    _views: &Views3,
    _projections: ArrayView3<'_, f32>,
    _grid: &VolumeGrid,
    _params: &FbpParams,
    _ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    Err(ReconError::param("algorithm", "FDK is not implemented yet"))
}
