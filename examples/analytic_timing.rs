//! Wall-clock and CPU time of the analytic benchmarks, for a machine shared with other work where
//! criterion's wall-clock figures overstate the cost: CPU time (user + system of this process, from
//! `/proc/self/stat`) divided by the thread count estimates the wall time on an idle machine.
//!
//! `cargo run --release --example analytic_timing -- [parallel|fan_arc|fan_flat|fdk128|fdk256|helical|cone_pair] [runs]`;
//! under `/usr/bin/time -v` the maximum resident set size is the peak memory. `cone_pair` times one
//! forward and one back projection of the matched cone-beam pair, apart, on the peers' cone case
//! (`benches/peers/`: 128³ of 1 mm from 360 views of 256², magnification 1.5), the two passes of
//! every iteration of the cone-beam iterative methods, and FDK of the same projections (its voxel-driven
//! back projection of the same voxel updates, with the filtering). `helical` runs the helical weighted
//! FBP ([`helical`]: 128³ of 2 mm from 5 turns of 360 views at pitch 1 on a 256 × 64 panel) and counts
//! its voxel updates exactly: the (voxel, view) pairs where the voxel projects inside the panel.

use std::time::Instant;

use ctrecon::recon::algorithm::FbpParams;
use ctrecon::recon::analytic::{fbp_2d, fdk};
use ctrecon::recon::control::Cancel;
use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::{
    Angles, ConeBeam, FanBeam, FanDetector, Geometry, Panel, ParallelBeam, Views, Views2, Views3,
};
use ctrecon::recon::grid::{ImageGrid, VolumeGrid};
use ctrecon::recon::projector::{Operator, Projector3};
use ndarray::{Array2, Array3};

/// CPU seconds (user + system) used by this process so far; 0 where /proc is missing.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15 (1-based).
    let Some(rest) = stat.rsplit(')').next() else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
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

fn cone(n: usize) -> (ConeBeam, VolumeGrid) {
    let g = ConeBeam {
        angles: Angles::uniform(360, 360.0),
        dso_mm: 1000.0,
        dsd_mm: 1500.0,
        detector: Panel {
            nu: 2 * n,
            nv: 2 * n,
            du_mm: 1.6 * 128.0 / n as f64,
            dv_mm: 1.6 * 128.0 / n as f64,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    };
    (g, VolumeGrid::cube(n, 256.0 / n as f64))
}

/// The helical case: 5 turns of 360 views at pitch 1 (DSO 1000 mm, DSD 1500 mm, 256 × 64 elements
/// of 1.6 mm, 68 mm at the rotation axis) through a 128³ volume of 2 mm.
fn helical() -> (Views3, VolumeGrid) {
    let json = r#"{"type": "helical", "dso_mm": 1000, "dsd_mm": 1500, "pitch": 1.0, "turns": 5,
        "views_per_turn": 360, "z_start_mm": -170.7,
        "detector": {"nu": 256, "nv": 64, "du_mm": 1.6, "dv_mm": 1.6}}"#;
    let g: Geometry = serde_json::from_str(json).expect("valid helical JSON");
    match g.to_views().expect("valid helical geometry") {
        Views::D3(v) => (v, VolumeGrid::cube(128, 2.0)),
        _ => unreachable!("a helical geometry is a cone beam"),
    }
}

/// (voxel, view) pairs of `grid` where the voxel's centre projects inside the panel (rows within the
/// outer row centres, columns within the outer column centres): the updates the helical FBP makes.
fn helical_updates(views: &Views3, grid: &VolumeGrid) -> f64 {
    let d = views.detector;
    let (half_u, half_v) = (
        (d.nu as f64 - 1.0) / 2.0 * d.du_mm,
        (d.nv as f64 - 1.0) / 2.0 * d.dv_mm,
    );
    let mut n = 0u64;
    for v in &views.views {
        let dsd = ((v.det_centre[0] - v.source[0]).powi(2)
            + (v.det_centre[1] - v.source[1]).powi(2))
        .sqrt();
        let normal = [
            (v.det_centre[0] - v.source[0]) / dsd,
            (v.det_centre[1] - v.source[1]) / dsd,
        ];
        for y in 0..grid.ny {
            for x in 0..grid.nx {
                let r = [grid.x(x) - v.source[0], grid.y(y) - v.source[1]];
                let lc = r[0] * normal[0] + r[1] * normal[1];
                let lat = r[0] * v.det_u[0] + r[1] * v.det_u[1];
                if lc <= 0.0 || (dsd * lat / lc).abs() > half_u {
                    continue;
                }
                let reach = half_v * lc / dsd;
                n += (0..grid.nz)
                    .filter(|&z| (grid.z(z) - v.source[2]).abs() < reach)
                    .count() as u64;
            }
        }
    }
    n as f64
}

/// CPU and wall seconds of `f`.
fn timed(f: impl FnOnce()) -> (f64, f64) {
    let (wall0, cpu0) = (Instant::now(), cpu_seconds());
    f();
    (cpu_seconds() - cpu0, wall0.elapsed().as_secs_f64())
}

/// One forward and one back projection of the peers' cone case, `runs` times, timed apart.
fn cone_pair(runs: usize) {
    let g = ConeBeam {
        angles: Angles::uniform(360, 360.0),
        dso_mm: 500.0,
        dsd_mm: 750.0,
        detector: Panel {
            nu: 256,
            nv: 256,
            du_mm: 1.5,
            dv_mm: 1.5,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    };
    let grid = VolumeGrid::cube(128, 1.0);
    let views = g.to_views().expect("valid cone geometry");
    let op = Projector3::new(&views, &grid);
    let volume: Vec<f32> = (0..op.image_len())
        .map(|i| ((i as f32 * 0.001).sin() + 1.0) * 0.01)
        .collect();
    let subset: Vec<usize> = (0..op.view_count()).collect();
    let mut data = vec![0.0f32; op.view_count() * op.view_len()];
    let mut back = vec![0.0f32; op.image_len()];
    let cancel = Cancel::new();
    let threads = rayon::current_num_threads();
    for _ in 0..runs {
        let f = timed(|| {
            data.fill(0.0);
            op.forward(&volume, &subset, &mut data, &cancel)
                .expect("forward runs");
        });
        let b = timed(|| {
            op.back(&data, &subset, &mut back, &cancel)
                .expect("back runs");
        });
        // FDK of the same projections: a voxel-driven back projection of the same updates, with its
        // filtering, for comparison with the matched back projection.
        let proj = ndarray::ArrayView3::from_shape(views.shape(), &data[..]).expect("view shape");
        let params = FbpParams::default();
        let v = timed(|| {
            fdk(&views, proj, &grid, &params, unattended()).expect("FDK runs");
        });
        println!(
            "cone_pair ({threads} threads): forward CPU {:.3} s (wall {:.3} s), back CPU {:.3} s \
             (wall {:.3} s), FDK CPU {:.3} s (wall {:.3} s); checksum {:.6e}",
            f.0,
            f.1,
            b.0,
            b.1,
            v.0,
            v.1,
            back.iter().map(|&v| v as f64).sum::<f64>()
        );
    }
}

fn main() {
    ctrecon::config::limit_simd_from_env();
    let args: Vec<String> = std::env::args().collect();
    let case = args.get(1).map(String::as_str).unwrap_or("parallel");
    let runs: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    if case == "cone_pair" {
        cone_pair(runs);
        return;
    }
    let params = FbpParams::default();
    let threads = rayon::current_num_threads() as f64;
    let grid = ImageGrid::square(512, 0.5);
    let (updates, mut run): (f64, Box<dyn FnMut()>) = match case {
        "parallel" | "fan_arc" | "fan_flat" => {
            let views = match case {
                "parallel" => ParallelBeam {
                    angles: Angles::uniform(720, 180.0),
                    det_count: 725,
                    det_spacing_mm: 0.5,
                    det_offset_mm: 0.0,
                }
                .to_views()
                .expect("valid parallel geometry"),
                "fan_arc" => fan(FanDetector::Arc {
                    count: 800,
                    spacing_deg: 0.06,
                    offset_deg: 0.0,
                }),
                _ => fan(FanDetector::Flat {
                    count: 800,
                    spacing_mm: 1.06,
                    offset_mm: 0.0,
                }),
            };
            let sino = Array2::from_shape_fn(views.shape(), |(k, i)| {
                ((i as f32 * 0.01 + k as f32 * 0.003).sin() + 1.0) * 10.0
            });
            let updates = 512.0 * 512.0 * views.views.len() as f64;
            (
                updates,
                Box::new(move || {
                    fbp_2d(&views, sino.view(), &grid, &params, unattended()).expect("FBP runs");
                }),
            )
        }
        "helical" => {
            let (views, vol) = helical();
            let proj = Array3::from_shape_fn(views.shape(), |(k, r, i)| {
                ((i as f32 * 0.01 + r as f32 * 0.02 + k as f32 * 0.003).sin() + 1.0) * 10.0
            });
            let updates = helical_updates(&views, &vol);
            println!(
                "helical: {} views, {updates:.4e} voxel updates ({:.0} views per voxel on average)",
                views.views.len(),
                updates / vol.voxels() as f64
            );
            (
                updates,
                Box::new(move || {
                    fdk(&views, proj.view(), &vol, &params, unattended())
                        .expect("helical FBP runs");
                }),
            )
        }
        _ => {
            let n = if case == "fdk256" { 256 } else { 128 };
            let (g, vol) = cone(n);
            let views = g.to_views().expect("valid cone geometry");
            let proj = Array3::from_shape_fn(views.shape(), |(k, r, i)| {
                ((i as f32 * 0.01 + r as f32 * 0.02 + k as f32 * 0.003).sin() + 1.0) * 10.0
            });
            let updates = (n * n * n) as f64 * 360.0;
            (
                updates,
                Box::new(move || {
                    fdk(&views, proj.view(), &vol, &params, unattended()).expect("FDK runs");
                }),
            )
        }
    };
    for _ in 0..runs {
        let (wall0, cpu0) = (Instant::now(), cpu_seconds());
        run();
        let (wall, cpu) = (wall0.elapsed().as_secs_f64(), cpu_seconds() - cpu0);
        println!(
            "{case}: wall {wall:.3} s, CPU {cpu:.2} s ({threads} threads: ≈ {:.3} s on idle cores), \
             {:.3e} voxel-updates per CPU-second",
            cpu / threads,
            updates / cpu.max(1e-9)
        );
    }
}
