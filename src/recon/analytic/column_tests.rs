use super::*;

/// A panel of `cols × rows` stored columns (pads zero, data in [−1, 1]) and the slack after it.
fn panel_values(cols: usize, rows: usize, seed: u32) -> Vec<f32> {
    let mut q = vec![0.0f32; cols * rows + SLACK];
    for c in PAD..cols - PAD {
        for r in PAD..rows - PAD {
            let h = ((c * rows + r) as u32).wrapping_mul(2654435761) ^ seed;
            q[c * rows + r] = (h % 1000) as f32 / 500.0 - 1.0;
        }
    }
    q
}

/// Safe f64 reference: bilinear interpolation at (iu + fu, clamped row position).
fn reference(q: &[f32], rows: usize, line: &ZLine, k: usize) -> f64 {
    let hv = (rows - 2) as f64;
    let pos = (line.pos0 as f64 + k as f64 * line.dpos as f64).clamp(0.0, hv);
    let iv = pos.floor() as usize;
    let fv = pos - iv as f64;
    let at = |c: usize, r: usize| q[c * rows + r] as f64;
    let fu = line.fu as f64;
    let c0 = at(line.iu, iv) * (1.0 - fu) + at(line.iu + 1, iv) * fu;
    let c1 = at(line.iu, iv + 1) * (1.0 - fu) + at(line.iu + 1, iv + 1) * fu;
    line.w as f64 * (c0 * (1.0 - fv) + c1 * fv)
}

type Kernel = Box<dyn Fn(&mut [f32], ColumnPanel<'_>, &ZLine)>;

/// The public kernel, the scalar reference and every vector form this CPU runs (each called on the
/// whole line, whether or not its step suits it), so that every path is compared.
#[allow(unsafe_code)]
fn kernels() -> Vec<(&'static str, Kernel)> {
    let mut out: Vec<(&'static str, Kernel)> = vec![
        ("public", Box::new(cone_column)),
        ("scalar", Box::new(cone_column_scalar)),
    ];
    #[cfg(target_arch = "x86_64")]
    {
        use super::super::column_x86 as x86;
        // The vector forms are called on the line's span, as the public kernel calls them.
        let span = |acc: &mut [f32], p: ColumnPanel<'_>, l: &ZLine| {
            let (k0, k1) = l.span(acc.len(), p.rows);
            (k0, k1.max(k0))
        };
        if crate::recon::cpu::avx2_fma() {
            out.push((
                "avx2 dispatch",
                Box::new(move |acc, p, l| {
                    let span = span(acc, p, l);
                    unsafe { x86::cone_columns(acc, p, &[(0, *l, span)], false) }
                }),
            ));
            out.push((
                "avx2 pairs",
                Box::new(move |acc, p, l| {
                    let (k0, k1) = span(acc, p, l);
                    unsafe { x86::column_narrow::<false>(&mut acc[k0..k1], k0, p, l) }
                }),
            ));
        } else {
            println!("skipped: the AVX2 column kernels (this CPU lacks AVX2 + FMA)");
        }
        if crate::recon::cpu::avx512f() {
            out.push((
                "avx-512 dispatch",
                Box::new(move |acc, p, l| {
                    let span = span(acc, p, l);
                    unsafe { x86::cone_columns(acc, p, &[(0, *l, span)], true) }
                }),
            ));
        } else {
            println!("skipped: the AVX-512F column kernels (this CPU lacks AVX-512F)");
        }
    }
    out
}

/// Lines rising and falling by up to 7 rows per voxel (so every window width and the pair loads are
/// taken), starting below, inside and above the panel, at the first and last usable column, of lengths
/// that leave tails of every size: every kernel matches the f64 reference.
#[test]
fn every_form_matches_the_bilinear_reference_for_every_step() {
    let (cols, rows) = (13 + 2 * PAD, 150 + 2 * PAD);
    let q = panel_values(cols, rows, 17);
    let panel = ColumnPanel { q: &q, cols, rows };
    for (name, kernel) in kernels() {
        for dpos in [
            0.0f32, 0.3, -0.3, 1.0, -1.6, 1.75, 1.9, -2.5, 3.0, -3.9, 4.2, -7.0,
        ] {
            for pos0 in [-20.0f32, 0.0, 1.5, 40.25, 100.0, 151.9, 170.0] {
                for (iu, fu) in [(0usize, 0.25f32), (5, 0.0), (7, 0.7), (cols - 2, 0.5)] {
                    let line = ZLine {
                        iu,
                        fu,
                        w: 0.8,
                        pos0,
                        dpos,
                    };
                    for n in [1usize, 7, 16, 31, 77] {
                        let mut acc = vec![0.5f32; n];
                        kernel(&mut acc, panel, &line);
                        for (k, a) in acc.iter().enumerate() {
                            let want = 0.5 + reference(&q, rows, &line, k);
                            let size = pos0.abs() as f64 + (k as f64 * dpos as f64).abs();
                            // f32 positions carry ~1e-7 of their size; samples differ by at most 2.
                            assert!(
                                (*a as f64 - want).abs() < 2e-6 * (1.0 + size),
                                "{name}: dpos {dpos}, pos0 {pos0}, iu {iu}, n {n}, k {k}: {a} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }
}

/// The voxels outside `span` read only padding: the public kernel, which skips them, equals the
/// scalar one, which does not, there (exactly zero added).
#[test]
fn voxels_outside_the_span_add_exactly_nothing() {
    let (cols, rows) = (8 + 2 * PAD, 40 + 2 * PAD);
    let q = panel_values(cols, rows, 3);
    let panel = ColumnPanel { q: &q, cols, rows };
    for (pos0, dpos) in [
        (-30.0f32, 0.9f32),
        (60.0, -0.77),
        (2.0, 0.0),
        (-1.0, 0.0),
        (0.6, 2.9),
    ] {
        let line = ZLine {
            iu: 3,
            fu: 0.4,
            w: 1.0,
            pos0,
            dpos,
        };
        let (k0, k1) = line.span(100, rows);
        let mut all = vec![0.0f32; 100];
        cone_column_scalar(&mut all, panel, &line);
        for (k, v) in all.iter().enumerate() {
            if k < k0 || k >= k1 {
                assert_eq!(
                    *v, 0.0,
                    "pos0 {pos0}, dpos {dpos}: voxel {k} outside {k0}..{k1}"
                );
            }
        }
        assert!(all[k0..k1].iter().any(|v| *v != 0.0) || k0 == k1);
        let mut public = vec![0.0f32; 100];
        cone_column(&mut public, panel, &line);
        for (k, (a, b)) in public.iter().zip(&all).enumerate() {
            // The vector forms fuse multiply-adds; positions carry ~1e-7 of their size.
            let size = pos0.abs() + k as f32 * dpos.abs();
            assert!(
                (a - b).abs() <= 2e-6 * (1.0 + size),
                "pos0 {pos0}, dpos {dpos}, {k}: {a} vs {b}"
            );
        }
    }
}

#[test]
fn a_line_behind_the_source_or_beside_the_panel_adds_nothing() {
    let map = [10.0, 6.0, 10.0, 20.0];
    assert!(ZLine::new(0.0, 1.0, 0.0, 1.0, map, 12).is_none());
    assert!(ZLine::new(-5.0, 1.0, 0.0, 1.0, map, 12).is_none());
    assert!(ZLine::new(f32::NAN, 1.0, 0.0, 1.0, map, 12).is_none());
    // Columns: 10·lat/lc + 6 must lie in (0, 10).
    assert!(ZLine::new(10.0, -6.5, 0.0, 1.0, map, 12).is_none());
    assert!(ZLine::new(10.0, 4.5, 0.0, 1.0, map, 12).is_none());
    let z = ZLine::new(10.0, 2.5, -3.0, 0.5, map, 12).unwrap();
    assert!(z.iu == 8 && (z.fu - 0.5).abs() < 1e-5, "{z:?}");
    assert!((z.w - 0.01).abs() < 1e-9);
    assert!((z.pos0 - 17.0).abs() < 1e-5 && (z.dpos - 0.5).abs() < 1e-6);
}

/// A panel too short for its sizes, or a column at the edge, is refused without reading anything.
#[test]
fn inconsistent_panels_are_ignored() {
    let q = vec![1.0f32; 10 * 10];
    let line = ZLine {
        iu: 2,
        fu: 0.5,
        w: 1.0,
        pos0: 5.0,
        dpos: 0.5,
    };
    let mut acc = vec![0.0f32; 20];
    // No slack after the columns.
    let short = ColumnPanel {
        q: &q,
        cols: 10,
        rows: 10,
    };
    cone_column(&mut acc, short, &line);
    cone_column_scalar(&mut acc, short, &line);
    let q = vec![1.0f32; 10 * 10 + SLACK];
    let edge = ZLine { iu: 9, ..line };
    let full = ColumnPanel {
        q: &q,
        cols: 10,
        rows: 10,
    };
    cone_column(&mut acc, full, &edge);
    assert!(acc.iter().all(|v| *v == 0.0));
}

/// The lines of a row set up together are those of `ZLine::new` and `ZLine::span` voxel by voxel, to
/// the bit: rows through the source, beside the panel, with level and steep lines, over and under
/// the panel, partial rows and NaN.
#[test]
fn lines_set_up_together_are_those_set_up_one_by_one() {
    let mut seed = 0x2545_f491_u32;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        seed as f32 / u32::MAX as f32
    };
    let (cols, rows, n) = (70, 90, 64);
    let mut checked = (0, 0);
    for case in 0..4000 {
        let row = RowLine {
            lc0: if case % 97 == 0 {
                f32::NAN
            } else {
                40.0 * next() - 2.0
            },
            dlc: 0.8 * next() - 0.4,
            lat0: 30.0 * next() - 15.0,
            dlat: 0.6 * next() - 0.3,
            latv0: 40.0 * next() - 20.0,
            dlatv: 0.2 * next() - 0.1,
        };
        let dlatv = if case % 5 == 0 {
            0.0
        } else {
            2.0 * next() - 1.0
        };
        let map = [
            20.0 * next(),
            35.0,
            30.0 * next(),
            45.0 + 20.0 * next() - 10.0,
        ];
        let (x0, xs) = (case % 13, 1 + case % ROW_LINES);
        let mut together = Vec::new();
        ZLine::row(&row, (x0, xs), dlatv, map, (cols, rows), n, |i, z, span| {
            together.push((i, z, span));
        });
        let mut alone = Vec::new();
        for i in 0..xs {
            let x = (x0 + i) as f32;
            let (lc, lat) = (row.lc0 + x * row.dlc, row.lat0 + x * row.dlat);
            let latv = row.latv0 + x * row.dlatv;
            if let Some(z) = ZLine::new(lc, lat, latv, dlatv, map, cols) {
                let span = z.span(n, rows);
                if span.0 < span.1 {
                    alone.push((i, z, span));
                }
            }
        }
        assert_eq!(together.len(), alone.len(), "case {case}");
        for (a, b) in together.iter().zip(&alone) {
            let bits = |z: &ZLine| [z.fu, z.w, z.pos0, z.dpos].map(f32::to_bits);
            assert!(
                a.0 == b.0 && a.1.iu == b.1.iu && a.2 == b.2,
                "case {case}: {a:?} {b:?}"
            );
            assert_eq!(bits(&a.1), bits(&b.1), "case {case}: {a:?} {b:?}");
        }
        checked.0 += alone.len();
        checked.1 += xs - alone.len();
    }
    // Both kinds of voxel were met often.
    assert!(checked.0 > 10_000 && checked.1 > 1000, "{checked:?}");
}
