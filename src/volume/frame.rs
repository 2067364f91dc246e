//! A volume and its placement in patient space.

use ndarray::Array3;

use crate::recon::grid::VolumeGrid;

/// Placement of a `[z][y][x]` sample grid in patient space (LPS, millimetres), as DICOM describes it:
/// voxel `[k][j][i]` sits at `origin + i·Δx·dir[0] + j·Δy·dir[1] + k·Δz·dir[2]`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Frame {
    /// Spacing along the column (x, index `i`), row (y, index `j`) and slice (z, index `k`) axes (mm, > 0).
    pub spacing_mm: [f64; 3],
    /// Patient position of voxel `[0][0][0]` (mm).
    pub origin_mm: [f64; 3],
    /// Unit vectors (LPS) of the column, row and slice index axes. For a tilted acquisition the slice axis
    /// need not be orthogonal to the other two.
    pub direction: [[f64; 3]; 3],
}

impl Frame {
    /// Axis-aligned frame: x to the patient's left, y posterior, z superior.
    pub const AXIS_ALIGNED: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

    /// The frame of a reconstruction grid: axis-aligned, centred where the grid says.
    pub fn from_grid(grid: &VolumeGrid) -> Self {
        Self {
            spacing_mm: grid.spacing_mm,
            origin_mm: [grid.x(0), grid.y(0), grid.z(0)],
            direction: Self::AXIS_ALIGNED,
        }
    }

    /// Patient position (mm) of the (possibly fractional) index `[k][j][i]`.
    pub fn position(&self, k: f64, j: f64, i: f64) -> [f64; 3] {
        let steps = [
            i * self.spacing_mm[0],
            j * self.spacing_mm[1],
            k * self.spacing_mm[2],
        ];
        let mut p = self.origin_mm;
        for (axis, step) in self.direction.iter().zip(steps) {
            for (pc, ac) in p.iter_mut().zip(axis) {
                *pc += step * ac;
            }
        }
        p
    }
}

impl Frame {
    /// Fractional index `[k, j, i]` of patient position `p_mm`, the inverse of [`Frame::position`]; `None` when the
    /// direction vectors are degenerate. For many points, build the [`IndexMap`] once.
    pub fn index_of(&self, p_mm: [f64; 3]) -> Option<[f64; 3]> {
        self.index_map().map(|m| m.index(p_mm))
    }

    /// The inverse of [`Frame::position`] as a precomputed affine map; `None` when the direction vectors are
    /// degenerate.
    pub fn index_map(&self) -> Option<IndexMap> {
        // Columns of M are the scaled index axes: p − origin = M · (i, j, k).
        let m: [[f64; 3]; 3] = std::array::from_fn(|r| {
            std::array::from_fn(|c| self.direction[c][r] * self.spacing_mm[c])
        });
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        if det.abs() < 1e-12 || !det.is_finite() {
            return None;
        }
        // Inverse by the adjugate; rows ordered k, j, i.
        let inv_row = |r: usize| -> [f64; 3] {
            let (a, b) = ((r + 1) % 3, (r + 2) % 3);
            std::array::from_fn(|c| {
                let (x, y) = ((c + 1) % 3, (c + 2) % 3);
                (m[x][a] * m[y][b] - m[x][b] * m[y][a]) / det
            })
        };
        Some(IndexMap {
            origin_mm: self.origin_mm,
            rows: [inv_row(2), inv_row(1), inv_row(0)],
        })
    }

    /// Patient positions (mm) of the eight corner samples of a `[z][y][x]` grid of `dim` samples (bit 2 of
    /// the corner number picks the last slice, bit 1 the last row, bit 0 the last column).
    pub fn corners(&self, dim: (usize, usize, usize)) -> [[f64; 3]; 8] {
        let (nz, ny, nx) = dim;
        std::array::from_fn(|c| {
            self.position(
                ((c >> 2) & 1) as f64 * nz.saturating_sub(1) as f64,
                ((c >> 1) & 1) as f64 * ny.saturating_sub(1) as f64,
                (c & 1) as f64 * nx.saturating_sub(1) as f64,
            )
        })
    }

    /// Unit normal of the slice planes (column axis × row axis).
    pub fn slice_normal(&self) -> [f64; 3] {
        let [a, b, _] = self.direction;
        let n = [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            n.map(|c| c / len)
        } else {
            [0.0, 0.0, 1.0]
        }
    }
}

/// Patient position (mm) → fractional index `[k, j, i]` of a [`Frame`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndexMap {
    origin_mm: [f64; 3],
    /// Rows of the inverse of the scaled direction matrix, for k, j and i.
    rows: [[f64; 3]; 3],
}

impl IndexMap {
    pub fn index(&self, p_mm: [f64; 3]) -> [f64; 3] {
        let d = [
            p_mm[0] - self.origin_mm[0],
            p_mm[1] - self.origin_mm[1],
            p_mm[2] - self.origin_mm[2],
        ];
        self.rows.map(|r| r[0] * d[0] + r[1] * d[1] + r[2] * d[2])
    }
}

/// A scalar volume (`[z][y][x]`, f32: μ in 1/mm for reconstructions, HU for CT series) and its frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume {
    pub data: Array3<f32>,
    pub frame: Frame,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_frame_places_voxels_where_the_grid_does() {
        let g = VolumeGrid {
            nx: 4,
            ny: 3,
            nz: 2,
            spacing_mm: [0.5, 0.75, 2.0],
            centre_mm: [10.0, -5.0, 1.0],
        };
        let f = Frame::from_grid(&g);
        for (k, j, i) in [(0, 0, 0), (1, 2, 3), (1, 0, 2)] {
            let p = f.position(k as f64, j as f64, i as f64);
            let want = [g.x(i), g.y(j), g.z(k)];
            for c in 0..3 {
                assert!(
                    (p[c] - want[c]).abs() < 1e-12,
                    "[{k}][{j}][{i}] axis {c}: {} vs {}",
                    p[c],
                    want[c]
                );
            }
        }
    }

    #[test]
    fn index_of_inverts_position_for_a_sheared_frame() {
        let f = Frame {
            spacing_mm: [0.7, 0.7, 2.5],
            origin_mm: [-100.0, 50.0, 10.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 0.96, -0.28], [0.0, 0.28, 0.96]],
        };
        let p = f.position(3.0, 17.5, 250.25);
        let idx = f.index_of(p).unwrap();
        for (got, want) in idx.iter().zip([3.0, 17.5, 250.25]) {
            assert!((got - want).abs() < 1e-9, "{idx:?}");
        }
    }

    #[test]
    fn an_oblique_frame_follows_its_direction_vectors() {
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let f = Frame {
            spacing_mm: [1.0, 2.0, 3.0],
            origin_mm: [1.0, 1.0, 1.0],
            direction: [[s, s, 0.0], [-s, s, 0.0], [0.0, 0.0, 1.0]],
        };
        let p = f.position(1.0, 1.0, 1.0);
        let want = [1.0 + s - 2.0 * s, 1.0 + s + 2.0 * s, 4.0];
        for c in 0..3 {
            assert!((p[c] - want[c]).abs() < 1e-12);
        }
    }
}
