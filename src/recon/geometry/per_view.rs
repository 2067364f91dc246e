//! Geometries given view by view, with ASTRA's `cone_vec` and `fanflat_vec` semantics: a trajectory that no
//! parametric geometry describes (a measured, wobbling or non-circular orbit; a calibrated scanner's
//! per-view positions; a geometry exported from another toolkit).
//!
//! A cone view is 12 numbers `[sx, sy, sz, dx, dy, dz, ux, uy, uz, vx, vy, vz]` (mm): the source `s`, the
//! centre of the detector `d` (the midpoint of its `nu × nv` elements), `u` the step from one detector
//! column to the next and `v` the step from one row to the next (so `|u|`, `|v|` are the element pitches).
//! Element `[r][c]` of a view sits at `d + (c − (nu−1)/2)·u + (r − (nv−1)/2)·v`, which is ctrecon's
//! projection layout `[view][v][u]` (ASTRA stores `[v][view][u]`: transpose axes 0 and 1 on the way in).
//! A fan view is 6 numbers `[sx, sy, dx, dy, ux, uy]` with element `c` at `d + (c − (count−1)/2)·u`.
//!
//! ctrecon's canonical form shares one detector sampling between views, so every view's `|u|` (and `|v|`)
//! must be the same (to 1 part in 10⁶), `u ⟂ v`, and the source must not lie in the detector plane. View
//! angles are read off the source position (`β = atan2(sx, −sy)`, unwrapped), which is what weights and
//! centre searches use; projectors and iterative methods use the vectors alone, and FBP/FDK accept a
//! per-view geometry only where the vectors describe a circular orbit (checked, else a clear refusal).

use serde::{Deserialize, Serialize};

use super::angles::MAX_VIEWS;
use super::vectors::{
    Detector1, Detector2, DetectorShape, Source2, View2, View3, Views2, Views3, cross3, dot2, dot3,
    norm2, norm3, scale2, scale3, sub2, sub3,
};
use crate::recon::error::{GeometryError, count};
use crate::recon::grid::MAX_AXIS;

/// Relative tolerance on pitches that must agree between views and on the right angle between `u` and `v`.
const PITCH_TOLERANCE: f64 = 1e-6;

/// Detector size of a cone-beam vector geometry (the pitches come from the vectors).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VectorPanel {
    pub nu: usize,
    pub nv: usize,
}

/// Detector size of a fan-beam vector geometry.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VectorRow {
    pub count: usize,
}

/// 3D cone beam with a flat panel, one `[s, d, u, v]` row of 12 numbers per view (ASTRA `cone_vec`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConeVectors {
    pub detector: VectorPanel,
    pub vectors: Vec<[f64; 12]>,
}

/// 2D fan beam with a flat detector, one `[s, d, u]` row of 6 numbers per view (ASTRA `fanflat_vec`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FanVectors {
    pub detector: VectorRow,
    pub vectors: Vec<[f64; 6]>,
}

fn invalid(msg: String) -> GeometryError {
    GeometryError::Invalid(msg)
}

fn check_finite<const N: usize>(k: usize, row: &[f64; N]) -> Result<(), GeometryError> {
    match row.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(invalid(format!(
            "`vectors[{k}][{i}]` must be finite, got {}",
            row[i]
        ))),
        None => Ok(()),
    }
}

/// The pitch every view must share: view 0's, with view `k`'s checked against it.
fn same_pitch(name: &str, k: usize, pitch: f64, first: f64) -> Result<(), GeometryError> {
    if pitch <= 0.0 {
        return Err(invalid(format!(
            "`vectors[{k}]`: the {name} step has length 0 (it is the detector pitch)"
        )));
    }
    if (pitch - first).abs() > PITCH_TOLERANCE * first {
        return Err(invalid(format!(
            "`vectors[{k}]`: the {name} step is {pitch} mm long, view 0's is {first} mm; ctrecon needs one \
             detector pitch for all views"
        )));
    }
    Ok(())
}

fn check_views(n: usize) -> Result<(), GeometryError> {
    count("vectors", n, MAX_VIEWS).map(|_| ())
}

/// View angles `atan2(x, −y)` of the sources, unwrapped into a continuous sequence.
fn unwrapped_angles(sources: impl Iterator<Item = (f64, f64)>) -> Vec<f64> {
    let mut out: Vec<f64> = Vec::new();
    for (x, y) in sources {
        let a = x.atan2(-y);
        let a = match out.last() {
            Some(&prev) => {
                let turns = ((prev - a) / std::f64::consts::TAU).round();
                a + turns * std::f64::consts::TAU
            }
            None => a,
        };
        out.push(a);
    }
    out
}

impl ConeVectors {
    pub fn to_views(&self) -> Result<Views3, GeometryError> {
        let nu = count("detector.nu", self.detector.nu, MAX_AXIS)?;
        let nv = count("detector.nv", self.detector.nv, MAX_AXIS)?;
        check_views(self.vectors.len())?;
        let split = |r: &[f64; 12]| {
            let p = |i: usize| [r[i], r[i + 1], r[i + 2]];
            (p(0), p(3), p(6), p(9))
        };
        let (du, dv) = {
            let (_, _, u, v) = split(&self.vectors[0]);
            (norm3(u), norm3(v))
        };
        let mut views = Vec::with_capacity(self.vectors.len());
        let angles = unwrapped_angles(self.vectors.iter().map(|r| (r[0], r[1])));
        for (k, (row, &angle_rad)) in self.vectors.iter().zip(&angles).enumerate() {
            check_finite(k, row)?;
            let (s, d, u, v) = split(row);
            same_pitch("u (column)", k, norm3(u), du)?;
            same_pitch("v (row)", k, norm3(v), dv)?;
            let (eu, ev) = (scale3(u, 1.0 / du), scale3(v, 1.0 / dv));
            if dot3(eu, ev).abs() > PITCH_TOLERANCE {
                return Err(invalid(format!(
                    "`vectors[{k}]`: u and v make an angle of {:.4}°; ctrecon needs rectangular detector elements \
                     (u ⟂ v)",
                    dot3(eu, ev).clamp(-1.0, 1.0).acos().to_degrees()
                )));
            }
            let normal = cross3(eu, ev);
            let to_detector = sub3(d, s);
            if dot3(to_detector, normal).abs() <= PITCH_TOLERANCE * norm3(to_detector) {
                return Err(invalid(format!(
                    "`vectors[{k}]`: the source lies in the detector's plane"
                )));
            }
            views.push(View3 {
                angle_rad,
                source: s,
                det_centre: d,
                det_u: eu,
                det_v: ev,
            });
        }
        let detector = Detector2 {
            nu,
            nv,
            du_mm: du,
            dv_mm: dv,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
            shape: super::vectors::PanelShape::Flat,
        };
        Ok(Views3 { detector, views })
    }
}

impl FanVectors {
    pub fn to_views(&self) -> Result<Views2, GeometryError> {
        let n = count("detector.count", self.detector.count, MAX_AXIS)?;
        check_views(self.vectors.len())?;
        let du = norm2([self.vectors[0][4], self.vectors[0][5]]);
        let angles = unwrapped_angles(self.vectors.iter().map(|r| (r[0], r[1])));
        let mut views = Vec::with_capacity(self.vectors.len());
        for (k, (row, &angle_rad)) in self.vectors.iter().zip(&angles).enumerate() {
            check_finite(k, row)?;
            let (s, d, u) = ([row[0], row[1]], [row[2], row[3]], [row[4], row[5]]);
            same_pitch("u", k, norm2(u), du)?;
            let eu = scale2(u, 1.0 / du);
            let to_detector = sub2(d, s);
            let normal = [-eu[1], eu[0]];
            if dot2(to_detector, normal).abs() <= PITCH_TOLERANCE * norm2(to_detector) {
                return Err(invalid(format!(
                    "`vectors[{k}]`: the source lies on the detector's line"
                )));
            }
            views.push(View2 {
                angle_rad,
                source: Source2::Point { position: s },
                det_centre: d,
                det_u: eu,
            });
        }
        let detector = Detector1 {
            count: n,
            spacing: du,
            offset: 0.0,
            shape: DetectorShape::Flat,
        };
        Ok(Views2 { detector, views })
    }
}

/// The per-view vectors of a cone-beam geometry in canonical form (ASTRA `cone_vec` rows): the exact
/// inverse of [`ConeVectors::to_views`] up to the panel offsets, which move into `d`.
pub fn cone_vectors(views: &Views3) -> ConeVectors {
    let det = &views.detector;
    let vectors = views
        .views
        .iter()
        .map(|w| {
            let d = super::vectors::add3(
                w.det_centre,
                super::vectors::add3(
                    scale3(w.det_u, det.offset_u_mm),
                    scale3(w.det_v, det.offset_v_mm),
                ),
            );
            let u = scale3(w.det_u, det.du_mm);
            let v = scale3(w.det_v, det.dv_mm);
            [
                w.source[0],
                w.source[1],
                w.source[2],
                d[0],
                d[1],
                d[2],
                u[0],
                u[1],
                u[2],
                v[0],
                v[1],
                v[2],
            ]
        })
        .collect();
    ConeVectors {
        detector: VectorPanel {
            nu: det.nu,
            nv: det.nv,
        },
        vectors,
    }
}

/// The per-view vectors of a flat-detector fan beam in canonical form (ASTRA `fanflat_vec` rows); `None`
/// for parallel beams and arc detectors, which this form cannot express.
pub fn fan_vectors(views: &Views2) -> Option<FanVectors> {
    if views.detector.shape != DetectorShape::Flat {
        return None;
    }
    let det = &views.detector;
    let mut vectors = Vec::with_capacity(views.views.len());
    for w in &views.views {
        let Source2::Point { position: s } = w.source else {
            return None;
        };
        let d = super::vectors::add2(w.det_centre, scale2(w.det_u, det.offset));
        let u = scale2(w.det_u, det.spacing);
        vectors.push([s[0], s[1], d[0], d[1], u[0], u[1]]);
    }
    Some(FanVectors {
        detector: VectorRow { count: det.count },
        vectors,
    })
}

/// The smallest distance of a source from the rotation axis (z) over all views: what a field of view must
/// stay inside.
pub(super) fn nearest_source_3d(v: &ConeVectors) -> Option<f64> {
    v.vectors
        .iter()
        .map(|r| r[0].hypot(r[1]))
        .min_by(f64::total_cmp)
}

pub(super) fn nearest_source_2d(v: &FanVectors) -> Option<f64> {
    v.vectors
        .iter()
        .map(|r| r[0].hypot(r[1]))
        .min_by(f64::total_cmp)
}
