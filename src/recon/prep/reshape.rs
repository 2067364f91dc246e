//! Detector binning and cropping, with the panel each implies, and angle subsets.
//!
//! Binning averages blocks of `u × v` pixels; the pixels left over at the high end of an axis (when the
//! count is not a multiple of the factor) are dropped, which moves the panel's centre by half of them.
//! Cropping keeps a window of the panel; its centre becomes the panel's new centre. In both cases the
//! returned [`Panel`] puts every physical point where the data put it (tested with a projected point).

use ndarray::{Array2, ArrayView2, ArrayViewMut2, Axis, s};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;
use crate::recon::geometry::{Angles, Panel, Views3};

/// Average blocks of `u` columns × `v` rows. JSON: `{"u": 2, "v": 2}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bin {
    pub u: usize,
    pub v: usize,
}

impl Bin {
    fn check(&self, nv: usize, nu: usize) -> Result<(usize, usize), ReconError> {
        if self.u == 0 || self.v == 0 {
            return Err(ReconError::param("bin", "factors must be at least 1"));
        }
        if self.u > nu || self.v > nv {
            return Err(ReconError::param(
                "bin",
                format!("factors {}×{} exceed the panel {nu}×{nv}", self.u, self.v),
            ));
        }
        Ok((nv / self.v, nu / self.u))
    }

    /// Shape `[v][u]` of a binned view of `[nv][nu]`.
    pub fn shape(&self, nv: usize, nu: usize) -> Result<[usize; 2], ReconError> {
        let (a, b) = self.check(nv, nu)?;
        Ok([a, b])
    }

    /// The binned view.
    pub fn apply_view(&self, view: ArrayView2<'_, f32>) -> Result<Array2<f32>, ReconError> {
        let (nv, nu) = view.dim();
        let [a, b] = self.shape(nv, nu)?;
        let mut out = Array2::zeros((a, b));
        self.apply_view_into(view, out.view_mut())?;
        Ok(out)
    }

    /// The binned view into `out` (shape [`Bin::shape`]).
    pub fn apply_view_into(
        &self,
        view: ArrayView2<'_, f32>,
        mut out: ArrayViewMut2<'_, f32>,
    ) -> Result<(), ReconError> {
        let (nv, nu) = view.dim();
        let [a, b] = self.shape(nv, nu)?;
        if out.shape() != [a, b] {
            return Err(ReconError::ShapeMismatch {
                expected: vec![a, b],
                got: out.shape().to_vec(),
            });
        }
        let norm = 1.0 / (self.u * self.v) as f32;
        let (bu, bv) = (self.u, self.v);
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(r, mut row)| {
                row.fill(0.0);
                for src in view.slice(s![r * bv..(r + 1) * bv, ..b * bu]).rows() {
                    for (c, o) in row.iter_mut().enumerate() {
                        *o += (0..bu).map(|k| src[c * bu + k]).sum::<f32>();
                    }
                }
                row.mapv_inplace(|x| x * norm);
            });
        Ok(())
    }

    /// The panel of binned data.
    pub fn panel(&self, p: &Panel) -> Result<Panel, ReconError> {
        let (nv, nu) = self.check(p.nv, p.nu)?;
        let drop_u = (p.nu - nu * self.u) as f64;
        let drop_v = (p.nv - nv * self.v) as f64;
        Ok(Panel {
            nu,
            nv,
            du_mm: p.du_mm * self.u as f64,
            dv_mm: p.dv_mm * self.v as f64,
            offset_u_mm: p.offset_u_mm - drop_u * p.du_mm / 2.0,
            offset_v_mm: p.offset_v_mm - drop_v * p.dv_mm / 2.0,
        })
    }
}

/// Keep columns `u0 .. u0 + nu` and rows `v0 .. v0 + nv`. JSON: `{"u0": 8, "v0": 0, "nu": 112, "nv": 128}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Crop {
    pub u0: usize,
    pub v0: usize,
    pub nu: usize,
    pub nv: usize,
}

impl Crop {
    /// Refuse an empty window or one beyond the panel `nv × nu`.
    pub fn check(&self, nv: usize, nu: usize) -> Result<(), ReconError> {
        if self.nu == 0 || self.nv == 0 {
            return Err(ReconError::param("crop", "the window must not be empty"));
        }
        if self.u0 + self.nu > nu || self.v0 + self.nv > nv {
            return Err(ReconError::param(
                "crop",
                format!(
                    "window {}+{} × {}+{} exceeds the panel {nu}×{nv}",
                    self.u0, self.nu, self.v0, self.nv
                ),
            ));
        }
        Ok(())
    }

    /// The window of `view` (a view of the data, no copy).
    pub fn apply_view<'a>(
        &self,
        view: ArrayView2<'a, f32>,
    ) -> Result<ArrayView2<'a, f32>, ReconError> {
        let (nv, nu) = view.dim();
        self.check(nv, nu)?;
        Ok(view.slice_move(s![self.v0..self.v0 + self.nv, self.u0..self.u0 + self.nu]))
    }

    /// The panel of cropped data: the window's centre is the new panel centre.
    pub fn panel(&self, p: &Panel) -> Result<Panel, ReconError> {
        self.check(p.nv, p.nu)?;
        let shift = |start: usize, n: usize, full: usize| {
            start as f64 + (n as f64 - 1.0) / 2.0 - (full as f64 - 1.0) / 2.0
        };
        Ok(Panel {
            nu: self.nu,
            nv: self.nv,
            offset_u_mm: p.offset_u_mm + shift(self.u0, self.nu, p.nu) * p.du_mm,
            offset_v_mm: p.offset_v_mm + shift(self.v0, self.nv, p.nv) * p.dv_mm,
            ..*p
        })
    }
}

/// Every `step`-th view from `start`, at most `count` of them. JSON: `{"start": 0, "step": 2}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AngleSubset {
    #[serde(default)]
    pub start: usize,
    pub step: usize,
    #[serde(default)]
    pub count: Option<usize>,
}

impl AngleSubset {
    /// The indices kept from a scan of `views` views.
    pub fn indices(&self, views: usize) -> Result<Vec<usize>, ReconError> {
        if self.step == 0 {
            return Err(ReconError::param("step", "must be at least 1"));
        }
        if self.start >= views {
            return Err(ReconError::param(
                "start",
                format!("view {} of a scan of {views} views", self.start),
            ));
        }
        let all = (self.start..views).step_by(self.step);
        Ok(match self.count {
            Some(n) => all.take(n).collect(),
            None => all.collect(),
        })
    }

    /// The kept views of a canonical geometry.
    pub fn apply_views(&self, views: &Views3) -> Result<Views3, ReconError> {
        let keep = self.indices(views.views.len())?;
        Ok(Views3 {
            detector: views.detector,
            views: keep.iter().map(|&k| views.views[k]).collect(),
        })
    }

    /// The kept angles as a list (degrees), from the resolved angles `radians` of the scan.
    pub fn apply_angles(&self, radians: &[f64]) -> Result<Angles, ReconError> {
        let keep = self.indices(radians.len())?;
        Ok(Angles::List {
            degrees: keep.iter().map(|&k| radians[k].to_degrees()).collect(),
        })
    }
}
