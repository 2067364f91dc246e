//! Trilinear samples and central-difference gradients of a volume at patient positions, through the affine map
//! from patient millimetres to fractional `[k, j, i]` indexes.

use super::{RenderError, V3};
use crate::volume::Volume;

/// A volume prepared for ray casting: contiguous samples, sizes and the affine patient → index map.
pub struct Sampler<'a> {
    data: &'a [f32],
    /// `[nz, ny, nx]`.
    pub n: [usize; 3],
    /// Fractional index `[k, j, i]` of the patient origin.
    origin: V3,
    /// `lin[a]`: change of index `a` per millimetre along x, y, z.
    lin: [V3; 3],
}

impl<'a> Sampler<'a> {
    /// A sampler of `vol`; its samples must be in standard (C) order.
    pub fn new(vol: &'a Volume) -> Result<Self, RenderError> {
        let (nz, ny, nx) = vol.data.dim();
        if nz < 2 || ny < 2 || nx < 2 {
            return Err(RenderError::BadVolume);
        }
        let data = vol.data.as_slice().ok_or(RenderError::BadVolume)?;
        let map = vol.frame.index_map().ok_or(RenderError::BadVolume)?;
        let origin = map.index([0.0; 3]);
        let col = |c: usize| {
            let mut e = [0.0; 3];
            e[c] = 1.0;
            let p = map.index(e);
            [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]]
        };
        let cols = [col(0), col(1), col(2)];
        let lin = std::array::from_fn(|a| [cols[0][a], cols[1][a], cols[2][a]]);
        Ok(Self {
            data,
            n: [nz, ny, nx],
            origin,
            lin,
        })
    }

    /// Fractional index `[k, j, i]` of patient point `p` (mm).
    #[inline]
    pub fn index(&self, p: V3) -> V3 {
        std::array::from_fn(|a| self.origin[a] + super::dot(self.lin[a], p))
    }

    /// Change of the fractional index per millimetre along direction `d`.
    #[inline]
    pub fn index_direction(&self, d: V3) -> V3 {
        std::array::from_fn(|a| super::dot(self.lin[a], d))
    }

    /// Trilinear value at fractional index `idx`, clamped to the grid.
    #[inline]
    pub fn at_index(&self, idx: [f32; 3]) -> f32 {
        let [nz, ny, nx] = self.n;
        let base = |x: f32, n: usize| -> (usize, f32) {
            let x = x.clamp(0.0, (n - 1) as f32);
            let b = (x as usize).min(n - 2);
            (b, x - b as f32)
        };
        let (k, fk) = base(idx[0], nz);
        let (j, fj) = base(idx[1], ny);
        let (i, fi) = base(idx[2], nx);
        let row = nx;
        let plane = ny * nx;
        let o = k * plane + j * row + i;
        let d = self.data;
        // SAFETY-free indexing: o + plane + row + 1 < nz·ny·nx because k ≤ nz−2, j ≤ ny−2, i ≤ nx−2.
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let c00 = lerp(d[o], d[o + 1], fi);
        let c01 = lerp(d[o + row], d[o + row + 1], fi);
        let c10 = lerp(d[o + plane], d[o + plane + 1], fi);
        let c11 = lerp(d[o + plane + row], d[o + plane + row + 1], fi);
        lerp(lerp(c00, c01, fj), lerp(c10, c11, fj), fk)
    }

    /// Gradient (value per millimetre, patient axes x, y, z) at fractional index `idx` by central differences of
    /// trilinear samples one index step apart.
    pub fn gradient(&self, idx: [f32; 3]) -> V3 {
        let mut g_idx = [0.0f64; 3];
        for (a, g) in g_idx.iter_mut().enumerate() {
            let (mut lo, mut hi) = (idx, idx);
            lo[a] -= 1.0;
            hi[a] += 1.0;
            *g = (self.at_index(hi) - self.at_index(lo)) as f64 / 2.0;
        }
        // ∂f/∂p_c = Σ_a ∂f/∂idx_a · ∂idx_a/∂p_c.
        std::array::from_fn(|c| (0..3).map(|a| g_idx[a] * self.lin[a][c]).sum())
    }

    /// The interval of `t` (mm) where `o + t·d` lies inside the grid of voxel centres; `None` when it misses.
    pub fn box_interval(&self, o: V3, d: V3) -> Option<(f64, f64)> {
        let io = self.index(o);
        let id = self.index_direction(d);
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        for a in 0..3 {
            let last = (self.n[a] - 1) as f64;
            if id[a].abs() < 1e-15 {
                if io[a] < 0.0 || io[a] > last {
                    return None;
                }
            } else {
                let t1 = -io[a] / id[a];
                let t2 = (last - io[a]) / id[a];
                lo = lo.max(t1.min(t2));
                hi = hi.min(t1.max(t2));
            }
        }
        (lo <= hi).then_some((lo, hi))
    }

    pub(crate) fn data(&self) -> &[f32] {
        self.data
    }
}
