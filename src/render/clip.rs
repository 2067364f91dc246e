//! Cut-away geometry: clip planes and clip boxes in patient space (mm, LPS), as ray intervals for rendering and as
//! a signed distance for clipping meshes.

use serde::{Deserialize, Serialize};

use super::{RenderError, V3, axpy, cross, dot, unit};

/// A clip plane through `point_mm`; the half-space that `normal` points into is kept.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipPlane {
    pub point_mm: V3,
    pub normal: V3,
}

/// Which part of a clip box stays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Keep {
    #[default]
    Inside,
    Outside,
}

/// A box of half-sizes `half_size_mm` about `centre_mm`, along the patient axes or, with `axes` = `[u, v]`, along
/// u, v and u × v (u and v are made orthonormal). `keep: outside` cuts the box out of the volume.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipBox {
    pub centre_mm: V3,
    pub half_size_mm: V3,
    #[serde(default)]
    pub axes: Option<[V3; 2]>,
    #[serde(default)]
    pub keep: Keep,
}

/// Every clip of a rendering or a mesh: what stays is inside every plane's half-space and every box's kept part.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Clip {
    #[serde(default)]
    pub planes: Vec<ClipPlane>,
    #[serde(default)]
    pub boxes: Vec<ClipBox>,
}

/// Largest number of planes plus boxes.
pub const MAX_CLIPS: usize = 16;

/// A part of a ray that survives the clips: `[t0, t1]` (mm) and the normal of the clip face it starts on, if any.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Span {
    pub t0: f64,
    pub t1: f64,
    pub face: Option<V3>,
}

impl ClipBox {
    fn frame(&self) -> [V3; 3] {
        self.axes
            .and_then(|[u, v]| {
                let u = unit(u)?;
                let v = unit(axpy(v, -dot(u, v), u))?;
                Some([u, v, cross(u, v)])
            })
            .unwrap_or([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    }
    /// Signed distance (mm, approximate outside) to the box surface, positive inside.
    fn inside_distance(&self, p: V3) -> f64 {
        let d = [
            p[0] - self.centre_mm[0],
            p[1] - self.centre_mm[1],
            p[2] - self.centre_mm[2],
        ];
        let f = self.frame();
        (0..3)
            .map(|a| self.half_size_mm[a] - dot(d, f[a]).abs())
            .fold(f64::INFINITY, f64::min)
    }
    /// `(t_in, normal_in, t_out, normal_out)` of the ray in the box, or `None`.
    fn hit(&self, o: V3, dir: V3) -> Option<(f64, V3, f64, V3)> {
        let f = self.frame();
        let d = [
            o[0] - self.centre_mm[0],
            o[1] - self.centre_mm[1],
            o[2] - self.centre_mm[2],
        ];
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        let (mut n_lo, mut n_hi) = (f[0], f[0]);
        for (&axis, &h) in f.iter().zip(&self.half_size_mm) {
            let (p, v) = (dot(d, axis), dot(dir, axis));
            if v.abs() < 1e-15 {
                if p.abs() > h {
                    return None;
                }
                continue;
            }
            let (t1, t2) = ((-h - p) / v, (h - p) / v);
            let (a_in, a_out) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
            if a_in > lo {
                lo = a_in;
                n_lo = axis;
            }
            if a_out < hi {
                hi = a_out;
                n_hi = axis;
            }
        }
        (lo <= hi).then_some((lo, n_lo, hi, n_hi))
    }
}

impl Clip {
    pub fn is_empty(&self) -> bool {
        self.planes.is_empty() && self.boxes.is_empty()
    }

    /// Checks: at most [`MAX_CLIPS`], finite values, non-zero plane normals, positive box sizes and independent
    /// box axes.
    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |reason: &str| Err(RenderError::BadClip(reason.into()));
        if self.planes.len() + self.boxes.len() > MAX_CLIPS {
            return bad("at most 16 clip planes and boxes");
        }
        let finite = |v: &V3| v.iter().all(|c| c.is_finite());
        for (i, p) in self.planes.iter().enumerate() {
            if !finite(&p.point_mm) {
                return bad("plane points must be finite");
            }
            if !finite(&p.normal) || unit(p.normal).is_none() {
                return Err(RenderError::ZeroClipNormal(i));
            }
        }
        for b in &self.boxes {
            if !finite(&b.centre_mm) || !b.half_size_mm.iter().all(|h| h.is_finite() && *h > 0.0) {
                return bad("box centres must be finite and half sizes positive");
            }
            if let Some([u, v]) = b.axes
                && unit(cross(u, v)).is_none()
            {
                return bad("box axes must be two independent directions");
            }
        }
        Ok(())
    }

    /// Signed distance (mm; exact for one plane, a lower bound otherwise) to the clipped region, positive where
    /// the volume is kept.
    pub fn distance(&self, p: V3) -> f64 {
        let mut d = f64::INFINITY;
        for pl in &self.planes {
            if let Some(n) = unit(pl.normal) {
                let q = pl.point_mm;
                d = d.min(dot([p[0] - q[0], p[1] - q[1], p[2] - q[2]], n));
            }
        }
        for b in &self.boxes {
            let inside = b.inside_distance(p);
            d = d.min(match b.keep {
                Keep::Inside => inside,
                Keep::Outside => -inside,
            });
        }
        d
    }

    /// The kept parts of the ray `o + t·dir` within `[t0, t1]`, in increasing `t`, into `out` (cleared first).
    pub(crate) fn spans(&self, o: V3, dir: V3, t0: f64, t1: f64, out: &mut Vec<Span>) {
        out.clear();
        out.push(Span { t0, t1, face: None });
        for pl in &self.planes {
            let Some(n) = unit(pl.normal) else { continue };
            let q = pl.point_mm;
            let s0 = dot([o[0] - q[0], o[1] - q[1], o[2] - q[2]], n);
            let s1 = dot(dir, n);
            if s1.abs() < 1e-15 {
                if s0 < 0.0 {
                    out.clear();
                }
                continue;
            }
            let t = -s0 / s1;
            if s1 > 0.0 {
                keep_after(out, t, n);
            } else {
                keep_before(out, t);
            }
        }
        for b in &self.boxes {
            match (b.hit(o, dir), b.keep) {
                (None, Keep::Inside) => out.clear(),
                (None, Keep::Outside) => {}
                (Some((ta, na, tb, _)), Keep::Inside) => {
                    keep_after(out, ta, na);
                    keep_before(out, tb);
                }
                (Some((ta, _, tb, nb)), Keep::Outside) => {
                    let mut next = Vec::with_capacity(out.len() + 1);
                    for s in out.iter() {
                        if s.t1 < ta || s.t0 > tb {
                            next.push(*s);
                            continue;
                        }
                        if s.t0 < ta {
                            next.push(Span { t1: ta, ..*s });
                        }
                        if s.t1 > tb {
                            next.push(Span {
                                t0: tb,
                                t1: s.t1,
                                face: Some(nb),
                            });
                        }
                    }
                    *out = next;
                }
            }
        }
    }
}

fn keep_after(out: &mut Vec<Span>, t: f64, n: V3) {
    out.retain(|s| s.t1 >= t);
    for s in out.iter_mut() {
        if s.t0 < t {
            s.t0 = t;
            s.face = Some(n);
        }
    }
}

fn keep_before(out: &mut Vec<Span>, t: f64) {
    out.retain(|s| s.t0 <= t);
    for s in out.iter_mut() {
        s.t1 = s.t1.min(t);
    }
}
