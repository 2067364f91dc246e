//! Vector helpers shared by the iterative methods: dot products in f64, axpy, safe reciprocals, ordered
//! subsets, constraints and progress reports.

use rayon::prelude::*;

use super::params::Bounds;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

const CHUNK: usize = 1 << 14;

/// ⟨a, b⟩ accumulated in f64.
pub fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| {
            x.iter()
                .zip(y)
                .map(|(p, q)| *p as f64 * *q as f64)
                .sum::<f64>()
        })
        .sum()
}

/// ‖a‖₂ accumulated in f64.
pub fn norm(a: &[f32]) -> f64 {
    dot(a, a).sqrt()
}

/// `y ← y + alpha·x`.
pub fn axpy(y: &mut [f32], alpha: f32, x: &[f32]) {
    y.par_chunks_mut(CHUNK)
        .zip(x.par_chunks(CHUNK))
        .for_each(|(y, x)| {
            for (p, q) in y.iter_mut().zip(x) {
                *p += alpha * q;
            }
        });
}

/// `out ← b − out` (turns a forward projection into a residual).
pub fn residual_in_place(out: &mut [f32], b: &[f32]) {
    out.par_chunks_mut(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .for_each(|(o, b)| {
            for (p, q) in o.iter_mut().zip(b) {
                *p = q - *p;
            }
        });
}

/// Element-wise reciprocal with a floor: values at most [`reciprocal_floor`] of the largest (rays or
/// pixels that the geometry barely touches) map to 0, so they are left alone instead of blowing up.
pub fn safe_reciprocal(v: &mut [f32]) {
    let max = v.iter().fold(0.0f32, |m, &x| m.max(x));
    let floor = reciprocal_floor(max);
    v.par_iter_mut()
        .for_each(|x| *x = if *x > floor { 1.0 / *x } else { 0.0 });
}

/// The floor of [`safe_reciprocal`] for values whose largest is `max`: `1e-6 × max`.
pub fn reciprocal_floor(max: f32) -> f32 {
    max * 1e-6
}

/// Clamp every value into `bounds`.
pub fn constrain(x: &mut [f32], bounds: Bounds) {
    if !bounds.is_none() {
        x.par_iter_mut().for_each(|v| *v = bounds.clamp(*v));
    }
}

/// `count` interleaved ordered subsets of `views` views: subset `s` holds views `s, s + count, …`.
pub fn subsets(views: usize, count: usize) -> Vec<Vec<usize>> {
    (0..count)
        .map(|s| (s..views).step_by(count).collect())
        .collect()
}

/// The data values of `subset` gathered view after view from `b` (`view_len` values per view).
pub fn gather(b: &[f32], subset: &[usize], view_len: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(subset.len() * view_len);
    for &v in subset {
        out.extend_from_slice(&b[v * view_len..(v + 1) * view_len]);
    }
    out
}

/// `out` = A x over `subset`, without projecting where `x` is all zeros (the usual start of the
/// iterative methods): every projector is linear, so A·0 is exactly zero there.
pub fn forward_from(
    op: &dyn Operator,
    x: &[f32],
    subset: &[usize],
    out: &mut [f32],
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    if x.par_iter().all(|v| *v == 0.0) {
        out.par_iter_mut().for_each(|v| *v = 0.0);
        return Ok(());
    }
    op.forward(x, subset, out, ctl.cancel)
}

/// A ∘ 1 over `subset` (row sums of the rows of those views).
pub fn row_sums(
    op: &dyn Operator,
    subset: &[usize],
    ctl: &Control<'_>,
) -> Result<Vec<f32>, ReconError> {
    let ones = vec![1.0f32; op.image_len()];
    let mut out = vec![0.0f32; subset.len() * op.view_len()];
    op.forward(&ones, subset, &mut out, ctl.cancel)?;
    Ok(out)
}

/// Aᵀ ∘ 1 over `subset` (column sums of the rows of those views).
pub fn column_sums(
    op: &dyn Operator,
    subset: &[usize],
    ctl: &Control<'_>,
) -> Result<Vec<f32>, ReconError> {
    let ones = vec![1.0f32; subset.len() * op.view_len()];
    let mut out = vec![0.0f32; op.image_len()];
    op.back(&ones, subset, &mut out, ctl.cancel)?;
    Ok(out)
}

/// Report iteration `k` of `n` with its residual ‖Ax − b‖.
pub fn report(ctl: &Control<'_>, stage: &str, k: usize, n: usize, residual: f64) {
    ctl.progress
        .report(stage, k as f64 / n.max(1) as f64, Some(k), Some(residual));
}

/// True when a tolerance is set and the relative residual has reached it.
pub fn converged(tolerance: Option<f64>, residual: f64, b_norm: f64) -> bool {
    match tolerance {
        Some(t) => b_norm > 0.0 && residual / b_norm < t || residual == 0.0,
        None => false,
    }
}

/// `x ← x + lambda·c∘g` (a diagonally preconditioned step).
pub fn axpy_scaled(x: &mut [f32], lambda: f32, c: &[f32], g: &[f32]) {
    x.par_chunks_mut(CHUNK)
        .zip(c.par_chunks(CHUNK).zip(g.par_chunks(CHUNK)))
        .for_each(|(x, (c, g))| {
            for ((x, c), g) in x.iter_mut().zip(c).zip(g) {
                *x += lambda * c * g;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::control::{Cancel, NoProgress};
    use crate::recon::projector::Projector3;
    use crate::recon::projector::cone_columns::tests::{cone, grid};

    #[test]
    fn forward_from_zeros_is_the_projection_of_zeros_bit_for_bit() {
        // The small cone beam and grid of the column pair's tests.
        let (views, grid) = (cone(false), grid());
        let op = Projector3::new(&views, &grid);
        let (cancel, all) = (Cancel::new(), (0..op.view_count()).collect::<Vec<_>>());
        let ctl = Control::new(&cancel, &NoProgress);
        let n = op.image_len();
        let images = [
            vec![0.0f32; n],
            vec![-0.0f32; n],
            (0..n).map(|i| ((i * 37) % 11) as f32 * 0.1).collect(),
        ];
        for (k, x) in images.iter().enumerate() {
            let mut want = vec![f32::NAN; all.len() * op.view_len()];
            op.forward(x, &all, &mut want, &cancel).unwrap();
            let mut got = vec![f32::NAN; want.len()];
            forward_from(&op, x, &all, &mut got, &ctl).unwrap();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "image {k}");
            // The zero images project to zeros; the third one does not.
            assert_eq!(want.iter().all(|v| *v == 0.0), k < 2, "image {k}");
        }
    }
}
