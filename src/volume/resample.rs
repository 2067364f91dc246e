//! Trilinear sampling and isotropic resampling. Interpolation adds no information: resampling only changes the
//! grid on which the measured values are shown.

use ndarray::{Array3, ArrayView3};
use rayon::prelude::*;

use super::error::VolumeError;
use super::frame::{Frame, Volume};

/// Trilinear interpolation at fractional index `[k, j, i]`; `None` outside the sample grid.
pub fn trilinear(vol: &ArrayView3<'_, f32>, idx: [f64; 3]) -> Option<f32> {
    let (nz, ny, nx) = vol.dim();
    let [k, j, i] = idx;
    let inside = |x: f64, n: usize| x > -1e-9 && x < n as f64 - 1.0 + 1e-9;
    if !(inside(k, nz) && inside(j, ny) && inside(i, nx)) {
        return None;
    }
    let base = |x: f64, n: usize| -> (usize, f64) {
        let b = (x.max(0.0).floor() as usize).min(n.saturating_sub(2));
        (b, (x - b as f64).clamp(0.0, 1.0))
    };
    let (k0, fk) = base(k, nz);
    let (j0, fj) = base(j, ny);
    let (i0, fi) = base(i, nx);
    let at = |kk: usize, jj: usize, ii: usize| {
        vol[[kk.min(nz - 1), jj.min(ny - 1), ii.min(nx - 1)]] as f64
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let c = |kk: usize| {
        lerp(
            lerp(at(kk, j0, i0), at(kk, j0, i0 + 1), fi),
            lerp(at(kk, j0 + 1, i0), at(kk, j0 + 1, i0 + 1), fi),
            fj,
        )
    };
    Some(lerp(c(k0), c(k0 + 1), fk) as f32)
}

/// The grid [`resample_isotropic`] produces for a volume of `dim` (`[z][y][x]`) samples in frame `f`: its
/// sample counts `[x, y, z]` and frame. Checks the spacing and the voxel limit without touching any data.
pub fn isotropic_grid(
    f: &Frame,
    dim: (usize, usize, usize),
    spacing_mm: Option<f64>,
    max_voxels: u64,
) -> Result<([usize; 3], Frame), VolumeError> {
    let s =
        spacing_mm.unwrap_or_else(|| f.spacing_mm.iter().copied().fold(f64::INFINITY, f64::min));
    if !(s.is_finite() && s > 0.0) {
        return Err(VolumeError::InvalidParameter {
            name: "spacing_mm",
            reason: format!("must be finite and positive, got {s}"),
        });
    }
    let (nz, ny, nx) = dim;
    if nz == 0 || ny == 0 || nx == 0 {
        return Err(VolumeError::Empty);
    }
    let axes = [f.direction[0], f.direction[1], f.slice_normal()];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in f.corners(dim) {
        for a in 0..3 {
            let t = dot(p, axes[a]);
            lo[a] = lo[a].min(t);
            hi[a] = hi[a].max(t);
        }
    }
    let n: [usize; 3] = std::array::from_fn(|a| ((hi[a] - lo[a]) / s + 1e-6).floor() as usize + 1);
    let voxels = (n[0] as u64)
        .saturating_mul(n[1] as u64)
        .saturating_mul(n[2] as u64);
    if voxels > max_voxels {
        return Err(VolumeError::InvalidParameter {
            name: "spacing_mm",
            reason: format!(
                "the resampled volume would have {voxels} voxels, more than the limit of {max_voxels}"
            ),
        });
    }
    let origin: [f64; 3] = std::array::from_fn(|c| (0..3).map(|a| lo[a] * axes[a][c]).sum());
    Ok((
        n,
        Frame {
            spacing_mm: [s; 3],
            origin_mm: origin,
            direction: axes,
        },
    ))
}

/// Resample `vol` onto a grid of cubic voxels of `spacing_mm` (default: the smallest input spacing) whose axes
/// are the input column and row axes and the slice normal, covering the whole input (a tilted series becomes
/// an orthogonal one). Samples outside the input get `fill`. Refuses outputs of more than `max_voxels`.
pub fn resample_isotropic(
    vol: &Volume,
    spacing_mm: Option<f64>,
    fill: f32,
    max_voxels: u64,
) -> Result<Volume, VolumeError> {
    let f = &vol.frame;
    let (n, out_frame) = isotropic_grid(f, vol.data.dim(), spacing_mm, max_voxels)?;
    let src = vol.data.view();
    let mut data = Array3::from_elem((n[2], n[1], n[0]), fill);
    let Some(map) = f.index_map() else {
        return Err(VolumeError::InvalidParameter {
            name: "frame",
            reason: "the volume's direction vectors are degenerate".into(),
        });
    };
    data.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(k, mut plane)| {
            for ((j, i), v) in plane.indexed_iter_mut() {
                let p = out_frame.position(k as f64, j as f64, i as f64);
                if let Some(x) = trilinear(&src, map.index(p)) {
                    *v = x;
                }
            }
        });
    Ok(Volume {
        data,
        frame: out_frame,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trilinear_reproduces_a_linear_field_exactly() {
        let v = Array3::from_shape_fn((4, 5, 6), |(k, j, i)| (3 * k + 2 * j + i) as f32);
        let got = trilinear(&v.view(), [1.25, 2.5, 4.75]).unwrap();
        assert!((got - (3.75 + 5.0 + 4.75)).abs() < 1e-5);
        assert!(trilinear(&v.view(), [3.0, 4.0, 5.0]).is_some());
        assert!(trilinear(&v.view(), [3.01, 0.0, 0.0]).is_none());
    }

    #[test]
    fn isotropic_resampling_keeps_positions_and_a_linear_field() {
        // 2.5 mm slices of 0.7 mm pixels holding x + 2y + 3z (mm).
        let frame = Frame {
            spacing_mm: [0.7, 0.7, 2.5],
            origin_mm: [-10.0, 5.0, 100.0],
            direction: Frame::AXIS_ALIGNED,
        };
        let data = Array3::from_shape_fn((9, 20, 21), |(k, j, i)| {
            let p = frame.position(k as f64, j as f64, i as f64);
            (p[0] + 2.0 * p[1] + 3.0 * p[2]) as f32
        });
        let vol = Volume { data, frame };
        let out = resample_isotropic(&vol, None, -1000.0, 1 << 24).unwrap();
        assert_eq!(out.frame.spacing_mm, [0.7; 3]);
        let (nz, ny, nx) = out.data.dim();
        assert_eq!((ny, nx), (20, 21));
        assert_eq!(nz, (8.0 * 2.5 / 0.7f64).floor() as usize + 1);
        for (k, j, i) in [(0, 0, 0), (10, 7, 3), (nz - 1, ny - 1, nx - 1)] {
            let p = out.frame.position(k as f64, j as f64, i as f64);
            let want = p[0] + 2.0 * p[1] + 3.0 * p[2];
            assert!(
                (out.data[[k, j, i]] as f64 - want).abs() < 1e-3,
                "[{k}][{j}][{i}]"
            );
        }
        assert!(resample_isotropic(&vol, Some(0.01), 0.0, 1 << 24).is_err());
        assert!(resample_isotropic(&vol, Some(-1.0), 0.0, 1 << 24).is_err());
    }
}
