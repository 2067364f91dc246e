//! Ring suppression in the sinogram: Vo's sorting-based stripe filter (Vo, Atwood & Drakopoulos, Opt.
//! Express 26 (2018) 28396; Algotom's `remove_stripe_based_sorting`). Each detector column of the
//! sinogram `[view][u]` is sorted over the views; in the sorted sinogram a detector pixel that responds
//! differently is a straight stripe, removed by a median filter across columns (along u) of each sorted
//! row; the values are then put back in their original order. Only the sinogram changes, never the image.

use ndarray::{Array2, ArrayViewMut2, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;

fn size21() -> usize {
    21
}

/// The sorting-based stripe filter: `size` (odd, default 21) is the width in detector columns of the
/// median filter across the sorted sinogram, as Algotom's `size`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SortingStripeFilter {
    #[serde(default = "size21")]
    pub size: usize,
}

impl Default for SortingStripeFilter {
    fn default() -> Self {
        Self { size: size21() }
    }
}

/// Mirror index `i` into `0..n` (scipy's `reflect`: `d c b a | a b c d | d c b a`).
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let period = 2 * n;
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - 1 - m }) as usize
}

impl SortingStripeFilter {
    /// Filter the sinogram `[view][u]` in place.
    pub fn apply(&self, mut sino: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        if self.size.is_multiple_of(2) || self.size < 3 {
            return Err(ReconError::param(
                "size",
                format!("must be odd and at least 3, got {}", self.size),
            ));
        }
        let (nviews, nu) = sino.dim();
        if nviews == 0 || nu == 0 {
            return Ok(());
        }
        if sino.iter().any(|v| !v.is_finite()) {
            return Err(ReconError::param("sinogram", "contains a non-finite value"));
        }
        // Sorted columns, stored transposed: order[u][rank] is the view of rank `rank` in column u.
        let mut order = Array2::<u32>::zeros((nu, nviews));
        let mut sorted = Array2::<f32>::zeros((nviews, nu));
        {
            let view = sino.view();
            order
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .enumerate()
                .for_each(|(u, mut ord)| {
                    let Some(ord) = ord.as_slice_mut() else {
                        return;
                    };
                    for (k, o) in ord.iter_mut().enumerate() {
                        *o = k as u32;
                    }
                    ord.sort_unstable_by(|&a, &b| {
                        view[[a as usize, u]].total_cmp(&view[[b as usize, u]])
                    });
                });
            for u in 0..nu {
                for rank in 0..nviews {
                    sorted[[rank, u]] = view[[order[[u, rank]] as usize, u]];
                }
            }
        }
        // Median across columns of every sorted row.
        let half = (self.size / 2) as isize;
        let size = self.size;
        let mut filtered = Array2::<f32>::zeros((nviews, nu));
        filtered
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(sorted.axis_iter(Axis(0)))
            .for_each(|(mut out, row)| {
                let mut w = vec![0f32; size];
                for (u, o) in out.iter_mut().enumerate() {
                    for (k, x) in w.iter_mut().enumerate() {
                        *x = row[reflect(u as isize + k as isize - half, nu)];
                    }
                    let (_, m, _) = w.select_nth_unstable_by(size / 2, f32::total_cmp);
                    *o = *m;
                }
            });
        for u in 0..nu {
            for rank in 0..nviews {
                sino[[order[[u, rank]] as usize, u]] = filtered[[rank, u]];
            }
        }
        Ok(())
    }
}
