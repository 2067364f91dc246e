//! The canonical per-view form every geometry converts into, and the only form projectors and
//! algorithms read (as ASTRA's `*_vec` geometries and RTK's per-view matrices do).
//!
//! A 2D view is a source (a point, or a ray direction for a parallel beam), the detector point where the
//! coordinate u = 0 lies, and the unit u axis. The detector sampling ([`Detector1`]) is shared by all views:
//! element `k` of `n` sits at `u_k = (k − (n−1)/2)·spacing + offset`. On a flat detector `u` is a distance
//! (mm) along the u axis from the u = 0 point; on an arc detector (centred on the source, radius
//! `R = |det_centre − source|`) `u` is the fan angle γ (radians) from the direction source → det_centre,
//! positive toward the u axis. A 3D view adds a v axis; elements are `[v][u]`.

use serde::{Deserialize, Serialize};

pub type Vec2 = [f64; 2];
pub type Vec3 = [f64; 3];

pub fn add2(a: Vec2, b: Vec2) -> Vec2 {
    [a[0] + b[0], a[1] + b[1]]
}
pub fn sub2(a: Vec2, b: Vec2) -> Vec2 {
    [a[0] - b[0], a[1] - b[1]]
}
pub fn scale2(a: Vec2, s: f64) -> Vec2 {
    [a[0] * s, a[1] * s]
}
pub fn dot2(a: Vec2, b: Vec2) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}
pub fn norm2(a: Vec2) -> f64 {
    a[0].hypot(a[1])
}
pub fn add3(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
pub fn sub3(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub fn scale3(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
pub fn dot3(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub fn cross3(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub fn norm3(a: Vec3) -> f64 {
    dot3(a, a).sqrt()
}

/// Shape of a 1D detector.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DetectorShape {
    /// Elements equally spaced along a line; spacing in mm.
    Flat,
    /// Elements equally spaced in angle on an arc centred on the source; spacing in radians.
    Arc,
}

/// Sampling of a 1D detector, shared by all views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detector1 {
    pub count: usize,
    /// Element spacing: mm (flat) or radians (arc).
    pub spacing: f64,
    /// Coordinate of the detector centre: mm (flat) or radians (arc).
    pub offset: f64,
    pub shape: DetectorShape,
}

impl Detector1 {
    /// Coordinate `u_k` of element `k`.
    pub fn coord(&self, k: usize) -> f64 {
        (k as f64 - (self.count as f64 - 1.0) / 2.0) * self.spacing + self.offset
    }
    /// Fractional element index of coordinate `u` (inverse of [`Detector1::coord`]).
    pub fn index_of(&self, u: f64) -> f64 {
        (u - self.offset) / self.spacing + (self.count as f64 - 1.0) / 2.0
    }
}

/// Where the rays of a 2D view come from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Source2 {
    /// All rays travel along this unit direction.
    Parallel { direction: Vec2 },
    /// All rays start at this point (mm).
    Point { position: Vec2 },
}

/// One 2D view in canonical form.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View2 {
    /// Nominal view angle (radians); used for angular weights, not for ray geometry.
    pub angle_rad: f64,
    pub source: Source2,
    /// Detector point with u = 0 (mm).
    pub det_centre: Vec2,
    /// Unit vector of the detector u axis.
    pub det_u: Vec2,
}

/// A line: a point on it and its unit direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray2 {
    pub origin: Vec2,
    pub direction: Vec2,
}

/// A 2D geometry in canonical form.
#[derive(Debug, Clone, PartialEq)]
pub struct Views2 {
    pub detector: Detector1,
    pub views: Vec<View2>,
}

impl Views2 {
    /// `[views, detector elements]`, the shape of a sinogram.
    pub fn shape(&self) -> [usize; 2] {
        [self.views.len(), self.detector.count]
    }

    /// Position (mm) of element `k` of view `view`.
    pub fn element_position(&self, view: &View2, k: usize) -> Vec2 {
        let u = self.detector.coord(k);
        match (self.detector.shape, view.source) {
            (DetectorShape::Arc, Source2::Point { position }) => {
                let to_centre = sub2(view.det_centre, position);
                let r = norm2(to_centre);
                let d = scale2(to_centre, 1.0 / r);
                add2(
                    position,
                    add2(scale2(d, r * u.cos()), scale2(view.det_u, r * u.sin())),
                )
            }
            _ => add2(view.det_centre, scale2(view.det_u, u)),
        }
    }

    /// The ray measured by element `k` of `view`: through the element, from the source.
    pub fn ray(&self, view: &View2, k: usize) -> Ray2 {
        let e = self.element_position(view, k);
        match view.source {
            Source2::Parallel { direction } => Ray2 {
                origin: e,
                direction,
            },
            Source2::Point { position } => {
                let d = sub2(e, position);
                Ray2 {
                    origin: position,
                    direction: scale2(d, 1.0 / norm2(d)),
                }
            }
        }
    }
}

/// Shape of a 2D detector (panel).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PanelShape {
    /// A plane: `u` and `v` are distances (mm) along the panel's axes.
    #[default]
    Flat,
    /// A cylinder whose axis runs along `det_v` through the source (ASTRA `cyl_cone_vec`, a clinical CT
    /// detector): `u` is the arc length (mm) on the cylinder of radius R, the distance from the source to
    /// the panel centre across `det_v`, from the panel centre toward `det_u` (made perpendicular to the
    /// direction source → centre); `v` is a distance along `det_v` as on a flat panel.
    Cylindrical,
}

/// The unit vector along `u` made perpendicular to the unit vector `n` (`u` itself where it already is):
/// the direction in which a cylindrical panel's arc leaves its centre.
pub fn tangent(u: Vec3, n: Vec3) -> Vec3 {
    let t = sub3(u, scale3(n, dot3(u, n)));
    let len = norm3(t);
    if len > 0.0 { scale3(t, 1.0 / len) } else { u }
}

/// Sampling of a 2D detector (panel), shared by all views. Element `[r][c]` sits at
/// `u_c = (c − (nu−1)/2)·du + offset_u`, `v_r = (r − (nv−1)/2)·dv + offset_v` (mm); on a cylindrical
/// panel `u` is an arc length ([`PanelShape`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detector2 {
    pub nu: usize,
    pub nv: usize,
    pub du_mm: f64,
    pub dv_mm: f64,
    pub offset_u_mm: f64,
    pub offset_v_mm: f64,
    pub shape: PanelShape,
}

impl Detector2 {
    pub fn u(&self, c: usize) -> f64 {
        (c as f64 - (self.nu as f64 - 1.0) / 2.0) * self.du_mm + self.offset_u_mm
    }
    pub fn v(&self, r: usize) -> f64 {
        (r as f64 - (self.nv as f64 - 1.0) / 2.0) * self.dv_mm + self.offset_v_mm
    }
    /// Fractional column of coordinate `u` (mm).
    pub fn col_of(&self, u: f64) -> f64 {
        (u - self.offset_u_mm) / self.du_mm + (self.nu as f64 - 1.0) / 2.0
    }
    /// Fractional row of coordinate `v` (mm).
    pub fn row_of(&self, v: f64) -> f64 {
        (v - self.offset_v_mm) / self.dv_mm + (self.nv as f64 - 1.0) / 2.0
    }
    /// The vector from `view`'s source to the point of column `col` with v = 0 (mm); see
    /// [`Views3::column_vector`].
    pub fn column_vector(&self, view: &View3, col: usize) -> Vec3 {
        let u = self.u(col);
        let w0 = sub3(view.det_centre, view.source);
        match self.shape {
            PanelShape::Flat => add3(w0, scale3(view.det_u, u)),
            PanelShape::Cylindrical => {
                // The panel centre's offset along the cylinder's axis, and its direction across it.
                let along = dot3(w0, view.det_v);
                let across = sub3(w0, scale3(view.det_v, along));
                let r = norm3(across);
                if r <= 0.0 {
                    return w0;
                }
                let n = scale3(across, 1.0 / r);
                let t = tangent(view.det_u, n);
                let g = u / r;
                add3(
                    scale3(view.det_v, along),
                    add3(scale3(n, r * g.cos()), scale3(t, r * g.sin())),
                )
            }
        }
    }
}

/// One cone-beam view in canonical form: a point source and a flat panel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View3 {
    pub angle_rad: f64,
    pub source: Vec3,
    /// Panel point with u = v = 0 (mm).
    pub det_centre: Vec3,
    /// Unit vectors of the panel axes.
    pub det_u: Vec3,
    pub det_v: Vec3,
}

/// A 3D line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray3 {
    pub origin: Vec3,
    pub direction: Vec3,
}

/// A cone-beam geometry in canonical form.
#[derive(Debug, Clone, PartialEq)]
pub struct Views3 {
    pub detector: Detector2,
    pub views: Vec<View3>,
}

impl Views3 {
    /// `[views, nv, nu]`, the shape of a projection stack.
    pub fn shape(&self) -> [usize; 3] {
        [self.views.len(), self.detector.nv, self.detector.nu]
    }
    /// Position (mm) of element `[row][col]` of `view`: on the plane through `det_centre` spanned by
    /// `det_u`, `det_v`, or on the cylinder of [`PanelShape::Cylindrical`].
    pub fn element_position(&self, view: &View3, row: usize, col: usize) -> Vec3 {
        let v = scale3(view.det_v, self.detector.v(row));
        match self.detector.shape {
            PanelShape::Flat => {
                let u = scale3(view.det_u, self.detector.u(col));
                add3(view.det_centre, add3(u, v))
            }
            PanelShape::Cylindrical => add3(view.source, add3(self.column_vector(view, col), v)),
        }
    }
    /// The vector from the source to the point of column `col` with v = 0: every element of the column
    /// sits at `source + column_vector + v·det_v`.
    pub fn column_vector(&self, view: &View3, col: usize) -> Vec3 {
        self.detector.column_vector(view, col)
    }
    /// The ray from the source through element `[row][col]`.
    pub fn ray(&self, view: &View3, row: usize, col: usize) -> Ray3 {
        let d = sub3(self.element_position(view, row, col), view.source);
        Ray3 {
            origin: view.source,
            direction: scale3(d, 1.0 / norm3(d)),
        }
    }
}

/// Per-view angular weights Δβ_k (radians): half the distance to the neighbouring views, one-sided at
/// the ends; for equally spaced angles every weight equals the step.
pub fn angular_steps(angles: &[f64]) -> Vec<f64> {
    let n = angles.len();
    if n < 2 {
        return vec![std::f64::consts::PI; n];
    }
    (0..n)
        .map(|k| {
            let (a, b) = match k {
                0 => (angles[0], angles[1]),
                k if k == n - 1 => (angles[n - 2], angles[n - 1]),
                k => return (angles[k + 1] - angles[k - 1]).abs() / 2.0,
            };
            (b - a).abs()
        })
        .collect()
}
