//! Gradient shading with a head light (the light comes from the eye): ambient, two-sided diffuse and
//! Blinn-Phong specular terms.

use serde::{Deserialize, Serialize};

use super::{RenderError, V3, dot, norm};

/// Shading coefficients. JSON: `{"ambient": 0.2, "diffuse": 0.7, "specular": 0.3, "shininess": 20}`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Shading {
    pub ambient: f64,
    pub diffuse: f64,
    pub specular: f64,
    pub shininess: f64,
}

impl Default for Shading {
    fn default() -> Self {
        Self {
            ambient: 0.2,
            diffuse: 0.7,
            specular: 0.3,
            shininess: 20.0,
        }
    }
}

impl Shading {
    /// No lighting: every sample shows its own colour.
    pub const FLAT: Shading = Shading {
        ambient: 1.0,
        diffuse: 0.0,
        specular: 0.0,
        shininess: 1.0,
    };

    pub fn validate(&self) -> Result<(), RenderError> {
        let ok = |v: f64| v.is_finite() && (0.0..=10.0).contains(&v);
        let shiny = self.shininess.is_finite() && (1.0..=1000.0).contains(&self.shininess);
        if !(ok(self.ambient) && ok(self.diffuse) && ok(self.specular) && shiny) {
            return Err(RenderError::InvalidParameter {
                name: "shading",
                reason: "coefficients within [0, 10] and shininess within [1, 1000]".into(),
            });
        }
        Ok(())
    }

    /// `(factor on the colour, white specular term)` for a surface with (unnormalised) normal `n` seen along
    /// unit direction `view`. A vanishing normal is lit as if it faced the light.
    #[inline]
    pub fn light(&self, n: V3, view: V3) -> (f32, f32) {
        let len = norm(n);
        let cos = if len > 1e-12 {
            (dot(n, view) / len).abs()
        } else {
            1.0
        };
        (
            (self.ambient + self.diffuse * cos) as f32,
            (self.specular * cos.powf(self.shininess)) as f32,
        )
    }
}

/// [`Shading::light`] prepared for one rendering, in single precision: the specular power comes from a table of
/// `cos^shininess` (linear between entries; exact at 0 and 1) when the shininess is at most [`TABLE_SHININESS`].
pub(crate) struct Lighting {
    ambient: f32,
    diffuse: f32,
    specular: f32,
    shininess: f32,
    /// `specular · cos^shininess` at `cos = i / (len − 1)`; empty when the power is computed.
    table: Vec<f32>,
}

/// Largest shininess looked up in a table: the linear interpolation error is at most
/// `s(s − 1) / (8 (len − 1)²)` ≈ 3 · 10⁻⁵ of the specular coefficient at 64.
const TABLE_SHININESS: f64 = 64.0;
const TABLE_LEN: usize = 4097;

impl Lighting {
    pub(crate) fn new(sh: &Shading) -> Self {
        let table = if sh.shininess <= TABLE_SHININESS {
            (0..TABLE_LEN)
                .map(|i| {
                    (sh.specular * (i as f64 / (TABLE_LEN - 1) as f64).powf(sh.shininess)) as f32
                })
                .collect()
        } else {
            Vec::new()
        };
        Self {
            ambient: sh.ambient as f32,
            diffuse: sh.diffuse as f32,
            specular: sh.specular as f32,
            shininess: sh.shininess as f32,
            table,
        }
    }

    /// `(factor on the colour, white specular term)` as [`Shading::light`] gives them for the (unnormalised)
    /// normal `n` and unit direction `view`.
    #[inline(always)]
    pub(crate) fn light(&self, n: [f32; 3], view: [f32; 3]) -> (f32, f32) {
        let len2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
        let cos = if len2 > 1e-24 {
            ((n[0] * view[0] + n[1] * view[1] + n[2] * view[2]).abs() / len2.sqrt()).min(1.0)
        } else {
            1.0
        };
        let spec = if self.table.is_empty() {
            self.specular * cos.powf(self.shininess)
        } else {
            let x = cos * (TABLE_LEN - 1) as f32;
            let i = (x as usize).min(TABLE_LEN - 2);
            let f = x - i as f32;
            let (a, b) = (self.table[i], self.table[i + 1]);
            a + (b - a) * f
        };
        (self.ambient + self.diffuse * cos, spec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_precision_lighting_matches_the_reference_within_a_tenth_of_a_grey_level() {
        for sh in [
            Shading::default(),
            Shading {
                specular: 10.0,
                shininess: 64.0,
                ..Shading::default()
            },
            Shading {
                specular: 2.0,
                shininess: 300.0,
                ..Shading::default()
            },
        ] {
            let l = Lighting::new(&sh);
            for q in 0..5000u32 {
                let h = |m: u32| (q.wrapping_mul(m) % 2001) as f64 / 1000.0 - 1.0;
                let n = [h(7919), h(104729), h(1299709)];
                let view = [0.0, 0.6, 0.8];
                let (lit, spec) = sh.light(n, view);
                let nf = n.map(|c| c as f32);
                let vf = view.map(|c| c as f32);
                let (lit2, spec2) = l.light(nf, vf);
                assert!(
                    (lit - lit2).abs() < 1e-5,
                    "{sh:?} {n:?}: lit {lit} vs {lit2}"
                );
                assert!(
                    (spec - spec2).abs() < 0.1 / 255.0,
                    "{sh:?} {n:?}: specular {spec} vs {spec2}"
                );
            }
        }
    }
}
