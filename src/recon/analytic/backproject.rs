//! Voxel-driven backprojection kernels: one image row (or volume row along x) against one filtered view.
//!
//! Filtered views are stored with two zero samples on each side of every detector row (and, in 3D, two
//! zero rows above and below), so a detector position is clamped into the stored range and reads zeros
//! outside the detector: no bounds checks are needed in the hot loop. Positions are in stored samples
//! (detector index + [`PAD`]). The per-view constants (angular weight, distance weights) are folded into
//! the stored values, so the kernels only interpolate and add. On x86-64 CPUs with AVX2 and FMA the
//! public kernels run the vector forms of `super::backproject_x86`; the `*_scalar` forms are the portable reference.

/// Zero samples stored on each side of a filtered detector row.
pub const PAD: usize = 2;

/// Clamp a stored position into `[0, hi]` (NaN goes to 0) and split it into index and fraction.
#[inline(always)]
pub(super) fn split(pos: f32, hi: f32) -> (usize, f32) {
    let p = if pos > 0.0 { pos } else { 0.0 };
    let p = if p < hi { p } else { hi };
    let i = p as usize;
    (i, p - i as f32)
}

/// Linear interpolation of `q` at `pos`; `q.len() ≥ 2`.
#[inline(always)]
#[allow(unsafe_code)]
fn lerp(q: &[f32], pos: f32) -> f32 {
    debug_assert!(q.len() >= 2);
    let (i, f) = split(pos, (q.len() - 2) as f32);
    // SAFETY: `split` clamps the position to [0, len − 2], so i ≤ len − 2 and i + 1 ≤ len − 1.
    let (a, b) = unsafe { (*q.get_unchecked(i), *q.get_unchecked(i + 1)) };
    a + f * (b - a)
}

/// Parallel beam: `acc[i] += q(pos0 + i·dpos)`.
#[allow(unsafe_code)]
pub fn parallel_row(acc: &mut [f32], q: &[f32], pos0: f32, dpos: f32) {
    if q.len() < 2 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if super::backproject_x86::available(q.len()) {
        let wide = super::backproject_x86::wide_available();
        // SAFETY: AVX2 and FMA (and AVX-512F where `wide`) are present, checked at run time, and
        // q.len() fits an i32 index.
        unsafe { super::backproject_x86::parallel_row(acc, q, pos0, dpos, wide) };
        return;
    }
    parallel_row_scalar(acc, q, pos0, dpos);
}

/// The portable (reference) form of [`parallel_row`].
pub fn parallel_row_scalar(acc: &mut [f32], q: &[f32], pos0: f32, dpos: f32) {
    if q.len() < 2 {
        return;
    }
    for (i, a) in acc.iter_mut().enumerate() {
        *a += lerp(q, pos0 + i as f32 * dpos);
    }
}

/// The line of one image row seen from one view: distance along the central ray `lc`, lateral offset
/// `lat` (and `latv` in 3D), all affine in the column index.
#[derive(Debug, Clone, Copy)]
pub struct RowLine {
    pub lc0: f32,
    pub dlc: f32,
    pub lat0: f32,
    pub dlat: f32,
    pub latv0: f32,
    pub dlatv: f32,
}

/// Smallest distance from the source a voxel may have; closer ones (or behind the source) add nothing.
pub const MIN_DEPTH: f32 = 1e-3;

/// Divergent beam on one detector row: `acc[i] += q(a·lat/lc + b) / lc²`.
#[allow(unsafe_code)]
pub fn fan_row(acc: &mut [f32], q: &[f32], line: &RowLine, a: f32, b: f32) {
    if q.len() < 2 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if super::backproject_x86::available(q.len()) {
        let wide = super::backproject_x86::wide_available();
        // SAFETY: AVX2 and FMA (and AVX-512F where `wide`) are present, checked at run time, and
        // q.len() fits an i32 index.
        unsafe { super::backproject_x86::fan_row(acc, q, line, a, b, wide) };
        return;
    }
    fan_row_scalar(acc, q, line, a, b);
}

/// The portable (reference) form of [`fan_row`].
pub fn fan_row_scalar(acc: &mut [f32], q: &[f32], line: &RowLine, a: f32, b: f32) {
    if q.len() < 2 {
        return;
    }
    for (i, out) in acc.iter_mut().enumerate() {
        let x = i as f32;
        let lc = line.lc0 + x * line.dlc;
        let inv = if lc > MIN_DEPTH { 1.0 / lc } else { 0.0 };
        let lat = line.lat0 + x * line.dlat;
        *out += inv * inv * lerp(q, lat * inv * a + b);
    }
}

/// A filtered cone-beam projection: `rows × width` values, row-major, zero-padded by [`PAD`] on all sides.
#[derive(Debug, Clone, Copy)]
pub struct Panel<'a> {
    pub q: &'a [f32],
    pub width: usize,
    pub rows: usize,
}

/// Cone beam: `acc[i] += q(au·lat/lc + bu, av·latv/lc + bv) / lc²` (bilinear).
#[allow(unsafe_code)]
pub fn cone_row(acc: &mut [f32], panel: Panel<'_>, line: &RowLine, map: [f32; 4]) {
    let Panel { q, width, rows } = panel;
    if width < 2 || rows < 2 || q.len() < width * rows {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if super::backproject_x86::available(width * rows) {
        // SAFETY: AVX2 and FMA are present (checked at run time), q holds width·rows ≥ 4 values and
        // width·rows fits an i32 index.
        unsafe { super::backproject_x86::cone_row(acc, panel, line, map) };
        return;
    }
    cone_row_scalar(acc, panel, line, map);
}

/// The portable (reference) form of [`cone_row`]; `map` is `[au, bu, av, bv]`.
#[allow(unsafe_code)]
pub fn cone_row_scalar(acc: &mut [f32], panel: Panel<'_>, line: &RowLine, map: [f32; 4]) {
    let Panel { q, width, rows } = panel;
    if width < 2 || rows < 2 || q.len() < width * rows {
        return;
    }
    let [au, bu, av, bv] = map;
    let (hu, hv) = ((width - 2) as f32, (rows - 2) as f32);
    for (i, out) in acc.iter_mut().enumerate() {
        let x = i as f32;
        let lc = line.lc0 + x * line.dlc;
        let inv = if lc > MIN_DEPTH { 1.0 / lc } else { 0.0 };
        let (iu, fu) = split((line.lat0 + x * line.dlat) * inv * au + bu, hu);
        let (iv, fv) = split((line.latv0 + x * line.dlatv) * inv * av + bv, hv);
        let k = iv * width + iu;
        // SAFETY: iu ≤ width − 2 and iv ≤ rows − 2, so k + width + 1 ≤ (rows − 1)·width + width − 1
        // = rows·width − 1 < q.len().
        let (q00, q01, q10, q11) = unsafe {
            (
                *q.get_unchecked(k),
                *q.get_unchecked(k + 1),
                *q.get_unchecked(k + width),
                *q.get_unchecked(k + width + 1),
            )
        };
        let top = q00 + fu * (q01 - q00);
        let bottom = q10 + fu * (q11 - q10);
        *out += inv * inv * (top + fv * (bottom - top));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Safe reference: linear interpolation with zero outside the samples `PAD..len − PAD`... in f64.
    fn reference_at(q: &[f32], pos: f64) -> f64 {
        let hi = (q.len() - 2) as f64;
        let p = pos.clamp(0.0, hi);
        let i = p.floor() as usize;
        let f = p - i as f64;
        q[i] as f64 * (1.0 - f) + q[i + 1] as f64 * f
    }

    type ParallelKernel = Box<dyn Fn(&mut [f32], &[f32], f32, f32)>;
    type FanKernel = Box<dyn Fn(&mut [f32], &[f32], &RowLine, f32, f32)>;

    /// The vector forms this CPU runs, made by `form(wide)`: the AVX2 kernel with 16-sample windows and,
    /// with AVX-512F, the one with 32/64-sample windows.
    fn simd_forms<K>(form: impl Fn(bool) -> K) -> Vec<(&'static str, K)> {
        let mut forms = Vec::new();
        #[cfg(target_arch = "x86_64")]
        for wide in [false, true] {
            if super::super::backproject_x86::available(1 << 20)
                && (!wide || super::super::backproject_x86::wide_available())
            {
                forms.push((if wide { "avx-512" } else { "avx2" }, form(wide)));
            } else {
                println!(
                    "skipped: the {} backprojection rows (this CPU lacks them)",
                    if wide { "AVX-512F" } else { "AVX2 + FMA" }
                );
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = form;
        forms
    }

    /// The public kernel, the scalar reference and every vector form, so that every path runs
    /// whichever the public kernel picks.
    #[allow(unsafe_code)]
    fn parallel_kernels() -> Vec<(&'static str, ParallelKernel)> {
        let mut kernels: Vec<(&'static str, ParallelKernel)> = vec![
            ("public", Box::new(parallel_row)),
            ("scalar", Box::new(parallel_row_scalar)),
        ];
        kernels.extend(simd_forms(|wide| -> ParallelKernel {
            Box::new(move |acc, q, pos0, dpos| {
                // SAFETY: `simd_forms` checked the features; the tests' rows are short.
                unsafe { super::super::backproject_x86::parallel_row(acc, q, pos0, dpos, wide) }
            })
        }));
        kernels
    }

    /// As [`parallel_kernels`], for [`fan_row`].
    #[allow(unsafe_code)]
    fn fan_kernels() -> Vec<(&'static str, FanKernel)> {
        let mut kernels: Vec<(&'static str, FanKernel)> = vec![
            ("public", Box::new(fan_row)),
            ("scalar", Box::new(fan_row_scalar)),
        ];
        kernels.extend(simd_forms(|wide| -> FanKernel {
            Box::new(move |acc, q, line, a, b| {
                // SAFETY: `simd_forms` checked the features; the tests' rows are short.
                unsafe { super::super::backproject_x86::fan_row(acc, q, line, a, b, wide) }
            })
        }));
        kernels
    }

    fn padded_row(n: usize, seed: u32) -> Vec<f32> {
        let mut q = vec![0.0f32; n + 2 * PAD];
        for (k, v) in q[PAD..PAD + n].iter_mut().enumerate() {
            *v = (((k as u32).wrapping_mul(2654435761) ^ seed) % 1000) as f32 / 500.0 - 1.0;
        }
        q
    }

    #[test]
    fn parallel_kernel_matches_the_safe_reference_inside_and_outside_the_detector() {
        let q = padded_row(50, 7);
        for (name, kernel) in parallel_kernels() {
            let mut acc = vec![0.5f32; 83];
            kernel(&mut acc, &q, -12.3, 0.91);
            for (i, a) in acc.iter().enumerate() {
                let want = 0.5 + reference_at(&q, -12.3 + i as f64 * 0.91);
                assert!((*a as f64 - want).abs() < 1e-5, "{name} {i}: {a} vs {want}");
            }
        }
    }

    /// Steps small enough for the vector kernels' 16-sample windows and too large for them, rising
    /// and falling, rows that start or end outside the detector (clamped positions) and rows longer
    /// than the detector, so that every path of the kernels (window, gather, tails) is compared.
    #[test]
    fn parallel_kernel_matches_the_reference_for_every_step_and_direction() {
        let q = padded_row(300, 11);
        for (name, kernel) in parallel_kernels() {
            for dpos in [0.0, 0.3, -0.3, 1.0, -1.5, 1.99, 2.01, -2.6, 4.7, -6.1, 9.5] {
                for pos0 in [-5.0, 0.0, 3.25, 21.7, 44.0, 150.0, 290.0] {
                    let mut acc = vec![0.25f32; 77];
                    kernel(&mut acc, &q, pos0, dpos);
                    for (i, a) in acc.iter().enumerate() {
                        let pos = pos0 as f64 + i as f64 * dpos as f64;
                        let want = 0.25 + reference_at(&q, pos);
                        // f32 positions carry ~1e-7 of the terms' size in error; samples differ by ≤ 2.
                        let size = pos0.abs() as f64 + (i as f64 * dpos as f64).abs();
                        assert!(
                            (*a as f64 - want).abs() < 1e-5 * (1.0 + size / 20.0),
                            "{name}: dpos {dpos}, pos0 {pos0}, {i}: {a} vs {want}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn fan_kernel_matches_the_reference_in_front_of_the_source_for_every_step() {
        let q = padded_row(300, 5);
        // (lc0, dlc, lat0, dlat, a, b): rows moving up to 1, 3 and 6 samples per pixel (the 16- and
        // 32-sample windows and gathers), converging and diverging, in both directions, starting or
        // ending off the detector; all points in front of the source.
        let cases = [
            (40.0, 0.02, -3.0, 0.05, 30.0, 153.5),
            (40.0, -0.2, 5.0, -0.11, 30.0, 133.5),
            (25.0, 0.1, -10.0, 0.6, 40.0, 130.0),
            (60.0, -0.3, 20.0, -0.9, 35.0, 134.0),
            (30.0, 0.0, -1.0, 0.0, 30.0, 20.0),
            (20.0, 0.0, -8.0, 0.5, 120.0, 60.0),
            (20.0, 0.01, 9.0, -0.5, 120.0, 240.0),
            (20.0, 0.0, -8.0, 1.0, 120.0, 10.0),
        ];
        for (lc0, dlc, lat0, dlat, a, b) in cases {
            let line = RowLine {
                lc0,
                dlc,
                lat0,
                dlat,
                latv0: 0.0,
                dlatv: 0.0,
            };
            for (name, kernel) in fan_kernels() {
                let mut acc = vec![0.0f32; 93];
                kernel(&mut acc, &q, &line, a, b);
                for (i, got) in acc.iter().enumerate() {
                    let x = i as f64;
                    let lc = lc0 as f64 + dlc as f64 * x;
                    let lat = lat0 as f64 + dlat as f64 * x;
                    let pos = a as f64 * lat / lc + b as f64;
                    let want = reference_at(&q, pos) / (lc * lc);
                    // Samples differ by at most 2 per sample and f32 positions carry ~1e-6 relative
                    // error; a wrong sample would be off by ~0.1/lc² or more.
                    assert!(
                        (*got as f64 - want).abs() < 2e-6 * (1.0 + pos.abs()) / (lc * lc),
                        "{name}: {line:?}, {i}: {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn fan_kernel_matches_the_safe_reference_and_ignores_points_behind_the_source() {
        let q = padded_row(64, 3);
        let line = RowLine {
            lc0: 30.0,
            dlc: -0.5,
            lat0: -20.0,
            dlat: 0.7,
            latv0: 0.0,
            dlatv: 0.0,
        };
        for (name, kernel) in fan_kernels() {
            let mut acc = vec![0.0f32; 90];
            kernel(&mut acc, &q, &line, 40.0, 33.5);
            for (i, a) in acc.iter().enumerate() {
                let lc = 30.0 - 0.5 * i as f64;
                let want = if lc > MIN_DEPTH as f64 {
                    let lat = -20.0 + 0.7 * i as f64;
                    reference_at(&q, 40.0 * lat / lc + 33.5) / (lc * lc)
                } else {
                    0.0
                };
                assert!(
                    (*a as f64 - want).abs() < 1e-5 * (1.0 + want.abs()),
                    "{name} {i}: {a} vs {want}"
                );
                assert!(a.is_finite());
            }
        }
    }

    #[test]
    fn cone_kernel_matches_the_safe_bilinear_reference_in_front_of_and_behind_the_source() {
        let (w, h) = (20 + 2 * PAD, 12 + 2 * PAD);
        let mut q = vec![0.0f32; w * h];
        for r in PAD..h - PAD {
            let row = padded_row(20, r as u32);
            q[r * w..(r + 1) * w].copy_from_slice(&row);
        }
        // The second row crosses the source plane at x = 50.
        for (lc0, dlc) in [(10.0f32, 0.1f32), (5.0, -0.1)] {
            let line = RowLine {
                lc0,
                dlc,
                lat0: -6.0,
                dlat: 0.3,
                latv0: 2.0,
                dlatv: -0.2,
            };
            for kernel in [cone_row, cone_row_scalar] {
                let mut acc = vec![0.0f32; 61];
                let panel = Panel {
                    q: &q,
                    width: w,
                    rows: h,
                };
                kernel(&mut acc, panel, &line, [15.0, 12.0, 9.0, 8.0]);
                for (i, a) in acc.iter().enumerate() {
                    let x = i as f64;
                    let lc = lc0 as f64 + dlc as f64 * x;
                    if lc <= MIN_DEPTH as f64 {
                        assert_eq!(*a, 0.0, "{i}: behind the source");
                        continue;
                    }
                    let pu = ((-6.0 + 0.3 * x) / lc * 15.0 + 12.0).clamp(0.0, (w - 2) as f64);
                    let pv = ((2.0 - 0.2 * x) / lc * 9.0 + 8.0).clamp(0.0, (h - 2) as f64);
                    let (iu, iv) = (pu.floor() as usize, pv.floor() as usize);
                    let (fu, fv) = (pu - iu as f64, pv - iv as f64);
                    let at = |r: usize, c: usize| q[r * w + c] as f64;
                    let top = at(iv, iu) * (1.0 - fu) + at(iv, iu + 1) * fu;
                    let bottom = at(iv + 1, iu) * (1.0 - fu) + at(iv + 1, iu + 1) * fu;
                    let want = (top * (1.0 - fv) + bottom * fv) / (lc * lc);
                    assert!(
                        (*a as f64 - want).abs() < 1e-6 * (1.0 + 1.0 / (lc * lc)),
                        "lc0 {lc0}, {i}: {a} vs {want}"
                    );
                }
            }
        }
    }
}
