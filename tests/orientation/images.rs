//! Fetching images and finding markers in them.

use serde_json::Value;

use crate::common::{TestApp, read_npy_f32};

pub async fn get_bytes(app: &TestApp, path: &str) -> Vec<u8> {
    let r = app.get(path).await;
    let status = r.status();
    let b = r.bytes().await.unwrap().to_vec();
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&b));
    b
}

/// A grey image (or a stack of them: `frames` × `rows` × `cols`).
#[derive(Debug, Clone, PartialEq)]
pub struct Grey {
    pub frames: usize,
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f32>,
}

impl Grey {
    pub fn at(&self, k: usize, r: usize, c: usize) -> f32 {
        self.data[(k * self.rows + r) * self.cols + c]
    }
    /// Frame `k` as a plane of values.
    pub fn frame(&self, k: usize) -> Plane<'_> {
        let n = self.rows * self.cols;
        Plane {
            rows: self.rows,
            cols: self.cols,
            values: &self.data[k * n..(k + 1) * n],
        }
    }
}

/// A `.npy` image or stack.
pub async fn npy(app: &TestApp, path: &str) -> Grey {
    let (shape, data) = read_npy_f32(&get_bytes(app, path).await);
    let (frames, rows, cols) = match shape[..] {
        [r, c] => (1, r, c),
        [f, r, c] => (f, r, c),
        _ => panic!("{path}: shape {shape:?}"),
    };
    Grey {
        frames,
        rows,
        cols,
        data,
    }
}

/// One plane of values, row by row.
#[derive(Debug, Clone, Copy)]
pub struct Plane<'a> {
    pub rows: usize,
    pub cols: usize,
    pub values: &'a [f32],
}

/// The `tEXt` chunks of a PNG.
pub fn png_text(bytes: &[u8]) -> Vec<(String, String)> {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let reader = decoder.read_info().unwrap();
    reader
        .info()
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect()
}

/// The JSON of `tEXt` chunk `key`.
pub fn png_json(bytes: &[u8], key: &str) -> Value {
    let text = png_text(bytes);
    let (_, t) = text
        .iter()
        .find(|(k, _)| k == key)
        .unwrap_or_else(|| panic!("no {key} chunk in {text:?}"));
    serde_json::from_str(t).unwrap()
}

/// An RGB PNG as the brightness (sum of the channels) of each pixel.
pub fn png_brightness(bytes: &[u8]) -> (usize, usize, Vec<f32>) {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let (w, h) = (info.width as usize, info.height as usize);
    let v = buf[..w * h * 3]
        .chunks_exact(3)
        .map(|p| p.iter().map(|&c| c as f32).sum())
        .collect();
    (h, w, v)
}

/// Centroid (row, column) of the marker seen near `near`: the brightest pixel within `radius` pixels of it,
/// then every pixel connected to that one at or above half its value (or above `floor`, whichever is
/// higher). `None` when nothing there reaches `floor`.
pub fn blob(img: Plane<'_>, near: (f64, f64), radius: f64, floor: f32) -> Option<(f64, f64)> {
    let (rows, cols) = (img.rows, img.cols);
    let at = |r: usize, c: usize| img.values[r * cols + c];
    let mut best: Option<(usize, usize)> = None;
    for r in 0..rows {
        for c in 0..cols {
            let d = (r as f64 - near.0).hypot(c as f64 - near.1);
            if d <= radius && best.is_none_or(|(br, bc)| at(r, c) > at(br, bc)) {
                best = Some((r, c));
            }
        }
    }
    let (br, bc) = best?;
    let peak = at(br, bc);
    if peak <= floor {
        return None;
    }
    let level = (peak / 2.0).max(floor);
    let mut seen = vec![false; rows * cols];
    let mut stack = vec![(br, bc)];
    seen[br * cols + bc] = true;
    let (mut sr, mut sc, mut n) = (0.0, 0.0, 0.0);
    while let Some((r, c)) = stack.pop() {
        sr += r as f64;
        sc += c as f64;
        n += 1.0;
        let next = [
            (r.wrapping_sub(1), c),
            (r + 1, c),
            (r, c.wrapping_sub(1)),
            (r, c + 1),
        ];
        for (nr, nc) in next {
            if nr < rows && nc < cols && !seen[nr * cols + nc] && at(nr, nc) >= level {
                seen[nr * cols + nc] = true;
                stack.push((nr, nc));
            }
        }
    }
    Some((sr / n, sc / n))
}

/// Assert that the marker of `what` is seen within `tol` pixels of `want` (row, column).
pub fn assert_marker(
    img: Plane<'_>,
    want: (f64, f64),
    floor: f32,
    tol: f64,
    what: &str,
) -> (f64, f64) {
    let got = blob(img, want, 1.5, floor)
        .unwrap_or_else(|| panic!("{what}: no marker near ({:.2}, {:.2})", want.0, want.1));
    assert!(
        (got.0 - want.0).abs() <= tol && (got.1 - want.1).abs() <= tol,
        "{what}: marker at ({:.2}, {:.2}), expected ({:.2}, {:.2})",
        got.0,
        got.1,
        want.0,
        want.1
    );
    got
}
