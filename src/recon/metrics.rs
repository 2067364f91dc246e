//! Image quality metrics against a reference: RMSE, PSNR, SSIM, optionally inside a mask.
