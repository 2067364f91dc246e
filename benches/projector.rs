//! Joseph projector pair: one forward and one back projection of 512² / 720 views / 725 detectors
//! (parallel beam), and of 256² / 360 views / 363 detectors.

use criterion::{Criterion, criterion_group, criterion_main};
use ctrecon::recon::geometry::{Angles, ParallelBeam, Views2};
use ctrecon::recon::grid::ImageGrid;
use ctrecon::recon::phantom::{Phantom2, Table2};
use ctrecon::recon::projector::{back_2d, forward_2d};
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

criterion_group!(benches, bench);
criterion_main!(benches);
