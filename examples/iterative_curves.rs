//! RMSE versus iteration of SIRT, SART and CGLS on the 2D modified Shepp–Logan phantom, 256² pixels of
//! 1 mm, 360 parallel views over 180°, 363 detectors of 1 mm, exact sinogram; RMSE over the inscribed disk
//! against the phantom averaged over 4×4 sub-samples (phantom values, range 0–1). Prints a Markdown table.
//!
//! `cargo run --release --example iterative_curves` — the table;
//! `cargo run --release --example iterative_curves -- cone` — one cone-beam SIRT×10 (128³ from 180
//! projections of 192²) with its wall time, for `/usr/bin/time -v` to measure peak memory.

use std::time::Instant;

use ctrecon::recon::algorithm::{
    AlgorithmSpec, CglsParams, FbpParams, OutputGrid, SartParams, SirtParams, reconstruct,
};
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{Angles, ConeBeam, Panel, ParallelBeam, Views};
use ctrecon::recon::grid::{ImageGrid, Limits, VolumeGrid};
use ctrecon::recon::metrics::{inscribed_disk, rmse};
use ctrecon::recon::phantom::{Phantom2, Phantom3, Table2, Table3};
use ndarray::Ix2;

fn cone() {
    let grid = VolumeGrid::cube(128, 1.0);
    let v3 = ConeBeam {
        angles: Angles::uniform(180, 360.0),
        dso_mm: 500.0,
        dsd_mm: 750.0,
        detector: Panel {
            nu: 192,
            nv: 192,
            du_mm: 1.5,
            dv_mm: 1.5,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .expect("valid geometry");
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
    println!("cone SIRT×10 128³ from 180×192²: {secs:.2} s, RMSE {e:.4}");
}

fn main() {
    if std::env::args().nth(1).as_deref() == Some("cone") {
        cone();
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
