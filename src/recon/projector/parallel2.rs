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

    /// The lowest detector element of sorted rays `rays` (they hold a contiguous run of elements).
    fn lowest_element(&self, rays: &std::ops::Range<usize>) -> usize {
        if self.reversed {
            self.count - rays.end
        } else {
            rays.start
        }
    }

    /// The lines `[lo, hi)` on which one of the sorted rays `first .. first + width` may touch a
    /// pixel (a superset: the positions of the vector's first and last lanes, with a margin for
    /// rounding).
    fn group_lines(&self, first: usize, width: usize) -> (usize, usize) {
        const MARGIN: f64 = 0.05;
        let s = f64::from(self.s);
        let lane0 = self.c0 + first as f64 * s;
        let lane7 = lane0 + (width.max(1) - 1) as f64 * s;
        let (mut lo, mut hi) = (0.0f64, self.lines() as f64);
        // lane 0 at line i lies below len: (len + m − lane0) − dc·i > 0; the last lane lies above −1:
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

    /// The lines of an `nx` × `ny` image of zeros: columns when `along_x`, else rows.
    pub fn zeros(nx: usize, ny: usize, along_x: bool) -> Self {
        let (count, len) = if along_x { (nx, ny) } else { (ny, nx) };
        let data = vec![0.0f32; PAD + count * (len + PAD)];
        Self { count, len, data }
    }

    /// The lines of `image` (flat `[y][x]`, `nx·ny` values): columns when `along_x`, else rows.
    ///
    /// # Panics
    /// If `image.len() != nx·ny`.
    pub fn from_image(image: &[f32], nx: usize, ny: usize, along_x: bool) -> Self {
        assert_eq!(image.len(), nx * ny, "image must hold nx·ny values");
        let Self {
            count,
            len,
            mut data,
        } = Self::zeros(nx, ny, along_x);
        let stride = len + PAD;
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
pub fn forward_view(lines: &WideLines, lv: &LineView, out: &mut [f32]) {
    forward_view_with(lines, lv, out, wide_available())
}

/// [`forward_view`] with the 16-ray AVX-512F kernel when `wide` (which must then be available), else
/// the 8-ray AVX2 one. Both compute the same values bit for bit.
fn forward_view_with(lines: &WideLines, lv: &LineView, out: &mut [f32], wide: bool) {
    forward_rays(lines, lv, 0..lv.count, out, wide);
}

/// [`forward_view_with`] for sorted rays `rays` only (`rays.start` a multiple of 16): `out` holds
/// their detector elements, the lowest first.
#[allow(unsafe_code)]
fn forward_rays(
    lines: &WideLines,
    lv: &LineView,
    rays: std::ops::Range<usize>,
    out: &mut [f32],
    wide: bool,
) {
    assert!(
        lines.count == lv.lines()
            && lines.len == lv.len
            && rays.start.is_multiple_of(16)
            && rays.start <= rays.end
            && rays.end <= lv.count
            && out.len() == rays.len(),
        "line layout, view plan, rays and data row disagree"
    );
    assert!(available(), "the line kernels need AVX2 and FMA");
    assert!(!wide || wide_available(), "the wide kernel needs AVX-512F");
    #[cfg(target_arch = "x86_64")]
    // SAFETY: AVX2 and FMA are present, and AVX-512F where `wide`; the sizes agree (checked above).
    unsafe {
        if wide {
            simd::forward_view16(lines, lv, rays, out)
        } else {
            simd::forward_view(lines, lv, rays, out)
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (rays, out);
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
                    // SAFETY: AVX2 and FMA are present, and AVX-512F where `wide` (asserted above);
                    // `scratch` holds step + padded values, `r` holds count + 40, and the plan's
                    // step lies in [S_MIN, S_MAX].
                    unsafe { back_line_into(&mut scratch, padded, r, lv, lv.b[i], wide) };
                }
                for (d, v) in dst.iter_mut().zip(&scratch[step..]) {
                    *d += v;
                }
            }
            Ok(())
        })
}

/// Add the back projection of one view's data on the line at position `b` to `scratch` (pixel `q` at
/// `scratch[step + q]` for `q < padded`, `step` = 16 when `wide`, else 8); `r` is the data in sorted ray
/// order from `r[1]`, with a zero before and at least 39 after.
///
/// # Safety
/// The CPU has AVX2 and FMA, and AVX-512F where `wide`; `scratch.len() ≥ step + padded` with `padded`
/// a multiple of `step`, `r.len() ≥ lv.count + 40`, and `lv.s ∈ [S_MIN, S_MAX]` (every plan's).
#[allow(unsafe_code)]
#[inline]
unsafe fn back_line_into(
    scratch: &mut [f32],
    padded: usize,
    r: &[f32],
    lv: &LineView,
    b: f32,
    wide: bool,
) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller's contract is the kernels'.
    unsafe {
        match (wide, lv.s < ONE_RAY) {
            (true, true) => simd::back_line16::<true>(scratch, padded, r, lv, b),
            (true, false) => simd::back_line16::<false>(scratch, padded, r, lv, b),
            (false, true) => simd::back_line::<true>(scratch, padded, r, lv, b),
            (false, false) => simd::back_line::<false>(scratch, padded, r, lv, b),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (scratch, padded, r, lv, b, wide);
}

/// [`back_line_into`] for two data rows on the same line (`first` from `r[0]`, `second` from
/// `r[1]`), sharing the rays' positions where the 16-pixel kernel runs; the same sums as two calls.
///
/// # Safety
/// As [`back_line_into`], for both pairs.
#[allow(unsafe_code)]
#[inline]
unsafe fn back_line_pair_into(
    [first, second]: [&mut [f32]; 2],
    padded: usize,
    r: [&[f32]; 2],
    lv: &LineView,
    b: f32,
    wide: bool,
) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller's contract is the kernels'.
    unsafe {
        match (wide, lv.s < ONE_RAY) {
            (true, true) => simd::back_lines16::<true, 2>([first, second], padded, r, lv, b),
            (true, false) => simd::back_lines16::<false, 2>([first, second], padded, r, lv, b),
            (false, _) => {
                back_line_into(first, padded, r[0], lv, b, false);
                back_line_into(second, padded, r[1], lv, b, false);
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (first, second, padded, r, lv, b, wide);
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
#[path = "parallel2_simd.rs"]
mod simd;

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
#[path = "parallel2_step.rs"]
mod step;

#[path = "parallel2_sweep.rs"]
mod sweep;
pub use sweep::LineSweep;

#[cfg(test)]
#[path = "parallel2_tests.rs"]
mod tests;
