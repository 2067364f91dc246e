//! Line-driven kernels for the parallel-beam views of the 2D Joseph pair.
//!
//! Every ray of a parallel view has the same direction, so on each line of the dominant axis the
//! samples of neighbouring rays sit at evenly spaced positions. With the rays sorted by position, ray
//! `k` samples line `i` at `t = fl(b_i + fl(k·s))` (pixel coordinates along the line: the sample
//! interpolates pixels `⌊t⌋` and `⌊t⌋ + 1` with weights `w0 = w − w1`, `w1 = (t − ⌊t⌋)·w`), where `s` is
//! the ray step in pixels, `b_i` the position of ray 0 and `w` the ray length per line (mm).
//!
//! - The forward pass runs 8 neighbouring rays per vector down the lines; their pixel pairs lie in 16
//!   neighbouring values of the line, so they are picked by permutes from one window instead of being
//!   gathered. The lines carry zero margins ([`WideLines`]), so a sample half or wholly outside the
//!   image reads zeros and needs no mask.
//! - The back pass runs 8 neighbouring pixels per vector along each line (16 with AVX-512F, whose
//!   two-register permute picks from 32 data values). Pixel `q` collects `w0` from
//!   the rays with `⌊t⌋ = q` and `w1` from those with `⌊t⌋ = q − 1`; it finds them from `K(q)`, the first
//!   ray with `t ≥ q` (estimated by a division, then settled by comparing the exact positions), and picks
//!   their data values from a window of the data row. It enumerates the same (pixel, weight) pairs as
//!   the forward pass, bit for bit, so the two are exact adjoints up to the order of the sums.
//!
//! A step `s ∈ [S_MIN, S_MAX]` keeps every window within its 16 (or 32) values and at most two rays
//! per pixel;
//! views outside it (detectors much finer or coarser than the pixels), fan views and CPUs without AVX2
//! use the ray-driven kernels of [`super::joseph2_loops`]. The positions come from the view's geometry once
//! per line instead of once per ray, so they differ from those of [`super::joseph2::Walk2`] by f32
//! rounding (a few 1e-5 pixel).

use rayon::prelude::*;

use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Source2, Views2};
use crate::recon::grid::ImageGrid;

/// Smallest and largest ray step (pixels) of the line kernels.
pub const S_MIN: f32 = 0.6;
pub const S_MAX: f32 = 1.85;

/// Steps from which no pixel holds two rays: consecutive positions differ by the step within 2 ulp of
/// positions below 2·MAX_POS (2⁻⁶ pixel), so by more than one pixel.
const ONE_RAY: f32 = 1.02;

/// Zero values before, between and after the lines of a [`WideLines`]: more than a vector of rays
/// reaches past the last pixel that one of them touches (7·S_MAX + 2 values), plus the window.
const PAD: usize = 40;

/// Largest |position| (pixels) of a planned view's samples: positions stay exact to 1/256 pixel, and
/// the back pass's estimate of `K(q)` stays within one ray.
const MAX_POS: f64 = 32768.0;

/// Largest line count, line length or ray count (positions and ray indices exact in f32, offsets in
/// i32).
const MAX_EXTENT: usize = 1 << 22;

/// True when the CPU runs the line kernels (AVX2 and FMA).
pub fn available() -> bool {
    crate::recon::cpu::avx2_fma()
}

/// True when the CPU also has AVX-512F, for the 16-pixel back kernel.
fn wide_available() -> bool {
    crate::recon::cpu::avx512f()
}

/// The sample positions of one parallel view (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct LineView {
    /// True when the dominant axis is x: the lines are image columns.
    pub along_x: bool,
    /// True when sorted ray `k` is detector element `count − 1 − k`.
    pub reversed: bool,
    /// Rays (detector elements).
    pub count: usize,
    /// Pixels per line.
    pub len: usize,
    /// Ray step along a line (pixels), in `[S_MIN, S_MAX]`.
    pub s: f32,
    /// Ray length per line (mm).
    pub weight: f32,
    /// Sorted ray 0 at line `i`: `c0 + i·dc` (pixels).
    c0: f64,
    dc: f64,
    /// `b[i] = (c0 + i·dc) as f32`.
    pub b: Vec<f32>,
}

impl LineView {
    /// The plan of `view`, or `None` when the line kernels do not take it (not a parallel view, fewer
    /// than 2 rays, a step outside `[S_MIN, S_MAX]`, sizes or positions out of range).
    pub fn plan(views: &Views2, view: usize, grid: &ImageGrid) -> Option<Self> {
        let v = &views.views[view];
        let Source2::Parallel { direction } = v.source else {
            return None;
        };
        let count = views.detector.count;
        if !(2..MAX_EXTENT).contains(&count) {
            return None;
        }
        // The index-space coordinates of `Walk2::new`.
        let (x0, y0) = (grid.x(0), grid.y(0));
        let bx = direction[0] / grid.dx_mm;
        let by = direction[1] / grid.dy_mm;
        let along_x = bx.abs() >= by.abs();
        let (ba, bc, lines, len) = if along_x {
            (bx, by, grid.nx, grid.ny)
        } else {
            (by, bx, grid.ny, grid.nx)
        };
        if ba == 0.0 || !ba.is_finite() || !bc.is_finite() {
            return None;
        }
        if !(1..MAX_EXTENT).contains(&lines) || !(1..MAX_EXTENT).contains(&len) {
            return None;
        }
        let dc = bc / ba;
        let start = |k: usize| {
            let e = views.element_position(v, k);
            let (ax, ay) = ((e[0] - x0) / grid.dx_mm, (e[1] - y0) / grid.dy_mm);
            let (a, c) = if along_x { (ax, ay) } else { (ay, ax) };
            c - a * dc
        };
        let (first, last) = (start(0), start(count - 1));
        let step = (last - first) / (count - 1) as f64;
        let (c0, reversed) = if step >= 0.0 {
            (first, false)
        } else {
            (last, true)
        };
        let s = step.abs() as f32;
        if !(S_MIN..=S_MAX).contains(&s) {
            return None;
        }
        let span = (count - 1) as f64 * f64::from(s);
        let end = (lines - 1) as f64 * dc;
        let corners = [c0, c0 + span, c0 + end, c0 + end + span];
        if !corners.iter().all(|p| p.abs() < MAX_POS) {
            return None;
        }
        Some(Self {
            along_x,
            reversed,
            count,
            len,
            s,
            weight: (1.0 / ba.abs()) as f32,
            c0,
            dc,
            b: (0..lines).map(|i| (c0 + i as f64 * dc) as f32).collect(),
        })
    }

    /// Lines (of the dominant axis).
    pub fn lines(&self) -> usize {
        self.b.len()
    }

    /// Detector element of sorted ray `k`.
    fn element(&self, k: usize) -> usize {
        if self.reversed { self.count - 1 - k } else { k }
    }

    /// The lines `[lo, hi)` on which one of the sorted rays `first .. first + 8` may touch a pixel (a
    /// superset: the positions of the vector's first and last lanes, with a margin for rounding).
    fn group_lines(&self, first: usize) -> (usize, usize) {
        const MARGIN: f64 = 0.05;
        let s = f64::from(self.s);
        let lane0 = self.c0 + first as f64 * s;
        let lane7 = lane0 + 7.0 * s;
        let (mut lo, mut hi) = (0.0f64, self.lines() as f64);
        // lane 0 at line i lies below len: (len + m − lane0) − dc·i > 0; lane 7 lies above −1:
        // (lane7 + 1 + m) + dc·i > 0.
        for (a, b) in [
            (self.len as f64 + MARGIN - lane0, -self.dc),
            (lane7 + 1.0 + MARGIN, self.dc),
        ] {
            if b == 0.0 {
                if a <= 0.0 {
                    return (0, 0);
                }
            } else if b > 0.0 {
                lo = lo.max(-a / b);
            } else {
                hi = hi.min(-a / b);
            }
        }
        let lo = (lo.floor() - 1.0).max(0.0);
        let hi = (hi.ceil() + 1.0).min(self.lines() as f64);
        if lo < hi {
            (lo as usize, hi as usize)
        } else {
            (0, 0)
        }
    }
}

/// The lines of an image along one axis, with `PAD` zeros before each line and after the last.
#[derive(Debug, Clone, PartialEq)]
pub struct WideLines {
    pub count: usize,
    pub len: usize,
    data: Vec<f32>,
}

impl WideLines {
    fn stride(&self) -> usize {
        self.len + PAD
    }

    /// Index of pixel 0 of line `i`.
    fn offset(&self, i: usize) -> usize {
        PAD + i * self.stride()
    }

    /// The lines of `image` (flat `[y][x]`, `nx·ny` values): columns when `along_x`, else rows.
    ///
    /// # Panics
    /// If `image.len() != nx·ny`.
    pub fn from_image(image: &[f32], nx: usize, ny: usize, along_x: bool) -> Self {
        assert_eq!(image.len(), nx * ny, "image must hold nx·ny values");
        let (count, len) = if along_x { (nx, ny) } else { (ny, nx) };
        let stride = len + PAD;
        let mut data = vec![0.0f32; PAD + count * stride];
        if count > 0 && len > 0 {
            let lines = data[PAD..].par_chunks_mut(stride);
            if along_x {
                lines.enumerate().for_each(|(x, line)| {
                    for (y, v) in line[..len].iter_mut().enumerate() {
                        *v = image[y * nx + x];
                    }
                });
            } else {
                lines
                    .zip(image.par_chunks(nx))
                    .for_each(|(line, row)| line[..len].copy_from_slice(row));
            }
        }
        Self { count, len, data }
    }
}

/// `out[k]` = the projection of the image held in `lines` along element `k` of the view of `lv`.
///
/// # Panics
/// If `lines` and `lv` disagree on the line count or length, or `out.len() != lv.count`, or the CPU
/// lacks AVX2 and FMA.
#[allow(unsafe_code)]
pub fn forward_view(lines: &WideLines, lv: &LineView, out: &mut [f32]) {
    assert!(
        lines.count == lv.lines() && lines.len == lv.len && out.len() == lv.count,
        "line layout, view plan and data row disagree"
    );
    assert!(available(), "the line kernels need AVX2 and FMA");
    #[cfg(target_arch = "x86_64")]
    // SAFETY: AVX2 and FMA are present; the sizes agree (checked above).
    unsafe {
        simd::forward_view(lines, lv, out)
    }
}

/// The back projection of views planned along one axis: `out` (`count` lines of `len` values, the
/// lines of [`WideLines`]) += Σ over `(lv, row)` of the view's transpose applied to its data row.
/// Lines run in parallel; `cancel` is checked once per line.
///
/// # Panics
/// If a plan disagrees with `count`, `len` or its data row, or the CPU lacks AVX2 and FMA.
pub fn back_lines(
    group: &[(&LineView, &[f32])],
    count: usize,
    len: usize,
    out: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    back_lines_with(group, count, len, out, cancel, wide_available())
}

/// [`back_lines`] with the 16-pixel AVX-512F kernel when `wide` (which must then be available), else
/// the 8-pixel AVX2 one.
#[allow(unsafe_code)]
fn back_lines_with(
    group: &[(&LineView, &[f32])],
    count: usize,
    len: usize,
    out: &mut [f32],
    cancel: &Cancel,
    wide: bool,
) -> Result<(), ReconError> {
    assert!(!wide || wide_available(), "the wide kernel needs AVX-512F");
    assert!(
        out.len() == count * len
            && group
                .iter()
                .all(|(lv, row)| lv.lines() == count && lv.len == len && row.len() == lv.count),
        "view plans, data rows and lines disagree"
    );
    assert!(available(), "the line kernels need AVX2 and FMA");
    if group.is_empty() || len == 0 {
        return Ok(());
    }
    // Each view's data in sorted ray order, with one zero before (ray −1) and 39 after.
    let rows: Vec<Vec<f32>> = group
        .par_iter()
        .map(|(lv, row)| {
            let mut r = vec![0.0f32; lv.count + 40];
            for (k, v) in r[1..=lv.count].iter_mut().enumerate() {
                *v = row[lv.element(k)];
            }
            r
        })
        .collect();
    const LINES_PER_TASK: usize = 4;
    // Pixels per kernel step.
    let step = if wide { 16 } else { 8 };
    let padded = len.div_ceil(step) * step;
    out.par_chunks_mut(len * LINES_PER_TASK)
        .enumerate()
        .try_for_each(|(task, block)| {
            let mut scratch = vec![0.0f32; step + padded];
            for (l, dst) in block.chunks_exact_mut(len).enumerate() {
                cancel.check()?;
                let i = task * LINES_PER_TASK + l;
                scratch.fill(0.0);
                for ((lv, _), r) in group.iter().zip(&rows) {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: AVX2 and FMA are present, and AVX-512F where `wide`; `scratch` holds
                    // step + padded values, `r` holds count + 40, and the plan's step lies in
                    // [S_MIN, S_MAX].
                    unsafe {
                        let b = lv.b[i];
                        match (wide, lv.s < ONE_RAY) {
                            (true, true) => {
                                simd::back_line16::<true>(&mut scratch, padded, r, lv, b)
                            }
                            (true, false) => {
                                simd::back_line16::<false>(&mut scratch, padded, r, lv, b)
                            }
                            (false, true) => {
                                simd::back_line::<true>(&mut scratch, padded, r, lv, b)
                            }
                            (false, false) => {
                                simd::back_line::<false>(&mut scratch, padded, r, lv, b)
                            }
                        }
                    }
                }
                for (d, v) in dst.iter_mut().zip(&scratch[step..]) {
                    *d += v;
                }
            }
            Ok(())
        })
}

/// The (pixel, weight) pairs of sorted ray `k` on line `i`, as the kernels compute them: pixels
/// `⌊t⌋` and `⌊t⌋ + 1` (either may lie outside `0 .. len`). The reference of the tests.
pub fn pairs(lv: &LineView, i: usize, k: usize) -> [(i64, f32); 2] {
    let t = lv.b[i] + k as f32 * lv.s;
    let j = t.floor();
    let w1 = (t - j) * lv.weight;
    [(j as i64, lv.weight - w1), (j as i64 + 1, w1)]
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod simd {
    use std::arch::x86_64::*;

    use super::{LineView, PAD, WideLines};
    use crate::recon::pairs::{lanes, select16};

    /// # Safety
    /// AVX2 and FMA must be available; `lines` and `lv` must agree and `out.len() == lv.count`.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn forward_view(lines: &WideLines, lv: &LineView, out: &mut [f32]) {
        let m = lv.count;
        let vs = _mm256_set1_ps(lv.s);
        let vw = _mm256_set1_ps(lv.weight);
        let data = lines.data.as_ptr();
        // The window [base, base + 17) stays inside the data for base ∈ [−PAD, len + PAD − 17].
        let (lowest, highest) = (-(PAD as isize), (lines.len + PAD - 17) as isize);
        let mut sums = [0.0f32; 8];
        for first in (0..m).step_by(8) {
            let ks = _mm256_mul_ps(lanes(first as f32), vs);
            let (lo, hi) = lv.group_lines(first);
            let mut acc0 = _mm256_setzero_ps();
            let mut acc1 = _mm256_setzero_ps();
            for (i, &b) in lv.b.iter().enumerate().take(hi).skip(lo) {
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
                out[lv.element(first + l)] = v;
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
    fn first_rays16(
        q: __m512,
        b: __m512,
        s: __m512,
        inv_s: __m512,
        count: i32,
    ) -> (__m512i, __m512) {
        let one = _mm512_set1_ps(1.0);
        let est = _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(
            _mm512_mul_ps(_mm512_sub_ps(q, b), inv_s),
        );
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
        let count = lv.count as i32;
        let (vb, vs, vw) = (
            _mm512_set1_ps(b),
            _mm512_set1_ps(lv.s),
            _mm512_set1_ps(lv.weight),
        );
        let inv_s = _mm512_set1_ps(1.0 / lv.s);
        let (one, onef) = (_mm512_set1_epi32(1), _mm512_set1_ps(1.0));
        let sixteen = _mm512_set1_ps(16.0);
        let rp = r.as_ptr();
        let ap = acc.as_mut_ptr();
        let lanes16 = _mm512_setr_ps(
            0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
        );
        let mut q = _mm512_add_ps(_mm512_set1_ps(-16.0), lanes16);
        let mut c_prev = _mm512_setzero_si512();
        for at in (0..=n16).step_by(16) {
            let (k, t) = first_rays16(q, vb, vs, inv_s, count);
            let q1 = _mm512_add_ps(q, onef);
            let any = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t, q1);
            // 16 pixels hold at most ⌊15/S_MIN⌋ + 2 = 27 rays: all in r[base + 1 ..][0 .. 32].
            let base = _mm_cvtsi128_si32(_mm512_castsi512_si128(k));
            debug_assert!((-1..=count).contains(&base));
            let rel = _mm512_sub_epi32(k, _mm512_set1_epi32(base));
            // SAFETY: base + 1 ∈ [0, count + 1] and r holds count + 40 values.
            let (lo, hi) = unsafe {
                let p = rp.add((base + 1) as usize);
                (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)))
            };
            let rv = _mm512_maskz_permutex2var_ps(any, lo, rel, hi);
            let w1 = _mm512_mul_ps(_mm512_sub_ps(t, q), vw);
            let mut a = _mm512_mul_ps(rv, _mm512_sub_ps(vw, w1));
            let mut c = _mm512_mul_ps(rv, w1);
            if TWO {
                let k2 = _mm512_add_epi32(k, one);
                let t2 = _mm512_add_ps(vb, _mm512_mul_ps(_mm512_cvtepi32_ps(k2), vs));
                let in_bin = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t2, q1);
                let r2 = _mm512_maskz_permutex2var_ps(in_bin, lo, _mm512_add_epi32(rel, one), hi);
                let w1 = _mm512_mul_ps(_mm512_sub_ps(t2, q), vw);
                a = _mm512_fmadd_ps(r2, _mm512_sub_ps(vw, w1), a);
                c = _mm512_fmadd_ps(r2, w1, c);
            }
            let c = _mm512_castps_si512(c);
            let c_before = _mm512_castsi512_ps(_mm512_alignr_epi32::<15>(c, c_prev));
            // SAFETY: at ≤ n16 and acc holds 16 + n16 values.
            unsafe {
                let p = ap.add(at);
                _mm512_storeu_ps(
                    p,
                    _mm512_add_ps(_mm512_loadu_ps(p), _mm512_add_ps(a, c_before)),
                );
            }
            c_prev = c;
            q = _mm512_add_ps(q, sixteen);
        }
    }
}

#[cfg(test)]
mod tests {
    //! The kernels against a scalar sum over [`pairs`] (the same pairs, summed in another order):
    //! parallel views at many angles (both axes, both ray orders), rectangular pixels, detector
    //! offsets, steps below 1 (pixels with two rays) and above; the AVX2 and AVX-512F back kernels
    //! both; and the exact adjoint.
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::recon::geometry::{Angles, FanBeam, FanDetector, ParallelBeam};

    fn grid() -> ImageGrid {
        ImageGrid {
            nx: 45,
            ny: 38,
            dx_mm: 1.0,
            dy_mm: 0.8,
            centre_mm: [0.6, -0.3],
        }
    }

    fn parallel(spacing: f64, count: usize, offset: f64) -> Views2 {
        ParallelBeam {
            angles: Angles::uniform(37, 360.0),
            det_count: count,
            det_spacing_mm: spacing,
            det_offset_mm: offset,
        }
        .to_views()
        .unwrap()
    }

    /// Every planned view of the test geometries (steps from 0.6 to 1.85 pixels).
    fn planned() -> Vec<(Views2, Vec<LineView>)> {
        let grid = grid();
        [
            (0.62, 77, 0.4),
            (0.9, 61, -1.3),
            (1.25, 41, 2.0),
            (1.0, 9, 0.0),
        ]
        .into_iter()
        .map(|(du, m, off)| {
            let views = parallel(du, m, off);
            let plans = (0..views.views.len())
                .filter_map(|v| LineView::plan(&views, v, &grid))
                .collect();
            (views, plans)
        })
        .collect()
    }

    fn random(n: usize, rng: &mut StdRng) -> Vec<f32> {
        (0..n).map(|_| rng.random::<f32>() - 0.2).collect()
    }

    /// Value of pixel `j` of line `i` of `image`, zero outside.
    fn pixel(image: &[f32], lv: &LineView, i: usize, j: i64) -> f32 {
        let g = grid();
        if j < 0 || j as usize >= lv.len {
            return 0.0;
        }
        let j = j as usize;
        if lv.along_x {
            image[j * g.nx + i]
        } else {
            image[i * g.nx + j]
        }
    }

    fn forward_reference(image: &[f32], lv: &LineView) -> Vec<f32> {
        let mut out = vec![0.0f32; lv.count];
        for k in 0..lv.count {
            let mut acc = 0.0f64;
            for i in 0..lv.lines() {
                for (j, w) in pairs(lv, i, k) {
                    acc += f64::from(pixel(image, lv, i, j) * w);
                }
            }
            out[lv.element(k)] = acc as f32;
        }
        out
    }

    /// Line layout (`count × len`) of Σ over the views of the transpose applied to `row`.
    fn back_reference(lv: &LineView, row: &[f32], out: &mut [f64]) {
        for i in 0..lv.lines() {
            for k in 0..lv.count {
                for (j, w) in pairs(lv, i, k) {
                    if j >= 0 && (j as usize) < lv.len {
                        out[i * lv.len + j as usize] += f64::from(row[lv.element(k)] * w);
                    }
                }
            }
        }
    }

    fn close(got: &[f32], want: &[f32], tol: f32) {
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-30);
        for (k, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= tol * scale,
                "{k}: {a} vs {b} (scale {scale})"
            );
        }
    }

    #[test]
    fn plans_take_parallel_views_with_steps_in_range() {
        let grid = grid();
        let sets = planned();
        let all = |i: usize| sets[i].1.len() == sets[i].0.views.len();
        // Every view of three spacings; at 1.25 mm the steepest views (1.87 pixels) are left out.
        assert!(all(0) && all(1) && all(3));
        assert!(sets[2].1.len() >= 30 && !all(2));
        let plans: Vec<&LineView> = sets.iter().flat_map(|(_, p)| p).collect();
        for (x, rev) in [(true, true), (true, false), (false, true), (false, false)] {
            assert!(plans.iter().any(|p| p.along_x == x && p.reversed == rev));
        }
        assert!(plans.iter().all(|p| (S_MIN..=S_MAX).contains(&p.s)));
        // Steps below S_MIN or above S_MAX, a single ray and fan views are left to the ray kernels.
        let none = |views: &Views2| {
            (0..views.views.len()).all(|v| LineView::plan(views, v, &grid).is_none())
        };
        assert!(none(&parallel(0.3, 61, 0.0)));
        assert!(none(&parallel(2.5, 61, 0.0)));
        assert!(none(&parallel(1.0, 1, 0.0)));
        let fan = FanBeam {
            angles: Angles::uniform(8, 360.0),
            dso_mm: 100.0,
            dsd_mm: 150.0,
            detector: FanDetector::Flat {
                count: 61,
                spacing_mm: 1.0,
                offset_mm: 0.0,
            },
            centre_mm: [0.0, 0.0],
        }
        .to_views()
        .unwrap();
        assert!(none(&fan));
    }

    #[test]
    fn forward_matches_the_pair_sums() {
        if !available() {
            println!("skipped: the AVX2 + FMA line kernels (this CPU lacks AVX2 or FMA)");
            return;
        }
        let g = grid();
        let mut rng = StdRng::seed_from_u64(11);
        let image = random(g.nx * g.ny, &mut rng);
        let rows = WideLines::from_image(&image, g.nx, g.ny, false);
        let cols = WideLines::from_image(&image, g.nx, g.ny, true);
        for (_, plans) in planned() {
            for lv in &plans {
                let mut got = vec![f32::NAN; lv.count];
                forward_view(if lv.along_x { &cols } else { &rows }, lv, &mut got);
                close(&got, &forward_reference(&image, lv), 1e-5);
            }
        }
    }

    #[test]
    fn back_kernels_match_the_pair_sums() {
        if !available() {
            println!("skipped: the AVX2 + FMA line kernels (this CPU lacks AVX2 or FMA)");
            return;
        }
        let g = grid();
        let mut rng = StdRng::seed_from_u64(12);
        let mut two_ray_pixels = 0;
        for (_, plans) in planned() {
            for along_x in [false, true] {
                let group: Vec<&LineView> = plans.iter().filter(|p| p.along_x == along_x).collect();
                let rows: Vec<Vec<f32>> =
                    group.iter().map(|lv| random(lv.count, &mut rng)).collect();
                let (count, len) = if along_x { (g.nx, g.ny) } else { (g.ny, g.nx) };
                let mut want = vec![0.0f64; count * len];
                for (lv, row) in group.iter().zip(&rows) {
                    back_reference(lv, row, &mut want);
                    // Pixels whose bin ⌊t⌋ = q holds two rays (steps below 1).
                    for i in 0..lv.lines() {
                        let bins: Vec<i64> = (0..lv.count).map(|k| pairs(lv, i, k)[0].0).collect();
                        two_ray_pixels += bins.windows(2).filter(|w| w[0] == w[1]).count();
                    }
                }
                let want: Vec<f32> = want.iter().map(|&v| v as f32).collect();
                let items: Vec<(&LineView, &[f32])> = group
                    .iter()
                    .copied()
                    .zip(rows.iter().map(Vec::as_slice))
                    .collect();
                for wide in [false, true] {
                    if wide && !wide_available() {
                        println!(
                            "skipped: the 16-pixel AVX-512F back kernel (this CPU lacks AVX-512F)"
                        );
                        continue;
                    }
                    let mut got = vec![0.5f32; count * len];
                    back_lines_with(&items, count, len, &mut got, &Cancel::new(), wide).unwrap();
                    let got: Vec<f32> = got.iter().map(|v| v - 0.5).collect();
                    close(&got, &want, 2e-5);
                }
            }
        }
        assert!(
            two_ray_pixels > 100,
            "{two_ray_pixels} pixels with two rays"
        );
    }

    #[test]
    fn the_line_pair_is_an_exact_adjoint() {
        if !available() {
            println!("skipped: the AVX2 + FMA line kernels (this CPU lacks AVX2 or FMA)");
            return;
        }
        let g = grid();
        let mut rng = StdRng::seed_from_u64(13);
        let x = random(g.nx * g.ny, &mut rng);
        let wide_lines = [
            WideLines::from_image(&x, g.nx, g.ny, false),
            WideLines::from_image(&x, g.nx, g.ny, true),
        ];
        for (_, plans) in planned() {
            for lv in &plans {
                let y = random(lv.count, &mut rng);
                let mut ax = vec![0.0f32; lv.count];
                forward_view(&wide_lines[usize::from(lv.along_x)], lv, &mut ax);
                let (count, len) = (lv.lines(), lv.len);
                for wide in [false, true] {
                    if wide && !wide_available() {
                        println!(
                            "skipped: the 16-pixel AVX-512F back kernel (this CPU lacks AVX-512F)"
                        );
                        continue;
                    }
                    let mut aty = vec![0.0f32; count * len];
                    back_lines_with(&[(lv, &y)], count, len, &mut aty, &Cancel::new(), wide)
                        .unwrap();
                    let lhs: f64 = ax.iter().zip(&y).map(|(a, b)| f64::from(a * b)).sum();
                    let rhs: f64 = (0..count)
                        .flat_map(|i| (0..len).map(move |j| (i, j)))
                        .map(|(i, j)| f64::from(aty[i * len + j] * pixel(&x, lv, i, j as i64)))
                        .sum();
                    let norm = ax.iter().map(|v| f64::from(v * v)).sum::<f64>().sqrt()
                        * y.iter().map(|v| f64::from(v * v)).sum::<f64>().sqrt();
                    assert!((lhs - rhs).abs() <= 1e-6 * norm, "{lhs} vs {rhs}");
                }
            }
        }
    }

    #[test]
    fn cancelling_stops_the_back_projection() {
        if !available() {
            println!("skipped: the AVX2 + FMA line kernels (this CPU lacks AVX2 or FMA)");
            return;
        }
        let sets = planned();
        let lv = &sets[1].1[0];
        let row = vec![1.0f32; lv.count];
        let cancel = Cancel::new();
        cancel.cancel();
        let mut out = vec![0.0f32; lv.lines() * lv.len];
        let err = back_lines(&[(lv, &row)], lv.lines(), lv.len, &mut out, &cancel).unwrap_err();
        assert!(matches!(err, ReconError::Canceled), "{err:?}");
    }
}
