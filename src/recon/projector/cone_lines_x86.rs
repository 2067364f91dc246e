//! The loops with explicit AVX2 and AVX-512F row loops (8 or 16 rows per step, positions and
//! weights in the same f32 operations as [`position`], no fused multiply-add) and the line blends
//! compiled with those sets. Calling them is `unsafe` only because the CPU must have the sets.
use std::arch::x86_64::*;

use super::*;

#[path = "cone_lines_windows.rs"]
mod windows;
use windows::{every_other16, pick8, pick16, window_add};

/// `line = w0·a + w1·b` over `a.len()` values.
#[inline(always)]
fn blend(a: &[f32], b: &[f32], line: &mut [f32], step: &PlaneStep) {
    let len = a.len();
    for ((l, x), y) in line[..len].iter_mut().zip(a).zip(&b[..len]) {
        *l = step.w0 * *x + step.w1 * *y;
    }
}

macro_rules! row_loops {
    ($forward:ident, $back:ident, $feature:literal, $lanes:literal, $v:ty, $set1:ident, $setr:expr,
     $add:ident, $sub:ident, $mul:ident, $max:ident, $min:ident, $cvtt:ident, $cvt:ident,
     $loadu:ident, $storeu:ident, $storei:ident, $every_other:expr, $pick:expr, $scatter:expr,
     $tail:ident, $back_tail:ident) => {
        #[target_feature(enable = $feature)]
        pub unsafe fn $forward(
            a: &[f32],
            b: &[f32],
            line: &mut [f32],
            step: &PlaneStep,
            rows: Range<usize>,
            acc: &mut [f32],
        ) {
            blend(a, b, line, step);
            let len = a.len();
            let hi = (len - 2) as f32;
            let acc = &mut acc[..rows.end];
            let mut r = rows.start;
            let (e0, de, one, zero, top) = (
                $set1(step.e0),
                $set1(step.de),
                $set1(1.0),
                $set1(0.0),
                $set1(hi),
            );
            let lane = $setr;
            while r + $lanes <= rows.end {
                let rv = $add($set1(r as f32), lane);
                let q = $add($add(e0, $mul(rv, de)), one);
                let q = $min($max(q, zero), top);
                let i = $cvtt(q);
                let f = $sub(q, $cvt(i));
                // SAFETY: the clamp keeps every index in [0, len − 2], so `i` and `i + 1` read
                // inside `line`; `r + lanes ≤ rows.end ≤ acc.len()`.
                let (g0, g1) = unsafe { $pick(line, i) };
                let t = $add($mul($sub(one, f), g0), $mul(f, g1));
                unsafe {
                    let p = acc.as_mut_ptr().add(r);
                    $storeu(p, $add($loadu(p), t));
                }
                r += $lanes;
            }
            // SAFETY: the CPU has the form's features; `acc` holds `rows.end` values; `line`
            // holds at least `len` values.
            unsafe { $tail(line, len, step, rows.start, r, acc) };
        }

        #[target_feature(enable = $feature)]
        pub unsafe fn $back(
            a: &mut [f32],
            b: &mut [f32],
            lines: &mut [f32],
            step: &PlaneStep,
            rows: Range<usize>,
            data: &[f32],
        ) {
            let len = a.len();
            let hi = (len - 2) as f32;
            let (first, second) = split_scratch(lines, len);
            let n = rows.len();
            let data = &data[..n];
            let (e0, de, one, zero, top) = (
                $set1(step.e0),
                $set1(step.de),
                $set1(1.0),
                $set1(0.0),
                $set1(hi),
            );
            let stride = stride(step);
            let lane = $mul($setr, $set1(stride as f32));
            let spaced = $cvtt(lane);
            let (mut idx, mut p0, mut p1) = ([0i32; $lanes], [0.0f32; $lanes], [0.0f32; $lanes]);
            for parity in 0..stride {
                let mut j = parity;
                while j + stride * ($lanes - 1) < n {
                    let rv = $add($set1((rows.start + j) as f32), lane);
                    let q = $add($add(e0, $mul(rv, de)), one);
                    let q = $min($max(q, zero), top);
                    let i = $cvtt(q);
                    let f = $sub(q, $cvt(i));
                    // SAFETY: rows j, j + stride, …, j + stride·(lanes − 1) < n lie in `data`.
                    let d = unsafe {
                        if stride == 1 {
                            $loadu(data.as_ptr().add(j))
                        } else {
                            $every_other(&data[j..], spaced)
                        }
                    };
                    let (v0, v1) = ($mul($sub(one, f), d), $mul(f, d));
                    // SAFETY: the clamp keeps every index in [0, len − 2], inside both lines.
                    if !unsafe { $scatter(first, second, i, v0, v1) } {
                        // SAFETY: the stores fill the local arrays of `lanes` values.
                        unsafe {
                            $storei(idx.as_mut_ptr().cast(), i);
                            $storeu(p0.as_mut_ptr(), v0);
                            $storeu(p1.as_mut_ptr(), v1);
                        }
                        for l in 0..$lanes {
                            let k = (idx[l] as usize).min(len - 2);
                            first[k] += p0[l];
                            second[k] += p1[l];
                        }
                    }
                    j += stride * $lanes;
                }
                // SAFETY: the CPU has the form's features; rows j, j + stride, … < n lie in `data`;
                // both lines hold at least `len` values.
                unsafe { $back_tail(first, second, len, step, rows.start, j, stride, data) };
            }
            merge_and_spread(a, b, first, second, step);
        }
    };
}

row_loops!(
    forward_avx2,
    back_avx2,
    "avx2,fma",
    8,
    __m256,
    _mm256_set1_ps,
    _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0),
    _mm256_add_ps,
    _mm256_sub_ps,
    _mm256_mul_ps,
    _mm256_max_ps,
    _mm256_min_ps,
    _mm256_cvttps_epi32,
    _mm256_cvtepi32_ps,
    _mm256_loadu_ps,
    _mm256_storeu_ps,
    _mm256_storeu_si256,
    |d: &[f32], i: __m256i| _mm256_i32gather_ps::<4>(d.as_ptr(), i),
    pick8,
    no_scatter,
    tail_rows,
    back_tail_rows
);

/// The back loop's rows `j, j + stride, … < data.len()` one by one, on lines of `len` values
/// (the scratch lines may be longer).
///
/// # Safety
/// None beyond the CPU having AVX2 (the signature matches [`back_tail16`]).
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
unsafe fn back_tail_rows(
    first: &mut [f32],
    second: &mut [f32],
    len: usize,
    step: &PlaneStep,
    start: usize,
    j: usize,
    stride: usize,
    data: &[f32],
) {
    let (first, second) = (&mut first[..len], &mut second[..len]);
    let hi = (len - 2) as f32;
    for j in (j..data.len()).step_by(stride) {
        let (k, f) = position(step, start + j, hi);
        let k = k.min(len - 2);
        first[k] += (1.0 - f) * data[j];
        second[k] += f * data[j];
    }
}

/// The rows `r ..` of `acc` one by one (the forward loop's last, partial vector).
///
/// # Safety
/// None beyond the CPU having AVX2 (the signature matches [`tail16`]).
#[target_feature(enable = "avx2,fma")]
unsafe fn tail_rows(
    line: &[f32],
    len: usize,
    step: &PlaneStep,
    _start: usize,
    r: usize,
    acc: &mut [f32],
) {
    let line = &line[..len];
    let hi = (len - 2) as f32;
    for (j, out) in acc[r..].iter_mut().enumerate() {
        let (k, f) = position(step, r + j, hi);
        *out += (1.0 - f) * line[k.min(len - 2)] + f * line[(k + 1).min(len - 1)];
    }
}

/// AVX2 has no scatter: the rows are spread one by one.
///
/// # Safety
/// None beyond the CPU having AVX2 (the signature matches [`scatter_distinct`]).
#[target_feature(enable = "avx2,fma")]
unsafe fn no_scatter(_: &mut [f32], _: &mut [f32], _: __m256i, _: __m256, _: __m256) -> bool {
    false
}

row_loops!(
    forward_avx512,
    back_avx512,
    "avx512f,avx2,fma,bmi2,popcnt",
    16,
    __m512,
    _mm512_set1_ps,
    _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0
    ),
    _mm512_add_ps,
    _mm512_sub_ps,
    _mm512_mul_ps,
    _mm512_max_ps,
    _mm512_min_ps,
    _mm512_cvttps_epi32,
    _mm512_cvtepi32_ps,
    _mm512_loadu_ps,
    _mm512_storeu_ps,
    _mm512_storeu_si512,
    every_other16,
    pick16,
    window_add,
    tail16,
    back_tail16
);

/// 0, 1, …, 15.
#[target_feature(enable = "avx512f,avx2,fma")]
#[inline]
fn lanes16() -> __m512 {
    _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
    )
}

/// [`position`] of the 16 rows `rows` (as f32) with the operations of the row loops: the value
/// index and the weight of the next value, clamped into `[0, hi]`.
#[target_feature(enable = "avx512f,avx2,fma")]
#[inline]
fn positions16(step: &PlaneStep, rows: __m512, hi: f32) -> (__m512i, __m512) {
    let q = _mm512_add_ps(
        _mm512_add_ps(
            _mm512_set1_ps(step.e0),
            _mm512_mul_ps(rows, _mm512_set1_ps(step.de)),
        ),
        _mm512_set1_ps(1.0),
    );
    let q = _mm512_min_ps(_mm512_max_ps(q, _mm512_setzero_ps()), _mm512_set1_ps(hi));
    let i = _mm512_cvttps_epi32(q);
    (i, _mm512_sub_ps(q, _mm512_cvtepi32_ps(i)))
}

/// [`back_tail_rows`] for the rows of one pass left after its whole vectors (fewer than 16). Where
/// the pass has 16 rows or more, the last 16 of them go in one window step with the data of the
/// rows already added taken as zero (adding zero leaves a sum unchanged). Else one masked vector
/// step, added by one gather and scatter where the rows' indices are distinct, else one by one.
///
/// # Safety
/// `first` and `second` hold at least `len ≥ 3` values each, the rows left are fewer than 16, and
/// the CPU must have AVX-512F, BMI2 and POPCNT.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx512f,avx2,fma,bmi2,popcnt")]
unsafe fn back_tail16(
    first: &mut [f32],
    second: &mut [f32],
    len: usize,
    step: &PlaneStep,
    start: usize,
    j: usize,
    stride: usize,
    data: &[f32],
) {
    let m = data.len().saturating_sub(j).div_ceil(stride);
    if m == 0 {
        return;
    }
    debug_assert!(m < 16);
    let one = _mm512_set1_ps(1.0);
    let hi = (len - 2) as f32;
    let lane = _mm512_mul_ps(lanes16(), _mm512_set1_ps(stride as f32));
    let spaced = _mm512_cvttps_epi32(lane);
    if j >= stride * (16 - m) {
        let j0 = j - stride * (16 - m);
        let rv = _mm512_add_ps(_mm512_set1_ps((start + j0) as f32), lane);
        let (i, f) = positions16(step, rv, hi);
        // The lanes of rows j, j + stride, …: the last m.
        let fresh = (0xffff_u32 << (16 - m)) as __mmask16;
        // SAFETY: rows j0, j0 + stride, …, j0 + 15·stride (the pass's last) lie in `data`; the
        // clamp keeps every index in [0, len − 2], inside both lines.
        unsafe {
            let d = if stride == 1 {
                _mm512_loadu_ps(data.as_ptr().add(j0))
            } else {
                every_other16(&data[j0..], spaced)
            };
            let d = _mm512_maskz_mov_ps(fresh, d);
            let (v0, v1) = (_mm512_mul_ps(_mm512_sub_ps(one, f), d), _mm512_mul_ps(f, d));
            if window_add(first, second, i, v0, v1) {
                return;
            }
        }
    }
    let (first, second) = (&mut first[..len], &mut second[..len]);
    if m == 1 {
        // SAFETY: as the caller's.
        return unsafe { back_tail_rows(first, second, len, step, start, j, stride, data) };
    }
    let rv = _mm512_add_ps(_mm512_set1_ps((start + j) as f32), lane);
    let (i, f) = positions16(step, rv, hi);
    let mask = ((1u32 << m) - 1) as __mmask16;
    // Active neighbours (lanes l and l + 1 both below m) must differ.
    let pairs = mask >> 1;
    let next = _mm512_alignr_epi32::<1>(i, i);
    if _mm512_mask_cmpneq_epi32_mask(pairs, i, next) != pairs {
        // SAFETY: as the caller's.
        return unsafe { back_tail_rows(first, second, len, step, start, j, stride, data) };
    }
    // SAFETY: rows j + stride·l for the active lanes lie in `data`; the clamp keeps every index in
    // [0, len − 2], inside both lines; the active lanes write distinct values.
    unsafe {
        let d =
            _mm512_mask_i32gather_ps::<4>(_mm512_setzero_ps(), mask, spaced, data.as_ptr().add(j));
        let (v0, v1) = (_mm512_mul_ps(_mm512_sub_ps(one, f), d), _mm512_mul_ps(f, d));
        let g = _mm512_mask_i32gather_ps::<4>(_mm512_setzero_ps(), mask, i, first.as_ptr());
        _mm512_mask_i32scatter_ps::<4>(first.as_mut_ptr(), mask, i, _mm512_add_ps(g, v0));
        let g = _mm512_mask_i32gather_ps::<4>(_mm512_setzero_ps(), mask, i, second.as_ptr());
        _mm512_mask_i32scatter_ps::<4>(second.as_mut_ptr(), mask, i, _mm512_add_ps(g, v1));
    }
}

/// The rows `r .. acc.len()` (fewer than 16) of a line of `len` values (`line` may be longer), in one
/// vector step with the operations of the full steps, stored under a mask: where the rows from
/// `start` number 16 or more, the step covers the last 16 rows and only the rows from `r` are
/// stored; else it starts at `r` and its lanes past the end compute clamped positions too but are
/// not stored.
///
/// # Safety
/// `line` holds at least `len ≥ 3` values, `acc.len() − r < 16`, and the CPU must have AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn tail16(
    line: &[f32],
    len: usize,
    step: &PlaneStep,
    start: usize,
    r: usize,
    acc: &mut [f32],
) {
    let n = acc.len().saturating_sub(r);
    if n == 0 {
        return;
    }
    debug_assert!(n < 16);
    let (r0, mask) = if acc.len() >= start + 16 {
        // The lanes of rows r ..: the last n.
        (acc.len() - 16, (0xffff_u32 << (16 - n)) as __mmask16)
    } else {
        (r, ((1u32 << n) - 1) as __mmask16)
    };
    let one = _mm512_set1_ps(1.0);
    let rv = _mm512_add_ps(_mm512_set1_ps(r0 as f32), lanes16());
    let (i, f) = positions16(step, rv, (len - 2) as f32);
    // SAFETY: the clamp keeps every lane's index in [0, len − 2], so `i` and `i + 1` read inside
    // `line`; the masked load and store touch rows r .. acc.len() only.
    unsafe {
        let (g0, g1) = pick16(line, i);
        let t = _mm512_add_ps(
            _mm512_mul_ps(_mm512_sub_ps(one, f), g0),
            _mm512_mul_ps(f, g1),
        );
        let p = acc.as_mut_ptr().add(r0);
        let old = _mm512_maskz_loadu_ps(mask, p);
        _mm512_mask_storeu_ps(p, mask, _mm512_add_ps(old, t));
    }
}
