//! SART's single-view updates on the line kernels of [`super`], fused.
//!
//! A SART update with one parallel view is small (one forward and one back projection of a single
//! view), so the passes around the two kernels cost as much as the kernels: copying the image into a
//! line layout for the forward pass, clearing and summing the back projection's layout into an image,
//! then the weighted step and the constraint, each over the whole image. [`LineSweep`] keeps the image
//! in the line layout of the last view (image rows or columns, with the zero margins of
//! [`WideLines`]) and switches layout (a blocked transpose) only when the next view's dominant axis is
//! the other one. The back projection runs line by line, beside the back projection of ones (the
//! view's column sums), and the step `x ← clamp(x + λ·c·g)` follows at once, with `c` the reciprocal
//! column sums (0 where a sum is at most the view's floor): with AVX-512F on each vector of 16
//! pixels as soon as its two sums are complete (they never leave the registers), with AVX2 through
//! two scratch lines. Computing the sums again costs about what reading them back from memory did, and no
//! image-sized array per view is kept. The (pixel, weight) pairs, the data weights and the order of
//! every sum are those of the whole-image passes, so the updates are the same bit for bit.
//!
//! Updates last tens of microseconds, too short to wake sleeping pool threads for: the transposes,
//! the forward projection (by rays) and the back projection with its step (by lines) run in chunks
//! on a [`Team`] of pool threads that spin between updates. Each chunk computes what the whole loop
//! computes for its lines or rays, so an update is the same on any number of threads.

use std::sync::{Mutex, MutexGuard, PoisonError};

use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
use super::step::{sart_line16, step_line};
use super::{
    LineView, ONE_RAY, PAD, WideLines, available, back_line_into, back_line_pair_into,
    forward_rays, wide_available,
};
use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::team::Team;

/// Fewest pixels of an image for which the updates run on a team of threads.
const TEAM_PIXELS: usize = 1 << 14;

/// Most threads besides the caller's on such a team.
const MAX_PARTNERS: usize = 7;

/// Lines per chunk of a transpose and of a back projection with its step (a multiple of 8).
const CHUNK_LINES: usize = 32;

/// Rays per chunk of a forward projection (a multiple of 16).
const CHUNK_RAYS: usize = 64;

/// The constants of one view's step (see [`LineSweep::update`]).
#[derive(Clone, Copy)]
pub(super) struct Step {
    pub floor: f32,
    pub lambda: f32,
    pub lower: Option<f32>,
    pub upper: Option<f32>,
}

/// The state of a SART sweep over single parallel views (see the module docs).
pub struct LineSweep {
    plans: Vec<LineView>,
    nx: usize,
    ny: usize,
    /// The image as rows (`ny` lines of `nx`) and as columns (`nx` lines of `ny`); `along_x` says
    /// which one holds it.
    rows: WideLines,
    cols: WideLines,
    along_x: bool,
    /// Per view: the column sums at or below which a pixel's step weight is 0.
    floors: Vec<f32>,
    /// Pixels per back-kernel step (16 with AVX-512F, else 8).
    step: usize,
    wide: bool,
    /// One view's projection, its data in sorted ray order (a zero before, 39 after), ones in the
    /// same places, and two lines of back projection (of the data, of the ones).
    projection: Vec<f32>,
    data: Vec<f32>,
    ones: Vec<f32>,
}

impl LineSweep {
    /// The sweep over `plans` (one per view, all of one `nx` × `ny` grid). `floor` gives, from the
    /// largest column sum of a view, the sums at or below which its pixels get no step. `None` where
    /// the CPU lacks the line kernels, a plan is for another grid, or there are no plans.
    #[allow(unsafe_code)]
    pub fn new(
        plans: Vec<LineView>,
        nx: usize,
        ny: usize,
        floor: impl Fn(f32) -> f32 + Sync,
        cancel: &Cancel,
    ) -> Result<Option<Self>, ReconError> {
        let fits = |lv: &LineView| {
            let (lines, len) = if lv.along_x { (nx, ny) } else { (ny, nx) };
            lv.lines() == lines && lv.len == len
        };
        if !available() || plans.is_empty() || !plans.iter().all(fits) || nx == 0 || ny == 0 {
            return Ok(None);
        }
        let wide = wide_available();
        let step = if wide { 16 } else { 8 };
        let count = plans[0].count;
        if plans.iter().any(|lv| lv.count != count) {
            return Ok(None);
        }
        let mut ones = vec![0.0f32; count + 40];
        ones[1..=count].fill(1.0);
        let longest = nx.max(ny).div_ceil(step) * step;
        let floors = plans
            .par_iter()
            .map_init(
                || vec![0.0f32; step + longest],
                |scratch, lv| {
                    cancel.check()?;
                    let padded = lv.len.div_ceil(step) * step;
                    let mut max = 0.0f32;
                    for &b in &lv.b {
                        let scratch = &mut scratch[..step + padded];
                        scratch.fill(0.0);
                        // SAFETY: the CPU has the kernels (checked above, AVX-512F where
                        // `wide`); `scratch` holds step + padded values, `ones` count + 40, and
                        // every plan's step lies in [S_MIN, S_MAX].
                        unsafe { back_line_into(scratch, padded, &ones, lv, b, wide) };
                        max = scratch[step..step + lv.len]
                            .iter()
                            .fold(max, |m, &v| m.max(v));
                    }
                    Ok(floor(max))
                },
            )
            .collect::<Result<Vec<_>, ReconError>>()?;
        Ok(Some(Self {
            plans,
            nx,
            ny,
            rows: WideLines::zeros(nx, ny, false),
            cols: WideLines::zeros(nx, ny, true),
            along_x: false,
            floors,
            step,
            wide,
            projection: vec![0.0; count],
            data: vec![0.0; count + 40],
            ones,
        }))
    }

    /// How many pool threads besides the caller's should run [`Self::update`]'s chunks (see
    /// [`crate::recon::team`]): every other thread of the pool, at most [`MAX_PARTNERS`], for images
    /// of [`TEAM_PIXELS`] or more.
    pub fn partners(&self) -> usize {
        if self.nx * self.ny >= TEAM_PIXELS {
            rayon::current_num_threads()
                .saturating_sub(1)
                .min(MAX_PARTNERS)
        } else {
            0
        }
    }

    /// Use the 8-lane AVX2 kernels even where the CPU has AVX-512F.
    #[cfg(test)]
    pub(crate) fn narrow(&mut self) {
        self.wide = false;
        self.step = 8;
    }

    /// Take the image `x` (`[y][x]`, `nx·ny` values).
    pub fn load(&mut self, x: &[f32]) {
        debug_assert_eq!(x.len(), self.nx * self.ny);
        self.along_x = false;
        let nx = self.nx;
        for (y, row) in x.chunks_exact(nx).enumerate().take(self.ny) {
            let o = self.rows.offset(y);
            self.rows.data[o..o + nx].copy_from_slice(row);
        }
    }

    /// Write the image back to `x`.
    pub fn store(&self, x: &mut [f32]) {
        let nx = self.nx;
        if self.along_x {
            for (y, row) in x.chunks_exact_mut(nx).enumerate().take(self.ny) {
                for (i, v) in row.iter_mut().enumerate() {
                    *v = self.cols.data[self.cols.offset(i) + y];
                }
            }
        } else {
            for (y, row) in x.chunks_exact_mut(nx).enumerate().take(self.ny) {
                let o = self.rows.offset(y);
                row.copy_from_slice(&self.rows.data[o..o + nx]);
            }
        }
    }

    /// Hold the image in the layout of lines along x (columns) when `along_x`, else rows: line `i`
    /// of the other layout, value `j` → line `j`, value `i`, in chunks of destination lines.
    #[allow(unsafe_code)]
    fn hold(&mut self, team: &Team<'_>, along_x: bool) {
        if self.along_x == along_x {
            return;
        }
        let (from, to) = if along_x {
            (&self.rows, &mut self.cols)
        } else {
            (&self.cols, &mut self.rows)
        };
        let (count, len, stride) = (from.count, from.len, to.stride());
        // Blocks of 8 × 8 by AVX transposes (`full_i` × `full_j` values), the edges value by value.
        let (full_i, full_j) = if cfg!(target_arch = "x86_64") {
            (count / 8 * 8, len / 8 * 8)
        } else {
            (0, 0)
        };
        let chunks = pieces(&mut to.data[PAD..], stride * CHUNK_LINES, false);
        team.run(chunks.len(), &|c| {
            let mut dst = piece(&chunks, c);
            let j0 = c * CHUNK_LINES;
            let j1 = (j0 + CHUNK_LINES).min(len);
            #[cfg(target_arch = "x86_64")]
            for jb in (j0..j1.min(full_j)).step_by(8) {
                for i0 in (0..full_i).step_by(8) {
                    // SAFETY: the CPU has AVX2 (checked in `new`); lines i0 .. i0 + 8 of `from`
                    // hold values jb .. jb + 8 ≤ len, and this chunk's lines jb − j0 .. + 8 hold
                    // values i0 .. i0 + 8 ≤ count.
                    unsafe {
                        super::simd::transpose8(
                            from.data[from.offset(i0) + jb..].as_ptr(),
                            from.stride(),
                            dst[(jb - j0) * stride + i0..].as_mut_ptr(),
                            stride,
                        )
                    };
                }
            }
            for j in j0..j1 {
                let first = if j < full_j { full_i } else { 0 };
                for i in first..count {
                    dst[(j - j0) * stride + i] = from.data[from.offset(i) + j];
                }
            }
        });
        self.along_x = along_x;
    }

    /// One update with view `view`: `x ← clamp(x + λ·c ∘ Aᵀ(w ∘ (b − A x)))`, where `b` is the view's
    /// data, `w` its ray weights and `c` its step weights, clamped to `lower` and `upper` where
    /// given. Returns ‖b − A x‖² before the update. The transposes, the forward projection and the
    /// back projection with the step run in chunks on `team` (of lines or of rays; each chunk's
    /// values are those of the whole loop, so the update is the same on any team).
    #[allow(unsafe_code, clippy::too_many_arguments)]
    pub fn update(
        &mut self,
        team: &Team<'_>,
        view: usize,
        b: &[f32],
        w: &[f32],
        lambda: f32,
        lower: Option<f32>,
        upper: Option<f32>,
    ) -> f64 {
        let along_x = self.plans[view].along_x;
        self.hold(team, along_x);
        let lv = &self.plans[view];
        let lines = if along_x {
            &mut self.cols
        } else {
            &mut self.rows
        };
        let wide = self.wide;
        {
            let count = lv.count;
            let parts = pieces(&mut self.projection, CHUNK_RAYS, lv.reversed);
            let lines = &*lines;
            team.run(parts.len(), &|c| {
                let mut out = piece(&parts, c);
                let rays = c * CHUNK_RAYS..((c + 1) * CHUNK_RAYS).min(count);
                forward_rays(lines, lv, rays, &mut out, wide);
            });
        }
        for (k, d) in self.data[1..=lv.count].iter_mut().enumerate() {
            let e = lv.element(k);
            *d = (b[e] - self.projection[e]) * w[e];
        }
        let sum2 = self
            .projection
            .iter()
            .zip(b)
            .map(|(&p, &q)| {
                let r = f64::from(q - p);
                r * r
            })
            .sum::<f64>();
        let step = self.step;
        let (len, stride) = (lv.len, lines.stride());
        let padded = len.div_ceil(step) * step;
        let (data, ones, floor) = (&self.data, &self.ones, self.floors[view]);
        let constants = Step {
            floor,
            lambda,
            lower,
            upper,
        };
        // Line by line: the back projections of the data and of ones, then the line's step; with
        // AVX-512F fused vector by vector, else through two scratch lines.
        let line_step = |[g, sums]: &mut [Vec<f32>; 2], b: f32, line: &mut [f32]| {
            #[cfg(target_arch = "x86_64")]
            if wide {
                // SAFETY: the CPU has AVX-512F (checked in `new`); `data` and `ones` hold count +
                // 40 values, padded ≥ len is a multiple of 16, and the plan's step lies in
                // [S_MIN, S_MAX].
                unsafe {
                    if lv.s < ONE_RAY {
                        sart_line16::<true>(
                            &mut line[..len],
                            padded,
                            [data, ones],
                            lv,
                            b,
                            constants,
                        )
                    } else {
                        sart_line16::<false>(
                            &mut line[..len],
                            padded,
                            [data, ones],
                            lv,
                            b,
                            constants,
                        )
                    }
                }
                return;
            }
            let (g, sums) = (&mut g[..step + padded], &mut sums[..step + padded]);
            g.fill(0.0);
            sums.fill(0.0);
            // SAFETY: the CPU has the kernels (checked in `new`); the scratch lines hold step +
            // padded values, `data` and `ones` count + 40, and the plan's step lies in
            // [S_MIN, S_MAX].
            unsafe { back_line_pair_into([g, sums], padded, [data, ones], lv, b, wide) };
            #[cfg(target_arch = "x86_64")]
            // SAFETY: the CPU has AVX2 (checked in `new`); both scratch lines hold len values
            // from `step` on.
            unsafe {
                step_line(&mut line[..len], &sums[step..], &g[step..], constants)
            };
            #[cfg(not(target_arch = "x86_64"))]
            let _ = (line, constants);
        };
        // Each line is one stride of the layout after the leading margin: its values, then the
        // margin before the next line.
        let chunks = pieces(&mut lines.data[PAD..], stride * CHUNK_LINES, false);
        team.run(chunks.len(), &|c| {
            let mut chunk = piece(&chunks, c);
            let mut scratch = if wide {
                [Vec::new(), Vec::new()]
            } else {
                [vec![0.0f32; step + padded], vec![0.0f32; step + padded]]
            };
            let first = c * CHUNK_LINES;
            for (line, &b) in chunk.chunks_mut(stride).zip(&lv.b[first..]) {
                line_step(&mut scratch, b, line);
            }
        });
        sum2
    }
}

/// `data` cut into pieces of `size` values (the first piece at the end where `from_end`), each
/// behind a lock of its own, so that the chunks of a team step can take them from any thread.
fn pieces(data: &mut [f32], size: usize, from_end: bool) -> Vec<Mutex<&mut [f32]>> {
    if from_end {
        data.rchunks_mut(size).map(Mutex::new).collect()
    } else {
        data.chunks_mut(size).map(Mutex::new).collect()
    }
}

/// Piece `c` of [`pieces`] (each is taken once per step, so the lock is never contended; after a
/// panic elsewhere the piece is still handed out, and the panic reaches the caller).
fn piece<'a, 'b>(pieces: &'a [Mutex<&'b mut [f32]>], c: usize) -> MutexGuard<'a, &'b mut [f32]> {
    pieces[c].lock().unwrap_or_else(PoisonError::into_inner)
}
