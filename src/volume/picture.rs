//! 2D pictures for viewers: an image fitted into a viewport, and 8-bit greyscale JPEG encoding through a
//! window (the lossy twin of [`super::encode_png`]).

use ndarray::{Array2, ArrayView2};

use super::error::VolumeError;
use super::window::Window;

/// Largest viewport side (pixels).
pub const MAX_VIEWPORT_SIDE: usize = 8192;

/// `img` (`[row][column]`) scaled to the largest size that fits `rows × columns` with its aspect ratio kept
/// (at least one pixel a side). Each output pixel is the mean of the input pixels its footprint covers when
/// shrinking, and the bilinear sample at its centre when enlarging.
pub fn fit_viewport(
    img: ArrayView2<'_, f32>,
    rows: usize,
    columns: usize,
) -> Result<Array2<f32>, VolumeError> {
    let (h, w) = img.dim();
    if h == 0 || w == 0 {
        return Err(VolumeError::Empty);
    }
    if rows == 0 || columns == 0 || rows > MAX_VIEWPORT_SIDE || columns > MAX_VIEWPORT_SIDE {
        return Err(VolumeError::InvalidParameter {
            name: "viewport",
            reason: format!("each side is 1 to {MAX_VIEWPORT_SIDE} pixels"),
        });
    }
    let scale = (rows as f64 / h as f64).min(columns as f64 / w as f64);
    let oh = ((h as f64 * scale).round() as usize).clamp(1, rows);
    let ow = ((w as f64 * scale).round() as usize).clamp(1, columns);
    // Input pixels per output pixel along each axis.
    let (sy, sx) = (h as f64 / oh as f64, w as f64 / ow as f64);
    Ok(Array2::from_shape_fn((oh, ow), |(r, c)| {
        if sy >= 1.0 && sx >= 1.0 {
            box_mean(
                &img,
                (r as f64 * sy, (r + 1) as f64 * sy),
                (c as f64 * sx, (c + 1) as f64 * sx),
            )
        } else {
            bilinear(
                &img,
                (r as f64 + 0.5) * sy - 0.5,
                (c as f64 + 0.5) * sx - 0.5,
            )
        }
    }))
}

/// Mean of the pixels whose area lies in rows `y0..y1` and columns `x0..x1` (continuous coordinates,
/// partial pixels weighted by their covered fraction).
fn box_mean(img: &ArrayView2<'_, f32>, (y0, y1): (f64, f64), (x0, x1): (f64, f64)) -> f32 {
    let (h, w) = img.dim();
    let (mut sum, mut weight) = (0.0f64, 0.0f64);
    for r in (y0.floor() as usize)..(y1.ceil() as usize).min(h) {
        let wy = (y1.min(r as f64 + 1.0) - y0.max(r as f64)).max(0.0);
        for c in (x0.floor() as usize)..(x1.ceil() as usize).min(w) {
            let wx = (x1.min(c as f64 + 1.0) - x0.max(c as f64)).max(0.0);
            let v = img[[r, c]];
            if v.is_finite() {
                sum += v as f64 * wx * wy;
                weight += wx * wy;
            }
        }
    }
    if weight > 0.0 {
        (sum / weight) as f32
    } else {
        f32::NAN
    }
}

/// The bilinear sample of `img` at row `y`, column `x` (pixel centres at integers; clamped at the edges).
fn bilinear(img: &ArrayView2<'_, f32>, y: f64, x: f64) -> f32 {
    let (h, w) = img.dim();
    let y = y.clamp(0.0, (h - 1) as f64);
    let x = x.clamp(0.0, (w - 1) as f64);
    let (r0, c0) = (y.floor() as usize, x.floor() as usize);
    let (r1, c1) = ((r0 + 1).min(h - 1), (c0 + 1).min(w - 1));
    let (fy, fx) = (y - r0 as f64, x - c0 as f64);
    let at = |r: usize, c: usize| img[[r, c]] as f64;
    let top = at(r0, c0) * (1.0 - fx) + at(r0, c1) * fx;
    let bottom = at(r1, c0) * (1.0 - fx) + at(r1, c1) * fx;
    (top * (1.0 - fy) + bottom * fy) as f32
}

/// Encode `img` (`[row][column]`) as an 8-bit greyscale baseline JPEG through `window`, at `quality` 1–100
/// (the libjpeg scale: 100 is the finest quantisation).
pub fn encode_jpeg(
    img: ArrayView2<'_, f32>,
    window: Window,
    quality: u8,
) -> Result<Vec<u8>, VolumeError> {
    let (h, w) = img.dim();
    if h == 0 || w == 0 {
        return Err(VolumeError::Empty);
    }
    if !(1..=100).contains(&quality) {
        return Err(VolumeError::InvalidParameter {
            name: "quality",
            reason: "1 to 100".into(),
        });
    }
    let too_big = |_| VolumeError::InvalidParameter {
        name: "image",
        reason: "dimensions exceed the JPEG limit of 65535 a side".into(),
    };
    let (jw, jh) = (
        u16::try_from(w).map_err(too_big)?,
        u16::try_from(h).map_err(too_big)?,
    );
    let window = Window::new(window.width, window.level)?;
    let pixels: Vec<u8> = img
        .iter()
        .map(|&v| (window.unit(v) * 255.0).round() as u8)
        .collect();
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, quality)
        .encode(&pixels, jw, jh, jpeg_encoder::ColorType::Luma)
        .map_err(|e| VolumeError::Encode(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_picture_fits_its_viewport_with_its_aspect_ratio_and_keeps_its_mean() {
        let img = Array2::from_shape_fn((40, 60), |(r, c)| (r * 60 + c) as f32);
        let small = fit_viewport(img.view(), 20, 20).unwrap();
        assert_eq!(small.dim(), (13, 20));
        let mean = |a: &Array2<f32>| a.iter().map(|&v| v as f64).sum::<f64>() / a.len() as f64;
        assert!((mean(&small) - mean(&img)).abs() < 1.0, "{}", mean(&small));
        // Halving exactly: each output pixel is the mean of a 2 × 2 block.
        let half = fit_viewport(img.view(), 20, 30).unwrap();
        assert_eq!(half.dim(), (20, 30));
        assert_eq!(half[[0, 0]], (0.0 + 1.0 + 60.0 + 61.0) / 4.0);
        // Enlarging a ramp keeps it a ramp.
        let big = fit_viewport(img.view(), 80, 1000).unwrap();
        assert_eq!(big.dim(), (80, 120));
        assert!(big[[40, 60]] > big[[40, 59]] && big[[41, 60]] > big[[40, 60]]);
        assert!(fit_viewport(img.view(), 0, 10).is_err());
        assert!(fit_viewport(img.view(), 10, MAX_VIEWPORT_SIDE + 1).is_err());
    }

    #[test]
    fn a_jpeg_decodes_to_the_windowed_grey_levels_within_the_quantisation_error() {
        let img =
            Array2::from_shape_fn((64, 80), |(r, c)| (r as f32 * 4.0 + c as f32 * 2.0) - 100.0);
        let window = Window::new(400.0, 100.0).unwrap();
        let jpeg = encode_jpeg(img.view(), window, 90).unwrap();
        assert_eq!(&jpeg[..2], &[0xFF, 0xD8]);
        let mut dec = jpeg_decoder::Decoder::new(std::io::Cursor::new(&jpeg));
        let px = dec.decode().unwrap();
        let info = dec.info().unwrap();
        assert_eq!((info.width, info.height), (80, 64));
        assert_eq!(info.pixel_format, jpeg_decoder::PixelFormat::L8);
        let mean_abs: f64 = img
            .iter()
            .zip(&px)
            .map(|(&v, &g)| ((window.unit(v) * 255.0).round() - g as f64).abs())
            .sum::<f64>()
            / px.len() as f64;
        assert!(mean_abs < 2.0, "mean absolute difference {mean_abs}");
        assert!(encode_jpeg(img.view(), window, 0).is_err());
        assert!(encode_jpeg(img.view(), window, 101).is_err());
    }
}
