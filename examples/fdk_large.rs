//! FDK of a 256³ volume (1 mm voxels) from 360 projections of 512² (0.8 mm, DSO 1000 mm, DSD 1500 mm),
//! timed once after one warm-up run of the 128³ case. Run under `/usr/bin/time -v` for the peak memory:
//! `cargo build --release --example fdk_large && /usr/bin/time -v target/release/examples/fdk_large`.

use std::time::Instant;

use ctrecon::recon::algorithm::FbpParams;
use ctrecon::recon::analytic::fdk;
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{Angles, ConeBeam, Panel};
use ctrecon::recon::grid::VolumeGrid;
use ndarray::Array3;

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(256);
    let cone = ConeBeam {
        angles: Angles::uniform(360, 360.0),
        dso_mm: 1000.0,
        dsd_mm: 1500.0,
        detector: Panel {
            nu: 2 * n,
            nv: 2 * n,
            du_mm: 0.8 * 256.0 / n as f64,
            dv_mm: 0.8 * 256.0 / n as f64,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .expect("valid cone geometry");
    let proj = Array3::from_shape_fn(cone.shape(), |(k, r, i)| {
        ((i as f32 * 0.01 + r as f32 * 0.02 + k as f32 * 0.003).sin() + 1.0) * 10.0
    });
    let grid = VolumeGrid::cube(n, 256.0 / n as f64);
    let start = Instant::now();
    let vol = fdk(
        &cone,
        proj.view(),
        &grid,
        &FbpParams::default(),
        unattended(),
    )
    .expect("FDK runs");
    let secs = start.elapsed().as_secs_f64();
    let updates = (n * n * n) as f64 * 360.0;
    let threads = rayon::current_num_threads() as f64;
    println!(
        "FDK {n}³ from 360 × {}²: {secs:.2} s, {:.3e} voxel-updates/s/core ({} threads), centre {}",
        2 * n,
        updates / secs / threads,
        threads,
        vol[[n / 2, n / 2, n / 2]]
    );
}
