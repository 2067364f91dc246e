//! Convergence of the iterative methods on small consistent systems (b = A x_true with the Joseph
//! projector itself): CGLS reaches the known solution; SIRT, CGLS and MLEM decrease the residual
//! ‖Ax − b‖ monotonically; SART/OS-SART/ART approach the solution; bad parameters, oversized problems
//! and cancel give typed errors; progress carries the iteration and residual.

use std::sync::Mutex;

use ctrecon::recon::algorithm::{
    AlgorithmSpec, ArtParams, BackProjector, CglsParams, MlemParams, OutputGrid, SartParams,
    SirtParams, TvParams, reconstruct,
};
use ctrecon::recon::control::{Cancel, Control, unattended};
use ctrecon::recon::error::ReconError;
use ctrecon::recon::geometry::{Angles, ConeBeam, FanBeam, FanDetector, Panel, Views};
use ctrecon::recon::grid::{ImageGrid, Limits, VolumeGrid};
use ctrecon::recon::phantom::{Phantom2, Phantom3, Table2, Table3};
use ctrecon::recon::projector::{forward_2d, forward_3d};
use ndarray::{Array2, ArrayD};

fn small() -> (Views, ImageGrid, Array2<f32>, Array2<f32>) {
    let grid = ImageGrid::square(24, 1.0);
    let views = FanBeam {
        angles: Angles::uniform(60, 360.0),
        dso_mm: 60.0,
        dsd_mm: 100.0,
        detector: FanDetector::Flat {
            count: 48,
            spacing_mm: 1.2,
            offset_mm: 0.0,
        },
        centre_mm: [0.0, 0.0],
    }
    .to_views()
    .unwrap();
    let truth = Phantom2::from_table(Table2::ModifiedSheppLogan, 12.0).rasterize(&grid, 2);
    let b = forward_2d(&views, truth.view(), &grid);
    (Views::D2(views), grid, truth, b)
}

fn solve_with(
    spec: &AlgorithmSpec,
    views: &Views,
    grid: &ImageGrid,
    b: &Array2<f32>,
) -> (ArrayD<f32>, Vec<(usize, f64)>) {
    let log = Mutex::new(Vec::new());
    let progress = |_: &str, _: f64, it: Option<usize>, res: Option<f64>| {
        if let (Some(i), Some(r)) = (it, res) {
            log.lock().unwrap().push((i, r));
        }
    };
    let cancel = Cancel::new();
    let x = reconstruct(
        spec,
        views,
        b.view().into_dyn(),
        &OutputGrid::Image(*grid),
        &Limits::default(),
        Control::new(&cancel, &progress),
    )
    .unwrap();
    (x, log.into_inner().unwrap())
}

fn rel_error<D: ndarray::Dimension>(x: &ArrayD<f32>, truth: &ndarray::Array<f32, D>) -> f64 {
    let num: f64 = x
        .iter()
        .zip(truth.iter())
        .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
        .sum();
    let den: f64 = truth.iter().map(|b| (*b as f64).powi(2)).sum();
    (num / den).sqrt()
}

fn assert_monotone(name: &str, log: &[(usize, f64)]) {
    assert!(!log.is_empty(), "{name}: no progress");
    for (k, w) in log.windows(2).enumerate() {
        assert_eq!(w[1].0, w[0].0 + 1, "{name}: iteration numbers");
        // Allow f32 rounding once the residual is tiny.
        assert!(
            w[1].1 <= w[0].1 * (1.0 + 1e-6) + 1e-4,
            "{name}: residual rose at iteration {}: {} → {}",
            k + 2,
            w[0].1,
            w[1].1
        );
    }
}

#[test]
fn cgls_converges_to_the_known_solution_with_a_monotone_residual() {
    let (views, grid, truth, b) = small();
    let spec = AlgorithmSpec::Cgls(CglsParams {
        iterations: 300,
        ..CglsParams::default()
    });
    let (x, log) = solve_with(&spec, &views, &grid, &b);
    let e = rel_error(&x, &truth);
    println!(
        "CGLS×300: relative error {e:.2e}, final residual {:.2e}",
        log.last().unwrap().1
    );
    assert!(e < 1e-3, "relative error {e}");
    assert_monotone("cgls", &log);
}

#[test]
fn sirt_and_mlem_decrease_the_residual_monotonically_and_approach_the_solution() {
    let (views, grid, truth, b) = small();
    let (x, log) = solve_with(
        &AlgorithmSpec::Sirt(SirtParams {
            iterations: 200,
            ..SirtParams::default()
        }),
        &views,
        &grid,
        &b,
    );
    assert_monotone("sirt", &log);
    let e_sirt = rel_error(&x, &truth);
    let (x, log_m) = solve_with(
        &AlgorithmSpec::Mlem(MlemParams {
            iterations: 200,
            ..MlemParams::default()
        }),
        &views,
        &grid,
        &b,
    );
    assert_monotone("mlem", &log_m);
    let e_mlem = rel_error(&x, &truth);
    println!(
        "SIRT×200 relative error {e_sirt:.4} (residual {:.3e} → {:.3e}); MLEM×200 {e_mlem:.4} ({:.3e} → {:.3e})",
        log[0].1,
        log.last().unwrap().1,
        log_m[0].1,
        log_m.last().unwrap().1
    );
    assert!(e_sirt < 0.1, "SIRT {e_sirt}");
    assert!(e_mlem < 0.05, "MLEM {e_mlem}");
    assert!(log.last().unwrap().1 < 0.05 * log[0].1);
}

#[test]
fn sart_os_sart_art_and_tv_approach_the_solution() {
    let (views, grid, truth, b) = small();
    let cases = [
        (
            "sart",
            AlgorithmSpec::Sart(SartParams {
                iterations: 30,
                ..SartParams::default()
            }),
            0.05,
        ),
        (
            "os_sart",
            AlgorithmSpec::OsSart(SartParams {
                iterations: 50,
                subsets: 6,
                nonnegative: true,
                ..SartParams::default()
            }),
            0.05,
        ),
        (
            "art",
            AlgorithmSpec::Art(ArtParams {
                iterations: 30,
                ..ArtParams::default()
            }),
            0.05,
        ),
        (
            "tv",
            AlgorithmSpec::Tv(TvParams {
                iterations: 40,
                ..TvParams::default()
            }),
            0.12,
        ),
    ];
    for (name, spec, tol) in cases {
        let (x, log) = solve_with(&spec, &views, &grid, &b);
        let e = rel_error(&x, &truth);
        println!(
            "{name}: relative error {e:.4}, {} progress reports",
            log.len()
        );
        assert!(e < tol, "{name}: relative error {e}");
        assert!(
            log.last().unwrap().1 < log[0].1,
            "{name}: residual did not fall"
        );
    }
}

#[test]
fn box_constraints_hold_every_value_within_bounds_and_a_true_box_does_not_hurt() {
    let (views, grid, truth, b) = small();
    let (lo, hi) = truth
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    assert!(lo >= -1e-6 && hi <= 1.0 + 1e-6, "phantom in [{lo}, {hi}]");
    // A box tighter than the truth clamps; the box of the truth, [0, 1], fits it no worse than no box.
    let boxed = |upper: Option<f64>| {
        [
            AlgorithmSpec::Sirt(SirtParams {
                iterations: 40,
                nonnegative: true,
                upper,
                ..SirtParams::default()
            }),
            AlgorithmSpec::Sart(SartParams {
                iterations: 5,
                nonnegative: true,
                upper,
                ..SartParams::default()
            }),
            AlgorithmSpec::Art(ArtParams {
                iterations: 5,
                nonnegative: true,
                upper,
                ..ArtParams::default()
            }),
            AlgorithmSpec::Tv(TvParams {
                iterations: 10,
                upper,
                ..TvParams::default()
            }),
        ]
    };
    for spec in boxed(Some(0.5)) {
        let (x, _) = solve_with(&spec, &views, &grid, &b);
        let (l, h) = x
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        assert!(
            l >= 0.0 && h <= 0.5,
            "{}: values in [{l}, {h}]",
            spec.name()
        );
        // TV ends each iteration with its smoothing step, which may stay below the bound.
        if spec.name() != "tv" {
            assert!(h == 0.5, "{}: the bound is reached ({h})", spec.name());
        }
    }
    for (with_box, free) in boxed(Some(1.0)).iter().zip(boxed(None)) {
        let e_box = rel_error(&solve_with(with_box, &views, &grid, &b).0, &truth);
        let e_free = rel_error(&solve_with(&free, &views, &grid, &b).0, &truth);
        println!(
            "{}: [0, 1] box {e_box:.4}, [0, ∞) {e_free:.4}",
            with_box.name()
        );
        assert!(
            e_box <= e_free * 1.001,
            "{}: {e_box} > {e_free}",
            with_box.name()
        );
    }
    // Bounds that cannot hold are refused before any work.
    for upper in [-1.0, 0.0, f64::INFINITY] {
        let spec = AlgorithmSpec::Sirt(SirtParams {
            nonnegative: true,
            upper: Some(upper),
            ..SirtParams::default()
        });
        let e = reconstruct(
            &spec,
            &views,
            b.view().into_dyn(),
            &OutputGrid::Image(grid),
            &Limits::default(),
            unattended(),
        )
        .unwrap_err();
        assert!(
            matches!(e, ReconError::InvalidParameter { .. }),
            "{upper}: {e:?}"
        );
    }
}

#[test]
fn a_tolerance_stops_early() {
    let (views, grid, _, b) = small();
    let spec = AlgorithmSpec::Cgls(CglsParams {
        iterations: 500,
        tolerance: Some(1e-2),
        ..CglsParams::default()
    });
    let (_, log) = solve_with(&spec, &views, &grid, &b);
    let b_norm = b.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt();
    let (last_it, last_res) = *log.last().unwrap();
    assert!(last_it < 500, "ran all iterations");
    assert!(last_res / b_norm < 1e-2);
    assert!(log[log.len() - 2].1 / b_norm >= 1e-2);
}

#[test]
fn bad_parameters_oversized_problems_and_cancel_are_typed_errors() {
    let (views, grid, _, b) = small();
    let run = |spec: AlgorithmSpec, limits: Limits, cancel: &Cancel| {
        reconstruct(
            &spec,
            &views,
            b.view().into_dyn(),
            &OutputGrid::Image(grid),
            &limits,
            Control::new(cancel, &ctrecon::recon::control::NoProgress),
        )
    };
    let c = Cancel::new();
    let bad = [
        AlgorithmSpec::Sirt(SirtParams {
            iterations: 0,
            ..SirtParams::default()
        }),
        AlgorithmSpec::Sirt(SirtParams {
            relaxation: 2.5,
            ..SirtParams::default()
        }),
        AlgorithmSpec::OsSart(SartParams {
            subsets: 61,
            ..SartParams::default()
        }),
        AlgorithmSpec::Mlem(MlemParams {
            subsets: 0,
            ..MlemParams::default()
        }),
        AlgorithmSpec::Cgls(CglsParams {
            tolerance: Some(f64::NAN),
            ..CglsParams::default()
        }),
        AlgorithmSpec::Tv(TvParams {
            tv_weight: -1.0,
            ..TvParams::default()
        }),
        AlgorithmSpec::Art(ArtParams {
            relaxation: 0.0,
            ..ArtParams::default()
        }),
    ];
    for spec in bad {
        let r = run(spec.clone(), Limits::default(), &c);
        assert!(
            matches!(r, Err(ReconError::InvalidParameter { .. })),
            "{spec:?}: {r:?}"
        );
    }
    let r = run(
        AlgorithmSpec::Sirt(SirtParams::default()),
        Limits { max_bytes: 10_000 },
        &c,
    );
    assert!(matches!(r, Err(ReconError::TooLarge { .. })), "{r:?}");
    c.cancel();
    let r = run(
        AlgorithmSpec::Cgls(CglsParams::default()),
        Limits::default(),
        &c,
    );
    assert_eq!(r, Err(ReconError::Canceled));
}

#[test]
fn cone_beam_cgls_fits_the_data_of_a_small_volume() {
    let grid = VolumeGrid::cube(16, 1.0);
    let views = ConeBeam {
        angles: Angles::uniform(40, 360.0),
        dso_mm: 60.0,
        dsd_mm: 100.0,
        detector: Panel {
            nu: 32,
            nv: 32,
            du_mm: 1.0,
            dv_mm: 1.0,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .unwrap();
    let truth = Phantom3::from_table(Table3::ModifiedSheppLogan, 8.0).rasterize(&grid, 1);
    let b = forward_3d(&views, truth.view(), &grid);
    let x = reconstruct(
        &AlgorithmSpec::Cgls(CglsParams {
            iterations: 100,
            ..CglsParams::default()
        }),
        &Views::D3(views),
        b.view().into_dyn(),
        &OutputGrid::Volume(grid),
        &Limits::default(),
        unattended(),
    )
    .unwrap();
    let e = rel_error(&x, &truth);
    println!("cone CGLS×100 on 16³: relative error {e:.4}");
    assert!(e < 0.1, "relative error {e}");
}

/// The voxel-driven back projector (RTK's default pair) in conjugate gradients on B A x = B b: on a
/// consistent cone-beam system it reconstructs about as well as CGLS with the matched pair after the
/// same iterations, and it is a different method (different images). 2D geometries refuse it.
#[test]
fn cone_beam_cg_with_the_voxel_driven_back_projector_reconstructs_like_the_matched_pair() {
    let grid = VolumeGrid::cube(32, 1.0);
    let views = ConeBeam {
        angles: Angles::uniform(90, 360.0),
        dso_mm: 125.0,
        dsd_mm: 187.5,
        detector: Panel {
            nu: 64,
            nv: 64,
            du_mm: 1.5,
            dv_mm: 1.5,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .unwrap();
    let truth = Phantom3::from_table(Table3::ModifiedSheppLogan, 16.0).rasterize(&grid, 2);
    let b = forward_3d(&views, truth.view(), &grid);
    let views = Views::D3(views);
    let run = |back_projector| {
        let log = Mutex::new(Vec::new());
        let progress = |_: &str, _: f64, it: Option<usize>, res: Option<f64>| {
            if let (Some(i), Some(r)) = (it, res) {
                log.lock().unwrap().push((i, r));
            }
        };
        let cancel = Cancel::new();
        let x = reconstruct(
            &AlgorithmSpec::Cgls(CglsParams {
                iterations: 10,
                back_projector,
                ..CglsParams::default()
            }),
            &views,
            b.view().into_dyn(),
            &OutputGrid::Volume(grid),
            &Limits::default(),
            Control::new(&cancel, &progress),
        )
        .unwrap();
        (rel_error(&x, &truth), x, log.into_inner().unwrap())
    };
    let (matched, xm, _) = run(BackProjector::Matched);
    let (voxel, xv, log) = run(BackProjector::Voxel);
    let apart = xm
        .iter()
        .zip(xv.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let (first, last) = (log[0].1, log[log.len() - 1].1);
    println!(
        "cone CG×10 on 32³: relative error {voxel:.4} voxel-driven, {matched:.4} matched; \
         largest difference {apart:.4}; residual {first:.3e} → {last:.3e} over {} iterations",
        log.len()
    );
    assert_eq!(log.len(), 10);
    assert!(voxel < 1.1 * matched, "{voxel} against {matched}");
    assert!(apart > 1e-3, "the two pairs gave the same image");
    assert!(last < 0.5 * first, "residual {first} → {last}");

    let (views2, grid2, _, b2) = small();
    let r = reconstruct(
        &AlgorithmSpec::Cgls(CglsParams {
            back_projector: BackProjector::Voxel,
            ..CglsParams::default()
        }),
        &views2,
        b2.view().into_dyn(),
        &OutputGrid::Image(grid2),
        &Limits::default(),
        unattended(),
    );
    assert!(
        matches!(r, Err(ReconError::InvalidParameter { name, .. }) if name == "back_projector"),
        "{r:?}"
    );
}
