//! SART's fused single-view updates ([`LineSweep`]) against the whole-image passes on the same
//! operator: the same image bit for bit, after several passes, with and without bounds, on a
//! rectangular grid of rectangular pixels whose sides are not multiples of the kernels' widths,
//! with views along both axes and in both ray orders.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid};
use crate::recon::control::{Cancel, NoProgress};
use crate::recon::geometry::{Angles, FanBeam, FanDetector, ParallelBeam, Views, Views2};
use crate::recon::grid::ImageGrid;
use crate::recon::iterative::counted::Counted;
use crate::recon::iterative::estimate_bytes;
use crate::recon::projector::Projector2;

/// Parallel views and random data (uniform in `0 .. max`, from `seed`) for a test of the sweeps.
fn parallel_data(beam: ParallelBeam, seed: u64, max: f32) -> (Views2, Vec<f32>) {
    let views = beam.to_views().unwrap();
    let len = views.views.len() * views.detector.count;
    let mut rng = StdRng::seed_from_u64(seed);
    let b = (0..len).map(|_| rng.random_range(0.0..max)).collect();
    (views, b)
}

fn setup() -> (Views2, ImageGrid, Vec<f32>) {
    let grid = ImageGrid {
        nx: 45,
        ny: 38,
        dx_mm: 1.0,
        dy_mm: 0.8,
        centre_mm: [0.6, -0.3],
    };
    // 41 views over a full turn: dominant axes x and y, rays in both orders.
    let beam = ParallelBeam {
        angles: Angles::uniform(41, 360.0),
        det_count: 61,
        det_spacing_mm: 0.9,
        det_offset_mm: -1.3,
    };
    let (views, b) = parallel_data(beam, 21, 20.0);
    (views, grid, b)
}

/// `n` passes of the fused sweep (on `op`) and of the whole-image sweep (on `op` without line plans)
/// from `start`: the two images and each pass's two residuals.
#[allow(clippy::too_many_arguments)]
fn run_both(
    op: &dyn Operator,
    fused: &mut Sweep,
    passes: &mut Sweep,
    b: &[f32],
    start: &[f32],
    lambda: f32,
    bounds: Bounds,
    n: usize,
) -> (Vec<f32>, Vec<f32>, Vec<(f64, f64)>) {
    let cancel = Cancel::new();
    let ctl = Control::new(&cancel, &NoProgress);
    let plain = Counted::new(op);
    let (mut x1, mut x2) = (start.to_vec(), start.to_vec());
    let residuals = (0..n)
        .map(|_| {
            let r1 = fused.run(op, b, &mut x1, lambda, bounds, &ctl).unwrap();
            let r2 = passes
                .run(&plain, b, &mut x2, lambda, bounds, &ctl)
                .unwrap();
            (r1, r2)
        })
        .collect();
    (x1, x2, residuals)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn fused_updates_match_the_whole_image_passes_bit_for_bit() {
    let (views, grid, b) = setup();
    let op = Projector2::with_walk_table(&views, &grid);
    let cancel = Cancel::new();
    let ctl = Control::new(&cancel, &NoProgress);
    let mut fused = Sweep::new(&op, 41, &ctl).unwrap();
    if fused.lines.is_none() {
        assert!(
            !crate::recon::cpu::avx2_fma(),
            "the line plans were not taken"
        );
        println!("skipped: the fused SART updates need AVX2 + FMA (this CPU lacks them)");
        return;
    }
    let plain = Counted::new(&op);
    let mut passes = Sweep::new(&plain, 41, &ctl).unwrap();
    assert!(passes.lines.is_none());
    let (plans, _, _) = op.line_plans().unwrap();
    assert!(plans.iter().any(|p| p.along_x) && plans.iter().any(|p| !p.along_x));
    assert!(plans.iter().any(|p| p.reversed) && plans.iter().any(|p| !p.reversed));
    for bounds in [
        Bounds::default(),
        Bounds::new(true, Some(0.02)),
        Bounds::new(false, Some(0.05)),
    ] {
        let mut rng = StdRng::seed_from_u64(22);
        let start: Vec<f32> = (0..grid.nx * grid.ny)
            .map(|_| rng.random_range(-0.05..0.05f32))
            .collect();
        let (x1, x2, residuals) =
            run_both(&op, &mut fused, &mut passes, &b, &start, 0.9, bounds, 3);
        for (r1, r2) in residuals {
            assert!((r1 - r2).abs() <= 1e-9 * r2, "residuals {r1} and {r2}");
        }
        assert_eq!(bits(&x1), bits(&x2), "bounds {bounds:?}");
        assert!(x1.iter().any(|&v| v != 0.0));
    }
}

#[test]
fn fused_updates_on_the_avx2_kernels_match_the_whole_image_passes() {
    let (views, grid, b) = setup();
    let op = Projector2::with_walk_table(&views, &grid);
    let cancel = Cancel::new();
    let ctl = Control::new(&cancel, &NoProgress);
    let mut fused = Sweep::new(&op, 41, &ctl).unwrap();
    let Some(lines) = fused.lines.as_mut() else {
        println!("skipped: the fused SART updates need AVX2 + FMA (this CPU lacks them)");
        return;
    };
    lines.narrow();
    let plain = Counted::new(&op);
    let mut passes = Sweep::new(&plain, 41, &ctl).unwrap();
    let start = vec![0.0f32; grid.nx * grid.ny];
    let bounds = Bounds::new(true, None);
    let (x1, x2, _) = run_both(&op, &mut fused, &mut passes, &b, &start, 1.0, bounds, 3);
    // The 8- and 16-pixel back kernels sum a pixel's two rays in another order where it has two.
    let max = x2.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max > 0.0);
    for (a, b) in x1.iter().zip(&x2) {
        assert!((a - b).abs() <= 1e-5 * max, "{a} vs {b}");
    }
}

#[test]
fn subsets_of_several_views_keep_the_whole_image_passes() {
    let (views, grid, _) = setup();
    let op = Projector2::with_walk_table(&views, &grid);
    let cancel = Cancel::new();
    let ctl = Control::new(&cancel, &NoProgress);
    assert!(Sweep::new(&op, 8, &ctl).unwrap().lines.is_none());
}

#[test]
fn a_team_of_threads_gives_the_updates_of_one_thread_bit_for_bit() {
    // Enough pixels for the updates to run on a team; views along both axes (transposes), rays in
    // both orders, sides that are not multiples of the chunks.
    let grid = ImageGrid {
        nx: 173,
        ny: 141,
        dx_mm: 1.0,
        dy_mm: 0.9,
        centre_mm: [0.3, -0.2],
    };
    let beam = ParallelBeam {
        angles: Angles::uniform(23, 360.0),
        det_count: 251,
        det_spacing_mm: 0.8,
        det_offset_mm: 0.35,
    };
    let (views, b) = parallel_data(beam, 29, 40.0);
    let run = |threads: usize, narrow: bool| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let op = Projector2::with_walk_table(&views, &grid);
            let cancel = Cancel::new();
            let ctl = Control::new(&cancel, &NoProgress);
            let mut sweep = Sweep::new(&op, 23, &ctl).unwrap();
            let lines = sweep.lines.as_mut()?;
            assert_eq!(lines.partners(), threads - 1);
            if narrow {
                lines.narrow();
            }
            let mut x = vec![0.0f32; grid.nx * grid.ny];
            let bounds = Bounds::new(true, Some(1.5));
            let res: Vec<f64> = (0..3)
                .map(|_| sweep.run(&op, &b, &mut x, 1.0, bounds, &ctl).unwrap())
                .collect();
            Some((bits(&x), res))
        })
    };
    for narrow in [false, true] {
        let Some(one) = run(1, narrow) else {
            println!("skipped: the fused SART updates need AVX2 + FMA (this CPU lacks them)");
            return;
        };
        assert!(one.0.iter().any(|&v| f32::from_bits(v) > 0.0));
        for threads in [2, 3] {
            assert_eq!(
                run(threads, narrow),
                Some(one.clone()),
                "{threads} threads, narrow {narrow}"
            );
        }
    }
}

#[test]
fn fused_updates_split_between_threads_match_the_whole_image_passes() {
    // A large image, its updates on a team of three threads.
    let grid = ImageGrid {
        nx: 411,
        ny: 333,
        dx_mm: 1.0,
        dy_mm: 1.1,
        centre_mm: [0.0, 0.4],
    };
    assert!(grid.nx * grid.ny >= 1 << 17);
    let beam = ParallelBeam {
        angles: Angles::uniform(7, 180.0),
        det_count: 530,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.7,
    };
    let (views, b) = parallel_data(beam, 23, 50.0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    pool.install(|| {
        let op = Projector2::with_walk_table(&views, &grid);
        let cancel = Cancel::new();
        let ctl = Control::new(&cancel, &NoProgress);
        let mut fused = Sweep::new(&op, 7, &ctl).unwrap();
        if fused.lines.is_none() {
            println!("skipped: the fused SART updates need AVX2 + FMA (this CPU lacks them)");
            return;
        }
        let plain = Counted::new(&op);
        let mut passes = Sweep::new(&plain, 7, &ctl).unwrap();
        let start = vec![0.0f32; grid.nx * grid.ny];
        let bounds = Bounds::new(true, None);
        let (x1, x2, _) = run_both(&op, &mut fused, &mut passes, &b, &start, 1.0, bounds, 2);
        assert_eq!(bits(&x1), bits(&x2));
        assert!(x1.iter().any(|&v| v > 0.0));
    });
}

#[test]
fn the_memory_estimate_counts_per_view_weights_and_walks_only_where_they_are_kept() {
    let grid = OutputGrid::Image(ImageGrid::square(64, 1.0));
    let parallel = Views::D2(
        ParallelBeam {
            angles: Angles::uniform(90, 180.0),
            det_count: 91,
            det_spacing_mm: 1.0,
            det_offset_mm: 0.0,
        }
        .to_views()
        .unwrap(),
    );
    let fan = Views::D2(
        FanBeam {
            angles: Angles::uniform(90, 360.0),
            dso_mm: 200.0,
            dsd_mm: 300.0,
            detector: FanDetector::Flat {
                count: 120,
                spacing_mm: 1.2,
                offset_mm: 0.0,
            },
            centre_mm: [0.0, 0.0],
        }
        .to_views()
        .unwrap(),
    );
    let sart = AlgorithmSpec::Sart(SartParams::default());
    let os = |subsets| {
        AlgorithmSpec::OsSart(SartParams {
            subsets,
            ..SartParams::default()
        })
    };
    let weights = |views: u64| views * 64 * 64 * 4;
    let e = |spec: &AlgorithmSpec, views: &Views| estimate_bytes(spec, views, &grid);
    // Fan views keep the whole-image passes: one stored image of weights per view.
    assert_eq!(e(&sart, &fan), e(&os(45), &fan) + weights(45));
    assert_eq!(e(&os(90), &fan), e(&sart, &fan));
    if crate::recon::cpu::avx2_fma() {
        // Parallel views take the fused updates: no weights for SART or OS-SART with single views.
        assert_eq!(e(&sart, &parallel) + weights(45), e(&os(45), &parallel));
        assert_eq!(e(&os(90), &parallel), e(&sart, &parallel));
    } else {
        assert_eq!(e(&sart, &parallel), e(&os(45), &parallel) + weights(45));
    }
    // The table of every ray's walk is kept, and counted, only where a ray is walked: by ART, and
    // by every method on fan views; with every view on the line kernels the other methods never walk.
    let art = AlgorithmSpec::Art(serde_json::from_str("{}").unwrap());
    let all_lines = crate::recon::cpu::avx2_fma();
    for (spec, views, keeps) in [
        (&art, &parallel, true),
        (&art, &fan, true),
        (&sart, &fan, true),
        (&os(45), &fan, true),
        (&sart, &parallel, !all_lines),
        (&os(45), &parallel, !all_lines),
    ] {
        assert_eq!(
            crate::recon::iterative::keeps_walk_table(spec, views, &grid),
            keeps
        );
    }
}
