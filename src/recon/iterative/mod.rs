//! Iterative reconstruction (ART, SART, OS-SART, SIRT, CGLS, MLEM/OSEM, TV) over the matched projector
//! pair of [`crate::recon::projector`].

pub mod params;

use ndarray::{ArrayD, ArrayViewD};

use crate::recon::algorithm::{AlgorithmSpec, OutputGrid};
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::Views;
use crate::recon::grid::Limits;

/// Bytes an iterative run allocates besides its input (image-sized and data-sized work arrays).
pub fn estimate_bytes(_spec: &AlgorithmSpec, _views: &Views, _grid: &OutputGrid) -> u64 {
    0
}

/// Run the iterative algorithm of `spec` on `data`, starting from `initial` (or zero).
pub fn solve(
    spec: &AlgorithmSpec,
    _views: &Views,
    _data: ArrayViewD<'_, f32>,
    _grid: &OutputGrid,
    _initial: Option<ArrayViewD<'_, f32>>,
    _limits: &Limits,
    _ctl: Control<'_>,
) -> Result<ArrayD<f32>, ReconError> {
    Err(ReconError::param(
        "algorithm",
        format!("`{}` is not implemented yet", spec.name()),
    ))
}
