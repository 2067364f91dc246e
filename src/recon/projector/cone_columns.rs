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

use std::ops::Range;

use rayon::prelude::*;

use super::cone_lines::{Form, PlaneStep, SCRATCH_PAD, reaching};
pub use super::cone_stacks::work_bytes;
use super::cone_stacks::{Axis, Stack};
use super::footprint3::footprint;
use super::joseph3::{self, Walk3};
use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::geometry::Views3;
use crate::recon::grid::VolumeGrid;

/// Planes per band: a band of 16 planes of a 128² slab is about 1 MB, so the band stays in the
/// core's cache while every view reads it (forward) or adds to it (back, one task per band).
const BAND: usize = 16;

/// One detector column's rays in the layout of their dominant axis.
#[derive(Debug, Clone, Copy)]
struct Column {
    col: usize,
    axis: Axis,
    /// Planes the column's rays cross inside the grid (a superset).
    planes: (usize, usize),
    /// In-plane line coordinate at plane `k`: `c0 + k·dc` (voxel units).
    c0: f32,
    dc: f32,
    /// Position along z at plane `k`, row `r`: `a_e + (k − a_d)·(p + r·q)` (voxel units).
    a_e: f64,
    a_d: f64,
    p: f64,
    q: f64,
    /// Ray direction (unnormalised) without its z part, the z part at row 0 and per row, and the
    /// walk weight's factor `Δ_d/|d_d|`: a ray's weight is `|d|·Δ_d/|d_d|` (mm per plane).
    dx: f64,
    dy: f64,
    dz0: f64,
    dzr: f64,
    scale: f64,
    /// `|d_z|/Δz` above this value makes a ray steep (its walk steps along z).
    steep_above: f64,
}

impl Column {
    fn d_z(&self, row: usize) -> f64 {
        self.dz0 + row as f64 * self.dzr
    }
    fn is_steep(&self, row: usize, dz_mm: f64) -> bool {
        self.d_z(row).abs() / dz_mm > self.steep_above
    }
    /// Walk weight of row `row` (0 for steep rays, which the walks handle).
    fn weight(&self, row: usize, dz_mm: f64) -> f32 {
        if self.is_steep(row, dz_mm) {
            return 0.0;
        }
        let dz = self.d_z(row);
        ((self.dx * self.dx + self.dy * self.dy + dz * dz).sqrt() * self.scale) as f32
    }
    /// The step of plane `k`, its two line indices (padded), and the rows that reach the grid.
    /// Counts and indices convert through `u32` (every grid and panel here is far smaller), which
    /// gives the same values with cheaper conversions than `usize`.
    #[inline(always)]
    fn step(
        &self,
        k: usize,
        n_c: usize,
        n_e: usize,
        rows: &Range<usize>,
    ) -> (PlaneStep, usize, Range<usize>) {
        let t = (self.c0 + k as u32 as f32 * self.dc + 1.0)
            .max(0.0)
            .min(n_c as u32 as f32 + 1.0);
        let j = t as u32;
        let w1 = t - j as f32;
        let j = j as usize;
        let rel = k as u32 as f64 - self.a_d;
        let e0 = self.a_e + rel * self.p;
        let de = rel * self.q;
        let step = PlaneStep {
            w0: 1.0 - w1,
            w1,
            e0: e0 as f32,
            de: de as f32,
        };
        // Rows whose position lies in (−1, n_e) in f64, then in f32 as the loops compute it.
        let guess = if de.abs() < 1e-12 {
            rows.clone()
        } else {
            let inv = 1.0 / de;
            let r1 = (-1.0 - e0) * inv;
            let r2 = (n_e as u32 as f64 - e0) * inv;
            let (start, end) = (rows.start as u32 as f64, rows.end as u32 as f64);
            let lo = (floor(r1.min(r2)) + 1.0).clamp(start, end);
            let hi = ceil(r1.max(r2)).clamp(lo, end);
            lo as u32 as usize..hi as u32 as usize
        };
        let span = reaching(&step, guess, rows.clone(), n_e + 3);
        (step, j, span)
    }
}

/// `x.floor()` without the library call that baseline x86-64 makes of it (no SSE4.1 rounding):
/// through an integer where that is exact, else the library's; +0 where the library gives −0.
#[inline(always)]
fn floor(x: f64) -> f64 {
    if x.abs() < 4.0e15 {
        let t = x as i64 as f64;
        if t > x { t - 1.0 } else { t }
    } else {
        x.floor()
    }
}

/// `x.ceil()` as [`floor`] does `x.floor()`.
#[inline(always)]
fn ceil(x: f64) -> f64 {
    if x.abs() < 4.0e15 {
        let t = x as i64 as f64;
        if t < x { t + 1.0 } else { t }
    } else {
        x.ceil()
    }
}

/// One view's columns, or `None` when its panel is tilted (the walks handle it whole).
struct ViewPlan {
    rows: Range<usize>,
    columns: Vec<Column>,
    /// Steep rays `(row, col)`.
    steep: Vec<(usize, usize)>,
}

fn plan(views: &Views3, view: usize, grid: &VolumeGrid) -> Option<ViewPlan> {
    let v = &views.views[view];
    if v.det_v[0] != 0.0 || v.det_v[1] != 0.0 || v.det_v[2] == 0.0 {
        return None;
    }
    let det = &views.detector;
    let (rows, cols) = footprint(views, v, grid);
    let s = grid.spacing_mm;
    let lo = [grid.x(0), grid.y(0), grid.z(0)];
    let a: [f64; 3] = std::array::from_fn(|k| (v.source[k] - lo[k]) / s[k]);
    let mut columns = Vec::with_capacity(cols.len());
    let mut steep = Vec::new();
    let n = [grid.nx, grid.ny];
    for col in cols {
        let u = det.u(col);
        let p0: [f64; 3] =
            std::array::from_fn(|k| v.det_centre[k] + u * v.det_u[k] + det.v(0) * v.det_v[k]);
        let d = [
            p0[0] - v.source[0],
            p0[1] - v.source[1],
            p0[2] - v.source[2],
        ];
        let dzr = det.dv_mm * v.det_v[2];
        let b = [d[0] / s[0], d[1] / s[1]];
        let (axis, di, ci) = if b[0].abs() >= b[1].abs() {
            (Axis::X, 0, 1)
        } else {
            (Axis::Y, 1, 0)
        };
        let mut column = Column {
            col,
            axis,
            planes: (0, 0),
            c0: 0.0,
            dc: 0.0,
            a_e: a[2],
            a_d: a[di],
            p: 0.0,
            q: 0.0,
            dx: d[0],
            dy: d[1],
            dz0: d[2],
            dzr,
            scale: 0.0,
            steep_above: b[0].abs().max(b[1].abs()),
        };
        if b[di] != 0.0 && b[di].is_finite() {
            let sc = b[ci] / b[di];
            let c0 = a[ci] - a[di] * sc;
            let m = s[di] / (s[2] * d[di]);
            column.c0 = c0 as f32;
            column.dc = sc as f32;
            column.p = d[2] * m;
            column.q = dzr * m;
            column.scale = s[di] / d[di].abs();
            column.planes = planes(c0, sc, n[ci], n[di]);
        }
        for row in rows.clone() {
            if b[di] == 0.0 || column.is_steep(row, s[2]) {
                steep.push((row, col));
            }
        }
        columns.push(column);
    }
    Some(ViewPlan {
        rows,
        columns,
        steep,
    })
}

/// Planes `[lo, hi)` of `count` where `c0 + k·s` lies in (−1, n) (a superset, as the walks compute it).
fn planes(c0: f64, s: f64, n: usize, count: usize) -> (usize, usize) {
    if s.abs() < 1e-12 {
        return if c0 > -1.0 && c0 < n as f64 {
            (0, count)
        } else {
            (0, 0)
        };
    }
    let k1 = (-1.0 - c0) / s;
    let k2 = (n as f64 - c0) / s;
    let lo = k1.min(k2).floor().max(0.0);
    let hi = (k1.max(k2).ceil() + 1.0).min(count as f64);
    if lo.is_nan() || hi.is_nan() || hi <= lo {
        (0, 0)
    } else {
        (lo as usize, hi as usize)
    }
}

/// Forward-project every view of `subset` (flat `volume` `[z][y][x]`) into `out` (`[view][v][u]`).
pub fn forward(
    views: &Views3,
    grid: &VolumeGrid,
    volume: &[f32],
    subset: &[usize],
    out: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    forward_with(Form::detect(), views, grid, volume, subset, out, cancel)
}

/// [`forward`] with the loops of `form` (which the CPU must run: [`Form::available`]).
pub fn forward_with(
    form: Form,
    views: &Views3,
    grid: &VolumeGrid,
    volume: &[f32],
    subset: &[usize],
    out: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let plans: Vec<Option<ViewPlan>> = subset.par_iter().map(|&v| plan(views, v, grid)).collect();
    let (nu, nv) = (views.detector.nu, views.detector.nv);
    let view_len = nu * nv;
    // Each planned view's sums, column after column (`[u][v]`), in the view's own part of `out`,
    // accumulated one band of planes at a time so that the band's stack lines stay in the core's
    // cache while every view reads them.
    out.par_chunks_mut(view_len).for_each(|o| o.fill(0.0));
    for axis in [Axis::X, Axis::Y] {
        if !uses_axis(&plans, axis) {
            continue;
        }
        let stack = Stack::of(volume, grid, axis);
        let (pl, len) = (stack.plane_len(), stack.len);
        let planes = stack.values.len() / pl;
        for first in (0..planes).step_by(BAND) {
            let last = (first + BAND).min(planes);
            out.par_chunks_mut(view_len).zip(&plans).try_for_each_init(
                || vec![0.0f32; len + SCRATCH_PAD],
                |line, (sums, plan)| {
                    cancel.check()?;
                    let Some(plan) = plan else { return Ok(()) };
                    for c in plan.columns.iter().filter(|c| c.axis == axis) {
                        let acc = &mut sums[c.col * nv..(c.col + 1) * nv];
                        for k in c.planes.0.max(first)..c.planes.1.min(last) {
                            let (step, j, rows) = c.step(k, stack.lines, grid.nz, &plan.rows);
                            if rows.is_empty() {
                                continue;
                            }
                            let base = k * pl + j * len;
                            let (a, b) = stack.values[base..base + 2 * len].split_at(len);
                            form.forward(a, b, line, &step, rows, acc);
                        }
                    }
                    Ok::<(), ReconError>(())
                },
            )?;
        }
    }
    // The sums weighted into `[v][u]`, the steep rays, and the views whose panel is tilted.
    out.par_chunks_mut(view_len)
        .zip(subset.par_iter().zip(&plans))
        .try_for_each_init(
            || vec![0.0f32; view_len],
            |sums, (row, (&view, plan))| {
                cancel.check()?;
                let Some(plan) = plan else {
                    joseph3::forward_view(views, view, grid, volume, row);
                    return Ok(());
                };
                sums.copy_from_slice(row);
                row.fill(0.0);
                for c in &plan.columns {
                    let acc = &sums[c.col * nv..(c.col + 1) * nv];
                    for r in plan.rows.clone() {
                        row[r * nu + c.col] = acc[r] * c.weight(r, grid.spacing_mm[2]);
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

/// `image` = the back projection of `data` (`[view][v][u]`, one view per `subset` entry), overwriting it.
pub fn back(
    views: &Views3,
    grid: &VolumeGrid,
    data: &[f32],
    subset: &[usize],
    image: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    back_with(Form::detect(), views, grid, data, subset, image, cancel)
}

/// [`back`] with the loops of `form` (which the CPU must run: [`Form::available`]).
pub fn back_with(
    form: Form,
    views: &Views3,
    grid: &VolumeGrid,
    data: &[f32],
    subset: &[usize],
    image: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let nu = views.detector.nu;
    let view_len = nu * views.detector.nv;
    let plans: Vec<Option<ViewPlan>> = subset.par_iter().map(|&v| plan(views, v, grid)).collect();
    // Each column's data, weighted, contiguous along v: `[view][column][row − rows.start]`.
    let weighted: Vec<Vec<f32>> = plans
        .par_iter()
        .zip(data.par_chunks_exact(view_len))
        .map(|(plan, d)| {
            let Some(plan) = plan else { return Vec::new() };
            let h = plan.rows.len();
            let mut w = vec![0.0f32; plan.columns.len() * h];
            for (i, c) in plan.columns.iter().enumerate() {
                for r in plan.rows.clone() {
                    w[i * h + r - plan.rows.start] =
                        d[r * nu + c.col] * c.weight(r, grid.spacing_mm[2]);
                }
            }
            w
        })
        .collect();
    image.fill(0.0);
    for axis in [Axis::X, Axis::Y] {
        if !uses_axis(&plans, axis) {
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
                for (plan, w) in plans.iter().zip(&weighted) {
                    cancel.check()?;
                    let Some(plan) = plan else { continue };
                    let h = plan.rows.len();
                    for (i, c) in plan.columns.iter().enumerate() {
                        if c.axis != axis {
                            continue;
                        }
                        let column = &w[i * h..(i + 1) * h];
                        for k in c.planes.0.max(first)..c.planes.1.min(last) {
                            let (step, j, rows) = c.step(k, lines, grid.nz, &plan.rows);
                            if rows.is_empty() {
                                continue;
                            }
                            let base = (k - first) * pl + j * len;
                            let (a, b) = values[base..base + 2 * len].split_at_mut(len);
                            let data = &column[rows.start - plan.rows.start..];
                            form.back(a, b, &mut line, &step, rows, data);
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
