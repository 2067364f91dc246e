//! CGLS: conjugate gradients on the normal equations AᵀA x = Aᵀ b, without forming AᵀA; with a
//! back projector B that is not Aᵀ ([`BackProjector::Voxel`]), conjugate gradients on B A x = B b.

use super::ops::{axpy, converged, dot, forward_from, norm, report, residual_in_place};
use super::params::{BackProjector, CglsParams};
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Run CGLS from `x` (overwritten). The residual reported with iteration `k` is ‖A x_k − b‖, which
/// CGLS decreases monotonically. Stops early when the search direction vanishes (exact solution).
///
/// With [`BackProjector::Voxel`], `op`'s back side B is not Aᵀ and the iteration is conjugate
/// gradients on B A x = B b (RTK's conjugate gradient filter): the step is ⟨s, s⟩ / ⟨d, B A d⟩ for the
/// back-projected residual s = B (b − A x) and the direction d, and s is updated with B A d instead of
/// being back-projected afresh. Where B = Aᵀ this is CGLS in exact arithmetic; where B is only close to
/// Aᵀ up to a positive factor, B A is not symmetric and the iterates are no longer the least-squares
/// ones, which is why it is an option and not the default. The residual it reports is no longer
/// monotone, and it also stops where a step would not be positive. Either way an iteration takes one
/// forward and one back projection.
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
    // B A d, for the voxel-driven back projector only.
    let mut z = (p.back_projector == BackProjector::Voxel).then(|| vec![0.0f32; x.len()]);
    for k in 1..=p.iterations {
        ctl.check()?;
        if gamma <= 0.0 {
            report(ctl, "cgls", k, p.iterations, norm(&r));
            break;
        }
        op.forward(&dir, &all, &mut q, ctl.cancel)?;
        let curvature = match z.as_mut() {
            None => dot(&q, &q),
            Some(z) => {
                op.back(&q, &all, z, ctl.cancel)?;
                let c = dot(&dir, z);
                if c <= 0.0 || !c.is_finite() {
                    report(ctl, "cgls", k, p.iterations, norm(&r));
                    break;
                }
                c
            }
        };
        if curvature <= 0.0 {
            break;
        }
        let alpha = (gamma / curvature) as f32;
        axpy(x, alpha, &dir);
        axpy(&mut r, -alpha, &q);
        if let Some(z) = &z {
            axpy(&mut s, -alpha, z);
        }
        let res = norm(&r);
        // x is final after the last iteration or on convergence: what follows only prepares the
        // next direction, so it is skipped then (ten iterations of CGLS take ten forward and ten back
        // projections in all, not eleven back projections).
        if k == p.iterations || converged(p.tolerance, res, b_norm) {
            report(ctl, "cgls", k, p.iterations, res);
            break;
        }
        if z.is_none() {
            op.back(&r, &all, &mut s, ctl.cancel)?;
        }
        let gamma_new = dot(&s, &s);
        let beta = (gamma_new / gamma) as f32;
        gamma = gamma_new;
        for (d, sv) in dir.iter_mut().zip(&s) {
            *d = sv + beta * *d;
        }
        report(ctl, "cgls", k, p.iterations, res);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::control::{Cancel, NoProgress};
    use crate::recon::geometry::{Angles, ParallelBeam};
    use crate::recon::grid::ImageGrid;
    use crate::recon::iterative::counted::Counted;
    use crate::recon::projector::Projector2;

    /// k iterations from zero take k forward and k back projections (the first back projection of
    /// the data, then one per iteration but the last); a run that converges at its first iteration
    /// takes one of each. The image still fits the data: its residual falls below a tenth of ‖b‖.
    #[test]
    fn the_last_iteration_takes_no_back_projection() {
        let grid = ImageGrid::square(24, 1.0);
        let views = ParallelBeam {
            angles: Angles::uniform(30, 180.0),
            det_count: 35,
            det_spacing_mm: 1.0,
            det_offset_mm: 0.0,
        }
        .to_views()
        .unwrap();
        let projector = Projector2::new(&views, &grid);
        let truth: Vec<f32> = (0..grid.nx * grid.ny)
            .map(|i| ((i % 7) as f32 * 0.3).sin().abs())
            .collect();
        let mut b = vec![0.0f32; projector.view_count() * projector.view_len()];
        let all: Vec<usize> = (0..projector.view_count()).collect();
        projector
            .forward(&truth, &all, &mut b, &Cancel::new())
            .unwrap();
        for (iterations, tolerance, passes) in [(5, None, 5), (1, None, 1), (8, Some(0.99), 1)] {
            let counted = Counted::new(&projector);
            let mut x = vec![0.0f32; truth.len()];
            let params = CglsParams {
                iterations,
                tolerance,
                ..CglsParams::default()
            };
            let cancel = Cancel::new();
            cgls(
                &counted,
                &b,
                &mut x,
                &params,
                &Control::new(&cancel, &NoProgress),
            )
            .unwrap();
            let counts = counted.passes();
            assert_eq!(
                counts,
                (passes, passes),
                "{iterations} iterations, tolerance {tolerance:?}"
            );
            let mut r = vec![0.0f32; b.len()];
            projector.forward(&x, &all, &mut r, &cancel).unwrap();
            let misfit = r
                .iter()
                .zip(&b)
                .map(|(a, b)| f64::from(a - b).powi(2))
                .sum::<f64>();
            assert!(
                misfit.sqrt() < 0.1 * norm(&b),
                "{iterations} iterations: {misfit}"
            );
        }
    }
}
