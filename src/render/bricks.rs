//! Empty-space skipping: the minimum and maximum of the volume over bricks of [`BRICK`]³ voxels, and the mask of
//! the bricks a ray must sample for a given transfer function or set of iso-values.

use rayon::prelude::*;

use super::{Sampler, V3};

/// Side of a brick (voxels).
pub const BRICK: usize = 8;

/// Per-brick `(min, max)` of the samples a trilinear lookup inside the brick can touch (the brick's voxels
/// and the next layer on each axis).
pub struct BrickGrid {
    /// Bricks along `[z, y, x]`.
    pub nb: [usize; 3],
    pub range: Vec<(f32, f32)>,
}

/// Which bricks hold something to see, and how far each empty brick is from the nearest busy one.
pub(crate) struct BrickMask {
    nb: [usize; 3],
    /// Chessboard distance (bricks) to the nearest busy brick: 0 for a busy brick, at most [`FAR`].
    dist: Vec<u8>,
}

/// The distance given to a brick with no busy brick within 255 bricks.
const FAR: u8 = u8::MAX;

impl BrickGrid {
    /// Build the grid of a volume (in parallel over brick slabs).
    pub fn new(s: &Sampler<'_>) -> Self {
        let [nz, ny, nx] = s.n;
        let nb = [nz, ny, nx].map(|n| (n - 1).div_ceil(BRICK).max(1));
        let data = s.data();
        let range: Vec<(f32, f32)> = (0..nb[0])
            .into_par_iter()
            .flat_map_iter(|bz| {
                let mut out = Vec::with_capacity(nb[1] * nb[2]);
                for by in 0..nb[1] {
                    for bx in 0..nb[2] {
                        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                        for k in bz * BRICK..((bz + 1) * BRICK + 1).min(nz) {
                            for j in by * BRICK..((by + 1) * BRICK + 1).min(ny) {
                                let row = (k * ny + j) * nx;
                                let end = ((bx + 1) * BRICK + 1).min(nx);
                                for &v in &data[row + bx * BRICK..row + end] {
                                    lo = lo.min(v);
                                    hi = hi.max(v);
                                }
                            }
                        }
                        out.push((lo, hi));
                    }
                }
                out
            })
            .collect();
        Self { nb, range }
    }

    /// The mask of bricks for which `busy(min, max)` holds.
    pub(crate) fn mask(&self, busy: impl Fn(f32, f32) -> bool + Sync) -> BrickMask {
        let busy: Vec<bool> = self
            .range
            .par_iter()
            .map(|&(lo, hi)| busy(lo, hi))
            .collect();
        BrickMask {
            nb: self.nb,
            dist: chessboard_distance(self.nb, &busy),
        }
    }
}

/// The chessboard (L∞) distance, in bricks, from every brick to the nearest busy one (exact: two raster passes
/// over the 26-neighbourhood with unit steps), saturated at [`FAR`].
fn chessboard_distance(nb: [usize; 3], busy: &[bool]) -> Vec<u8> {
    let [nz, ny, nx] = nb;
    let at = |z: usize, y: usize, x: usize| (z * ny + y) * nx + x;
    let mut d: Vec<u8> = busy.iter().map(|&b| if b { 0 } else { FAR }).collect();
    let mut pass = |forward: bool| {
        for zz in 0..nz {
            let z = if forward { zz } else { nz - 1 - zz };
            for yy in 0..ny {
                let y = if forward { yy } else { ny - 1 - yy };
                for xx in 0..nx {
                    let x = if forward { xx } else { nx - 1 - xx };
                    let mut m = d[at(z, y, x)];
                    if m == 0 {
                        continue;
                    }
                    // The 13 neighbours already visited in this pass's raster order.
                    for (dz, dy, dx) in HALF_NEIGHBOURS {
                        let (dz, dy, dx) = if forward {
                            (-dz, -dy, -dx)
                        } else {
                            (dz, dy, dx)
                        };
                        let (Some(z2), Some(y2), Some(x2)) = (
                            z.checked_add_signed(dz).filter(|&v| v < nz),
                            y.checked_add_signed(dy).filter(|&v| v < ny),
                            x.checked_add_signed(dx).filter(|&v| v < nx),
                        ) else {
                            continue;
                        };
                        m = m.min(d[at(z2, y2, x2)].saturating_add(1));
                    }
                    d[at(z, y, x)] = m;
                }
            }
        }
    };
    pass(true);
    pass(false);
    d
}

/// The 13 neighbour offsets `(dz, dy, dx)` that come after a cell in raster order.
const HALF_NEIGHBOURS: [(isize, isize, isize); 13] = [
    (0, 0, 1),
    (0, 1, -1),
    (0, 1, 0),
    (0, 1, 1),
    (1, -1, -1),
    (1, -1, 0),
    (1, -1, 1),
    (1, 0, -1),
    (1, 0, 0),
    (1, 0, 1),
    (1, 1, -1),
    (1, 1, 0),
    (1, 1, 1),
];

impl BrickMask {
    /// The brick holding fractional index `idx` (clamped to the grid), per axis.
    #[inline(always)]
    fn brick(&self, idx: [f32; 3]) -> [usize; 3] {
        // Through u32: a cheaper conversion than to usize, and a grid has fewer than 2³² voxels a side.
        std::array::from_fn(|a| (idx[a].max(0.0) as u32 as usize / BRICK).min(self.nb[a] - 1))
    }

    /// Where a ray at fractional index `idx`, moving along `dir`, stands: whether the brick holding `idx` is
    /// busy (outside the grid: not busy), and the ray parameter (mm, measured from `idx`) where it leaves the
    /// block of empty bricks about that brick (the bricks closer to it than its distance to the nearest busy
    /// brick; just that brick when it is busy). One lookup for both.
    #[inline(always)]
    pub(crate) fn step(&self, idx: [f32; 3], dir: &RayDir) -> (bool, f64) {
        let b = self.brick(idx);
        let d = self.dist[(b[0] * self.nb[1] + b[1]) * self.nb[2] + b[2]];
        let busy = d == 0 && idx.iter().all(|&x| x >= 0.0);
        let reach = d.saturating_sub(1) as usize;
        let lo = b.map(|b| (b as f64 - reach as f64) * BRICK as f64);
        let t = dir.exit(idx, lo, ((2 * reach + 1) * BRICK) as f64);
        (busy, t)
    }
}

/// A ray's direction in index units per millimetre, with its reciprocal per axis: where the ray leaves a brick
/// ([`BrickMask::step`]) or a block of cells (`Occupancy::block_exit`).
pub(crate) struct RayDir {
    /// `+1`, `-1`, or `0` for an axis the ray (nearly) does not move along.
    sign: [i8; 3],
    /// `1 / dir` where the ray moves along the axis.
    inv: [f64; 3],
}

impl RayDir {
    pub(crate) fn new(dir: V3) -> Self {
        let sign = dir.map(|x| {
            if x > 1e-12 {
                1
            } else if x < -1e-12 {
                -1
            } else {
                0
            }
        });
        let inv = std::array::from_fn(|a| if sign[a] == 0 { 0.0 } else { 1.0 / dir[a] });
        Self { sign, inv }
    }

    /// The ray parameter (mm, from fractional index `idx` inside the cube) where the ray leaves the cube of
    /// index side `size` whose lowest corner is `lo`; never negative.
    #[inline(always)]
    pub(crate) fn exit(&self, idx: [f32; 3], lo: [f64; 3], size: f64) -> f64 {
        let mut t = f64::INFINITY;
        for a in 0..3 {
            let x = idx[a] as f64;
            let ta = if self.sign[a] > 0 {
                (lo[a] + size - x) * self.inv[a]
            } else if self.sign[a] < 0 {
                (lo[a] - x) * self.inv[a]
            } else {
                continue;
            };
            // Plain comparisons: no operand is NaN (finite index, finite reciprocal).
            if ta < t {
                t = ta;
            }
        }
        if t > 0.0 { t } else { 0.0 }
    }
}

/// Samples `t0 + k·step` along a ray span, and the reciprocal of the step. Sample numbers stay below 2⁶³
/// (a span is finite and the step at least 1/64 of the smallest spacing), so they convert through `i64`, a
/// cheaper conversion than from `u64`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Samples {
    step: f64,
    inv_step: f64,
}

impl Samples {
    pub(crate) fn new(step: f64) -> Self {
        Self {
            step,
            inv_step: 1.0 / step,
        }
    }

    /// `k·step`.
    #[inline(always)]
    pub(crate) fn offset(&self, k: u64) -> f64 {
        k as i64 as f64 * self.step
    }

    /// The index of the first sample `t0 + k·step` beyond `exit` (mm). Skipped samples lie in empty space, so
    /// a sample exactly at `exit` (on the face of what is skipped) may go either way.
    #[inline(always)]
    pub(crate) fn first_beyond(&self, exit: f64, t0: f64) -> u64 {
        let x = (exit - t0) * self.inv_step;
        // Truncation floors a non-negative number; beyond 2⁶² (an unbounded exit) the span has ended anyway.
        if x >= 0.0 {
            x.min(4.6e18) as i64 as u64 + 1
        } else {
            1
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chessboard_distance_is_the_largest_axis_offset_to_the_nearest_busy_brick() {
        let nb = [5, 7, 9];
        let busy_cells = [[1usize, 2, 3], [4, 6, 8]];
        let mut busy = vec![false; nb[0] * nb[1] * nb[2]];
        for [z, y, x] in busy_cells {
            busy[(z * nb[1] + y) * nb[2] + x] = true;
        }
        let d = chessboard_distance(nb, &busy);
        for z in 0..nb[0] {
            for y in 0..nb[1] {
                for x in 0..nb[2] {
                    let want = busy_cells
                        .iter()
                        .map(|c| z.abs_diff(c[0]).max(y.abs_diff(c[1])).max(x.abs_diff(c[2])))
                        .min()
                        .unwrap();
                    assert_eq!(
                        d[(z * nb[1] + y) * nb[2] + x] as usize,
                        want,
                        "({z}, {y}, {x})"
                    );
                }
            }
        }
        let none = chessboard_distance(nb, &vec![false; busy.len()]);
        assert!(none.iter().all(|&v| v == FAR));
    }
}
