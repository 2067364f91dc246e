//! ART (Kaczmarz): x ← x + λ (b_i − a_i·x)/‖a_i‖² a_i, one ray at a time.

use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::ops::{constrain, report};
use super::params::ArtParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

/// Seed of the shuffled ray order (fixed: results are reproducible).
pub const SHUFFLE_SEED: u64 = 0x5eed_a127;

/// Run ART from `x` (overwritten). Rays are visited view by view and element by element, or in one
/// shuffled order (fixed seed) used for every sweep. Non-negativity is applied after each sweep. The
/// residual reported with sweep `k` is accumulated over the sweep, each ray measured just before its
/// update. Cancel is checked every `view_len` rays.
pub fn art(
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    p: &ArtParams,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    let m = op.view_len();
    let n_rays = op.view_count() * m;
    let mut order: Vec<u32> = (0..n_rays as u32).collect();
    if p.shuffle {
        order.shuffle(&mut StdRng::seed_from_u64(SHUFFLE_SEED));
    }
    let mut inv_norm2 = vec![0.0f32; n_rays];
    for (i, v) in inv_norm2.iter_mut().enumerate() {
        if i % m == 0 {
            ctl.check()?;
        }
        let n2 = op.ray_norm2(i / m, i % m);
        *v = if n2 > 0.0 { 1.0 / n2 } else { 0.0 };
    }
    let lambda = p.relaxation as f32;
    constrain(x, p.bounds());
    for k in 1..=p.iterations {
        let mut sum2 = 0.0f64;
        for (c, &i) in order.iter().enumerate() {
            if c % m == 0 {
                ctl.check()?;
            }
            let i = i as usize;
            if inv_norm2[i] == 0.0 {
                continue;
            }
            let (view, e) = (i / m, i % m);
            let r = b[i] - op.ray_dot(view, e, x);
            sum2 += r as f64 * r as f64;
            op.ray_axpy(view, e, lambda * r * inv_norm2[i], x);
        }
        constrain(x, p.bounds());
        report(ctl, "art", k, p.iterations, sum2.sqrt());
    }
    Ok(())
}
