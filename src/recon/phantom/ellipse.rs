//! 2D phantoms: ellipses in phantom units, their rasterisation on an [`ImageGrid`] and their exact
//! projection for any 2D geometry in canonical form ([`Views2`]).

use ndarray::{Array2, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::quadric::{Quadric, fill_row};
use super::{MAX_BODIES, Table2, check_scale, finite_field, positive_field};
use crate::recon::error::ReconError;
use crate::recon::geometry::{Vec2, Views2};
use crate::recon::grid::ImageGrid;

/// One filled ellipse in phantom units (the square [−1, 1]², scaled by the phantom's `scale_mm`).
///
/// A point `(x, y)` (phantom units) is inside when `x'²/a² + y'²/b² ≤ 1` with
/// `x' = (x − x0) cos φ + (y − y0) sin φ`, `y' = −(x − x0) sin φ + (y − y0) cos φ`: the `a` axis is turned
/// by φ counter-clockwise from +x toward +y about the (unrotated) centre `(x0, y0)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ellipse {
    /// Additive attenuation μ (1/mm); overlapping ellipses add.
    pub value: f64,
    /// Semi-axis along the ellipse's own x axis (phantom units, > 0).
    pub a: f64,
    /// Semi-axis along the ellipse's own y axis (phantom units, > 0).
    pub b: f64,
    /// Centre (phantom units).
    #[serde(default)]
    pub x0: f64,
    #[serde(default)]
    pub y0: f64,
    /// Rotation of the `a` axis from +x toward +y (degrees).
    #[serde(default)]
    pub phi_deg: f64,
}

impl Ellipse {
    /// Refuse non-finite values and non-positive semi-axes; `index` names the ellipse in the error.
    pub fn validate(&self, index: usize) -> Result<(), ReconError> {
        let what = |field| format!("ellipse {index}: `{field}`");
        finite_field("ellipses", &what("value"), self.value)?;
        positive_field("ellipses", &what("a"), self.a)?;
        positive_field("ellipses", &what("b"), self.b)?;
        finite_field("ellipses", &what("x0"), self.x0)?;
        finite_field("ellipses", &what("y0"), self.y0)?;
        finite_field("ellipses", &what("phi_deg"), self.phi_deg)?;
        Ok(())
    }

    /// The ellipse in millimetres for a phantom scale of `scale_mm`.
    pub(crate) fn quadric(&self, scale_mm: f64) -> Quadric<2> {
        let (s, c) = self.phi_deg.to_radians().sin_cos();
        let (a, b, k) = (self.a, self.b, scale_mm);
        Quadric {
            // diag(1/a, 1/b) · Rᵀ / scale
            m: [[c / (a * k), s / (a * k)], [-s / (b * k), c / (b * k)]],
            q0: [
                (c * self.x0 + s * self.y0) / a,
                (-s * self.x0 + c * self.y0) / b,
            ],
            // scale · R · diag(a, b)
            m_inv: [[k * c * a, -k * s * b], [k * s * a, k * c * b]],
            value: self.value,
        }
    }
}

/// A 2D phantom: a list of ellipses in phantom units and the scale that maps them to millimetres.
///
/// A point at `(x, y)` mm sits at `(x, y) / scale_mm` in phantom units, so `scale_mm` is half the side of
/// the square field of view that the unit square covers. Values are μ in 1/mm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Phantom2 {
    pub ellipses: Vec<Ellipse>,
    /// Millimetres per phantom unit (> 0).
    pub scale_mm: f64,
}

impl Phantom2 {
    /// A validated phantom from a user list of ellipses.
    pub fn new(ellipses: Vec<Ellipse>, scale_mm: f64) -> Result<Self, ReconError> {
        let p = Self { ellipses, scale_mm };
        p.validate()?;
        Ok(p)
    }

    /// A named table scaled by `scale_mm` (a positive, finite number of millimetres per phantom unit;
    /// call [`Phantom2::validate`] when it comes from outside).
    pub fn from_table(table: Table2, scale_mm: f64) -> Self {
        Self {
            ellipses: table.ellipses(),
            scale_mm,
        }
    }

    /// Check the scale, the number of ellipses and every ellipse.
    pub fn validate(&self) -> Result<(), ReconError> {
        check_scale(self.scale_mm)?;
        if self.ellipses.len() > MAX_BODIES {
            return Err(ReconError::param(
                "ellipses",
                format!("at most {MAX_BODIES} ellipses, got {}", self.ellipses.len()),
            ));
        }
        for (i, e) in self.ellipses.iter().enumerate() {
            e.validate(i)?;
        }
        Ok(())
    }

    pub(crate) fn quadrics(&self) -> Vec<Quadric<2>> {
        self.ellipses
            .iter()
            .map(|e| e.quadric(self.scale_mm))
            .collect()
    }

    /// μ (1/mm) at the point `(x_mm, y_mm)`: the sum of the values of the ellipses that contain it.
    pub fn value_at(&self, x_mm: f64, y_mm: f64) -> f64 {
        self.quadrics()
            .iter()
            .filter(|q| {
                let u = q.unit_frame(&[x_mm, y_mm]);
                u[0] * u[0] + u[1] * u[1] <= 1.0
            })
            .map(|q| q.value)
            .sum()
    }

    /// Exact line integral of μ along the whole line `origin + λ·direction` (mm, `direction` a unit
    /// vector): Σ value × chord length (mm), dimensionless.
    pub fn line_integral(&self, origin: Vec2, direction: Vec2) -> f64 {
        self.quadrics()
            .iter()
            .map(|q| q.line_integral(&origin, &direction))
            .sum()
    }

    /// The phantom sampled on `grid`, shape `[ny][nx]`: each pixel is the mean of `supersample ×
    /// supersample` point samples spread evenly over the pixel (`supersample` 0 counts as 1; 1 samples
    /// the pixel centre). Rows run in parallel.
    pub fn rasterize(&self, grid: &ImageGrid, supersample: usize) -> Array2<f32> {
        let s = supersample.max(1);
        let bodies = self.quadrics();
        let mut out = Array2::<f32>::zeros(grid.shape());
        let hx = grid.dx_mm / s as f64;
        // Position of the first sub-sample of the row.
        let x_start = grid.x(0) - grid.dx_mm / 2.0 + hx / 2.0;
        let norm = 1.0 / (s * s) as f64;
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(j, mut row)| {
                let mut buf = vec![0.0f64; grid.nx * s];
                let mut acc = vec![0.0f64; grid.nx];
                for my in 0..s {
                    let y = grid.y(j) + ((my as f64 + 0.5) / s as f64 - 0.5) * grid.dy_mm;
                    buf.fill(0.0);
                    fill_row(&bodies, &[x_start, y], hx, &mut buf);
                    for (a, chunk) in acc.iter_mut().zip(buf.chunks_exact(s)) {
                        *a += chunk.iter().sum::<f64>();
                    }
                }
                for (o, a) in row.iter_mut().zip(&acc) {
                    *o = (a * norm) as f32;
                }
            });
        out
    }

    /// Exact projections, shape `[views][detector elements]`: element `[i][k]` is the line integral of μ
    /// along `views.ray(view i, k)` (the whole line through the source and the element; the phantom is
    /// assumed to lie between them). Works for every 2D geometry: parallel, fan arc, fan flat. Views run
    /// in parallel.
    pub fn project(&self, views: &Views2) -> Array2<f32> {
        let bodies = self.quadrics();
        let mut out = Array2::<f32>::zeros(views.shape());
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(views.views.par_iter())
            .for_each(|(mut row, view)| {
                for (k, o) in row.iter_mut().enumerate() {
                    let ray = views.ray(view, k);
                    let p: f64 = bodies
                        .iter()
                        .map(|q| q.line_integral(&ray.origin, &ray.direction))
                        .sum();
                    *o = p as f32;
                }
            });
        out
    }
}
