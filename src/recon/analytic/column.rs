//! Cone-beam backprojection along z: one line of voxels parallel to the rotation axis against one filtered
//! view.
//!
//! On a planar circular orbit whose detector u axis has no z component, every voxel of a line along z
//! has the same distance from the source along the central ray and the same lateral offset, so it
//! projects into one detector column position (index `iu`, fraction `fu`) with one distance weight,
//! and its row position is affine in z. The kernel then interpolates between two stored detector
//! columns at rows that advance by a fixed step: no division per voxel, and the samples of a vector of
//! voxels lie close together in the column. Views for this kernel are stored by columns
//! ([`ColumnPanel`]), zero-padded by [`PAD`] samples on all sides like the row-major panels of
//! `backproject`. On x86-64 CPUs with AVX2 and FMA (and AVX-512F) the public kernel runs the vector forms
//! of `super::column_x86`; [`cone_column_scalar`] is the portable reference.

use super::backproject::{MIN_DEPTH, PAD, RowLine, split};

/// Values stored after the last column of a [`ColumnPanel`], so that the vector kernels may load a
/// window of samples from any row of the last column.
pub const SLACK: usize = 64;

/// A filtered cone-beam projection stored by detector columns: `cols` columns of `rows` values each
/// (`q[c·rows + r]`), zero-padded by [`PAD`] on all sides, then at least [`SLACK`] more values.
#[derive(Debug, Clone, Copy)]
pub struct ColumnPanel<'a> {
    pub q: &'a [f32],
    pub cols: usize,
    pub rows: usize,
}

impl<'a> ColumnPanel<'a> {
    /// The stored columns `iu` and `iu + 1`, as pointers for the vector kernels.
    ///
    /// # Safety
    /// `iu + 1 < cols` and `cols·rows ≤ q.len()`.
    #[allow(unsafe_code)]
    pub(super) unsafe fn columns(&self, iu: usize) -> (*const f32, *const f32) {
        // SAFETY: iu + 1 < cols and cols·rows ≤ q.len(), so both columns start inside q.
        unsafe {
            let a = self.q.as_ptr().add(iu * self.rows);
            (a, a.add(self.rows))
        }
    }

    /// Whether the panel holds what its sizes promise (the kernels do nothing otherwise).
    fn valid(&self) -> bool {
        self.cols >= 2
            && self.rows >= 2 * PAD
            && self
                .cols
                .checked_mul(self.rows)
                .and_then(|n| n.checked_add(SLACK))
                .is_some_and(|n| n <= self.q.len() && n < i32::MAX as usize)
    }
}

/// One line of voxels along z seen from one view: stored column position `iu + fu`, distance weight
/// `w` (1/lc²) and stored row position `pos0 + k·dpos` of voxel k.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZLine {
    pub iu: usize,
    pub fu: f32,
    pub w: f32,
    pub pos0: f32,
    pub dpos: f32,
}

impl ZLine {
    /// The line of voxels at distance `lc` along the central ray and lateral offset `lat`, whose first
    /// voxel has vertical offset `latv` and whose voxels are `dlatv` apart vertically, on a panel of
    /// `cols` stored columns; `map = [au, bu, av, bv]` maps `lat/lc` and `latv/lc` to stored columns and
    /// rows. `None` where the line adds nothing: at or behind the source, or projecting outside the
    /// stored columns (whose clamped reads are the zero padding). The reference for [`ZLine::row`].
    #[cfg(test)]
    pub fn new(
        lc: f32,
        lat: f32,
        latv: f32,
        dlatv: f32,
        map: [f32; 4],
        cols: usize,
    ) -> Option<Self> {
        if lc.is_nan() || lc <= MIN_DEPTH {
            return None;
        }
        let inv = 1.0 / lc;
        let [au, bu, av, bv] = map;
        let pu = lat * inv * au + bu;
        if pu.is_nan() || pu <= 0.0 || pu >= cols.saturating_sub(2) as f32 {
            return None;
        }
        let iu = pu as usize;
        Some(ZLine {
            iu,
            fu: pu - iu as f32,
            w: inv * inv,
            pos0: latv * inv * av + bv,
            dpos: dlatv * inv * av,
        })
    }

    /// The voxels `k0..k1` (within `0..n`) that can read data, each with its row position inside
    /// `[0, rows − 2]`: the voxels whose position lies in `[0.5, rows − 1.5]`. The bounds carry f32
    /// rounding of about 10⁻⁷ of the row positions involved, far below the half sample of margin on
    /// either side for the steps the kernels' windows take (at most four rows per voxel). Every voxel
    /// outside lies below row 1 or above row `rows − 2`, where the interpolation reads only padding.
    #[cfg(test)]
    pub fn span(&self, n: usize, rows: usize) -> (usize, usize) {
        let (lo, hi) = (0.5f32, rows as f32 - 1.5);
        let (p0, d) = (self.pos0, self.dpos);
        let top = n as f32;
        let (first, last) = if d != 0.0 {
            let inv = 1.0 / d;
            let (a, b) = ((lo - p0) * inv, (hi - p0) * inv);
            (a.min(b), a.max(b))
        } else if p0 >= lo && p0 <= hi {
            (0.0, top)
        } else {
            (1.0, 0.0)
        };
        span_of(first, last, n)
    }

    /// The lines through voxels `x0..x0 + xs` (`xs` ≤ [`ROW_LINES`]) of one row along x of the volume,
    /// handed to `out(i, line, span)` where voxel `x0 + i` adds something: for each, what
    /// [`ZLine::new`] (with `lc`, `lat`, `latv` of the voxel on `row` and the vertical step `dlatv`)
    /// and [`ZLine::span`] (for `n` voxels on `rows` stored rows) give, to the bit. The lines are
    /// computed lane by lane without branches, so that their divisions vectorise; only the lines that
    /// add something are converted to indices.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    pub fn row(
        row: &RowLine,
        (x0, xs): (usize, usize),
        dlatv: f32,
        map: [f32; 4],
        (cols, rows): (usize, usize),
        n: usize,
        mut out: impl FnMut(usize, ZLine, (usize, usize)),
    ) {
        const L: usize = ROW_LINES;
        let [au, bu, av, bv] = map;
        let last_column = cols.saturating_sub(2) as f32;
        let (lo, hi, top) = (0.5f32, rows as f32 - 1.5, n as f32);
        let (mut pu, mut w, mut pos0, mut dpos) =
            ([0.0f32; L], [0.0f32; L], [0.0f32; L], [0.0f32; L]);
        let (mut first, mut last, mut adds) = ([0.0f32; L], [0.0f32; L], [false; L]);
        for i in 0..L {
            let x = (x0 + i) as f32;
            let lc = row.lc0 + x * row.dlc;
            let lat = row.lat0 + x * row.dlat;
            let latv = row.latv0 + x * row.dlatv;
            let inv = 1.0 / lc;
            let p = lat * inv * au + bu;
            // NaN fails every comparison, as in `new`.
            adds[i] = lc > MIN_DEPTH && p > 0.0 && p < last_column;
            pu[i] = p;
            w[i] = inv * inv;
            pos0[i] = latv * inv * av + bv;
            dpos[i] = dlatv * inv * av;
        }
        for i in 0..L {
            let (p0, d) = (pos0[i], dpos[i]);
            let inv = 1.0 / d;
            let (a, b) = ((lo - p0) * inv, (hi - p0) * inv);
            let inside = p0 >= lo && p0 <= hi;
            (first[i], last[i]) = if d != 0.0 {
                (a.min(b), a.max(b))
            } else if inside {
                (0.0, top)
            } else {
                (1.0, 0.0)
            };
        }
        for i in 0..xs.min(L) {
            if !adds[i] {
                continue;
            }
            let (k0, k1) = span_of(first[i], last[i], n);
            if k0 < k1 {
                let iu = pu[i] as usize;
                let line = ZLine {
                    iu,
                    fu: pu[i] - iu as f32,
                    w: w[i],
                    pos0: pos0[i],
                    dpos: dpos[i],
                };
                out(i, line, (k0, k1));
            }
        }
    }
}

/// Lines of one row along x that [`ZLine::row`] sets up together.
pub const ROW_LINES: usize = 8;

/// The voxels `k0..k1` of `n` from the first and last (fractional) voxel positions that read data:
/// k0 = ⌈first⌉ and k1 = ⌊last⌋ + 1, clamped into [0, n] before the conversions (NaN fails both
/// comparisons and gives an empty span).
#[inline]
fn span_of(first: f32, last: f32, n: usize) -> (usize, usize) {
    let top = n as f32;
    let k0 = if first > 0.0 {
        let t = first.min(top);
        let k = t as usize;
        k + usize::from((k as f32) < t)
    } else {
        0
    };
    let k1 = if last >= 0.0 {
        (last.min(top) as usize + 1).min(n)
    } else {
        0
    };
    (k0.min(k1), k1)
}

/// Cone beam along z: `acc[k] += w · Q(iu + fu, pos0 + k·dpos)` (bilinear) for the voxels of
/// [`ZLine::span`]; the others would add zero.
#[cfg(test)]
pub fn cone_column(acc: &mut [f32], panel: ColumnPanel<'_>, line: &ZLine) {
    let span = line.span(acc.len(), panel.rows);
    cone_columns(acc, panel, &[(0, *line, span)]);
}

/// A line of voxels in a block of lines: the index of its first voxel in the block, the line as one
/// view sees it, and its span ([`ZLine::row`]).
pub type Placed = (usize, ZLine, (usize, usize));

/// Cone beam along z for many lines of a block against one panel: `acc[start + k] += w · Q(iu + fu,
/// pos0 + k·dpos)` for the voxels k of each line's span, the spans computed by the caller so that the
/// set-up of many lines can run ahead of their kernels. The panel is checked once and each line as it
/// comes ([`placed`]: a line outside the block or the panel adds nothing); the vector forms take all
/// the lines in one call.
#[allow(unsafe_code)]
pub fn cone_columns(acc: &mut [f32], panel: ColumnPanel<'_>, lines: &[Placed]) {
    if !panel.valid() {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if crate::recon::cpu::avx2_fma() {
        let wide = crate::recon::cpu::avx512f();
        // SAFETY: AVX2 and FMA (and AVX-512F where `wide`) are present, checked at run time; the
        // panel is valid, checked above.
        unsafe { super::column_x86::cone_columns(acc, panel, lines, wide) };
        return;
    }
    for (start, line, span) in lines {
        if let Some(out) = placed(acc, panel, *start, line, *span) {
            cone_column_from(out, span.0, panel, line);
        }
    }
}

/// The voxels `k0..k1` of a line whose first voxel is `acc[start]`, where they lie inside `acc`, the
/// span is not empty and the line reads two stored columns of the panel (`iu + 1 < cols`).
#[inline(always)]
pub(super) fn placed<'a>(
    acc: &'a mut [f32],
    panel: ColumnPanel<'_>,
    start: usize,
    line: &ZLine,
    (k0, k1): (usize, usize),
) -> Option<&'a mut [f32]> {
    if line.iu + 2 > panel.cols || k0 >= k1 {
        return None;
    }
    acc.get_mut(start.checked_add(k0)?..start.checked_add(k1)?)
}

/// The portable (reference) form of [`cone_column`], over every voxel of `acc`.
#[cfg(test)]
pub fn cone_column_scalar(acc: &mut [f32], panel: ColumnPanel<'_>, line: &ZLine) {
    if !panel.valid() || line.iu + 2 > panel.cols {
        return;
    }
    cone_column_from(acc, 0, panel, line);
}

/// [`cone_column_scalar`] for `acc` holding voxels `k0..k0 + acc.len()`; the vector forms' tails.
/// The panel must be valid and `iu + 1 < cols`.
pub(super) fn cone_column_from(acc: &mut [f32], k0: usize, panel: ColumnPanel<'_>, line: &ZLine) {
    let ColumnPanel { q, rows, .. } = panel;
    let start = line.iu * rows;
    let (a, b) = (&q[start..start + rows], &q[start + rows..start + 2 * rows]);
    let hv = (rows - 2) as f32;
    for (j, out) in acc.iter_mut().enumerate() {
        let (iv, fv) = split(line.pos0 + (k0 + j) as f32 * line.dpos, hv);
        let c0 = a[iv] + line.fu * (b[iv] - a[iv]);
        let c1 = a[iv + 1] + line.fu * (b[iv + 1] - a[iv + 1]);
        *out += line.w * (c0 + fv * (c1 - c0));
    }
}

#[cfg(test)]
#[path = "column_tests.rs"]
mod tests;
