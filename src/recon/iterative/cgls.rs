//! CGLS: conjugate gradients on the normal equations AᵀA x = Aᵀ b, without forming AᵀA.

use super::ops::{axpy, converged, dot, forward_from, norm, report, residual_in_place};
use super::params::CglsParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Run CGLS from `x` (overwritten). The residual reported with iteration `k` is ‖A x_k − b‖, which
/// CGLS decreases monotonically. Stops early when the search direction vanishes (exact solution).
pub fn cgls(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &CglsParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let all: Vec<usize> = (0..op.view_count()).collect();
    let b_norm = norm(b);
    let mut r = vec![0.0f32; b.len()];
    forward_from(op, x, &all, &mut r, ctl)?;
    residual_in_place(&mut r, b);
    let mut s = vec![0.0f32; x.len()];
    op.back(&r, &all, &mut s, ctl.cancel)?;
    let mut dir = s.clone();
    let mut gamma = dot(&s, &s);
    let mut q = vec![0.0f32; b.len()];
    for k in 1..=p.iterations {
        ctl.check()?;
        if gamma <= 0.0 {
            report(ctl, "cgls", k, p.iterations, norm(&r));
            break;
        }
        op.forward(&dir, &all, &mut q, ctl.cancel)?;
        let qq = dot(&q, &q);
        if qq <= 0.0 {
            break;
        }
        let alpha = (gamma / qq) as f32;
        axpy(x, alpha, &dir);
        axpy(&mut r, -alpha, &q);
        op.back(&r, &all, &mut s, ctl.cancel)?;
        let gamma_new = dot(&s, &s);
        let beta = (gamma_new / gamma) as f32;
        gamma = gamma_new;
        for (d, sv) in dir.iter_mut().zip(&s) {
            *d = sv + beta * *d;
        }
        let res = norm(&r);
        report(ctl, "cgls", k, p.iterations, res);
        if converged(p.tolerance, res, b_norm) {
            break;
        }
    }
    Ok(())
}
