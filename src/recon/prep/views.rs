//! Where calibration reads its views from, and the panel roll (tilt) applied to a canonical geometry.
//!
//! A calibration reads only the views it needs, one at a time, through a [`ViewSource`]: a projection
//! stack in memory is one, and so is a reader of a scan's files that decodes view `i` on demand.

use ndarray::{ArrayView3, ArrayViewMut2};

use crate::recon::error::ReconError;
use crate::recon::geometry::Views3;

/// Views of a scan, read one at a time into a `[v][u]` buffer of the panel's shape.
pub trait ViewSource: Sync {
    /// Number of views.
    fn view_count(&self) -> usize;
    /// Read view `index` (line integrals, `[v][u]`) into `out`.
    fn read_view(&self, index: usize, out: ArrayViewMut2<'_, f32>) -> Result<(), ReconError>;
    /// Read rows `first_row ..` of view `index` into `out` (`[rows][nu]`). The default reads the whole
    /// view; a source that can read rows alone (a stack in memory, a striped TIFF) should.
    fn read_rows(
        &self,
        index: usize,
        first_row: usize,
        nv: usize,
        mut out: ArrayViewMut2<'_, f32>,
    ) -> Result<(), ReconError> {
        let (rows, nu) = out.dim();
        if first_row + rows > nv {
            return Err(ReconError::param(
                "rows",
                format!("rows {first_row}+{rows} of {nv}"),
            ));
        }
        let mut full = ndarray::Array2::<f32>::zeros((nv, nu));
        self.read_view(index, full.view_mut())?;
        out.assign(&full.slice(ndarray::s![first_row..first_row + rows, ..]));
        Ok(())
    }
}

impl ViewSource for ArrayView3<'_, f32> {
    fn view_count(&self) -> usize {
        self.shape()[0]
    }
    fn read_view(&self, index: usize, mut out: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        if index >= self.shape()[0] {
            return Err(ReconError::param("view", format!("no view {index}")));
        }
        let v = self.index_axis(ndarray::Axis(0), index);
        if v.shape() != out.shape() {
            return Err(ReconError::ShapeMismatch {
                expected: v.shape().to_vec(),
                got: out.shape().to_vec(),
            });
        }
        out.assign(&v);
        Ok(())
    }
    fn read_rows(
        &self,
        index: usize,
        first_row: usize,
        nv: usize,
        mut out: ArrayViewMut2<'_, f32>,
    ) -> Result<(), ReconError> {
        let (rows, nu) = out.dim();
        let shape = self.shape();
        if index >= shape[0] || shape[1] != nv || shape[2] != nu || first_row + rows > nv {
            return Err(ReconError::param(
                "rows",
                format!("rows {first_row}+{rows} × {nu} of view {index} of a stack {shape:?}"),
            ));
        }
        out.assign(&self.slice(ndarray::s![index, first_row..first_row + rows, ..]));
        Ok(())
    }
}

/// Roll the panel of every view by `tilt_deg` about its central ray, counter-clockwise seen from the
/// source: `u' = u cos θ + v sin θ`, `v' = v cos θ − u sin θ` (see the module docs of
/// [`prep`](super)). The central ray's foot (`det_centre`) stays where it is.
pub fn roll_views(views: &mut Views3, tilt_deg: f64) {
    let (s, c) = tilt_deg.to_radians().sin_cos();
    for v in &mut views.views {
        let (u, w) = (v.det_u, v.det_v);
        v.det_u = std::array::from_fn(|i| u[i] * c + w[i] * s);
        v.det_v = std::array::from_fn(|i| w[i] * c - u[i] * s);
    }
}
