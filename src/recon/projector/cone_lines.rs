//! The inner loops of the column-ordered cone-beam Joseph pair ([`super::cone_columns`]): on one plane
//! of a column's rays, the two neighbouring volume lines along z are blended into one line with the
//! in-plane weights, and every detector row of the column samples that line linearly at its own
//! position (forward) — or, transposed, every row spreads its value onto the line and the line is added
//! back to the two volume lines (back).
//!
//! Lines are padded: value `e + 1` of a line holds voxel `e`, values `0`, `n + 1` and `n + 2` are zero
//! (forward) or discarded (back), so a position clamped into `[0, n + 1]` needs no branch. A row's
//! padded position is `e0 + r·de + 1` in f32, computed by the same expression in both directions, so
//! the back loop enumerates exactly the (voxel, weight) pairs of the forward loop.
//!
//! The loops are written once and compiled three times: portable, and with AVX2 + FMA or AVX-512F
//! enabled (chosen once per process by [`crate::recon::cpu`]), where the compiler vectorises the line
//! blends and the forward row loop. None of the forms changes the order of f32 operations (no fused
//! multiply-add is formed from separate operations), so all three give the same values bit for bit.

use std::ops::Range;

/// One plane of a column: the in-plane weights of the two volume lines and the affine row positions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaneStep {
    /// Weights of the first and second volume line.
    pub w0: f32,
    pub w1: f32,
    /// Position of row `r` along the line (voxel units, before padding): `e0 + r·de`.
    pub e0: f32,
    pub de: f32,
}

/// The padded position of row `r` on a line of `n` voxels, clamped into `[0, n + 1]`: value index
/// `⌊q⌋` and weight `q − ⌊q⌋` of value `⌊q⌋ + 1`.
#[inline(always)]
fn position(step: &PlaneStep, r: usize, hi: f32) -> (usize, f32) {
    let q = (step.e0 + r as f32 * step.de + 1.0).max(0.0).min(hi);
    let i = q as usize;
    (i, q - i as f32)
}

#[inline(always)]
fn forward_body(
    a: &[f32],
    b: &[f32],
    line: &mut [f32],
    step: &PlaneStep,
    rows: Range<usize>,
    acc: &mut [f32],
) {
    let len = line.len();
    let (a, b) = (&a[..len], &b[..len]);
    for ((l, x), y) in line.iter_mut().zip(a).zip(b) {
        *l = step.w0 * *x + step.w1 * *y;
    }
    let hi = (len - 2) as f32;
    let line = &*line;
    let start = rows.start;
    for (i, out) in acc[rows].iter_mut().enumerate() {
        let (k, f) = position(step, start + i, hi);
        // `k ≤ len − 2` by the clamp, so both reads are in bounds.
        *out += (1.0 - f) * line[k.min(len - 2)] + f * line[(k + 1).min(len - 1)];
    }
}

#[inline(always)]
fn back_body(
    a: &mut [f32],
    b: &mut [f32],
    lines: &mut [f32],
    step: &PlaneStep,
    rows: Range<usize>,
    data: &[f32],
) {
    let len = lines.len() / 2;
    lines.fill(0.0);
    let hi = (len - 2) as f32;
    let (first, second) = lines.split_at_mut(len);
    // Even rows first, then odd rows: neighbouring rows of one parity are at least a value
    // apart when rows are at least half a voxel apart, which the vector forms use.
    let data = &data[..rows.len()];
    for parity in 0..2 {
        for i in (parity..data.len()).step_by(2) {
            let (k, f) = position(step, rows.start + i, hi);
            let k = k.min(len - 2);
            first[k] += (1.0 - f) * data[i];
            second[k] += f * data[i];
        }
    }
    merge_and_spread(a, b, first, second, step);
}

/// `line[e] = first[e] + second[e − 1]`, then `a += w0·line`, `b += w1·line`.
#[inline(always)]
fn merge_and_spread(a: &mut [f32], b: &mut [f32], first: &[f32], second: &[f32], step: &PlaneStep) {
    let len = first.len();
    let (a, b) = (&mut a[..len], &mut b[..len]);
    let l = first[0];
    a[0] += step.w0 * l;
    b[0] += step.w1 * l;
    for e in 1..len {
        let l = first[e] + second[e - 1];
        a[e] += step.w0 * l;
        b[e] += step.w1 * l;
    }
}

/// Which compiled form of the loops runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    Portable,
    /// Compiled with AVX2 + FMA; only where the CPU has them.
    Avx2,
    /// Compiled with AVX-512F; only where the CPU has it.
    Avx512,
}

impl Form {
    /// The widest form this process may run.
    pub fn detect() -> Self {
        if crate::recon::cpu::avx512f() {
            Form::Avx512
        } else if crate::recon::cpu::avx2_fma() {
            Form::Avx2
        } else {
            Form::Portable
        }
    }

    /// Every form this CPU runs (for tests).
    pub fn available() -> Vec<Self> {
        let mut forms = vec![Form::Portable];
        if crate::recon::cpu::avx2_fma() {
            forms.push(Form::Avx2);
        }
        if crate::recon::cpu::avx512f() {
            forms.push(Form::Avx512);
        }
        forms
    }

    /// Forward: `line = w0·a + w1·b` (over `line.len()` values), then `acc[r] += ` the line sampled at
    /// row `r`'s position, for `r` in `rows`. `a` and `b` hold at least `line.len()` values, `line`
    /// at least 3; positions are clamped into the padding.
    #[inline]
    #[allow(unsafe_code)]
    pub fn forward(
        self,
        a: &[f32],
        b: &[f32],
        line: &mut [f32],
        step: &PlaneStep,
        rows: Range<usize>,
        acc: &mut [f32],
    ) {
        match self {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `Form::Avx2` is only built where the CPU has AVX2 and FMA (`detect`, `available`).
            Form::Avx2 => unsafe { x86::forward_avx2(a, b, line, step, rows, acc) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `Form::Avx512` is only built where the CPU has AVX-512F.
            Form::Avx512 => unsafe { x86::forward_avx512(a, b, line, step, rows, acc) },
            _ => forward_body(a, b, line, step, rows, acc),
        }
    }

    /// Back, the transpose of [`Form::forward`]: the line = the rows' `data` spread at their
    /// positions (`data[i]` belongs to row `rows.start + i`), then `a += w0·line`, `b += w1·line`.
    /// `lines` is scratch of twice the line length: the weights of each row's first and second value
    /// are summed apart (so neighbouring rows do not wait on each other's sums), then merged.
    #[inline]
    #[allow(unsafe_code)]
    pub fn back(
        self,
        a: &mut [f32],
        b: &mut [f32],
        lines: &mut [f32],
        step: &PlaneStep,
        rows: Range<usize>,
        data: &[f32],
    ) {
        match self {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as in `forward`.
            Form::Avx2 => unsafe { x86::back_avx2(a, b, lines, step, rows, data) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as in `forward`.
            Form::Avx512 => unsafe { x86::back_avx512(a, b, lines, step, rows, data) },
            _ => back_body(a, b, lines, step, rows, data),
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    //! The loops with explicit AVX2 and AVX-512F row loops (8 or 16 rows per step, positions and
    //! weights in the same f32 operations as [`position`], no fused multiply-add) and the line blends
    //! compiled with those sets. Calling them is `unsafe` only because the CPU must have the sets.
    use std::arch::x86_64::*;

    use super::*;

    /// `line = w0·a + w1·b`.
    #[inline(always)]
    fn blend(a: &[f32], b: &[f32], line: &mut [f32], step: &PlaneStep) {
        let len = line.len();
        for ((l, x), y) in line.iter_mut().zip(&a[..len]).zip(&b[..len]) {
            *l = step.w0 * *x + step.w1 * *y;
        }
    }

    macro_rules! row_loops {
        ($forward:ident, $back:ident, $feature:literal, $lanes:literal, $v:ty, $set1:ident, $setr:expr,
         $add:ident, $sub:ident, $mul:ident, $max:ident, $min:ident, $cvtt:ident, $cvt:ident,
         $loadu:ident, $storeu:ident, $storei:ident, $gather:expr, $inc:expr, $scatter:expr) => {
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
                let len = line.len();
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
                    let (g0, g1) =
                        unsafe { ($gather(line.as_ptr(), i), $gather(line.as_ptr(), $inc(i))) };
                    let t = $add($mul($sub(one, f), g0), $mul(f, g1));
                    unsafe {
                        let p = acc.as_mut_ptr().add(r);
                        $storeu(p, $add($loadu(p), t));
                    }
                    r += $lanes;
                }
                for (j, out) in acc[r..].iter_mut().enumerate() {
                    let (k, f) = position(step, r + j, hi);
                    *out += (1.0 - f) * line[k.min(len - 2)] + f * line[(k + 1).min(len - 1)];
                }
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
                let len = lines.len() / 2;
                lines.fill(0.0);
                let hi = (len - 2) as f32;
                let (first, second) = lines.split_at_mut(len);
                let n = rows.len();
                let data = &data[..n];
                let (e0, de, one, zero, top) = (
                    $set1(step.e0),
                    $set1(step.de),
                    $set1(1.0),
                    $set1(0.0),
                    $set1(hi),
                );
                let lane = $setr;
                let lane2 = $add(lane, lane);
                let every_other = $cvtt(lane2);
                let (mut idx, mut p0, mut p1) =
                    ([0i32; $lanes], [0.0f32; $lanes], [0.0f32; $lanes]);
                for parity in 0..2 {
                    let mut j = parity;
                    while j + 2 * ($lanes - 1) < n {
                        let rv = $add($set1((rows.start + j) as f32), lane2);
                        let q = $add($add(e0, $mul(rv, de)), one);
                        let q = $min($max(q, zero), top);
                        let i = $cvtt(q);
                        let f = $sub(q, $cvt(i));
                        // SAFETY: rows j, j + 2, …, j + 2·(lanes − 1) < n lie in `data`.
                        let d = unsafe { $gather(data.as_ptr().add(j), every_other) };
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
                        j += 2 * $lanes;
                    }
                    while j < n {
                        let (k, f) = position(step, rows.start + j, hi);
                        let k = k.min(len - 2);
                        first[k] += (1.0 - f) * data[j];
                        second[k] += f * data[j];
                        j += 2;
                    }
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
        |p: *const f32, i: __m256i| _mm256_i32gather_ps::<4>(p, i),
        |i: __m256i| _mm256_add_epi32(i, _mm256_set1_epi32(1)),
        no_scatter
    );

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
        "avx512f,avx2,fma",
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
        |p: *const f32, i: __m512i| _mm512_i32gather_ps::<4>(i, p),
        |i: __m512i| _mm512_add_epi32(i, _mm512_set1_epi32(1)),
        scatter_distinct
    );

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
}
