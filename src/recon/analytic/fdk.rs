//! FDK (Feldkamp–Davis–Kress) reconstruction of circular cone-beam projections on a flat panel, full scan,
//! Parker short scan or Wang offset (half-fan) detector.
//!
//! Virtual detector at the isocentre, coordinates (p, ζ) = (u, v)·D/DSD: pre-weight D/√(D² + p² + ζ²)
//! (times the redundancy weight of the in-plane fan angle), ramp along detector rows only (h/2, the ½ of
//! a full turn), backproject Σ Δβ D²/lc² Q(u′, v′) with lc the distance from the source along the central
//! ray. The volume is accumulated in batches of projections: filter the batch (projections in parallel),
//! backproject it (in parallel over planes of the volume), drop it.
//!
//! Two backprojection loops. Where the detector's u axis has no z component (every parametric geometry),
//! a line of voxels along z projects into one detector column position with one distance weight and row
//! positions affine in z: the views are stored by detector columns and each (x, y) line of the volume is
//! backprojected by `column::cone_columns`, all views of the batch into a plane of lines held per thread,
//! which is then added to the volume ([`COLUMN_BATCH`] views per pass). Otherwise (a detector rolled about
//! the central ray) rows along x are backprojected by `backproject::cone_row` ([`VIEWS_PER_THREAD`] views
//! per thread and pass). Memory: the volume plus the batch's filtered projections and a plane per thread.

use ndarray::{Array3, ArrayView3, Axis};
use rayon::prelude::*;

use super::backproject::{PAD, Panel, RowLine, cone_row};
use super::column::{ColumnPanel, ROW_LINES, SLACK, ZLine, cone_columns};
use super::fdk_filter::{ROW_BLOCK, Setup, put_columns};
use super::filter::padded_len;
use super::orbit::Frame;
use super::progress::Ticker;
use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Detector2, Views3};
use crate::recon::grid::VolumeGrid;

/// FDK; see the module docs.
pub fn fdk(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    fdk_with(views, proj, grid, params, ctl, None)
}

/// The voxel-driven back projection of FDK applied to the projections as they are, neither filtered
/// nor pre-weighted: every voxel's centre is projected into every view, the view is sampled
/// bilinearly there and weighted Δβ·D²/lc² (the angular step, the source distance, the distance of
/// the voxel from the source along the central ray). It is not the transpose of the Joseph forward
/// projector (which weights by the path of each ray through the voxel), but close to it up to a
/// constant factor: the back projector RTK's iterative filters use by default. Same geometries,
/// loops and speed as [`fdk`], without the filtering.
pub fn back_project_voxels(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    run(views, proj, grid, &FbpParams::default(), ctl, None, false)
}

/// [`fdk`] with the backprojection loop forced (`Some(true)`: along z, which the geometry must allow;
/// `Some(false)`: along x), for the tests that compare the two.
pub(crate) fn fdk_with(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
    along_z: Option<bool>,
) -> Result<Array3<f32>, ReconError> {
    run(views, proj, grid, params, ctl, along_z, true)
}

/// FDK (`filtered`) or its back projection alone.
fn run(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
    along_z: Option<bool>,
    filtered: bool,
) -> Result<Array3<f32>, ReconError> {
    super::check_stack(views, proj, grid, params)?;
    if views.views.is_empty() {
        return Err(ReconError::param("geometry", "no views"));
    }
    let setup = Setup::new(views, params)?;
    let det = views.detector;
    let (width, rows) = (setup.ne + 2 * PAD, det.nv + 2 * PAD);
    let columns = along_z.unwrap_or_else(|| lines_along_z(&setup.frames, grid, &det));
    let panel_len = if columns {
        width * rows + SLACK
    } else {
        width * rows
    };
    let batch = batch_views(columns, panel_len);
    // Along x the views are added to the volume itself; along z to blocks of lines (see `Lines`).
    let mut volume = if columns {
        Array3::<f32>::zeros((0, 0, 0))
    } else {
        Array3::<f32>::zeros(grid.shape())
    };
    let mut lines = if columns {
        Lines::new(grid)
    } else {
        Lines::default()
    };
    let mut panels = vec![0.0f32; batch * panel_len];
    let ticker = Ticker::new(ctl, "fdk", views.views.len());
    let sampling = det_map(&det, setup.lo);
    for first in (0..views.views.len()).step_by(batch) {
        let last = (first + batch).min(views.views.len());
        panels[..(last - first) * panel_len]
            .par_chunks_mut(panel_len)
            .enumerate()
            .try_for_each_init(
                || (setup.filter.scratch(), vec![0.0f32; ROW_BLOCK * setup.ne]),
                |(scratch, block), (b, panel)| {
                    ctl.check()?;
                    let ne = setup.ne;
                    let put = |r: usize, values: &[f32]| {
                        if columns {
                            // Rows arrive in order: a block is written once full or at the last row.
                            let i = r % ROW_BLOCK;
                            block[i * ne..(i + 1) * ne].copy_from_slice(values);
                            if i + 1 == ROW_BLOCK || r + 1 == det.nv {
                                put_columns(panel, rows, r - i, &block[..(i + 1) * ne], ne);
                            }
                        } else {
                            let start = (r + PAD) * width + PAD;
                            panel[start..start + values.len()].copy_from_slice(values);
                        }
                    };
                    if filtered {
                        setup.filter_view(proj, first + b, scratch, put);
                    } else {
                        setup.raw_view(proj, first + b, put);
                    }
                    Ok::<(), ReconError>(())
                },
            )?;
        ctl.check()?;
        let batch_frames = &setup.frames[first..last];
        let maps: Vec<[f32; 4]> = batch_frames
            .iter()
            .map(|f| panel_map(f, &sampling))
            .collect();
        let panels = &panels[..(last - first) * panel_len];
        if columns {
            let stored: Vec<ColumnPanel<'_>> = panels
                .chunks_exact(panel_len)
                .map(|q| ColumnPanel {
                    q,
                    cols: width,
                    rows,
                })
                .collect();
            backproject_columns(&mut lines, grid, batch_frames, &maps, &stored, ctl)?;
        } else {
            let stored = Panel {
                q: panels,
                width,
                rows,
            };
            backproject_rows(&mut volume, grid, batch_frames, &maps, stored, ctl)?;
        }
        ticker.add(last - first);
    }
    if columns {
        volume = lines.into_volume(grid);
    }
    Ok(volume)
}

/// Whether every line of voxels along z projects into one detector column position: the detector's
/// u axis has no z component, up to 10⁻⁴ of a detector column over the volume's height.
fn lines_along_z(frames: &[Frame], grid: &VolumeGrid, det: &Detector2) -> bool {
    let (z0, z1) = (grid.z(0), grid.z(grid.nz.saturating_sub(1)));
    frames.iter().all(|f| {
        let reach = (z0 - f.source[2]).abs().max((z1 - f.source[2]).abs());
        // The central ray is horizontal by construction (`orbit::frames`): only the panel can tilt lines.
        f.e_u[2].abs() * reach <= 1e-4 * det.du_mm
    })
}

/// Filtered projections held per worker thread by the backprojection along x: each pass over the
/// volume adds this many views per thread.
pub const VIEWS_PER_THREAD: usize = 4;

/// Filtered projections per pass of the backprojection along z, where every thread reads every view
/// of the batch: a pass zeroes a plane of lines per thread and adds it to the volume, so more views per
/// pass spread that cost thinner. Held to [`COLUMN_BATCH_BYTES`] of filtered projections.
pub const COLUMN_BATCH: usize = 32;

/// Memory the filtered projections of one pass along z may take.
pub const COLUMN_BATCH_BYTES: usize = 256 << 20;

/// Views per pass for a loop and a stored projection of `panel_len` values.
fn batch_views(columns: bool, panel_len: usize) -> usize {
    let per_threads = rayon::current_num_threads().max(1) * VIEWS_PER_THREAD;
    if columns {
        let fit = COLUMN_BATCH_BYTES / (4 * panel_len).max(1);
        fit.min(COLUMN_BATCH).max(per_threads)
    } else {
        per_threads
    }
}

/// Side of the square tiles of lines along z that a thread backprojects together (a row of a tile is
/// set up at once, [`ROW_LINES`] lines): the tile's lines read only a narrow band of detector columns
/// of every view of the batch, which stays in the core's cache while the tile's lines are summed (a
/// whole plane of lines would stream every view through it).
const TILE: usize = ROW_LINES;

/// The volume while it is backprojected along z: blocks of [`TILE`] planes y (the last may be thinner),
/// each holding its lines along z contiguous, `[y][x][z]`. Turned into the `[z][y][x]` volume once at
/// the end, block by block, each block freed once copied.
#[derive(Default)]
struct Lines {
    blocks: Vec<Vec<f32>>,
}

impl Lines {
    /// Blocks of zeros written, not only allocated: a zeroed allocation maps the shared zero page,
    /// which the window loop's first read of a sum keeps and its first store then copies, a second
    /// page fault that also flushes every other thread's TLB (4 % of the CPU time on two threads).
    /// Each block is written by one of the threads that will sum into it.
    fn new(grid: &VolumeGrid) -> Self {
        let plane = grid.nx * grid.nz;
        let starts: Vec<usize> = (0..grid.ny).step_by(TILE).collect();
        let blocks = starts
            .into_par_iter()
            .map(|y0| {
                let len = TILE.min(grid.ny - y0) * plane;
                let mut block = Vec::with_capacity(len);
                block.resize(len, 0.0f32);
                block
            })
            .collect();
        Lines { blocks }
    }

    fn into_volume(self, grid: &VolumeGrid) -> Array3<f32> {
        let (nx, nz) = (grid.nx, grid.nz);
        let mut volume = Array3::<f32>::zeros(grid.shape());
        volume
            .axis_chunks_iter_mut(Axis(1), TILE)
            .into_par_iter()
            .zip(self.blocks.into_par_iter())
            .for_each(|(mut planes, block)| {
                let ys = planes.len_of(Axis(1));
                if let Ok(block) = ArrayView3::from_shape((ys, nx, nz), &block[..]) {
                    planes.assign(&block.permuted_axes([2, 0, 1]));
                }
            });
        volume
    }
}

/// Add the batch, stored by columns, to the lines: blocks of [`TILE`] planes y in parallel, within a
/// block tile by tile (`TILE × TILE` lines) and within a tile view by view, so that each view's band
/// of detector columns is read from the cache by every line of the tile.
fn backproject_columns(
    lines: &mut Lines,
    grid: &VolumeGrid,
    frames: &[Frame],
    maps: &[[f32; 4]],
    panels: &[ColumnPanel<'_>],
    ctl: Control<'_>,
) -> Result<(), ReconError> {
    let (nx, nz) = (grid.nx, grid.nz);
    let dz = grid.spacing_mm[2];
    lines
        .blocks
        .par_iter_mut()
        .enumerate()
        .try_for_each(|(block, acc)| {
            // A block of a pass takes tens of milliseconds: a cancel is seen well within a second.
            ctl.check()?;
            let ys = acc.len() / (nx * nz).max(1);
            // Per plane y of the block and view: the line of the volume's first row along x.
            let rows: Vec<(RowLine, f32)> = (0..ys)
                .flat_map(|j| {
                    frames.iter().map(move |f| {
                        let y = block * TILE + j;
                        (volume_row(f, grid, y, 0), (dz * f.e_v[2]) as f32)
                    })
                })
                .collect();
            let mut set = Vec::with_capacity(TILE * TILE);
            for x0 in (0..nx).step_by(TILE) {
                let xs = TILE.min(nx - x0);
                for (b, (map, panel)) in maps.iter().zip(panels).enumerate() {
                    // The tile's lines are set up first, so that their divisions overlap.
                    set.clear();
                    for j in 0..ys {
                        let (line, dlatv) = &rows[j * frames.len() + b];
                        let sizes = (panel.cols, panel.rows);
                        ZLine::row(line, (x0, xs), *dlatv, *map, sizes, nz, |i, z, span| {
                            set.push(((j * nx + x0 + i) * nz, z, span));
                        });
                    }
                    cone_columns(acc, *panel, &set);
                }
            }
            Ok(())
        })
}

/// Add the batch, stored by rows (`stored` holds the batch's views one after the other), to the volume:
/// slices z in parallel, each row along x against every view of the batch.
fn backproject_rows(
    volume: &mut Array3<f32>,
    grid: &VolumeGrid,
    frames: &[Frame],
    maps: &[[f32; 4]],
    stored: Panel<'_>,
    ctl: Control<'_>,
) -> Result<(), ReconError> {
    let Panel {
        q: panels,
        width,
        rows,
    } = stored;
    volume
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .try_for_each(|(z, mut slice)| {
            ctl.check()?;
            let mut acc = vec![0.0f32; grid.nx];
            for y in 0..grid.ny {
                acc.fill(0.0);
                for (b, (f, map)) in frames.iter().zip(maps).enumerate() {
                    let panel = Panel {
                        q: &panels[b * width * rows..(b + 1) * width * rows],
                        width,
                        rows,
                    };
                    cone_row(&mut acc, panel, &volume_row(f, grid, y, z), *map);
                }
                for (o, a) in slice.row_mut(y).iter_mut().zip(&acc) {
                    *o += *a;
                }
            }
            Ok(())
        })
}

/// Detector sampling (du, dv, offset_u, offset_v, base_u, base_v): stored column =
/// (u − offset_u)/du + (nu − 1)/2 + PAD + lo, with `lo` zero columns added on the left.
fn det_map(det: &Detector2, lo: usize) -> [f64; 6] {
    [
        det.du_mm,
        det.dv_mm,
        det.offset_u_mm,
        det.offset_v_mm,
        (det.nu as f64 - 1.0) / 2.0 + (PAD + lo) as f64,
        (det.nv as f64 - 1.0) / 2.0 + PAD as f64,
    ]
}

/// [au, bu, av, bv] with stored column = au·lat/lc + bu and stored row = av·latv/lc + bv.
fn panel_map(f: &Frame, m: &[f64; 6]) -> [f32; 4] {
    let [du, dv, ou, ov, cu, cv] = *m;
    [
        (f.dsd / du) as f32,
        (cu - (f.u0 + ou) / du) as f32,
        (f.dsd / dv) as f32,
        (cv - (f.v0 + ov) / dv) as f32,
    ]
}

fn volume_row(f: &Frame, grid: &VolumeGrid, y: usize, z: usize) -> RowLine {
    let [lc0, lat0, latv0] = f.local([grid.x(0), grid.y(y), grid.z(z)]);
    let dx = grid.spacing_mm[0];
    RowLine {
        lc0: lc0 as f32,
        dlc: (dx * f.dir[0]) as f32,
        lat0: lat0 as f32,
        dlat: (dx * f.e_u[0]) as f32,
        latv0: latv0 as f32,
        dlatv: (dx * f.e_v[0]) as f32,
    }
}

/// Bytes FDK allocates: the volume, the filtered projections of one pass, a plane of lines (or a row)
/// and filter buffers per thread.
pub fn estimate_bytes(views: &Views3, grid: &VolumeGrid, params: &FbpParams) -> u64 {
    let d = views.detector;
    // Offset panels are extended up to twice their width before filtering.
    let panel = (2 * d.nu + 2 * PAD)
        .saturating_mul(d.nv + 2 * PAD)
        .saturating_add(SLACK);
    let threads = rayon::current_num_threads() as u64;
    // At least the batch of the loop along x (`batch_views` never returns less).
    let batch = batch_views(true, panel) as u64;
    let padded = padded_len(d.nu, params.padded_len)
        .map(|p| p as u64)
        .unwrap_or(0);
    let per_thread = padded
        .saturating_mul(8 * 4)
        .saturating_add((d.nu as u64 * 2).saturating_mul(4))
        .saturating_add(
            (grid.nx as u64)
                .saturating_mul(grid.nz as u64)
                .saturating_mul(4),
        );
    grid.voxels()
        .saturating_mul(4)
        .saturating_add((panel as u64).saturating_mul(4).saturating_mul(batch))
        .saturating_add(threads.saturating_mul(per_thread))
}

#[cfg(test)]
#[path = "fdk_tests.rs"]
mod tests;
