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
    let none =
        |views: &Views2| (0..views.views.len()).all(|v| LineView::plan(views, v, &grid).is_none());
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
            let lines = if lv.along_x { &cols } else { &rows };
            let mut narrow = vec![f32::NAN; lv.count];
            forward_view_with(lines, lv, &mut narrow, false);
            close(&narrow, &forward_reference(&image, lv), 1e-5);
            if !wide_available() {
                println!("skipped: the 16-ray AVX-512F forward kernel (this CPU lacks AVX-512F)");
                continue;
            }
            // The same operations per ray: the same values bit for bit.
            let mut wide = vec![f32::NAN; lv.count];
            forward_view_with(lines, lv, &mut wide, true);
            assert_eq!(
                wide.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                narrow.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
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
            let rows: Vec<Vec<f32>> = group.iter().map(|lv| random(lv.count, &mut rng)).collect();
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
                back_lines_with(&[(lv, &y)], count, len, &mut aty, &Cancel::new(), wide).unwrap();
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
