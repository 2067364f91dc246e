//! SIRT: x ← x + λ C Aᵀ R (b − A x), R = diag(1/row sums), C = diag(1/column sums).

use super::ops::{
    axpy_scaled, column_sums, constrain, converged, forward_from, norm, report, residual_in_place,
    row_sums, safe_reciprocal,
};
use super::params::SirtParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Run SIRT from `x` (overwritten with the result). The residual reported with iteration `k` is
/// ‖A x_k − b‖ of the iterate after `k` updates.
pub fn sirt(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &SirtParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let all: Vec<usize> = (0..op.view_count()).collect();
    let mut r_weight = row_sums(op, &all, ctl)?;
    safe_reciprocal(&mut r_weight);
    let mut c_weight = column_sums(op, &all, ctl)?;
    safe_reciprocal(&mut c_weight);
    let b_norm = norm(b);
    let mut r = vec![0.0f32; b.len()];
    let mut bp = vec![0.0f32; x.len()];
    constrain(x, p.bounds());
    forward_from(op, x, &all, &mut r, ctl)?;
    residual_in_place(&mut r, b);
    let lambda = p.relaxation as f32;
    for k in 1..=p.iterations {
        ctl.check()?;
        for (v, w) in r.iter_mut().zip(&r_weight) {
            *v *= w;
        }
        op.back(&r, &all, &mut bp, ctl.cancel)?;
        axpy_scaled(x, lambda, &c_weight, &bp);
        constrain(x, p.bounds());
        op.forward(x, &all, &mut r, ctl.cancel)?;
        residual_in_place(&mut r, b);
        let res = norm(&r);
        report(ctl, "sirt", k, p.iterations, res);
        if converged(p.tolerance, res, b_norm) {
            break;
        }
    }
    Ok(())
}
