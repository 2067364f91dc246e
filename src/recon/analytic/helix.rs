//! The helix behind a helical scan, recovered from the canonical per-view form, and the per-view panel
//! maps the helical filtered back projection reads: the circle the sources turn on (a least-squares
//! circle through their (x, y)), the view angles about its centre (unwrapped), the source height as an
//! affine function of the angle (the nominal helix, which a flying focal spot's z offsets scatter about),
//! and per view the flat panel's distance, axes and central-ray offsets as seen from that view's own
//! source.

use crate::recon::error::ReconError;
use crate::recon::geometry::vectors::{cross3, dot3, norm3, scale3, sub3, tangent};
use crate::recon::geometry::{Detector2, PanelShape, Vec3, Views3, angular_steps};
use crate::recon::grid::VolumeGrid;

fn unsupported(reason: &str) -> ReconError {
    ReconError::param(
        "geometry",
        format!(
            "{reason}; the iterative methods (sirt, cgls, os_sart, sart, art, mlem, tv) take any per-view geometry \
             with a flat panel"
        ),
    )
}

/// One view as the back projection maps voxels onto it: point `p` lands at panel coordinates
/// `u = dsd·((p − source)·e_u)/lc − u0`, `v = dsd·((p − source)·e_v)/lc − v0` with `lc = (p − source)·normal`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ViewMap {
    pub source: Vec3,
    /// Unit normal of the panel, from the source toward it (horizontal).
    pub normal: Vec3,
    pub e_u: Vec3,
    /// +1 where the panel's v axis points up (+z), −1 where it points down.
    pub v_sign: f64,
    /// Source to the panel plane along `normal` (mm).
    pub dsd: f64,
    /// Panel coordinates of the foot of the perpendicular from the source, negated (mm).
    pub u0: f64,
    pub v0: f64,
    /// Angle of the source about the helix axis (radians, unwrapped; same origin and sense as every
    /// ctrecon angle: the source at `centre + R·(sin β, −cos β)`).
    pub angle: f64,
    /// Angular step Δβ of the view (radians).
    pub step: f64,
    /// The nominal helix's source (x, y) at `angle` (mm): what the conjugate views are found from.
    pub nominal: [f64; 2],
}

/// The nominal helix: `source(β) = (centre + R·(sin β, −cos β), z0 + slope·β)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Helix {
    pub centre: [f64; 2],
    pub radius: f64,
    pub z0: f64,
    /// Source rise per radian of angle (mm); its sign is the table direction times the rotation sense.
    pub slope: f64,
    /// Angles of the first and last views, ordered (`lo < hi`), widened by half a step.
    pub lo: f64,
    pub hi: f64,
}

impl Helix {
    pub fn source_xy(&self, beta: f64) -> [f64; 2] {
        let (s, c) = beta.sin_cos();
        [
            self.centre[0] + self.radius * s,
            self.centre[1] - self.radius * c,
        ]
    }
    pub fn z(&self, beta: f64) -> f64 {
        self.z0 + self.slope * beta
    }
    /// Angle of point (x, y) about the axis, in the convention of [`ViewMap::angle`], within (−π, π].
    pub fn angle_of(&self, x: f64, y: f64) -> f64 {
        (x - self.centre[0]).atan2(-(y - self.centre[1]))
    }
}

/// Least-squares circle `x² + y² + D x + E y + F = 0` through the points (Kåsa's fit): (centre, radius).
fn circle(points: &[[f64; 2]]) -> Option<([f64; 2], f64)> {
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for p in points {
        let row = [p[0], p[1], 1.0];
        let rhs = -(p[0] * p[0] + p[1] * p[1]);
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += row[i] * row[j];
            }
            b[i] += row[i] * rhs;
        }
    }
    let det3 = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det3(&a);
    if d.abs() <= 1e-300 || !d.is_finite() {
        return None;
    }
    let solve = |k: usize| {
        let mut m = a;
        for (i, row) in m.iter_mut().enumerate() {
            row[k] = b[i];
        }
        det3(&m) / d
    };
    let (dd, ee, ff) = (solve(0), solve(1), solve(2));
    let centre = [-dd / 2.0, -ee / 2.0];
    let r2 = centre[0] * centre[0] + centre[1] * centre[1] - ff;
    (r2 > 0.0 && r2.is_finite()).then(|| (centre, r2.sqrt()))
}

/// The flat panel a cylindrical detector of radius `radius` (mm) is rebinned onto: the plane tangent to
/// the cylinder at its centre, as many columns spanning the same fan angles, the same rows. A flat panel
/// is its own.
pub(super) fn flat_panel(det: &Detector2, radius: f64) -> Result<Detector2, ReconError> {
    if det.shape == PanelShape::Flat {
        return Ok(*det);
    }
    let (g0, g1) = (
        (det.u(0) - det.du_mm / 2.0) / radius,
        (det.u(det.nu - 1) + det.du_mm / 2.0) / radius,
    );
    if g0.abs().max(g1.abs()) >= 80f64.to_radians() {
        return Err(unsupported(
            "a cylindrical detector wider than ±80° of fan angle cannot be rebinned onto a flat panel",
        ));
    }
    let (t0, t1) = (
        radius * (det.u(0) / radius).tan(),
        radius * (det.u(det.nu - 1) / radius).tan(),
    );
    let du_mm = if det.nu > 1 {
        (t1 - t0) / (det.nu - 1) as f64
    } else {
        det.du_mm
    };
    Ok(Detector2 {
        du_mm,
        offset_u_mm: (t0 + t1) / 2.0,
        shape: PanelShape::Flat,
        ..*det
    })
}

/// The helix and the per-view maps of `views`, or why the helical back projection cannot take them.
pub(super) fn helix_of(views: &Views3) -> Result<(Helix, Vec<ViewMap>), ReconError> {
    let det = views.detector;
    if views.views.len() < 2 {
        return Err(unsupported("a helical scan needs at least two views"));
    }
    if det.nv < 2 {
        return Err(unsupported(
            "the helical back projection needs a detector of at least two rows",
        ));
    }
    let xy: Vec<[f64; 2]> = views
        .views
        .iter()
        .map(|v| [v.source[0], v.source[1]])
        .collect();
    let (centre, radius) =
        circle(&xy).ok_or_else(|| unsupported("the sources do not lie on a circle about z"))?;
    let far = xy
        .iter()
        .map(|p| ((p[0] - centre[0]).hypot(p[1] - centre[1]) - radius).abs())
        .fold(0.0f64, f64::max);
    if far > 1e-3 * radius {
        return Err(unsupported(
            "FDK needs a circular orbit or a helix about z (sources at a constant distance from the axis)",
        ));
    }
    // Angles about the fitted centre, unwrapped.
    let mut angles: Vec<f64> = Vec::with_capacity(xy.len());
    for p in &xy {
        let a = (p[0] - centre[0]).atan2(-(p[1] - centre[1]));
        let a = match angles.last() {
            Some(&prev) => a + ((prev - a) / std::f64::consts::TAU).round() * std::f64::consts::TAU,
            None => a,
        };
        angles.push(a);
    }
    let rising = angles[1] > angles[0];
    if angles
        .windows(2)
        .any(|w| (w[1] > w[0]) != rising || w[1] == w[0])
    {
        return Err(unsupported(
            "a helical scan needs view angles that turn one way (strictly monotonic)",
        ));
    }
    // The source height as an affine function of the angle, by least squares.
    let n = angles.len() as f64;
    let (ma, mz) = (
        angles.iter().sum::<f64>() / n,
        views.views.iter().map(|v| v.source[2]).sum::<f64>() / n,
    );
    let (mut saz, mut saa) = (0.0, 0.0);
    for (a, v) in angles.iter().zip(&views.views) {
        saz += (a - ma) * (v.source[2] - mz);
        saa += (a - ma) * (a - ma);
    }
    let slope = saz / saa;
    let z0 = mz - slope * ma;
    let mut maps: Vec<ViewMap> = Vec::with_capacity(views.views.len());
    let steps = angular_steps(&angles);
    let cylindrical = det.shape == PanelShape::Cylindrical;
    for ((v, &angle), &step) in views.views.iter().zip(&angles).zip(&steps) {
        let r = sub3(v.det_centre, v.source);
        // A cylindrical panel is read through the plane tangent to it at its centre, whose normal is the
        // direction from the source to the centre across the cylinder's axis.
        let across = sub3(r, scale3(v.det_v, dot3(r, v.det_v)));
        let (mut normal, e_u) = if cylindrical {
            let n = scale3(across, 1.0 / norm3(across).max(f64::MIN_POSITIVE));
            (n, tangent(v.det_u, n))
        } else {
            (cross3(v.det_u, v.det_v), v.det_u)
        };
        if dot3(normal, r) < 0.0 {
            normal = scale3(normal, -1.0);
        }
        let len = norm3(normal);
        if len <= 0.0 || normal[2].abs() > 1e-6 * len || e_u[2].abs() > 1e-6 {
            return Err(unsupported(
                "the helical back projection needs a detector whose columns run along z",
            ));
        }
        let normal = scale3(normal, 1.0 / len);
        let dsd = dot3(r, normal);
        if dsd <= 0.0 || !dsd.is_finite() {
            return Err(unsupported("the detector lies behind the source"));
        }
        maps.push(ViewMap {
            source: v.source,
            normal,
            e_u,
            v_sign: v.det_v[2].signum(),
            dsd,
            u0: dot3(r, e_u),
            v0: dot3(r, v.det_v),
            angle,
            step,
            nominal: [0.0; 2],
        });
    }
    let dsd = maps[0].dsd;
    let tolerance = 0.5 * det.dv_mm * radius / dsd;
    let off = views
        .views
        .iter()
        .zip(&angles)
        .map(|(v, a)| (v.source[2] - (z0 + slope * a)).abs())
        .fold(0.0f64, f64::max);
    if off > tolerance || slope.abs() * std::f64::consts::TAU <= 1e-6 * det.dv_mm {
        return Err(unsupported(
            "the sources do not lie on a helix (their height is not an affine function of the angle, within half a \
             detector row)",
        ));
    }
    let (first, last) = (angles[0], angles[angles.len() - 1]);
    let half = 0.5 * steps[0].max(steps[steps.len() - 1]);
    let helix = Helix {
        centre,
        radius,
        z0,
        slope,
        lo: first.min(last) - half,
        hi: first.max(last) + half,
    };
    for m in &mut maps {
        m.nominal = helix.source_xy(m.angle);
    }
    Ok((helix, maps))
}

/// The widest angle range over which one voxel of the grid can stay in a view's cone (radians), plus
/// a turn: conjugate views farther from a view than this never see the same voxel.
pub(super) fn visible_span(
    helix: &Helix,
    det: &Detector2,
    maps: &[ViewMap],
    grid: &VolumeGrid,
) -> f64 {
    let reach = [grid.x(0), grid.x(grid.nx.saturating_sub(1))]
        .iter()
        .flat_map(|&x| {
            [grid.y(0), grid.y(grid.ny.saturating_sub(1))]
                .map(|y| (x - helix.centre[0]).hypot(y - helix.centre[1]))
        })
        .fold(0.0f64, f64::max);
    let dsd = maps.iter().map(|m| m.dsd).fold(f64::MAX, f64::min);
    let height =
        (det.nv as f64 * det.dv_mm + 2.0 * det.offset_v_mm.abs()) * (helix.radius + reach) / dsd;
    height / helix.slope.abs() + std::f64::consts::TAU
}

/// How far the ray through `p` turns from view `a` to view `b` (radians, ≥ 0).
pub(super) fn turned(p: [f64; 2], a: &ViewMap, b: &ViewMap) -> f64 {
    let dir = |m: &ViewMap| (p[1] - m.source[1]).atan2(p[0] - m.source[0]);
    let turn = b.angle - a.angle;
    let extra = (dir(b) - dir(a) - turn + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
        - std::f64::consts::PI;
    (turn + extra).abs()
}
