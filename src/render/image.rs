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

/// What each pixel of a picture shows.
pub(crate) trait Shade: Sync {
    /// Buffers a tile's pixels reuse.
    type Scratch;
    fn scratch(&self) -> Self::Scratch;
    /// Linear RGB (0–1) and depth (mm, NaN for background) of the pixel at (`row`, `col`). Mark it
    /// `#[inline(always)]`: it is compiled into each form of the tile loop ([`render_tiles`]).
    fn shade(&self, scratch: &mut Self::Scratch, row: usize, col: usize) -> ([f32; 3], f32);

    /// Shade `pixels` (row, col), handing each one's colour and depth to `put`, in any order. The default
    /// shades them one by one; a shader may keep several rays in flight, each computed as [`Shade::shade`]
    /// computes it. Mark it `#[inline(always)]` as well.
    #[inline(always)]
    fn shade_pixels(
        &self,
        scratch: &mut Self::Scratch,
        pixels: impl Iterator<Item = (usize, usize)>,
        mut put: impl FnMut(usize, usize, [f32; 3], f32),
    ) {
        for (r, c) in pixels {
            let (px, d) = self.shade(scratch, r, c);
            put(r, c, px, d);
        }
    }
}

/// Render one `width × height` picture for each of `shaders`, in parallel over the bands of rows of all the
/// pictures at once, so that no picture of a sequence waits for the last band of the one before. Each band is
/// rendered tile by tile ([`TILE`] columns wide, for rays that stay close together) with one scratch for its
/// pixels to reuse, straight into the picture's bytes and depths.
///
/// On x86-64 CPUs with AVX2, FMA and BMI2 the band loop, with [`Shade::shade`] inlined into it, is compiled for
/// them: the same operations in the same order (Rust never fuses a multiply and an add by itself), so the
/// pictures are equal bit for bit, in fewer instructions (three-operand forms, shifts by a register without
/// flags).
pub(crate) fn render_frames<S: Shade>(width: usize, height: usize, shaders: &[S]) -> Vec<RgbImage> {
    let wide = wide_tiles();
    // Bands of up to TILE rows, at least four per thread for one picture.
    let band = (height / (4 * rayon::current_num_threads()).max(1)).clamp(1, TILE);
    let mut frames: Vec<RgbImage> = shaders
        .iter()
        .map(|_| RgbImage {
            width,
            height,
            rgb: vec![0u8; 3 * width * height],
            depth_mm: vec![f32::NAN; width * height],
        })
        .collect();
    if width == 0 || height == 0 {
        return frames;
    }
    let mut work = Vec::new();
    for (shader, f) in shaders.iter().zip(frames.iter_mut()) {
        let bands = f
            .rgb
            .chunks_mut(3 * width * band)
            .zip(f.depth_mm.chunks_mut(width * band));
        for (k, (rgb, depth)) in bands.enumerate() {
            work.push((shader, k * band, rgb, depth));
        }
    }
    work.into_par_iter().for_each(|(shader, r0, rgb, depth)| {
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        if wide {
            // SAFETY: `wide_tiles` found the features this function is compiled for.
            return unsafe { fill_band_wide(shader, r0, width, rgb, depth) };
        }
        let _ = wide;
        fill_band(shader, r0, width, rgb, depth)
    });
    frames
}

/// The pixels of the rows from `r0` whose bytes and depths are `rgb` and `depth` (`width` pixels a row).
#[inline(always)]
fn fill_band(shader: &impl Shade, r0: usize, width: usize, rgb: &mut [u8], depth: &mut [f32]) {
    let mut scratch = shader.scratch();
    let rows = depth.len() / width.max(1);
    for c0 in (0..width).step_by(TILE) {
        let cols = c0..(c0 + TILE).min(width);
        let pixels = (r0..r0 + rows).flat_map(|r| cols.clone().map(move |c| (r, c)));
        shader.shade_pixels(&mut scratch, pixels, |r, c, px, d| {
            let o = (r - r0) * width + c;
            depth[o] = d;
            for (b, v) in rgb[3 * o..3 * o + 3].iter_mut().zip(px) {
                *b = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            }
        });
    }
}

/// [`fill_band`] compiled for AVX2, FMA and BMI2.
///
/// # Safety
/// The CPU must have those features ([`wide_tiles`]).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)] // Kernel entry compiled for more CPU features; the tests compare it with `fill_band`.
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn fill_band_wide(
    shader: &impl Shade,
    r0: usize,
    width: usize,
    rgb: &mut [u8],
    depth: &mut [f32],
) {
    fill_band(shader, r0, width, rgb, depth)
}

/// Whether bands take [`fill_band_wide`].
fn wide_tiles() -> bool {
    #[cfg(test)]
    if PORTABLE_ONLY.load(std::sync::atomic::Ordering::Relaxed) {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("lzcnt")
            && std::arch::is_x86_feature_detected!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Tests set this to render through the portable tile loop only.
#[cfg(test)]
pub(crate) static PORTABLE_ONLY: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

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

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::render::{
        Camera, Clip, ClipPlane, Preset, RenderError, Scene, Shading, SsdOptions, Surface,
        VrOptions, surface_render, surface_render_frames, volume_render, volume_render_frames,
    };
    use crate::volume::{Frame, Volume};
    use ndarray::Array3;
    use std::sync::atomic::Ordering;

    /// A pixel's colour and depth made from its place and picture, to see where each lands.
    struct Places(usize);
    impl Shade for Places {
        type Scratch = ();
        fn scratch(&self) {}
        #[inline(always)]
        fn shade(&self, _: &mut (), r: usize, c: usize) -> ([f32; 3], f32) {
            let v = (self.0 * 1_000_000 + r * 1000 + c) as f32;
            let (r, c) = ((r % 256) as f32, (c % 256) as f32);
            ([r / 255.0, c / 255.0, (100 * self.0) as f32 / 255.0], v)
        }
    }

    #[test]
    fn every_pixel_of_every_picture_lands_in_its_place() {
        let shaders = [Places(0), Places(1), Places(2)];
        for (w, h) in [(70, 45), (32, 32), (1, 97), (100, 1), (517, 300)] {
            let frames = render_frames(w, h, &shaders);
            assert_eq!(frames.len(), 3);
            for (k, img) in frames.iter().enumerate() {
                assert_eq!((img.width, img.height, img.rgb.len()), (w, h, 3 * w * h));
                for r in 0..h {
                    for c in 0..w {
                        assert_eq!(
                            img.pixel(r, c),
                            [r as u8, c as u8, 100 * k as u8],
                            "{w}×{h} picture {k} ({r}, {c})"
                        );
                        assert_eq!(img.depth(r, c), (k * 1_000_000 + r * 1000 + c) as f32);
                    }
                }
            }
        }
        assert!(
            render_frames(0, 5, &shaders)
                .iter()
                .all(|f| f.rgb.is_empty())
        );
        assert!(render_frames::<Places>(8, 8, &[]).is_empty());
    }

    /// A noisy ball with a bony shell in a box, so that rays cross busy and empty bricks, cells in and out of
    /// the windows and the grid's faces, and end early or late.
    pub(crate) fn noisy_ball() -> Volume {
        let (nz, ny, nx) = (37, 45, 52);
        Volume {
            data: Array3::from_shape_fn((nz, ny, nx), |(k, j, i)| {
                let r = ((k as f32 - 18.0).powi(2) * 4.0
                    + (j as f32 - 22.0).powi(2)
                    + (i as f32 - 26.0).powi(2))
                .sqrt();
                let noise = ((k * 7919 + j * 104_729 + i * 1_299_709) % 997) as f32 - 498.0;
                let body = if r < 20.0 { 40.0 } else { -1000.0 };
                let bone = if (8.0..12.0).contains(&r) { 900.0 } else { 0.0 };
                body + bone + 0.4 * noise
            }),
            frame: Frame {
                spacing_mm: [0.8, 0.8, 2.0],
                origin_mm: [-20.0, 10.0, 5.0],
                direction: Frame::AXIS_ALIGNED,
            },
        }
    }

    /// `a` and `b` have the same bytes and the same depths bit for bit.
    pub(crate) fn assert_same_picture(a: &RgbImage, b: &RgbImage, what: &str) {
        assert_eq!(a.rgb, b.rgb, "{what}");
        let bits = |img: &RgbImage| img.depth_mm.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(a), bits(b), "{what}");
    }

    #[test]
    fn the_tile_loop_for_wider_cpus_renders_the_same_pictures_bit_for_bit() {
        let vol = noisy_ball();
        let scene = Scene::new(&vol).unwrap();
        let half = Clip {
            planes: vec![ClipPlane {
                point_mm: [0.0, 28.0, 40.0],
                normal: [0.3, 1.0, 0.0],
            }],
            boxes: vec![],
        };
        let render = |cam: &Camera, k: usize| {
            let rays = cam.rays(&vol.frame, vol.data.dim(), 61, 47, 4096).unwrap();
            let preset = Preset::ALL[k % Preset::ALL.len()];
            let clip = if k.is_multiple_of(2) {
                Clip::default()
            } else {
                half.clone()
            };
            let vr = VrOptions {
                transfer_function: preset.transfer_function(),
                shading: Shading::default(),
                clip: clip.clone(),
                background: [0.1, 0.2, 0.3],
                step_mm: None,
            };
            let ssd = SsdOptions {
                surfaces: vec![
                    Surface {
                        iso: -500.0,
                        color: [0.9, 0.7, 0.6],
                        opacity: 0.3,
                    },
                    Surface {
                        iso: 300.0,
                        color: [0.95, 0.92, 0.84],
                        opacity: 1.0,
                    },
                ],
                shading: Shading::default(),
                depth_cue: 0.4,
                clip,
                background: [0.0; 3],
                step_mm: None,
            };
            (
                volume_render(&scene, &rays, &vr).unwrap(),
                surface_render(&scene, &rays, &ssd).unwrap(),
            )
        };
        let cams: Vec<Camera> = (0..6)
            .map(|k| Camera {
                azimuth_deg: 37.0 * k as f64,
                elevation_deg: 25.0 - 10.0 * k as f64,
                ..Camera::default()
            })
            .collect();
        let wide: Vec<_> = cams.iter().enumerate().map(|(k, c)| render(c, k)).collect();
        PORTABLE_ONLY.store(true, Ordering::Relaxed);
        let portable: Vec<_> = cams.iter().enumerate().map(|(k, c)| render(c, k)).collect();
        PORTABLE_ONLY.store(false, Ordering::Relaxed);
        for (k, (a, b)) in wide.iter().zip(&portable).enumerate() {
            for (x, y) in [(&a.0, &b.0), (&a.1, &b.1)] {
                assert_same_picture(x, y, &format!("camera {k}"));
                // Each picture shows the ball and some background.
                let shown = x.depth_mm.iter().filter(|d| !d.is_nan()).count();
                assert!((100..61 * 47 - 100).contains(&shown), "camera {k}: {shown}");
            }
        }
        if !wide_tiles() {
            eprintln!("NOTE: this CPU has no AVX2/FMA/BMI2: both loops were the portable one");
        }
    }

    #[test]
    fn a_sequence_rendered_together_equals_its_frames_rendered_one_by_one() {
        let vol = Volume {
            data: Array3::from_shape_fn((30, 34, 38), |(k, j, i)| {
                let r = ((k as f32 - 15.0).powi(2)
                    + (j as f32 - 17.0).powi(2)
                    + (i as f32 - 19.0).powi(2))
                .sqrt();
                if r < 8.0 {
                    900.0
                } else if r < 13.0 {
                    40.0
                } else {
                    -1000.0
                }
            }),
            frame: Frame {
                spacing_mm: [1.0, 0.9, 0.9],
                origin_mm: [0.0; 3],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        let scene = Scene::new(&vol).unwrap();
        let rays: Vec<_> = (0..5)
            .map(|k| {
                Camera {
                    azimuth_deg: 72.0 * k as f64,
                    ..Camera::default()
                }
                .rays(&vol.frame, vol.data.dim(), 45, 37, 4096)
                .unwrap()
            })
            .collect();
        let vr = VrOptions {
            transfer_function: Preset::Bone.transfer_function(),
            shading: Shading::default(),
            clip: Clip::default(),
            background: [0.0; 3],
            step_mm: None,
        };
        let ssd = SsdOptions {
            surfaces: vec![Surface {
                iso: 300.0,
                color: [0.95, 0.92, 0.84],
                opacity: 1.0,
            }],
            shading: Shading::default(),
            depth_cue: 0.4,
            clip: Clip::default(),
            background: [0.0; 3],
            step_mm: None,
        };
        let together = volume_render_frames(&scene, &rays, &vr).unwrap();
        let surfaces = surface_render_frames(&scene, &rays, &ssd).unwrap();
        assert_eq!((together.len(), surfaces.len()), (5, 5));
        for (k, r) in rays.iter().enumerate() {
            let one = volume_render(&scene, r, &vr).unwrap();
            assert_eq!(one.rgb, together[k].rgb, "VR frame {k}");
            assert!(
                one.rgb.iter().any(|&b| b > 0),
                "VR frame {k} shows the ball"
            );
            let one = surface_render(&scene, r, &ssd).unwrap();
            assert_eq!(one.rgb, surfaces[k].rgb, "SSD frame {k}");
        }
        // Frames of different sizes are not one sequence.
        let other = Camera::default()
            .rays(&vol.frame, vol.data.dim(), 20, 37, 4096)
            .unwrap();
        let mixed = [rays[0], other];
        assert!(matches!(
            volume_render_frames(&scene, &mixed, &vr),
            Err(RenderError::InvalidParameter { name: "size", .. })
        ));
        assert!(volume_render_frames(&scene, &[], &vr).unwrap().is_empty());
    }
}
