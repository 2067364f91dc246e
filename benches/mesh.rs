//! Marching cubes on a 256³ volume holding a smooth surface with about 765k triangles, and MIPs of a
//! 512×512×133 volume (the size of a typical chest CT series) along each axis.

use criterion::{Criterion, criterion_group, criterion_main};
use ndarray::Array3;

use ctrecon::mesh::marching_cubes;
use ctrecon::recon::grid::VolumeGrid;
use ctrecon::volume::{Axis, Frame, ProjectionKind, project};

/// A sphere of radius 110 voxels with a wavy surface, as a smooth field (positive inside).
fn wavy_sphere(n: usize) -> Array3<f32> {
    let c = (n as f32 - 1.0) / 2.0;
    Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        let (x, y, z) = (i as f32 - c, j as f32 - c, k as f32 - c);
        let r = (x * x + y * y + z * z).sqrt();
        let wave = 9.0 * (x / 2.8).sin() * (y / 2.9).sin() * (z / 2.8).cos();
        100.0 + wave - r
    })
}

fn bench(c: &mut Criterion) {
    let n = 256;
    let vol = wavy_sphere(n);
    let frame = Frame::from_grid(&VolumeGrid::cube(n, 0.8));
    let tris = marching_cubes(vol.view(), &frame, 0.0).triangle_count();
    println!("marching cubes 256³: {tris} triangles");
    let mut g = c.benchmark_group("mesh");
    g.sample_size(10);
    g.bench_function("marching_cubes_256", |b| {
        b.iter(|| marching_cubes(vol.view(), &frame, 0.0))
    });
    g.finish();

    let ct = Array3::from_shape_fn((133, 512, 512), |(k, j, i)| {
        ((k * 7 + j * 3 + i) % 2000) as f32 - 1000.0
    });
    let mut g = c.benchmark_group("mip_512x512x133");
    g.sample_size(10);
    for axis in [Axis::Axial, Axis::Coronal, Axis::Sagittal] {
        g.bench_function(format!("{axis:?}"), |b| {
            b.iter(|| project(ct.view(), axis, ProjectionKind::Max, None))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
