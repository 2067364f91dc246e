//! Cell occupancy: one bit per voxel cell (the 2 × 2 × 2 voxels a trilinear lookup reads) saying whether the
//! range of its eight corners meets one of a set of value windows — the transfer function's visible window for
//! volume rendering, the iso-values for surfaces. A trilinear sample lies within the range of its cell's
//! corners, so a sample in a cell whose bit is clear has a value outside every window: volume rendering skips
//! it without reading the eight voxels, and a surface search knows on which side of every iso-value it lies
//! from one corner.
//!
//! A second, coarser level holds one bit per block of 2 × 2 × 2 cells (the OR of its eight cell bits): a ray in
//! a clear block crosses the rest of the block in one jump ([`Occupancy::block_exit`]) instead of sample by
//! sample. The block bits (an eighth of the cell bits) stay in cache where the cell bits do not.
//!
//! The bits are built once per window set (only inside bricks whose min/max range meets a window: the other
//! cells stay clear) and kept by the [`Scene`](super::Scene), so every frame of a rotating sequence shares them.

use rayon::prelude::*;

use super::bricks::RayDir;
use super::{BRICK, BrickGrid, Sampler};

/// Side of a block of cells (cells).
const BLOCK: usize = 2;

/// Occupied cells of a volume for one set of value windows.
pub(crate) struct Occupancy {
    /// Cells along `[z, y, x]`: one fewer than the voxels.
    nc: [usize; 3],
    /// 64-bit words per row of cells.
    wpr: usize,
    /// Bit `i % 64` of word `(k·nc_y + j)·wpr + i / 64`: cell `[k, j, i]`.
    bits: Vec<u64>,
    /// Blocks of [`BLOCK`]³ cells along `[z, y, x]`.
    nbk: [usize; 3],
    /// 64-bit words per row of blocks.
    bwpr: usize,
    /// Bit `i % 64` of word `(k·nbk_y + j)·bwpr + i / 64`: whether a cell of block `[k, j, i]` is occupied.
    blocks: Vec<u64>,
}

/// Closed value intervals `[lo, hi]`; a cell is occupied when the range of its corners meets one of them.
pub(crate) type Windows = Vec<(f32, f32)>;

fn meets(windows: &[(f32, f32)], lo: f32, hi: f32) -> bool {
    windows.iter().any(|&(a, b)| hi >= a && lo <= b)
}

impl Occupancy {
    /// The occupancy of `s` for `windows`; `bricks` is the volume's min/max grid (cells of bricks whose range
    /// meets no window are left clear without reading their voxels). Parallel over planes of cells.
    pub(crate) fn new(s: &Sampler<'_>, bricks: &BrickGrid, windows: &[(f32, f32)]) -> Self {
        let [nz, ny, nx] = s.n;
        let nc = [nz - 1, ny - 1, nx - 1];
        let wpr = nc[2].div_ceil(64);
        let nb = bricks.nb;
        let brick_on: Vec<bool> = bricks
            .range
            .iter()
            .map(|&(lo, hi)| meets(windows, lo, hi))
            .collect();
        let mut bits = vec![0u64; nc[0] * nc[1] * wpr];
        let data = s.data();
        bits.par_chunks_mut(nc[1] * wpr)
            .enumerate()
            .for_each(|(k, plane)| {
                let bz = k / BRICK;
                let (mut lo, mut hi) = (vec![0.0f32; nx], vec![0.0f32; nx]);
                let row = |kk: usize, jj: usize| &data[(kk * ny + jj) * nx..][..nx];
                for j in 0..nc[1] {
                    let by = j / BRICK;
                    let (r0, r1, r2, r3) =
                        (row(k, j), row(k, j + 1), row(k + 1, j), row(k + 1, j + 1));
                    let out = &mut plane[j * wpr..(j + 1) * wpr];
                    for bx in 0..nb[2] {
                        if !brick_on[(bz * nb[1] + by) * nb[2] + bx] {
                            continue;
                        }
                        let (i0, i1) = (bx * BRICK, ((bx + 1) * BRICK).min(nc[2]));
                        // The range of each column of four voxels, then of each pair of columns.
                        for i in i0..=i1 {
                            let (a, b, c, d) = (r0[i], r1[i], r2[i], r3[i]);
                            lo[i] = a.min(b).min(c.min(d));
                            hi[i] = a.max(b).max(c.max(d));
                        }
                        for i in i0..i1 {
                            if meets(windows, lo[i].min(lo[i + 1]), hi[i].max(hi[i + 1])) {
                                out[i / 64] |= 1 << (i % 64);
                            }
                        }
                    }
                }
            });
        let (nbk, bwpr, blocks) = blocks_of(nc, wpr, &bits);
        Self {
            nc,
            wpr,
            bits,
            nbk,
            bwpr,
            blocks,
        }
    }

    /// Whether cell `c` (its first corner `[k, j, i]`, as [`Sampler::cell`] gives it) is occupied.
    #[inline(always)]
    pub(crate) fn busy(&self, c: [usize; 3]) -> bool {
        let w = self.bits[(c[0] * self.nc[1] + c[1]) * self.wpr + c[2] / 64];
        (w >> (c[2] % 64)) & 1 != 0
    }

    /// Whether the block holding cell `c` has an occupied cell.
    #[inline(always)]
    pub(crate) fn block_busy(&self, c: [usize; 3]) -> bool {
        let b = c.map(|x| x / BLOCK);
        let w = self.blocks[(b[0] * self.nbk[1] + b[1]) * self.bwpr + b[2] / 64];
        (w >> (b[2] % 64)) & 1 != 0
    }

    /// The ray parameter (mm, from `idx`) where a ray at fractional index `idx` in cell `c` leaves the block of
    /// that cell: samples before it read only the block's cells.
    #[inline(always)]
    pub(crate) fn block_exit(&self, idx: [f32; 3], c: [usize; 3], dir: &RayDir) -> f64 {
        dir.exit(idx, c.map(|x| (x / BLOCK * BLOCK) as f64), BLOCK as f64)
    }

    /// Number of occupied cells and of all cells.
    pub(crate) fn count(&self) -> (usize, usize) {
        let busy = self.bits.iter().map(|w| w.count_ones() as usize).sum();
        (busy, self.nc[0] * self.nc[1] * self.nc[2])
    }
}

/// The block bits of cell bits `bits` (`nc` cells, `wpr` words a row): block `[k, j, i]` is set when one of the
/// cells `[BLOCK·k + dk, BLOCK·j + dj, BLOCK·i + di]` (within the grid) is. Parallel over planes of blocks.
fn blocks_of(nc: [usize; 3], wpr: usize, bits: &[u64]) -> ([usize; 3], usize, Vec<u64>) {
    let nbk = nc.map(|n| n.div_ceil(BLOCK));
    let bwpr = nbk[2].div_ceil(64);
    let mut blocks = vec![0u64; nbk[0] * nbk[1] * bwpr];
    blocks
        .par_chunks_mut(nbk[1] * bwpr)
        .enumerate()
        .for_each(|(bk, plane)| {
            let mut row = vec![0u64; wpr];
            for bj in 0..nbk[1] {
                // The OR of the block's cell rows, then of each pair of bits along x.
                row.fill(0);
                for k in bk * BLOCK..((bk + 1) * BLOCK).min(nc[0]) {
                    for j in bj * BLOCK..((bj + 1) * BLOCK).min(nc[1]) {
                        let r = &bits[(k * nc[1] + j) * wpr..][..wpr];
                        row.iter_mut().zip(r).for_each(|(o, &w)| *o |= w);
                    }
                }
                let out = &mut plane[bj * bwpr..(bj + 1) * bwpr];
                for (wi, &w) in row.iter().enumerate() {
                    let mut pairs = w | (w >> 1);
                    // Even bits of `pairs` are the 32 blocks of this word, in order.
                    let mut packed = 0u64;
                    for b in 0..32 {
                        packed |= (pairs & 1) << b;
                        pairs >>= 2;
                    }
                    let first = wi * 32;
                    out[first / 64] |= packed << (first % 64);
                }
            }
        });
    (nbk, bwpr, blocks)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{Frame, Volume};
    use ndarray::Array3;

    #[test]
    fn a_cell_is_occupied_exactly_when_its_corners_range_meets_a_window() {
        // Values that cross the windows often, over a grid that is not a multiple of the brick or the word.
        let (nz, ny, nx) = (19, 23, 71);
        let vol = Volume {
            data: Array3::from_shape_fn((nz, ny, nx), |(k, j, i)| {
                ((k * 7919 + j * 104_729 + i * 1_299_709) % 1000) as f32 - 500.0
            }),
            frame: Frame {
                spacing_mm: [1.0, 1.0, 1.0],
                origin_mm: [0.0; 3],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let s = Sampler::new(&vol).unwrap();
        let bricks = BrickGrid::new(&s);
        for windows in [
            vec![(440.0, f32::INFINITY)],
            vec![(f32::NEG_INFINITY, -440.0)],
            vec![(495.0, f32::INFINITY)],
            vec![(-470.0, -470.0), (455.0, 455.0)],
            vec![],
        ] {
            let occ = Occupancy::new(&s, &bricks, &windows);
            let mut busy = 0;
            for k in 0..nz - 1 {
                for j in 0..ny - 1 {
                    for i in 0..nx - 1 {
                        let corners = [0, 1]
                            .into_iter()
                            .flat_map(|a| {
                                [0, 1]
                                    .into_iter()
                                    .flat_map(move |b| [0, 1].map(|c| (a, b, c)))
                            })
                            .map(|(a, b, c)| vol.data[[k + a, j + b, i + c]]);
                        let (lo, hi) = corners
                            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), v| {
                                (l.min(v), h.max(v))
                            });
                        let want = windows.iter().any(|&(a, b)| hi >= a && lo <= b);
                        assert_eq!(occ.busy([k, j, i]), want, "{windows:?} at [{k}, {j}, {i}]");
                        busy += usize::from(want);
                    }
                }
            }
            assert_eq!(occ.count(), (busy, (nz - 1) * (ny - 1) * (nx - 1)));
            // A block is busy exactly when one of its cells is.
            let mut clear_blocks = 0;
            for k in 0..nz - 1 {
                for j in 0..ny - 1 {
                    for i in 0..nx - 1 {
                        let first = [k, j, i].map(|x| x / BLOCK * BLOCK);
                        let mut any = false;
                        for dk in 0..BLOCK {
                            for dj in 0..BLOCK {
                                for di in 0..BLOCK {
                                    let c = [first[0] + dk, first[1] + dj, first[2] + di];
                                    if c[0] < nz - 1 && c[1] < ny - 1 && c[2] < nx - 1 {
                                        any |= occ.busy(c);
                                    }
                                }
                            }
                        }
                        assert_eq!(
                            occ.block_busy([k, j, i]),
                            any,
                            "{windows:?} block of [{k}, {j}, {i}]"
                        );
                        clear_blocks += usize::from(!any);
                    }
                }
            }
            if !windows.is_empty() {
                assert!(clear_blocks > 0, "{windows:?}: no clear block to test");
                assert!(
                    busy > 0 && busy < (nz - 1) * (ny - 1) * (nx - 1),
                    "{windows:?}: {busy}"
                );
            }
        }
    }

    #[test]
    fn a_ray_leaves_a_block_where_its_line_crosses_the_block_faces() {
        use crate::render::bricks::RayDir;
        // Cell [3, 5, 6] lies in the block of cells [2..4, 4..6, 6..8]: index cube [2, 4] × [4, 6] × [6, 8].
        for (idx, dir, want) in [
            ([3.5f32, 5.0, 6.5], [0.0, 0.0, 2.0], 0.75), // +x: to i = 8
            ([3.5, 5.0, 6.5], [0.0, -0.5, 0.0], 2.0),    // −y: to j = 4
            ([3.5, 5.0, 6.5], [1.0, 1.0, 0.0], 0.5),     // +z first (k = 4), before j = 6
            ([2.0, 4.0, 6.0], [-1.0, 0.0, 0.0], 0.0),    // on the face, leaving: no step
        ] {
            let occ_dir = RayDir::new(dir);
            let cell = idx.map(|x| x as usize);
            let lo = cell.map(|x| (x / BLOCK * BLOCK) as f64);
            let got = occ_dir.exit(idx, lo, BLOCK as f64);
            assert!(
                (got - want).abs() < 1e-12,
                "{idx:?} along {dir:?}: {got} vs {want}"
            );
        }
    }
}
