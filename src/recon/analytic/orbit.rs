//! The circular orbit behind a divergent-beam scan, recovered from the canonical per-view form: the
//! rotation centre, and per view the source, the unit direction source → centre, the detector axes, the
//! source-to-isocentre distance D and the source-to-detector distance, and where the central ray meets the
//! detector in detector coordinates.

use crate::recon::error::ReconError;
use crate::recon::geometry::vectors::{dot3, norm3, scale3, sub3};
use crate::recon::geometry::{DetectorShape, PanelShape, Source2, Vec3, Views2, Views3};

/// One view of a circular orbit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Frame {
    pub angle_rad: f64,
    pub source: Vec3,
    /// Unit direction from the source to the rotation centre (the central ray).
    pub dir: Vec3,
    pub e_u: Vec3,
    pub e_v: Vec3,
    /// Source to rotation centre (mm).
    pub dso: f64,
    /// Source to the detector plane along `dir` (flat), or the arc radius (mm).
    pub dsd: f64,
    /// Coordinate of the central ray in the detector's own u coordinate, negated: `u_rel = u + u0`
    /// (mm on a flat detector, radians on an arc).
    pub u0: f64,
    /// Same for v (mm).
    pub v0: f64,
}

impl Frame {
    /// (distance along the central ray, lateral u, lateral v) of point `p` relative to the source.
    pub fn local(&self, p: Vec3) -> [f64; 3] {
        let r = sub3(p, self.source);
        [dot3(r, self.dir), dot3(r, self.e_u), dot3(r, self.e_v)]
    }
}

fn unsupported(reason: &str) -> ReconError {
    ReconError::param(
        "geometry",
        format!(
            "{reason}; the iterative methods (sirt, cgls, os_sart, sart, art, mlem, tv) take any per-view geometry"
        ),
    )
}

/// Least-squares intersection (x, y) of the central rays `source → det_centre`.
fn centre_of(rays: &[(Vec3, Vec3)]) -> Result<[f64; 2], ReconError> {
    let (mut a, mut b) = ([[0.0f64; 2]; 2], [0.0f64; 2]);
    for &(s, d) in rays {
        let n = d[0].hypot(d[1]);
        if n == 0.0 {
            return Err(unsupported("a central ray runs along z"));
        }
        let d = [d[0] / n, d[1] / n];
        let p = [
            [1.0 - d[0] * d[0], -d[0] * d[1]],
            [-d[0] * d[1], 1.0 - d[1] * d[1]],
        ];
        for i in 0..2 {
            for j in 0..2 {
                a[i][j] += p[i][j];
            }
            b[i] += p[i][0] * s[0] + p[i][1] * s[1];
        }
    }
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let trace = a[0][0] + a[1][1];
    if det.abs() <= 1e-12 * trace * trace || !det.is_finite() {
        return Err(unsupported(
            "a divergent beam needs views from at least two directions",
        ));
    }
    Ok([
        (a[1][1] * b[0] - a[0][1] * b[1]) / det,
        (a[0][0] * b[1] - a[1][0] * b[0]) / det,
    ])
}

fn frames(
    views: impl Iterator<Item = (f64, Vec3, Vec3, Vec3, Vec3)> + Clone,
    shape: DetectorShape,
) -> Result<Vec<Frame>, ReconError> {
    // The perpendicular from the source onto the detector passes through the rotation centre whatever
    // the panel's offset (a per-view geometry's `det_centre` is the panel's middle, not the central ray's
    // foot); for an arc, `det_centre − source` is the central ray.
    let rays: Vec<(Vec3, Vec3)> = views
        .clone()
        .map(|(_, s, c, e_u, e_v)| {
            let r = sub3(c, s);
            let along_u = scale3(e_u, dot3(r, e_u));
            let along_v = scale3(e_v, dot3(r, e_v));
            (s, sub3(sub3(r, along_u), along_v))
        })
        .collect();
    let [cx, cy] = centre_of(&rays)?;
    let mut out = Vec::with_capacity(rays.len());
    for (angle_rad, source, det_centre, e_u, e_v) in views {
        let centre = [cx, cy, source[2]];
        let to_c = sub3(centre, source);
        let dso = norm3(to_c);
        if dso <= 0.0 || dso.is_nan() {
            return Err(unsupported("the source sits on the rotation centre"));
        }
        let dir = scale3(to_c, 1.0 / dso);
        if dot3(dir, e_u).abs() > 1e-6 || dot3(dir, e_v).abs() > 1e-6 {
            return Err(unsupported(
                "FBP and FDK need a detector facing the rotation centre (no tilt)",
            ));
        }
        let r = sub3(det_centre, source);
        let along = dot3(r, dir);
        let (dsd, u0) = match shape {
            DetectorShape::Flat => (along, dot3(r, e_u)),
            DetectorShape::Arc => (norm3(r), dot3(r, e_u).atan2(along)),
        };
        if dsd <= 0.0 || dsd.is_nan() {
            return Err(unsupported("the detector lies behind the source"));
        }
        out.push(Frame {
            angle_rad,
            source,
            dir,
            e_u,
            e_v,
            dso,
            dsd,
            u0,
            v0: dot3(r, e_v),
        });
    }
    let (lo, hi) = out.iter().fold((f64::MAX, 0.0f64), |(lo, hi), f| {
        (lo.min(f.dso), hi.max(f.dso))
    });
    if hi - lo > 1e-6 * hi {
        return Err(unsupported(
            "FBP and FDK need a circular orbit (constant source-to-centre distance)",
        ));
    }
    Ok(out)
}

/// Frames of a fan beam (2D, lifted to z = 0).
pub(crate) fn fan_frames(views: &Views2) -> Result<Vec<Frame>, ReconError> {
    let mut list = Vec::with_capacity(views.views.len());
    for v in &views.views {
        let Source2::Point { position } = v.source else {
            return Err(unsupported("mixed parallel and fan views"));
        };
        list.push((
            v.angle_rad,
            [position[0], position[1], 0.0],
            [v.det_centre[0], v.det_centre[1], 0.0],
            [v.det_u[0], v.det_u[1], 0.0],
            [0.0, 0.0, 1.0],
        ));
    }
    frames(list.into_iter(), views.detector.shape)
}

/// Frames of a circular cone beam with a flat panel.
pub(crate) fn cone_frames(views: &Views3) -> Result<Vec<Frame>, ReconError> {
    let list: Vec<_> = views
        .views
        .iter()
        .map(|v| (v.angle_rad, v.source, v.det_centre, v.det_u, v.det_v))
        .collect();
    if !is_planar(views) {
        return Err(unsupported("FDK needs a planar circular orbit or a helix"));
    }
    if views.detector.shape != PanelShape::Flat {
        return Err(unsupported(
            "circular FDK needs a flat panel (a cylindrical detector is reconstructed on a helix)",
        ));
    }
    frames(list.into_iter(), DetectorShape::Flat)
}

/// Whether every source lies in one plane z = const (within 10⁻⁹ of its height).
pub(crate) fn is_planar(views: &Views3) -> bool {
    let z0 = views.views.first().map(|v| v.source[2]).unwrap_or(0.0);
    views
        .views
        .iter()
        .all(|v| (v.source[2] - z0).abs() <= 1e-9 * (1.0 + z0.abs()))
}
