//! The optional preprocessing steps a user asks for on top of a scan's normalisation, as one value
//! (`{"angles", "crop", "bin", "linearise", "stripes"}`, every part optional), applied in a fixed order:
//! the views kept (angle subset), then per view crop → bin → linearise, then stripe suppression on the
//! sinogram of each detector row. The same plan gives the geometry of the result and the record of the
//! steps, so that an import and `ctrecon recon` apply and report exactly the same thing.

use ndarray::{Array2, ArrayView2, ArrayViewMut2, ArrayViewMut3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::{AngleSubset, Bin, Crop, Linearise, SortingStripeFilter};
use crate::recon::error::ReconError;
use crate::recon::geometry::{Geometry, Views};

/// The steps asked for. JSON: `{"angles": {"start": 0, "step": 2}, "crop": {"u0", "v0", "nu", "nv"},
/// "bin": {"u": 2, "v": 2}, "linearise": {"coefficients": [0, 1, 0.05]}, "stripes": {"size": 21}}`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrepPlan {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angles: Option<AngleSubset>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<Crop>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bin: Option<Bin>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linearise: Option<Linearise>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stripes: Option<SortingStripeFilter>,
}

/// Bytes of projections one stripe pass holds at a time (rows of every view).
pub const STRIPE_BLOCK_BYTES: usize = 64 << 20;

impl PrepPlan {
    pub fn is_empty(&self) -> bool {
        *self == PrepPlan::default()
    }

    /// The views kept of a scan of `views` views, in order.
    pub fn kept_views(&self, views: usize) -> Result<Vec<usize>, ReconError> {
        match &self.angles {
            Some(a) => a.indices(views),
            None => Ok((0..views).collect()),
        }
    }

    /// `(nv, nu)` of a view after crop and bin.
    pub fn view_shape(&self, nv: usize, nu: usize) -> Result<(usize, usize), ReconError> {
        let (mut nv, mut nu) = (nv, nu);
        if let Some(c) = &self.crop {
            c.check(nv, nu)?;
            (nv, nu) = (c.nv, c.nu);
        }
        if let Some(b) = &self.bin {
            let [a, c] = b.shape(nv, nu)?;
            (nv, nu) = (a, c);
        }
        Ok((nv, nu))
    }

    /// Check the plan against a scan of `views` views of `nv × nu` (before any work).
    pub fn check(&self, views: usize, nv: usize, nu: usize) -> Result<(), ReconError> {
        if self.kept_views(views)?.is_empty() {
            return Err(ReconError::param("angles", "keeps no view"));
        }
        self.view_shape(nv, nu)?;
        if let Some(l) = &self.linearise {
            l.apply_view(Array2::zeros((1, 1)).view_mut())?;
        }
        if let Some(s) = &self.stripes {
            s.apply(Array2::zeros((1, 1)).view_mut())?;
        }
        Ok(())
    }

    /// One view (`nv × nu`, ctrecon's detector order, line integrals) cropped, binned and linearised.
    pub fn apply_view(&self, view: ArrayView2<'_, f32>) -> Result<Array2<f32>, ReconError> {
        let cropped = match &self.crop {
            Some(c) => c.apply_view(view)?,
            None => view,
        };
        let mut out = match &self.bin {
            Some(b) => b.apply_view(cropped)?,
            None => cropped.to_owned(),
        };
        if let Some(l) = &self.linearise {
            l.apply_view(out.view_mut())?;
        }
        Ok(out)
    }

    /// Stripe suppression on a block `[view][rows][u]` holding every view of some detector rows.
    pub fn apply_stripes(&self, mut block: ArrayViewMut3<'_, f32>) -> Result<(), ReconError> {
        let Some(s) = &self.stripes else {
            return Ok(());
        };
        block
            .axis_iter_mut(Axis(1))
            .into_par_iter()
            .try_for_each(|sino: ArrayViewMut2<'_, f32>| s.apply(sino))
    }

    /// Detector rows per stripe block for `views` views of `nu` columns.
    pub fn stripe_rows(views: usize, nu: usize) -> usize {
        (STRIPE_BLOCK_BYTES / (views.max(1) * nu.max(1) * 4)).max(1)
    }

    /// The geometry of the preprocessed data (a cone beam's panel and angles).
    pub fn geometry(&self, geometry: &Geometry) -> Result<Geometry, ReconError> {
        if self.angles.is_none() && self.crop.is_none() && self.bin.is_none() {
            return Ok(geometry.clone());
        }
        let Geometry::Cone(cone) = geometry else {
            return Err(ReconError::param(
                "preprocessing",
                "cropping, binning and angle subsets apply to cone beams",
            ));
        };
        let mut cone = cone.clone();
        if let Some(c) = &self.crop {
            cone.detector = c.panel(&cone.detector)?;
        }
        if let Some(b) = &self.bin {
            cone.detector = b.panel(&cone.detector)?;
        }
        if let Some(a) = &self.angles {
            let Views::D3(views) = Geometry::Cone(cone.clone()).to_views()? else {
                return Err(ReconError::param("geometry", "a cone beam has 3D views"));
            };
            let radians: Vec<f64> = views.views.iter().map(|v| v.angle_rad).collect();
            cone.angles = a.apply_angles(&radians)?;
        }
        Ok(Geometry::Cone(cone))
    }

    /// The steps as recorded in a dataset's `preprocessing` list, in the order applied.
    pub fn steps(&self, views_before: usize, views_after: usize) -> Vec<Value> {
        let mut out = Vec::new();
        if let Some(a) = &self.angles {
            out.push(json!({"step": "angle_subset", "start": a.start, "step_views": a.step,
                            "count": a.count, "views_before": views_before, "views_after": views_after}));
        }
        if let Some(c) = &self.crop {
            out.push(json!({"step": "crop", "u0": c.u0, "v0": c.v0, "nu": c.nu, "nv": c.nv}));
        }
        if let Some(b) = &self.bin {
            out.push(json!({"step": "bin", "u": b.u, "v": b.v}));
        }
        if let Some(l) = &self.linearise {
            out.push(json!({"step": "linearise", "coefficients": l.coefficients}));
        }
        if let Some(s) = &self.stripes {
            out.push(json!({"step": "stripes", "method": "sorting", "size": s.size}));
        }
        out
    }
}
