//! Analytic reconstruction end to end (array in, array out, all cores): parallel FBP 512² from 720 views
//! of 725 detectors, fan-beam FBP 512² from 720 views (arc and flat), FDK 128³ from 360 projections of
//! 256². The larger FDK (256³ from 360 projections of 512²) is timed by `examples/analytic_timing.rs`
//! (`fdk256`), which also gives CPU time and, under `/usr/bin/time -v`, the peak memory.
//!
//! `helical` times the helical weighted FBP of 128³ of 2 mm from 5 turns of 360 views of 64 × 256 at
//! pitch 1 beside FDK (`examples/analytic_timing.rs helical` counts its voxel updates).
//!
//! The data are smooth synthetic arrays: the cost of FBP and FDK does not depend on the values.

use criterion::{Criterion, criterion_group, criterion_main};
use ndarray::{Array2, Array3};

use ctrecon::recon::algorithm::FbpParams;
use ctrecon::recon::analytic::{fbp_2d, fdk};
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{
    Angles, ConeBeam, FanBeam, FanDetector, Geometry, Panel, ParallelBeam, Views, Views2,
};
use ctrecon::recon::grid::{ImageGrid, VolumeGrid};

fn sinogram(shape: [usize; 2]) -> Array2<f32> {
    Array2::from_shape_fn(shape, |(k, i)| {
        ((i as f32 * 0.01 + k as f32 * 0.003).sin() + 1.0) * 10.0
    })
}

fn fan(detector: FanDetector) -> Views2 {
    FanBeam {
        angles: Angles::uniform(720, 360.0),
        dso_mm: 500.0,
        dsd_mm: 950.0,
        detector,
        centre_mm: [0.0, 0.0],
    }
    .to_views()
    .expect("valid fan geometry")
}

fn bench(c: &mut Criterion) {
    ctrecon::config::limit_simd_from_env();
    let params = FbpParams::default();
    let grid = ImageGrid::square(512, 0.5);
    let mut g = c.benchmark_group("fbp_512");
    g.sample_size(10);
    let parallel = ParallelBeam {
        angles: Angles::uniform(720, 180.0),
        det_count: 725,
        det_spacing_mm: 0.5,
        det_offset_mm: 0.0,
    }
    .to_views()
    .expect("valid parallel geometry");
    let sino = sinogram(parallel.shape());
    g.bench_function("parallel_720x725", |b| {
        b.iter(|| fbp_2d(&parallel, sino.view(), &grid, &params, unattended()))
    });
    // ±23.8° covers the 181 mm radius of the 256 mm image at DSO 500 mm.
    let arc = fan(FanDetector::Arc {
        count: 800,
        spacing_deg: 0.06,
        offset_deg: 0.0,
    });
    let sino = sinogram(arc.shape());
    g.bench_function("fan_arc_720x800", |b| {
        b.iter(|| fbp_2d(&arc, sino.view(), &grid, &params, unattended()))
    });
    let flat = fan(FanDetector::Flat {
        count: 800,
        spacing_mm: 1.06,
        offset_mm: 0.0,
    });
    let sino = sinogram(flat.shape());
    g.bench_function("fan_flat_720x800", |b| {
        b.iter(|| fbp_2d(&flat, sino.view(), &grid, &params, unattended()))
    });
    g.finish();

    let cone = ConeBeam {
        angles: Angles::uniform(360, 360.0),
        dso_mm: 1000.0,
        dsd_mm: 1500.0,
        detector: Panel {
            nu: 256,
            nv: 256,
            du_mm: 1.6,
            dv_mm: 1.6,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .expect("valid cone geometry");
    let proj = Array3::from_shape_fn(cone.shape(), |(k, r, i)| {
        ((i as f32 * 0.01 + r as f32 * 0.02 + k as f32 * 0.003).sin() + 1.0) * 10.0
    });
    let vol = VolumeGrid::cube(128, 2.0);
    let mut g = c.benchmark_group("fdk");
    g.sample_size(10);
    g.bench_function("fdk_128_from_360x256x256", |b| {
        b.iter(|| fdk(&cone, proj.view(), &vol, &params, unattended()))
    });
    let json = r#"{"type": "helical", "dso_mm": 1000, "dsd_mm": 1500, "pitch": 1.0, "turns": 5,
        "views_per_turn": 360, "z_start_mm": -170.7,
        "detector": {"nu": 256, "nv": 64, "du_mm": 1.6, "dv_mm": 1.6}}"#;
    let helix: Geometry = serde_json::from_str(json).expect("valid helical JSON");
    let Ok(Views::D3(helix)) = helix.to_views() else {
        panic!("a helical geometry is a cone beam")
    };
    let proj = Array3::from_shape_fn(helix.shape(), |(k, r, i)| {
        ((i as f32 * 0.01 + r as f32 * 0.02 + k as f32 * 0.003).sin() + 1.0) * 10.0
    });
    g.bench_function("helical_128_from_1800x64x256", |b| {
        b.iter(|| fdk(&helix, proj.view(), &vol, &params, unattended()))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
