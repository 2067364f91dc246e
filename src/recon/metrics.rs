//! Image quality metrics against a reference: RMSE, PSNR, SSIM, optionally inside a mask.
//!
//! All metrics compare `image` with `reference` of the same shape, in f64. A mask (same shape, `true`
//! = counted) restricts the comparison; an empty mask is an error. PSNR takes the data range explicitly
//! (`10·log10(range² / MSE)`), never the image's own maximum.

use ndarray::{Array2, ArrayView, ArrayView2, Dimension, Zip};

use crate::recon::error::ReconError;

fn check_shapes(image: &[usize], other: &[usize], what: &'static str) -> Result<(), ReconError> {
    if image == other {
        Ok(())
    } else if what == "mask" {
        Err(ReconError::param(
            "mask",
            format!("mask shape {other:?} differs from the image shape {image:?}"),
        ))
    } else {
        Err(ReconError::ShapeMismatch {
            expected: other.to_vec(),
            got: image.to_vec(),
        })
    }
}

/// Mean squared error of `image` against `reference`, inside `mask` if given.
pub fn mse<D: Dimension>(
    image: ArrayView<'_, f32, D>,
    reference: ArrayView<'_, f32, D>,
    mask: Option<ArrayView<'_, bool, D>>,
) -> Result<f64, ReconError> {
    check_shapes(image.shape(), reference.shape(), "reference")?;
    let (mut sum, mut count) = (0.0f64, 0usize);
    match mask {
        Some(m) => {
            check_shapes(image.shape(), m.shape(), "mask")?;
            Zip::from(&image)
                .and(&reference)
                .and(&m)
                .for_each(|a, b, &k| {
                    if k {
                        let d = *a as f64 - *b as f64;
                        sum += d * d;
                        count += 1;
                    }
                });
        }
        None => {
            Zip::from(&image).and(&reference).for_each(|a, b| {
                let d = *a as f64 - *b as f64;
                sum += d * d;
                count += 1;
            });
        }
    }
    if count == 0 {
        return Err(ReconError::param("mask", "no element to compare"));
    }
    if !sum.is_finite() {
        return Err(ReconError::param("image", "contains non-finite values"));
    }
    Ok(sum / count as f64)
}

/// Root-mean-square error, inside `mask` if given.
pub fn rmse<D: Dimension>(
    image: ArrayView<'_, f32, D>,
    reference: ArrayView<'_, f32, D>,
    mask: Option<ArrayView<'_, bool, D>>,
) -> Result<f64, ReconError> {
    Ok(mse(image, reference, mask)?.sqrt())
}

/// Peak signal-to-noise ratio in dB for a data range `data_range` (> 0): `10·log10(range²/MSE)`;
/// infinite for identical images.
pub fn psnr<D: Dimension>(
    image: ArrayView<'_, f32, D>,
    reference: ArrayView<'_, f32, D>,
    data_range: f64,
    mask: Option<ArrayView<'_, bool, D>>,
) -> Result<f64, ReconError> {
    check_range(data_range)?;
    let m = mse(image, reference, mask)?;
    Ok(10.0 * (data_range * data_range / m).log10())
}

fn check_range(data_range: f64) -> Result<(), ReconError> {
    if data_range.is_finite() && data_range > 0.0 {
        Ok(())
    } else {
        Err(ReconError::param(
            "data_range",
            format!("must be positive and finite, got {data_range}"),
        ))
    }
}

/// The disk inscribed in an `ny × nx` image: pixel centres within `min(nx, ny)/2` pixels of the image
/// centre.
pub fn inscribed_disk(ny: usize, nx: usize) -> Array2<bool> {
    let r = nx.min(ny) as f64 / 2.0;
    let (cy, cx) = ((ny as f64 - 1.0) / 2.0, (nx as f64 - 1.0) / 2.0);
    Array2::from_shape_fn((ny, nx), |(j, i)| {
        let (dy, dx) = (j as f64 - cy, i as f64 - cx);
        dx * dx + dy * dy <= r * r
    })
}

/// Gaussian-weighted local means of a 2D array (σ = 1.5 px, truncated at ±5 px), renormalised where the
/// window leaves the image.
fn gaussian_filter(a: &Array2<f64>) -> Array2<f64> {
    const R: isize = 5;
    let w: Vec<f64> = (-R..=R)
        .map(|k| (-(k * k) as f64 / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    let (ny, nx) = a.dim();
    let pass = |src: &Array2<f64>, along_x: bool| {
        Array2::from_shape_fn((ny, nx), |(j, i)| {
            let (mut s, mut ws) = (0.0, 0.0);
            for k in -R..=R {
                let (jj, ii) = if along_x {
                    (j as isize, i as isize + k)
                } else {
                    (j as isize + k, i as isize)
                };
                if jj >= 0 && ii >= 0 && (jj as usize) < ny && (ii as usize) < nx {
                    let wk = w[(k + R) as usize];
                    s += wk * src[[jj as usize, ii as usize]];
                    ws += wk;
                }
            }
            s / ws
        })
    };
    pass(&pass(a, true), false)
}

/// Structural similarity (Wang et al. 2004: Gaussian window σ = 1.5, K1 = 0.01, K2 = 0.03) of a 2D
/// image against a reference with data range `data_range`, averaged over the SSIM map inside `mask`
/// (or everywhere).
pub fn ssim(
    image: ArrayView2<'_, f32>,
    reference: ArrayView2<'_, f32>,
    data_range: f64,
    mask: Option<ArrayView2<'_, bool>>,
) -> Result<f64, ReconError> {
    check_range(data_range)?;
    check_shapes(image.shape(), reference.shape(), "reference")?;
    if let Some(m) = &mask {
        check_shapes(image.shape(), m.shape(), "mask")?;
    }
    if image.iter().chain(reference.iter()).any(|v| !v.is_finite()) {
        return Err(ReconError::param("image", "contains non-finite values"));
    }
    let x = image.mapv(|v| v as f64);
    let y = reference.mapv(|v| v as f64);
    let mx = gaussian_filter(&x);
    let my = gaussian_filter(&y);
    let sxx = gaussian_filter(&(&x * &x));
    let syy = gaussian_filter(&(&y * &y));
    let sxy = gaussian_filter(&(&x * &y));
    let c1 = (0.01 * data_range).powi(2);
    let c2 = (0.03 * data_range).powi(2);
    let (mut sum, mut count) = (0.0, 0usize);
    for ((j, i), &ux) in mx.indexed_iter() {
        if let Some(m) = &mask
            && !m[[j, i]]
        {
            continue;
        }
        let uy = my[[j, i]];
        let vx = sxx[[j, i]] - ux * ux;
        let vy = syy[[j, i]] - uy * uy;
        let cxy = sxy[[j, i]] - ux * uy;
        sum +=
            (2.0 * ux * uy + c1) * (2.0 * cxy + c2) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
        count += 1;
    }
    if count == 0 {
        return Err(ReconError::param("mask", "no element to compare"));
    }
    Ok(sum / count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn rmse_and_psnr_of_a_constant_offset_are_exact() {
        let a = Array2::<f32>::from_elem((8, 8), 1.25);
        let b = Array2::<f32>::from_elem((8, 8), 1.0);
        assert!((rmse(a.view(), b.view(), None).unwrap() - 0.25).abs() < 1e-12);
        let p = psnr(a.view(), b.view(), 2.0, None).unwrap();
        assert!((p - 20.0 * (2.0f64 / 0.25).log10()).abs() < 1e-9);
        assert!(psnr(a.view(), b.view(), 0.0, None).is_err());
    }

    #[test]
    fn a_mask_restricts_the_comparison() {
        let mut a = Array2::<f32>::zeros((4, 4));
        a[[0, 0]] = 10.0;
        let b = Array2::<f32>::zeros((4, 4));
        let mut m = Array2::from_elem((4, 4), true);
        m[[0, 0]] = false;
        assert_eq!(rmse(a.view(), b.view(), Some(m.view())).unwrap(), 0.0);
        assert!((rmse(a.view(), b.view(), None).unwrap() - 2.5).abs() < 1e-12);
        let none = Array2::from_elem((4, 4), false);
        assert!(rmse(a.view(), b.view(), Some(none.view())).is_err());
        let small = Array2::<f32>::zeros((3, 4));
        assert!(matches!(
            rmse(a.view(), small.view(), None),
            Err(ReconError::ShapeMismatch { .. })
        ));
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_drops_with_noise() {
        let a = Array2::from_shape_fn((32, 32), |(j, i)| ((i / 8 + j / 8) % 2) as f32);
        assert!((ssim(a.view(), a.view(), 1.0, None).unwrap() - 1.0).abs() < 1e-12);
        let noisy = Array2::from_shape_fn((32, 32), |(j, i)| {
            a[[j, i]] + if (i * 7 + j * 13) % 5 == 0 { 0.3 } else { -0.1 }
        });
        let s = ssim(noisy.view(), a.view(), 1.0, None).unwrap();
        assert!(s < 0.9 && s > 0.0, "{s}");
    }

    #[test]
    fn the_inscribed_disk_holds_about_pi_over_four_of_the_pixels() {
        let d = inscribed_disk(256, 256);
        let f = d.iter().filter(|&&b| b).count() as f64 / (256.0 * 256.0);
        assert!((f - std::f64::consts::FRAC_PI_4).abs() < 0.005, "{f}");
    }
}
