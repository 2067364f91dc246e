//! AVX2 + FMA backprojection kernels, 8 pixels at a time, selected at run time by [`super::backproject`];
//! the scalar forms there are the reference and handle the tails.
//!
//! Each pixel needs a pair of neighbouring detector samples. In 2D, where the 8 pixels of a vector read
//! nearby samples, the pairs are picked by permutes from a window of 16 samples loaded once (32 samples
//! with AVX-512F's two-register permute), chosen per row from the row's largest step; rows too steep
//! for a window, and vectors whose pairs fall outside it, use 64-bit gathers. In 3D the pairs come from
//! one 64-bit load each (neighbouring voxels often straddle two detector rows there). Rows wholly in
//! front of the source skip the depth mask. These were the faster choices on the development machine's
//! AMD EPYC. Tested against the safe reference in `backproject`'s tests, whose rows reach every path
//! (they run these kernels on any AVX2 machine, and the 32-sample windows on AVX-512F ones).
#![allow(unsafe_code)] // SIMD kernel: every `unsafe` below carries its `// SAFETY:` note.

use std::arch::x86_64::*;

use crate::recon::pairs::{lanes, load_pairs, select16};

use super::backproject::{
    MIN_DEPTH, Panel, RowLine, cone_row_scalar, fan_row_scalar, parallel_row_scalar,
};

/// True when the CPU has AVX2 and FMA and indices below `len` fit an i32.
pub fn available(len: usize) -> bool {
    len < i32::MAX as usize && crate::recon::cpu::avx2_fma()
}

/// Clamp to [0, hi] (NaN → 0) and split into index and fraction.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn split(p: __m256, hi: __m256) -> (__m256i, __m256) {
    let p = _mm256_min_ps(_mm256_max_ps(p, _mm256_setzero_ps()), hi);
    let i = _mm256_cvttps_epi32(p);
    (i, _mm256_sub_ps(p, _mm256_cvtepi32_ps(i)))
}

/// [`split`] for positions known to lie inside the row.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn split_inside(p: __m256) -> (__m256i, __m256) {
    let i = _mm256_cvttps_epi32(p);
    (i, _mm256_sub_ps(p, _mm256_cvtepi32_ps(i)))
}

/// The pairs `(q[k_j], q[k_j + 1])` for the 8 indices of `k`, as two vectors in index order: one
/// 64-bit gather per 4 pairs (half the gathered elements of two 32-bit gathers).
///
/// # Safety
/// `base + k_j` and `base + k_j + 1` must be readable for every j.
#[target_feature(enable = "avx2,fma")]
unsafe fn gather_pairs(base: *const f32, k: __m256i) -> (__m256, __m256) {
    let lo = _mm256_castsi256_si128(k);
    let hi = _mm256_extracti128_si256::<1>(k);
    // SAFETY: the caller guarantees both floats of every pair are readable (8-byte unaligned loads).
    let (p0, p1) = unsafe {
        (
            _mm256_castpd_ps(_mm256_i32gather_pd::<4>(base as *const f64, lo)),
            _mm256_castpd_ps(_mm256_i32gather_pd::<4>(base as *const f64, hi)),
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

/// Window widths of [`window_pairs`]: 0 (always gather), 16 samples (AVX2), or 32 and 64 samples
/// (AVX-512F, whose two-register permute makes 32 cheaper than 16 there).
pub const GATHER: usize = 0;

/// True when the CPU also has AVX-512F, for the 32-sample windows.
pub fn wide_available() -> bool {
    crate::recon::cpu::avx512f()
}

/// The window width that holds the pairs of 8 neighbouring pixels whose positions are at most `step`
/// samples apart — 16 without `wide` (AVX-512F), 32 or 64 with it — or [`GATHER`].
pub fn window_for(step: f32, wide: bool) -> usize {
    // 8 pixels span 7·step samples, plus one for the pair's second sample and one for rounding.
    let span = 7.0 * step.abs() + 2.0;
    if !wide && span <= 16.0 {
        16
    } else if wide && span <= 32.0 {
        32
    } else if wide && span <= 64.0 {
        64
    } else {
        GATHER
    }
}

/// [`window_pairs`] over 32 samples: one two-register permute (AVX-512F) per vector of samples.
///
/// # Safety
/// AVX-512F must be available; `start ≥ 0`, `start + 32 < len` for the row at `base` of length `len`;
/// `rel = k − start` with every lane in `[0, 30]`.
#[target_feature(enable = "avx2,fma,avx512f")]
#[inline]
unsafe fn window32_pairs(base: *const f32, start: usize, rel: __m256i) -> (__m256, __m256) {
    let idx = _mm512_castsi256_si512(rel);
    // SAFETY: start + 32 < len, so the 16-float loads at start, start + 1, start + 16 and start + 17
    // (the last ending at start + 32) are inside the row.
    unsafe {
        let p = base.add(start);
        let (lo, hi) = (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)));
        let (lo1, hi1) = (_mm512_loadu_ps(p.add(1)), _mm512_loadu_ps(p.add(17)));
        // Lanes 8–15 of the index are undefined and their picks unused.
        (
            _mm512_castps512_ps256(_mm512_permutex2var_ps(lo, idx, hi)),
            _mm512_castps512_ps256(_mm512_permutex2var_ps(lo1, idx, hi1)),
        )
    }
}

/// [`window_pairs`] over 64 samples: two two-register permutes (AVX-512F) and a blend per vector.
///
/// # Safety
/// AVX-512F must be available; `start ≥ 0`, `start + 64 < len` for the row at `base` of length `len`;
/// `rel = k − start` with every lane in `[0, 62]`.
#[target_feature(enable = "avx2,fma,avx512f")]
#[inline]
unsafe fn window64_pairs(base: *const f32, start: usize, rel: __m256i) -> (__m256, __m256) {
    let idx = _mm512_castsi256_si512(rel);
    // Bit 5 of the index chooses the upper 32 samples (lanes 8–15 are undefined and unused).
    let upper = _mm512_test_epi32_mask(idx, _mm512_set1_epi32(32));
    // SAFETY: start + 64 < len, so the 16-float loads at start + 16·r and start + 16·r + 1 for
    // r = 0..4 (the last ending at start + 64) are inside the row.
    unsafe {
        let p = base.add(start);
        let pick = |p: *const f32| {
            let low = _mm512_permutex2var_ps(_mm512_loadu_ps(p), idx, _mm512_loadu_ps(p.add(16)));
            let high =
                _mm512_permutex2var_ps(_mm512_loadu_ps(p.add(32)), idx, _mm512_loadu_ps(p.add(48)));
            _mm512_castps512_ps256(_mm512_mask_blend_ps(upper, low, high))
        };
        (pick(p), pick(p.add(1)))
    }
}

/// The pairs `(q[k_j], q[k_j + 1])` for the 8 indices of `k`, like [`gather_pairs`]. Where all 8 pairs lie
/// in the `W` samples from the smaller of the first and last index (neighbouring pixels read nearby
/// samples, the usual case), they are picked by permutes from plain loads, several times cheaper than
/// gathers on the development machine; otherwise, or with `W = GATHER`, by gathers.
///
/// # Safety
/// `len = q.len()` of the row at `base`, `2 ≤ len < i32::MAX`; with `W = GATHER` every `k_j` must lie in
/// `[0, len − 2]` (with a window, indices outside are clamped).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn window_pairs<const W: usize>(
    base: *const f32,
    len: usize,
    k: __m256i,
) -> (__m256, __m256) {
    if W == 16 || W == 32 || W == 64 {
        let first = _mm256_cvtsi256_si32(k);
        let last = _mm256_extract_epi32::<7>(k);
        // The samples [start, start + W] must be inside the row.
        let start = first.min(last);
        if start >= 0 && start as usize + W < len {
            let rel = _mm256_sub_epi32(k, _mm256_set1_epi32(start));
            // Every pair (rel, rel + 1) must fall in 0..W: rel in [0, W − 2].
            let outside = _mm256_or_si256(
                _mm256_cmpgt_epi32(rel, _mm256_set1_epi32(W as i32 - 2)),
                _mm256_cmpgt_epi32(_mm256_setzero_si256(), rel),
            );
            if _mm256_testz_si256(outside, outside) != 0 {
                // SAFETY: W = 32 and 64 are only instantiated in kernels compiled for AVX-512F, called
                // where it is present; start + W < len and rel in [0, W − 2] were checked above.
                if W == 32 {
                    return unsafe { window32_pairs(base, start as usize, rel) };
                }
                if W == 64 {
                    return unsafe { window64_pairs(base, start as usize, rel) };
                }
                // SAFETY: start + 16 < len, so the loads at start, start + 1, start + 8 and
                // start + 9 (8 floats each, the last ending at start + 16) are inside the row.
                let (a, b) = unsafe {
                    let p = base.add(start as usize);
                    let (lo, hi) = (_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8)));
                    let (lo1, hi1) = (_mm256_loadu_ps(p.add(1)), _mm256_loadu_ps(p.add(9)));
                    // The second sample of each pair is the same pick from the window one further on.
                    (select16(lo, hi, rel), select16(lo1, hi1, rel))
                };
                return (a, b);
            }
        }
    }
    // Callers with windows may pass positions they did not clamp (known to be inside the row up to
    // rounding): clamp here, on the rare vectors that miss the window.
    let k = if W == GATHER {
        k
    } else {
        let top = _mm256_set1_epi32(len as i32 - 2);
        _mm256_min_epi32(_mm256_max_epi32(k, _mm256_setzero_si256()), top)
    };
    // SAFETY: every k_j is in [0, len − 2] (clamped here or by the caller), so k_j and k_j + 1 are
    // readable.
    unsafe { gather_pairs(base, k) }
}

/// # Safety
/// AVX2 and FMA must be available, and AVX-512F too where `wide`; `2 ≤ q.len() < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn parallel_row(acc: &mut [f32], q: &[f32], pos0: f32, dpos: f32, wide: bool) {
    // Positions are affine along the row: when both ends lie a sample inside it, every one does and
    // they need no clamping.
    let last = acc.len().saturating_sub(1) as f64;
    let (p0, p1) = (pos0 as f64, pos0 as f64 + last * dpos as f64);
    let inside = p0.min(p1) >= 1.0 && p0.max(p1) <= q.len() as f64 - 3.0;
    // SAFETY: the caller's contract, passed on; unclamped positions only with a window.
    unsafe {
        match (window_for(dpos, wide), inside) {
            (16, true) => parallel_row_in::<16, false>(acc, q, pos0, dpos),
            (16, false) => parallel_row_in::<16, true>(acc, q, pos0, dpos),
            (32, true) => parallel_row_in_wide::<32, false>(acc, q, pos0, dpos),
            (32, false) => parallel_row_in_wide::<32, true>(acc, q, pos0, dpos),
            (64, true) => parallel_row_in_wide::<64, false>(acc, q, pos0, dpos),
            (64, false) => parallel_row_in_wide::<64, true>(acc, q, pos0, dpos),
            _ => parallel_row_in::<GATHER, true>(acc, q, pos0, dpos),
        }
    }
}

/// Defines a kernel twice: for AVX2 + FMA, and also with AVX-512F for the 32-sample windows
/// ([`window32_pairs`] is only inlined into, and only called from, the second).
macro_rules! with_wide_variant {
    ($(#[$doc:meta])* unsafe fn $name:ident / $wide:ident $($rest:tt)*) => {
        $(#[$doc])*
        #[target_feature(enable = "avx2,fma")]
        unsafe fn $name $($rest)*

        $(#[$doc])*
        #[target_feature(enable = "avx2,fma,avx512f")]
        unsafe fn $wide $($rest)*
    };
}

with_wide_variant! {
    /// [`parallel_row`] reading samples through [`window_pairs::<W>`] (W = 32 and 64 only in the wide form);
    /// without `CLAMP` the positions are not clamped into the row (W must then be a window).
    ///
    /// # Safety
    /// As [`parallel_row`]; the wide form needs AVX-512F.
    unsafe fn parallel_row_in / parallel_row_in_wide<const W: usize, const CLAMP: bool>(
        acc: &mut [f32],
        q: &[f32],
        pos0: f32,
        dpos: f32,
    ) {
        let n = acc.len();
        let hi = _mm256_set1_ps((q.len() - 2) as f32);
        let (vp0, vd) = (_mm256_set1_ps(pos0), _mm256_set1_ps(dpos));
        let eight = _mm256_set1_ps(8.0);
        let base = q.as_ptr();
        let mut x = lanes(0.0);
        let mut i = 0;
        while i + 8 <= n {
            let pos = _mm256_fmadd_ps(x, vd, vp0);
            let (k, f) = if CLAMP { split(pos, hi) } else { split_inside(pos) };
            // SAFETY: `split` clamps every index to [0, len − 2] with CLAMP; without it W is a window,
            // which bounds its own reads.
            let (a, b) = unsafe { window_pairs::<W>(base, q.len(), k) };
            let v = _mm256_fmadd_ps(f, _mm256_sub_ps(b, a), a);
            // SAFETY: i + 8 ≤ acc.len().
            unsafe {
                let out = acc.as_mut_ptr().add(i);
                _mm256_storeu_ps(out, _mm256_add_ps(_mm256_loadu_ps(out), v));
            }
            x = _mm256_add_ps(x, eight);
            i += 8;
        }
        parallel_row_scalar(&mut acc[i..], q, pos0 + i as f32 * dpos, dpos);
    }
}

/// `acc[i..i + 8] += inv² · v`, the divergent-beam distance weight times the interpolated values.
///
/// # Safety
/// `i + 8 ≤ acc.len()`.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn add_weighted(acc: &mut [f32], i: usize, inv: __m256, v: __m256) {
    let w = _mm256_mul_ps(inv, inv);
    // SAFETY: the caller guarantees the 8 floats from i are inside acc.
    unsafe {
        let out = acc.as_mut_ptr().add(i);
        _mm256_storeu_ps(out, _mm256_fmadd_ps(w, v, _mm256_loadu_ps(out)));
    }
}

/// 1/x by the reciprocal estimate (12 bits) refined by one Newton step: ~23 bits, cheaper than a
/// division (relative error below 1e-6).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn reciprocal(x: __m256) -> __m256 {
    let r = _mm256_rcp_ps(x);
    _mm256_mul_ps(r, _mm256_fnmadd_ps(x, r, _mm256_set1_ps(2.0)))
}

/// 1/lc; with `MASK`, 0 where lc ≤ MIN_DEPTH (without it every lc must be above MIN_DEPTH).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn inverse_depth<const MASK: bool>(lc: __m256) -> __m256 {
    if !MASK {
        return reciprocal(lc);
    }
    let min = _mm256_set1_ps(MIN_DEPTH);
    let valid = _mm256_cmp_ps::<_CMP_GT_OQ>(lc, min);
    _mm256_and_ps(reciprocal(_mm256_max_ps(lc, min)), valid)
}

/// # Safety
/// AVX2 and FMA must be available, and AVX-512F too where `wide`; `2 ≤ q.len() < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn fan_row(acc: &mut [f32], q: &[f32], line: &RowLine, a: f32, b: f32, wide: bool) {
    // The position a·lat/lc + b moves by a·c/lc² per pixel (c is constant along the row), fastest where
    // lc is smallest, at one end. A row that reaches behind the source is gathered.
    let last = acc.len().saturating_sub(1) as f32;
    let depth = line.lc0.min(line.lc0 + last * line.dlc);
    // SAFETY (all arms): the caller's contract, passed on; without the depth mask only where every
    // pixel of the row is in front of the source.
    if depth > MIN_DEPTH {
        let c = line.dlat * line.lc0 - line.lat0 * line.dlc;
        // The position is monotonic along such a row: when both ends lie a sample inside the row,
        // every pixel does and the positions need no clamping.
        let at = |x: f32| {
            let x = x as f64;
            a as f64 * (line.lat0 as f64 + x * line.dlat as f64)
                / (line.lc0 as f64 + x * line.dlc as f64)
                + b as f64
        };
        let (p0, p1) = (at(0.0), at(last));
        let inside = p0.min(p1) >= 1.0 && p0.max(p1) <= q.len() as f64 - 3.0;
        match (window_for(a * c / (depth * depth), wide), inside) {
            (16, true) => unsafe { fan_row_in::<16, false, false>(acc, q, line, a, b) },
            (16, false) => unsafe { fan_row_in::<16, false, true>(acc, q, line, a, b) },
            (32, true) => unsafe { fan_row_in_wide::<32, false, false>(acc, q, line, a, b) },
            (32, false) => unsafe { fan_row_in_wide::<32, false, true>(acc, q, line, a, b) },
            (64, true) => unsafe { fan_row_in_wide::<64, false, false>(acc, q, line, a, b) },
            (64, false) => unsafe { fan_row_in_wide::<64, false, true>(acc, q, line, a, b) },
            _ => unsafe { fan_row_in::<GATHER, false, true>(acc, q, line, a, b) },
        }
    } else {
        unsafe { fan_row_in::<GATHER, true, true>(acc, q, line, a, b) }
    }
}

with_wide_variant! {
    /// [`fan_row`] reading samples through [`window_pairs::<W>`] (W = 32 and 64 only in the wide form);
    /// `MASK` drops pixels at or behind the source (without it every pixel must have lc > [`MIN_DEPTH`]);
    /// without `CLAMP` the positions are not clamped into the row (W must then be a window).
    ///
    /// # Safety
    /// As [`fan_row`]; the wide form needs AVX-512F.
    unsafe fn fan_row_in / fan_row_in_wide<const W: usize, const MASK: bool, const CLAMP: bool>(
        acc: &mut [f32],
        q: &[f32],
        line: &RowLine,
        a: f32,
        b: f32,
    ) {
        let n = acc.len();
        let hi = _mm256_set1_ps((q.len() - 2) as f32);
        let vb = _mm256_set1_ps(b);
        let (lc0, dlc) = (_mm256_set1_ps(line.lc0), _mm256_set1_ps(line.dlc));
        // a·lat, so that the position is one multiply-add from it.
        let (lat0, dlat) = (_mm256_set1_ps(a * line.lat0), _mm256_set1_ps(a * line.dlat));
        let eight = _mm256_set1_ps(8.0);
        let base = q.as_ptr();
        let mut x = lanes(0.0);
        let mut i = 0;
        while i + 8 <= n {
            let lc = _mm256_fmadd_ps(x, dlc, lc0);
            let inv = inverse_depth::<MASK>(lc);
            let lat = _mm256_fmadd_ps(x, dlat, lat0);
            let pos = _mm256_fmadd_ps(lat, inv, vb);
            let (k, f) = if CLAMP { split(pos, hi) } else { split_inside(pos) };
            // SAFETY: indices clamped to [0, len − 2] with CLAMP; without it W is a window, which
            // bounds its own reads (every position is inside [1, len − 3] up to rounding then).
            let (qa, qb) = unsafe { window_pairs::<W>(base, q.len(), k) };
            let v = _mm256_fmadd_ps(f, _mm256_sub_ps(qb, qa), qa);
            // SAFETY: i + 8 ≤ acc.len().
            unsafe { add_weighted(acc, i, inv, v) };
            x = _mm256_add_ps(x, eight);
            i += 8;
        }
        let mut rest = *line;
        rest.lc0 += i as f32 * line.dlc;
        rest.lat0 += i as f32 * line.dlat;
        fan_row_scalar(&mut acc[i..], q, &rest, a, b);
    }
}

/// # Safety
/// AVX2 and FMA must be available; `width, rows ≥ 2`, `q.len() ≥ width·rows`, `width·rows < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn cone_row(acc: &mut [f32], panel: Panel<'_>, line: &RowLine, map: [f32; 4]) {
    let last = acc.len().saturating_sub(1) as f32;
    // SAFETY (both arms): the caller's contract, passed on; without the depth mask only where every
    // voxel of the row is in front of the source (lc is affine along the row).
    if line.lc0.min(line.lc0 + last * line.dlc) > MIN_DEPTH {
        unsafe { cone_row_in::<false>(acc, panel, line, map) }
    } else {
        unsafe { cone_row_in::<true>(acc, panel, line, map) }
    }
}

/// [`cone_row`]; `MASK` drops voxels at or behind the source (without it every voxel must have
/// lc > [`MIN_DEPTH`]).
///
/// # Safety
/// As [`cone_row`].
#[target_feature(enable = "avx2,fma")]
unsafe fn cone_row_in<const MASK: bool>(
    acc: &mut [f32],
    panel: Panel<'_>,
    line: &RowLine,
    map: [f32; 4],
) {
    let Panel { q, width, rows } = panel;
    let n = acc.len();
    let [au, bu, av, bv] = map;
    let (hu, hv) = (
        _mm256_set1_ps((width - 2) as f32),
        _mm256_set1_ps((rows - 2) as f32),
    );
    let (vbu, vbv) = (_mm256_set1_ps(bu), _mm256_set1_ps(bv));
    let (lc0, dlc) = (_mm256_set1_ps(line.lc0), _mm256_set1_ps(line.dlc));
    // au·lat and av·latv, so that each position is one multiply-add from them.
    let (lat0, dlat) = (
        _mm256_set1_ps(au * line.lat0),
        _mm256_set1_ps(au * line.dlat),
    );
    let (latv0, dlatv) = (
        _mm256_set1_ps(av * line.latv0),
        _mm256_set1_ps(av * line.dlatv),
    );
    let eight = _mm256_set1_ps(8.0);
    let vw = _mm256_set1_epi32(width as i32);
    let base = q.as_ptr();
    let mut x = lanes(0.0);
    let mut i = 0;
    while i + 8 <= n {
        let lc = _mm256_fmadd_ps(x, dlc, lc0);
        let inv = inverse_depth::<MASK>(lc);
        let lat = _mm256_fmadd_ps(x, dlat, lat0);
        let latv = _mm256_fmadd_ps(x, dlatv, latv0);
        let (iu, fu) = split(_mm256_fmadd_ps(lat, inv, vbu), hu);
        let (iv, fv) = split(_mm256_fmadd_ps(latv, inv, vbv), hv);
        let k = _mm256_add_epi32(_mm256_mullo_epi32(iv, vw), iu);
        // SAFETY: iu ≤ width − 2 and iv ≤ rows − 2, so k + width + 1 ≤ rows·width − 1 < q.len().
        let ((q00, q01), (q10, q11)) =
            unsafe { (load_pairs(base, k), load_pairs(base.add(width), k)) };
        let top = _mm256_fmadd_ps(fu, _mm256_sub_ps(q01, q00), q00);
        let bottom = _mm256_fmadd_ps(fu, _mm256_sub_ps(q11, q10), q10);
        let v = _mm256_fmadd_ps(fv, _mm256_sub_ps(bottom, top), top);
        // SAFETY: i + 8 ≤ acc.len().
        unsafe { add_weighted(acc, i, inv, v) };
        x = _mm256_add_ps(x, eight);
        i += 8;
    }
    let mut rest = *line;
    rest.lc0 += i as f32 * line.dlc;
    rest.lat0 += i as f32 * line.dlat;
    rest.latv0 += i as f32 * line.dlatv;
    cone_row_scalar(&mut acc[i..], panel, &rest, map);
}
