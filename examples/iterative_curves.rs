//! RMSE versus iteration of SIRT, SART and CGLS on the 2D modified Shepp–Logan phantom, 256² pixels of
//! 1 mm, 360 parallel views over 180°, 363 detectors of 1 mm, exact sinogram; RMSE over the inscribed disk
//! against the phantom averaged over 4×4 sub-samples (phantom values, range 0–1). Prints a Markdown table.
//!
//! `cargo run --release --example iterative_curves` — the table;
//! `cargo run --release --example iterative_curves -- cone` — one cone-beam SIRT×10 (128³ from 180
//! projections of 192²) with its wall time, for `/usr/bin/time -v` to measure peak memory
//! (`-- cone V D`: from V projections of D², e.g. `-- cone 360 256`);
//! `cargo run --release --example iterative_curves -- projector [N [only]]` — best of N (default 5)
//! wall times of one forward and one back projection of 512² / 720 views / 725 detectors and of 256² /
//! 360 / 363 (parallel beam) and of a cone beam (64³ from 90 projections of 96²), and (unless `only`)
//! of SIRT×100 and CGLS×50 on the 256² case.

use std::time::Instant;

use ctrecon::recon::algorithm::{
    AlgorithmSpec, CglsParams, FbpParams, OutputGrid, SartParams, SirtParams, reconstruct,
};
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{Angles, ConeBeam, Panel, ParallelBeam, Views};
use ctrecon::recon::grid::{ImageGrid, Limits, VolumeGrid};
use ctrecon::recon::metrics::{inscribed_disk, rmse};
use ctrecon::recon::phantom::{Phantom2, Phantom3, Table2, Table3};
use ctrecon::recon::projector::{back_2d, back_3d, forward_2d, forward_3d};
use ndarray::Ix2;

/// Best wall time (s) of `n` runs of `f`.
fn best_of(n: usize, mut f: impl FnMut()) -> f64 {
    (0..n.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn parallel(n: usize, views: usize, det: usize) -> (ctrecon::recon::geometry::Views2, ImageGrid) {
    let v = ParallelBeam {
        angles: Angles::uniform(views, 180.0),
        det_count: det,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    }
    .to_views()
    .expect("valid geometry");
    (v, ImageGrid::square(n, 1.0))
}

fn projector(runs: usize, iterative: bool) {
    for (n, views, det) in [(512, 720, 725), (256, 360, 363)] {
        let (v, grid) = parallel(n, views, det);
        let image =
            Phantom2::from_table(Table2::ModifiedSheppLogan, n as f64 / 2.0).rasterize(&grid, 1);
        let sino = forward_2d(&v, image.view(), &grid);
        let f = best_of(runs, || {
            std::hint::black_box(forward_2d(&v, image.view(), &grid));
        });
        let b = best_of(runs, || {
            std::hint::black_box(back_2d(&v, sino.view(), &grid));
        });
        println!("projector {n}² {views} views {det} det: forward {f:.4} s, back {b:.4} s");
    }
    let (grid3, v3) = cone_case(64, 90, 96);
    let vol = Phantom3::from_table(Table3::ModifiedSheppLogan, 32.0).rasterize(&grid3, 1);
    let proj = forward_3d(&v3, vol.view(), &grid3);
    let f = best_of(runs, || {
        std::hint::black_box(forward_3d(&v3, vol.view(), &grid3));
    });
    let b = best_of(runs, || {
        std::hint::black_box(back_3d(&v3, proj.view(), &grid3));
    });
    println!("projector cone 64³ 90 views 96² det: forward {f:.4} s, back {b:.4} s");
    if !iterative {
        return;
    }
    let (v2, grid) = parallel(256, 360, 363);
    let sino = Phantom2::from_table(Table2::ModifiedSheppLogan, 128.0).project(&v2);
    let views = Views::D2(v2);
    let specs = [
        (
            "SIRT×100",
            AlgorithmSpec::Sirt(SirtParams {
                iterations: 100,
                ..SirtParams::default()
            }),
        ),
        (
            "CGLS×50",
            AlgorithmSpec::Cgls(CglsParams {
                iterations: 50,
                ..CglsParams::default()
            }),
        ),
    ];
    for (name, spec) in specs {
        let s = best_of(runs.min(3), || {
            std::hint::black_box(
                reconstruct(
                    &spec,
                    &views,
                    sino.view().into_dyn(),
                    &OutputGrid::Image(grid),
                    &Limits::default(),
                    unattended(),
                )
                .expect("reconstruction"),
            );
        });
        println!("{name} 256² 360 views: {s:.3} s");
    }
}

/// The cone-beam case at scale `n`³ from `views` projections of `det`² elements of 1.5·128/n mm
/// (n = 128: the 128³ / 180 × 192² case).
fn cone_case(n: usize, views: usize, det: usize) -> (VolumeGrid, ctrecon::recon::geometry::Views3) {
    let pitch = 1.5 * 128.0 / n as f64;
    let v3 = ConeBeam {
        angles: Angles::uniform(views, 360.0),
        dso_mm: 500.0 * n as f64 / 128.0,
        dsd_mm: 750.0 * n as f64 / 128.0,
        detector: Panel {
            nu: det,
            nv: det,
            du_mm: pitch,
            dv_mm: pitch,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .expect("valid geometry");
    (VolumeGrid::cube(n, 1.0), v3)
}

fn cone(count: usize, det: usize) {
    let (grid, v3) = cone_case(128, count, det);
    let phantom = Phantom3::from_table(Table3::ModifiedSheppLogan, 64.0);
    let proj = phantom.project(&v3);
    let views = Views::D3(v3);
    let spec = AlgorithmSpec::Sirt(SirtParams {
        iterations: 10,
        ..SirtParams::default()
    });
    let t = Instant::now();
    let vol = reconstruct(
        &spec,
        &views,
        proj.view().into_dyn(),
        &OutputGrid::Volume(grid),
        &Limits::default(),
        unattended(),
    )
    .expect("reconstruction");
    let secs = t.elapsed().as_secs_f64();
    let reference = phantom.rasterize(&grid, 2).into_dyn();
    let e = rmse(vol.view(), reference.view(), None).expect("same shape");
    println!("cone SIRT×10 128³ from {count}×{det}²: {secs:.2} s, RMSE {e:.4}");
}

fn main() {
    ctrecon::config::limit_simd_from_env();
    if std::env::args().nth(1).as_deref() == Some("cone") {
        let arg = |i: usize, default: usize| {
            std::env::args()
                .nth(i)
                .and_then(|s| s.parse().ok())
                .unwrap_or(default)
        };
        cone(arg(2, 180), arg(3, 192));
        return;
    }
    if std::env::args().nth(1).as_deref() == Some("projector") {
        let runs = std::env::args()
            .nth(2)
            .and_then(|s| s.parse().ok())
            .unwrap_or(5);
        projector(runs, std::env::args().nth(3).as_deref() != Some("only"));
        return;
    }
    let n = 256;
    let grid = ImageGrid::square(n, 1.0);
    let v2 = ParallelBeam {
        angles: Angles::uniform(360, 180.0),
        det_count: 363,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    }
    .to_views()
    .expect("valid geometry");
    let phantom = Phantom2::from_table(Table2::ModifiedSheppLogan, n as f64 / 2.0);
    let sino = phantom.project(&v2);
    let reference = phantom.rasterize(&grid, 4);
    let mask = inscribed_disk(n, n);
    let views = Views::D2(v2);
    let score = |spec: &AlgorithmSpec| {
        let t = Instant::now();
        let img = reconstruct(
            spec,
            &views,
            sino.view().into_dyn(),
            &OutputGrid::Image(grid),
            &Limits::default(),
            unattended(),
        )
        .expect("reconstruction")
        .into_dimensionality::<Ix2>()
        .expect("2D image");
        let secs = t.elapsed().as_secs_f64();
        let e = rmse(img.view(), reference.view(), Some(mask.view())).expect("same shape");
        (e, secs)
    };
    let only_sart = std::env::args().nth(1).as_deref() == Some("sart");
    println!("| method | iterations | RMSE | time (s) |");
    println!("|---|---|---|---|");
    let (e, s) = score(&AlgorithmSpec::Fbp(FbpParams::default()));
    println!("| FBP (ram-lak) | – | {e:.4} | {s:.2} |");
    for it in [10, 20, 50, 100].into_iter().filter(|_| !only_sart) {
        let (e, s) = score(&AlgorithmSpec::Sirt(SirtParams {
            iterations: it,
            ..SirtParams::default()
        }));
        println!("| SIRT | {it} | {e:.4} | {s:.2} |");
    }
    for it in [1, 2, 5, 10] {
        let (e, s) = score(&AlgorithmSpec::Sart(SartParams {
            iterations: it,
            ..SartParams::default()
        }));
        println!("| SART | {it} | {e:.4} | {s:.2} |");
    }
    for it in [5, 10, 20, 50].into_iter().filter(|_| !only_sart) {
        let (e, s) = score(&AlgorithmSpec::Cgls(CglsParams {
            iterations: it,
            ..CglsParams::default()
        }));
        println!("| CGLS | {it} | {e:.4} | {s:.2} |");
    }
}
