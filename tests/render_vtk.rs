//! Side by side with VTK: the same volume, orthographic camera and iso-value rendered offscreen by VTK
//! (`benches/render_vtk.py`: flying edges + OpenGL) and by ctrecon's shaded surface display; the silhouettes
//! must agree (intersection over union ≥ 0.98). Runs when Python with VTK is present (`scripts/install-peers.sh`
//! puts it in `.venv-peers/`); with `CTRECON_REQUIRE_PEERS=1` (CI) a missing VTK fails the test.

use std::path::{Path, PathBuf};
use std::process::Command;

use ctrecon::render::{
    Camera, Clip, NamedView, Scene, Shading, SsdOptions, Surface, surface_render, volume_bounds,
};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

/// The Python that has VTK: `.venv-peers/bin/python`, else `python3`; `None` when neither imports vtk.
fn python_with_vtk() -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-peers/bin/python");
    [venv, PathBuf::from("python3")].into_iter().find(|py| {
        Command::new(py)
            .args(["-c", "import vtk, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// An ellipsoid and an overlapping ball as a signed-distance-like field (inside positive, mm), 1 mm voxels.
fn phantom() -> Volume {
    let n = [72usize, 80, 88]; // z, y, x
    let frame = Frame {
        spacing_mm: [1.0, 1.0, 1.0],
        origin_mm: [-43.5, -39.5, -35.5],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((n[0], n[1], n[2]), |(k, j, i)| {
        let [x, y, z] = frame.position(k as f64, j as f64, i as f64);
        let q = ((x / 32.0).powi(2) + (y / 22.0).powi(2) + (z / 26.0).powi(2)).sqrt();
        let ellipsoid = (1.0 - q) * 22.0;
        let ball = 13.0 - ((x - 22.0).powi(2) + (y + 14.0).powi(2) + (z - 16.0).powi(2)).sqrt();
        ellipsoid.max(ball) as f32
    });
    Volume { data, frame }
}

#[test]
fn ctrecon_and_vtk_draw_the_same_silhouette_of_an_iso_surface() {
    let Some(python) = python_with_vtk() else {
        if std::env::var("CTRECON_REQUIRE_PEERS").as_deref() == Ok("1") {
            panic!("VTK is required (CTRECON_REQUIRE_PEERS=1): run scripts/install-peers.sh");
        }
        eprintln!("SKIPPED: no Python with VTK (run scripts/install-peers.sh)");
        return;
    };
    let vol = phantom();
    let (w, h) = (200usize, 160usize);
    let cam = Camera {
        view: NamedView::Anterior,
        azimuth_deg: 30.0,
        elevation_deg: 20.0,
        zoom: 1.3,
        ..Camera::default()
    };
    let rays = cam.rays(&vol.frame, vol.data.dim(), w, h, 4096).unwrap();
    let scene = Scene::new(&vol).unwrap();
    let opts = SsdOptions {
        surfaces: vec![Surface {
            iso: 0.0,
            color: [1.0; 3],
            opacity: 1.0,
        }],
        shading: Shading::default(),
        depth_cue: 0.0,
        clip: Clip::default(),
        background: [0.0; 3],
        step_mm: None,
    };
    let ours: Vec<bool> = surface_render(&scene, &rays, &opts)
        .unwrap()
        .depth_mm
        .iter()
        .map(|d| d.is_finite())
        .collect();

    let dir = tempfile::tempdir().unwrap();
    let raw: Vec<u8> = vol.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.path().join("volume.f32"), raw).unwrap();
    let (nz, ny, nx) = vol.data.dim();
    let (centre, _) = volume_bounds(&vol.frame, vol.data.dim());
    let spec = serde_json::json!({
        "volume": dir.path().join("volume.f32"),
        "dims": [nx, ny, nz],
        "spacing": vol.frame.spacing_mm,
        "origin": vol.frame.origin_mm,
        "camera": {"eye": rays.eye, "centre": centre, "up": rays.up,
                   "parallel_scale": h as f64 * rays.pixel / 2.0},
        "width": w, "height": h, "iso": 0.0, "mode": "silhouette",
        "out": dir.path().join("silhouette.u8"),
    });
    std::fs::write(dir.path().join("spec.json"), spec.to_string()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/render_vtk.py");
    let out = Command::new(&python)
        .arg(&script)
        .arg(dir.path().join("spec.json"))
        .env("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "VTK failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    println!("{}", String::from_utf8_lossy(&out.stdout).trim());
    let theirs: Vec<bool> = std::fs::read(dir.path().join("silhouette.u8"))
        .unwrap()
        .iter()
        .map(|&v| v > 127)
        .collect();
    assert_eq!(theirs.len(), w * h);
    let both = ours.iter().zip(&theirs).filter(|(a, b)| **a && **b).count();
    let either = ours.iter().zip(&theirs).filter(|(a, b)| **a || **b).count();
    let iou = both as f64 / either as f64;
    println!(
        "silhouette IoU ctrecon vs VTK: {iou:.4} ({both} of {either} pixels; ctrecon {}, VTK {})",
        ours.iter().filter(|&&a| a).count(),
        theirs.iter().filter(|&&a| a).count()
    );
    assert!(either > 5000, "the surface covers {either} pixels");
    assert!(iou >= 0.98, "IoU {iou:.4}");
}
