//! Multiplanar reformatting in patient space: oblique planes, thick slabs (average, MIP, MinIP), slab series
//! (e.g. 3 mm thick every 3 mm), curved planes along a polyline, and rotating MIPs.
//!
//! A [`Plane`] is a centre point and two orthonormal in-plane axes in patient millimetres (LPS): `u` runs along
//! image columns (left → right on screen), `v` along rows (top → bottom). The slab normal is `u × v`.

use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::display::ProjectionKind;
use super::error::VolumeError;
use super::frame::Volume;
use super::resample::trilinear;
use crate::recon::geometry::vectors::{cross3 as cross, dot3 as dot};

type V3 = [f64; 3];

fn unit(a: V3) -> Option<V3> {
    let n = dot(a, a).sqrt();
    (n > 1e-12 && n.is_finite()).then(|| a.map(|c| c / n))
}
fn axpy(p: V3, s: f64, d: V3) -> V3 {
    [p[0] + s * d[0], p[1] + s * d[1], p[2] + s * d[2]]
}

/// An image plane in patient space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plane {
    /// Patient position (mm) of the image centre.
    pub centre_mm: V3,
    /// Unit column direction.
    pub u: V3,
    /// Unit row direction (orthogonal to `u`).
    pub v: V3,
    /// Image size in pixels (columns, rows).
    pub size: [usize; 2],
    /// Pixel size (mm).
    pub pixel_mm: f64,
}

/// Largest image side any reformat produces.
pub const MAX_SIDE: usize = 8192;

impl Plane {
    /// A plane through `centre_mm` perpendicular to `normal`, rows pointing as close to inferior (−z) as the
    /// normal allows (so superior is at the top), or posterior for axial-like planes.
    pub fn oblique(
        centre_mm: V3,
        normal: V3,
        size: [usize; 2],
        pixel_mm: f64,
    ) -> Result<Self, VolumeError> {
        let n = unit(normal).ok_or_else(|| VolumeError::InvalidParameter {
            name: "normal",
            reason: "must be a finite non-zero vector".into(),
        })?;
        let down = if n[2].abs() > 0.9 {
            [0.0, 1.0, 0.0]
        } else {
            [0.0, 0.0, -1.0]
        };
        // v: `down` with its normal component removed.
        let v =
            unit(axpy(down, -dot(down, n), n)).ok_or_else(|| VolumeError::InvalidParameter {
                name: "normal",
                reason: "degenerate".into(),
            })?;
        let u = cross(v, n);
        let plane = Self {
            centre_mm,
            u,
            v,
            size,
            pixel_mm,
        };
        plane.validate()?;
        Ok(plane)
    }

    pub fn validate(&self) -> Result<(), VolumeError> {
        let bad = |reason: &str| VolumeError::InvalidParameter {
            name: "plane",
            reason: reason.into(),
        };
        if !(self.pixel_mm.is_finite() && self.pixel_mm > 0.0) {
            return Err(bad("pixel_mm must be finite and positive"));
        }
        if self.size.iter().any(|&s| s == 0 || s > MAX_SIDE) {
            return Err(bad("size must be within 1..=8192 pixels"));
        }
        if self.centre_mm.iter().any(|c| !c.is_finite()) {
            return Err(bad("centre_mm must be finite"));
        }
        let (lu, lv) = (dot(self.u, self.u), dot(self.v, self.v));
        if (lu - 1.0).abs() > 1e-6 || (lv - 1.0).abs() > 1e-6 || dot(self.u, self.v).abs() > 1e-6 {
            return Err(bad("u and v must be orthonormal"));
        }
        Ok(())
    }

    /// Unit normal `u × v`.
    pub fn normal(&self) -> V3 {
        cross(self.u, self.v)
    }

    /// Patient position of pixel `(row, col)` shifted by `offset_mm` along the normal.
    pub fn point(&self, row: usize, col: usize, offset_mm: f64) -> V3 {
        let cu = (col as f64 - (self.size[0] as f64 - 1.0) / 2.0) * self.pixel_mm;
        let cv = (row as f64 - (self.size[1] as f64 - 1.0) / 2.0) * self.pixel_mm;
        axpy(
            axpy(axpy(self.centre_mm, cu, self.u), cv, self.v),
            offset_mm,
            self.normal(),
        )
    }
}

/// A slab through a plane: `thickness_mm` along the normal, combined by `kind`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Slab {
    pub thickness_mm: f64,
    pub kind: ProjectionKind,
}

fn smallest_spacing(vol: &Volume) -> f64 {
    vol.frame
        .spacing_mm
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min)
}

/// Samples along one ray combined by a [`ProjectionKind`] (maximum, minimum or mean).
struct Combine {
    kind: ProjectionKind,
    acc: Option<f32>,
    n: u32,
}

impl Combine {
    fn new(kind: ProjectionKind) -> Self {
        Self {
            kind,
            acc: None,
            n: 0,
        }
    }

    #[inline]
    fn add(&mut self, s: f32) {
        self.n += 1;
        self.acc = Some(match (self.acc, self.kind) {
            (None, _) => s,
            (Some(a), ProjectionKind::Max) => a.max(s),
            (Some(a), ProjectionKind::Min) => a.min(s),
            (Some(a), ProjectionKind::Mean) => a + s,
        });
    }

    /// The combined value; `None` when no sample was added.
    fn value(&self) -> Option<f32> {
        self.acc.map(|a| match self.kind {
            ProjectionKind::Mean => a / self.n as f32,
            _ => a,
        })
    }
}

/// Combine samples along offsets `offsets` at every pixel of `plane`; pixels with no sample inside get `fill`.
fn render(
    vol: &Volume,
    rows: usize,
    cols: usize,
    point: impl Fn(usize, usize, f64) -> V3 + Sync,
    offsets: &[f64],
    kind: ProjectionKind,
    fill: f32,
) -> Array2<f32> {
    let data = vol.data.view();
    let mut out = Array2::from_elem((rows, cols), fill);
    let Some(map) = vol.frame.index_map() else {
        return out;
    };
    debug_assert!(offsets.windows(2).all(|w| w[0] <= w[1]), "offsets ascend");
    let (nz, ny, nx) = vol.data.dim();
    let last = [nz, ny, nx].map(|n| n as f64 - 1.0);
    out.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(r, mut row)| {
            for (c, px) in row.iter_mut().enumerate() {
                // `point` is affine in the offset: index = i0 + o · d. Keep the offsets whose sample lies in the
                // volume (a small margin; trilinear checks again).
                let i0 = map.index(point(r, c, 0.0));
                let d = if offsets.len() > 1 {
                    let i1 = map.index(point(r, c, 1.0));
                    [i1[0] - i0[0], i1[1] - i0[1], i1[2] - i0[2]]
                } else {
                    [0.0; 3]
                };
                let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
                for a in 0..3 {
                    if d[a].abs() < 1e-12 {
                        if i0[a] < -1e-6 || i0[a] > last[a] + 1e-6 {
                            hi = f64::NEG_INFINITY;
                        }
                    } else {
                        let t1 = (-1e-6 - i0[a]) / d[a];
                        let t2 = (last[a] + 1e-6 - i0[a]) / d[a];
                        lo = lo.max(t1.min(t2));
                        hi = hi.min(t1.max(t2));
                    }
                }
                if lo > hi {
                    continue;
                }
                let start = offsets.partition_point(|&o| o < lo);
                let end = offsets.partition_point(|&o| o <= hi);
                let mut acc = Combine::new(kind);
                for &o in &offsets[start..end.max(start)] {
                    let idx = [i0[0] + o * d[0], i0[1] + o * d[1], i0[2] + o * d[2]];
                    if let Some(s) = trilinear(&data, idx) {
                        acc.add(s);
                    }
                }
                if let Some(v) = acc.value() {
                    *px = v;
                }
            }
        });
    out
}

fn slab_offsets(thickness_mm: f64, step_mm: f64) -> Result<Vec<f64>, VolumeError> {
    if !(thickness_mm.is_finite() && thickness_mm >= 0.0) {
        return Err(VolumeError::InvalidParameter {
            name: "thickness_mm",
            reason: format!("must be finite and non-negative, got {thickness_mm}"),
        });
    }
    let n = (thickness_mm / step_mm).floor() as usize + 1;
    if n > 4 * MAX_SIDE {
        return Err(VolumeError::InvalidParameter {
            name: "thickness_mm",
            reason: "slab too thick for the volume's sampling".into(),
        });
    }
    Ok((0..n)
        .map(|k| (k as f64 - (n as f64 - 1.0) / 2.0) * step_mm)
        .collect())
}

/// Reformat `vol` on `plane`: a thin plane, or a slab when `slab` is given. Outside the volume: `fill`.
pub fn reformat(
    vol: &Volume,
    plane: &Plane,
    slab: Option<Slab>,
    fill: f32,
) -> Result<Array2<f32>, VolumeError> {
    plane.validate()?;
    let (offsets, kind) = match slab {
        None => (vec![0.0], ProjectionKind::Mean),
        Some(s) => (
            slab_offsets(s.thickness_mm, smallest_spacing(vol) / 2.0)?,
            s.kind,
        ),
    };
    Ok(render(
        vol,
        plane.size[1],
        plane.size[0],
        |r, c, o| plane.point(r, c, o),
        &offsets,
        kind,
        fill,
    ))
}

/// A series of slabs `thickness_mm` thick every `spacing_mm` along the plane normal, centred on the plane and
/// covering ±`extent_mm` (clinical thick-slab reformats, e.g. 3 mm every 3 mm).
pub fn slab_series(
    vol: &Volume,
    plane: &Plane,
    slab: Slab,
    spacing_mm: f64,
    extent_mm: f64,
    fill: f32,
) -> Result<Vec<Array2<f32>>, VolumeError> {
    if !(spacing_mm.is_finite() && spacing_mm > 0.0 && extent_mm.is_finite() && extent_mm >= 0.0) {
        return Err(VolumeError::InvalidParameter {
            name: "spacing_mm",
            reason: "spacing must be positive and extent non-negative".into(),
        });
    }
    let count = (2.0 * extent_mm / spacing_mm).floor() as usize + 1;
    if count > MAX_SIDE {
        return Err(VolumeError::InvalidParameter {
            name: "spacing_mm",
            reason: format!("{count} slabs is too many"),
        });
    }
    (0..count)
        .map(|s| {
            let shift = (s as f64 - (count as f64 - 1.0) / 2.0) * spacing_mm;
            let moved = Plane {
                centre_mm: axpy(plane.centre_mm, shift, plane.normal()),
                ..*plane
            };
            reformat(vol, &moved, Some(slab), fill)
        })
        .collect()
}

/// Curved MPR: columns follow the polyline `points_mm` (sampled every `pixel_mm` of arc length), rows run along
/// the unit direction `down` (default inferior, −z) over `height` pixels centred on the curve.
pub fn curved(
    vol: &Volume,
    points_mm: &[V3],
    down: Option<V3>,
    height: usize,
    pixel_mm: f64,
    fill: f32,
) -> Result<Array2<f32>, VolumeError> {
    let bad = |reason: String| VolumeError::InvalidParameter {
        name: "curve",
        reason,
    };
    if points_mm.len() < 2 {
        return Err(bad("needs at least two points".into()));
    }
    if points_mm.iter().flatten().any(|c| !c.is_finite()) {
        return Err(bad("points must be finite".into()));
    }
    if !(pixel_mm.is_finite() && pixel_mm > 0.0) || height == 0 || height > MAX_SIDE {
        return Err(bad(
            "pixel_mm must be positive and height within 1..=8192".into()
        ));
    }
    let down = unit(down.unwrap_or([0.0, 0.0, -1.0]))
        .ok_or_else(|| bad("`down` must be non-zero".into()))?;
    // Resample the polyline by arc length.
    let mut samples = vec![points_mm[0]];
    let mut carry = 0.0;
    for w in points_mm.windows(2) {
        let d = [w[1][0] - w[0][0], w[1][1] - w[0][1], w[1][2] - w[0][2]];
        let len = dot(d, d).sqrt();
        let mut t = pixel_mm - carry;
        while t <= len {
            samples.push(axpy(w[0], t / len, d));
            if samples.len() > MAX_SIDE {
                return Err(bad("the curve is longer than 8192 pixels".into()));
            }
            t += pixel_mm;
        }
        carry = len - (t - pixel_mm);
    }
    let cols = samples.len();
    Ok(render(
        vol,
        height,
        cols,
        |r, c, _| {
            axpy(
                samples[c],
                (r as f64 - (height as f64 - 1.0) / 2.0) * pixel_mm,
                down,
            )
        },
        &[0.0],
        ProjectionKind::Mean,
        fill,
    ))
}

/// The rays of a rotating projection: image geometry and the sample offsets along each ray.
struct RotatingRays<'a> {
    centre: V3,
    pixel: f64,
    width: usize,
    height: usize,
    offsets: &'a [f64],
}

fn is_axis_aligned(f: &super::frame::Frame) -> bool {
    f.direction
        .iter()
        .zip(super::frame::Frame::AXIS_ALIGNED)
        .all(|(a, b)| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9))
}

/// [`rotating_projection`] for an axis-aligned frame. Every ray of an output row lies in one axial plane, so the
/// row's plane is interpolated along z once and shared by all angles; rays then march with bilinear samples.
/// Mathematically the same samples as the general path (trilinear = bilinear of the z-interpolated plane).
fn rotating_axis_aligned(
    vol: &Volume,
    rays: &RotatingRays<'_>,
    views: &[(V3, V3)],
    kind: ProjectionKind,
    fill: f32,
) -> Vec<Array2<f32>> {
    let (nz, ny, nx) = vol.data.dim();
    let f = &vol.frame;
    let data = vol.data.view();
    let (w, h) = (rays.width, rays.height);
    let last = [(ny - 1) as f64, (nx - 1) as f64];
    let eps = 1e-9;
    // rows[r] holds row r of every frame, frame after frame.
    let rows: Vec<Vec<f32>> = (0..h)
        .into_par_iter()
        .map(|r| {
            let mut out = vec![fill; views.len() * w];
            let z = rays.centre[2] - (r as f64 - (h as f64 - 1.0) / 2.0) * rays.pixel;
            let k = (z - f.origin_mm[2]) / f.spacing_mm[2];
            if !(k > -eps && k < (nz - 1) as f64 + eps) {
                return out;
            }
            let k0 = (k.max(0.0).floor() as usize).min(nz.saturating_sub(2));
            let fk = (k - k0 as f64).clamp(0.0, 1.0) as f32;
            let a = data.index_axis(ndarray::Axis(0), k0);
            let plane: Vec<f32> = if nz == 1 {
                a.iter().copied().collect()
            } else {
                let b = data.index_axis(ndarray::Axis(0), k0 + 1);
                a.iter()
                    .zip(b.iter())
                    .map(|(&p, &q)| p + (q - p) * fk)
                    .collect()
            };
            let at = |j: usize, i: usize| plane[j.min(ny - 1) * nx + i.min(nx - 1)] as f64;
            for (v_index, (view, u)) in views.iter().enumerate() {
                for c in 0..w {
                    let cu = (c as f64 - (w as f64 - 1.0) / 2.0) * rays.pixel;
                    // Index (j, i) of the ray's point at offset 0 and its step per mm of offset.
                    let x0 = rays.centre[0] + cu * u[0];
                    let y0 = rays.centre[1] + cu * u[1];
                    let p0 = [
                        (y0 - f.origin_mm[1]) / f.spacing_mm[1],
                        (x0 - f.origin_mm[0]) / f.spacing_mm[0],
                    ];
                    let d = [view[1] / f.spacing_mm[1], view[0] / f.spacing_mm[0]];
                    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
                    for a in 0..2 {
                        if d[a].abs() < 1e-12 {
                            if p0[a] < -eps || p0[a] > last[a] + eps {
                                hi = f64::NEG_INFINITY;
                            }
                        } else {
                            let t1 = (-eps - p0[a]) / d[a];
                            let t2 = (last[a] + eps - p0[a]) / d[a];
                            lo = lo.max(t1.min(t2));
                            hi = hi.min(t1.max(t2));
                        }
                    }
                    if lo > hi {
                        continue;
                    }
                    let start = rays.offsets.partition_point(|&o| o < lo);
                    let end = rays.offsets.partition_point(|&o| o <= hi).max(start);
                    let mut acc = Combine::new(kind);
                    for &o in &rays.offsets[start..end] {
                        let (j, i) = (p0[0] + o * d[0], p0[1] + o * d[1]);
                        if !(j > -eps && j < last[0] + eps && i > -eps && i < last[1] + eps) {
                            continue;
                        }
                        let j0 = (j.max(0.0).floor() as usize).min(ny.saturating_sub(2));
                        let i0 = (i.max(0.0).floor() as usize).min(nx.saturating_sub(2));
                        let (fj, fi) = (
                            (j - j0 as f64).clamp(0.0, 1.0),
                            (i - i0 as f64).clamp(0.0, 1.0),
                        );
                        let top = at(j0, i0) + (at(j0, i0 + 1) - at(j0, i0)) * fi;
                        let bottom = at(j0 + 1, i0) + (at(j0 + 1, i0 + 1) - at(j0 + 1, i0)) * fi;
                        acc.add((top + (bottom - top) * fj) as f32);
                    }
                    if let Some(v) = acc.value() {
                        out[v_index * w + c] = v;
                    }
                }
            }
            out
        })
        .collect();
    (0..views.len())
        .map(|v| Array2::from_shape_fn((h, w), |(r, c)| rows[r][v * w + c]))
        .collect()
}

/// Maximum (or other) projections seen from `angles_deg` around the superior (z) axis through the volume
/// centre; angle 0 looks from anterior to posterior (a coronal MIP), 90° from the patient's left.
pub fn rotating_projection(
    vol: &Volume,
    angles_deg: &[f64],
    kind: ProjectionKind,
    fill: f32,
) -> Result<Vec<Array2<f32>>, VolumeError> {
    let (nz, ny, nx) = vol.data.dim();
    if nz == 0 || ny == 0 || nx == 0 {
        return Err(VolumeError::Empty);
    }
    if angles_deg.is_empty() || angles_deg.len() > 720 || angles_deg.iter().any(|a| !a.is_finite())
    {
        return Err(VolumeError::InvalidParameter {
            name: "angles",
            reason: "give 1 to 720 finite angles".into(),
        });
    }
    let f = &vol.frame;
    let lo = f.position(0.0, 0.0, 0.0);
    let hi = f.position((nz - 1) as f64, (ny - 1) as f64, (nx - 1) as f64);
    let centre = [
        (lo[0] + hi[0]) / 2.0,
        (lo[1] + hi[1]) / 2.0,
        (lo[2] + hi[2]) / 2.0,
    ];
    let half = [
        (hi[0] - lo[0]).abs() / 2.0,
        (hi[1] - lo[1]).abs() / 2.0,
        (hi[2] - lo[2]).abs() / 2.0,
    ];
    let pixel = smallest_spacing(vol).max(0.5);
    let radius = half[0].hypot(half[1]);
    let half_width = (radius / pixel).ceil() as usize;
    let width = (2 * half_width + 1).clamp(1, MAX_SIDE);
    let height = ((2.0 * half[2] / pixel).ceil() as usize + 1).clamp(1, MAX_SIDE);
    let offsets: Vec<f64> = {
        let n = 2 * half_width + 1;
        (0..n)
            .map(|k| (k as f64 - (n as f64 - 1.0) / 2.0) * pixel)
            .collect()
    };
    let view_of = |a: f64| {
        let t = a.to_radians();
        // Looking along +y at 0°: the viewer stands anterior; columns run to the patient's left.
        ([-t.sin(), t.cos(), 0.0], [t.cos(), t.sin(), 0.0])
    };
    let rays = RotatingRays {
        centre,
        pixel,
        width,
        height,
        offsets: &offsets,
    };
    let views: Vec<_> = angles_deg.iter().map(|&a| view_of(a)).collect();
    Ok(if is_axis_aligned(f) {
        rotating_axis_aligned(vol, &rays, &views, kind, fill)
    } else {
        rotating_general(vol, &rays, &views, kind, fill)
    })
}

/// [`rotating_projection`] for any frame: trilinear samples along every ray.
fn rotating_general(
    vol: &Volume,
    rays: &RotatingRays<'_>,
    views: &[(V3, V3)],
    kind: ProjectionKind,
    fill: f32,
) -> Vec<Array2<f32>> {
    let (w, h, pixel) = (rays.width, rays.height, rays.pixel);
    views
        .iter()
        .map(|&(view, u)| {
            let v = [0.0, 0.0, -1.0];
            render(
                vol,
                h,
                w,
                |r, c, o| {
                    let cu = (c as f64 - (w as f64 - 1.0) / 2.0) * pixel;
                    let cv = (r as f64 - (h as f64 - 1.0) / 2.0) * pixel;
                    axpy(axpy(axpy(rays.centre, cu, u), cv, v), o, view)
                },
                rays.offsets,
                kind,
                fill,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::frame::Frame;
    use ndarray::Array3;

    /// 1 mm voxels holding x + 10 y + 100 z (mm), centred on the origin.
    fn linear() -> Volume {
        let frame = Frame {
            spacing_mm: [1.0; 3],
            origin_mm: [-10.0, -10.0, -10.0],
            direction: Frame::AXIS_ALIGNED,
        };
        let data = Array3::from_shape_fn((21, 21, 21), |(k, j, i)| {
            let p = frame.position(k as f64, j as f64, i as f64);
            (p[0] + 10.0 * p[1] + 100.0 * p[2]) as f32
        });
        Volume { data, frame }
    }

    #[test]
    fn an_oblique_plane_samples_the_field_where_it_lies() {
        let vol = linear();
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let plane = Plane::oblique([1.0, 2.0, 3.0], [s, s, 0.0], [9, 7], 1.0).unwrap();
        let img = reformat(&vol, &plane, None, f32::NAN).unwrap();
        assert_eq!(img.dim(), (7, 9));
        for (r, c) in [(0, 0), (3, 4), (6, 8)] {
            let p = plane.point(r, c, 0.0);
            let want = p[0] + 10.0 * p[1] + 100.0 * p[2];
            assert!((img[[r, c]] as f64 - want).abs() < 1e-3, "({r},{c})");
        }
        // Superior at the top: rows run toward −z.
        assert!(img[[0, 4]] > img[[6, 4]]);
    }

    #[test]
    fn a_thick_average_slab_of_a_linear_field_equals_the_centre_plane_and_mip_the_far_side() {
        let vol = linear();
        let plane = Plane::oblique([0.0; 3], [0.0, 0.0, 1.0], [5, 5], 1.0).unwrap();
        let thin = reformat(&vol, &plane, None, 0.0).unwrap();
        let avg = reformat(
            &vol,
            &plane,
            Some(Slab {
                thickness_mm: 3.0,
                kind: ProjectionKind::Mean,
            }),
            0.0,
        )
        .unwrap();
        let mip = reformat(
            &vol,
            &plane,
            Some(Slab {
                thickness_mm: 3.0,
                kind: ProjectionKind::Max,
            }),
            0.0,
        )
        .unwrap();
        for (a, (b, m)) in thin.iter().zip(avg.iter().zip(mip.iter())) {
            assert!((a - b).abs() < 1e-3);
            assert!((m - a - 150.0).abs() < 1e-2, "{m} vs {a}"); // +1.5 mm of z at 100 per mm
        }
        let series = slab_series(
            &vol,
            &plane,
            Slab {
                thickness_mm: 3.0,
                kind: ProjectionKind::Mean,
            },
            3.0,
            6.0,
            0.0,
        )
        .unwrap();
        assert_eq!(series.len(), 5);
        assert!(
            (series[4][[2, 2]] - series[2][[2, 2]] - 600.0 * plane.normal()[2] as f32).abs() < 1e-2
        );
    }

    #[test]
    fn curved_mpr_follows_the_polyline_by_arc_length() {
        let vol = linear();
        let pts = [[-5.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.0, 5.0, 0.0]];
        let img = curved(&vol, &pts, None, 3, 1.0, f32::NAN).unwrap();
        assert_eq!(img.dim(), (3, 16));
        // Column 12 is 2 mm along the second segment: (5, 2, 0).
        assert!((img[[1, 12]] - 25.0).abs() < 1e-3, "{}", img[[1, 12]]);
        assert!((img[[0, 12]] - 125.0).abs() < 1e-3);
        assert!(curved(&vol, &pts[..1], None, 3, 1.0, 0.0).is_err());
    }

    #[test]
    fn the_axis_aligned_rotating_projection_samples_like_the_general_one() {
        // Random values on an anisotropic axis-aligned grid; every kind and some oblique angles.
        let frame = Frame {
            spacing_mm: [1.0, 1.25, 2.5],
            origin_mm: [-9.0, -7.0, 3.0],
            direction: Frame::AXIS_ALIGNED,
        };
        let mut seed = 7u64;
        let data = Array3::from_shape_fn((9, 13, 17), |_| {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        });
        let vol = Volume { data, frame };
        let offsets: Vec<f64> = (0..41).map(|k| (k as f64 - 20.0) * 0.7).collect();
        let rays = RotatingRays {
            centre: [0.5, 1.0, 13.0],
            pixel: 0.7,
            width: 41,
            height: 33,
            offsets: &offsets,
        };
        let views: Vec<(V3, V3)> = [0.0f64, 17.0, 90.0, 135.0, 251.0]
            .iter()
            .map(|a| {
                let t = a.to_radians();
                ([-t.sin(), t.cos(), 0.0], [t.cos(), t.sin(), 0.0])
            })
            .collect();
        for kind in [
            ProjectionKind::Max,
            ProjectionKind::Min,
            ProjectionKind::Mean,
        ] {
            let fast = rotating_axis_aligned(&vol, &rays, &views, kind, -1.0);
            let slow = rotating_general(&vol, &rays, &views, kind, -1.0);
            for (a, b) in fast.iter().zip(&slow) {
                let worst = a
                    .iter()
                    .zip(b)
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0f32, f32::max);
                assert!(worst < 1e-5, "{kind:?}: {worst}");
                assert!(a.iter().any(|&x| x >= 0.0) && a.iter().any(|&x| x == -1.0));
            }
        }
    }

    #[test]
    fn rotating_mip_at_0_degrees_is_the_coronal_mip() {
        let mut data = Array3::<f32>::zeros((11, 11, 11));
        data[[8, 3, 2]] = 7.0; // z = 3, y = −2, x = −3 (mm)
        let vol = Volume {
            data,
            frame: Frame {
                spacing_mm: [1.0; 3],
                origin_mm: [-5.0; 3],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let frames = rotating_projection(&vol, &[0.0, 90.0], ProjectionKind::Max, 0.0).unwrap();
        let (h, w) = frames[0].dim();
        let at = |img: &Array2<f32>| {
            let (mut best, mut arg) = (0.0, (0, 0));
            for ((r, c), &v) in img.indexed_iter() {
                if v > best {
                    best = v;
                    arg = (r, c);
                }
            }
            (best, arg)
        };
        let (v0, (r0, c0)) = at(&frames[0]);
        assert!(v0 > 6.9);
        // Row: z = 3 mm above the centre → 3 px above the middle row; column: x = −3 → 3 px left.
        assert_eq!(r0 as f64, (h as f64 - 1.0) / 2.0 - 3.0);
        assert!((c0 as f64 - ((w as f64 - 1.0) / 2.0 - 3.0)).abs() <= 0.5);
        // At 90° the columns run along +y: y = −2 → 2 px left of the middle.
        let (_, (_, c1)) = at(&frames[1]);
        assert!((c1 as f64 - ((w as f64 - 1.0) / 2.0 - 2.0)).abs() <= 0.5);
    }
}
