//! Quality of a reconstruction against its phantom: RMSE, PSNR and SSIM over the whole grid.
//!
//! PSNR uses the truth's dynamic range L = max − min as the peak. SSIM is the mean over 8 × 8 windows of
//! each axial slice (non-overlapping, edge windows clipped) with C1 = (0.01 L)², C2 = (0.03 L)².

use ndarray::{ArrayView3, Axis, s};

use super::model::Quality;

/// Compare `recon` with `truth` (same shape, `[z][y][x]`).
pub fn quality(
    recon: ArrayView3<'_, f32>,
    truth: ArrayView3<'_, f32>,
    supersample: usize,
) -> Quality {
    let n = recon.len().max(1) as f64;
    let sq: f64 = recon
        .iter()
        .zip(truth.iter())
        .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
        .sum();
    let rmse = (sq / n).sqrt();
    let (lo, hi) = truth
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v as f64), hi.max(v as f64))
        });
    let range = if hi > lo { hi - lo } else { 1.0 };
    let psnr_db = if rmse > 0.0 {
        20.0 * (range / rmse).log10()
    } else {
        f64::INFINITY
    };
    let (c1, c2) = ((0.01 * range).powi(2), (0.03 * range).powi(2));
    let (mut total, mut windows) = (0.0, 0usize);
    for (a, b) in recon.axis_iter(Axis(0)).zip(truth.axis_iter(Axis(0))) {
        let (ny, nx) = a.dim();
        for y0 in (0..ny).step_by(8) {
            for x0 in (0..nx).step_by(8) {
                let wa = a.slice(s![y0..(y0 + 8).min(ny), x0..(x0 + 8).min(nx)]);
                let wb = b.slice(s![y0..(y0 + 8).min(ny), x0..(x0 + 8).min(nx)]);
                let m = wa.len() as f64;
                let ma = wa.iter().map(|&v| v as f64).sum::<f64>() / m;
                let mb = wb.iter().map(|&v| v as f64).sum::<f64>() / m;
                let (mut va, mut vb, mut cov) = (0.0, 0.0, 0.0);
                for (&p, &q) in wa.iter().zip(wb.iter()) {
                    let (dp, dq) = (p as f64 - ma, q as f64 - mb);
                    va += dp * dp;
                    vb += dq * dq;
                    cov += dp * dq;
                }
                let (va, vb, cov) = (va / m, vb / m, cov / m);
                total += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                    / ((ma * ma + mb * mb + c1) * (va + vb + c2));
                windows += 1;
            }
        }
    }
    Quality {
        rmse,
        psnr_db,
        ssim: total / windows.max(1) as f64,
        truth_supersample: supersample,
    }
}

#[cfg(test)]
mod tests {
    use ndarray::Array3;

    use super::*;

    #[test]
    fn identical_images_score_perfectly_and_a_constant_offset_gives_its_rmse() {
        let t = Array3::from_shape_fn((2, 16, 16), |(z, y, x)| ((x + y + z) % 5) as f32 * 0.01);
        let q = quality(t.view(), t.view(), 1);
        assert_eq!(q.rmse, 0.0);
        assert!((q.ssim - 1.0).abs() < 1e-12);
        let shifted = t.mapv(|v| v + 0.004);
        let q = quality(shifted.view(), t.view(), 1);
        assert!((q.rmse - 0.004).abs() < 1e-6, "{}", q.rmse);
        // L = 0.04: PSNR = 20 log10(0.04 / 0.004) = 20 dB.
        assert!((q.psnr_db - 20.0).abs() < 1e-3, "{}", q.psnr_db);
        assert!(q.ssim < 1.0);
    }
}
