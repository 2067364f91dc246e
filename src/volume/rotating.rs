//! Rotating projections: maximum (or other) projections seen from angles around the superior axis through the
//! volume centre, as the frames of a rotating MIP.

use ndarray::Array2;
use rayon::prelude::*;

use super::display::ProjectionKind;
use super::error::VolumeError;
use super::frame::Volume;
use super::mpr::{Combine, MAX_SIDE, V3, axpy, render, smallest_spacing, whole_ceil};

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

/// The viewing direction and the screen right (LPS unit vectors) of the frame seen from `angle_deg` about the
/// superior axis; screen down is inferior. At 0° the viewer stands anterior and looks along +y with the
/// patient's left on the right (a coronal image); at 90° from the patient's left, looking along −x with
/// posterior on the right (a sagittal image); at 180° from behind; at 270° from the patient's right.
pub fn rotating_axes(angle_deg: f64) -> (V3, V3) {
    let t = angle_deg.to_radians();
    ([-t.sin(), t.cos(), 0.0], [t.cos(), t.sin(), 0.0])
}

/// Maximum (or other) projections seen from `angles_deg` around the superior (z) axis through the volume
/// centre; angle 0 looks from anterior to posterior (a coronal MIP), 90° from the patient's left
/// ([`rotating_axes`]).
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
    let half_width = whole_ceil(radius / pixel) as usize;
    let width = (2 * half_width + 1).clamp(1, MAX_SIDE);
    let height = (whole_ceil(2.0 * half[2] / pixel) as usize + 1).clamp(1, MAX_SIDE);
    let offsets: Vec<f64> = {
        let n = 2 * half_width + 1;
        (0..n)
            .map(|k| (k as f64 - (n as f64 - 1.0) / 2.0) * pixel)
            .collect()
    };
    let rays = RotatingRays {
        centre,
        pixel,
        width,
        height,
        offsets: &offsets,
    };
    let views: Vec<_> = angles_deg.iter().map(|&a| rotating_axes(a)).collect();
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
