//! Transfer functions: piecewise-linear colour and opacity over the volume's values, and the HU presets.
//!
//! Opacity is per millimetre of path: a sample step of Δ mm gets α' = 1 − (1 − α)^Δ. Below the first control
//! point and above the last one the end values hold. Presets (value HU → colour RGB 0–1, opacity per mm):
//!
//! | preset          | control points |
//! |-----------------|----------------|
//! | `bone`          | −1000 → (0, 0, 0) 0; 150 → (0.73, 0.25, 0.30) 0; 400 → (0.91, 0.82, 0.55) 0.6; 1500 → (1, 1, 1) 0.9 |
//! | `soft_tissue`   | −1000 → (0, 0, 0) 0; −600 → (0.55, 0.30, 0.20) 0; −300 → (0.85, 0.55, 0.45) 0.2; 100 → (0.95, 0.75, 0.65) 0.25; 1000 → (1, 1, 1) 0.3 |
//! | `ct_angiography`| −1000 → (0, 0, 0) 0; 100 → (0.60, 0.10, 0.10) 0; 200 → (0.90, 0.30, 0.20) 0.4; 400 → (1, 0.85, 0.70) 0.8; 1500 → (1, 1, 1) 0.9 |
//! | `lung`          | −1000 → (0, 0, 0) 0; −900 → (0.30, 0.30, 0.50) 0; −700 → (0.70, 0.60, 0.60) 0.08; −500 → (0.85, 0.70, 0.65) 0.1; −300 → (0.90, 0.75, 0.70) 0; 1000 → (0, 0, 0) 0 |

use serde::{Deserialize, Serialize};

use super::RenderError;

/// One control point: at `value` (volume units), colour `color` (RGB, 0–1) and opacity `opacity` per mm (0–1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlPoint {
    pub value: f64,
    pub color: [f64; 3],
    pub opacity: f64,
}

/// A piecewise-linear transfer function: control points in increasing value. JSON:
/// `{"points": [{"value": 150, "color": [0.7, 0.2, 0.3], "opacity": 0}, …]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferFunction {
    pub points: Vec<ControlPoint>,
}

/// The built-in transfer functions (values in HU; see the module table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    Bone,
    SoftTissue,
    CtAngiography,
    Lung,
}

impl Preset {
    pub const ALL: [Preset; 4] = [
        Preset::Bone,
        Preset::SoftTissue,
        Preset::CtAngiography,
        Preset::Lung,
    ];
    pub fn name(self) -> &'static str {
        match self {
            Preset::Bone => "bone",
            Preset::SoftTissue => "soft_tissue",
            Preset::CtAngiography => "ct_angiography",
            Preset::Lung => "lung",
        }
    }
    /// The preset's transfer function in HU.
    pub fn transfer_function(self) -> TransferFunction {
        let p = |value, color, opacity| ControlPoint {
            value,
            color,
            opacity,
        };
        let black = [0.0; 3];
        let points = match self {
            Preset::Bone => vec![
                p(-1000.0, black, 0.0),
                p(150.0, [0.73, 0.25, 0.30], 0.0),
                p(400.0, [0.91, 0.82, 0.55], 0.6),
                p(1500.0, [1.0, 1.0, 1.0], 0.9),
            ],
            Preset::SoftTissue => vec![
                p(-1000.0, black, 0.0),
                p(-600.0, [0.55, 0.30, 0.20], 0.0),
                p(-300.0, [0.85, 0.55, 0.45], 0.2),
                p(100.0, [0.95, 0.75, 0.65], 0.25),
                p(1000.0, [1.0, 1.0, 1.0], 0.3),
            ],
            Preset::CtAngiography => vec![
                p(-1000.0, black, 0.0),
                p(100.0, [0.60, 0.10, 0.10], 0.0),
                p(200.0, [0.90, 0.30, 0.20], 0.4),
                p(400.0, [1.0, 0.85, 0.70], 0.8),
                p(1500.0, [1.0, 1.0, 1.0], 0.9),
            ],
            Preset::Lung => vec![
                p(-1000.0, black, 0.0),
                p(-900.0, [0.30, 0.30, 0.50], 0.0),
                p(-700.0, [0.70, 0.60, 0.60], 0.08),
                p(-500.0, [0.85, 0.70, 0.65], 0.1),
                p(-300.0, [0.90, 0.75, 0.70], 0.0),
                p(1000.0, black, 0.0),
            ],
        };
        TransferFunction { points }
    }
}

impl TransferFunction {
    /// Checks: at least one point, finite values in increasing order, colours and opacities in [0, 1].
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.points.is_empty() {
            return Err(RenderError::EmptyTransferFunction);
        }
        let bad = |reason: &str| {
            Err(RenderError::InvalidParameter {
                name: "transfer_function",
                reason: reason.into(),
            })
        };
        if self.points.len() > 256 {
            return bad("at most 256 control points");
        }
        let unit = |v: f64| v.is_finite() && (0.0..=1.0).contains(&v);
        for p in &self.points {
            if !p.value.is_finite() || !unit(p.opacity) || !p.color.iter().all(|&c| unit(c)) {
                return bad("values must be finite, colours and opacities within [0, 1]");
            }
        }
        if self.points.windows(2).any(|w| w[1].value < w[0].value) {
            return bad("control points must be in increasing value");
        }
        Ok(())
    }

    /// The function with every value mapped by `f` (e.g. HU → μ); `f` must be increasing.
    pub fn map_values(&self, f: impl Fn(f64) -> f64) -> Self {
        Self {
            points: self
                .points
                .iter()
                .map(|p| ControlPoint {
                    value: f(p.value),
                    ..*p
                })
                .collect(),
        }
    }

    /// Colour and opacity per mm at `v` (linear between control points, constant beyond the ends).
    pub fn eval(&self, v: f64) -> ([f64; 3], f64) {
        let pts = &self.points;
        let Some(first) = pts.first() else {
            return ([0.0; 3], 0.0);
        };
        if v <= first.value {
            return (first.color, first.opacity);
        }
        let k = pts.partition_point(|p| p.value <= v);
        if k >= pts.len() {
            let last = pts[pts.len() - 1];
            return (last.color, last.opacity);
        }
        let (a, b) = (pts[k - 1], pts[k]);
        let t = if b.value > a.value {
            (v - a.value) / (b.value - a.value)
        } else {
            1.0
        };
        let lerp = |x: f64, y: f64| x + (y - x) * t;
        (
            std::array::from_fn(|c| lerp(a.color[c], b.color[c])),
            lerp(a.opacity, b.opacity),
        )
    }

    /// Largest opacity over the values `[lo, hi]`.
    pub fn max_opacity(&self, lo: f64, hi: f64) -> f64 {
        let mut m = self.eval(lo).1.max(self.eval(hi).1);
        for p in &self.points {
            if p.value > lo && p.value < hi {
                m = m.max(p.opacity);
            }
        }
        m
    }
}

/// A lookup table of a transfer function for one sample step: premultiplied-free colour and step opacity on
/// `LUT_SIZE` values between the first and last control points.
pub(crate) struct Lut {
    lo: f32,
    scale: f32,
    /// `[r, g, b, α_step]`.
    table: Vec<[f32; 4]>,
    /// Values below the first or above the second are transparent ([`Lut::get`] gives α = 0 there).
    visible: (f32, f32),
}

const LUT_SIZE: usize = 4096;

impl Lut {
    pub(crate) fn new(tf: &TransferFunction, step_mm: f64) -> Self {
        let lo = tf.points.first().map_or(0.0, |p| p.value);
        let hi = tf.points.last().map_or(1.0, |p| p.value).max(lo + 1e-6);
        let n = LUT_SIZE;
        let table = (0..n)
            .map(|i| {
                let v = lo + (hi - lo) * i as f64 / (n - 1) as f64;
                let (c, a) = tf.eval(v);
                let a = if a >= 1.0 {
                    1.0
                } else {
                    1.0 - (1.0 - a).powf(step_mm)
                };
                [c[0] as f32, c[1] as f32, c[2] as f32, a as f32]
            })
            .collect::<Vec<[f32; 4]>>();
        let scale = ((n - 1) as f64 / (hi - lo)) as f32;
        // `get` blends entries i and i + 1 at x = (v − lo)·scale: two entries of margin cover the rounding of x.
        let first = table.iter().position(|e| e[3] > 0.0);
        let last = table.iter().rposition(|e| e[3] > 0.0);
        let visible = match (first, last) {
            (Some(f), Some(l)) => (
                if f >= 2 {
                    lo as f32 + (f - 2) as f32 / scale
                } else {
                    f32::NEG_INFINITY
                },
                if l + 3 < n {
                    lo as f32 + (l + 2) as f32 / scale
                } else {
                    f32::INFINITY
                },
            ),
            _ => (f32::INFINITY, f32::NEG_INFINITY),
        };
        Self {
            lo: lo as f32,
            scale,
            table,
            visible,
        }
    }

    /// Whether `v` may have opacity: outside this window [`Lut::get`] gives α = 0.
    #[inline(always)]
    pub(crate) fn visible(&self, v: f32) -> bool {
        v >= self.visible.0 && v <= self.visible.1
    }

    /// The window of values that may have opacity (see [`Lut::visible`]), empty when none has.
    pub(crate) fn window(&self) -> Vec<(f32, f32)> {
        if self.visible.0 <= self.visible.1 {
            vec![self.visible]
        } else {
            Vec::new()
        }
    }

    /// `[r, g, b, α_step]` at `v`, linear between table entries.
    #[inline(always)]
    pub(crate) fn get(&self, v: f32) -> [f32; 4] {
        let x = ((v - self.lo) * self.scale).clamp(0.0, (self.table.len() - 1) as f32);
        let i = (x as usize).min(self.table.len() - 2);
        let t = x - i as f32;
        let (a, b) = (self.table[i], self.table[i + 1]);
        std::array::from_fn(|c| a[c] + (b[c] - a[c]) * t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_outside_the_visible_window_of_the_table_are_transparent() {
        for preset in Preset::ALL {
            let lut = Lut::new(&preset.transfer_function(), 0.35);
            let (mut seen_hidden, mut seen_visible) = (0, 0);
            for k in 0..200_000 {
                let v = -1200.0 + k as f32 * 0.0137;
                if lut.visible(v) {
                    seen_visible += 1;
                } else {
                    seen_hidden += 1;
                    assert_eq!(lut.get(v)[3], 0.0, "{} at {v}", preset.name());
                }
            }
            assert!(
                seen_hidden > 10_000 && seen_visible > 10_000,
                "{}",
                preset.name()
            );
        }
        let clear = TransferFunction {
            points: vec![ControlPoint {
                value: 0.0,
                color: [1.0; 3],
                opacity: 0.0,
            }],
        };
        let lut = Lut::new(&clear, 0.5);
        assert!(!lut.visible(0.0) && !lut.visible(-1e30) && !lut.visible(1e30));
    }
}
