//! Multiplanar reformatting in patient space: oblique planes, thick slabs (average, MIP, MinIP), slab series
//! (e.g. 3 mm thick every 3 mm) and curved planes along a polyline; rotating MIPs sample through it ([`super::rotating`]).
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

pub(super) type V3 = [f64; 3];

fn unit(a: V3) -> Option<V3> {
    let n = dot(a, a).sqrt();
    (n > 1e-12 && n.is_finite()).then(|| a.map(|c| c / n))
}
pub(super) fn axpy(p: V3, s: f64, d: V3) -> V3 {
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

/// Tolerance of [`whole_ceil`] and [`whole_floor`].
const WHOLE: f64 = 1e-6;

/// `x.ceil()` for a count of pixels or planes measured in millimetres: a value within 10⁻⁶ above a whole
/// number counts as that number, so that the rounding noise of a frame (a spacing of 0.7999999999999998
/// derived from slice positions) does not add a pixel, and with it move every pixel by half a pixel.
pub fn whole_ceil(x: f64) -> f64 {
    (x - WHOLE).ceil()
}

/// `x.floor()` for a count of pixels or planes measured in millimetres: a value within 10⁻⁶ below a whole
/// number counts as that number ([`whole_ceil`]).
fn whole_floor(x: f64) -> f64 {
    (x + WHOLE).floor()
}

/// Number of planes of a series every `spacing_mm` covering ±`extent_mm`.
pub fn series_count(spacing_mm: f64, extent_mm: f64) -> usize {
    whole_floor(2.0 * extent_mm / spacing_mm) as usize + 1
}

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

pub(super) fn smallest_spacing(vol: &Volume) -> f64 {
    vol.frame
        .spacing_mm
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min)
}

/// Samples along one ray combined by a [`ProjectionKind`] (maximum, minimum or mean).
pub(super) struct Combine {
    kind: ProjectionKind,
    acc: Option<f32>,
    n: u32,
}

impl Combine {
    pub(super) fn new(kind: ProjectionKind) -> Self {
        Self {
            kind,
            acc: None,
            n: 0,
        }
    }

    #[inline]
    pub(super) fn add(&mut self, s: f32) {
        self.n += 1;
        self.acc = Some(match (self.acc, self.kind) {
            (None, _) => s,
            (Some(a), ProjectionKind::Max) => a.max(s),
            (Some(a), ProjectionKind::Min) => a.min(s),
            (Some(a), ProjectionKind::Mean) => a + s,
        });
    }

    /// The combined value; `None` when no sample was added.
    pub(super) fn value(&self) -> Option<f32> {
        self.acc.map(|a| match self.kind {
            ProjectionKind::Mean => a / self.n as f32,
            _ => a,
        })
    }
}

/// Combine samples along offsets `offsets` at every pixel of `plane`; pixels with no sample inside get `fill`.
pub(super) fn render(
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
    let n = whole_floor(thickness_mm / step_mm) as usize + 1;
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
    let count = series_count(spacing_mm, extent_mm);
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
}
