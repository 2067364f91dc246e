//! The 3D parallel beam of synchrotron tomography: every ray is perpendicular to the rotation axis (z), so
//! every detector row is a 2D parallel-beam sinogram of the plane z = v. Its canonical form is a slice stack
//! ([`SliceViews`]): the 2D parallel views of one row, shared by every row, and the row sampling along z.
//!
//! Conventions: at view angle β the rays travel along `(−sin β, cos β, 0)` and the detector u axis is
//! `(cos β, sin β, 0)`, those of the 2D [`super::ParallelBeam`]; the v axis runs along +z. Element `[r][c]` of a
//! view measures the line through `u_c·(cos β, sin β, 0) + (0, 0, v_r)` with
//! `u_c = (c − (nu−1)/2)·du + offset_u`, `v_r = (r − (nv−1)/2)·dv + offset_v` (mm). Data are
//! `[view][v][u]`.

use ndarray::{Array2, ArrayView3, Axis, Zip};
use serde::{Deserialize, Serialize};

use super::vectors::{Ray3, Views2};
use super::{Angles, Panel, ParallelBeam};
use crate::recon::error::{GeometryError, count, finite, positive};
use crate::recon::grid::MAX_AXIS;

/// 3D parallel beam with a flat panel; default range 180°.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Parallel3d {
    pub angles: Angles,
    pub detector: Panel,
}

impl Parallel3d {
    /// Validate and convert to the slice-stack form.
    pub fn to_views(&self) -> Result<SliceViews, GeometryError> {
        let p = &self.detector;
        let nv = count("detector.nv", p.nv, MAX_AXIS)?;
        let dv_mm = positive("detector.dv_mm", p.dv_mm)?;
        let offset_v_mm = finite("detector.offset_v_mm", p.offset_v_mm)?;
        let row = ParallelBeam {
            angles: self.angles.clone(),
            det_count: count("detector.nu", p.nu, MAX_AXIS)?,
            det_spacing_mm: positive("detector.du_mm", p.du_mm)?,
            det_offset_mm: finite("detector.offset_u_mm", p.offset_u_mm)?,
        };
        Ok(SliceViews {
            rows: row.to_views()?,
            nv,
            dv_mm,
            offset_v_mm,
        })
    }
}

/// A 3D parallel beam in canonical form: the 2D parallel views every detector row shares, and the rows'
/// positions along z (row `r` at `v_r = (r − (nv−1)/2)·dv + offset_v` mm).
#[derive(Debug, Clone, PartialEq)]
pub struct SliceViews {
    /// The 2D parallel-beam views of one row (its detector is the u sampling).
    pub rows: Views2,
    pub nv: usize,
    pub dv_mm: f64,
    pub offset_v_mm: f64,
}

impl SliceViews {
    /// `[views, nv, nu]`, the shape of a projection stack.
    pub fn shape(&self) -> [usize; 3] {
        [self.rows.views.len(), self.nv, self.rows.detector.count]
    }
    /// z (mm) of row `r`.
    pub fn v(&self, r: usize) -> f64 {
        (r as f64 - (self.nv as f64 - 1.0) / 2.0) * self.dv_mm + self.offset_v_mm
    }
    /// Fractional row at height `z` (mm); inverse of [`SliceViews::v`].
    pub fn row_of(&self, z: f64) -> f64 {
        (z - self.offset_v_mm) / self.dv_mm + (self.nv as f64 - 1.0) / 2.0
    }
    /// The ray measured by element `[row][col]` of view `view`.
    pub fn ray(&self, view: usize, row: usize, col: usize) -> Ray3 {
        let v = &self.rows.views[view];
        let e = self.rows.element_position(v, col);
        let d = match v.source {
            super::Source2::Parallel { direction } => direction,
            super::Source2::Point { .. } => unreachable!("a parallel beam's rows are parallel"),
        };
        Ray3 {
            origin: [e[0], e[1], self.v(row)],
            direction: [d[0], d[1], 0.0],
        }
    }
    /// The sinogram (`[view][u]`) of the plane at height `z` (mm): the data linearly interpolated between the
    /// two nearest rows, a row beyond the detector counting as zero. `data` is `[view][v][u]` of
    /// [`SliceViews::shape`].
    pub fn sinogram_at(&self, data: ArrayView3<'_, f32>, z: f64) -> Array2<f32> {
        let [n, _, nu] = self.shape();
        let mut out = Array2::<f32>::zeros((n, nu));
        let f = self.row_of(z);
        if !f.is_finite() {
            return out;
        }
        let r0 = f.floor();
        let w1 = (f - r0) as f32;
        for (r, w) in [(r0, 1.0 - w1), (r0 + 1.0, w1)] {
            if w == 0.0 || r < 0.0 || r >= self.nv as f64 {
                continue;
            }
            let row = data.index_axis(Axis(1), r as usize);
            Zip::from(&mut out).and(&row).for_each(|o, &p| *o += w * p);
        }
        out
    }
    /// Whether the plane at height `z` (mm) meets the detector (lies within one row pitch of a row centre).
    pub fn covers(&self, z: f64) -> bool {
        let f = self.row_of(z);
        f > -1.0 && f < self.nv as f64
    }
}
