//! A volume and its placement in patient space.

use ndarray::Array3;

use crate::recon::grid::VolumeGrid;

/// Placement of a `[z][y][x]` sample grid in patient space (LPS, millimetres), as DICOM describes it:
/// voxel `[k][j][i]` sits at `origin + i·Δx·dir[0] + j·Δy·dir[1] + k·Δz·dir[2]`.
#[derive(Debug, Clone, Copy, PartialEq)]
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
