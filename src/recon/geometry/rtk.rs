//! RTK's geometry XML (`rtkThreeDCircularProjectionGeometryXMLFile`, version 3), read into and written from
//! ctrecon's per-view form.
//!
//! RTK's fixed frame turns about its y axis; ctrecon's about z. A point `(x, y, z)` of RTK's frame is
//! ctrecon's `(x, −z, y)`, so RTK's gantry angle is ctrecon's view angle β (both put the source at `+z`
//! resp. `−y` at 0° and turn it the same way). Per projection RTK's rotated frame is the fixed frame turned
//! by `R = Rz(−in-plane) · Rx(−out-of-plane) · Ry(−gantry)`; in it the source sits at
//! `(SourceOffsetX, SourceOffsetY, SourceToIsocenterDistance)` and projection coordinates `(u, v)` at
//! `(u + ProjectionOffsetX, v + ProjectionOffsetY, SID − SDD)`. RTK keeps the projection images' origin
//! and spacing with the images, not in the XML: ctrecon reads and writes the XML for images whose origin
//! is centred (`−(n−1)/2 · spacing`, the middle element at projection coordinate 0), so the projection
//! origin is the panel's middle and the pitch is given beside the file.
//!
//! Each projection's `<Matrix>` (3 × 4, fixed frame to projection coordinates) is written as RTK writes it
//! and checked on reading against the one the parameters give, as RTK's own reader does.

use std::fmt::Write as _;

use quick_xml::Reader;
use quick_xml::events::Event;

use super::angles::MAX_VIEWS;
use super::per_view::{ConeVectors, VectorPanel, cone_vectors};
use super::vectors::{Vec3, Views3, cross3, dot3, norm3, scale3, sub3};
use crate::recon::error::GeometryError;

/// The nine numbers RTK keeps per projection (mm and degrees).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RtkProjection {
    pub sid: f64,
    pub sdd: f64,
    pub gantry_deg: f64,
    pub projection_offset: [f64; 2],
    pub out_of_plane_deg: f64,
    pub in_plane_deg: f64,
    pub source_offset: [f64; 2],
}

/// Projection matrices of read files may differ from the parameters' by this much, relative to the
/// largest entry of their row (RTK writes 15 significant digits).
const MATRIX_TOLERANCE: f64 = 1e-6;

fn invalid(msg: String) -> GeometryError {
    GeometryError::Invalid(msg)
}

fn rtk_of(p: Vec3) -> Vec3 {
    [p[0], p[2], -p[1]]
}

fn ctrecon_of(p: Vec3) -> Vec3 {
    [p[0], -p[2], p[1]]
}

/// `R · p` with `R = Rz(a) · Rx(b) · Ry(c)` given as its rows.
fn rotation(a: f64, b: f64, c: f64) -> [Vec3; 3] {
    let (sa, ca) = a.sin_cos();
    let (sb, cb) = b.sin_cos();
    let (sc, cc) = c.sin_cos();
    // Rx(b)·Ry(c), then Rz(a) mixes its first two rows.
    let r0 = [cc, 0.0, sc];
    let r1 = [sb * sc, cb, -sb * cc];
    let r2 = [-cb * sc, sb, cb * cc];
    [
        [
            ca * r0[0] - sa * r1[0],
            ca * r0[1] - sa * r1[1],
            ca * r0[2] - sa * r1[2],
        ],
        [
            sa * r0[0] + ca * r1[0],
            sa * r0[1] + ca * r1[1],
            sa * r0[2] + ca * r1[2],
        ],
        r2,
    ]
}

impl RtkProjection {
    /// Rows of the rotation from RTK's fixed frame to this projection's frame.
    fn rows(&self) -> [Vec3; 3] {
        rotation(
            -self.in_plane_deg.to_radians(),
            -self.out_of_plane_deg.to_radians(),
            -self.gantry_deg.to_radians(),
        )
    }

    /// RTK's 3 × 4 matrix from fixed-frame points to homogeneous projection coordinates.
    pub fn matrix(&self) -> [[f64; 4]; 3] {
        let [ru, rv, rw] = self.rows();
        let [sox, soy] = self.source_offset;
        let [pox, poy] = self.projection_offset;
        let (sid, sdd) = (self.sid, self.sdd);
        // u·w = (sox − pox)(q_z − sid) − sdd (q_x − sox), v likewise, w = q_z − sid, for q = R p.
        let row = |r: Vec3, off: f64, src: f64| {
            let k = src - off;
            [
                -sdd * r[0] + k * rw[0],
                -sdd * r[1] + k * rw[1],
                -sdd * r[2] + k * rw[2],
                -k * sid + sdd * src,
            ]
        };
        [
            row(ru, pox, sox),
            row(rv, poy, soy),
            [rw[0], rw[1], rw[2], -sid],
        ]
    }

    /// `(source, projection origin, u axis, v axis)` in ctrecon's frame.
    fn vectors(&self) -> (Vec3, Vec3, Vec3, Vec3) {
        let [ru, rv, rw] = self.rows();
        // The inverse rotation is the transpose: a rotated-frame point q is Σ q_i · row_i.
        let back = |q: Vec3| {
            ctrecon_of([
                q[0] * ru[0] + q[1] * rv[0] + q[2] * rw[0],
                q[0] * ru[1] + q[1] * rv[1] + q[2] * rw[1],
                q[0] * ru[2] + q[1] * rv[2] + q[2] * rw[2],
            ])
        };
        let [sox, soy] = self.source_offset;
        let [pox, poy] = self.projection_offset;
        (
            back([sox, soy, self.sid]),
            back([pox, poy, self.sid - self.sdd]),
            back([1.0, 0.0, 0.0]),
            back([0.0, 1.0, 0.0]),
        )
    }

    /// RTK's parameters of one view: source `s`, panel middle `d` and unit axes `eu`, `ev` in ctrecon's
    /// frame.
    pub fn from_vectors(s: Vec3, d: Vec3, eu: Vec3, ev: Vec3) -> Result<Self, String> {
        let (s, d, eu, ev) = (rtk_of(s), rtk_of(d), rtk_of(eu), rtk_of(ev));
        let n = cross3(eu, ev);
        if dot3(sub3(s, d), n) <= 0.0 {
            return Err(
                "the panel faces away from the source along u × v (RTK cannot express a mirrored panel: \
                 reverse the columns)"
                    .into(),
            );
        }
        let b = n[1].clamp(-1.0, 1.0).asin();
        let c = (-n[0]).atan2(n[2]);
        let a = (-eu[1]).atan2(ev[1]);
        let sid = dot3(s, n);
        if sid <= 0.0 {
            return Err(format!(
                "the source is {sid} mm from the rotation axis' plane along the panel normal; RTK needs it in front"
            ));
        }
        let zd = dot3(d, n);
        Ok(RtkProjection {
            sid,
            sdd: sid - zd,
            gantry_deg: normalise_deg(-c.to_degrees()),
            projection_offset: [dot3(d, eu), dot3(d, ev)],
            out_of_plane_deg: -b.to_degrees(),
            in_plane_deg: -a.to_degrees(),
            source_offset: [dot3(s, eu), dot3(s, ev)],
        })
    }
}

/// An angle in [0°, 360°), as RTK keeps gantry angles.
fn normalise_deg(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r >= 360.0 { 0.0 } else { r }
}

/// The RTK XML of a cone-beam geometry whose projection images have a centred origin.
pub fn to_rtk_xml(views: &Views3) -> Result<String, GeometryError> {
    if views.detector.shape != super::vectors::PanelShape::Flat {
        return Err(GeometryError::Invalid(
            "RTK's circular geometry XML describes flat panels; a cylindrical detector has no such form".into(),
        ));
    }
    let vectors = cone_vectors(views);
    let mut out = String::from(
        "<?xml version=\"1.0\"?>\n<!DOCTYPE RTKGEOMETRY>\n<RTKThreeDCircularGeometry version=\"3\">\n",
    );
    for (k, r) in vectors.vectors.iter().enumerate() {
        let p = |i: usize| [r[i], r[i + 1], r[i + 2]];
        let (s, d, u, v) = (p(0), p(3), p(6), p(9));
        let eu = scale3(u, 1.0 / norm3(u));
        let ev = scale3(v, 1.0 / norm3(v));
        let q = RtkProjection::from_vectors(s, d, eu, ev)
            .map_err(|e| invalid(format!("view {k}: {e}")))?;
        let m = q.matrix();
        let _ = write!(
            out,
            "  <Projection>\n    <SourceToIsocenterDistance>{}</SourceToIsocenterDistance>\n    \
             <SourceToDetectorDistance>{}</SourceToDetectorDistance>\n    <GantryAngle>{}</GantryAngle>\n    \
             <ProjectionOffsetX>{}</ProjectionOffsetX>\n    <ProjectionOffsetY>{}</ProjectionOffsetY>\n    \
             <OutOfPlaneAngle>{}</OutOfPlaneAngle>\n    <InPlaneAngle>{}</InPlaneAngle>\n    \
             <SourceOffsetX>{}</SourceOffsetX>\n    <SourceOffsetY>{}</SourceOffsetY>\n    <Matrix>\n",
            q.sid,
            q.sdd,
            q.gantry_deg,
            q.projection_offset[0],
            q.projection_offset[1],
            q.out_of_plane_deg,
            q.in_plane_deg,
            q.source_offset[0],
            q.source_offset[1],
        );
        for row in m {
            let _ = writeln!(out, "      {} {} {} {}", row[0], row[1], row[2], row[3]);
        }
        out.push_str("    </Matrix>\n  </Projection>\n");
    }
    out.push_str("</RTKThreeDCircularGeometry>\n");
    Ok(out)
}

/// Values of one projection as read: globals first, then the projection's own elements.
#[derive(Debug, Clone, Default)]
struct Fields {
    sid: Option<f64>,
    sdd: Option<f64>,
    gantry: Option<f64>,
    pox: Option<f64>,
    poy: Option<f64>,
    oop: Option<f64>,
    ipa: Option<f64>,
    sox: Option<f64>,
    soy: Option<f64>,
    radius: Option<f64>,
    matrix: Option<Vec<f64>>,
}

impl Fields {
    fn set(&mut self, name: &str, text: &str, at: &str) -> Result<(), GeometryError> {
        let number = || {
            text.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    invalid(format!(
                        "{at}<{name}>: {:?} is not a finite number",
                        text.trim()
                    ))
                })
        };
        match name {
            "SourceToIsocenterDistance" => self.sid = Some(number()?),
            "SourceToDetectorDistance" => self.sdd = Some(number()?),
            "GantryAngle" => self.gantry = Some(number()?),
            "ProjectionOffsetX" => self.pox = Some(number()?),
            "ProjectionOffsetY" => self.poy = Some(number()?),
            "OutOfPlaneAngle" => self.oop = Some(number()?),
            "InPlaneAngle" => self.ipa = Some(number()?),
            "SourceOffsetX" => self.sox = Some(number()?),
            "SourceOffsetY" => self.soy = Some(number()?),
            "RadiusCylindricalDetector" => self.radius = Some(number()?),
            "Matrix" => {
                let m: Result<Vec<f64>, _> = text.split_whitespace().map(str::parse).collect();
                match m {
                    Ok(m) if m.len() == 12 && m.iter().all(|v| v.is_finite()) => {
                        self.matrix = Some(m)
                    }
                    _ => {
                        return Err(invalid(format!(
                            "{at}<Matrix>: expected 12 finite numbers (3 rows of 4)"
                        )));
                    }
                }
            }
            other => {
                return Err(invalid(format!(
                    "{at}<{other}>: not an element of RTK's circular geometry"
                )));
            }
        }
        Ok(())
    }

    fn projection(&self, k: usize) -> Result<RtkProjection, GeometryError> {
        let at = format!("<Projection> {k}: ");
        let need = |v: Option<f64>, name: &str| {
            v.ok_or_else(|| invalid(format!("{at}<{name}> is missing")))
        };
        if let Some(r) = self.radius
            && r != 0.0
        {
            return Err(invalid(format!(
                "{at}<RadiusCylindricalDetector> is {r}: ctrecon reads flat panels only"
            )));
        }
        let p = RtkProjection {
            sid: need(self.sid, "SourceToIsocenterDistance")?,
            sdd: need(self.sdd, "SourceToDetectorDistance")?,
            gantry_deg: need(self.gantry, "GantryAngle")?,
            projection_offset: [self.pox.unwrap_or(0.0), self.poy.unwrap_or(0.0)],
            out_of_plane_deg: self.oop.unwrap_or(0.0),
            in_plane_deg: self.ipa.unwrap_or(0.0),
            source_offset: [self.sox.unwrap_or(0.0), self.soy.unwrap_or(0.0)],
        };
        let Some(read) = &self.matrix else {
            return Err(invalid(format!("{at}<Matrix> is missing")));
        };
        for (i, row) in p.matrix().iter().enumerate() {
            let scale = row.iter().fold(1.0f64, |m, v| m.max(v.abs()));
            for (j, v) in row.iter().enumerate() {
                let got = read[4 * i + j];
                if (got - v).abs() > MATRIX_TOLERANCE * scale {
                    return Err(invalid(format!(
                        "{at}<Matrix> entry [{i}][{j}] is {got}, the parameters give {v}: matrix and parameters \
                         disagree"
                    )));
                }
            }
        }
        Ok(p)
    }
}

/// The projections of an RTK geometry XML, in file order.
pub fn parse_rtk_xml(text: &str) -> Result<Vec<RtkProjection>, GeometryError> {
    let mut reader = Reader::from_str(text);
    let mut globals = Fields::default();
    let mut current: Option<Fields> = None;
    let mut element: Option<String> = None;
    let mut value = String::new();
    let mut out = Vec::new();
    let mut root = false;
    loop {
        let event = reader
            .read_event()
            .map_err(|e| invalid(format!("not well-formed XML: {e}")))?;
        match event {
            Event::Start(e) => {
                let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
                match (name.as_str(), root, &current) {
                    ("RTKThreeDCircularGeometry", false, _) => root = true,
                    ("Projection", true, None) => {
                        if out.len() >= MAX_VIEWS {
                            return Err(invalid(format!("more than {MAX_VIEWS} projections")));
                        }
                        current = Some(globals.clone());
                    }
                    (_, true, _) if element.is_none() => {
                        element = Some(name);
                        value.clear();
                    }
                    _ => {
                        return Err(invalid(format!(
                            "unexpected element <{name}> (not an RTK circular geometry)"
                        )));
                    }
                }
            }
            Event::Text(t) if element.is_some() => {
                let t = t
                    .decode()
                    .map_err(|e| invalid(format!("not well-formed XML: {e}")))?;
                value.push_str(&t);
            }
            Event::End(e) => {
                let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
                if let Some(el) = element.take() {
                    let at = match &current {
                        Some(_) => format!("<Projection> {}: ", out.len()),
                        None => String::new(),
                    };
                    match &mut current {
                        Some(f) => f.set(&el, &value, &at)?,
                        None => globals.set(&el, &value, &at)?,
                    }
                } else if name == "Projection"
                    && let Some(f) = current.take()
                {
                    out.push(f.projection(out.len())?);
                }
            }
            Event::Empty(e) => {
                let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
                return Err(invalid(format!("<{name}/> is empty")));
            }
            Event::Eof => {
                if current.is_some() || element.is_some() {
                    return Err(invalid(
                        "the file ends inside <Projection> (truncated?)".into(),
                    ));
                }
                break;
            }
            _ => {}
        }
    }
    if !root {
        return Err(invalid(
            "no <RTKThreeDCircularGeometry> element: not an RTK geometry file".into(),
        ));
    }
    if out.is_empty() {
        return Err(invalid("the RTK geometry has no <Projection>".into()));
    }
    Ok(out)
}

/// A cone-beam geometry from RTK's XML, for projection images of `nu × nv` elements of `du × dv` mm with a
/// centred origin.
pub fn from_rtk_xml(
    text: &str,
    panel: VectorPanel,
    pitch_mm: [f64; 2],
) -> Result<ConeVectors, GeometryError> {
    let [du, dv] = pitch_mm;
    if !(du > 0.0 && dv > 0.0 && du.is_finite() && dv.is_finite()) {
        return Err(invalid(format!(
            "the detector pitch must be positive, got {du} × {dv} mm"
        )));
    }
    let vectors = parse_rtk_xml(text)?
        .iter()
        .map(|p| {
            let (s, d, eu, ev) = p.vectors();
            let (u, v) = (scale3(eu, du), scale3(ev, dv));
            [
                s[0], s[1], s[2], d[0], d[1], d[2], u[0], u[1], u[2], v[0], v[1], v[2],
            ]
        })
        .collect();
    Ok(ConeVectors {
        detector: panel,
        vectors,
    })
}
