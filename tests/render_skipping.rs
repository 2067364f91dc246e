//! Cell-level empty-space skipping leaves the pictures as they were: every picture of a set (the four VR presets,
//! a clipped VR, two rotation frames, the two-surface SSD and a clipped SSD) rendered with the scene's cell
//! occupancy and with the brick grid alone must agree pixel for pixel within one grey level, with the same hit
//! mask and first-hit depths. On a noisy synthetic chest always, and on LIDC-IDRI-0001 when `.testdata/lidc` is
//! present (else one skip line, or a failure with `CTRECON_REQUIRE_TEST_DATA=1`).
//!
//! `cargo test --test kernels render_skipping:: -- --ignored --nocapture` times both paths on LIDC at 512 × 512,
//! interleaved, on a 2-thread pool, and prints the comparison figures (the figures in `benches/README.md`).

use std::path::Path;
use std::time::Instant;

use ctrecon::dicom::{ReadLimits, read_upload};
use ctrecon::recon::control::unattended;
use ctrecon::render::{
    Camera, Clip, ClipBox, ClipPlane, Keep, Preset, RgbImage, Scene, Shading, SsdOptions, Surface,
    VrOptions, surface_render, volume_render,
};
use ctrecon::series::AssemblyOptions;
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

fn lidc() -> Option<Volume> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if !dir.is_dir() {
        if std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() == Ok("1") {
            panic!(
                "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
                dir.display()
            );
        }
        eprintln!(
            "SKIPPED: {} is missing (run scripts/fetch-test-data.sh)",
            dir.display()
        );
        return None;
    }
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    files.sort();
    let mut up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    let g = up.series.remove(0);
    Some(
        g.assemble(&AssemblyOptions::default(), true, unattended())
            .unwrap()
            .volume,
    )
}

/// A chest-like phantom (body 40 HU, lungs −800 HU, spine and ribs 700 HU, air −1000 HU) with ±250 HU of
/// deterministic noise, so that noise crosses the bone and lung thresholds inside most bricks, as in a
/// low-dose series.
fn noisy_chest(n: [usize; 3]) -> Volume {
    let frame = Frame {
        spacing_mm: [1.4, 1.4, 2.5],
        origin_mm: [
            -0.7 * (n[2] - 1) as f64,
            -0.7 * (n[1] - 1) as f64,
            -1.25 * (n[0] - 1) as f64,
        ],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((n[0], n[1], n[2]), |(k, j, i)| {
        let [x, y, z] = frame.position(k as f64, j as f64, i as f64);
        let e = |cx: f64, cy: f64, a: f64, b: f64| ((x - cx) / a).powi(2) + ((y - cy) / b).powi(2);
        let spine = e(0.0, 60.0, 14.0, 14.0) < 1.0;
        let rib = (e(0.0, 0.0, 120.0, 85.0) - 0.9).abs() < 0.05 && (z / 15.0).sin() > 0.3;
        let base = if spine || rib {
            700.0
        } else if e(-55.0, 0.0, 42.0, 60.0) < 1.0 || e(55.0, 0.0, 42.0, 60.0) < 1.0 {
            -800.0
        } else if e(0.0, 0.0, 125.0, 95.0) < 1.0 {
            40.0
        } else {
            -1000.0
        };
        let h = ((k * 73_856_093) ^ (j * 19_349_663) ^ (i * 83_492_791)) % 1_000_003;
        let noise = (h as f64 / 1_000_003.0 - 0.5) * 500.0;
        (base + if base > -1000.0 { noise } else { 0.0 }) as f32
    });
    Volume { data, frame }
}

fn vr(preset: Preset, clip: Clip) -> VrOptions {
    VrOptions {
        transfer_function: preset.transfer_function(),
        shading: Shading::default(),
        clip,
        background: [0.0; 3],
        step_mm: None,
    }
}

fn ssd(clip: Clip) -> SsdOptions {
    SsdOptions {
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
        clip,
        background: [0.0; 3],
        step_mm: None,
    }
}

/// One picture of the comparison set.
enum Job {
    Vr(Camera, VrOptions),
    Ssd(Camera, SsdOptions),
}

fn set(scene: &Scene<'_>) -> Vec<(String, Job)> {
    let c = scene.centre;
    let turned = |az: f64, el: f64| Camera {
        azimuth_deg: az,
        elevation_deg: el,
        ..Camera::default()
    };
    let mut out: Vec<(String, Job)> = Preset::ALL
        .iter()
        .map(|&p| {
            (
                format!("vr {} az 35", p.name()),
                Job::Vr(turned(35.0, 10.0), vr(p, Clip::default())),
            )
        })
        .collect();
    let front_cut = Clip {
        planes: vec![ClipPlane {
            point_mm: c,
            normal: [0.0, 1.0, 0.0],
        }],
        boxes: vec![],
    };
    out.push((
        "vr bone, front half cut away".into(),
        Job::Vr(turned(20.0, 0.0), vr(Preset::Bone, front_cut.clone())),
    ));
    for az in [90.0, 250.0] {
        out.push((
            format!("vr bone rotation frame az {az}"),
            Job::Vr(turned(az, 0.0), vr(Preset::Bone, Clip::default())),
        ));
    }
    out.push((
        "ssd skin 30 % over bone".into(),
        Job::Ssd(turned(0.0, 0.0), ssd(Clip::default())),
    ));
    let box_out = Clip {
        planes: vec![],
        boxes: vec![ClipBox {
            centre_mm: [c[0] + 40.0, c[1] - 60.0, c[2]],
            half_size_mm: [60.0, 60.0, 80.0],
            axes: None,
            keep: Keep::Outside,
        }],
    };
    out.push((
        "ssd skin over bone, box cut out".into(),
        Job::Ssd(turned(-30.0, 15.0), ssd(box_out)),
    ));
    out
}

fn render(scene: &Scene<'_>, vol: &Volume, job: &Job, size: usize) -> RgbImage {
    let rays = |cam: &Camera| {
        cam.rays(&vol.frame, vol.data.dim(), size, size, 4096)
            .unwrap()
    };
    match job {
        Job::Vr(cam, o) => volume_render(scene, &rays(cam), o).unwrap(),
        Job::Ssd(cam, o) => surface_render(scene, &rays(cam), o).unwrap(),
    }
}

/// How two pictures differ.
#[derive(Debug)]
struct Diff {
    max_grey: u8,
    pixels_differing: usize,
    psnr_db: f64,
    /// Intersection over union of the pixels that hit something.
    hit_iou: f64,
    /// Largest first-hit depth difference (mm) where both hit.
    max_depth_mm: f32,
}

fn diff(a: &RgbImage, b: &RgbImage) -> Diff {
    let mut se = 0.0f64;
    let mut max_grey = 0u8;
    for (x, y) in a.rgb.iter().zip(&b.rgb) {
        let d = x.abs_diff(*y);
        max_grey = max_grey.max(d);
        se += f64::from(d) * f64::from(d);
    }
    let pixels_differing = a
        .rgb
        .chunks(3)
        .zip(b.rgb.chunks(3))
        .filter(|(x, y)| x != y)
        .count();
    let mse = se / a.rgb.len() as f64;
    let psnr_db = if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    };
    let (mut both, mut either, mut max_depth_mm) = (0usize, 0usize, 0.0f32);
    for (da, db) in a.depth_mm.iter().zip(&b.depth_mm) {
        let (ha, hb) = (!da.is_nan(), !db.is_nan());
        both += usize::from(ha && hb);
        either += usize::from(ha || hb);
        if ha && hb {
            max_depth_mm = max_depth_mm.max((da - db).abs());
        }
    }
    Diff {
        max_grey,
        pixels_differing,
        psnr_db,
        hit_iou: if either == 0 {
            1.0
        } else {
            both as f64 / either as f64
        },
        max_depth_mm,
    }
}

/// Renders the set with and without cell skipping and checks the pictures agree.
fn compare(vol: &Volume, size: usize) {
    let mut scene = Scene::new(vol).unwrap();
    let mut some_hits = 0;
    for (name, job) in set(&scene) {
        scene.cell_skipping = false;
        let old = render(&scene, vol, &job, size);
        scene.cell_skipping = true;
        let new = render(&scene, vol, &job, size);
        let d = diff(&old, &new);
        eprintln!(
            "{name}: at most {} grey levels apart, {} pixels differ, PSNR {:.1} dB, hit IoU {:.4}, depths within {:.4} mm",
            d.max_grey, d.pixels_differing, d.psnr_db, d.hit_iou, d.max_depth_mm
        );
        assert!(
            d.max_grey <= 1 && d.hit_iou == 1.0 && d.max_depth_mm <= 1e-3,
            "{name}: {d:?}"
        );
        some_hits += usize::from(new.depth_mm.iter().any(|x| !x.is_nan()));
    }
    assert!(some_hits >= 8, "only {some_hits} pictures show anything");
    // The occupancies were built and skip most cells of the noisy body for the bone preset.
    let counts = scene.occupancy_counts();
    assert!(!counts.is_empty());
    eprintln!("occupied cells (kept occupancies): {counts:?}");
}

#[test]
fn cell_skipping_leaves_the_pictures_of_a_noisy_chest_unchanged() {
    compare(&noisy_chest([40, 180, 200]), 160);
}

#[test]
fn cell_skipping_leaves_the_lidc_pictures_unchanged() {
    let Some(vol) = lidc() else { return };
    compare(&vol, 256);
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

/// Wall time (s) of `f`.
fn time<T>(f: impl FnOnce() -> T) -> (f64, T) {
    let t = Instant::now();
    let out = f();
    (t.elapsed().as_secs_f64(), out)
}

#[test]
#[ignore = "timing: run with --ignored --nocapture"]
fn timing_with_and_without_cell_skipping_on_lidc() {
    let Some(vol) = lidc() else { return };
    let rounds: usize = std::env::var("ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);
    let frames: usize = std::env::var("FRAMES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(36);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    pool.install(|| {
        let cam = Camera::default();
        let bone = vr(Preset::Bone, Clip::default());
        let ssd = ssd(Clip::default());
        let rays = cam
            .rays(&vol.frame, vol.data.dim(), 512, 512, 4096)
            .unwrap();
        {
            // Geometry of the anterior view: rays that enter the volume's box and their samples in it.
            let scene = Scene::new(&vol).unwrap();
            let step = scene.default_step();
            let (mut hit, mut samples) = (0usize, 0.0f64);
            for r in 0..512 {
                for c in 0..512 {
                    let (o, d) = rays.ray(r as f64, c as f64);
                    if let Some((b0, b1)) = scene.sampler.box_interval(o, d) {
                        hit += 1;
                        samples += (b1 - b0.max(0.0)) / step;
                    }
                }
            }
            println!(
                "anterior 512 × 512: {hit} rays enter the box, {:.0} samples each on average ({:.1} M in all, step {step:.3} mm)",
                samples / hit as f64,
                samples / 1e6
            );
        }
        for round in 0..rounds {
            for skipping in [false, true] {
                let label = if skipping { "cells" } else { "bricks" };
                let (t_scene, mut scene) = time(|| Scene::new(&vol).unwrap());
                scene.cell_skipping = skipping;
                let load0 = load_average();
                // The first VR call builds the bone occupancy (kept for the later frames).
                let (t_vr_first, _) = time(|| volume_render(&scene, &rays, &bone).unwrap());
                let (t_vr, _) = time(|| volume_render(&scene, &rays, &bone).unwrap());
                let (t_ssd_first, _) = time(|| surface_render(&scene, &rays, &ssd).unwrap());
                let (t_ssd, _) = time(|| surface_render(&scene, &rays, &ssd).unwrap());
                let (t_rot, _) = time(|| {
                    for k in 0..frames {
                        let cam = Camera {
                            azimuth_deg: 360.0 / frames as f64 * k as f64,
                            ..Camera::default()
                        };
                        let r = cam
                            .rays(&vol.frame, vol.data.dim(), 512, 512, 4096)
                            .unwrap();
                        volume_render(&scene, &r, &bone).unwrap();
                    }
                });
                println!(
                    "round {round} {label:6}: scene {:.0} ms; VR bone first {:.0} ms, again {:.0} ms ({:.0} k rays/s); \
                     SSD first {:.0} ms, again {:.0} ms; rotation {frames} frames {:.2} s ({:.0} ms a frame); \
                     load {load0} → {}; occupied cells {:?}",
                    t_scene * 1e3,
                    t_vr_first * 1e3,
                    t_vr * 1e3,
                    512.0 * 512.0 / t_vr / 1e3,
                    t_ssd_first * 1e3,
                    t_ssd * 1e3,
                    t_rot,
                    t_rot / frames as f64 * 1e3,
                    load_average(),
                    scene.occupancy_counts(),
                );
            }
        }
        let scene = Scene::new(&vol).unwrap();
        vtk_raycast(&vol, &scene, &rays);
    });
}

/// VTK's CPU ray caster (`vtkFixedPointVolumeRayCastMapper`, `benches/render_vtk.py`) on the same volume,
/// camera, bone transfer function and step, timed over 4 frames turned 90° apart, when `VTK_PYTHON` (or
/// `.venv-peers/bin/python`, or `python3`) imports vtk.
fn vtk_raycast(vol: &Volume, scene: &Scene<'_>, rays: &ctrecon::render::ViewRays) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let candidates = [
        std::env::var_os("VTK_PYTHON").map(std::path::PathBuf::from),
        Some(root.join(".venv-peers/bin/python")),
        Some("python3".into()),
    ];
    let Some(python) = candidates.into_iter().flatten().find(|py| {
        std::process::Command::new(py)
            .args(["-c", "import vtk, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    }) else {
        println!("no Python with VTK: VTK's CPU ray caster not timed");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let raw: Vec<u8> = vol.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.path().join("volume.f32"), raw).unwrap();
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
    std::fs::write(dir.path().join("spec.json"), spec.to_string()).unwrap();
    let load0 = load_average();
    let out = std::process::Command::new(python)
        .arg(root.join("benches/render_vtk.py"))
        .arg(dir.path().join("spec.json"))
        .env("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
        .output()
        .unwrap();
    println!(
        "VTK vtkFixedPointVolumeRayCastMapper, same picture: {} {}; load {load0} → {}",
        String::from_utf8_lossy(&out.stdout).trim(),
        String::from_utf8_lossy(&out.stderr).trim(),
        load_average()
    );
}
