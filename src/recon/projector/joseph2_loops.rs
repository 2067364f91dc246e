//! The inner loops of the 2D Joseph projector pair over padded line layouts ([`super::padded2`]): the
//! dot product of one ray with an image (forward) and its transpose, `alpha ×` the ray added to an
//! accumulator (back), over any range of the ray's samples.
//!
//! Both loops compute every sample's pixel pair and weights with exactly the f32 operations of
//! [`Walk2::visit`], so each kernel enumerates the (pixel, weight) pairs of the reference walk, bit for
//! bit; only the order of the sums differs. A sample whose pair is half outside the grid uses the zero
//! (forward) or discarded (back) border value instead of a branch. [`Kernel::Avx2`] runs 8 samples per
//! step (`joseph2_avx2`); [`Kernel::Scalar`] is the portable form.

use super::joseph2::Walk2;

/// The samples of one ray in a line layout: sample `i ∈ [start, end)` lies on line `i` at padded
/// position `t = c0 + i·dc + 1` (pixel pair `⌊t⌋ − 1, ⌊t⌋` = values `⌊t⌋, ⌊t⌋ + 1` of the line) and
/// weighs `weight` mm. The fields of [`Walk2`] that a kernel needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    pub start: u32,
    pub end: u32,
    pub c0: f32,
    pub dc: f32,
    pub weight: f32,
}

impl Segment {
    /// The segment of `walk` (whose line count must fit a `u32`, see [`Kernel::fits`]).
    pub fn of(walk: &Walk2) -> Self {
        Self {
            start: walk.start as u32,
            end: walk.end as u32,
            c0: walk.c0,
            dc: walk.dc,
            weight: walk.weight,
        }
    }
}

/// Which form of the loops runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kernel {
    Scalar,
    /// AVX2 + FMA, 8 samples per step; only where the CPU has them.
    Avx2,
}

/// Largest line count or width the kernels take: sample indices and positions stay exact in f32, and
/// every value index of a layout fits an `i32`.
const MAX_EXTENT: usize = 1 << 22;

impl Kernel {
    /// True when layouts of `count` lines of `width` values suit the kernels.
    pub fn fits(count: usize, width: usize) -> bool {
        count < MAX_EXTENT && width < MAX_EXTENT && count.saturating_mul(width) < i32::MAX as usize
    }

    /// The fastest form this CPU runs.
    pub fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if super::joseph2_avx2::available() {
            return Self::Avx2;
        }
        Self::Scalar
    }

    /// Σ over samples `i ∈ [lo, hi)` of `seg` of value·weight, where `lines` holds lines `first ..` of a
    /// layout of `width` values per line.
    ///
    /// # Panics
    /// Unless `first ≤ lo`, `hi ≤ first + lines.len() / width`, `2 ≤ width` and [`Kernel::fits`] holds.
    #[inline]
    #[allow(unsafe_code)]
    pub fn dot(
        self,
        lines: &[f32],
        width: usize,
        first: usize,
        seg: &Segment,
        lo: usize,
        hi: usize,
    ) -> f32 {
        if lo >= hi {
            return 0.0;
        }
        check(lines.len(), width, first, lo, hi);
        match self {
            // SAFETY: `check` proved the bounds `dot_avx2` requires; `Avx2` is only chosen by
            // `detect` on a CPU with AVX2 and FMA (or by tests that check the same).
            #[cfg(target_arch = "x86_64")]
            Self::Avx2 => unsafe { super::joseph2_avx2::dot(lines, width, first, seg, lo, hi) },
            _ => dot_scalar(lines, width, first, seg, lo, hi),
        }
    }

    /// `lines[p] += alpha·w` over the (value, weight) pairs of samples `i ∈ [lo, hi)` of `seg`; the
    /// transpose of [`Kernel::dot`]. Same layout arguments and panics.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    #[allow(unsafe_code)]
    pub fn axpy(
        self,
        lines: &mut [f32],
        width: usize,
        first: usize,
        seg: &Segment,
        lo: usize,
        hi: usize,
        alpha: f32,
    ) {
        if lo >= hi {
            return;
        }
        check(lines.len(), width, first, lo, hi);
        match self {
            // SAFETY: as in `dot`.
            #[cfg(target_arch = "x86_64")]
            Self::Avx2 => unsafe {
                super::joseph2_avx2::axpy(lines, width, first, seg, lo, hi, alpha)
            },
            _ => axpy_scalar(lines, width, first, seg, lo, hi, alpha),
        }
    }
}

/// The bounds every kernel relies on: lines `lo .. hi` (relative to `first`) lie inside `len` values.
#[inline]
fn check(len: usize, width: usize, first: usize, lo: usize, hi: usize) {
    assert!(
        width >= 2 && first <= lo && lo < hi && hi - first <= len / width,
        "kernel range outside the lines"
    );
    assert!(Kernel::fits(hi, width), "layout too large for the kernels");
}

/// The pair of sample `i`: index of its first value relative to the start of line `i`, and weights
/// `(w0, w1)`; `None` when neither value is a pixel. The f32 operations of [`Walk2::visit`].
#[inline(always)]
fn sample(seg: &Segment, i: usize, top: f32) -> Option<(usize, f32, f32)> {
    let t = seg.c0 + i as f32 * seg.dc + 1.0;
    // Pixels exist for ⌊t⌋ ∈ [0, len], i.e. t ∈ (0, len + 1) (t ≤ 0 is skipped by the walk too).
    if !(t > 0.0 && t < top) {
        return None;
    }
    let j = t as usize;
    let w1 = (t - j as f32) * seg.weight;
    Some((j, seg.weight - w1, w1))
}

#[allow(unsafe_code)]
fn dot_scalar(
    lines: &[f32],
    width: usize,
    first: usize,
    seg: &Segment,
    lo: usize,
    hi: usize,
) -> f32 {
    let top = (width - 1) as f32;
    let mut acc = 0.0f32;
    for i in lo..hi {
        if let Some((j, w0, w1)) = sample(seg, i, top) {
            let p = (i - first) * width + j;
            // SAFETY: `check` gave (hi − first)·width ≤ lines.len(), and i < hi; `sample` gave
            // t < width − 1, so j ≤ width − 2 and p + 1 < (i − first + 1)·width ≤ lines.len().
            let (a, b) = unsafe { (*lines.get_unchecked(p), *lines.get_unchecked(p + 1)) };
            acc += a * w0;
            acc += b * w1;
        }
    }
    acc
}

#[allow(unsafe_code)]
fn axpy_scalar(
    lines: &mut [f32],
    width: usize,
    first: usize,
    seg: &Segment,
    lo: usize,
    hi: usize,
    alpha: f32,
) {
    let top = (width - 1) as f32;
    for i in lo..hi {
        if let Some((j, w0, w1)) = sample(seg, i, top) {
            let p = (i - first) * width + j;
            // SAFETY: as in `dot_scalar`, p + 1 < lines.len().
            unsafe {
                *lines.get_unchecked_mut(p) += alpha * w0;
                *lines.get_unchecked_mut(p + 1) += alpha * w1;
            }
        }
    }
}

#[cfg(test)]
#[path = "joseph2_loops_tests.rs"]
mod tests;
