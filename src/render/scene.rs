//! A volume prepared once for any number of renderings: the sampler, the min/max bricks and the bounding sphere.

use super::{BrickGrid, RenderError, Sampler, V3, volume_bounds};
use crate::volume::Volume;

/// A volume ready for ray casting (shared by every frame of a sequence).
pub struct Scene<'a> {
    pub sampler: Sampler<'a>,
    pub bricks: BrickGrid,
    pub centre: V3,
    pub radius: f64,
    /// Smallest voxel spacing (mm).
    pub min_spacing: f64,
}

impl<'a> Scene<'a> {
    pub fn new(vol: &'a Volume) -> Result<Self, RenderError> {
        let sampler = Sampler::new(vol)?;
        let bricks = BrickGrid::new(&sampler);
        let (centre, radius) = volume_bounds(&vol.frame, vol.data.dim());
        let min_spacing = vol
            .frame
            .spacing_mm
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        Ok(Self {
            sampler,
            bricks,
            centre,
            radius,
            min_spacing,
        })
    }

    /// The default sample step (mm): half the smallest spacing.
    pub fn default_step(&self) -> f64 {
        self.min_spacing / 2.0
    }

    /// A step request checked against the rule `step ≤ ½ smallest spacing`.
    pub fn step(&self, requested: Option<f64>) -> Result<f64, RenderError> {
        let max = self.default_step();
        match requested {
            None => Ok(max),
            Some(s) if s.is_finite() && s > 0.0 && s <= max * (1.0 + 1e-9) && s >= max / 64.0 => {
                Ok(s)
            }
            Some(s) => Err(RenderError::InvalidParameter {
                name: "step_mm",
                reason: format!(
                    "{s} is outside ({:.4}, {max:.4}] (at most half the smallest spacing)",
                    max / 64.0
                ),
            }),
        }
    }
}
