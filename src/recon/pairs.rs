//! Loading the 8 pairs `(q[k], q[k + 1])` that linear interpolation at 8 positions needs, and picking
//! values from a 16-value window, shared by the AVX2 kernels of the projectors and of the analytic
//! backprojection.
#![allow(unsafe_code)] // SIMD kernel: every `unsafe` below carries its `// SAFETY:` note.

use std::arch::x86_64::*;

/// `start + j` in lane `j`.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(crate) fn lanes(start: f32) -> __m256 {
    _mm256_add_ps(
        _mm256_set1_ps(start),
        _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0),
    )
}

/// Lanes 0–7 of `idx` pick from the 16 floats `lo ++ hi` (bits 0–2 of each index choose the float,
/// bit 3 the half; other bits are ignored).
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(crate) fn select16(lo: __m256, hi: __m256, idx: __m256i) -> __m256 {
    let upper = _mm256_castsi256_ps(_mm256_slli_epi32::<28>(idx));
    _mm256_blendv_ps(
        _mm256_permutevar8x32_ps(lo, idx),
        _mm256_permutevar8x32_ps(hi, idx),
        upper,
    )
}

/// The pairs `(q[k_j], q[k_j + 1])` for the 8 indices of `k`, as two vectors in lane order, with
/// eight 64-bit loads (faster here than two 64-bit gathers of 4 lanes: 1.2–1.3× on the whole forward
/// projection on the development machine's AMD EPYC).
///
/// # Safety
/// `base + k_j` and `base + k_j + 1` must be readable for every j.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(crate) unsafe fn load_pairs(base: *const f32, k: __m256i) -> (__m256, __m256) {
    let mut idx = [0i32; 8];
    // SAFETY: `idx` holds 8 values; the caller guarantees every pair is readable; the 8-byte loads
    // are unaligned ones (`_mm_loadu_si64`), the pairs being only 4-byte aligned.
    let (p0, p1) = unsafe {
        _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, k);
        let pair = |l: usize| _mm_loadu_si64(base.add(idx[l] as usize) as *const u8);
        let q0 = _mm_unpacklo_epi64(pair(0), pair(1));
        let q1 = _mm_unpacklo_epi64(pair(2), pair(3));
        let q2 = _mm_unpacklo_epi64(pair(4), pair(5));
        let q3 = _mm_unpacklo_epi64(pair(6), pair(7));
        (
            _mm256_castsi256_ps(_mm256_inserti128_si256::<1>(_mm256_castsi128_si256(q0), q1)),
            _mm256_castsi256_ps(_mm256_inserti128_si256::<1>(_mm256_castsi128_si256(q2), q3)),
        )
    };
    // p0 = [a0 b0 a1 b1 | a2 b2 a3 b3], p1 = [a4 b4 a5 b5 | a6 b6 a7 b7].
    let a = _mm256_shuffle_ps::<0b10_00_10_00>(p0, p1);
    let b = _mm256_shuffle_ps::<0b11_01_11_01>(p0, p1);
    // a = [a0 a1 a4 a5 | a2 a3 a6 a7]: swap the middle quarters back.
    let order = _mm256_setr_epi32(0, 1, 4, 5, 2, 3, 6, 7);
    (
        _mm256_permutevar8x32_ps(a, order),
        _mm256_permutevar8x32_ps(b, order),
    )
}
