//! Beam-hardening linearisation: `p' = Σ_k a_k p^k` (k from 0), as a water pre-correction with given
//! coefficients (`[0, 1, 0.05]` bends the measured line integrals up where the beam has hardened).

use ndarray::ArrayViewMut2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;

/// Most coefficients a polynomial takes.
pub const MAX_DEGREE: usize = 16;

/// The linearisation polynomial. JSON: `{"coefficients": [0, 1, 0.05]}` (a₀, a₁, a₂, …).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Linearise {
    pub coefficients: Vec<f64>,
}

impl Linearise {
    fn check(&self) -> Result<(), ReconError> {
        let n = self.coefficients.len();
        if n == 0 || n > MAX_DEGREE + 1 {
            return Err(ReconError::param(
                "coefficients",
                format!("between 1 and {} coefficients, got {n}", MAX_DEGREE + 1),
            ));
        }
        if self.coefficients.iter().any(|a| !a.is_finite()) {
            return Err(ReconError::param("coefficients", "must be finite"));
        }
        Ok(())
    }

    /// `p'` of one value (Horner, in f64).
    pub fn value(&self, p: f32) -> f32 {
        let p = p as f64;
        self.coefficients
            .iter()
            .rev()
            .fold(0.0, |acc, a| acc * p + a) as f32
    }

    /// Linearise a view (or any 2D block) in place.
    pub fn apply_view(&self, mut data: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        self.check()?;
        data.axis_iter_mut(ndarray::Axis(0))
            .into_par_iter()
            .for_each(|mut row| row.mapv_inplace(|p| self.value(p)));
        Ok(())
    }
}
