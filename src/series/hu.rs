//! The output planes in Hounsfield units: stored values rescaled (padding to [`PADDING_HU`]), each kept
//! slice converted in parallel, or planes on a uniform grid interpolated linearly between their neighbours.

use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

use super::{PADDING_HU, SeriesError, Slice};
use crate::recon::control::Control;

/// Stored values to HU (padding to [`PADDING_HU`]), counting padded pixels.
fn hu_of(s: &Slice, out: &mut [f32], padded: &AtomicUsize) {
    let (m, b) = (s.rescale_slope, s.rescale_intercept);
    let mut n = 0usize;
    for (o, &v) in out.iter_mut().zip(&s.stored) {
        let pad = s
            .padding
            .is_some_and(|(lo, hi)| (v as f64) >= lo.min(hi) && (v as f64) <= lo.max(hi));
        n += pad as usize;
        *o = if pad {
            PADDING_HU
        } else {
            (v as f64 * m + b) as f32
        };
    }
    padded.fetch_add(n, Ordering::Relaxed);
}

/// The output planes in HU: each kept slice converted (in parallel), or planes every `spacing_n` interpolated
/// linearly between their neighbours. Returns the number of padded pixels.
pub(super) fn fill_hu(
    data: &mut [f32],
    plane: usize,
    slices: &[Slice],
    kept: &[(f64, usize)],
    resample: bool,
    spacing_n: f64,
    ctl: Control<'_>,
) -> Result<usize, SeriesError> {
    let padded = AtomicUsize::new(0);
    let (nz, out_nz) = (kept.len(), data.len() / plane);
    if resample {
        let d0 = kept[0].0;
        let mut hu_a = vec![0f32; plane];
        let mut hu_b = vec![0f32; plane];
        let mut loaded = (usize::MAX, usize::MAX);
        let mut seg = 0usize;
        for (k, out) in data.chunks_exact_mut(plane).enumerate() {
            ctl.check()?;
            ctl.step("assemble", k as f64 / out_nz as f64);
            let d = d0 + k as f64 * spacing_n;
            while seg + 2 < nz && kept[seg + 1].0 < d - 1e-9 {
                seg += 1;
            }
            let (da, db) = (kept[seg].0, kept[(seg + 1).min(nz - 1)].0);
            let t = if db > da {
                ((d - da) / (db - da)).clamp(0.0, 1.0)
            } else {
                0.0
            } as f32;
            let (ia, ib) = (kept[seg].1, kept[(seg + 1).min(nz - 1)].1);
            if loaded != (ia, ib) {
                hu_of(&slices[ia], &mut hu_a, &padded);
                hu_of(&slices[ib], &mut hu_b, &padded);
                loaded = (ia, ib);
            }
            for ((o, a), b) in out.iter_mut().zip(&hu_a).zip(&hu_b) {
                *o = a + t * (b - a);
            }
        }
    } else {
        // Slices convert independently: one task per slice on the caller's pool.
        let done = AtomicUsize::new(0);
        data.par_chunks_exact_mut(plane).enumerate().try_for_each(
            |(k, out)| -> Result<(), SeriesError> {
                ctl.check()?;
                hu_of(&slices[kept[k].1], out, &padded);
                let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_multiple_of(16) {
                    ctl.step("assemble", n as f64 / out_nz as f64);
                }
                Ok(())
            },
        )?;
    }
    ctl.step("assemble", 1.0);
    Ok(padded.load(Ordering::Relaxed))
}
