//! MLEM and OSEM: x ← x / (Aᵀ_S 1) · Aᵀ_S (b_S / A_S x) for each subset S (MLEM: one subset).

use super::ops::{column_sums, converged, gather, norm, report, safe_reciprocal, subsets};
use super::params::MlemParams;
use super::sart::stores_weights;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Run MLEM/OSEM. Negative data values (noise on rays through air) are treated as 0. The start is a
/// uniform image whose projections carry the same total as the data (MLEM cannot start from zero);
/// pixels no ray sees end at 0. The residual reported with iteration `k` is ‖A x − b‖ accumulated over
/// the pass, each subset measured just before its update (for MLEM: the iterate entering iteration k).
pub fn mlem(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &MlemParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let m = op.view_len();
    let b: Vec<f32> = b.iter().map(|v| v.max(0.0)).collect();
    let b_norm = norm(&b);
    let all: Vec<usize> = (0..op.view_count()).collect();
    let sens_all = column_sums(op, &all, ctl)?;
    // Uniform start c with Σ A(c·1) = c·Σ Aᵀ1 = Σ b.
    let total_b: f64 = b.iter().map(|&v| v as f64).sum();
    let total_a: f64 = sens_all.iter().map(|&v| v as f64).sum();
    let c = if total_a > 0.0 && total_b > 0.0 {
        (total_b / total_a) as f32
    } else {
        0.0
    };
    x.fill(c);
    let sets = subsets(op.view_count(), p.subsets);
    let stored = stores_weights(p.subsets, x.len());
    let mut sens: Vec<Vec<f32>> = Vec::new();
    if stored {
        if p.subsets == 1 {
            let mut s = sens_all;
            safe_reciprocal(&mut s);
            sens.push(s);
        } else {
            for s in &sets {
                let mut w = column_sums(op, s, ctl)?;
                safe_reciprocal(&mut w);
                sens.push(w);
            }
        }
    }
    let mut bp = vec![0.0f32; x.len()];
    for k in 1..=p.iterations {
        let mut sum2 = 0.0f64;
        for (si, s) in sets.iter().enumerate() {
            ctl.check()?;
            let bs = gather(&b, s, m);
            let mut ratio = vec![0.0f32; bs.len()];
            op.forward(x, s, &mut ratio, ctl.cancel)?;
            for (a, &bv) in ratio.iter_mut().zip(&bs) {
                let d = *a - bv;
                sum2 += d as f64 * d as f64;
                *a = if *a > 0.0 { bv / *a } else { 0.0 };
            }
            op.back(&ratio, s, &mut bp, ctl.cancel)?;
            let update = |inv: &[f32], x: &mut [f32]| {
                for ((xv, g), w) in x.iter_mut().zip(&bp).zip(inv) {
                    *xv *= g * w;
                }
            };
            if stored {
                update(&sens[si], x);
            } else {
                let mut w = column_sums(op, s, ctl)?;
                safe_reciprocal(&mut w);
                update(&w, x);
            }
        }
        let res = sum2.sqrt();
        report(ctl, "mlem", k, p.iterations, res);
        if converged(p.tolerance, res, b_norm) {
            break;
        }
    }
    Ok(())
}
