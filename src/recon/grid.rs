//! Sampling grids for images and volumes, and the memory limit checked before allocating.
//!
//! Sample `i` of `n` along an axis with spacing `d` (mm) sits at `(i − (n−1)/2)·d + centre`. A "pixel grid"
//! covering a field of view `F` uses `d = F/n`; the grid of the seed program `phantom3d`, which samples both
//! ends of [−1, 1], uses `d = 2/(n−1)`.

use serde::{Deserialize, Serialize};

use super::error::{GeometryError, ReconError, count, finite, positive};

/// Largest number of samples along one axis that any grid or detector accepts.
pub const MAX_AXIS: usize = 1 << 15;

fn coord(i: usize, n: usize, d: f64, c: f64) -> f64 {
    (i as f64 - (n as f64 - 1.0) / 2.0) * d + c
}

/// A 2D image grid: `ny` rows along y by `nx` columns along x.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageGrid {
    pub nx: usize,
    pub ny: usize,
    /// Pixel size along x and y (mm).
    pub dx_mm: f64,
    pub dy_mm: f64,
    /// Position of the grid centre (mm), default the isocentre.
    #[serde(default)]
    pub centre_mm: [f64; 2],
}

impl ImageGrid {
    /// A square `n × n` grid of pixels of `pixel_mm`, centred on the isocentre.
    pub fn square(n: usize, pixel_mm: f64) -> Self {
        Self {
            nx: n,
            ny: n,
            dx_mm: pixel_mm,
            dy_mm: pixel_mm,
            centre_mm: [0.0, 0.0],
        }
    }
    pub fn validate(&self) -> Result<(), GeometryError> {
        count("nx", self.nx, MAX_AXIS)?;
        count("ny", self.ny, MAX_AXIS)?;
        positive("dx_mm", self.dx_mm)?;
        positive("dy_mm", self.dy_mm)?;
        finite("centre_mm[0]", self.centre_mm[0])?;
        finite("centre_mm[1]", self.centre_mm[1])?;
        Ok(())
    }
    /// x coordinate (mm) of column `i`.
    pub fn x(&self, i: usize) -> f64 {
        coord(i, self.nx, self.dx_mm, self.centre_mm[0])
    }
    /// y coordinate (mm) of row `j`.
    pub fn y(&self, j: usize) -> f64 {
        coord(j, self.ny, self.dy_mm, self.centre_mm[1])
    }
    /// `[ny, nx]`, the shape of an image on this grid.
    pub fn shape(&self) -> [usize; 2] {
        [self.ny, self.nx]
    }
    /// Radius (mm) of the circle around the isocentre that contains every pixel corner.
    pub fn enclosing_radius_mm(&self) -> f64 {
        let hx = self.nx as f64 * self.dx_mm / 2.0 + self.centre_mm[0].abs();
        let hy = self.ny as f64 * self.dy_mm / 2.0 + self.centre_mm[1].abs();
        hx.hypot(hy)
    }
}

/// A 3D volume grid, arrays `[z][y][x]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeGrid {
    pub nx: usize,
    pub ny: usize,
    pub nz: usize,
    /// Voxel size along x, y, z (mm).
    pub spacing_mm: [f64; 3],
    /// Position of the grid centre (x, y, z in mm).
    #[serde(default)]
    pub centre_mm: [f64; 3],
}

impl VolumeGrid {
    /// A cube of `n³` voxels of `voxel_mm`, centred on the isocentre.
    pub fn cube(n: usize, voxel_mm: f64) -> Self {
        Self {
            nx: n,
            ny: n,
            nz: n,
            spacing_mm: [voxel_mm; 3],
            centre_mm: [0.0; 3],
        }
    }
    pub fn validate(&self) -> Result<(), GeometryError> {
        count("nx", self.nx, MAX_AXIS)?;
        count("ny", self.ny, MAX_AXIS)?;
        count("nz", self.nz, MAX_AXIS)?;
        for (k, name) in ["spacing_mm[0]", "spacing_mm[1]", "spacing_mm[2]"]
            .iter()
            .enumerate()
        {
            positive(name, self.spacing_mm[k])?;
        }
        for (k, name) in ["centre_mm[0]", "centre_mm[1]", "centre_mm[2]"]
            .iter()
            .enumerate()
        {
            finite(name, self.centre_mm[k])?;
        }
        Ok(())
    }
    pub fn x(&self, i: usize) -> f64 {
        coord(i, self.nx, self.spacing_mm[0], self.centre_mm[0])
    }
    pub fn y(&self, j: usize) -> f64 {
        coord(j, self.ny, self.spacing_mm[1], self.centre_mm[1])
    }
    pub fn z(&self, k: usize) -> f64 {
        coord(k, self.nz, self.spacing_mm[2], self.centre_mm[2])
    }
    /// `[nz, ny, nx]`, the shape of a volume on this grid.
    pub fn shape(&self) -> [usize; 3] {
        [self.nz, self.ny, self.nx]
    }
    /// The axial (x, y) grid of one slice.
    pub fn slice_grid(&self) -> ImageGrid {
        ImageGrid {
            nx: self.nx,
            ny: self.ny,
            dx_mm: self.spacing_mm[0],
            dy_mm: self.spacing_mm[1],
            centre_mm: [self.centre_mm[0], self.centre_mm[1]],
        }
    }
    /// Number of voxels, saturating instead of overflowing.
    pub fn voxels(&self) -> u64 {
        (self.nx as u64)
            .saturating_mul(self.ny as u64)
            .saturating_mul(self.nz as u64)
    }
}

/// Memory limits checked before any allocation sized by input.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Most bytes one computation may allocate for its arrays.
    pub max_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Self { max_bytes: 8 << 30 }
    }
}

impl Limits {
    /// `Err(TooLarge)` when `needed_bytes` exceeds the limit.
    pub fn check(&self, needed_bytes: u64) -> Result<(), ReconError> {
        if needed_bytes > self.max_bytes {
            Err(ReconError::TooLarge {
                needed_bytes,
                limit_bytes: self.max_bytes,
            })
        } else {
            Ok(())
        }
    }
    /// Bytes of `elements` f32 values, saturating.
    pub fn f32_bytes(elements: u64) -> u64 {
        elements.saturating_mul(4)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_centres_are_symmetric_about_the_grid_centre() {
        let g = ImageGrid::square(4, 0.5);
        assert_eq!([g.x(0), g.x(1), g.x(2), g.x(3)], [-0.75, -0.25, 0.25, 0.75]);
        let v = VolumeGrid {
            centre_mm: [0.0, 0.0, 10.0],
            ..VolumeGrid::cube(3, 2.0)
        };
        assert_eq!([v.z(0), v.z(1), v.z(2)], [8.0, 10.0, 12.0]);
    }

    #[test]
    fn limits_refuse_what_does_not_fit() {
        let l = Limits { max_bytes: 1000 };
        assert!(l.check(1000).is_ok());
        assert_eq!(
            l.check(1001),
            Err(ReconError::TooLarge {
                needed_bytes: 1001,
                limit_bytes: 1000
            })
        );
    }
}
