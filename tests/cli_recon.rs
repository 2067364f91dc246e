//! `ctrecon phantom` → `ctrecon recon` on files: the reconstruction of the exact sinogram matches the
//! phantom, the PNG has the slice's size, bad input fails with a message and a non-zero status.

use std::path::Path;
use std::process::Command;

use ctrecon::recon::grid::ImageGrid;
use ctrecon::recon::metrics::{inscribed_disk, rmse};
use ctrecon::recon::phantom::{Phantom2, Table2};
use ndarray::{ArrayD, Ix2};
use ndarray_npy::ReadNpyExt;

fn ctrecon(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(args)
        .output()
        .expect("run the ctrecon binary")
}

fn read(path: &Path) -> ArrayD<f32> {
    ArrayD::<f32>::read_npy(std::fs::File::open(path).expect("open npy")).expect("read npy")
}

#[test]
fn phantom_then_recon_reproduces_the_shepp_logan_phantom_and_writes_a_png() {
    let dir = tempfile::tempdir().unwrap();
    let sino = dir.path().join("sino.npy");
    let out = dir.path().join("recon.npy");
    let png = dir.path().join("recon.png");
    let geometry = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/geometries/parallel.json");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let run = ctrecon(&[
        "phantom",
        "--geometry",
        geometry,
        "--fov-mm",
        "256",
        "--out",
        &s(&sino),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let run = ctrecon(&[
        "recon",
        "--input",
        &s(&sino),
        "--algorithm",
        "fbp",
        "--size",
        "256",
        "--pixel-mm",
        "1",
        "--output",
        &s(&out),
        "--png",
        &s(&png),
        "--ww",
        "0.4",
        "--wl",
        "0.2",
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let image = read(&out).into_dimensionality::<Ix2>().unwrap();
    let grid = ImageGrid::square(256, 1.0);
    let reference = Phantom2::from_table(Table2::ModifiedSheppLogan, 128.0).rasterize(&grid, 4);
    let mask = inscribed_disk(256, 256);
    let e = rmse(image.view(), reference.view(), Some(mask.view())).unwrap();
    println!("CLI parallel FBP RMSE {e:.5}");
    // The library's own test reaches 0.0217 on this grid (tests/analytic_shepp_logan.rs).
    assert!(e <= 0.022, "RMSE {e}");
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    // IHDR: width and height, big-endian, at bytes 16..24.
    assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 256);
    assert_eq!(u32::from_be_bytes(bytes[20..24].try_into().unwrap()), 256);
    // The PNG names its screen sides: the image axes, row 0 at the smallest y.
    let reader = png::Decoder::new(std::io::Cursor::new(&bytes))
        .read_info()
        .unwrap();
    let text = &reader.info().uncompressed_latin1_text;
    let o = text.iter().find(|t| t.keyword == "Orientation").unwrap();
    let o: serde_json::Value = serde_json::from_str(&o.text).unwrap();
    assert_eq!(
        o,
        serde_json::json!({"left": "-x", "right": "+x", "top": "-y", "bottom": "+y"})
    );
}

#[test]
fn recon_with_a_hann_filter_via_params_json_and_a_cone_volume_slice_png() {
    let dir = tempfile::tempdir().unwrap();
    let proj = dir.path().join("proj.npy");
    let geometry = dir.path().join("cone.json");
    std::fs::write(
        &geometry,
        r#"{"type": "cone", "angles": {"count": 90}, "dso_mm": 400, "dsd_mm": 800,
            "detector": {"nu": 96, "nv": 64, "du_mm": 2.0, "dv_mm": 2.0}}"#,
    )
    .unwrap();
    let out = dir.path().join("vol.npy");
    let png = dir.path().join("slice.png");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let run = ctrecon(&[
        "phantom",
        "--geometry",
        &s(&geometry),
        "--fov-mm",
        "64",
        "--out",
        &s(&proj),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let run = ctrecon(&[
        "recon",
        "--data",
        &s(&proj),
        "--algorithm",
        "fdk",
        "--params",
        r#"{"filter": "hann"}"#,
        "--size",
        "32",
        "--pixel-mm",
        "2",
        "--out",
        &s(&out),
        "--png",
        &s(&png),
        "--slice",
        "10",
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert_eq!(read(&out).shape(), &[32, 32, 32]);
    assert!(std::fs::metadata(&png).unwrap().len() > 50);
}

#[test]
fn bad_input_fails_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing.npy");
    let out = dir.path().join("out.npy");
    let run = ctrecon(&[
        "recon",
        "--input",
        missing.to_str().unwrap(),
        "--output",
        out.to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("error"));
    let run = ctrecon(&[
        "recon",
        "--input",
        missing.to_str().unwrap(),
        "--geometry",
        concat!(env!("CARGO_MANIFEST_DIR"), "/docs/geometries/parallel.json"),
        "--algorithm",
        "fbp",
        "--params",
        r#"{"cutof": 0.5}"#,
        "--output",
        out.to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("cutof"));
}

/// `CTRECON_SIMD` caps the kernels of every command: `phantom` and `recon` under each cap give the same
/// images within f32 rounding, and `worker` takes the variable too (it stops for want of a shared database,
/// not for an unknown setting).
#[test]
fn every_command_takes_the_simd_cap_and_the_results_agree_within_rounding() {
    let dir = tempfile::tempdir().unwrap();
    let geometry = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/geometries/parallel.json");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let run = |simd: Option<&str>, args: &[&str]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_ctrecon"));
        cmd.args(args)
            .env_remove("CTRECON_SIMD")
            .env_remove("CTRECON_DATABASE_URL")
            .env("CTRECON_DATA_DIR", dir.path().join("data"));
        if let Some(v) = simd {
            cmd.env("CTRECON_SIMD", v);
        }
        let out = cmd.output().expect("run the ctrecon binary");
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    let mut images = Vec::new();
    for simd in [None, Some("avx2"), Some("scalar")] {
        let tag = simd.unwrap_or("native");
        let sino = dir.path().join(format!("sino-{tag}.npy"));
        let out = dir.path().join(format!("recon-{tag}.npy"));
        let (ok, err) = run(
            simd,
            &[
                "phantom",
                "--geometry",
                geometry,
                "--fov-mm",
                "256",
                "--out",
                &s(&sino),
            ],
        );
        assert!(ok, "phantom with CTRECON_SIMD={tag}: {err}");
        let (ok, err) = run(
            simd,
            &[
                "recon",
                "--input",
                &s(&sino),
                "--algorithm",
                "fbp",
                "--size",
                "128",
                "--pixel-mm",
                "2",
                "--output",
                &s(&out),
            ],
        );
        assert!(ok, "recon with CTRECON_SIMD={tag}: {err}");
        images.push((tag, read(&sino), read(&out)));
    }
    let (_, sino0, image0) = &images[0];
    let peak = image0.iter().fold(0f32, |m, v| m.max(v.abs()));
    for (tag, sino, image) in &images[1..] {
        let worst = |a: &ArrayD<f32>, b: &ArrayD<f32>| {
            a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()))
        };
        assert_eq!(sino.shape(), sino0.shape());
        assert!(
            worst(sino, sino0) <= 1e-5,
            "{tag}: the phantom's sinogram differs"
        );
        assert!(
            worst(image, image0) <= 1e-4 * peak.max(1.0),
            "{tag}: FBP differs by {} (peak {peak})",
            worst(image, image0)
        );
    }
    let (ok, err) = run(Some("avx2"), &["worker", "--health-bind", "127.0.0.1:0"]);
    assert!(!ok, "a worker without a shared database does not start");
    assert!(!err.contains("unknown setting"), "{err}");
    assert!(err.contains("needs a shared job database"), "{err}");
}
