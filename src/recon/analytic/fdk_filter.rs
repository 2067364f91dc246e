//! FDK's filtering: the per-scan set-up (orbit frames, angular steps, redundancy and pre-weights, the
//! row filter) and the weighted, filtered rows of a view, written into the panels the backprojection
//! loops of [`super::fdk`] read.

use ndarray::ArrayView3;

use super::backproject::PAD;
use super::fbp2d::fan_extent;
use super::filter::{FilterScratch, Kernel, RowFilter};
use super::orbit::{Frame, cone_frames};
use super::weights::{Redundancy, extension};
use crate::recon::algorithm::FbpParams;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Detector2, Views3, angular_steps};

/// The per-scan filtering set-up: orbit frames, angular steps, redundancy weights and the row filter.
pub(super) struct Setup {
    pub(super) frames: Vec<Frame>,
    pub(super) steps: Vec<f64>,
    pub(super) redundancy: Redundancy,
    /// Zero columns added on the left of offset panels, and the filtered row length.
    pub(super) lo: usize,
    pub(super) ne: usize,
    pub(super) filter: RowFilter,
    pub(super) det: Detector2,
    /// The pre-weight D/√(D² + p² + ζ²) of every detector element (`[v][u]`) where all views share
    /// the detector's distance and centre (every parametric geometry); otherwise computed per view.
    pub(super) pre: Option<Vec<f64>>,
}

impl Setup {
    pub(super) fn new(views: &Views3, params: &FbpParams) -> Result<Self, ReconError> {
        let det = views.detector;
        let frames = cone_frames(views)?;
        let f0 = frames[0];
        let angles: Vec<f64> = frames.iter().map(|f| f.angle_rad).collect();
        let steps = angular_steps(&angles);
        let ends = (det.u(0) + f0.u0, det.u(det.nu - 1) + f0.u0);
        let (gmin, gmax, element) = fan_extent(ends, det.du_mm, Some(f0.dsd));
        let redundancy = Redundancy::classify(&angles, gmin, gmax, element)?;
        // Offset panels are filtered on rows extended with zeros on the short side.
        let (lo, hi) = extension(&redundancy, (ends.0 + ends.1) / det.du_mm);
        let ne = det.nu + lo + hi;
        let kernel = Kernel::Ramp {
            spacing: det.du_mm * f0.dso / f0.dsd,
        };
        let filter = RowFilter::new(ne, kernel, 0.5, params)?;
        // Frames computed from rotated vectors differ in their last bits (750 against
        // 749.9999999999999 mm): within 10⁻⁹ of the distance and of a detector element, the first
        // frame's weights differ from each view's own by less than 10⁻⁹ of their value, a
        // sixtieth of f32 rounding.
        let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-9 * scale;
        let shared = frames.iter().all(|f| {
            close(f.dsd, f0.dsd, f0.dsd)
                && close(f.u0, f0.u0, det.du_mm)
                && close(f.v0, f0.v0, det.dv_mm)
        });
        let pre = shared.then(|| {
            (0..det.nv)
                .flat_map(|r| (0..det.nu).map(move |c| pre_weight(&f0, &det, r, c)))
                .collect()
        });
        Ok(Setup {
            frames,
            steps,
            redundancy,
            lo,
            ne,
            filter,
            det,
            pre,
        })
    }

    /// Weight and filter every detector row of view `k`, handing each filtered row (`ne` values, the
    /// angular step and D² folded in) to `put` with its row index, in order from row 0.
    pub(super) fn filter_view(
        &self,
        proj: ArrayView3<'_, f32>,
        k: usize,
        scratch: &mut FilterScratch,
        mut put: impl FnMut(usize, &[f32]),
    ) {
        let (nv, ne) = (self.det.nv, self.ne);
        let post = self.steps[k] * self.frames[k].dso * self.frames[k].dso;
        let mut row = vec![0.0f32; ne];
        let mut held = (Vec::new(), Vec::new());
        let mut emit = |r: usize, filtered: &[f64]| {
            for (o, q) in row.iter_mut().zip(filtered) {
                *o = (q * post) as f32;
            }
            put(r, &row);
        };
        // Rows two at a time through one complex FFT; an odd last row alone.
        for r in (0..nv).step_by(2) {
            if r + 1 < nv {
                let (first, second) = scratch.inputs(ne);
                self.weigh_row(proj, k, r, first, &mut held);
                self.weigh_row(proj, k, r + 1, second, &mut held);
                self.filter.run_pair(scratch);
                let (first, second) = scratch.outputs(ne);
                emit(r, first);
                emit(r + 1, second);
            } else {
                self.weigh_row(proj, k, r, scratch.input(ne), &mut held);
                self.filter.run(scratch);
                emit(r, scratch.output(ne));
            }
        }
    }

    /// Every detector row of view `k` as it is, times the angular step and D² (the factors
    /// [`Self::filter_view`] folds into its rows), on rows of `ne` values like the filtered ones,
    /// handed to `put` in order from row 0.
    pub(super) fn raw_view(
        &self,
        proj: ArrayView3<'_, f32>,
        k: usize,
        mut put: impl FnMut(usize, &[f32]),
    ) {
        let (nu, lo) = (self.det.nu, self.lo);
        let post = (self.steps[k] * self.frames[k].dso * self.frames[k].dso) as f32;
        let mut row = vec![0.0f32; self.ne];
        for r in 0..self.det.nv {
            let out = &mut row[lo..lo + nu];
            for (o, d) in out.iter_mut().zip(proj.slice(ndarray::s![k, r, ..])) {
                *o = d * post;
            }
            put(r, &row);
        }
    }

    /// Row `r` of view `k`, pre- and redundancy-weighted, into `input` (`ne` values: `lo` zeros, the
    /// row, zeros). `held` keeps a row copied out of a strided view and pre-weights computed for a view
    /// without the shared table.
    fn weigh_row(
        &self,
        proj: ArrayView3<'_, f32>,
        k: usize,
        r: usize,
        input: &mut [f64],
        (copied, computed): &mut (Vec<f32>, Vec<f64>),
    ) {
        let (det, f, lo) = (&self.det, &self.frames[k], self.lo);
        let view = proj.slice(ndarray::s![k, r, ..]);
        let data = match view.as_slice() {
            Some(data) => data,
            None => {
                copied.clear();
                copied.extend(view.iter());
                &copied[..]
            }
        };
        let pre = match &self.pre {
            Some(table) => &table[r * det.nu..(r + 1) * det.nu],
            None => {
                computed.clear();
                computed.extend((0..det.nu).map(|c| pre_weight(f, det, r, c)));
                &computed[..]
            }
        };
        input.fill(0.0);
        let data_part = &mut input[lo..lo + det.nu];
        if self.redundancy.is_full() {
            // The redundancy weight is 1: a loop without it, which vectorises.
            for ((o, d), p) in data_part.iter_mut().zip(data).zip(pre) {
                *o = *d as f64 * p;
            }
        } else {
            for (c, ((o, d), p)) in data_part.iter_mut().zip(data).zip(pre).enumerate() {
                let u = det.u(c) + f.u0;
                *o = *d as f64 * p * self.redundancy.weight(f.angle_rad, (u / f.dsd).atan());
            }
        }
    }
}

/// D/√(D² + p² + ζ²) at detector element (row `r`, column `c`) of view `f`, in detector coordinates
/// relative to the central ray.
pub(super) fn pre_weight(f: &Frame, det: &Detector2, r: usize, c: usize) -> f64 {
    let (u, v) = (det.u(c) + f.u0, det.v(r) + f.v0);
    f.dsd / (f.dsd * f.dsd + u * u + v * v).sqrt()
}

/// Filtered rows of a view gathered before they are written into its panel stored by columns, so that
/// each column receives this many contiguous values at once rather than one value per row.
pub(super) const ROW_BLOCK: usize = 16;

/// Write `block`, the filtered rows `r0..` of a view (`[row][ne]`), into the view's panel stored by
/// columns (`rows` stored values per column, zero-padded by [`PAD`] on all sides): column `c` of the
/// block becomes one contiguous run of stored column `PAD + c`, from stored row `PAD + r0`.
pub(super) fn put_columns(panel: &mut [f32], rows: usize, r0: usize, block: &[f32], ne: usize) {
    let n = block.len() / ne.max(1);
    let columns = panel[PAD * rows..].chunks_exact_mut(rows).take(ne);
    for (c, column) in columns.enumerate() {
        let run = &mut column[PAD + r0..PAD + r0 + n];
        for (o, v) in run.iter_mut().zip(block[c..].iter().step_by(ne)) {
            *o = *v;
        }
    }
}
