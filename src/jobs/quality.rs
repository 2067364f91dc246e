//! Quality of a reconstruction against its phantom, through [`crate::recon::metrics`]: RMSE, PSNR with
//! the truth's dynamic range L = max − min as the data range, and SSIM (Gaussian window, σ = 1.5) averaged
//! over the axial slices.

use ndarray::{ArrayView3, Axis};
use rayon::prelude::*;

use super::model::Quality;
use crate::recon::ReconError;
use crate::recon::control::Control;
use crate::recon::metrics::{psnr, rmse, ssim};

/// Compare `recon` with `truth` (same shape, `[z][y][x]`).
pub fn quality(
    recon: ArrayView3<'_, f32>,
    truth: ArrayView3<'_, f32>,
    supersample: usize,
    ctl: Control<'_>,
) -> Result<Quality, ReconError> {
    let (lo, hi) = truth
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v as f64), hi.max(v as f64))
        });
    let range = if hi > lo { hi - lo } else { 1.0 };
    // Slices in parallel, each checking the cancel flag (a 192³ volume's SSIM takes seconds on one
    // thread); summed in slice order, so the result does not depend on the threads.
    let per_slice = recon
        .axis_iter(Axis(0))
        .into_par_iter()
        .zip(truth.axis_iter(Axis(0)).into_par_iter())
        .map(|(a, b)| {
            ctl.check()?;
            ssim(a, b, range, None)
        })
        .collect::<Result<Vec<f64>, ReconError>>()?;
    let total: f64 = per_slice.iter().sum();
    Ok(Quality {
        rmse: rmse(recon, truth, None)?,
        psnr_db: Some(psnr(recon, truth, range, None)?).filter(|p| p.is_finite()),
        ssim: total / recon.len_of(Axis(0)).max(1) as f64,
        truth_supersample: supersample,
    })
}

#[cfg(test)]
mod tests {
    use ndarray::Array3;

    use super::*;
    use crate::recon::control::{Cancel, unattended};

    #[test]
    fn identical_volumes_score_perfectly_and_a_constant_offset_gives_its_rmse() {
        let t = Array3::from_shape_fn((2, 16, 16), |(z, y, x)| ((x + y + z) % 5) as f32 * 0.01);
        let q = quality(t.view(), t.view(), 1, unattended()).unwrap();
        assert_eq!((q.rmse, q.psnr_db), (0.0, None));
        assert!((q.ssim - 1.0).abs() < 1e-12);
        let shifted = t.mapv(|v| v + 0.004);
        let q = quality(shifted.view(), t.view(), 1, unattended()).unwrap();
        assert!((q.rmse - 0.004).abs() < 1e-6, "{}", q.rmse);
        // L = 0.04: PSNR = 20 log10(0.04 / 0.004) = 20 dB.
        assert!((q.psnr_db.unwrap() - 20.0).abs() < 1e-3, "{:?}", q.psnr_db);
        assert!(q.ssim < 1.0);
    }

    #[test]
    fn a_cancel_stops_the_comparison() {
        let t = Array3::from_shape_fn((4, 16, 16), |(z, y, x)| ((x + y + z) % 5) as f32 * 0.01);
        let cancel = Cancel::new();
        cancel.cancel();
        let progress = crate::recon::control::NoProgress;
        let r = quality(t.view(), t.view(), 1, Control::new(&cancel, &progress));
        assert!(matches!(r, Err(ReconError::Canceled)), "{r:?}");
    }
}
