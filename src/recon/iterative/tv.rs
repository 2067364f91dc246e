//! Total-variation regularised reconstruction for sparse-view data: each outer iteration is one
//! OS-SART pass (data consistency) followed by the proximal step of the isotropic TV semi-norm,
//! x ← argmin_u ½‖u − x‖² + w·TV(u) (with u ≥ 0 when non-negative), solved by the fast gradient
//! projection of Beck & Teboulle (2009) on the dual. TV uses forward differences along every axis of
//! more than one sample (2D images: x, y; volumes: x, y, z).

use rayon::prelude::*;

use super::ops::{constrain, report};
use super::params::TvParams;
use super::sart::Sweep;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// The automatic TV weight is this fraction of the 99th percentile of |x| after the first data pass.
pub const AUTO_WEIGHT_FRACTION: f64 = 0.01;

/// Shape `[nz, ny, nx]` of the image (`nz = 1` for 2D).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shape3 {
    pub nz: usize,
    pub ny: usize,
    pub nx: usize,
}

impl Shape3 {
    fn len(&self) -> usize {
        self.nz * self.ny * self.nx
    }
    /// (stride, size) of every axis with more than one sample.
    fn axes(&self) -> Vec<(usize, usize)> {
        [
            (1, self.nx),
            (self.nx, self.ny),
            (self.nx * self.ny, self.nz),
        ]
        .into_iter()
        .filter(|&(_, n)| n > 1)
        .collect()
    }
}

/// Coordinate along an axis of (stride, size) of flat index `i`.
#[inline]
fn coord(i: usize, stride: usize, n: usize) -> usize {
    (i / stride) % n
}

const ROW: usize = 4096;

/// out = P_C(v − w·Dᵀ q).
fn primal(
    v: &[f32],
    q: &[Vec<f32>],
    axes: &[(usize, usize)],
    w: f32,
    nonneg: bool,
    out: &mut [f32],
) {
    out.par_chunks_mut(ROW).enumerate().for_each(|(blk, o)| {
        let off = blk * ROW;
        for (k, ov) in o.iter_mut().enumerate() {
            let i = off + k;
            let mut dt = 0.0f32;
            for (a, &(s, n)) in axes.iter().enumerate() {
                let c = coord(i, s, n);
                if c > 0 {
                    dt += q[a][i - s];
                }
                if c + 1 < n {
                    dt -= q[a][i];
                }
            }
            let val = v[i] - w * dt;
            *ov = if nonneg { val.max(0.0) } else { val };
        }
    });
}

#[allow(clippy::needless_range_loop)] // j indexes several component blocks at once
/// The proximal map of w·TV at `v` (with u ≥ 0 when `nonneg`), `iterations` FGP steps.
pub fn prox_tv(v: &[f32], shape: Shape3, w: f32, iterations: usize, nonneg: bool) -> Vec<f32> {
    let n = shape.len();
    let axes = shape.axes();
    let mut x = v.to_vec();
    if w <= 0.0 || axes.is_empty() {
        if nonneg {
            x.iter_mut().for_each(|u| *u = u.max(0.0));
        }
        return x;
    }
    let k = axes.len();
    let step = 1.0 / (4.0 * k as f32 * w);
    let mut p = vec![vec![0.0f32; n]; k];
    let mut r = p.clone();
    let mut t = 1.0f32;
    for _ in 0..iterations {
        primal(v, &r, &axes, w, nonneg, &mut x);
        // p_new = P_ball(r + step·D x), then r = p_new + ((t−1)/t_new)(p_new − p).
        let t_new = (1.0 + (1.0 + 4.0 * t * t).sqrt()) / 2.0;
        let mom = (t - 1.0) / t_new;
        let mut p_new = vec![vec![0.0f32; n]; k];
        {
            let xs = &x;
            let rs = &r;
            let axes = &axes;
            // Split every component into the same blocks and process them together.
            let mut comps: Vec<std::slice::ChunksMut<'_, f32>> =
                p_new.iter_mut().map(|c| c.chunks_mut(ROW)).collect();
            let mut blocks: Vec<Vec<&mut [f32]>> = Vec::new();
            loop {
                let mut blk = Vec::with_capacity(k);
                for c in comps.iter_mut() {
                    match c.next() {
                        Some(b) => blk.push(b),
                        None => break,
                    }
                }
                if blk.len() < k {
                    break;
                }
                blocks.push(blk);
            }
            blocks
                .into_par_iter()
                .enumerate()
                .for_each(|(bi, mut blk)| {
                    let off = bi * ROW;
                    let len = blk[0].len();
                    let mut g = [0.0f32; 3];
                    for j in 0..len {
                        let i = off + j;
                        let mut nrm = 0.0f32;
                        for (a, &(s, nn)) in axes.iter().enumerate() {
                            let d = if coord(i, s, nn) + 1 < nn {
                                xs[i + s] - xs[i]
                            } else {
                                0.0
                            };
                            g[a] = rs[a][i] + step * d;
                            nrm += g[a] * g[a];
                        }
                        let scale = if nrm > 1.0 { 1.0 / nrm.sqrt() } else { 1.0 };
                        for a in 0..k {
                            blk[a][j] = g[a] * scale;
                        }
                    }
                });
        }
        for a in 0..k {
            for ((rv, pn), po) in r[a].iter_mut().zip(&p_new[a]).zip(&p[a]) {
                *rv = pn + mom * (pn - po);
            }
        }
        p = p_new;
        t = t_new;
    }
    primal(v, &p, &axes, w, nonneg, &mut x);
    x
}

/// The 99th percentile of |x|.
fn robust_max(x: &[f32]) -> f32 {
    if x.is_empty() {
        return 0.0;
    }
    let mut a: Vec<f32> = x.iter().map(|v| v.abs()).collect();
    let k = ((a.len() - 1) as f64 * 0.99) as usize;
    let (_, v, _) = a.select_nth_unstable_by(k, |p, q| p.total_cmp(q));
    *v
}

/// Run the TV method from `x` (overwritten). The residual reported with iteration `k` is that of its
/// OS-SART pass (accumulated over the pass, before the TV step).
pub fn tv(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &TvParams,
    shape: Shape3,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let mut sweep = Sweep::new(op, p.subsets, ctl)?;
    let mut w = p.tv_weight as f32;
    for k in 1..=p.iterations {
        let res = sweep.run(op, b, x, 1.0, p.bounds(), ctl)?;
        if k == 1 && p.tv_weight == 0.0 {
            w = (AUTO_WEIGHT_FRACTION * robust_max(x) as f64) as f32;
        }
        ctl.check()?;
        let y = prox_tv(x, shape, w, p.tv_iterations, p.nonnegative);
        x.copy_from_slice(&y);
        constrain(x, p.bounds());
        report(ctl, "tv", k, p.iterations, res);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tv_prox_keeps_a_constant_image_and_flattens_noise() {
        let shape = Shape3 {
            nz: 1,
            ny: 16,
            nx: 16,
        };
        let c = vec![0.7f32; 256];
        let out = prox_tv(&c, shape, 0.1, 50, true);
        assert!(out.iter().all(|v| (v - 0.7).abs() < 1e-5));
        // A checkerboard of ±0.05 around 0.5 with a large weight collapses to its mean.
        let v: Vec<f32> = (0..256)
            .map(|i| {
                0.5 + if (i / 16 + i % 16) % 2 == 0 {
                    0.05
                } else {
                    -0.05
                }
            })
            .collect();
        let out = prox_tv(&v, shape, 1.0, 200, false);
        let worst = out.iter().fold(0.0f32, |m, u| m.max((u - 0.5).abs()));
        assert!(worst < 2e-3, "{worst}");
    }
}
