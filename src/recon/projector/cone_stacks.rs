//! The padded plane stacks of the column-ordered cone-beam pair ([`super::cone_columns`]): the volume
//! copied with the planes of one dominant axis slowest and z fastest, one zero value before and two
//! after every z line and every plane's list of lines, so that a column's two z lines are contiguous
//! and a sample half outside the grid reads zeros (forward) or writes values that are dropped (back).

use rayon::prelude::*;

use crate::recon::geometry::Views3;
use crate::recon::grid::VolumeGrid;

/// A dominant axis of a column's walks: planes along `x` (lines indexed by y) or along `y`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    X,
    Y,
}

/// Bytes a forward or back projection of `views` on `grid` allocates besides its input and output:
/// the two padded plane stacks and (back) the weighted copy of the data.
pub fn work_bytes(views: &Views3, grid: &VolumeGrid) -> u64 {
    let (nx, ny, nz) = (grid.nx as u64, grid.ny as u64, grid.nz as u64 + 3);
    let stacks = nx
        .saturating_mul(ny + 3)
        .saturating_add(ny.saturating_mul(nx + 3))
        .saturating_mul(nz);
    let data = (views.views.len() as u64)
        .saturating_mul(views.detector.nu as u64)
        .saturating_mul(views.detector.nv as u64);
    stacks.saturating_add(data).saturating_mul(4)
}

/// Planes (or z slabs) copied together between a stack and the volume.
const BLOCK: usize = 16;

/// Padded plane stack of one axis: `planes` planes of `lines + 3` lines of `nz + 3` values.
pub struct Stack {
    pub lines: usize,
    pub len: usize,
    pub values: Vec<f32>,
}

impl Stack {
    pub fn zeros(planes: usize, lines: usize, nz: usize) -> Self {
        let len = nz + 3;
        Self {
            lines,
            len,
            values: vec![0.0; planes * (lines + 3) * len],
        }
    }
    pub fn plane_len(&self) -> usize {
        (self.lines + 3) * self.len
    }
    /// Copy of `volume` (`[z][y][x]`) with planes along `axis`.
    pub fn of(volume: &[f32], grid: &VolumeGrid, axis: Axis) -> Self {
        let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
        let (planes, lines) = match axis {
            Axis::X => (nx, ny),
            Axis::Y => (ny, nx),
        };
        let mut s = Self::zeros(planes, lines, nz);
        let (pl, len) = (s.plane_len(), s.len);
        // Blocks of BLOCK planes, line by line along z: the volume's values of a block's planes
        // lie side by side (x planes) or in a few lines that the next stack lines read again (y
        // planes), so each cache line of the volume is read about once.
        s.values
            .par_chunks_mut(pl * BLOCK)
            .enumerate()
            .for_each(|(b, block)| {
                let k0 = b * BLOCK;
                let count = block.len() / pl;
                for l in 0..lines {
                    for z in 0..nz {
                        let at = (l + 1) * len + z + 1;
                        for (dk, plane) in block.chunks_exact_mut(pl).take(count).enumerate() {
                            let (x, y) = match axis {
                                Axis::X => (k0 + dk, l),
                                Axis::Y => (l, k0 + dk),
                            };
                            plane[at] = volume[(z * ny + y) * nx + x];
                        }
                    }
                }
            });
        s
    }
    /// `volume` (`[z][y][x]`) += the unpadded values of `self`, in blocks of [`BLOCK`] slabs of z:
    /// each stack line's values for a block are contiguous, and the block's slabs are written
    /// along x together.
    pub fn add_into(&self, volume: &mut [f32], grid: &VolumeGrid, axis: Axis) {
        let (nx, ny) = (grid.nx, grid.ny);
        let slab = nx * ny;
        let (pl, len) = (self.plane_len(), self.len);
        volume
            .par_chunks_mut(slab * BLOCK)
            .enumerate()
            .for_each(|(b, slabs)| {
                let z0 = b * BLOCK;
                let count = slabs.len() / slab;
                for y in 0..ny {
                    for x in 0..nx {
                        let (k, l) = match axis {
                            Axis::X => (x, y),
                            Axis::Y => (y, x),
                        };
                        let start = k * pl + (l + 1) * len + z0 + 1;
                        for (dz, v) in self.values[start..start + count].iter().enumerate() {
                            slabs[dz * slab + y * nx + x] += v;
                        }
                    }
                }
            });
    }
}
