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
