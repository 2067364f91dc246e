//! AVX2 + FMA forms of the 2D Joseph loops of [`super::joseph2_loops`], 8 consecutive samples of one ray per
//! step: positions and weights with the f32 operations of the scalar form (no FMA there, so the pairs
//! and weights are bit for bit those of [`super::joseph2::Walk2::visit`]); the forward loop reads each
//! sample's two neighbouring values with one 64-bit load, the back loop adds to them with one 64-bit
//! load and store (AVX2 has no scatter). Selected at run time by [`super::joseph2_loops::Kernel::detect`] and tested
//! against the scalar form in `joseph2_loops`'s tests.
#![allow(unsafe_code)] // SIMD kernel: every `unsafe` below carries its `// SAFETY:` note.

use std::arch::x86_64::*;

use crate::recon::pairs::load_pairs;

use super::joseph2_loops::Segment;

/// True when the CPU has AVX2 and FMA.
pub fn available() -> bool {
    crate::recon::cpu::avx2_fma()
}

/// The per-segment constants of the loops.
struct Consts {
    c0: __m256,
    dc: __m256,
    weight: __m256,
    one: __m256,
    top: __m256,
    hi: __m256,
    lanes: __m256,
    /// `(lane)·width` for each lane.
    lane_offsets: __m256i,
}

#[target_feature(enable = "avx2,fma")]
fn consts(seg: &Segment, width: usize, hi: usize) -> Consts {
    let w = width as i32;
    Consts {
        c0: _mm256_set1_ps(seg.c0),
        dc: _mm256_set1_ps(seg.dc),
        weight: _mm256_set1_ps(seg.weight),
        one: _mm256_set1_ps(1.0),
        top: _mm256_set1_ps((width - 1) as f32),
        hi: _mm256_set1_ps(hi as f32),
        lanes: _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0),
        lane_offsets: _mm256_setr_epi32(0, w, 2 * w, 3 * w, 4 * w, 5 * w, 6 * w, 7 * w),
    }
}

/// Samples `fi = i .. i + 8` (as f32) whose lines start at values `line_base` (`(i' − first)·width`
/// per lane): the index of each pair's first value, the weights `(w0, w1)` and the mask of lanes with a
/// pixel (and, when `TAIL`, below `hi`). The other lanes get index 0 and zero weights.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn samples<const TAIL: bool>(
    k: &Consts,
    fi: __m256,
    line_base: __m256i,
) -> (__m256i, __m256, __m256, __m256) {
    // t = (c0 + fi·dc) + 1 with separate roundings, as the scalar `sample` computes it.
    let t = _mm256_add_ps(_mm256_add_ps(k.c0, _mm256_mul_ps(fi, k.dc)), k.one);
    let inside = _mm256_and_ps(
        _mm256_cmp_ps::<_CMP_GT_OQ>(t, _mm256_setzero_ps()),
        _mm256_cmp_ps::<_CMP_LT_OQ>(t, k.top),
    );
    let valid = if TAIL {
        _mm256_and_ps(inside, _mm256_cmp_ps::<_CMP_LT_OQ>(fi, k.hi))
    } else {
        inside
    };
    let tc = _mm256_and_ps(t, valid);
    let j = _mm256_cvttps_epi32(tc);
    let w1 = _mm256_mul_ps(_mm256_sub_ps(tc, _mm256_cvtepi32_ps(j)), k.weight);
    let w0 = _mm256_and_ps(_mm256_sub_ps(k.weight, w1), valid);
    let idx = _mm256_add_epi32(line_base, j);
    (
        _mm256_and_si256(idx, _mm256_castps_si256(valid)),
        w0,
        w1,
        valid,
    )
}

/// The lane vectors of the first step from sample `lo`: `lo + lane` (f32, exact below 2²⁴) and
/// `(lo − first + lane)·width`, and their increments per step.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn start(k: &Consts, width: usize, first: usize, lo: usize) -> (__m256, __m256i, __m256, __m256i) {
    (
        _mm256_add_ps(_mm256_set1_ps(lo as f32), k.lanes),
        _mm256_add_epi32(
            _mm256_set1_epi32(((lo - first) * width) as i32),
            k.lane_offsets,
        ),
        _mm256_set1_ps(8.0),
        _mm256_set1_epi32(8 * width as i32),
    )
}

#[target_feature(enable = "avx2,fma")]
#[inline]
fn sum8(v: __m256) -> f32 {
    let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    let s = _mm_add_ss(s, _mm_movehdup_ps(s));
    _mm_cvtss_f32(s)
}

/// [`super::joseph2_loops::Kernel::dot`] with AVX2.
///
/// # Safety
/// AVX2 and FMA must be available; `2 ≤ width`, `first ≤ lo < hi`, `(hi − first)·width ≤ lines.len()`
/// and `hi·width < i32::MAX`, `hi, width < 2²²` (what `joseph2_loops::check` asserts).
#[target_feature(enable = "avx2,fma")]
pub unsafe fn dot(
    lines: &[f32],
    width: usize,
    first: usize,
    seg: &Segment,
    lo: usize,
    hi: usize,
) -> f32 {
    let k = consts(seg, width, hi);
    let base = lines.as_ptr();
    let (mut fi, mut line_base, df, dl) = start(&k, width, first, lo);
    let mut acc0 = _mm256_setzero_ps();
    let mut acc1 = _mm256_setzero_ps();
    // Full steps, then one masked step for the last 1–8 samples.
    let mut i = lo;
    loop {
        let tail = i + 8 >= hi;
        let (idx, w0, w1, valid) = if tail {
            samples::<true>(&k, fi, line_base)
        } else {
            samples::<false>(&k, fi, line_base)
        };
        // SAFETY: a lane below `hi` has t ∈ (0, width − 1), so its index is (i' − first)·width + j
        // with j ≤ width − 2 and both values lie in its line, inside `lines`; other lanes (those
        // past `hi` exist only in the tail step, which masks them) read values 0 and 1 (width ≥ 2,
        // one line at least).
        let (a, b) = unsafe { load_pairs(base, idx) };
        // Lanes without a pixel add nothing, even where values 0 and 1 are not finite.
        let (a, b) = (_mm256_and_ps(a, valid), _mm256_and_ps(b, valid));
        acc0 = _mm256_fmadd_ps(w0, a, acc0);
        acc1 = _mm256_fmadd_ps(w1, b, acc1);
        if tail {
            break;
        }
        i += 8;
        fi = _mm256_add_ps(fi, df);
        line_base = _mm256_add_epi32(line_base, dl);
    }
    sum8(_mm256_add_ps(acc0, acc1))
}

/// [`super::joseph2_loops::Kernel::axpy`] with AVX2 positions and weights; each sample adds its two values
/// with one 64-bit load, add and store (AVX2 has no scatter).
///
/// # Safety
/// As [`dot`].
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
pub unsafe fn axpy(
    lines: &mut [f32],
    width: usize,
    first: usize,
    seg: &Segment,
    lo: usize,
    hi: usize,
    alpha: f32,
) {
    let k = consts(seg, width, hi);
    let va = _mm256_set1_ps(alpha);
    let base = lines.as_mut_ptr();
    let (mut fi, mut line_base, df, dl) = start(&k, width, first, lo);
    let mut idx = [0i32; 8];
    let mut i = lo;
    loop {
        let tail = i + 8 >= hi;
        let (p, w0, w1, valid) = if tail {
            samples::<true>(&k, fi, line_base)
        } else {
            samples::<false>(&k, fi, line_base)
        };
        // Lanes without a pixel add exactly 0 to values 0 and 1, whatever `alpha` is.
        let du = _mm256_and_ps(_mm256_mul_ps(va, w0), valid);
        let dv = _mm256_and_ps(_mm256_mul_ps(va, w1), valid);
        // (du, dv) pairs: lo = [0 1 | 4 5], hi = [2 3 | 6 7] (lane numbers).
        let lo_pairs = _mm256_unpacklo_ps(du, dv);
        let hi_pairs = _mm256_unpackhi_ps(du, dv);
        let quads = [
            _mm256_castps256_ps128(lo_pairs),
            _mm256_castps256_ps128(hi_pairs),
            _mm256_extractf128_ps::<1>(lo_pairs),
            _mm256_extractf128_ps::<1>(hi_pairs),
        ];
        // SAFETY: `idx` holds 8 values (unaligned store).
        unsafe { _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, p) };
        for (q, pair) in quads.into_iter().enumerate() {
            for (half, d) in [pair, _mm_movehl_ps(pair, pair)].into_iter().enumerate() {
                let at = idx[2 * q + half] as usize;
                // SAFETY: as in `dot`, values `at` and `at + 1` lie in `lines` (lanes past `hi` or
                // without a pixel have index 0 and add zeros); one 8-byte unaligned load and store
                // (the pair is only 4-byte aligned), one sample at a time through the raw pointer.
                unsafe {
                    let cell = base.add(at) as *mut u8;
                    let cur = _mm_castsi128_ps(_mm_loadu_si64(cell));
                    _mm_storeu_si64(cell, _mm_castps_si128(_mm_add_ps(cur, d)));
                }
            }
        }
        if tail {
            break;
        }
        i += 8;
        fi = _mm256_add_ps(fi, df);
        line_base = _mm256_add_epi32(line_base, dl);
    }
}
