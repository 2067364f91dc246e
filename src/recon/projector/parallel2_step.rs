//! SART's step on one line of the image, `x ← clamp(x + (λ·c)·g)` with `c = 1/s` where the column
//! sum `s` exceeds the view's floor (else 0): over two scratch lines (AVX2), or fused with the
//! 16-pixel back projection so that `g` and `s` never leave the registers (AVX-512F).

use std::arch::x86_64::*;

use super::LineView;
use super::simd::back_rows16;
use super::sweep::Step;

/// `x ← clamp(x + (λ·c)·g)` value by value with `c = 1/s` where the column sum `s` exceeds `floor`,
/// else 0 (a division, a multiply, a multiply and an add, as the scalar form), clamped below by
/// `lower` and above by `upper` where given (`max` then `min`, which pick the bound for a NaN as
/// `f32::max` and `f32::min` do).
///
/// # Safety
/// AVX must be available; `sums` and `g` hold at least `x.len()` values.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn step_line(x: &mut [f32], sums: &[f32], g: &[f32], step: Step) {
    let Step {
        floor,
        lambda,
        lower,
        upper,
    } = step;
    let n = x.len();
    debug_assert!(sums.len() >= n && g.len() >= n);
    let vl = _mm256_set1_ps(lambda);
    let vf = _mm256_set1_ps(floor);
    let one = _mm256_set1_ps(1.0);
    let lo = _mm256_set1_ps(lower.unwrap_or(0.0));
    let hi = _mm256_set1_ps(upper.unwrap_or(0.0));
    let (xp, sp, gp) = (x.as_mut_ptr(), sums.as_ptr(), g.as_ptr());
    let mut i = 0;
    while i + 8 <= n {
        // SAFETY: i + 8 ≤ n ≤ every length.
        unsafe {
            let s = _mm256_loadu_ps(sp.add(i));
            let above = _mm256_cmp_ps::<_CMP_GT_OQ>(s, vf);
            let c = _mm256_and_ps(_mm256_div_ps(one, s), above);
            let d = _mm256_mul_ps(_mm256_mul_ps(vl, c), _mm256_loadu_ps(gp.add(i)));
            let mut v = _mm256_add_ps(_mm256_loadu_ps(xp.add(i)), d);
            if lower.is_some() {
                v = _mm256_max_ps(v, lo);
            }
            if upper.is_some() {
                v = _mm256_min_ps(v, hi);
            }
            _mm256_storeu_ps(xp.add(i), v);
        }
        i += 8;
    }
    for ((x, &s), &g) in x[i..].iter_mut().zip(&sums[i..n]).zip(&g[i..n]) {
        let c = if s > floor { 1.0 / s } else { 0.0 };
        let v = *x + lambda * c * g;
        let v = lower.map_or(v, |l| v.max(l));
        *x = upper.map_or(v, |u| v.min(u));
    }
}

/// The back projections of `rs[0]` (the data, `g`) and `rs[1]` (ones, the column sums `s`) on one
/// line, as [`super::simd::back_lines16`] computes them into zeroed lines, each vector of 16 pixels
/// stepped as [`step_line`] steps it (a division, two multiplies, an add, `max` then `min`; the
/// same values bit for bit) as soon as it is complete. `x` holds the line's `len` pixels.
///
/// # Safety
/// As [`super::simd::back_line16`] for both rows, with `n16 ≥ x.len()` a multiple of 16.
#[target_feature(enable = "avx2,fma,avx512f")]
pub(super) unsafe fn sart_line16<const TWO: bool>(
    x: &mut [f32],
    n16: usize,
    rs: [&[f32]; 2],
    lv: &LineView,
    b: f32,
    step: Step,
) {
    let len = x.len();
    debug_assert!(n16 >= len && n16.is_multiple_of(16));
    let vl = _mm512_set1_ps(step.lambda);
    let vf = _mm512_set1_ps(step.floor);
    let one = _mm512_set1_ps(1.0);
    let lo = _mm512_set1_ps(step.lower.unwrap_or(0.0));
    let hi = _mm512_set1_ps(step.upper.unwrap_or(0.0));
    let xp = x.as_mut_ptr();
    // SAFETY: the caller's for the rows; the vector at `at` holds pixels at − 16 … at − 1, of
    // which those in 0 .. len are read and written (masked), all inside `x`.
    unsafe {
        back_rows16::<TWO, 2>(n16, rs, lv, b, |at, [g, s]| {
            if at == 0 || at - 16 >= len {
                return;
            }
            let p = at - 16;
            let mask: __mmask16 = if len - p >= 16 {
                0xffff
            } else {
                (1u16 << (len - p)) - 1
            };
            let above = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(s, vf);
            let c = _mm512_maskz_div_ps(above, one, s);
            let d = _mm512_mul_ps(_mm512_mul_ps(vl, c), g);
            let mut v = _mm512_add_ps(_mm512_maskz_loadu_ps(mask, xp.add(p)), d);
            if step.lower.is_some() {
                v = _mm512_max_ps(v, lo);
            }
            if step.upper.is_some() {
                v = _mm512_min_ps(v, hi);
            }
            _mm512_mask_storeu_ps(xp.add(p), mask, v);
        })
    }
}
