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
        s.values
            .par_chunks_mut(pl)
            .enumerate()
            .for_each(|(k, plane)| {
                for z in 0..nz {
                    for l in 0..lines {
                        let (x, y) = match axis {
                            Axis::X => (k, l),
                            Axis::Y => (l, k),
                        };
                        plane[(l + 1) * len + z + 1] = volume[(z * ny + y) * nx + x];
                    }
                }
            });
        s
    }
    /// `volume` (`[z][y][x]`) += the unpadded values of `self`.
    pub fn add_into(&self, volume: &mut [f32], grid: &VolumeGrid, axis: Axis) {
        let (nx, ny) = (grid.nx, grid.ny);
        let (pl, len) = (self.plane_len(), self.len);
        volume
            .par_chunks_mut(nx * ny)
            .enumerate()
            .for_each(|(z, slab)| {
                for y in 0..ny {
                    for x in 0..nx {
                        let (k, l) = match axis {
                            Axis::X => (x, y),
                            Axis::Y => (y, x),
                        };
                        slab[y * nx + x] += self.values[k * pl + (l + 1) * len + z + 1];
                    }
                }
            });
    }
}
