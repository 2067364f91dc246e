//! Dead and hot detector pixels: found as outliers of a flat or dark frame (|x − m| above `k` robust
//! standard deviations, `m` the median of the pixel's 3 × 3 neighbours without itself, the scale being
//! 1.4826 × the median of |x − m| over the frame), or given as a mask, and replaced in every view by the median of
//! their valid neighbours (3 × 3, or 5 × 5 where no 3 × 3 neighbour is valid). Frames are `[v][u]`.

use ndarray::{Array2, ArrayView2, ArrayViewMut2, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;

fn six() -> f32 {
    6.0
}

/// The repair step: the outlier threshold `k_mad` (robust standard deviations, default 6) used to find
/// bad pixels in a flat or dark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RepairPixels {
    #[serde(default = "six")]
    pub k_mad: f32,
}

impl Default for RepairPixels {
    fn default() -> Self {
        Self { k_mad: six() }
    }
}

fn median(values: &mut [f32]) -> f32 {
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, f32::total_cmp);
    *m
}

/// Median of the neighbours of `(r, c)` in its 3 × 3 window (the pixel itself and places outside the frame
/// excluded; the mean of the two middle values of an even count).
fn neighbour_median(frame: &ArrayView2<'_, f32>, r: usize, c: usize) -> f32 {
    let (nr, nc) = frame.dim();
    let mut w = [0f32; 8];
    let mut k = 0;
    for dr in [-1isize, 0, 1] {
        for dc in [-1isize, 0, 1] {
            let (rr, cc) = (r as isize + dr, c as isize + dc);
            if (dr == 0 && dc == 0) || rr < 0 || cc < 0 || rr >= nr as isize || cc >= nc as isize {
                continue;
            }
            w[k] = frame[[rr as usize, cc as usize]];
            k += 1;
        }
    }
    let vals = &mut w[..k];
    vals.sort_unstable_by(f32::total_cmp);
    match k {
        0 => frame[[r, c]],
        k if !k.is_multiple_of(2) => vals[k / 2],
        k => 0.5 * (vals[k / 2 - 1] + vals[k / 2]),
    }
}

/// The bad pixels of `frame` (a flat or a dark): `true` where `|x − m| > k·1.4826·MAD`, `m` the median of the
/// pixel's neighbours.
pub fn find_outliers(frame: ArrayView2<'_, f32>, k_mad: f32) -> Result<Array2<bool>, ReconError> {
    if !(k_mad.is_finite() && k_mad > 0.0) {
        return Err(ReconError::param(
            "k_mad",
            format!("must be positive, got {k_mad}"),
        ));
    }
    if frame.is_empty() {
        return Err(ReconError::param("frame", "is empty"));
    }
    if frame.iter().any(|v| !v.is_finite()) {
        return Err(ReconError::param("frame", "contains a non-finite value"));
    }
    let mut dev = Array2::<f32>::zeros(frame.raw_dim());
    dev.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(r, mut row)| {
            for (c, d) in row.iter_mut().enumerate() {
                *d = (frame[[r, c]] - neighbour_median(&frame, r, c)).abs();
            }
        });
    let mut all: Vec<f32> = dev.iter().copied().collect();
    let mad = median(&mut all);
    // A noise-free frame has MAD 0: then any deviation above f32 rounding of the frame's scale counts.
    let scale = frame.iter().fold(0f32, |m, v| m.max(v.abs()));
    let threshold = (k_mad * 1.4826 * mad).max(scale * 1e-5);
    Ok(dev.mapv(|d| d > threshold))
}

/// Replace every pixel flagged in `mask` by the median of its valid (unflagged) neighbours; returns how
/// many pixels were repaired. A flagged pixel with no valid neighbour within 5 × 5 is left as it is.
pub fn repair_pixels(
    mut data: ArrayViewMut2<'_, f32>,
    mask: ArrayView2<'_, bool>,
) -> Result<usize, ReconError> {
    if data.shape() != mask.shape() {
        return Err(ReconError::ShapeMismatch {
            expected: mask.shape().to_vec(),
            got: data.shape().to_vec(),
        });
    }
    let (nr, nc) = data.dim();
    let mut fixes = Vec::new();
    for ((r, c), &bad) in mask.indexed_iter() {
        if !bad {
            continue;
        }
        let mut w = [0f32; 25];
        for reach in [1isize, 2] {
            let mut k = 0;
            for dr in -reach..=reach {
                for dc in -reach..=reach {
                    let (rr, cc) = (r as isize + dr, c as isize + dc);
                    if rr < 0 || cc < 0 || rr >= nr as isize || cc >= nc as isize {
                        continue;
                    }
                    let (rr, cc) = (rr as usize, cc as usize);
                    if !mask[[rr, cc]] {
                        w[k] = data[[rr, cc]];
                        k += 1;
                    }
                }
            }
            if k > 0 {
                // The lower median of an even count keeps the value one of the neighbours'.
                let vals = &mut w[..k];
                vals.sort_unstable_by(f32::total_cmp);
                fixes.push((r, c, vals[(k - 1) / 2]));
                break;
            }
        }
    }
    for &(r, c, v) in &fixes {
        data[[r, c]] = v;
    }
    Ok(fixes.len())
}
