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
