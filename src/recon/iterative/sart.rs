//! SART (one view per update) and OS-SART (ordered subsets of views):
//! x ← x + λ C_S Aᵀ_S R_S (b_S − A_S x) for each subset S in turn, C_S = diag(1/Σ_{i∈S} a_ij),
//! R = diag(1/Σ_j a_ij).

use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::ops::{
    axpy_scaled, column_sums, constrain, converged, norm, reciprocal_floor, report,
    residual_in_place, row_sums, safe_reciprocal, subsets,
};
use super::params::{Bounds, SartParams};
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;
use crate::recon::projector::parallel2::LineSweep;
use crate::recon::team::with_team;

/// Most f32 values of per-subset column sums kept in memory; beyond this they are recomputed on each
/// use (one extra back projection per subset).
pub const MAX_STORED_WEIGHTS: u64 = 1 << 26;

/// Seed of the subset order.
pub const ORDER_SEED: u64 = 0x5a27_0bde;

/// Whether the per-subset column sums of `count` subsets of an `image_len` image are stored.
pub fn stores_weights(count: usize, image_len: usize) -> bool {
    (count as u64).saturating_mul(image_len as u64) <= MAX_STORED_WEIGHTS
}

/// Precomputed weights of an ordered-subset sweep.
pub struct Sweep {
    pub subsets: Vec<Vec<usize>>,
    /// 1 / row sums, the whole data, view after view.
    r_weight: Vec<f32>,
    /// 1 / column sums per subset, when stored.
    c_weights: Option<Vec<Vec<f32>>>,
    /// The fused single-view updates, when every subset is one view that the line kernels take
    /// (they compute the column sums as they go: no `c_weights` then).
    lines: Option<LineSweep>,
}

impl Sweep {
    pub fn new(op: &dyn Operator, count: usize, ctl: &Control<'_>) -> Result<Self, ReconError> {
        let all: Vec<usize> = (0..op.view_count()).collect();
        let mut r_weight = row_sums(op, &all, ctl)?;
        safe_reciprocal(&mut r_weight);
        let mut subsets = subsets(op.view_count(), count);
        // Visit the subsets in a fixed pseudo-random order (as ASTRA's SART does): successive updates
        // from nearby angles are nearly parallel and converge slowly.
        subsets.shuffle(&mut StdRng::seed_from_u64(ORDER_SEED));
        let single = subsets.iter().all(|s| s.len() == 1);
        let lines = match op.line_plans() {
            Some((plans, nx, ny)) if single => {
                LineSweep::new(plans, nx, ny, reciprocal_floor, ctl.cancel)?
            }
            _ => None,
        };
        let c_weights = if lines.is_none() && stores_weights(count, op.image_len()) {
            let mut w = Vec::with_capacity(count);
            for s in &subsets {
                let mut c = column_sums(op, s, ctl)?;
                safe_reciprocal(&mut c);
                w.push(c);
            }
            Some(w)
        } else {
            None
        };
        Ok(Self {
            subsets,
            r_weight,
            c_weights,
            lines,
        })
    }

    /// One pass over all subsets; returns the residual accumulated over the pass, each subset measured
    /// just before its update: √Σ_S ‖b_S − A_S x‖².
    pub fn run(
        &mut self,
        op: &dyn Operator,
        b: &[f32],
        x: &mut [f32],
        lambda: f32,
        bounds: Bounds,
        ctl: &Control<'_>,
    ) -> Result<f64, ReconError> {
        let m = op.view_len();
        if let Some(lines) = &mut self.lines {
            lines.load(x);
            let (subsets, r_weight) = (&self.subsets, &self.r_weight);
            // The updates' chunks run on a team of pool threads that stay awake between updates;
            // nothing in this loop calls into the pool itself.
            let sum2 = with_team(lines.partners(), |team| {
                let mut sum2 = 0.0f64;
                for s in subsets {
                    ctl.check()?;
                    let v = s[0];
                    let (b, w) = (&b[v * m..(v + 1) * m], &r_weight[v * m..(v + 1) * m]);
                    sum2 += lines.update(team, v, b, w, lambda, bounds.lower, bounds.upper);
                }
                Ok::<f64, ReconError>(sum2)
            })?;
            lines.store(x);
            return Ok(sum2.sqrt());
        }
        let mut bp = vec![0.0f32; x.len()];
        let mut sum2 = 0.0f64;
        // The subset's data and residual, reused by every subset (no allocation per view).
        let most = self.subsets.iter().map(Vec::len).max().unwrap_or(0) * m;
        let (mut bs, mut r) = (Vec::with_capacity(most), Vec::with_capacity(most));
        for (si, s) in self.subsets.iter().enumerate() {
            ctl.check()?;
            bs.clear();
            for &v in s {
                bs.extend_from_slice(&b[v * m..(v + 1) * m]);
            }
            r.clear();
            r.resize(bs.len(), 0.0f32);
            op.forward(x, s, &mut r, ctl.cancel)?;
            residual_in_place(&mut r, &bs);
            let rn = norm(&r);
            sum2 += rn * rn;
            for (k, &v) in s.iter().enumerate() {
                let w = &self.r_weight[v * m..(v + 1) * m];
                for (rv, wv) in r[k * m..(k + 1) * m].iter_mut().zip(w) {
                    *rv *= wv;
                }
            }
            op.back(&r, s, &mut bp, ctl.cancel)?;
            match &self.c_weights {
                Some(c) => axpy_scaled(x, lambda, &c[si], &bp),
                None => {
                    let mut c = column_sums(op, s, ctl)?;
                    safe_reciprocal(&mut c);
                    axpy_scaled(x, lambda, &c, &bp);
                }
            }
            constrain(x, bounds);
        }
        Ok(sum2.sqrt())
    }
}

/// Run SART/OS-SART with `subsets` ordered subsets (SART: one per view) from `x` (overwritten). The
/// residual reported with iteration `k` is accumulated over its pass (see [`Sweep::run`]).
pub fn sart(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &SartParams,
    subsets: usize,
    stage: &str,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let mut sweep = Sweep::new(op, subsets, ctl)?;
    let b_norm = norm(b);
    constrain(x, p.bounds());
    for k in 1..=p.iterations {
        let res = sweep.run(op, b, x, p.relaxation as f32, p.bounds(), ctl)?;
        report(ctl, stage, k, p.iterations, res);
        if converged(p.tolerance, res, b_norm) {
            break;
        }
    }
    Ok(())
}

#[cfg(test)]
#[path = "sart_tests.rs"]
mod tests;
