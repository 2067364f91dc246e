//! Poisson (photon-counting) noise on line-integral data.

use ndarray::{ArrayViewMut, Axis, Dimension, RemoveAxis};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Poisson};
use rayon::prelude::*;

use crate::recon::error::{ReconError, ensure_finite};

/// Largest accepted number of incident photons per detector element.
pub const MAX_INCIDENT_PHOTONS: f64 = 1e15;

/// SplitMix64 finaliser: decorrelates the per-lane seeds derived from one user seed.
fn mix(seed: u64, lane: u64) -> u64 {
    let mut z = seed ^ lane.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn noisy(p: f32, i0: f64, rng: &mut StdRng) -> f32 {
    let lambda = i0 * (-(p as f64)).exp();
    let counts = match Poisson::new(lambda) {
        Ok(dist) => dist.sample(rng),
        // λ = 0 (total absorption): no photon arrives. λ beyond rand_distr's limit (only for strongly
        // negative p): the relative noise 1/√λ < 1e-9 is far below f32 resolution, keep the mean.
        Err(_) if lambda > 0.0 => lambda.round(),
        Err(_) => 0.0,
    };
    // A zero count has no logarithm: it is floored to one photon, so p ≤ ln I0.
    (i0.ln() - counts.max(1.0).ln()) as f32
}

/// Replace every line integral `p` of `projections` (any shape) by a noisy one: detected counts
/// `N ~ Poisson(I0·exp(−p))`, then `p ← −ln(max(N, 1)/I0)`. The floor at one photon keeps fully absorbed
/// rays finite (at most `ln I0`).
///
/// Deterministic for a given `seed`, independent of the number of threads: each index along the first
/// axis (a view) draws from its own generator seeded from `seed` and that index.
///
/// Errors: `incident_photons` not positive, not finite or above `MAX_INCIDENT_PHOTONS`
/// (`InvalidParameter`); a non-finite projection value (`NonFinite`), checked before anything changes.
pub fn poisson_noise<D: Dimension + RemoveAxis>(
    mut projections: ArrayViewMut<f32, D>,
    incident_photons: f64,
    seed: u64,
) -> Result<(), ReconError> {
    let i0 = incident_photons;
    if !(i0.is_finite() && i0 > 0.0 && i0 <= MAX_INCIDENT_PHOTONS) {
        return Err(ReconError::param(
            "incident_photons",
            format!("must be positive, finite and at most {MAX_INCIDENT_PHOTONS:e}, got {i0}"),
        ));
    }
    ensure_finite(projections.view())?;
    if projections.ndim() == 0 {
        let mut rng = StdRng::seed_from_u64(mix(seed, 0));
        for p in projections.iter_mut() {
            *p = noisy(*p, i0, &mut rng);
        }
        return Ok(());
    }
    projections
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(lane, mut sub)| {
            let mut rng = StdRng::seed_from_u64(mix(seed, lane as u64));
            for p in sub.iter_mut() {
                *p = noisy(*p, i0, &mut rng);
            }
        });
    Ok(())
}

#[cfg(test)]
mod tests {
    use ndarray::{Array2, Array3};

    use super::*;

    #[test]
    fn noisy_projections_average_to_the_noiseless_value() {
        // p = 1, I0 = 1e5: λ = 36 788, std(p̂) ≈ 1/√λ = 5.2e-3, bias ≈ 1/(2λ) = 1.4e-5.
        let mut p = Array2::<f32>::from_elem((200, 100), 1.0);
        poisson_noise(p.view_mut(), 1e5, 7).unwrap();
        let n = p.len() as f64;
        let mean = p.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = p.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / (n - 1.0);
        let lambda = 1e5 * (-1.0f64).exp();
        // Standard error of the mean: 5.2e-3/√20000 = 3.7e-5; allow 5 of them.
        assert!(
            (mean - 1.0).abs() < 5.0 * (1.0 / lambda / n).sqrt() + 1e-5,
            "mean {mean}"
        );
        // Sample variance of 20 000 draws is within 5 % of 1/λ.
        assert!(
            (var * lambda - 1.0).abs() < 0.05,
            "var·λ = {}",
            var * lambda
        );
    }

    #[test]
    fn the_same_seed_gives_the_same_noise_and_another_seed_does_not() {
        let clean = Array3::<f32>::from_shape_fn((8, 4, 16), |(i, j, k)| (i + j + k) as f32 * 0.1);
        let run = |seed| {
            let mut p = clean.clone();
            poisson_noise(p.view_mut(), 1e4, seed).unwrap();
            p
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
        assert_ne!(run(3), clean);
    }

    #[test]
    fn fully_absorbed_rays_are_floored_at_one_photon() {
        let mut p = Array2::<f32>::from_elem((1, 4), 1e4);
        poisson_noise(p.view_mut(), 1000.0, 1).unwrap();
        for v in p.iter() {
            assert!((*v as f64 - 1000f64.ln()).abs() < 1e-5);
        }
    }

    #[test]
    fn bad_photon_counts_and_non_finite_data_are_refused() {
        let mut p = Array2::<f32>::zeros((2, 2));
        for i0 in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e16] {
            assert!(matches!(
                poisson_noise(p.view_mut(), i0, 0),
                Err(ReconError::InvalidParameter {
                    name: "incident_photons",
                    ..
                })
            ));
        }
        p[[1, 0]] = f32::NAN;
        assert_eq!(
            poisson_noise(p.view_mut(), 1e3, 0),
            Err(ReconError::NonFinite { index: 2 })
        );
    }
}
