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

    /// The cell (the 2 × 2 × 2 voxels) a trilinear lookup at fractional index `idx` reads, as the index of its
    /// first corner `[k, j, i]`, and the position inside it (0–1 per axis), clamped to the grid.
    #[inline(always)]
    pub(crate) fn cell(&self, idx: [f32; 3]) -> ([usize; 3], [f32; 3]) {
        let base = |x: f32, n: usize| -> (usize, f32) {
            let x = x.clamp(0.0, (n - 1) as f32);
            // Through u32: a cheaper conversion than to usize, and a grid has fewer than 2³² voxels a side.
            let b = (x as u32 as usize).min(n - 2);
            (b, x - b as f32)
        };
        let (k, fk) = base(idx[0], self.n[0]);
        let (j, fj) = base(idx[1], self.n[1]);
        let (i, fi) = base(idx[2], self.n[2]);
        ([k, j, i], [fk, fj, fi])
    }

    /// Trilinear value at fractional index `idx`, clamped to the grid.
    #[inline(always)]
    pub fn at_index(&self, idx: [f32; 3]) -> f32 {
        let (c, f) = self.cell(idx);
        self.at_cell(c, f)
    }

    /// Trilinear value at position `f` inside cell `c` (as [`Sampler::cell`] gives them).
    #[inline(always)]
    pub(crate) fn at_cell(&self, c: [usize; 3], f: [f32; 3]) -> f32 {
        let [_, ny, nx] = self.n;
        let [k, j, i] = c;
        let [fk, fj, fi] = f;
        let row = nx;
        let plane = ny * nx;
        let o = k * plane + j * row + i;
        let d = self.data;
        // o + plane + row + 1 < nz·ny·nx because k ≤ nz−2, j ≤ ny−2, i ≤ nx−2.
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let c00 = lerp(d[o], d[o + 1], fi);
        let c01 = lerp(d[o + row], d[o + row + 1], fi);
        let c10 = lerp(d[o + plane], d[o + plane + 1], fi);
        let c11 = lerp(d[o + plane + row], d[o + plane + row + 1], fi);
        lerp(lerp(c00, c01, fj), lerp(c10, c11, fj), fk)
    }

    /// The first corner voxel of cell `c`.
    #[inline(always)]
    pub(crate) fn corner(&self, c: [usize; 3]) -> f32 {
        self.data[(c[0] * self.n[1] + c[1]) * self.n[2] + c[2]]
    }

    /// Gradient (value per millimetre, patient axes x, y, z) at fractional index `idx` by central differences of
    /// trilinear samples one index step apart.
    #[inline(always)]
    pub fn gradient(&self, idx: [f32; 3]) -> V3 {
        let g_idx = self
            .index_gradient_inside(idx)
            .unwrap_or_else(|| self.index_gradient_clamped(idx));
        // ∂f/∂p_c = Σ_a ∂f/∂idx_a · ∂idx_a/∂p_c.
        let g = g_idx.map(f64::from);
        let l = &self.lin;
        [
            g[0] * l[0][0] + g[1] * l[1][0] + g[2] * l[2][0],
            g[0] * l[0][1] + g[1] * l[1][1] + g[2] * l[2][1],
            g[0] * l[0][2] + g[1] * l[1][2] + g[2] * l[2][2],
        ]
    }

    /// The index-space gradient `(T(idx + e_a) − T(idx − e_a)) / 2` of the trilinear field `T`, sample by sample
    /// (clamped to the grid like [`Sampler::at_index`]).
    fn index_gradient_clamped(&self, idx: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|a| {
            let (mut lo, mut hi) = (idx, idx);
            lo[a] -= 1.0;
            hi[a] += 1.0;
            (self.at_index(hi) - self.at_index(lo)) / 2.0
        })
    }

    /// [`Sampler::index_gradient_clamped`] where none of its six samples is clamped, from the 32 voxels they
    /// touch (each loaded once); `None` within a voxel of the grid's faces.
    #[inline(always)]
    fn index_gradient_inside(&self, idx: [f32; 3]) -> Option<[f32; 3]> {
        let [nz, ny, nx] = self.n;
        let base = |x: f32, n: usize| -> Option<(usize, f32)> {
            if x.is_nan() || x < 1.0 {
                return None;
            }
            let b = x as u32 as usize;
            (b + 2 < n).then_some((b, x - b as f32))
        };
        let (k, fk) = base(idx[0], nz)?;
        let (j, fj) = base(idx[1], ny)?;
        let (i, fi) = base(idx[2], nx)?;
        let (row, plane) = (nx, ny * nx);
        let d = self.data;
        #[inline(always)]
        fn lerp(a: f32, b: f32, t: f32) -> f32 {
            a + (b - a) * t
        }
        // The value at i + fi of the row whose voxel i is at offset `o`.
        #[inline(always)]
        fn row_at(d: &[f32], o: usize, fi: f32) -> f32 {
            lerp(d[o], d[o + 1], fi)
        }
        let at_row = |o: usize| row_at(d, o, fi);
        let o00 = k * plane + j * row + i;
        // Along x: the rows (k + dk, j + dj) from i − 1 to i + 2; `v` their values at i + fi, `gx` their
        // differences one voxel either side.
        let mut v = [[0.0f32; 2]; 2];
        let mut gx = [[0.0f32; 2]; 2];
        for dk in 0..2 {
            for dj in 0..2 {
                let o = o00 + dk * plane + dj * row;
                let x = &d[o - 1..o + 3];
                v[dk][dj] = lerp(x[1], x[2], fi);
                gx[dk][dj] = lerp(x[2], x[3], fi) - lerp(x[0], x[1], fi);
            }
        }
        let mut gy = [0.0f32; 2];
        let mut gz = [0.0f32; 2];
        for n in 0..2 {
            let below = at_row(o00 + n * plane - row);
            let above = at_row(o00 + n * plane + 2 * row);
            gy[n] = lerp(v[n][1], above, fj) - lerp(below, v[n][0], fj);
            let below = at_row(o00 - plane + n * row);
            let above = at_row(o00 + 2 * plane + n * row);
            gz[n] = lerp(v[1][n], above, fk) - lerp(below, v[0][n], fk);
        }
        Some([
            lerp(gz[0], gz[1], fj) / 2.0,
            lerp(gy[0], gy[1], fk) / 2.0,
            lerp(
                lerp(gx[0][0], gx[0][1], fj),
                lerp(gx[1][0], gx[1][1], fj),
                fk,
            ) / 2.0,
        ])
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{Frame, Volume};
    use ndarray::Array3;

    #[test]
    fn the_gradient_from_32_voxels_is_the_central_difference_of_six_trilinear_samples() {
        let vol = Volume {
            data: Array3::from_shape_fn((9, 10, 11), |(k, j, i)| {
                ((k * 7 + j * 13 + i * 29) % 17) as f32 - 0.3 * (k * j) as f32
                    + 0.1 * (i * i) as f32
            }),
            frame: Frame {
                spacing_mm: [0.7, 0.8, 2.5],
                origin_mm: [1.0, -2.0, 3.0],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let s = Sampler::new(&vol).unwrap();
        let (mut inside, mut total) = (0, 0);
        for q in 0..2000u32 {
            let h = |m: u32| (q.wrapping_mul(m) % 1000) as f32 / 1000.0;
            let idx = [
                h(7919) * 8.6 - 0.3,
                h(104729) * 9.6 - 0.3,
                h(1299709) * 10.6 - 0.3,
            ];
            let want = s.index_gradient_clamped(idx);
            total += 1;
            if let Some(got) = s.index_gradient_inside(idx) {
                inside += 1;
                for a in 0..3 {
                    assert!(
                        (got[a] - want[a]).abs() < 1e-3,
                        "{idx:?} axis {a}: {got:?} vs {want:?}"
                    );
                }
            }
            let g = s.gradient(idx);
            let want_mm = [want[2] / 0.7, want[1] / 0.8, want[0] / 2.5];
            for c in 0..3 {
                assert!(
                    (g[c] - want_mm[c] as f64).abs() < 2e-3,
                    "{idx:?}: {g:?} vs {want_mm:?}"
                );
            }
        }
        assert!(
            inside > total / 4,
            "{inside} of {total} samples took the 32-voxel path"
        );
    }
}
