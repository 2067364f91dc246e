//! Stored renderings (uint8 RGB `.npy`, `[frames][rows][columns][3]`) and what they are sent as: one frame as
//! an RGB PNG, every frame as an animated PNG, or RGB Secondary Capture (one frame, or all of them as a
//! multi-frame instance) in the source's study and frame of reference.

use sha2::{Digest, Sha256};

use super::query::{ProductFormat, ProductQuery, RenderContext};
use crate::dicom::{RgbFrames, write_secondary_capture_rgb};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::dicom_problem;
use crate::jobs::model::{FileInfo, ProductResult};
use crate::render::{RenderError, RgbImage, encode_rgb_apng, encode_rgb_png};
use crate::storage::npy::hex;

const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Size and SHA-256 of a stored file.
pub fn file_info(bytes: &[u8]) -> FileInfo {
    FileInfo {
        bytes: bytes.len() as u64,
        sha256: hex(&Sha256::digest(bytes)),
    }
}

/// Encode equally sized frames as a uint8 `.npy` of shape `[frames, rows, columns, 3]` (format 1.0).
pub fn encode_rgb_npy(frames: &[RgbImage]) -> Vec<u8> {
    let (h, w) = frames.first().map_or((0, 0), |f| (f.height, f.width));
    let mut dict = format!(
        "{{'descr': '|u1', 'fortran_order': False, 'shape': ({}, {h}, {w}, 3), }}",
        frames.len()
    );
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len() + frames.len() * h * w * 3);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    for f in frames {
        out.extend_from_slice(&f.rgb);
    }
    out
}

/// The frames of a `.npy` written by [`encode_rgb_npy`].
pub fn decode_rgb_npy(bytes: &[u8]) -> Result<Vec<RgbImage>, Problem> {
    let bad = || {
        tracing::error!("a stored rendering is not a uint8 RGB .npy");
        Problem::internal()
    };
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(bad());
    }
    let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = bytes
        .get(10..10 + len)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(bad)?;
    if !header.contains("'|u1'") {
        return Err(bad());
    }
    let shape: Vec<usize> = header
        .split("'shape': (")
        .nth(1)
        .and_then(|t| t.split(')').next())
        .map(|t| {
            t.split(',')
                .filter(|x| !x.trim().is_empty())
                .filter_map(|x| x.trim().parse().ok())
                .collect()
        })
        .ok_or_else(bad)?;
    let [n, h, w, 3] = shape[..] else {
        return Err(bad());
    };
    let data = &bytes[10 + len..];
    let frame = h * w * 3;
    if data.len() != n * frame {
        return Err(bad());
    }
    Ok(data
        .chunks_exact(frame.max(1))
        .map(|c| RgbImage {
            width: w,
            height: h,
            rgb: c.to_vec(),
            depth_mm: Vec::new(),
        })
        .collect())
}

fn render_problem(e: &RenderError) -> Problem {
    Problem::new(ErrorCode::from(e), e.to_string())
}

/// True for products stored as RGB renderings.
pub fn is_rendering(p: &ProductResult) -> bool {
    matches!(p.kind.as_str(), "volume_render" | "surface_render")
}

/// A stored rendering as PNG (frame `frame`, default 0), APNG (every frame) or Secondary Capture (frame
/// `frame`, or every frame as one multi-frame instance when no frame is named).
pub fn render_rgb_product(
    bytes: &[u8],
    p: &ProductResult,
    q: &ProductQuery,
    format: ProductFormat,
    ctx: &RenderContext,
) -> Result<Vec<u8>, Problem> {
    let frames = decode_rgb_npy(bytes)?;
    let n = frames.len();
    let pick = |k: usize| {
        frames.get(k).ok_or_else(|| {
            Problem::new(
                ErrorCode::SliceOutOfRange,
                format!("frame {k} is outside the {n} frames of the product"),
            )
        })
    };
    let description = p.description.clone().unwrap_or_default();
    // PNG text of frame `k`: what the picture shows and the screen sides of that frame.
    let text = |k: usize| {
        let mut text = vec![("Description".to_string(), description.clone())];
        if let Some(o) = p.frame_sides(k, ctx.patient) {
            text.push((
                "Orientation".to_string(),
                serde_json::to_string(&o).unwrap_or_default(),
            ));
        }
        text
    };
    let delay = q.delay_ms.unwrap_or(100);
    match format {
        ProductFormat::Png => {
            let k = q.frame.unwrap_or(0);
            encode_rgb_png(pick(k)?, &text(k)).map_err(|e| render_problem(&e))
        }
        ProductFormat::Apng => {
            encode_rgb_apng(&frames, delay, &text(0)).map_err(|e| render_problem(&e))
        }
        ProductFormat::Dicom => {
            let chosen: Vec<&RgbImage> = match q.frame {
                Some(k) => vec![pick(k)?],
                None => frames.iter().collect(),
            };
            let first = chosen.first().ok_or_else(Problem::internal)?;
            let data: Vec<&[u8]> = chosen.iter().map(|f| f.rgb.as_slice()).collect();
            // One instance of every frame names the sides only when the frames share them.
            let sides = match q.frame {
                Some(k) => p.frame_sides(k, ctx.patient),
                None => p.shared_sides(ctx.patient),
            }
            .filter(|_| ctx.patient);
            write_secondary_capture_rgb(
                &RgbFrames {
                    rows: first.height,
                    columns: first.width,
                    frames: &data,
                    frame_time_ms: delay as f64,
                },
                &ctx.meta,
                &description,
                sides.as_ref(),
            )
            .map(|(_, b)| b)
            .map_err(|e| dicom_problem(&e))
        }
        ProductFormat::Npy | ProductFormat::Stl => Err(Problem::internal()),
    }
}
