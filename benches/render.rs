//! Rendering: a 512 × 512 volume rendering (bone preset) and shaded surface display of the 133-slice LIDC-IDRI-0001
//! series (512² × 133, `.testdata/lidc`; a synthetic chest of the same size when the data is missing), and a
//! 36-frame VR rotation, on a 2-thread pool (the target machine has 2 cores). Throughput is in rays (pixels)
//! per second. Goals: one VR frame under 0.3 s, the 36-frame rotation under 6 s.

mod common;

use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use ctrecon::dicom::{ReadLimits, read_upload};
use ctrecon::recon::control::unattended;
use ctrecon::render::{
    Camera, Clip, Preset, Scene, Shading, SsdOptions, Surface, VrOptions, surface_render,
    volume_render, volume_render_frames,
};
use ctrecon::series::AssemblyOptions;
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

fn lidc() -> Option<Volume> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .filter_map(|p| {
            Some((
                p.file_name()?.to_string_lossy().into_owned(),
                std::fs::read(&p).ok()?,
            ))
        })
        .collect();
    files.sort();
    if files.len() != 133 {
        return None;
    }
    let mut up = read_upload(&files, &ReadLimits::default(), unattended()).ok()?;
    let g = up.series.remove(0);
    Some(
        g.assemble(&AssemblyOptions::default(), true, unattended())
            .ok()?
            .volume,
    )
}

/// A chest-like phantom of the LIDC series' size: body 40 HU, lungs −800 HU, spine and ribs 700 HU.
fn synthetic() -> Volume {
    let frame = Frame {
        spacing_mm: [0.7, 0.7, 2.5],
        origin_mm: [-179.0, -179.0, -165.0],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((133, 512, 512), |(k, j, i)| {
        let [x, y, z] = frame.position(k as f64, j as f64, i as f64);
        let e = |cx: f64, cy: f64, a: f64, b: f64| ((x - cx) / a).powi(2) + ((y - cy) / b).powi(2);
        let spine = e(0.0, 80.0, 18.0, 18.0) < 1.0;
        let rib = (e(0.0, 0.0, 150.0, 110.0) - 0.9).abs() < 0.04 && (z / 20.0).sin() > 0.3;
        if spine || rib {
            700.0
        } else if e(-70.0, 0.0, 55.0, 80.0) < 1.0 || e(70.0, 0.0, 55.0, 80.0) < 1.0 {
            -800.0
        } else if e(0.0, 0.0, 160.0, 120.0) < 1.0 {
            40.0
        } else {
            -1000.0
        }
    });
    Volume { data, frame }
}

fn bench(c: &mut Criterion) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("thread pool");
    let (vol, source) = match lidc() {
        Some(v) => (v, "lidc"),
        None => {
            eprintln!(
                "NOTE: .testdata/lidc is missing: rendering a synthetic chest of the same size"
            );
            (synthetic(), "synthetic")
        }
    };
    let scene = pool.install(|| Scene::new(&vol).expect("scene"));
    let rays = Camera::default()
        .rays(&vol.frame, vol.data.dim(), 512, 512, 4096)
        .expect("camera");
    let vr = VrOptions {
        transfer_function: Preset::Bone.transfer_function(),
        shading: Shading::default(),
        clip: Clip::default(),
        background: [0.0; 3],
        step_mm: None,
    };
    let ssd = SsdOptions {
        surfaces: vec![
            Surface {
                iso: -500.0,
                color: [0.9, 0.7, 0.6],
                opacity: 0.3,
            },
            Surface {
                iso: 300.0,
                color: [0.95, 0.92, 0.84],
                opacity: 1.0,
            },
        ],
        shading: Shading::default(),
        depth_cue: 0.4,
        clip: Clip::default(),
        background: [0.0; 3],
        step_mm: None,
    };
    let mut g = c.benchmark_group(format!("render_{source}"));
    g.sample_size(10);
    g.throughput(Throughput::Elements(512 * 512));
    g.bench_function("vr_bone_512x512", |b| {
        b.iter(|| pool.install(|| volume_render(&scene, &rays, &vr).expect("renders")))
    });
    g.bench_function("ssd_skin_over_bone_512x512", |b| {
        b.iter(|| pool.install(|| surface_render(&scene, &rays, &ssd).expect("renders")))
    });
    g.bench_function("bricks_and_sampler_setup", |b| {
        b.iter(|| pool.install(|| Scene::new(&vol).expect("scene").bricks.range.len()))
    });
    g.throughput(Throughput::Elements(36 * 512 * 512));
    g.bench_function("vr_bone_rotation_36x512x512", |b| {
        b.iter(|| {
            pool.install(|| {
                let rays: Vec<_> = (0..36)
                    .map(|k| {
                        let cam = Camera {
                            azimuth_deg: 10.0 * k as f64,
                            ..Camera::default()
                        };
                        cam.rays(&vol.frame, vol.data.dim(), 512, 512, 4096)
                            .expect("camera")
                    })
                    .collect();
                volume_render_frames(&scene, &rays, &vr)
                    .expect("renders")
                    .len()
            })
        })
    });
    g.finish();
    vtk_peer(&vol, &scene, &rays);
}

/// VTK's CPU ray caster (vtkFixedPointVolumeRayCastMapper) on the same volume, camera, transfer function and
/// step, when a Python with VTK is present (`scripts/install-peers.sh`); printed beside criterion's figures.
fn vtk_peer(vol: &Volume, scene: &Scene<'_>, rays: &ctrecon::render::ViewRays) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let Some(python) = common::vtk_python("VTK's CPU ray caster") else {
        return;
    };
    let Ok(dir) = tempfile::tempdir() else { return };
    let raw: Vec<u8> = vol.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    if std::fs::write(dir.path().join("volume.f32"), raw).is_err() {
        return;
    }
    let (nz, ny, nx) = vol.data.dim();
    let points: Vec<[f64; 5]> = Preset::Bone
        .transfer_function()
        .points
        .iter()
        .map(|p| [p.value, p.color[0], p.color[1], p.color[2], p.opacity])
        .collect();
    let spec = serde_json::json!({
        "volume": dir.path().join("volume.f32"),
        "dims": [nx, ny, nz], "spacing": vol.frame.spacing_mm, "origin": vol.frame.origin_mm,
        "camera": {"eye": rays.eye, "centre": scene.centre, "up": rays.up,
                   "parallel_scale": rays.height as f64 * rays.pixel / 2.0},
        "width": rays.width, "height": rays.height, "mode": "raycast", "points": points,
        "step_mm": scene.default_step(), "frames": 4,
    });
    if std::fs::write(dir.path().join("spec.json"), spec.to_string()).is_err() {
        return;
    }
    let out = std::process::Command::new(python)
        .arg(root.join("benches/render_vtk.py"))
        .arg(dir.path().join("spec.json"))
        .env("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
        .output();
    match out {
        Ok(o) if o.status.success() => println!(
            "VTK vtkFixedPointVolumeRayCastMapper, same picture: {}",
            String::from_utf8_lossy(&o.stdout).trim()
        ),
        Ok(o) => eprintln!("VTK failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("VTK did not start: {e}"),
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
