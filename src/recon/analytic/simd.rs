//! AVX2 + FMA backprojection kernels, 8 pixels at a time (each pixel's pair of detector samples by a 64-bit
//! gather in 2D, where neighbouring pixels read neighbouring samples, and by one 64-bit load each in 3D, where
//! they do not: the faster choice for each on the development machine), selected at run time by
//! [`super::backproject`]; the scalar forms there are the reference and handle the tails. Tested against
//! the safe reference in `backproject`'s tests (which run these kernels on any AVX2 machine).

use std::arch::x86_64::*;

use crate::recon::pairs::load_pairs;

use super::backproject::{
    MIN_DEPTH, Panel, RowLine, cone_row_scalar, fan_row_scalar, parallel_row_scalar,
};

/// True when the CPU has AVX2 and FMA and indices below `len` fit an i32.
pub fn available(len: usize) -> bool {
    len < i32::MAX as usize
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
}

#[target_feature(enable = "avx2,fma")]
#[inline]
fn lanes(i: usize) -> __m256 {
    _mm256_add_ps(
        _mm256_set1_ps(i as f32),
        _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0),
    )
}

/// Clamp to [0, hi] (NaN → 0) and split into index and fraction.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn split(p: __m256, hi: __m256) -> (__m256i, __m256) {
    let p = _mm256_min_ps(_mm256_max_ps(p, _mm256_setzero_ps()), hi);
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

/// # Safety
/// AVX2 and FMA must be available; `2 ≤ q.len() < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn parallel_row(acc: &mut [f32], q: &[f32], pos0: f32, dpos: f32) {
    let n = acc.len();
    let hi = _mm256_set1_ps((q.len() - 2) as f32);
    let (vp0, vd) = (_mm256_set1_ps(pos0), _mm256_set1_ps(dpos));
    let base = q.as_ptr();
    let mut i = 0;
    while i + 8 <= n {
        let (k, f) = split(_mm256_fmadd_ps(lanes(i), vd, vp0), hi);
        // SAFETY: `split` clamps every index to [0, len − 2], so k and k + 1 are inside q.
        let (a, b) = unsafe { gather_pairs(base, k) };
        let v = _mm256_fmadd_ps(f, _mm256_sub_ps(b, a), a);
        // SAFETY: i + 8 ≤ acc.len().
        unsafe {
            let out = acc.as_mut_ptr().add(i);
            _mm256_storeu_ps(out, _mm256_add_ps(_mm256_loadu_ps(out), v));
        }
        i += 8;
    }
    parallel_row_scalar(&mut acc[i..], q, pos0 + i as f32 * dpos, dpos);
}

/// 1/lc where lc > MIN_DEPTH, else 0 (relative error below 1e-6).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn inverse_depth(lc: __m256) -> __m256 {
    let min = _mm256_set1_ps(MIN_DEPTH);
    let valid = _mm256_cmp_ps::<_CMP_GT_OQ>(lc, min);
    // Reciprocal estimate (12 bits) refined by one Newton step: ~23 bits, cheaper than a division.
    let x = _mm256_max_ps(lc, min);
    let r = _mm256_rcp_ps(x);
    let inv = _mm256_mul_ps(r, _mm256_fnmadd_ps(x, r, _mm256_set1_ps(2.0)));
    _mm256_and_ps(inv, valid)
}

/// # Safety
/// AVX2 and FMA must be available; `2 ≤ q.len() < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn fan_row(acc: &mut [f32], q: &[f32], line: &RowLine, a: f32, b: f32) {
    let n = acc.len();
    let hi = _mm256_set1_ps((q.len() - 2) as f32);
    let (va, vb) = (_mm256_set1_ps(a), _mm256_set1_ps(b));
    let (lc0, dlc) = (_mm256_set1_ps(line.lc0), _mm256_set1_ps(line.dlc));
    let (lat0, dlat) = (_mm256_set1_ps(line.lat0), _mm256_set1_ps(line.dlat));
    let base = q.as_ptr();
    let mut i = 0;
    while i + 8 <= n {
        let x = lanes(i);
        let inv = inverse_depth(_mm256_fmadd_ps(x, dlc, lc0));
        let lat = _mm256_fmadd_ps(x, dlat, lat0);
        let (k, f) = split(_mm256_fmadd_ps(_mm256_mul_ps(lat, inv), va, vb), hi);
        // SAFETY: indices clamped to [0, len − 2].
        let (qa, qb) = unsafe { gather_pairs(base, k) };
        let v = _mm256_fmadd_ps(f, _mm256_sub_ps(qb, qa), qa);
        let w = _mm256_mul_ps(inv, inv);
        // SAFETY: i + 8 ≤ acc.len().
        unsafe {
            let out = acc.as_mut_ptr().add(i);
            _mm256_storeu_ps(out, _mm256_fmadd_ps(w, v, _mm256_loadu_ps(out)));
        }
        i += 8;
    }
    let mut rest = *line;
    rest.lc0 += i as f32 * line.dlc;
    rest.lat0 += i as f32 * line.dlat;
    fan_row_scalar(&mut acc[i..], q, &rest, a, b);
}

/// # Safety
/// AVX2 and FMA must be available; `width, rows ≥ 2`, `q.len() ≥ width·rows`, `width·rows < i32::MAX`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn cone_row(acc: &mut [f32], panel: Panel<'_>, line: &RowLine, map: [f32; 4]) {
    let Panel { q, width, rows } = panel;
    let n = acc.len();
    let [au, bu, av, bv] = map;
    let (hu, hv) = (
        _mm256_set1_ps((width - 2) as f32),
        _mm256_set1_ps((rows - 2) as f32),
    );
    let (vau, vbu, vav, vbv) = (
        _mm256_set1_ps(au),
        _mm256_set1_ps(bu),
        _mm256_set1_ps(av),
        _mm256_set1_ps(bv),
    );
    let (lc0, dlc) = (_mm256_set1_ps(line.lc0), _mm256_set1_ps(line.dlc));
    let (lat0, dlat) = (_mm256_set1_ps(line.lat0), _mm256_set1_ps(line.dlat));
    let (latv0, dlatv) = (_mm256_set1_ps(line.latv0), _mm256_set1_ps(line.dlatv));
    let vw = _mm256_set1_epi32(width as i32);
    let base = q.as_ptr();
    let mut i = 0;
    while i + 8 <= n {
        let x = lanes(i);
        let inv = inverse_depth(_mm256_fmadd_ps(x, dlc, lc0));
        let lat = _mm256_fmadd_ps(x, dlat, lat0);
        let latv = _mm256_fmadd_ps(x, dlatv, latv0);
        let (iu, fu) = split(_mm256_fmadd_ps(_mm256_mul_ps(lat, inv), vau, vbu), hu);
        let (iv, fv) = split(_mm256_fmadd_ps(_mm256_mul_ps(latv, inv), vav, vbv), hv);
        let k = _mm256_add_epi32(_mm256_mullo_epi32(iv, vw), iu);
        // SAFETY: iu ≤ width − 2 and iv ≤ rows − 2, so k + width + 1 ≤ rows·width − 1 < q.len().
        let ((q00, q01), (q10, q11)) =
            unsafe { (load_pairs(base, k), load_pairs(base.add(width), k)) };
        let top = _mm256_fmadd_ps(fu, _mm256_sub_ps(q01, q00), q00);
        let bottom = _mm256_fmadd_ps(fu, _mm256_sub_ps(q11, q10), q10);
        let v = _mm256_fmadd_ps(fv, _mm256_sub_ps(bottom, top), top);
        let w = _mm256_mul_ps(inv, inv);
        // SAFETY: i + 8 ≤ acc.len().
        unsafe {
            let out = acc.as_mut_ptr().add(i);
            _mm256_storeu_ps(out, _mm256_fmadd_ps(w, v, _mm256_loadu_ps(out)));
        }
        i += 8;
    }
    let mut rest = *line;
    rest.lc0 += i as f32 * line.dlc;
    rest.lat0 += i as f32 * line.dlat;
    rest.latv0 += i as f32 * line.dlatv;
    cone_row_scalar(&mut acc[i..], panel, &rest, map);
}
