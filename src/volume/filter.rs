//! Smoothing (separable Gaussian with σ in millimetres, 3×3×3 median) and threshold segmentation with
//! connected-component selection.

use ndarray::{Array3, ArrayView3, Axis, Zip};
use rayon::prelude::*;

use super::error::VolumeError;

/// Gaussian smoothing with standard deviation `sigma_mm` along each axis (spacing `[x, y, z]` in mm); edges are
/// clamped. σ = 0 leaves the volume unchanged.
pub fn gaussian(
    vol: ArrayView3<'_, f32>,
    spacing_mm: [f64; 3],
    sigma_mm: f64,
) -> Result<Array3<f32>, VolumeError> {
    if !(sigma_mm.is_finite() && sigma_mm >= 0.0) {
        return Err(VolumeError::InvalidParameter {
            name: "sigma_mm",
            reason: format!("must be finite and non-negative, got {sigma_mm}"),
        });
    }
    let mut out = vol.to_owned();
    // Array axis 2 is x, 1 is y, 0 is z.
    for (axis, spacing) in [
        (2usize, spacing_mm[0]),
        (1, spacing_mm[1]),
        (0, spacing_mm[2]),
    ] {
        let sigma = sigma_mm / spacing;
        if sigma < 1e-3 {
            continue;
        }
        let radius = (3.0 * sigma).ceil() as isize;
        let mut kernel: Vec<f32> = (-radius..=radius)
            .map(|d| (-(d as f64).powi(2) / (2.0 * sigma * sigma)).exp() as f32)
            .collect();
        let sum: f32 = kernel.iter().sum();
        kernel.iter_mut().for_each(|k| *k /= sum);
        let src = out.clone();
        Zip::from(out.lanes_mut(Axis(axis)))
            .and(src.lanes(Axis(axis)))
            .par_for_each(|mut dst, line| {
                let n = line.len() as isize;
                for (x, d) in dst.iter_mut().enumerate() {
                    let mut acc = 0.0f32;
                    for (t, &w) in kernel.iter().enumerate() {
                        let p = (x as isize + t as isize - radius).clamp(0, n - 1);
                        acc += w * line[p as usize];
                    }
                    *d = acc;
                }
            });
    }
    Ok(out)
}

/// 3×3×3 median filter (edges clamped): removes salt-and-pepper noise while keeping edges.
pub fn median3(vol: ArrayView3<'_, f32>) -> Array3<f32> {
    let (nz, ny, nx) = vol.dim();
    let mut out = Array3::zeros((nz, ny, nx));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(k, mut plane)| {
            let mut buf = [0.0f32; 27];
            for ((j, i), v) in plane.indexed_iter_mut() {
                let mut n = 0;
                for dk in -1isize..=1 {
                    for dj in -1isize..=1 {
                        for di in -1isize..=1 {
                            let kk = (k as isize + dk).clamp(0, nz as isize - 1) as usize;
                            let jj = (j as isize + dj).clamp(0, ny as isize - 1) as usize;
                            let ii = (i as isize + di).clamp(0, nx as isize - 1) as usize;
                            buf[n] = vol[[kk, jj, ii]];
                            n += 1;
                        }
                    }
                }
                *v = *buf.select_nth_unstable_by(13, f32::total_cmp).1;
            }
        });
    out
}

/// Voxels with `lo ≤ value ≤ hi`.
pub fn threshold(vol: ArrayView3<'_, f32>, lo: f32, hi: f32) -> Array3<bool> {
    vol.mapv(|v| v >= lo && v <= hi)
}

/// The largest 6-connected component of `mask` (ties: the first in memory order).
pub fn largest_component(mask: &Array3<bool>) -> Array3<bool> {
    let (nz, ny, nx) = mask.dim();
    let mut label = Array3::<u32>::zeros((nz, ny, nx));
    let mut sizes = vec![0usize];
    let mut stack = Vec::new();
    for start in ndarray::indices((nz, ny, nx)) {
        if !mask[start] || label[start] != 0 {
            continue;
        }
        let id = sizes.len() as u32;
        sizes.push(0);
        label[start] = id;
        stack.push(start);
        while let Some((k, j, i)) = stack.pop() {
            sizes[id as usize] += 1;
            let mut visit = |p: (usize, usize, usize)| {
                if mask[p] && label[p] == 0 {
                    label[p] = id;
                    stack.push(p);
                }
            };
            if k > 0 {
                visit((k - 1, j, i));
            }
            if k + 1 < nz {
                visit((k + 1, j, i));
            }
            if j > 0 {
                visit((k, j - 1, i));
            }
            if j + 1 < ny {
                visit((k, j + 1, i));
            }
            if i > 0 {
                visit((k, j, i - 1));
            }
            if i + 1 < nx {
                visit((k, j, i + 1));
            }
        }
    }
    let best = (1..sizes.len()).max_by_key(|&l| (sizes[l], std::cmp::Reverse(l)));
    match best {
        Some(b) => label.mapv(|l| l == b as u32),
        None => Array3::from_elem((nz, ny, nx), false),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_keeps_the_mean_and_spreads_a_point_by_sigma() {
        let mut v = Array3::<f32>::zeros((1, 1, 101));
        v[[0, 0, 50]] = 1.0;
        let g = gaussian(v.view(), [0.5, 1.0, 1.0], 2.0).unwrap();
        let total: f32 = g.sum();
        assert!((total - 1.0).abs() < 1e-5);
        // σ = 2 mm = 4 samples: variance 16 samples², less ~2.5 % for the kernel truncated at 3σ.
        let var: f32 = g
            .iter()
            .enumerate()
            .map(|(x, &w)| w * (x as f32 - 50.0).powi(2))
            .sum();
        assert!((var - 16.0).abs() < 0.5, "{var}");
        assert!(gaussian(v.view(), [1.0; 3], -1.0).is_err());
    }

    #[test]
    fn median_removes_an_isolated_spike_and_keeps_a_step() {
        let mut v = Array3::from_shape_fn((5, 5, 6), |(_, _, i)| if i < 3 { 0.0f32 } else { 10.0 });
        v[[2, 2, 1]] = 1000.0;
        let m = median3(v.view());
        assert_eq!(m[[2, 2, 1]], 0.0);
        assert_eq!(m[[2, 2, 2]], 0.0);
        assert_eq!(m[[2, 2, 3]], 10.0);
    }

    #[test]
    fn threshold_and_largest_component_pick_the_big_blob() {
        let v = Array3::from_shape_fn((6, 6, 12), |(k, j, i)| {
            let big = (1..5).contains(&k) && (1..5).contains(&j) && (1..5).contains(&i);
            let small = k == 2 && j == 2 && (8..10).contains(&i);
            if big || small { 500.0f32 } else { -1000.0 }
        });
        let mask = threshold(v.view(), 300.0, f32::INFINITY);
        assert_eq!(mask.iter().filter(|&&b| b).count(), 64 + 2);
        let big = largest_component(&mask);
        assert_eq!(big.iter().filter(|&&b| b).count(), 64);
        assert!(!big[[2, 2, 8]]);
    }
}
