//! The cone-beam Joseph pair organised by detector columns, for panels whose v axis is the volume's z
//! axis (every circular cone beam): the same (voxel, weight) pairs as the ray walks of
//! [`super::joseph3`], up to f32 rounding of the sample positions, computed in passes as cheap as a
//! voxel-driven back projection.
//!
//! With the panel's v axis along z, the rays of one detector column share their x and y components,
//! so they share the dominant axis of their walk (x or y, unless the ray is steeper than 45° in z,
//! see below), cross every plane of that axis at the same in-plane position, and so read the same two
//! volume lines along z there; along those lines, the crossing of row `r` is affine in `r`. A column's
//! forward projection is therefore, plane after plane, one blend of two contiguous z lines and one
//! linear interpolation per row ([`super::cone_lines`]); the back projection is its transpose.
//!
//! Layouts: the volume is copied into two padded plane stacks, one per dominant axis (`[x][y][z]` and
//! `[y][x][z]`, one zero value before and two after every line and every plane's line list), so that
//! the z lines are contiguous and a sample half outside the grid reads zeros. Both directions go one
//! band of planes at a time, so that the band's lines stay in the core's cache while every view
//! reads or adds to them: the forward projection keeps each view's sums per column in the view's
//! part of the output and weights them into the panel's layout at the end; the back projection
//! accumulates into the stack layouts, one band per task (no two tasks write the same values), and
//! adds them into the `[z][y][x]` volume at the end.
//!
//! Rays whose walk steps along z (|d_z|/Δz larger than both others) and views whose panel is tilted
//! keep the ray walks of [`super::joseph3`].

use rayon::prelude::*;

use super::cone_lines::{Form, SCRATCH_PAD};
use super::cone_plans::ViewPlan;
#[cfg(test)]
use super::cone_plans::plan;
pub use super::cone_plans::{PlanCache, Plans};
use super::cone_stacks::{Axis, Stack};
use super::cone_steps::{BAND, Planned, band_steps};
use super::joseph3::{self, Walk3};
use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::geometry::Views3;
use crate::recon::grid::VolumeGrid;

/// Bytes the pair allocates besides its input and output: the padded stacks and the weighted data of
/// one pass ([`super::cone_stacks::work_bytes`]) and the plans a projector keeps
/// ([`super::cone_plans::cached_bytes`]).
pub fn work_bytes(views: &Views3, grid: &VolumeGrid) -> u64 {
    super::cone_stacks::work_bytes(views, grid)
        .saturating_add(super::cone_plans::cached_bytes(views))
}

/// Forward-project every view of `plans` (flat `volume` `[z][y][x]`) into `out` (`[view][v][u]`, in
/// the plans' subset order) with the loops of `form` (which the CPU must run: [`Form::available`]).
pub fn forward_with(
    form: Form,
    views: &Views3,
    grid: &VolumeGrid,
    plans: &Plans,
    volume: &[f32],
    out: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let (subset, plans) = (plans.subset(), &plans.views);
    let (nu, nv) = (views.detector.nu, views.detector.nv);
    let view_len = nu * nv;
    // Each planned view's sums, column after column (`[u][v]`), in the view's own part of `out`,
    // accumulated one band of planes at a time so that the band's stack lines stay in the core's
    // cache while every view reads them.
    out.par_chunks_mut(view_len).for_each(|o| o.fill(0.0));
    for axis in [Axis::X, Axis::Y] {
        if !uses_axis(plans, axis) {
            continue;
        }
        let stack = Stack::of(volume, grid, axis);
        let (pl, len) = (stack.plane_len(), stack.len);
        let planes = stack.values.len() / pl;
        for first in (0..planes).step_by(BAND) {
            let last = (first + BAND).min(planes);
            out.par_chunks_mut(view_len).zip(plans).try_for_each_init(
                || (vec![0.0f32; len + SCRATCH_PAD], [Planned::default(); BAND]),
                |(line, steps), (sums, plan)| {
                    cancel.check()?;
                    let Some(plan) = plan else { return Ok(()) };
                    for c in plan.columns.iter().filter(|c| c.axis == axis) {
                        let acc = &mut sums[c.col * nv..(c.col + 1) * nv];
                        let ks = c.planes.0.max(first)..c.planes.1.min(last);
                        let n = band_steps(form, c, ks, stack.lines, grid.nz, &plan.rows, steps);
                        for s in &steps[..n] {
                            let base = s.k * pl + s.j * len;
                            let (a, b) = stack.values[base..base + 2 * len].split_at(len);
                            form.forward(a, b, line, &s.step, s.rows.0..s.rows.1, acc);
                        }
                    }
                    Ok::<(), ReconError>(())
                },
            )?;
        }
    }
    // The sums weighted into `[v][u]`, the steep rays, and the views whose panel is tilted.
    out.par_chunks_mut(view_len)
        .zip(subset.par_iter().zip(plans))
        .try_for_each_init(
            || (vec![0.0f32; view_len], vec![0.0f32; nv]),
            |(sums, weights), (row, (&view, plan))| {
                cancel.check()?;
                let Some(plan) = plan else {
                    joseph3::forward_view(views, view, grid, volume, row);
                    return Ok(());
                };
                sums.copy_from_slice(row);
                row.fill(0.0);
                for c in &plan.columns {
                    let acc = &sums[c.col * nv..(c.col + 1) * nv];
                    c.weights(form, weights);
                    for (r, w) in (c.flat.0..c.flat.1).zip(weights.iter()) {
                        row[r * nu + c.col] = acc[r] * w;
                    }
                }
                for &(r, col) in &plan.steep {
                    row[r * nu + col] = Walk3::new(&views.ray(&views.views[view], r, col), grid)
                        .map_or(0.0, |w| w.dot(volume));
                }
                Ok(())
            },
        )
}

/// Whether any planned view has a column whose rays walk along `axis`.
fn uses_axis(plans: &[Option<ViewPlan>], axis: Axis) -> bool {
    plans
        .iter()
        .flatten()
        .any(|p| p.columns.iter().any(|c| c.axis == axis))
}

/// `image` = the back projection of `data` (`[view][v][u]`, one view per entry of the plans' subset),
/// overwriting it, with the loops of `form` (which the CPU must run: [`Form::available`]).
pub fn back_with(
    form: Form,
    views: &Views3,
    grid: &VolumeGrid,
    plans: &Plans,
    data: &[f32],
    image: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let nu = views.detector.nu;
    let view_len = nu * views.detector.nv;
    // Each column's data, weighted, contiguous along v: `[view][column][row − rows.start]`, in the
    // buffers `plans` shares with the other plans of its cache (or fresh ones while another pass
    // holds them).
    let (mut kept, mut fresh) = (plans.weighted.try_lock().ok(), Vec::new());
    let weighted: &mut Vec<Vec<f32>> = kept.as_deref_mut().unwrap_or(&mut fresh);
    let (subset, plans) = (plans.subset(), &plans.views);
    weighted.resize_with(plans.len(), Vec::new);
    weighted
        .par_iter_mut()
        .zip(plans.par_iter().zip(data.par_chunks_exact(view_len)))
        .for_each_init(
            || vec![0.0f32; views.detector.nv],
            |weights, (w, (plan, d))| {
                let Some(plan) = plan else { return };
                let h = plan.rows.len();
                // Every value is written: a kept buffer last held another subset's views.
                w.resize(plan.columns.len() * h, 0.0);
                for (c, column) in plan.columns.iter().zip(w.chunks_exact_mut(h)) {
                    c.weights(form, weights);
                    let (lo, hi) = (c.flat.0 - plan.rows.start, c.flat.1 - plan.rows.start);
                    column[..lo].fill(0.0);
                    column[hi..].fill(0.0);
                    let rows = (c.flat.0..c.flat.1).zip(weights.iter());
                    for ((r, w), out) in rows.zip(&mut column[lo..hi]) {
                        *out = d[r * nu + c.col] * w;
                    }
                }
            },
        );
    let weighted: &[Vec<f32>] = weighted;
    image.fill(0.0);
    for axis in [Axis::X, Axis::Y] {
        if !uses_axis(plans, axis) {
            continue;
        }
        let (planes, lines) = match axis {
            Axis::X => (grid.nx, grid.ny),
            Axis::Y => (grid.ny, grid.nx),
        };
        let mut stack = Stack::zeros(planes, lines, grid.nz);
        let (pl, len) = (stack.plane_len(), stack.len);
        stack
            .values
            .par_chunks_mut(pl * BAND)
            .enumerate()
            .try_for_each(|(band, values)| {
                let first = band * BAND;
                let last = first + values.len() / pl;
                let mut line = vec![0.0f32; 2 * (len + SCRATCH_PAD)];
                let mut steps = [Planned::default(); BAND];
                for (plan, w) in plans.iter().zip(weighted) {
                    cancel.check()?;
                    let Some(plan) = plan else { continue };
                    let h = plan.rows.len();
                    for (i, c) in plan.columns.iter().enumerate() {
                        if c.axis != axis {
                            continue;
                        }
                        let column = &w[i * h..(i + 1) * h];
                        let ks = c.planes.0.max(first)..c.planes.1.min(last);
                        let n = band_steps(form, c, ks, lines, grid.nz, &plan.rows, &mut steps);
                        for s in &steps[..n] {
                            let base = (s.k - first) * pl + s.j * len;
                            let (a, b) = values[base..base + 2 * len].split_at_mut(len);
                            let data = &column[s.rows.0 - plan.rows.start..];
                            form.back(a, b, &mut line, &s.step, s.rows.0..s.rows.1, data);
                        }
                    }
                }
                Ok::<(), ReconError>(())
            })?;
        stack.add_into(image, grid, axis);
    }
    for ((plan, &view), d) in plans.iter().zip(subset).zip(data.chunks_exact(view_len)) {
        match plan {
            None => joseph3::back_view(views, view, grid, d, image),
            Some(plan) => {
                for &(r, col) in &plan.steep {
                    if let Some(w) = Walk3::new(&views.ray(&views.views[view], r, col), grid) {
                        w.axpy(d[r * nu + col], image);
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
#[path = "cone_columns_tests.rs"]
pub(crate) mod tests;
