//! Reconstruction of a 3D parallel beam ([`SliceViews`]) slice by slice: each output slice z takes the
//! sinogram of the plane at its height (rows linearly interpolated, zero beyond the detector) and runs the 2D
//! parallel-beam method of the same spec (FBP for `fbp` and `fdk`; every iterative method as in 2D, its FBP
//! start included) on the slice's grid. Slices run in parallel on the rayon pool; a slice whose plane misses
//! the detector stays zero. Cancel is checked by every slice's own 2D run; progress is reported once per
//! finished slice (stage = the method's name, fraction = slices done / nz).

use std::sync::Mutex;

use ndarray::{Array3, ArrayView3, Axis};
use rayon::prelude::*;

use super::{AlgorithmSpec, OutputGrid};
use crate::recon::control::{Control, NoProgress};
use crate::recon::error::ReconError;
use crate::recon::geometry::{SliceViews, Views};
use crate::recon::grid::{Limits, VolumeGrid};

/// Slices run at once: one per rayon thread, at most one per slice.
fn concurrent_slices(grid: &VolumeGrid) -> u64 {
    (rayon::current_num_threads() as u64).clamp(1, grid.nz.max(1) as u64)
}

/// Bytes a slice-by-slice run allocates besides its input: the output volume, and for every slice running
/// at once its interpolated sinogram and everything its 2D run allocates (output image included).
pub fn estimate_bytes(spec: &AlgorithmSpec, views: &SliceViews, grid: &VolumeGrid) -> u64 {
    let rows = Views::D2(views.rows.clone());
    let slice = OutputGrid::Image(grid.slice_grid());
    let [n, _, nu] = views.shape();
    let sinogram = Limits::f32_bytes((n as u64).saturating_mul(nu as u64));
    let per_slice = super::run::estimate_bytes(spec, &rows, &slice).saturating_add(sinogram);
    Limits::f32_bytes(grid.voxels())
        .saturating_add(concurrent_slices(grid).saturating_mul(per_slice))
}

/// Reconstruct the projections `data` (`[view][v][u]`, line integrals; shape already checked) of `views` on
/// `grid` (`[z][y][x]`) slice by slice with `spec`. Limits have been checked for the whole run.
pub fn reconstruct(
    spec: &AlgorithmSpec,
    views: &SliceViews,
    data: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    limits: &Limits,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    let rows = Views::D2(views.rows.clone());
    let slice = OutputGrid::Image(grid.slice_grid());
    let mut out = Array3::<f32>::zeros(grid.shape());
    let done = Mutex::new(0usize);
    let quiet = Control::new(ctl.cancel, &NoProgress);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .try_for_each(|(k, mut img)| {
            ctl.check()?;
            let z = grid.z(k);
            if views.covers(z) {
                let sino = views.sinogram_at(data, z);
                let image = super::run::reconstruct(
                    spec,
                    &rows,
                    sino.view().into_dyn(),
                    &slice,
                    limits,
                    quiet,
                )?;
                let image = image.into_dimensionality::<ndarray::Ix2>().map_err(|e| {
                    ReconError::param("grid", format!("a slice is not an image: {e}"))
                })?;
                img.assign(&image);
            }
            // Reported under the lock, so that the fractions arrive in order.
            let mut n = done.lock().unwrap_or_else(|e| e.into_inner());
            *n += 1;
            ctl.step(spec.name(), *n as f64 / grid.nz as f64);
            Ok::<(), ReconError>(())
        })?;
    Ok(out)
}
