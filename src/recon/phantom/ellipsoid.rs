//! 3D phantoms: ellipsoids with the seed program's Euler convention, their voxelisation on a
//! [`VolumeGrid`] and their exact cone-beam ([`Views3`]) and 3D parallel-beam ([`SliceViews`]) projections.

use ndarray::{Array3, ArrayViewMut2, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::quadric::{Quadric, fill_row, mapped_interval, mul};
use super::{MAX_BODIES, Table3, check_scale, finite_field, positive_field};
use crate::recon::control::{Control, unattended};
use crate::recon::error::ReconError;
use crate::recon::geometry::vectors::{add3, dot3, norm3, scale3, sub3};
use crate::recon::geometry::{Detector2, PanelShape, SliceViews, Vec3, View3, Views3};
use crate::recon::grid::VolumeGrid;

/// One filled ellipsoid in phantom units (the cube [−1, 1]³, scaled by the phantom's `scale_mm`), as in
/// the seed program `phantom3d`: a point `p` (phantom units) is inside when
/// `((αp)₀ − x0)²/a² + ((αp)₁ − y0)²/b² + ((αp)₂ − z0)²/c² ≤ 1` with α = [`euler_matrix`]`(φ, θ, ψ)`.
/// The centre is compared in the rotated frame, so a rotated ellipsoid's centre sits at `αᵀ (x0, y0, z0)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ellipsoid {
    /// Additive attenuation μ (1/mm); overlapping ellipsoids add.
    pub value: f64,
    /// Semi-axes (phantom units, > 0).
    pub a: f64,
    pub b: f64,
    pub c: f64,
    /// Centre in the rotated frame (phantom units).
    #[serde(default)]
    pub x0: f64,
    #[serde(default)]
    pub y0: f64,
    #[serde(default)]
    pub z0: f64,
    /// Euler angles (degrees) of [`euler_matrix`].
    #[serde(default)]
    pub phi_deg: f64,
    #[serde(default)]
    pub theta_deg: f64,
    #[serde(default)]
    pub psi_deg: f64,
}

/// The seed program's Euler matrix α(φ, θ, ψ) (angles in radians), rows first:
/// `[cψcφ − cθsφsψ, cψsφ + cθcφsψ, sψsθ; −sψcφ − cθsφcψ, −sψsφ + cθcφcψ, cψsθ; sθsφ, −sθcφ, cθ]`.
/// It is orthogonal; with θ = 0 it turns the coordinates by −(φ + ψ) about z.
pub fn euler_matrix(phi: f64, theta: f64, psi: f64) -> [[f64; 3]; 3] {
    let (sf, cf) = phi.sin_cos();
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = psi.sin_cos();
    [
        [cp * cf - ct * sf * sp, cp * sf + ct * cf * sp, sp * st],
        [-sp * cf - ct * sf * cp, -sp * sf + ct * cf * cp, cp * st],
        [st * sf, -st * cf, ct],
    ]
}

impl Ellipsoid {
    /// Refuse non-finite values and non-positive semi-axes; `index` names the ellipsoid in the error.
    pub fn validate(&self, index: usize) -> Result<(), ReconError> {
        let what = |field| format!("ellipsoid {index}: `{field}`");
        finite_field("ellipsoids", &what("value"), self.value)?;
        positive_field("ellipsoids", &what("a"), self.a)?;
        positive_field("ellipsoids", &what("b"), self.b)?;
        positive_field("ellipsoids", &what("c"), self.c)?;
        for (name, v) in [
            ("x0", self.x0),
            ("y0", self.y0),
            ("z0", self.z0),
            ("phi_deg", self.phi_deg),
            ("theta_deg", self.theta_deg),
            ("psi_deg", self.psi_deg),
        ] {
            finite_field("ellipsoids", &what(name), v)?;
        }
        Ok(())
    }

    /// The ellipsoid in millimetres for a phantom scale of `scale_mm`: `M = diag(1/a, 1/b, 1/c)·α/scale`,
    /// `q0 = diag(1/a, 1/b, 1/c)·c0`.
    pub(crate) fn quadric(&self, scale_mm: f64) -> Quadric<3> {
        let al = euler_matrix(
            self.phi_deg.to_radians(),
            self.theta_deg.to_radians(),
            self.psi_deg.to_radians(),
        );
        let axes = [self.a, self.b, self.c];
        let centre = [self.x0, self.y0, self.z0];
        let mut m = [[0.0; 3]; 3];
        let mut m_inv = [[0.0; 3]; 3];
        let mut q0 = [0.0; 3];
        for i in 0..3 {
            q0[i] = centre[i] / axes[i];
            for j in 0..3 {
                m[i][j] = al[i][j] / (axes[i] * scale_mm);
                // scale · αᵀ · diag(a, b, c)
                m_inv[i][j] = scale_mm * al[j][i] * axes[j];
            }
        }
        Quadric {
            m,
            q0,
            m_inv,
            value: self.value,
        }
    }
}

/// The seed program's grid for `phantom3d(n)`: `n` samples per axis covering [−1, 1] with both ends
/// sampled (spacing `2/(n−1)·scale_mm`), centred on the isocentre. Slice `z` of a volume rasterised on
/// it (supersample 1) is the seed's `phantom3d(n)(:, :, z)` (rows y, columns x). For `n = 1` the single
/// sample sits at the centre with spacing `2·scale_mm`.
pub fn seed_grid(n: usize, scale_mm: f64) -> VolumeGrid {
    let spacing = if n > 1 {
        2.0 / (n as f64 - 1.0) * scale_mm
    } else {
        2.0 * scale_mm
    };
    VolumeGrid::cube(n, spacing)
}

/// A 3D phantom: a list of ellipsoids in phantom units and the scale that maps them to millimetres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Phantom3 {
    pub ellipsoids: Vec<Ellipsoid>,
    /// Millimetres per phantom unit (> 0).
    pub scale_mm: f64,
}

impl Phantom3 {
    /// A validated phantom from a user list of ellipsoids.
    pub fn new(ellipsoids: Vec<Ellipsoid>, scale_mm: f64) -> Result<Self, ReconError> {
        let p = Self {
            ellipsoids,
            scale_mm,
        };
        p.validate()?;
        Ok(p)
    }

    /// A named table scaled by `scale_mm` (a positive, finite number of millimetres per phantom unit;
    /// call [`Phantom3::validate`] when it comes from outside).
    pub fn from_table(table: Table3, scale_mm: f64) -> Self {
        Self {
            ellipsoids: table.ellipsoids(),
            scale_mm,
        }
    }

    /// Check the scale, the number of ellipsoids and every ellipsoid.
    pub fn validate(&self) -> Result<(), ReconError> {
        check_scale(self.scale_mm)?;
        if self.ellipsoids.len() > MAX_BODIES {
            return Err(ReconError::param(
                "ellipsoids",
                format!(
                    "at most {MAX_BODIES} ellipsoids, got {}",
                    self.ellipsoids.len()
                ),
            ));
        }
        for (i, e) in self.ellipsoids.iter().enumerate() {
            e.validate(i)?;
        }
        Ok(())
    }

    pub(crate) fn quadrics(&self) -> Vec<Quadric<3>> {
        self.ellipsoids
            .iter()
            .map(|e| e.quadric(self.scale_mm))
            .collect()
    }

    /// μ (1/mm) at the point `p_mm = (x, y, z)`.
    pub fn value_at(&self, p_mm: Vec3) -> f64 {
        self.quadrics()
            .iter()
            .filter(|q| {
                let u = q.unit_frame(&p_mm);
                dot3(u, u) <= 1.0
            })
            .map(|q| q.value)
            .sum()
    }

    /// Exact line integral of μ along the whole line `origin + λ·direction` (mm, `direction` a unit
    /// vector).
    pub fn line_integral(&self, origin: Vec3, direction: Vec3) -> f64 {
        self.quadrics()
            .iter()
            .map(|q| q.line_integral(&origin, &direction))
            .sum()
    }

    /// The phantom sampled on `grid`, shape `[nz][ny][nx]`: each voxel is the mean of `supersample³`
    /// point samples spread evenly over the voxel (`supersample` 0 counts as 1). Slices run in parallel.
    pub fn rasterize(&self, grid: &VolumeGrid, supersample: usize) -> Array3<f32> {
        // Never canceled, so never an error.
        self.rasterize_cancelable(grid, supersample, unattended())
            .unwrap_or_else(|_| Array3::zeros(grid.shape()))
    }

    /// [`Self::rasterize`], checking `ctl`'s cancel flag before each slice.
    pub fn rasterize_cancelable(
        &self,
        grid: &VolumeGrid,
        supersample: usize,
        ctl: Control<'_>,
    ) -> Result<Array3<f32>, ReconError> {
        let s = supersample.max(1);
        let sf = s as f64;
        let bodies = self.quadrics();
        let [dx, dy, dz] = grid.spacing_mm;
        let mut out = Array3::<f32>::zeros(grid.shape());
        let hx = dx / sf;
        let x_start = grid.x(0) - dx / 2.0 + hx / 2.0;
        let norm = 1.0 / (s * s * s) as f64;
        let sub = |m: usize, d: f64| ((m as f64 + 0.5) / sf - 0.5) * d;
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .try_for_each(|(k, mut slice)| {
                ctl.check()?;
                let mut buf = vec![0.0f64; grid.nx * s];
                let mut acc = vec![0.0f64; grid.nx];
                for (j, mut row) in slice.axis_iter_mut(Axis(0)).enumerate() {
                    acc.fill(0.0);
                    for mz in 0..s {
                        let z = grid.z(k) + sub(mz, dz);
                        for my in 0..s {
                            let y = grid.y(j) + sub(my, dy);
                            buf.fill(0.0);
                            fill_row(&bodies, &[x_start, y, z], hx, &mut buf);
                            for (a, chunk) in acc.iter_mut().zip(buf.chunks_exact(s)) {
                                *a += chunk.iter().sum::<f64>();
                            }
                        }
                    }
                    for (o, a) in row.iter_mut().zip(&acc) {
                        *o = (a * norm) as f32;
                    }
                }
                Ok::<(), ReconError>(())
            })?;
        Ok(out)
    }

    /// Exact cone-beam projections, shape `[views][nv][nu]`: element `[i][r][c]` is the line integral
    /// of μ along `views.ray(view i, r, c)` (the whole line through the source and the element centre).
    /// Views run in parallel; within a view each ellipsoid only visits the detector rectangle its
    /// bounding box casts.
    pub fn project(&self, views: &Views3) -> Array3<f32> {
        let bodies = self.quadrics();
        let mut out = Array3::<f32>::zeros(views.shape());
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(views.views.par_iter())
            .for_each(|(img, view)| project_view(&bodies, &views.detector, view, img));
        out
    }

    /// Exact 3D parallel-beam projections, shape `[views][nv][nu]`: element `[i][r][c]` is the line integral
    /// of μ along the horizontal ray `views.ray(i, r, c)`. Views run in parallel.
    pub fn project_parallel(&self, views: &SliceViews) -> Array3<f32> {
        let bodies = self.quadrics();
        let mut out = Array3::<f32>::zeros(views.shape());
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(i, mut img)| {
                for ((r, c), p) in img.indexed_iter_mut() {
                    let ray = views.ray(i, r, c);
                    *p = bodies
                        .iter()
                        .map(|q| q.line_integral(&ray.origin, &ray.direction))
                        .sum::<f64>() as f32;
                }
            });
        out
    }
}

/// Where on the panel a body can cast a shadow.
enum Footprint {
    /// Rows `r0..=r1`, columns `c0..=c1`.
    Rect([usize; 4]),
    /// Nowhere on the panel.
    Miss,
    /// Unknown (the source is inside the bounding box or the panel is degenerate): every element.
    All,
}

fn footprint(body: &Quadric<3>, det: &Detector2, view: &View3) -> Footprint {
    let w0 = sub3(view.det_centre, view.source);
    let (eu, ev) = (view.det_u, view.det_v);
    let n = [
        eu[1] * ev[2] - eu[2] * ev[1],
        eu[2] * ev[0] - eu[0] * ev[2],
        eu[0] * ev[1] - eu[1] * ev[0],
    ];
    let dn = dot3(w0, n);
    let (guu, guv, gvv) = (dot3(eu, eu), dot3(eu, ev), dot3(ev, ev));
    let g = guu * gvv - guv * guv;
    if dn.abs() < 1e-12 * norm3(w0) * norm3(n) || g.abs() < 1e-12 {
        return Footprint::All;
    }
    let (mut umin, mut umax, mut vmin, mut vmax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for corner in body.box_corners() {
        let wp = sub3(corner, view.source);
        let t = dot3(wp, n) / dn;
        // A corner at or behind the source plane: the cast shadow is unbounded.
        if t.is_nan() || t <= 1e-9 {
            return Footprint::All;
        }
        let rel = sub3(scale3(wp, 1.0 / t), w0);
        let (ru, rv) = (dot3(rel, eu), dot3(rel, ev));
        let u = (gvv * ru - guv * rv) / g;
        let v = (guu * rv - guv * ru) / g;
        umin = umin.min(u);
        umax = umax.max(u);
        vmin = vmin.min(v);
        vmax = vmax.max(v);
    }
    let range = |lo: f64, hi: f64, n: usize| -> Option<Option<(usize, usize)>> {
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        // One element of margin on each side for rounding.
        let (lo, hi) = (lo.floor() - 1.0, hi.ceil() + 1.0);
        let last = n as f64 - 1.0;
        if hi < 0.0 || lo > last {
            return Some(None);
        }
        Some(Some((lo.max(0.0) as usize, hi.min(last) as usize)))
    };
    if det.shape == PanelShape::Cylindrical {
        // The shadow on the plane tangent to the cylinder at the panel centre, mapped onto the
        // cylinder: u = R·atan(u_plane/R); heights above the source shrink by cos(atan(u_plane/R)).
        let along = dot3(w0, ev);
        let r = norm3(sub3(w0, scale3(ev, along)));
        if dot3(w0, eu).abs() > 1e-9 * r || r <= 0.0 || guv.abs() > 1e-9 {
            return Footprint::All;
        }
        let c_min = 1.0 / (1.0 + (umin.abs().max(umax.abs()) / r).powi(2)).sqrt();
        let (hmin, hmax) = (vmin + along, vmax + along);
        vmin = hmin.min(hmin * c_min) - along;
        vmax = hmax.max(hmax * c_min) - along;
        umin = r * (umin / r).atan();
        umax = r * (umax / r).atan();
    }
    let cols = range(det.col_of(umin), det.col_of(umax), det.nu);
    let rows = range(det.row_of(vmin), det.row_of(vmax), det.nv);
    match (rows, cols) {
        (Some(Some((r0, r1))), Some(Some((c0, c1)))) => Footprint::Rect([r0, r1, c0, c1]),
        (Some(None), _) | (_, Some(None)) => Footprint::Miss,
        _ => Footprint::All,
    }
}

/// One cone-beam view. The ray through element `(c, v)` is `s + λ w` with `w = w_c + v·e_v` (`w_c` the
/// column's vector from the source, [`Detector2::column_vector`], flat or cylindrical), which maps
/// linearly into each body's unit-ball frame; the chord in λ times `|w|` is the length in mm.
fn project_view(bodies: &[Quadric<3>], det: &Detector2, view: &View3, mut img: ArrayViewMut2<f32>) {
    let (nu, nv) = (det.nu, det.nv);
    if nu == 0 || nv == 0 {
        return;
    }
    let s = view.source;
    let columns: Vec<Vec3> = (0..nu).map(|c| det.column_vector(view, c)).collect();
    let mut mapped = vec![[0.0f64; 3]; nu];
    let mut acc = vec![0.0f64; nu * nv];
    for body in bodies {
        let [r0, r1, c0, c1] = match footprint(body, det, view) {
            Footprint::Rect(r) => r,
            Footprint::Miss => continue,
            Footprint::All => [0, nv - 1, 0, nu - 1],
        };
        let q = body.unit_frame(&s);
        for col in c0..=c1 {
            mapped[col] = mul(&body.m, &columns[col]);
        }
        let c = mul(&body.m, &view.det_v);
        for row in r0..=r1 {
            let dv = scale3(c, det.v(row));
            let line = &mut acc[row * nu..(row + 1) * nu];
            for col in c0..=c1 {
                let r = add3(mapped[col], dv);
                if let Some((_, half)) = mapped_interval(&q, &r) {
                    line[col] += body.value * 2.0 * half;
                }
            }
        }
    }
    for (row, mut out_row) in img.axis_iter_mut(Axis(0)).enumerate() {
        let dv = scale3(view.det_v, det.v(row));
        for (col, o) in out_row.iter_mut().enumerate() {
            let w = add3(columns[col], dv);
            *o = (acc[row * nu + col] * norm3(w)) as f32;
        }
    }
}
