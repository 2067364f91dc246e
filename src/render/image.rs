//! Rendered images: 8-bit RGB with the depth of what each pixel shows, the tile-parallel pixel loop, and RGB PNG
//! and animated PNG encoding.

use rayon::prelude::*;

use super::RenderError;

/// Side of the square pixel tiles rendered in parallel.
pub const TILE: usize = 32;

/// An 8-bit RGB image (`rgb` row by row, 3 bytes a pixel) and, per pixel, the distance (mm) along its ray to
/// the first thing it shows (NaN for background).
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
    pub depth_mm: Vec<f32>,
}

impl RgbImage {
    /// `[r, g, b]` at (`row`, `col`).
    pub fn pixel(&self, row: usize, col: usize) -> [u8; 3] {
        let o = 3 * (row * self.width + col);
        [self.rgb[o], self.rgb[o + 1], self.rgb[o + 2]]
    }
    pub fn depth(&self, row: usize, col: usize) -> f32 {
        self.depth_mm[row * self.width + col]
    }
}

/// Render `width × height` pixels with `shade(scratch, row, col) → (linear RGB 0–1, depth)`, in parallel over
/// tiles; each tile gets one `scratch` from `init` for its pixels to reuse.
pub(crate) fn render_tiles<S>(
    width: usize,
    height: usize,
    init: impl Fn() -> S + Sync,
    shade: impl Fn(&mut S, usize, usize) -> ([f32; 3], f32) + Sync,
) -> RgbImage {
    let (tw, th) = (width.div_ceil(TILE), height.div_ceil(TILE));
    type Tile = (usize, Vec<([f32; 3], f32)>);
    let tiles: Vec<Tile> = (0..tw * th)
        .into_par_iter()
        .map(|t| {
            let (r0, c0) = ((t / tw) * TILE, (t % tw) * TILE);
            let mut out = Vec::with_capacity(TILE * TILE);
            let mut scratch = init();
            for r in r0..(r0 + TILE).min(height) {
                for c in c0..(c0 + TILE).min(width) {
                    out.push(shade(&mut scratch, r, c));
                }
            }
            (t, out)
        })
        .collect();
    let mut rgb = vec![0u8; 3 * width * height];
    let mut depth_mm = vec![f32::NAN; width * height];
    for (t, px) in tiles {
        let (r0, c0) = ((t / tw) * TILE, (t % tw) * TILE);
        let cols = (c0 + TILE).min(width) - c0;
        for (k, (c, d)) in px.into_iter().enumerate() {
            let (r, cc) = (r0 + k / cols, c0 + k % cols);
            let o = r * width + cc;
            depth_mm[o] = d;
            for (ch, v) in c.iter().enumerate() {
                rgb[3 * o + ch] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            }
        }
    }
    RgbImage {
        width,
        height,
        rgb,
        depth_mm,
    }
}

fn enc_err(e: png::EncodingError) -> RenderError {
    RenderError::Encode(e.to_string())
}

fn header<'a>(
    out: &'a mut Vec<u8>,
    width: usize,
    height: usize,
    text: &[(String, String)],
) -> Result<png::Encoder<'a, &'a mut Vec<u8>>, RenderError> {
    let size = |n: usize| {
        u32::try_from(n).map_err(|_| RenderError::Encode("image too large for PNG".into()))
    };
    let mut enc = png::Encoder::new(out, size(width)?, size(height)?);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    for (k, v) in text {
        enc.add_text_chunk(k.clone(), v.clone()).map_err(enc_err)?;
    }
    Ok(enc)
}

/// An 8-bit RGB PNG of `img`, with `(keyword, text)` pairs as `tEXt` chunks.
pub fn encode_rgb_png(img: &RgbImage, text: &[(String, String)]) -> Result<Vec<u8>, RenderError> {
    let mut out = Vec::new();
    let enc = header(&mut out, img.width, img.height, text)?;
    let mut w = enc.write_header().map_err(enc_err)?;
    w.write_image_data(&img.rgb).map_err(enc_err)?;
    w.finish().map_err(enc_err)?;
    Ok(out)
}

/// An 8-bit RGB animated PNG of equally sized `frames`, `delay_ms` per frame, looping.
pub fn encode_rgb_apng(
    frames: &[RgbImage],
    delay_ms: u16,
    text: &[(String, String)],
) -> Result<Vec<u8>, RenderError> {
    let first = frames
        .first()
        .ok_or(RenderError::Encode("no frame".into()))?;
    if frames
        .iter()
        .any(|f| (f.width, f.height) != (first.width, first.height))
    {
        return Err(RenderError::Encode("frames differ in size".into()));
    }
    let n =
        u32::try_from(frames.len()).map_err(|_| RenderError::Encode("too many frames".into()))?;
    let mut out = Vec::new();
    let mut enc = header(&mut out, first.width, first.height, text)?;
    enc.set_animated(n, 0).map_err(enc_err)?;
    enc.set_frame_delay(delay_ms.max(1), 1000)
        .map_err(enc_err)?;
    let mut w = enc.write_header().map_err(enc_err)?;
    for f in frames {
        w.write_image_data(&f.rgb).map_err(enc_err)?;
    }
    w.finish().map_err(enc_err)?;
    Ok(out)
}
