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

/// Which bricks hold something to see.
pub(crate) struct BrickMask {
    nb: [usize; 3],
    busy: Vec<bool>,
}

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
        BrickMask {
            nb: self.nb,
            busy: self
                .range
                .par_iter()
                .map(|&(lo, hi)| busy(lo, hi))
                .collect(),
        }
    }
}

impl BrickMask {
    /// Whether the brick holding fractional index `idx` is busy (outside the grid: not busy).
    #[inline]
    pub(crate) fn busy_at(&self, idx: [f32; 3]) -> bool {
        let mut b = [0usize; 3];
        for a in 0..3 {
            if idx[a] < 0.0 {
                return false;
            }
            b[a] = (idx[a] as usize / BRICK).min(self.nb[a] - 1);
        }
        self.busy[(b[0] * self.nb[1] + b[1]) * self.nb[2] + b[2]]
    }

    /// The ray parameter (mm) where a ray at fractional index `idx`, moving `dir` index units per mm, leaves
    /// the brick that holds `idx`; measured from `idx`.
    #[inline]
    pub(crate) fn exit(&self, idx: [f32; 3], dir: V3) -> f64 {
        let mut t = f64::INFINITY;
        for a in 0..3 {
            let b = (idx[a].max(0.0) as usize / BRICK).min(self.nb[a] - 1) as f64;
            let x = idx[a] as f64;
            if dir[a] > 1e-12 {
                t = t.min(((b + 1.0) * BRICK as f64 - x) / dir[a]);
            } else if dir[a] < -1e-12 {
                t = t.min((x - b * BRICK as f64) / -dir[a]);
            }
        }
        t.max(0.0)
    }
}
