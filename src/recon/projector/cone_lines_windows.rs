//! The window forms of the row loops' reads and adds: where the rows of one vector reach a short run
//! of consecutive line values (their positions are affine in the row), the values are read from that
//! window by permutes and added to it through expands and plain loads and stores, instead of gathers
//! and scatters; elsewhere the gathers and scatters run. Every form picks and adds the same values as
//! the gathers and scatters, so the loops' results do not change.
use std::arch::x86_64::*;

/// `(line[i], line[i + 1])` of 8 lanes whose indices increase or decrease from lane to lane: from a
/// window of 16 values of `line` (two permutes and a blend each) where the indices span at most 14
/// and the window lies inside `line`, else by two gathers.
///
/// # Safety
/// Every `i + 1` must lie inside `line`, and the CPU must have AVX2.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn pick8(line: &[f32], i: __m256i) -> (__m256, __m256) {
    let (p, next) = (line.as_ptr(), _mm256_add_epi32(i, _mm256_set1_epi32(1)));
    let (head, tail) = (_mm256_extract_epi32::<0>(i), _mm256_extract_epi32::<7>(i));
    let low = head.min(tail);
    let base = low.max(0) as usize;
    if head.max(tail) - low > 14 || base + 16 > line.len() {
        // SAFETY: as the caller's.
        return unsafe {
            (
                _mm256_i32gather_ps::<4>(p, i),
                _mm256_i32gather_ps::<4>(p, next),
            )
        };
    }
    // SAFETY: base + 16 ≤ line.len(), checked above.
    let (w0, w1) = unsafe {
        (
            _mm256_loadu_ps(p.add(base)),
            _mm256_loadu_ps(p.add(base + 8)),
        )
    };
    let pick = |k: __m256i| {
        let k = _mm256_sub_epi32(k, _mm256_set1_epi32(low));
        let upper = _mm256_castsi256_ps(_mm256_cmpgt_epi32(k, _mm256_set1_epi32(7)));
        let (a, b) = (
            _mm256_permutevar8x32_ps(w0, k),
            _mm256_permutevar8x32_ps(w1, k),
        );
        _mm256_blendv_ps(a, b, upper)
    };
    (pick(i), pick(next))
}

/// `first[i] += v0`, `second[i] += v1` in one gather and scatter each when the 16 indices are
/// distinct (they increase or decrease, so distinct neighbours suffice); false otherwise.
///
/// # Safety
/// Every index must lie inside both slices, and the CPU must have AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn scatter_distinct(
    first: &mut [f32],
    second: &mut [f32],
    i: __m512i,
    v0: __m512,
    v1: __m512,
) -> bool {
    let next = _mm512_alignr_epi32::<1>(i, i);
    if _mm512_mask_cmpneq_epi32_mask(0x7fff, i, next) != 0x7fff {
        return false;
    }
    // SAFETY: the caller's indices lie inside both slices; distinct lanes write distinct values.
    unsafe {
        let g = _mm512_i32gather_ps::<4>(i, first.as_ptr());
        _mm512_i32scatter_ps::<4>(first.as_mut_ptr(), i, _mm512_add_ps(g, v0));
        let g = _mm512_i32gather_ps::<4>(i, second.as_ptr());
        _mm512_i32scatter_ps::<4>(second.as_mut_ptr(), i, _mm512_add_ps(g, v1));
    }
    true
}

/// The smallest and largest of 16 indices that increase or decrease from lane to lane (those of the
/// first and the last lane), and whether they decrease.
#[target_feature(enable = "avx512f,avx2,fma")]
#[inline]
fn span16(i: __m512i) -> (i32, i32, bool) {
    let head = _mm_cvtsi128_si32(_mm512_castsi512_si128(i));
    let tail = _mm_extract_epi32::<3>(_mm512_extracti32x4_epi32::<3>(i));
    (head.min(tail), head.max(tail), head > tail)
}

/// `first[i] += v0`, `second[i] += v1` for 16 distinct indices that increase or decrease from lane
/// to lane, without a scatter where neighbouring lanes' indices lie one or two values apart (so
/// all 16 lie in a window of 32 values) and both slices hold the window: the values are expanded
/// into the window's slots in index order and the window is added with plain loads and stores
/// (slots no row reaches add zero, which leaves their sums unchanged: a sum that starts at +0 is
/// never −0). Else [`scatter_distinct`], which returns false where indices repeat.
///
/// The slots the lanes reach follow from the steps between neighbours: in index order, each lane
/// takes the next slot and a step of two leaves one empty after it, so the slot mask is the bit
/// pattern `1` or `10` per lane, packed by a bit extract.
///
/// # Safety
/// Every index must lie inside both slices, and the CPU must have AVX-512F, BMI2 and POPCNT.
#[target_feature(enable = "avx512f,avx2,fma,bmi2,popcnt")]
pub(super) unsafe fn window_add(
    first: &mut [f32],
    second: &mut [f32],
    i: __m512i,
    v0: __m512,
    v1: __m512,
) -> bool {
    let (low, _, descending) = span16(i);
    let base = low.max(0) as usize;
    let steps = _mm512_abs_epi32(_mm512_sub_epi32(_mm512_alignr_epi32::<1>(i, i), i));
    let ones = _mm512_mask_cmpeq_epi32_mask(0x7fff, steps, _mm512_set1_epi32(1));
    let twos = _mm512_mask_cmpeq_epi32_mask(0x7fff, steps, _mm512_set1_epi32(2));
    if ones | twos != 0x7fff || base + 32 > first.len() || base + 32 > second.len() {
        // SAFETY: as the caller's.
        return unsafe { scatter_distinct(first, second, i, v0, v1) };
    }
    // The steps of two in index order: lane order, or reversed where the indices decrease.
    let gaps = if descending {
        (twos.reverse_bits() >> 1) as u32
    } else {
        twos as u32
    };
    const EVEN: u32 = 0x5555_5555;
    let hit = _pext_u32(EVEN, EVEN | (_pdep_u32(gaps, EVEN) << 1));
    let (lower, upper) = ((hit & 0xffff) as __mmask16, (hit >> 16) as __mmask16);
    // The lane each slot takes: lanes in increasing index order (reversed where the indices
    // decrease), the lower 16 slots' lanes first, the upper slots' lanes after them.
    let taken = _mm512_set1_epi32(lower.count_ones() as i32);
    let order = if descending {
        _mm512_setr_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0)
    } else {
        _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
    };
    let after = if descending {
        _mm512_sub_epi32(order, taken)
    } else {
        _mm512_add_epi32(order, taken)
    };
    let low_lanes = _mm512_maskz_expand_epi32(lower, order);
    let high_lanes = _mm512_maskz_expand_epi32(upper, after);
    for (line, v) in [(first, v0), (second, v1)] {
        let low_slots = _mm512_maskz_permutexvar_ps(lower, low_lanes, v);
        let high_slots = _mm512_maskz_permutexvar_ps(upper, high_lanes, v);
        // SAFETY: base + 32 ≤ line.len(), checked above.
        unsafe {
            let p = line.as_mut_ptr().add(base);
            _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), low_slots));
            let p = p.add(16);
            _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), high_slots));
        }
    }
    true
}

/// `(line[i], line[i + 1])` of 16 lanes whose indices increase or decrease from lane to lane: two
/// permutes of a window of 32 values of `line` where the indices span at most 31 and the window lies
/// inside `line`, else two gathers.
///
/// # Safety
/// Every `i + 1` must lie inside `line`, and the CPU must have AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma")]
pub(super) unsafe fn pick16(line: &[f32], i: __m512i) -> (__m512, __m512) {
    let (low, high, _) = span16(i);
    let base = low.max(0) as usize;
    let next = _mm512_add_epi32(i, _mm512_set1_epi32(1));
    if high - low > 30 || base + 32 > line.len() {
        let p = line.as_ptr();
        // SAFETY: as the caller's.
        return unsafe {
            (
                _mm512_i32gather_ps::<4>(i, p),
                _mm512_i32gather_ps::<4>(next, p),
            )
        };
    }
    // SAFETY: base + 32 ≤ line.len(), checked above.
    let (w0, w1) = unsafe {
        let p = line.as_ptr().add(base);
        (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)))
    };
    let low = _mm512_set1_epi32(low);
    (
        _mm512_permutex2var_ps(w0, _mm512_sub_epi32(i, low), w1),
        _mm512_permutex2var_ps(w0, _mm512_sub_epi32(next, low), w1),
    )
}

/// `d[0], d[2], …, d[30]`: two loads and a permute where `d` holds 32 values, else a gather by the
/// indices `spaced` (0, 2, …, 30).
///
/// # Safety
/// `d` holds at least 31 values, and the CPU must have AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma")]
pub(super) unsafe fn every_other16(d: &[f32], spaced: __m512i) -> __m512 {
    // SAFETY: as the caller's; the loads read d[0 .. 32] only where d holds them.
    unsafe {
        if d.len() >= 32 {
            let p = d.as_ptr();
            _mm512_permutex2var_ps(_mm512_loadu_ps(p), spaced, _mm512_loadu_ps(p.add(16)))
        } else {
            _mm512_i32gather_ps::<4>(spaced, d.as_ptr())
        }
    }
}
