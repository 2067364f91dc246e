//! A volume prepared once for any number of renderings: the sampler, the min/max bricks, the bounding sphere and
//! the brick masks and cell occupancies built so far (one per transfer function or set of iso-values, shared by
//! every frame that uses it).

use std::sync::{Arc, Mutex, PoisonError};

use super::bricks::BrickMask;
use super::occupancy::{Occupancy, Windows};
use super::{BrickGrid, RenderError, Sampler, V3, volume_bounds};
use crate::volume::Volume;

/// Rendering set-ups a scene keeps (the most recently used).
const KEPT_PREPARED: usize = 4;

/// What one transfer function or set of iso-values needs besides the volume: the mask of busy bricks and, with
/// cell skipping, the cell occupancy.
pub(crate) struct Prepared {
    pub(crate) mask: BrickMask,
    pub(crate) cells: Option<Occupancy>,
}

/// A volume ready for ray casting (shared by every frame of a sequence).
pub struct Scene<'a> {
    pub sampler: Sampler<'a>,
    pub bricks: BrickGrid,
    pub centre: V3,
    pub radius: f64,
    /// Smallest voxel spacing (mm).
    pub min_spacing: f64,
    /// Whether samples in cells that cannot show anything are skipped (default). `false` renders with the brick
    /// grid alone, the earlier sample path, to compare pictures and times; the pictures are the same.
    pub cell_skipping: bool,
    prepared: Mutex<Vec<(Vec<u64>, Arc<Prepared>)>>,
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
            cell_skipping: true,
            prepared: Mutex::new(Vec::new()),
        })
    }

    /// The brick mask and cell occupancy of one rendering set-up, identified by `key` (the transfer function or
    /// iso-values and step it was made for): built on first use with `mask` and `windows`, then kept for the
    /// next frames. With cell skipping off, the mask is built for every call and nothing is kept (the earlier
    /// path).
    pub(crate) fn prepared(
        &self,
        key: Vec<u64>,
        mask: impl FnOnce() -> BrickMask + Send,
        windows: Windows,
    ) -> Arc<Prepared> {
        if !self.cell_skipping {
            return Arc::new(Prepared {
                mask: mask(),
                cells: None,
            });
        }
        {
            let mut kept = self.prepared.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(p) = kept.iter().position(|(k, _)| *k == key) {
                let hit = kept.remove(p);
                let out = Arc::clone(&hit.1);
                kept.insert(0, hit);
                return out;
            }
        }
        // Built outside the lock: two frames asking at once may both build it; one copy is kept.
        let (mask, cells) = rayon::join(mask, || {
            Occupancy::new(&self.sampler, &self.bricks, &windows)
        });
        let out = Arc::new(Prepared {
            mask,
            cells: Some(cells),
        });
        let mut kept = self.prepared.lock().unwrap_or_else(PoisonError::into_inner);
        if !kept.iter().any(|(k, _)| *k == key) {
            kept.insert(0, (key, Arc::clone(&out)));
            kept.truncate(KEPT_PREPARED);
        }
        out
    }

    /// Occupied and total cells of each cell occupancy kept, most recently used first.
    pub fn occupancy_counts(&self) -> Vec<(usize, usize)> {
        let kept = self.prepared.lock().unwrap_or_else(PoisonError::into_inner);
        kept.iter()
            .filter_map(|(_, p)| p.cells.as_ref().map(Occupancy::count))
            .collect()
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
