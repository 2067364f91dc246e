//! The minimal conversion of a scan's views into ctrecon's projections: line integrals
//! `p = −ln((I − D)/(F − D))` with the scan's dark `D` and flat `F` when it has both, else
//! `p = −ln(I / white level)` (DESIGN.md §11), the transmission clamped to [`TRANSMISSION_FLOOR`] (clamped
//! pixels counted), oriented into ctrecon's detector order. One function, to be replaced by the full
//! preprocessing chain.

use ndarray::Array3;

use super::{Intensity, Scan, ScanError};

/// Smallest transmission kept: darker (or non-finite) pixels are clamped to it (p ≤ 13.8).
pub const TRANSMISSION_FLOOR: f32 = 1e-6;

/// Projections `[view][v][u]` as line integrals, and how many pixels were clamped.
#[derive(Debug)]
pub struct LineIntegrals {
    pub projections: Array3<f32>,
    pub clamped: u64,
}

/// Read every view of `scan` and convert it to line integrals in ctrecon's detector order. Refuses
/// (before allocating) a stack of more than `max_bytes` of `f32`.
pub fn line_integrals(scan: &mut Scan, max_bytes: u64) -> Result<LineIntegrals, ScanError> {
    let (nv, nu) = scan.views.shape();
    let n = scan.views.view_count();
    let bytes = (n as u64)
        .saturating_mul(nv as u64)
        .saturating_mul(nu as u64)
        .saturating_mul(4);
    if bytes > max_bytes {
        return Err(ScanError::Limit {
            file: scan.source.clone(),
            what: format!(
                "{n} views of {nu} × {nv} need {bytes} bytes as floats (at most {max_bytes})"
            ),
        });
    }
    let white = match scan.intensity {
        Intensity::FlatCorrected { white_level } | Intensity::Raw { white_level } => {
            white_level as f32
        }
        Intensity::Transmission => 1.0,
    };
    let refs = match (&scan.dark, &scan.flat) {
        (Some(d), Some(f)) if d.len() == nv * nu && f.len() == nv * nu => {
            Some((d.clone(), f.clone()))
        }
        (None, Some(f)) if f.len() == nv * nu => Some((vec![0.0; nv * nu], f.clone())),
        _ => None,
    };
    let mut out = Array3::<f32>::zeros((n, nv, nu));
    let mut image = vec![0f32; nv * nu];
    let mut line = vec![0f32; nv * nu];
    let mut clamped = 0u64;
    for (i, mut view) in out.outer_iter_mut().enumerate() {
        scan.views.read_view(i, &mut image)?;
        for (k, p) in line.iter_mut().enumerate() {
            let t = match &refs {
                Some((d, f)) => (image[k] - d[k]) / (f[k] - d[k]),
                None => image[k] / white,
            };
            let t = if t.is_finite() && t >= TRANSMISSION_FLOOR {
                t
            } else {
                clamped += 1;
                TRANSMISSION_FLOOR
            };
            *p = -t.ln();
        }
        let Some(dst) = view.as_slice_mut() else {
            unreachable!("a fresh array is contiguous")
        };
        scan.orientation.apply(&line, nv, nu, dst);
    }
    Ok(LineIntegrals {
        projections: out,
        clamped,
    })
}
