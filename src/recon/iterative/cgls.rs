//! CGLS: conjugate gradients on the normal equations AᵀA x = Aᵀ b, without forming AᵀA; with a
//! back projector B that is not Aᵀ ([`BackProjector::Voxel`]), conjugate gradients on B A x = B b
//! ([`cg_normal`]).

use super::ops::{axpy, converged, dot, forward_from, norm, report, residual_in_place};
use super::params::{BackProjector, CglsParams};
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Run CGLS from `x` (overwritten). The residual reported with iteration `k` is ‖A x_k − b‖, which
/// CGLS decreases monotonically. Stops early when the search direction vanishes (exact solution).
/// With [`BackProjector::Voxel`], `op`'s back side is that back projector and [`cg_normal`] runs.
pub fn cgls(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &CglsParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    if p.back_projector == BackProjector::Voxel {
        return cg_normal(op, b, x, p, ctl);
    }
    let Start {
        all,
        b_norm,
        mut r,
        mut s,
        mut dir,
        mut gamma,
    } = Start::new(op, b, x, ctl)?;
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
        let res = norm(&r);
        // x is final after the last iteration or on convergence: the back projection below only
        // prepares the next direction, so it is skipped then (ten iterations take ten forward and
        // ten back projections in all, not eleven back projections).
        if k == p.iterations || converged(p.tolerance, res, b_norm) {
            report(ctl, "cgls", k, p.iterations, res);
            break;
        }
        op.back(&r, &all, &mut s, ctl.cancel)?;
        let gamma_new = dot(&s, &s);
        let beta = (gamma_new / gamma) as f32;
        gamma = gamma_new;
        turn(&mut dir, &s, beta);
        report(ctl, "cgls", k, p.iterations, res);
    }
    Ok(())
}

/// What both iterations start from: every view, ‖b‖, the data residual r = b − A x, the back-projected
/// residual s = B r, the first direction (s) and ⟨s, s⟩.
struct Start {
    all: Vec<usize>,
    b_norm: f64,
    r: Vec<f32>,
    s: Vec<f32>,
    dir: Vec<f32>,
    gamma: f64,
}

impl Start {
    fn new(op: &dyn Operator, b: &[f32], x: &[f32], ctl: &Control<'_>) -> Result<Self, ReconError> {
        let all: Vec<usize> = (0..op.view_count()).collect();
        let b_norm = norm(b);
        let mut r = vec![0.0f32; b.len()];
        forward_from(op, x, &all, &mut r, ctl)?;
        residual_in_place(&mut r, b);
        let mut s = vec![0.0f32; x.len()];
        op.back(&r, &all, &mut s, ctl.cancel)?;
        Ok(Start {
            all,
            b_norm,
            dir: s.clone(),
            gamma: dot(&s, &s),
            r,
            s,
        })
    }
}

/// The next direction: `dir = s + beta·dir`.
fn turn(dir: &mut [f32], s: &[f32], beta: f32) {
    for (d, sv) in dir.iter_mut().zip(s) {
        *d = sv + beta * *d;
    }
}

/// Conjugate gradients on B A x = B b, with `op`'s back side as B (RTK's conjugate gradient filter):
/// the step is ⟨s, s⟩ / ⟨d, B A d⟩ for the residual s = B (b − A x) and the direction d. Where B = Aᵀ
/// this is CGLS in exact arithmetic; where B is only close to Aᵀ up to a positive factor, B A is
/// not symmetric and the iterates are no longer the least-squares ones, which is why it is an option
/// and not the default. Each iteration takes one forward and one back projection, and one back
/// projection of the data before the first. Reports ‖A x_k − b‖ like CGLS (no longer monotone) and
/// stops on the same tolerance, or where a step would not be positive.
fn cg_normal(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &CglsParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let Start {
        all,
        b_norm,
        mut r,
        mut s,
        mut dir,
        mut gamma,
    } = Start::new(op, b, x, ctl)?;
    let mut q = vec![0.0f32; b.len()];
    let mut z = vec![0.0f32; x.len()];
    for k in 1..=p.iterations {
        ctl.check()?;
        if gamma <= 0.0 {
            report(ctl, "cgls", k, p.iterations, norm(&r));
            break;
        }
        op.forward(&dir, &all, &mut q, ctl.cancel)?;
        op.back(&q, &all, &mut z, ctl.cancel)?;
        let curvature = dot(&dir, &z);
        if curvature <= 0.0 || !curvature.is_finite() {
            report(ctl, "cgls", k, p.iterations, norm(&r));
            break;
        }
        let alpha = (gamma / curvature) as f32;
        axpy(x, alpha, &dir);
        axpy(&mut r, -alpha, &q);
        axpy(&mut s, -alpha, &z);
        let res = norm(&r);
        if k == p.iterations || converged(p.tolerance, res, b_norm) {
            report(ctl, "cgls", k, p.iterations, res);
            break;
        }
        let gamma_new = dot(&s, &s);
        let beta = (gamma_new / gamma) as f32;
        gamma = gamma_new;
        turn(&mut dir, &s, beta);
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
