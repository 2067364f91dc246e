//! AVX2 + FMA and AVX-512F forms of the z-line cone-beam kernel of [`super::column`], which is their
//! reference and handles the AVX2 tails.
//!
//! The row positions of a vector of voxels advance by a fixed step, so their samples usually lie in a
//! short stretch of the two detector columns: the stretch is loaded from both columns, blended at the
//! column fraction once, and each voxel's pair of neighbouring samples is picked from it by permutes —
//! a window of 16 samples for 8 voxels (AVX2), 32 or 64 samples for 16 voxels (AVX-512F's two-register
//! permute). Lines whose step is too large for a window read their pairs with 64-bit loads.
#![allow(unsafe_code)] // SIMD kernel: every `unsafe` below carries its `// SAFETY:` note.

use std::arch::x86_64::*;

use crate::recon::pairs::{lanes, load_pairs, select16};

use super::column::{ColumnPanel, Placed, SLACK, ZLine, cone_column_from, placed};

/// Whether `lanes` voxels whose row positions are `step` apart read all their sample pairs from a
/// window of `window` samples starting [`behind`] the first voxel's index: their indices spread over
/// at most ⌈(lanes − 1)·|step|⌉ + 1 samples, and the last pair needs one sample more.
fn fits(step: f32, lanes: usize, window: usize) -> bool {
    (lanes - 1) as f32 * step.abs() + 3.0 <= (window - 1) as f32
}

/// How far below the first voxel's sample index a window starts: 0 when the positions rise, and
/// ⌈(lanes − 1)·|step|⌉ + 1 when they fall (the last voxel's index is at least that much lower).
fn behind(step: f32, lanes: usize) -> i32 {
    if step >= 0.0 {
        0
    } else {
        // Lines whose step is too large for a window never use it (and the conversion saturates).
        ((lanes - 1) as f32 * -step) as i32 + 2
    }
}

/// The lines of [`super::column::cone_columns`] one after the other, each [`placed`] and computed by
/// the form its step suits: 16 voxels from a window of 32 or 64 samples (AVX-512F, where `wide`), else
/// 8 voxels from a window of 16 samples or from 64-bit loads.
///
/// # Safety
/// AVX2 and FMA must be available, and AVX-512F too where `wide`; `panel` must be valid
/// (`cols·rows + SLACK ≤ q.len() < i32::MAX`, `rows ≥ 4`). Memory safety rests on these alone; the
/// values are right for voxels inside [`ZLine::span`] (the windows do not clamp positions).
#[target_feature(enable = "avx2,fma")]
pub unsafe fn cone_columns(acc: &mut [f32], panel: ColumnPanel<'_>, lines: &[Placed], wide: bool) {
    debug_assert!(panel.cols * panel.rows + SLACK <= panel.q.len());
    // SAFETY: the caller's contract, passed on; the AVX-512F loop only where `wide`.
    unsafe {
        if wide {
            columns_wide(acc, panel, lines)
        } else {
            columns_narrow(acc, panel, lines)
        }
    }
}

/// # Safety
/// As [`cone_columns`], and AVX-512F must be available.
#[target_feature(enable = "avx2,fma,avx512f")]
unsafe fn columns_wide(acc: &mut [f32], panel: ColumnPanel<'_>, lines: &[Placed]) {
    for (start, line, span) in lines {
        let Some(out) = placed(acc, panel, *start, line, *span) else {
            continue;
        };
        // SAFETY: the CPU has AVX-512F, AVX2 and FMA and the panel is valid (the caller's
        // contract); `placed` checked iu + 1 < cols and gave the span's voxels.
        unsafe {
            if fits(line.dpos, 16, 32) {
                column_wide::<32>(out, span.0, panel, line)
            } else if fits(line.dpos, 16, 64) {
                column_wide::<64>(out, span.0, panel, line)
            } else {
                column_eight(out, span.0, panel, line)
            }
        }
    }
}

/// # Safety
/// As [`cone_columns`].
#[target_feature(enable = "avx2,fma")]
unsafe fn columns_narrow(acc: &mut [f32], panel: ColumnPanel<'_>, lines: &[Placed]) {
    for (start, line, span) in lines {
        let Some(out) = placed(acc, panel, *start, line, *span) else {
            continue;
        };
        // SAFETY: the CPU has AVX2 and FMA and the panel is valid (the caller's contract); `placed`
        // checked iu + 1 < cols and gave the span's voxels.
        unsafe { column_eight(out, span.0, panel, line) }
    }
}

/// 8 voxels at a time: from a 16-sample window where the step [`fits`], else from 64-bit loads.
///
/// # Safety
/// As [`column_narrow`].
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn column_eight(acc: &mut [f32], k0: usize, panel: ColumnPanel<'_>, line: &ZLine) {
    // SAFETY: the caller's contract, passed on.
    unsafe {
        if fits(line.dpos, 8, 16) {
            column_narrow::<true>(acc, k0, panel, line)
        } else {
            column_narrow::<false>(acc, k0, panel, line)
        }
    }
}

/// 8 voxels at a time; with `WINDOW` (the step must [`fits`] 8 lanes in 16 samples) the pairs come from
/// a 16-sample window of the blended columns, otherwise from 64-bit loads in both columns.
///
/// # Safety
/// As [`cone_columns`], with `iu + 1 < cols`; `acc` holds the voxels `k0..k0 + acc.len()`.
#[inline]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn column_narrow<const WINDOW: bool>(
    acc: &mut [f32],
    k0: usize,
    panel: ColumnPanel<'_>,
    line: &ZLine,
) {
    let rows = panel.rows;
    // SAFETY: iu + 1 < cols and the panel is valid (the caller's contract).
    let (a, b) = unsafe { panel.columns(line.iu) };
    let top = rows as i32 - 2;
    let hv = _mm256_set1_ps(top as f32);
    let (p0, step) = (_mm256_set1_ps(line.pos0), _mm256_set1_ps(line.dpos));
    let (fu, w) = (_mm256_set1_ps(line.fu), _mm256_set1_ps(line.w));
    let (one, eight) = (_mm256_set1_epi32(1), _mm256_set1_ps(8.0));
    let back = behind(line.dpos, 8);
    let n = acc.len();
    let mut k = lanes(k0 as f32);
    let mut i = 0;
    while i + 8 <= n {
        let pos = _mm256_fmadd_ps(k, step, p0);
        let (c0, c1, fv) = if WINDOW {
            // The span keeps every position inside [0, rows − 2]; the window's start is clamped
            // there as well, so that its loads stay inside the panel whatever the positions.
            let iv = _mm256_cvttps_epi32(pos);
            let fv = _mm256_sub_ps(pos, _mm256_cvtepi32_ps(iv));
            let start = (_mm256_cvtsi256_si32(iv) - back).clamp(0, top) as usize;
            let rel = _mm256_sub_epi32(iv, _mm256_set1_epi32(start as i32));
            // SAFETY: start ≤ rows − 2, so the 16 floats from start in column iu + 1 end before
            // (iu + 2)·rows + 14 ≤ cols·rows + SLACK ≤ q.len().
            let (lo, hi) = unsafe {
                let (a, b) = (a.add(start), b.add(start));
                let (a0, a1) = (_mm256_loadu_ps(a), _mm256_loadu_ps(a.add(8)));
                let (b0, b1) = (_mm256_loadu_ps(b), _mm256_loadu_ps(b.add(8)));
                (
                    _mm256_fmadd_ps(fu, _mm256_sub_ps(b0, a0), a0),
                    _mm256_fmadd_ps(fu, _mm256_sub_ps(b1, a1), a1),
                )
            };
            // `fits` keeps every rel in [0, 14] (select16 reads only its low four bits).
            (
                select16(lo, hi, rel),
                select16(lo, hi, _mm256_add_epi32(rel, one)),
                fv,
            )
        } else {
            let pos = _mm256_min_ps(_mm256_max_ps(pos, _mm256_setzero_ps()), hv);
            let iv = _mm256_cvttps_epi32(pos);
            let fv = _mm256_sub_ps(pos, _mm256_cvtepi32_ps(iv));
            // SAFETY: every iv is clamped into [0, rows − 2], so iv and iv + 1 are inside both
            // columns.
            let ((a0, a1), (b0, b1)) = unsafe { (load_pairs(a, iv), load_pairs(b, iv)) };
            (
                _mm256_fmadd_ps(fu, _mm256_sub_ps(b0, a0), a0),
                _mm256_fmadd_ps(fu, _mm256_sub_ps(b1, a1), a1),
                fv,
            )
        };
        let v = _mm256_fmadd_ps(fv, _mm256_sub_ps(c1, c0), c0);
        // SAFETY: i + 8 ≤ acc.len().
        unsafe {
            let out = acc.as_mut_ptr().add(i);
            _mm256_storeu_ps(out, _mm256_fmadd_ps(w, v, _mm256_loadu_ps(out)));
        }
        k = _mm256_add_ps(k, eight);
        i += 8;
    }
    cone_column_from(&mut acc[i..], k0 + i, panel, line);
}

/// 16 voxels at a time (the last vector masked) from a window of `W` = 32 or 64 samples of the blended
/// columns; the step must [`fits`] 16 lanes in `W` samples.
///
/// # Safety
/// As [`column_narrow`], and AVX-512F must be available.
#[inline]
#[target_feature(enable = "avx2,fma,avx512f")]
unsafe fn column_wide<const W: usize>(
    acc: &mut [f32],
    k0: usize,
    panel: ColumnPanel<'_>,
    line: &ZLine,
) {
    let rows = panel.rows;
    // SAFETY: iu + 1 < cols and the panel is valid (the caller's contract).
    let (a, b) = unsafe { panel.columns(line.iu) };
    let top = rows as i32 - 2;
    let (p0, step) = (_mm512_set1_ps(line.pos0), _mm512_set1_ps(line.dpos));
    let (fu, w) = (_mm512_set1_ps(line.fu), _mm512_set1_ps(line.w));
    let (one, upper_bit) = (_mm512_set1_epi32(1), _mm512_set1_epi32(32));
    let sixteen = _mm512_set1_ps(16.0);
    let back = behind(line.dpos, 16);
    let mut k = _mm512_add_ps(
        _mm512_set1_ps(k0 as f32),
        _mm512_setr_ps(
            0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
        ),
    );
    let n = acc.len();
    let mut i = 0;
    while i < n {
        let mask: __mmask16 = if n - i >= 16 {
            0xffff
        } else {
            (1u16 << (n - i)) - 1
        };
        // The span keeps the positions of the voxels inside [0, rows − 2] (those of masked lanes
        // may lie outside: their picks are dropped). The window's start is clamped there as well,
        // so that its loads stay inside the panel whatever the positions.
        let pos = _mm512_fmadd_ps(k, step, p0);
        let iv = _mm512_cvttps_epi32(pos);
        let fv = _mm512_sub_ps(pos, _mm512_cvtepi32_ps(iv));
        let first = _mm_cvtsi128_si32(_mm512_castsi512_si128(iv));
        let start = (first - back).clamp(0, top) as usize;
        let rel = _mm512_sub_epi32(iv, _mm512_set1_epi32(start as i32));
        let rel1 = _mm512_add_epi32(rel, one);
        // Blend the two columns over the window once: `W / 16` vectors of samples.
        // SAFETY: start ≤ rows − 2 (clamped), so the W floats from start in column iu + 1 end before
        // (iu + 2)·rows + W − 2 ≤ cols·rows + SLACK ≤ q.len() (W ≤ SLACK).
        let blended = |r: usize| unsafe {
            let (a, b) = (a.add(start + 16 * r), b.add(start + 16 * r));
            let (a, b) = (_mm512_loadu_ps(a), _mm512_loadu_ps(b));
            _mm512_fmadd_ps(fu, _mm512_sub_ps(b, a), a)
        };
        // `fits` keeps every rel in [0, W − 2]; the permutes read only the index bits below W.
        let (c0, c1) = if W == 32 {
            let (lo, hi) = (blended(0), blended(1));
            (
                _mm512_permutex2var_ps(lo, rel, hi),
                _mm512_permutex2var_ps(lo, rel1, hi),
            )
        } else {
            let (v0, v1, v2, v3) = (blended(0), blended(1), blended(2), blended(3));
            let pick = |idx: __m512i| {
                let upper = _mm512_test_epi32_mask(idx, upper_bit);
                _mm512_mask_blend_ps(
                    upper,
                    _mm512_permutex2var_ps(v0, idx, v1),
                    _mm512_permutex2var_ps(v2, idx, v3),
                )
            };
            (pick(rel), pick(rel1))
        };
        let v = _mm512_fmadd_ps(fv, _mm512_sub_ps(c1, c0), c0);
        // SAFETY: the mask covers only the voxels i..min(i + 16, n) of acc (all 16 where the mask
        // is full: a plain load and store).
        unsafe {
            let out = acc.as_mut_ptr().add(i);
            if mask == 0xffff {
                _mm512_storeu_ps(out, _mm512_fmadd_ps(w, v, _mm512_loadu_ps(out)));
            } else {
                let sum = _mm512_fmadd_ps(w, v, _mm512_maskz_loadu_ps(mask, out));
                _mm512_mask_storeu_ps(out, mask, sum);
            }
        }
        k = _mm512_add_ps(k, sixteen);
        i += 16;
    }
}
