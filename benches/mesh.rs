//! Marching cubes on a 256³ volume holding a smooth surface with about 738k triangles, on one and on two
//! threads, and MIPs of a 512×512×133 volume (the size of a typical chest CT series) along each axis. When a
//! Python with VTK is present (`scripts/install-peers.sh`), VTK's `vtkFlyingEdges3D` meshes the same volume at
//! the same iso-value (`benches/mesh_vtk.py`) and its best time is printed beside criterion's.

mod common;

use std::path::Path;

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
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        g.bench_function(format!("marching_cubes_256/{threads}_threads"), |b| {
            b.iter(|| pool.install(|| marching_cubes(vol.view(), &frame, 0.0).triangle_count()))
        });
    }
    g.finish();
    vtk_peer(&vol, &frame);

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

/// vtkFlyingEdges3D on `vol` at iso-value 0, asked for one and for two threads, when a Python with VTK is
/// present.
fn vtk_peer(vol: &Array3<f32>, frame: &Frame) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let Some(python) = common::vtk_python("vtkFlyingEdges3D") else {
        return;
    };
    let Ok(dir) = tempfile::tempdir() else { return };
    let raw: Vec<u8> = vol.iter().flat_map(|v| v.to_le_bytes()).collect();
    if std::fs::write(dir.path().join("volume.f32"), raw).is_err() {
        return;
    }
    let (nz, ny, nx) = vol.dim();
    let spec = serde_json::json!({
        "volume": dir.path().join("volume.f32"), "dims": [nx, ny, nz],
        "spacing": frame.spacing_mm, "origin": frame.origin_mm, "iso": 0.0, "threads": [1, 2], "rounds": 10,
    });
    if std::fs::write(dir.path().join("spec.json"), spec.to_string()).is_err() {
        return;
    }
    match std::process::Command::new(python)
        .arg(root.join("benches/mesh_vtk.py"))
        .arg(dir.path().join("spec.json"))
        .output()
    {
        Ok(o) if o.status.success() => {
            for line in String::from_utf8_lossy(&o.stdout).lines() {
                println!("VTK vtkFlyingEdges3D, same volume: {line}");
            }
        }
        Ok(o) => eprintln!("VTK failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("VTK did not start: {e}"),
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
