//! The AVX2/FMA and AVX-512F line kernels of [`super`] (the parallel-beam views of the 2D Joseph pair).

use std::arch::x86_64::*;
use std::ops::Range;

use super::{LineView, PAD, WideLines};
use crate::recon::pairs::{lanes, select16};

/// The forward projection of sorted rays `rays` of view `lv` (8 per step): `out` holds their
/// detector elements, the lowest first.
///
/// # Safety
/// AVX2 and FMA must be available; `lines` and `lv` must agree, `rays.start` must be a multiple of
/// 8, `rays.end ≤ lv.count`, and `out.len() == rays.len()`.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn forward_view(
    lines: &WideLines,
    lv: &LineView,
    rays: Range<usize>,
    out: &mut [f32],
) {
    let (m, low) = (rays.end, lv.lowest_element(&rays));
    let vs = _mm256_set1_ps(lv.s);
    let vw = _mm256_set1_ps(lv.weight);
    let data = lines.data.as_ptr();
    // The window [base, base + 17) stays inside the data for base ∈ [−PAD, len + PAD − 17].
    let (lowest, highest) = (-(PAD as isize), (lines.len + PAD - 17) as isize);
    let mut sums = [0.0f32; 8];
    for first in rays.step_by(8) {
        let ks = _mm256_mul_ps(lanes(first as f32), vs);
        let (lo, hi) = lv.group_lines(first, 8);
        let mut acc0 = _mm256_setzero_ps();
        let mut acc1 = _mm256_setzero_ps();
        for (i, &b) in (lo..hi).zip(&lv.b[lo..hi]) {
            let t = _mm256_add_ps(_mm256_set1_ps(b), ks);
            let floor = _mm256_floor_ps(t);
            let j = _mm256_cvtps_epi32(floor);
            let w1 = _mm256_mul_ps(_mm256_sub_ps(t, floor), vw);
            let w0 = _mm256_sub_ps(vw, w1);
            // On the lines of `group_lines` every lane lies within 7·S_MAX + 2 pixels of the
            // image, so the clamp never binds there; it only keeps the reads inside the data.
            let base = (_mm256_cvtsi256_si32(j) as isize).clamp(lowest, highest);
            let rel = _mm256_sub_epi32(j, _mm256_set1_epi32(base as i32));
            // SAFETY: offset(i) + base ∈ [offset(i) − PAD, offset(i) + len + PAD − 17], and
            // the 17 values from there lie in the data (PAD zeros before each line and after the
            // last).
            let (a, b) = unsafe {
                let p = data.add(lines.offset(i)).offset(base);
                let (l0, h0) = (_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8)));
                let (l1, h1) = (_mm256_loadu_ps(p.add(1)), _mm256_loadu_ps(p.add(9)));
                (select16(l0, h0, rel), select16(l1, h1, rel))
            };
            acc0 = _mm256_fmadd_ps(w0, a, acc0);
            acc1 = _mm256_fmadd_ps(w1, b, acc1);
        }
        // SAFETY: `sums` holds 8 values.
        unsafe { _mm256_storeu_ps(sums.as_mut_ptr(), _mm256_add_ps(acc0, acc1)) };
        for (l, &v) in sums.iter().enumerate().take(m - first) {
            out[lv.element(first + l) - low] = v;
        }
    }
}

/// [`forward_view`] with AVX-512F, 16 neighbouring rays per vector: their pixel pairs lie in 32
/// neighbouring values of the line (16 rays span at most 15·S_MAX + 2 < 31 pixels), picked by one
/// two-register permute each. The same operations per ray as the 8-ray kernel, so the same values.
///
/// # Safety
/// AVX2, FMA and AVX-512F must be available; as [`forward_view`], with `rays.start` a multiple of 16.
#[target_feature(enable = "avx2,fma,avx512f")]
pub(super) unsafe fn forward_view16(
    lines: &WideLines,
    lv: &LineView,
    rays: Range<usize>,
    out: &mut [f32],
) {
    let (m, low) = (rays.end, lv.lowest_element(&rays));
    let vs = _mm512_set1_ps(lv.s);
    let vw = _mm512_set1_ps(lv.weight);
    let one = _mm512_set1_epi32(1);
    let data = lines.data.as_ptr();
    // The window [base, base + 32) stays inside the data for base ∈ [−PAD, len + PAD − 32].
    let (lowest, highest) = (-(PAD as isize), (lines.len + PAD - 32) as isize);
    let steps = _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
    );
    let mut sums = [0.0f32; 16];
    for first in rays.step_by(16) {
        let ks = _mm512_mul_ps(_mm512_add_ps(_mm512_set1_ps(first as f32), steps), vs);
        let (lo, hi) = lv.group_lines(first, 16);
        let mut acc0 = _mm512_setzero_ps();
        let mut acc1 = _mm512_setzero_ps();
        for (i, &b) in (lo..hi).zip(&lv.b[lo..hi]) {
            let t = _mm512_add_ps(_mm512_set1_ps(b), ks);
            let floor = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(t);
            let j = _mm512_cvtps_epi32(floor);
            let w1 = _mm512_mul_ps(_mm512_sub_ps(t, floor), vw);
            let w0 = _mm512_sub_ps(vw, w1);
            // On the lines of `group_lines` every lane lies within 15·S_MAX + 2 pixels of the
            // image, so the clamp never binds there; it only keeps the reads inside the data.
            let base =
                (_mm_cvtsi128_si32(_mm512_castsi512_si128(j)) as isize).clamp(lowest, highest);
            let rel = _mm512_sub_epi32(j, _mm512_set1_epi32(base as i32));
            // SAFETY: offset(i) + base ∈ [offset(i) − PAD, offset(i) + len + PAD − 32], and the 32
            // values from there lie in the data (PAD zeros before each line and after the last).
            let (l, h) = unsafe {
                let p = data.add(lines.offset(i)).offset(base);
                (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)))
            };
            let a = _mm512_permutex2var_ps(l, rel, h);
            let c = _mm512_permutex2var_ps(l, _mm512_add_epi32(rel, one), h);
            acc0 = _mm512_fmadd_ps(w0, a, acc0);
            acc1 = _mm512_fmadd_ps(w1, c, acc1);
        }
        // SAFETY: `sums` holds 16 values.
        unsafe { _mm512_storeu_ps(sums.as_mut_ptr(), _mm512_add_ps(acc0, acc1)) };
        for (l, &v) in sums.iter().enumerate().take(m - first) {
            out[lv.element(first + l) - low] = v;
        }
    }
}

/// `K(q)`, the first sorted ray with `t ≥ q`, for the 8 pixels of `q`, clamped to `[−1, count]`,
/// and its position `t` (meaningful where not clamped).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn first_rays(q: __m256, b: __m256, s: __m256, inv_s: __m256, count: i32) -> (__m256i, __m256) {
    let one = _mm256_set1_ps(1.0);
    // Within one ray of K(q): positions below 2¹⁵ pixels and steps ≥ S_MIN keep the division's
    // error far below one ray.
    let est = _mm256_ceil_ps(_mm256_mul_ps(_mm256_sub_ps(q, b), inv_s));
    let t_below = _mm256_add_ps(b, _mm256_mul_ps(_mm256_sub_ps(est, one), s));
    let t_at = _mm256_add_ps(b, _mm256_mul_ps(est, s));
    let t_above = _mm256_add_ps(b, _mm256_mul_ps(_mm256_add_ps(est, one), s));
    // Positions grow with the ray index, so at most one of these holds.
    let down = _mm256_cmp_ps::<_CMP_GE_OQ>(t_below, q);
    let up = _mm256_cmp_ps::<_CMP_LT_OQ>(t_at, q);
    let k = _mm256_cvtps_epi32(est);
    // A true mask is −1: add `down`, subtract `up`.
    let k = _mm256_sub_epi32(
        _mm256_add_epi32(k, _mm256_castps_si256(down)),
        _mm256_castps_si256(up),
    );
    let t = _mm256_blendv_ps(_mm256_blendv_ps(t_at, t_below, down), t_above, up);
    let k = _mm256_max_epi32(
        _mm256_min_epi32(k, _mm256_set1_epi32(count)),
        _mm256_set1_epi32(-1),
    );
    (k, t)
}

/// Add the back projection of one view's data on line position `b` to the pixels of `acc`:
/// `acc[8 + q] += Σ` over the rays of `q`, for `q ∈ [0, n8)` (`acc[0..8]` takes the sums of pixels
/// −8 … −1, which do not exist). `r` is the data in sorted ray order at `r[k + 1]`, with zeros at
/// `r[0]` and after the last ray.
///
/// # Safety
/// AVX2 and FMA must be available; `acc.len() ≥ 8 + n8`, `n8` a multiple of 8,
/// `r.len() ≥ lv.count + 24`, and `lv.s ∈ [S_MIN, S_MAX]`. Results: exact only with `TWO` (a
/// second ray per pixel) where `lv.s <` [`super::ONE_RAY`].
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn back_line<const TWO: bool>(
    acc: &mut [f32],
    n8: usize,
    r: &[f32],
    lv: &LineView,
    b: f32,
) {
    let count = lv.count as i32;
    let (vb, vs, vw) = (
        _mm256_set1_ps(b),
        _mm256_set1_ps(lv.s),
        _mm256_set1_ps(lv.weight),
    );
    let inv_s = _mm256_set1_ps(1.0 / lv.s);
    let (one, onef) = (_mm256_set1_epi32(1), _mm256_set1_ps(1.0));
    let eight = _mm256_set1_ps(8.0);
    let prev_lane = _mm256_setr_epi32(7, 0, 1, 2, 3, 4, 5, 6);
    let rp = r.as_ptr();
    let ap = acc.as_mut_ptr();
    // Pixels −8 … −1 first: their bins' w1 reach pixel 0.
    let mut q = lanes(-8.0);
    let mut c_prev = _mm256_setzero_ps();
    for at in (0..=n8).step_by(8) {
        let (k, t) = first_rays(q, vb, vs, inv_s, count);
        // Bin q (⌊t⌋ = q) holds ray K(q) when t_K < q + 1 (and a second ray only where TWO).
        let q1 = _mm256_add_ps(q, onef);
        let any = _mm256_cmp_ps::<_CMP_LT_OQ>(t, q1);
        // K grows with q and lies in [−1, count]: the vector's rays (and the second rays) lie in
        // r[base + 1 ..][0 .. 16], since 8 pixels hold at most ⌊7/S_MIN⌋ + 2 of them.
        let base = _mm256_cvtsi256_si32(k);
        debug_assert!((-1..=count).contains(&base));
        let rel = _mm256_sub_epi32(k, _mm256_set1_epi32(base));
        // SAFETY: `first_rays` clamps K to [−1, count], so base + 1 ∈ [0, count + 1], and r
        // holds count + 24 values.
        let (lo, hi) = unsafe {
            let p = rp.add((base + 1) as usize);
            (_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8)))
        };
        // Clamped K (−1 or count) picks one of the zeros around the data.
        let rv = _mm256_and_ps(select16(lo, hi, rel), any);
        let w1 = _mm256_mul_ps(_mm256_sub_ps(t, q), vw);
        let w0 = _mm256_sub_ps(vw, w1);
        let mut a = _mm256_mul_ps(rv, w0);
        let mut c = _mm256_mul_ps(rv, w1);
        if TWO {
            let k2 = _mm256_add_epi32(k, one);
            let t2 = _mm256_add_ps(vb, _mm256_mul_ps(_mm256_cvtepi32_ps(k2), vs));
            let in_bin = _mm256_cmp_ps::<_CMP_LT_OQ>(t2, q1);
            let r2 = _mm256_and_ps(select16(lo, hi, _mm256_add_epi32(rel, one)), in_bin);
            let w1 = _mm256_mul_ps(_mm256_sub_ps(t2, q), vw);
            let w0 = _mm256_sub_ps(vw, w1);
            a = _mm256_fmadd_ps(r2, w0, a);
            c = _mm256_fmadd_ps(r2, w1, c);
        }
        // Pixel q takes w0 from its own bin and w1 from bin q − 1.
        let c_before = _mm256_blend_ps::<0b0000_0001>(
            _mm256_permutevar8x32_ps(c, prev_lane),
            _mm256_permutevar8x32_ps(c_prev, _mm256_set1_epi32(7)),
        );
        // SAFETY: at ≤ n8 and acc holds 8 + n8 values.
        unsafe {
            let p = ap.add(at);
            _mm256_storeu_ps(
                p,
                _mm256_add_ps(_mm256_loadu_ps(p), _mm256_add_ps(a, c_before)),
            );
        }
        c_prev = c;
        q = _mm256_add_ps(q, eight);
    }
}

/// [`first_rays`] for 16 pixels (AVX-512F).
#[target_feature(enable = "avx2,fma,avx512f")]
#[inline]
fn first_rays16(q: __m512, b: __m512, s: __m512, inv_s: __m512, count: i32) -> (__m512i, __m512) {
    let one = _mm512_set1_ps(1.0);
    let est = _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(_mm512_mul_ps(
        _mm512_sub_ps(q, b),
        inv_s,
    ));
    let t_below = _mm512_add_ps(b, _mm512_mul_ps(_mm512_sub_ps(est, one), s));
    let t_at = _mm512_add_ps(b, _mm512_mul_ps(est, s));
    let t_above = _mm512_add_ps(b, _mm512_mul_ps(_mm512_add_ps(est, one), s));
    let down = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(t_below, q);
    let up = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t_at, q);
    let k = _mm512_cvtps_epi32(est);
    let k1 = _mm512_set1_epi32(1);
    let k = _mm512_mask_sub_epi32(k, down, k, k1);
    let k = _mm512_mask_add_epi32(k, up, k, k1);
    let t = _mm512_mask_blend_ps(up, _mm512_mask_blend_ps(down, t_at, t_below), t_above);
    let k = _mm512_max_epi32(
        _mm512_min_epi32(k, _mm512_set1_epi32(count)),
        _mm512_set1_epi32(-1),
    );
    (k, t)
}

/// [`back_line`] with AVX-512F, 16 pixels per step: `acc[16 + q] += …` for `q ∈ [0, n16)`
/// (`acc[0..16]` takes pixels −16 … −1), the rays picked from a window of 32 data values.
///
/// # Safety
/// AVX2, FMA and AVX-512F must be available; `acc.len() ≥ 16 + n16`, `n16` a multiple of 16,
/// `r.len() ≥ lv.count + 40`, and `lv.s ∈ [S_MIN, S_MAX]`; `TWO` as in [`back_line`].
#[target_feature(enable = "avx2,fma,avx512f")]
pub(super) unsafe fn back_line16<const TWO: bool>(
    acc: &mut [f32],
    n16: usize,
    r: &[f32],
    lv: &LineView,
    b: f32,
) {
    // SAFETY: the caller's.
    unsafe { back_lines16::<TWO, 1>([acc], n16, [r], lv, b) }
}

/// [`back_line16`] for `N` data rows on the same line at once (`accs[n]` from `rs[n]`): the rays'
/// positions and weights are found once for all, and each row's sums are those of
/// [`back_line16`] alone, bit for bit.
///
/// # Safety
/// As [`back_line16`], for every pair `(accs[n], rs[n])`.
#[target_feature(enable = "avx2,fma,avx512f")]
pub(super) unsafe fn back_lines16<const TWO: bool, const N: usize>(
    accs: [&mut [f32]; N],
    n16: usize,
    rs: [&[f32]; N],
    lv: &LineView,
    b: f32,
) {
    let aps = accs.map(|a| a.as_mut_ptr());
    // SAFETY: the caller's; every accumulator holds 16 + n16 values and `at` ≤ n16.
    unsafe {
        back_rows16::<TWO, N>(n16, rs, lv, b, |at, sums| {
            for (&ap, v) in aps.iter().zip(sums) {
                let p = ap.add(at);
                _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), v));
            }
        })
    }
}

/// The loop of [`back_lines16`]: for `at` = 0, 16, … n16 in turn, `put(at, v)` with `v[n]` what
/// row `n` adds to pixels `at − 16 … at − 1`, each vector computed once.
///
/// # Safety
/// As [`back_line16`] for every row of `rs`; `put` is called with `at ≤ n16`.
#[target_feature(enable = "avx2,fma,avx512f")]
#[inline]
pub(super) unsafe fn back_rows16<const TWO: bool, const N: usize>(
    n16: usize,
    rs: [&[f32]; N],
    lv: &LineView,
    b: f32,
    mut put: impl FnMut(usize, [__m512; N]),
) {
    let count = lv.count as i32;
    let (vb, vs, vw) = (
        _mm512_set1_ps(b),
        _mm512_set1_ps(lv.s),
        _mm512_set1_ps(lv.weight),
    );
    let inv_s = _mm512_set1_ps(1.0 / lv.s);
    let (one, onef) = (_mm512_set1_epi32(1), _mm512_set1_ps(1.0));
    let sixteen = _mm512_set1_ps(16.0);
    let rps = rs.map(|r| r.as_ptr());
    let lanes16 = _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
    );
    let mut q = _mm512_add_ps(_mm512_set1_ps(-16.0), lanes16);
    let mut c_prev = [_mm512_setzero_si512(); N];
    for at in (0..=n16).step_by(16) {
        let (k, t) = first_rays16(q, vb, vs, inv_s, count);
        let q1 = _mm512_add_ps(q, onef);
        let any = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t, q1);
        // 16 pixels hold at most ⌊15/S_MIN⌋ + 2 = 27 rays: all in r[base + 1 ..][0 .. 32].
        let base = _mm_cvtsi128_si32(_mm512_castsi512_si128(k));
        debug_assert!((-1..=count).contains(&base));
        let rel = _mm512_sub_epi32(k, _mm512_set1_epi32(base));
        let w1 = _mm512_mul_ps(_mm512_sub_ps(t, q), vw);
        let w0 = _mm512_sub_ps(vw, w1);
        // The second ray of each pixel, where it has one.
        let (in_bin, rel2, w1b, w0b) = if TWO {
            let k2 = _mm512_add_epi32(k, one);
            let t2 = _mm512_add_ps(vb, _mm512_mul_ps(_mm512_cvtepi32_ps(k2), vs));
            let in_bin = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t2, q1);
            let w1 = _mm512_mul_ps(_mm512_sub_ps(t2, q), vw);
            (
                in_bin,
                _mm512_add_epi32(rel, one),
                w1,
                _mm512_sub_ps(vw, w1),
            )
        } else {
            (0, rel, w1, w0)
        };
        let mut out = [_mm512_setzero_ps(); N];
        for n in 0..N {
            // SAFETY: base + 1 ∈ [0, count + 1] and every row holds count + 40 values.
            let (lo, hi) = unsafe {
                let p = rps[n].add((base + 1) as usize);
                (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)))
            };
            let rv = _mm512_maskz_permutex2var_ps(any, lo, rel, hi);
            let mut a = _mm512_mul_ps(rv, w0);
            let mut c = _mm512_mul_ps(rv, w1);
            if TWO {
                let r2 = _mm512_maskz_permutex2var_ps(in_bin, lo, rel2, hi);
                a = _mm512_fmadd_ps(r2, w0b, a);
                c = _mm512_fmadd_ps(r2, w1b, c);
            }
            let c = _mm512_castps_si512(c);
            let c_before = _mm512_castsi512_ps(_mm512_alignr_epi32::<15>(c, c_prev[n]));
            out[n] = _mm512_add_ps(a, c_before);
            c_prev[n] = c;
        }
        put(at, out);
        q = _mm512_add_ps(q, sixteen);
    }
}

/// `dst[j·dst_stride + i] = src[i·src_stride + j]` for `i, j < 8`.
///
/// # Safety
/// AVX must be available; the 8 rows of 8 values at `src` and at `dst` lie inside their buffers.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn transpose8(
    src: *const f32,
    src_stride: usize,
    dst: *mut f32,
    dst_stride: usize,
) {
    // SAFETY: the caller's.
    unsafe {
        let r: [__m256; 8] = std::array::from_fn(|i| _mm256_loadu_ps(src.add(i * src_stride)));
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let s0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let s1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let s2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let s3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let s4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let s5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let s6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let s7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        let out = [
            _mm256_permute2f128_ps::<0x20>(s0, s4),
            _mm256_permute2f128_ps::<0x20>(s1, s5),
            _mm256_permute2f128_ps::<0x20>(s2, s6),
            _mm256_permute2f128_ps::<0x20>(s3, s7),
            _mm256_permute2f128_ps::<0x31>(s0, s4),
            _mm256_permute2f128_ps::<0x31>(s1, s5),
            _mm256_permute2f128_ps::<0x31>(s2, s6),
            _mm256_permute2f128_ps::<0x31>(s3, s7),
        ];
        for (j, v) in out.into_iter().enumerate() {
            _mm256_storeu_ps(dst.add(j * dst_stride), v);
        }
    }
}
