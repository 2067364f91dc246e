//! Iterative methods end to end (sinogram in, image out, all cores): SIRT×100 and CGLS×50 on 256² /
//! 360 views / 363 detectors (parallel beam), and cone-beam SIRT×10 on 128³ from 180 projections of 192².
//! The cone case is skipped unless `CTRECON_BENCH_CONE=1` (it takes minutes with 10 samples).

mod common;

use criterion::{Criterion, criterion_group, criterion_main};
use ctrecon::recon::algorithm::{AlgorithmSpec, CglsParams, OutputGrid, SirtParams, reconstruct};
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{Angles, ParallelBeam, Views};
use ctrecon::recon::grid::{ImageGrid, Limits, VolumeGrid};
use ctrecon::recon::phantom::{Phantom2, Phantom3, Table2, Table3};
use std::hint::black_box;

fn bench_2d(c: &mut Criterion) {
    ctrecon::config::limit_simd_from_env();
    let grid = ImageGrid::square(256, 1.0);
    let v2 = ParallelBeam {
        angles: Angles::uniform(360, 180.0),
        det_count: 363,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    }
    .to_views()
    .unwrap();
    let sino = Phantom2::from_table(Table2::ModifiedSheppLogan, 128.0).project(&v2);
    let views = Views::D2(v2);
    let mut g = c.benchmark_group("iterative");
    g.sample_size(10);
    let specs = [
        (
            "sirt×100 256² 360 views",
            AlgorithmSpec::Sirt(SirtParams {
                iterations: 100,
                ..SirtParams::default()
            }),
        ),
        (
            "cgls×50 256² 360 views",
            AlgorithmSpec::Cgls(CglsParams {
                iterations: 50,
                ..CglsParams::default()
            }),
        ),
    ];
    for (name, spec) in specs {
        g.bench_function(name, |b| {
            b.iter(|| {
                black_box(
                    reconstruct(
                        &spec,
                        &views,
                        sino.view().into_dyn(),
                        &OutputGrid::Image(grid),
                        &Limits::default(),
                        unattended(),
                    )
                    .unwrap(),
                )
            })
        });
    }
    g.finish();
}

fn bench_cone(c: &mut Criterion) {
    if std::env::var("CTRECON_BENCH_CONE").as_deref() != Ok("1") {
        return;
    }
    let grid = VolumeGrid::cube(128, 1.0);
    let v3 = common::peers_cone(180, 192);
    let proj = Phantom3::from_table(Table3::ModifiedSheppLogan, 64.0).project(&v3);
    let views = Views::D3(v3);
    let spec = AlgorithmSpec::Sirt(SirtParams {
        iterations: 10,
        ..SirtParams::default()
    });
    let mut g = c.benchmark_group("iterative");
    g.sample_size(10);
    g.bench_function("cone sirt×10 128³ 180×192²", |b| {
        b.iter(|| {
            black_box(
                reconstruct(
                    &spec,
                    &views,
                    proj.view().into_dyn(),
                    &OutputGrid::Volume(grid),
                    &Limits::default(),
                    unattended(),
                )
                .unwrap(),
            )
        })
    });
    g.finish();
}

criterion_group!(benches, bench_2d, bench_cone);
criterion_main!(benches);
