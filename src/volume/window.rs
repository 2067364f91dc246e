//! Window/level, Hounsfield conversion and greyscale PNG encoding.

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use super::error::VolumeError;

/// Linear attenuation of water (1/mm) at about 70 keV, the default for μ → HU.
pub const MU_WATER_PER_MM: f64 = 0.0192;

/// Hounsfield units of attenuation `mu` (1/mm): HU = 1000 (μ − μ_water)/μ_water; air (μ = 0) is −1000.
pub fn mu_to_hu(mu: f32, mu_water: f64) -> f32 {
    (1000.0 * (mu as f64 - mu_water) / mu_water) as f32
}

/// A display window: values from `level − width/2` (black) to `level + width/2` (white).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Window {
    pub width: f64,
    pub level: f64,
}

impl Window {
    /// A window with a finite positive width and a finite level.
    pub fn new(width: f64, level: f64) -> Result<Self, VolumeError> {
        if !(width.is_finite() && width > 0.0 && level.is_finite()) {
            return Err(VolumeError::BadWindow { width, level });
        }
        Ok(Self { width, level })
    }

    /// A window from the 0.5th to the 99.5th percentile of the finite values of `img` (width 1 when flat).
    pub fn auto(img: ArrayView2<'_, f32>) -> Self {
        let mut v: Vec<f32> = img.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Self {
                width: 1.0,
                level: 0.0,
            };
        }
        let n = v.len();
        let lo_k = (n - 1) * 5 / 1000;
        let hi_k = (n - 1) - (n - 1) * 5 / 1000;
        let lo = *v.select_nth_unstable_by(lo_k, f32::total_cmp).1 as f64;
        let hi = *v.select_nth_unstable_by(hi_k, f32::total_cmp).1 as f64;
        let width = if hi > lo { hi - lo } else { 1.0 };
        Self {
            width,
            level: if hi > lo { (hi + lo) / 2.0 } else { lo },
        }
    }

    /// Map `v` to [0, 1].
    pub fn unit(&self, v: f32) -> f64 {
        let lo = self.level - self.width / 2.0;
        let t = (v as f64 - lo) / self.width;
        if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) }
    }
}

/// The usual CT display windows (width/level in HU).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WindowPreset {
    /// 400/40.
    SoftTissue,
    /// 1500/−600.
    Lung,
    /// 150/90.
    Liver,
    /// 2500/480.
    Bone,
    /// 80/40.
    Brain,
}

impl WindowPreset {
    pub fn window(self) -> Window {
        let (width, level) = match self {
            WindowPreset::SoftTissue => (400.0, 40.0),
            WindowPreset::Lung => (1500.0, -600.0),
            WindowPreset::Liver => (150.0, 90.0),
            WindowPreset::Bone => (2500.0, 480.0),
            WindowPreset::Brain => (80.0, 40.0),
        };
        Window { width, level }
    }
}

/// Sample depth of an encoded image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum BitDepth {
    #[default]
    #[serde(rename = "8")]
    Eight,
    #[serde(rename = "16")]
    Sixteen,
}

/// Encode `img` (`[row][column]`) as a greyscale PNG through `window`.
pub fn encode_png(
    img: ArrayView2<'_, f32>,
    window: Window,
    depth: BitDepth,
) -> Result<Vec<u8>, VolumeError> {
    encode_png_annotated(img, window, depth, &[])
}

/// [`encode_png`] with `(keyword, text)` pairs written as PNG `tEXt` chunks before the image data (keywords
/// of 1–79 Latin-1 characters).
pub fn encode_png_annotated(
    img: ArrayView2<'_, f32>,
    window: Window,
    depth: BitDepth,
    text: &[(String, String)],
) -> Result<Vec<u8>, VolumeError> {
    let (h, w) = img.dim();
    if h == 0 || w == 0 {
        return Err(VolumeError::Empty);
    }
    let window = Window::new(window.width, window.level)?;
    let too_big = |_| VolumeError::InvalidParameter {
        name: "image",
        reason: "dimensions exceed the PNG limit".into(),
    };
    let (pw, ph) = (
        u32::try_from(w).map_err(too_big)?,
        u32::try_from(h).map_err(too_big)?,
    );
    let pixels: Vec<u8> = match depth {
        BitDepth::Eight => img
            .iter()
            .map(|&v| (window.unit(v) * 255.0).round() as u8)
            .collect(),
        BitDepth::Sixteen => img
            .iter()
            .flat_map(|&v| ((window.unit(v) * 65535.0).round() as u16).to_be_bytes())
            .collect(),
    };
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, pw, ph);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(match depth {
        BitDepth::Eight => png::BitDepth::Eight,
        BitDepth::Sixteen => png::BitDepth::Sixteen,
    });
    for (k, v) in text {
        enc.add_text_chunk(k.clone(), v.clone())
            .map_err(|e| VolumeError::Encode(e.to_string()))?;
    }
    let mut writer = enc
        .write_header()
        .map_err(|e| VolumeError::Encode(e.to_string()))?;
    writer
        .write_image_data(&pixels)
        .map_err(|e| VolumeError::Encode(e.to_string()))?;
    writer
        .finish()
        .map_err(|e| VolumeError::Encode(e.to_string()))?;
    Ok(out)
}

/// Encode equally sized `frames` as an 8-bit greyscale animated PNG (APNG), `delay_ms` per frame, looping.
pub fn encode_apng(
    frames: &[ndarray::Array2<f32>],
    window: Window,
    delay_ms: u16,
) -> Result<Vec<u8>, VolumeError> {
    encode_apng_annotated(frames, window, delay_ms, &[])
}

/// [`encode_apng`] with `(keyword, text)` pairs written as PNG `tEXt` chunks.
pub fn encode_apng_annotated(
    frames: &[ndarray::Array2<f32>],
    window: Window,
    delay_ms: u16,
    text: &[(String, String)],
) -> Result<Vec<u8>, VolumeError> {
    let first = frames.first().ok_or(VolumeError::Empty)?;
    let (h, w) = first.dim();
    if h == 0 || w == 0 {
        return Err(VolumeError::Empty);
    }
    if frames.iter().any(|f| f.dim() != (h, w)) {
        return Err(VolumeError::InvalidParameter {
            name: "frames",
            reason: "all frames must have the same size".into(),
        });
    }
    let window = Window::new(window.width, window.level)?;
    let enc_err = |e: png::EncodingError| VolumeError::Encode(e.to_string());
    let too_big = |_| VolumeError::InvalidParameter {
        name: "image",
        reason: "dimensions exceed the PNG limit".into(),
    };
    let n = u32::try_from(frames.len()).map_err(too_big)?;
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(
        &mut out,
        u32::try_from(w).map_err(too_big)?,
        u32::try_from(h).map_err(too_big)?,
    );
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    for (k, v) in text {
        enc.add_text_chunk(k.clone(), v.clone()).map_err(enc_err)?;
    }
    enc.set_animated(n, 0).map_err(enc_err)?;
    enc.set_frame_delay(delay_ms, 1000).map_err(enc_err)?;
    let mut writer = enc.write_header().map_err(enc_err)?;
    for f in frames {
        let pixels: Vec<u8> = f
            .iter()
            .map(|&v| (window.unit(v) * 255.0).round() as u8)
            .collect();
        writer.write_image_data(&pixels).map_err(enc_err)?;
    }
    writer.finish().map_err(enc_err)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    #[test]
    fn hounsfield_units_put_air_at_minus_1000_and_water_at_0() {
        assert_eq!(mu_to_hu(0.0, MU_WATER_PER_MM), -1000.0);
        assert!(mu_to_hu(0.0192, MU_WATER_PER_MM).abs() < 1e-3);
        assert!((mu_to_hu(0.0384, MU_WATER_PER_MM) - 1000.0).abs() < 1e-2);
    }

    #[test]
    fn the_window_maps_its_ends_to_black_and_white() {
        let w = WindowPreset::SoftTissue.window();
        assert_eq!(w.unit(-160.0), 0.0);
        assert_eq!(w.unit(240.0), 1.0);
        assert!((w.unit(40.0) - 0.5).abs() < 1e-12);
        assert!(Window::new(0.0, 1.0).is_err());
        assert!(Window::new(f64::NAN, 1.0).is_err());
    }

    #[test]
    fn auto_window_spans_the_bulk_of_the_values() {
        let img = ndarray::Array2::from_shape_fn((10, 100), |(r, c)| (r * 100 + c) as f32);
        let w = Window::auto(img.view());
        assert!((w.level - 499.5).abs() < 5.0, "{w:?}");
        assert!((w.width - 990.0).abs() < 10.0, "{w:?}");
    }

    #[test]
    fn an_animated_png_carries_every_frame() {
        let frames: Vec<_> = (0..3)
            .map(|k| ndarray::Array2::from_elem((4, 5), k as f32))
            .collect();
        let bytes = encode_apng(&frames, Window::new(2.0, 1.0).unwrap(), 100).unwrap();
        let mut r = png::Decoder::new(std::io::Cursor::new(bytes))
            .read_info()
            .unwrap();
        assert_eq!(r.info().animation_control().map(|a| a.num_frames), Some(3));
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        let mut firsts = Vec::new();
        for _ in 0..3 {
            r.next_frame(&mut buf).unwrap();
            firsts.push(buf[0]);
        }
        assert_eq!(firsts, vec![0, 128, 255]);
        assert!(encode_apng(&[], Window::new(1.0, 0.0).unwrap(), 100).is_err());
    }

    #[test]
    fn png_round_trips_through_the_decoder_in_8_and_16_bits() {
        let img = array![[0.0f32, 0.5], [1.0, 2.0]];
        let w = Window::new(1.0, 0.5).unwrap();
        for (depth, max) in [(BitDepth::Eight, 255u32), (BitDepth::Sixteen, 65535)] {
            let bytes = encode_png(img.view(), w, depth).unwrap();
            let dec = png::Decoder::new(std::io::Cursor::new(bytes));
            let mut r = dec.read_info().unwrap();
            let mut buf = vec![0; r.output_buffer_size().unwrap()];
            let info = r.next_frame(&mut buf).unwrap();
            assert_eq!((info.width, info.height), (2, 2));
            let vals: Vec<u32> = match depth {
                BitDepth::Eight => buf[..4].iter().map(|&b| b as u32).collect(),
                BitDepth::Sixteen => buf[..8]
                    .chunks(2)
                    .map(|c| u16::from_be_bytes([c[0], c[1]]) as u32)
                    .collect(),
            };
            assert_eq!(vals, vec![0, max.div_ceil(2), max, max]);
        }
    }
}
