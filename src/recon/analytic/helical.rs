//! Helical filtered back projection: a weighted FDK in the manner of Stierstorfer et al. (2004), without
//! the rebinning to parallel rays (docs/helical.md argues the choice and gives the formula).
//!
//! Each view is pre-weighted `DSD/√(DSD² + u² + v²)` and ramp-filtered along detector rows as in
//! circular FDK, but without FDK's ½. A voxel `x` is then summed over every view `β` whose cone it lies in:
//! `f(x) = Σ_β Δβ · R²/lc² · w(β, x) · Q_β(u(x), v(x))`, where `lc` is the voxel's distance from the source
//! along the panel normal and `w = W(q_β) / Σ_k W(q_k)`: `q` is the voxel's row coordinate on the panel
//! scaled to ±1 at the outer row centres, `W(q) = 1` for `|q| ≤ Q`, falling smoothly (`1 − s²(3 − 2s)`,
//! `s = (|q| − Q)/(1 − Q)`) to 0 at `|q| = 1`, and the sum runs over the views `β_k` that measure the
//! same line through `x` (its conjugates: `β + 2πm`, and the opposite source `β₁ + 2πm` where the line
//! meets the orbit again) and exist in the scan. The weights of each line through `x` therefore add up
//! to 1, which on a circle reduces to FDK's ½ + ½; the rows near the panel's edges, the most
//! cone-angle-inexact, get little weight wherever a conjugate view sees the voxel nearer its centre.
//!
//! Long objects: a voxel is kept only if the views that see it cover a π-range of line directions
//! (the last view's ray through it turned by at least π − 1.5 steps from the first's); voxels beyond
//! the data's z coverage (seen over less than that) are set to 0 instead of being filled with
//! partial, streaky sums.
//!
//! Loops: views are filtered in batches (in parallel), each batch stored by detector columns; the
//! volume is accumulated as lines along z (`[y][x][z]`), planes y in parallel, each line against every
//! view of the batch: a line projects into one detector column position with row positions affine in z.

use ndarray::{Array3, ArrayView3};
use rayon::prelude::*;

use super::filter::{Kernel, RowFilter, padded_len};
use super::helix::{Helix, ViewMap, flat_panel, helix_of, turned, visible_span};
use super::progress::Ticker;
use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Detector2, Views3};
use crate::recon::grid::VolumeGrid;

/// `Q`: the half-width, in scaled row coordinates, over which the row weight is 1.
pub const FLAT_ROWS: f64 = 0.6;

/// Views filtered and back-projected per pass, at most.
const BATCH: usize = 64;

/// The row weight `W(q)`; see the module docs.
#[inline]
fn row_weight(q: f32) -> f32 {
    const Q: f32 = FLAT_ROWS as f32;
    // Branch-free, so that the loops over a line vectorise: s = 1 (weight 0) from |q| = 1 on.
    let s = ((q.abs() - Q) * (1.0 / (1.0 - Q))).clamp(0.0, 1.0);
    1.0 - s * s * (3.0 - 2.0 * s)
}

/// Most conjugate views a voxel's line is weighted against (enough for pitches down to about 0.15; below,
/// the weights of a line add up to less than 1).
const MAX_CONJUGATES: usize = 16;

/// What the helical back projection refuses about `views`, checked without data.
pub fn check(views: &Views3, params: &FbpParams) -> Result<(), ReconError> {
    helix_of(views)?;
    padded_len(views.detector.nu, params.padded_len)?;
    Ok(())
}

/// Helical weighted FBP of `proj` (`[view][v][u]`) onto `grid` (`[z][y][x]`); see the module docs.
pub fn helical_fbp(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    super::check_stack(views, proj, grid, params)?;
    let (helix, maps) = helix_of(views)?;
    let measured = views.detector;
    let det = flat_panel(&measured, maps[0].dsd)?;
    let kernel = Kernel::Ramp {
        spacing: det.du_mm * helix.radius / maps[0].dsd,
    };
    let filter = RowFilter::new(det.nu, kernel, 1.0, params)?;
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    let line_len = nx * nz;
    let mut sums = vec![0.0f32; ny * line_len];
    let mut first = vec![u32::MAX; ny * line_len];
    let mut last = vec![0u32; ny * line_len];
    let stored = (det.nu + 2) * (det.nv + 1);
    let mut panels = vec![0.0f32; BATCH * stored];
    let ticker = Ticker::new(ctl, "helical_fbp", maps.len());
    let span = visible_span(&helix, &det, &maps, grid);
    for start in (0..maps.len()).step_by(BATCH) {
        let end = (start + BATCH).min(maps.len());
        panels[..(end - start) * stored]
            .par_chunks_mut(stored)
            .enumerate()
            .try_for_each_init(
                || filter.scratch(),
                |scratch, (b, panel)| {
                    ctl.check()?;
                    filter_view(
                        &filter,
                        scratch,
                        (&measured, &det),
                        &maps[start + b],
                        helix.radius,
                        proj,
                        start + b,
                        panel,
                    );
                    Ok::<(), ReconError>(())
                },
            )?;
        let batch = Batch {
            panels: &panels[..(end - start) * stored],
            maps: &maps[start..end],
            first: start,
        };
        sums.par_chunks_mut(line_len)
            .zip(first.par_chunks_mut(line_len))
            .zip(last.par_chunks_mut(line_len))
            .enumerate()
            .try_for_each_init(
                || LineScratch {
                    weights: vec![0.0; nz],
                    column: vec![0.0; det.nv + 1],
                },
                |scratch, (y, ((acc, lo), hi))| {
                    ctl.check()?;
                    for x in 0..nx {
                        let at = x * nz..(x + 1) * nz;
                        let p = [grid.x(x), grid.y(y)];
                        let line = Line {
                            acc: &mut acc[at.clone()],
                            first: &mut lo[at.clone()],
                            last: &mut hi[at],
                        };
                        back_project_line(line, scratch, p, &batch, &helix, &det, grid, span);
                    }
                    Ok::<(), ReconError>(())
                },
            )?;
        ticker.add(end - start);
    }
    Ok(assemble(&sums, &first, &last, &maps, grid))
}

/// Views of one pass: their filtered panels (`[column][row]`, one zero column on each side and a zero
/// row after the last) and maps, and the index of the pass's first view.
struct Batch<'a> {
    panels: &'a [f32],
    maps: &'a [ViewMap],
    first: usize,
}

/// Buffers of one thread's lines: the weights of a line's voxels in one view, a blended column.
struct LineScratch {
    weights: Vec<f32>,
    column: Vec<f32>,
}

/// One line of voxels along z: its sums and the first and last view that saw each voxel.
struct Line<'a> {
    acc: &'a mut [f32],
    first: &'a mut [u32],
    last: &'a mut [u32],
}

/// Pre-weight and filter view `k` into `panel`, stored by columns, with Δβ·R² folded in. The rows are
/// those of `flat` (the measured panel, or the flat panel a cylindrical one is rebinned onto, sampled
/// bilinearly: column at fan angle atan(u/R), row at height × cos of it).
#[allow(clippy::too_many_arguments)]
fn filter_view(
    filter: &RowFilter,
    scratch: &mut super::filter::FilterScratch,
    (measured, flat): (&Detector2, &Detector2),
    m: &ViewMap,
    radius: f64,
    proj: ArrayView3<'_, f32>,
    k: usize,
    panel: &mut [f32],
) {
    let (nu, nv) = (flat.nu, flat.nv);
    let rows = nv + 1;
    let post = m.step * radius * radius;
    let view = proj.index_axis(ndarray::Axis(0), k);
    let cylindrical = measured.shape != crate::recon::geometry::PanelShape::Flat;
    // Where each flat column lies on the cylinder: its column and the cosine of its fan angle.
    let arc: Vec<(f64, f64)> = (0..nu)
        .map(|c| {
            let g = ((flat.u(c) + m.u0) / m.dsd).atan();
            (measured.col_of(m.dsd * g - m.u0), g.cos())
        })
        .collect();
    let sample = |r: usize, c: usize| -> f64 {
        if !cylindrical {
            return f64::from(view[[r, c]]);
        }
        let (col, cos) = arc[c];
        let height = (flat.v(r) + m.v0) * cos - m.v0;
        let row = measured.row_of(height);
        let at = |i: f64, j: f64| -> f64 {
            if i < 0.0 || j < 0.0 || i > (nv - 1) as f64 || j > (measured.nu - 1) as f64 {
                return 0.0;
            }
            f64::from(view[[i as usize, j as usize]])
        };
        let (r0, c0) = (row.floor(), col.floor());
        let (fr, fc) = (row - r0, col - c0);
        let top = at(r0, c0) * (1.0 - fc) + at(r0, c0 + 1.0) * fc;
        let bottom = at(r0 + 1.0, c0) * (1.0 - fc) + at(r0 + 1.0, c0 + 1.0) * fc;
        top * (1.0 - fr) + bottom * fr
    };
    panel.fill(0.0);
    for r in 0..nv {
        let v = flat.v(r) + m.v0;
        let input = scratch.input(nu);
        for (c, o) in input.iter_mut().enumerate() {
            let u = flat.u(c) + m.u0;
            *o = sample(r, c) * m.dsd / (m.dsd * m.dsd + u * u + v * v).sqrt();
        }
        filter.run(scratch);
        for (c, q) in scratch.output(nu).iter().enumerate() {
            panel[(c + 1) * rows + r] = (q * post) as f32;
        }
    }
}

/// Row coordinate of a line: `q(iz) = a + b·iz`, scaled to ±1 at the outer row centres.
#[derive(Clone, Copy, Default)]
struct Affine {
    a: f32,
    b: f32,
}

impl Affine {
    /// The `iz` range (within `0..nz`) where `|q| < 1`.
    fn inside(&self, nz: usize) -> (usize, usize) {
        if self.b == 0.0 {
            return if self.a.abs() < 1.0 { (0, nz) } else { (0, 0) };
        }
        let (t0, t1) = ((-1.0 - self.a) / self.b, (1.0 - self.a) / self.b);
        let (lo, hi) = (t0.min(t1), t0.max(t1));
        let lo = lo.ceil().max(0.0);
        let hi = (hi.floor() + 1.0).min(nz as f32);
        if hi <= lo {
            (0, 0)
        } else {
            (lo as usize, hi as usize)
        }
    }
}

/// `q(iz)` of point `p` seen from a source at `(s_xy, s_z)` on a panel of `map`'s distance, whose
/// normal is `normal`, and the distance `lc`.
fn row_line(
    p: [f64; 2],
    s: [f64; 3],
    normal: [f64; 2],
    m: &ViewMap,
    det: &Detector2,
    grid: &VolumeGrid,
) -> Option<(Affine, f64)> {
    let lc = (p[0] - s[0]) * normal[0] + (p[1] - s[1]) * normal[1];
    if lc <= 1e-9 * m.dsd {
        return None;
    }
    let half = (det.nv as f64 - 1.0) / 2.0;
    let k = m.dsd * m.v_sign / (lc * det.dv_mm);
    // row(z) = k·(z − s_z) − (v0 + offset_v)/dv + half; q = (row − half)/half.
    let row0 = k * (grid.z(0) - s[2]) - (m.v0 + det.offset_v_mm) / det.dv_mm;
    let q = Affine {
        a: (row0 / half) as f32,
        b: (k * grid.spacing_mm[2] / half) as f32,
    };
    Some((q, lc))
}

/// Add the views of `batch` to the line of voxels above `p` (x, y in mm).
#[allow(clippy::too_many_arguments)]
fn back_project_line(
    line: Line<'_>,
    scratch: &mut LineScratch,
    p: [f64; 2],
    batch: &Batch<'_>,
    helix: &Helix,
    det: &Detector2,
    grid: &VolumeGrid,
    span: f64,
) {
    let Line { acc, first, last } = line;
    let (nu, nv, nz) = (det.nu, det.nv, grid.nz);
    let rows = nv + 1;
    let stored = (nu + 2) * rows;
    let half = (nv as f32 - 1.0) / 2.0;
    let mut conj = [Affine::default(); MAX_CONJUGATES];
    for (b, m) in batch.maps.iter().enumerate() {
        let normal = [m.normal[0], m.normal[1]];
        let Some((q0, lc)) = row_line(p, m.source, normal, m, det, grid) else {
            continue;
        };
        let lat = (p[0] - m.source[0]) * m.e_u[0] + (p[1] - m.source[1]) * m.e_u[1];
        let col =
            (m.dsd * lat / lc - m.u0 - det.offset_u_mm) / det.du_mm + (nu as f64 - 1.0) / 2.0 + 1.0;
        if !(col >= 0.0 && col < (nu + 1) as f64) {
            continue;
        }
        let (lo, hi) = q0.inside(nz);
        if lo >= hi {
            continue;
        }
        let n = conjugates(p, m, helix, det, grid, span, (lo, hi), &mut conj);
        let post = (1.0 / (lc * lc)) as f32;
        // The weight of every voxel of the range: W(q₀)/(W(q₀) + Σ W(q_k)), times 1/lc².
        // Indices go through i32 so that these loops vectorise (the grid's axes are far below 2³¹).
        let weights = &mut scratch.weights[..hi - lo];
        weights.fill(0.0);
        for c in &conj[..n] {
            // Each conjugate only over the part of the range where it sees the line (W = 0 elsewhere).
            let (clo, chi) = c.inside(nz);
            let (clo, chi) = (clo.max(lo), chi.min(hi));
            if clo >= chi {
                continue;
            }
            for (k, w) in weights[clo - lo..chi - lo].iter_mut().enumerate() {
                *w += row_weight(c.a + c.b * (clo + k) as i32 as f32);
            }
        }
        for (k, w) in weights.iter_mut().enumerate() {
            let w0 = row_weight(q0.a + q0.b * (lo + k) as i32 as f32);
            *w = w0 * post / (w0 + *w).max(f32::MIN_POSITIVE);
        }
        // The two detector columns around the line's position, blended once.
        let ic = col.floor() as usize;
        let fu = (col - ic as f64) as f32;
        let panel = &batch.panels[b * stored..(b + 1) * stored];
        let (c0, c1) = (
            &panel[ic * rows..(ic + 1) * rows],
            &panel[(ic + 1) * rows..(ic + 2) * rows],
        );
        let column = &mut scratch.column[..rows];
        for ((o, a), b) in column.iter_mut().zip(c0).zip(c1) {
            *o = a + fu * (b - a);
        }
        for (k, w) in weights.iter().enumerate() {
            let iz = lo + k;
            let row = (q0.a + q0.b * iz as i32 as f32) * half + half;
            let i = (row.max(0.0) as usize).min(nv - 2);
            let f = (row - i as f32).clamp(0.0, 1.0);
            acc[iz] += (column[i] + f * (column[i + 1] - column[i])) * w;
        }
        let view = (batch.first + b) as u32;
        for v in &mut first[lo..hi] {
            *v = (*v).min(view);
        }
        for v in &mut last[lo..hi] {
            *v = (*v).max(view);
        }
    }
}

/// The row lines of the views that measure the lines through `p` that view `m` measures, and that
/// exist in the scan and see `p` somewhere in `range`; returns how many were written into `out`.
#[allow(clippy::too_many_arguments)]
fn conjugates(
    p: [f64; 2],
    m: &ViewMap,
    helix: &Helix,
    det: &Detector2,
    grid: &VolumeGrid,
    span: f64,
    range: (usize, usize),
    out: &mut [Affine; MAX_CONJUGATES],
) -> usize {
    let tau = std::f64::consts::TAU;
    let beta = m.angle;
    // Where the line from the nominal source through p meets the orbit again.
    let s = m.nominal;
    let d = [p[0] - s[0], p[1] - s[1]];
    let len = d[0].hypot(d[1]);
    if len <= 0.0 {
        return 0;
    }
    let d = [d[0] / len, d[1] / len];
    let t = 2.0 * (d[0] * (helix.centre[0] - s[0]) + d[1] * (helix.centre[1] - s[1]));
    let far = [s[0] + t * d[0], s[1] + t * d[1]];
    let opposite = helix.angle_of(far[0], far[1]);
    let beta1 = beta + (opposite - beta).rem_euclid(tau);
    let turns = (span / tau).ceil() as i64 + 1;
    let mut n = 0;
    // Views a whole number of turns apart share the source's (x, y): one row line per base angle, its
    // offset moved by the source's rise per turn.
    for base in [beta, beta1] {
        // The opposite source is where the line meets the orbit again.
        let sxy = if base == beta { s } else { far };
        let normal = [
            (helix.centre[0] - sxy[0]) / helix.radius,
            (helix.centre[1] - sxy[1]) / helix.radius,
        ];
        let source = [sxy[0], sxy[1], helix.z(base)];
        let Some((q, _)) = row_line(p, source, normal, m, det, grid) else {
            continue;
        };
        let per_turn = f64::from(q.b) / grid.spacing_mm[2] * helix.slope * tau;
        for m_turn in -turns..=turns {
            let candidate = base + m_turn as f64 * tau;
            if (base == beta && m_turn == 0)
                || (candidate - beta).abs() > span
                || candidate < helix.lo
                || candidate > helix.hi
            {
                continue;
            }
            let shifted = Affine {
                a: (f64::from(q.a) - per_turn * m_turn as f64) as f32,
                b: q.b,
            };
            let (lo, hi) = shifted.inside(grid.nz);
            if lo.max(range.0) < hi.min(range.1) && n < MAX_CONJUGATES {
                out[n] = shifted;
                n += 1;
            }
        }
    }
    n
}

/// The `[z][y][x]` volume from the lines, each voxel kept only where the views that saw it cover a
/// π-range of line directions (see the module docs).
fn assemble(
    sums: &[f32],
    first: &[u32],
    last: &[u32],
    maps: &[ViewMap],
    grid: &VolumeGrid,
) -> Array3<f32> {
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    let step = maps.iter().map(|m| m.step).sum::<f64>() / maps.len() as f64;
    let needed = std::f64::consts::PI - 1.5 * step;
    let mut volume = Array3::<f32>::zeros((nz, ny, nx));
    volume
        .axis_iter_mut(ndarray::Axis(1))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut plane)| {
            for x in 0..nx {
                let p = [grid.x(x), grid.y(y)];
                for iz in 0..nz {
                    let at = (y * nx + x) * nz + iz;
                    let (a, b) = (first[at], last[at]);
                    if a == u32::MAX || a >= b {
                        continue;
                    }
                    let (ma, mb) = (&maps[a as usize], &maps[b as usize]);
                    if turned(p, ma, mb) >= needed {
                        plane[[iz, x]] = sums[at];
                    }
                }
            }
        });
    volume
}

/// Bytes the helical FBP allocates: the lines, their first and last views, the volume, the filtered
/// views of a pass and a filter per thread.
pub fn estimate_bytes(views: &Views3, grid: &VolumeGrid, params: &FbpParams) -> u64 {
    let d = views.detector;
    let stored = ((d.nu + 2) as u64).saturating_mul((d.nv + 1) as u64);
    let padded = padded_len(d.nu, params.padded_len)
        .map(|p| p as u64)
        .unwrap_or(0);
    let threads = rayon::current_num_threads() as u64;
    grid.voxels()
        .saturating_mul(16)
        .saturating_add(stored.saturating_mul(4 * BATCH as u64))
        .saturating_add(threads.saturating_mul(padded.saturating_mul(8 * 4)))
}
