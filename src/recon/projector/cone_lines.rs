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
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PlaneStep {
    /// Weights of the first and second volume line.
    pub w0: f32,
    pub w1: f32,
    /// Position of row `r` along the line (voxel units, before padding): `e0 + r·de`.
    pub e0: f32,
    pub de: f32,
}

/// The padded position of row `r`, before clamping: `e0 + r·de + 1` in f32 (`r as u32 as f32` is
/// `r as f32` for rows far fewer than 2³², converted more cheaply).
#[inline(always)]
fn padded(step: &PlaneStep, r: usize) -> f32 {
    step.e0 + r as u32 as f32 * step.de + 1.0
}

/// The padded position of row `r` on a line of `n` voxels, clamped into `[0, n + 1]`: value index
/// `⌊q⌋` and weight `q − ⌊q⌋` of value `⌊q⌋ + 1`.
#[inline(always)]
fn position(step: &PlaneStep, r: usize, hi: f32) -> (usize, f32) {
    let q = padded(step, r).max(0.0).min(hi);
    let i = q as usize;
    (i, q - i as f32)
}

/// The rows of `rows` whose padded position on a line of `len` values is not clamped (lies in
/// `(0, len − 2)`), found from `guess` (a sub-range of `rows` computed in f64 that differs from them
/// by at most a row of rounding at either end). A clamped row reads only zeros and weight-zero
/// values (forward) and writes only padding values and zeros (back), so leaving it out changes no
/// voxel and no row's sum. Positions are monotone in the row, so the rows kept are contiguous.
#[inline(always)]
pub fn reaching(
    step: &PlaneStep,
    guess: Range<usize>,
    rows: Range<usize>,
    len: usize,
) -> Range<usize> {
    let hi = (len - 2) as u32 as f32;
    let inside = |r: usize| {
        let q = padded(step, r);
        q > 0.0 && q < hi
    };
    let mut lo = guess.start.clamp(rows.start, rows.end);
    let mut end = guess.end.clamp(lo, rows.end);
    // Each bound is moved by a first test and only then by a loop: the guess is almost always
    // exact, and the compiler turns these loops into vector searches that cost far more than one
    // test.
    if lo > rows.start && inside(lo - 1) {
        lo -= 1;
        while lo > rows.start && inside(lo - 1) {
            lo -= 1;
        }
    }
    if lo < end && !inside(lo) {
        lo += 1;
        while lo < end && !inside(lo) {
            lo += 1;
        }
    }
    if end < rows.end && inside(end) {
        end += 1;
        while end < rows.end && inside(end) {
            end += 1;
        }
    }
    if end > lo && !inside(end - 1) {
        end -= 1;
        while end > lo && !inside(end - 1) {
            end -= 1;
        }
    }
    lo..end
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
    let len = a.len();
    let b = &b[..len];
    for ((l, x), y) in line[..len].iter_mut().zip(a).zip(b) {
        *l = step.w0 * *x + step.w1 * *y;
    }
    let hi = (len - 2) as f32;
    let line = &line[..len];
    let start = rows.start;
    for (i, out) in acc[rows].iter_mut().enumerate() {
        let (k, f) = position(step, start + i, hi);
        // `k ≤ len − 2` by the clamp, so both reads are in bounds.
        *out += (1.0 - f) * line[k.min(len - 2)] + f * line[(k + 1).min(len - 1)];
    }
}

/// Extra scratch values after each line of the loops' scratch (the forward's line, each of the
/// back's two), which let the AVX-512F form read or add a window of 32 values starting at any value
/// of the line.
pub const SCRATCH_PAD: usize = 32;

/// The stride of the back loops' row order: rows a value or more apart go in order (stride 1);
/// closer rows go even rows first, then odd rows (stride 2), so that neighbouring rows of one pass
/// are a value apart when rows are at least half a voxel apart, which the vector forms use. Where
/// rows are half a voxel apart or more, a voxel's value receives at most two rows, whose sum does
/// not depend on their order; every form follows this order, so all give the same bits.
#[inline(always)]
fn stride(step: &PlaneStep) -> usize {
    if step.de.abs() >= 1.0 { 1 } else { 2 }
}

/// The back loops' scratch `lines` as its two lines, each at least as long as the volume line. The
/// scratch is zero on entry and left zero ([`merge_and_spread`] clears what it reads; values past
/// those are only ever added zeros).
#[inline(always)]
fn split_scratch(lines: &mut [f32], len: usize) -> (&mut [f32], &mut [f32]) {
    let half = lines.len() / 2;
    assert!(half >= len, "back scratch shorter than two lines");
    lines.split_at_mut(half)
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
    let len = a.len();
    let hi = (len - 2) as f32;
    let (first, second) = split_scratch(lines, len);
    let data = &data[..rows.len()];
    let stride = stride(step);
    for parity in 0..stride {
        for i in (parity..data.len()).step_by(stride) {
            let (k, f) = position(step, rows.start + i, hi);
            let k = k.min(len - 2);
            first[k] += (1.0 - f) * data[i];
            second[k] += f * data[i];
        }
    }
    merge_and_spread(a, b, first, second, step);
}

/// `line[e] = first[e] + second[e − 1]`, then `a += w0·line`, `b += w1·line` (over `a.len()` values),
/// clearing the values of `first` and `second` it reads (the rows never reach `second[len − 1]`).
#[inline(always)]
fn merge_and_spread(
    a: &mut [f32],
    b: &mut [f32],
    first: &mut [f32],
    second: &mut [f32],
    step: &PlaneStep,
) {
    let len = a.len();
    let (first, second, b) = (&mut first[..len], &mut second[..len], &mut b[..len]);
    let l = first[0];
    first[0] = 0.0;
    a[0] += step.w0 * l;
    b[0] += step.w1 * l;
    for e in 1..len {
        let l = first[e] + second[e - 1];
        first[e] = 0.0;
        second[e - 1] = 0.0;
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
    /// Compiled with AVX-512F, BMI2 and POPCNT; only where the CPU has them.
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

    /// Forward: `line = w0·a + w1·b` (over `a.len()` values, at least 3), then `acc[r] += ` the line
    /// sampled at row `r`'s position, for `r` in `rows`. `b` and the scratch `line` hold at least
    /// `a.len()` values; with [`SCRATCH_PAD`] more in `line` the AVX-512F form reads the rows' values
    /// from windows of 32 instead of gathering them. Positions are clamped into the padding.
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
            // SAFETY: `Form::Avx512` is only built where the CPU has AVX-512F, BMI2 and POPCNT.
            Form::Avx512 => unsafe { x86::forward_avx512(a, b, line, step, rows, acc) },
            _ => forward_body(a, b, line, step, rows, acc),
        }
    }

    /// Back, the transpose of [`Form::forward`]: the line = the rows' `data` spread at their
    /// positions (`data[i]` belongs to row `rows.start + i`), then `a += w0·line`, `b += w1·line`,
    /// over `a.len()` values (`b` as long). `lines` is scratch of at least twice that, zero on entry
    /// and left zero (callers keep one for every call): the weights
    /// of each row's first and second value are summed apart (so neighbouring rows do not wait on
    /// each other's sums), then merged; with [`SCRATCH_PAD`] more values per line the AVX-512F
    /// form adds whole windows of rows at once.
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
#[path = "cone_lines_x86.rs"]
mod x86;

#[cfg(test)]
mod tests {
    //! Every compiled form against the portable loops, bit for bit, for every length of the last,
    //! partial vector: rows closer than one value (several rows per value, so the back loops spread
    //! some rows one by one), about one apart, farther apart, ascending and descending, and rows
    //! whose positions are clamped into the padding.
    use super::*;

    fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| ((i as u32).wrapping_mul(2_654_435_761) ^ seed) % 1000)
            .map(|v| v as f32 / 250.0 - 1.0)
            .collect()
    }

    #[test]
    fn reaching_keeps_exactly_the_rows_whose_positions_are_not_clamped() {
        let len = 48;
        let hi = (len - 2) as f32;
        for &(e0, de) in &[
            (3.2f32, 0.26f32),
            (-1.0, 0.5),
            (-10.5, 0.93),
            (44.0, -0.61),
            (45.0, -1.0),
            (-3.0, 2.2),
            (-200.0, 0.3),
            (20.0, 0.0),
            (60.0, 0.0),
        ] {
            let step = PlaneStep {
                w0: 0.5,
                w1: 0.5,
                e0,
                de,
            };
            for rows in [0..80usize, 7..31] {
                let want: Vec<usize> = rows
                    .clone()
                    .filter(|&r| {
                        let q = e0 + r as f32 * de + 1.0;
                        q > 0.0 && q < hi
                    })
                    .collect();
                // Guesses off by up to two rows at either end, and empty ones.
                let (lo, end) = match (want.first(), want.last()) {
                    (Some(&lo), Some(&last)) => (lo, last + 1),
                    _ => (rows.start + 3, rows.start + 3),
                };
                for dl in -2i64..=2 {
                    for de_ in -2i64..=2 {
                        let g0 = (lo as i64 + dl).max(0) as usize;
                        let g1 = (end as i64 + de_).max(g0 as i64) as usize;
                        let got: Vec<usize> = reaching(&step, g0..g1, rows.clone(), len).collect();
                        assert_eq!(got, want, "{step:?}, rows {rows:?}, guess {g0}..{g1}");
                    }
                }
            }
        }
    }

    #[test]
    fn every_form_gives_the_portable_values_for_every_tail() {
        let n = 45; // a line of 45 voxels: 48 values with the padding
        let (a, b) = (values(n + 3, 1), values(n + 3, 2));
        let data = values(80, 3);
        for &(e0, de) in &[
            (3.2f32, 0.26f32),
            (-1.7, 0.5),
            (0.4, 0.93),
            (10.1, 1.0),
            (-20.0, 1.7),
            (44.0, -0.61),
            (50.0, -1.4),
            (2.0, 3.1),
            (1.3, 1.96),
            (47.5, -1.0),
            (-3.0, 2.2),
        ] {
            let step = PlaneStep {
                w0: 0.37,
                w1: 0.63,
                e0,
                de,
            };
            for start in [0usize, 3] {
                for end in start..start + 40 {
                    let rows = start..end;
                    let mut want = values(end, 4);
                    let mut line = vec![0.0f32; n + 3];
                    Form::Portable.forward(&a, &b, &mut line, &step, rows.clone(), &mut want);
                    let (mut wa, mut wb) = (a.clone(), b.clone());
                    let mut lines = vec![0.0f32; 2 * (n + 3)];
                    let d = &data[..rows.len()];
                    Form::Portable.back(&mut wa, &mut wb, &mut lines, &step, rows.clone(), d);
                    for form in Form::available() {
                        for pad in [0, SCRATCH_PAD] {
                            let mut line = vec![7.0f32; n + 3 + pad];
                            let mut got = values(end, 4);
                            form.forward(&a, &b, &mut line, &step, rows.clone(), &mut got);
                            assert_eq!(got, want, "{form:?} forward, {step:?}, rows {rows:?}");
                        }
                        // Scratch of two bare lines, and with room for whole windows.
                        for pad in [0, SCRATCH_PAD] {
                            let mut lines = vec![0.0f32; 2 * (n + 3 + pad)];
                            let (mut ga, mut gb) = (a.clone(), b.clone());
                            form.back(&mut ga, &mut gb, &mut lines, &step, rows.clone(), d);
                            assert!(lines.iter().all(|&v| v == 0.0), "{form:?} left scratch");
                            assert_eq!(
                                (ga, gb),
                                (wa.clone(), wb.clone()),
                                "{form:?} back, {step:?}, rows {rows:?}, pad {pad}"
                            );
                        }
                    }
                }
            }
        }
    }
}
