//! Joseph projector pair: one forward and one back projection of 512² / 720 views / 725 detectors
//! (parallel beam), of 256² / 360 views / 363 detectors, and of 128³ from 360 cone-beam views of
//! 256² (the cone iterative case of `benches/peers/`: the column-ordered pair of `cone_columns`).

mod common;

use criterion::{Criterion, criterion_group, criterion_main};
use ctrecon::recon::geometry::{Angles, ParallelBeam, Views2};
use ctrecon::recon::grid::{ImageGrid, VolumeGrid};
use ctrecon::recon::phantom::{Phantom2, Phantom3, Table2, Table3};
use ctrecon::recon::projector::{back_2d, back_3d, forward_2d, forward_3d};
use std::hint::black_box;

fn setup(n: usize, views: usize, det: usize) -> (Views2, ImageGrid) {
    let v = ParallelBeam {
        angles: Angles::uniform(views, 180.0),
        det_count: det,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    }
    .to_views()
    .unwrap();
    (v, ImageGrid::square(n, 1.0))
}

fn bench(c: &mut Criterion) {
    ctrecon::config::limit_simd_from_env();
    let mut g = c.benchmark_group("projector");
    g.sample_size(10);
    for (n, views, det) in [(512, 720, 725), (256, 360, 363)] {
        let (v, grid) = setup(n, views, det);
        let image =
            Phantom2::from_table(Table2::ModifiedSheppLogan, n as f64 / 2.0).rasterize(&grid, 1);
        let sino = forward_2d(&v, image.view(), &grid);
        g.bench_function(format!("forward {n}² {views} views"), |b| {
            b.iter(|| black_box(forward_2d(&v, image.view(), &grid)))
        });
        g.bench_function(format!("back {n}² {views} views"), |b| {
            b.iter(|| black_box(back_2d(&v, sino.view(), &grid)))
        });
    }
    g.finish();
}

fn bench_cone(c: &mut Criterion) {
    ctrecon::config::limit_simd_from_env();
    let grid = VolumeGrid::cube(128, 1.0);
    let views = common::peers_cone(360, 256);
    let phantom = Phantom3::from_table(Table3::ModifiedSheppLogan, 64.0);
    let volume = phantom.rasterize(&grid, 1);
    let projections = phantom.project(&views);
    let mut g = c.benchmark_group("cone");
    g.sample_size(10);
    g.bench_function("forward 128³ 360×256²", |b| {
        b.iter(|| black_box(forward_3d(&views, volume.view(), &grid)))
    });
    g.bench_function("back 128³ 360×256²", |b| {
        b.iter(|| black_box(back_3d(&views, projections.view(), &grid)))
    });
    g.finish();
}

criterion_group!(benches, bench, bench_cone);
criterion_main!(benches);
