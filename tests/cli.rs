//! The `ctrecon` command line on files: phantoms, exact projections and their geometry sidecars.

use std::path::Path;
use std::process::Command;

use ctrecon::recon::geometry::{Geometry, Views};
use ctrecon::recon::grid::ImageGrid;
use ctrecon::recon::phantom::{Phantom2, Table2};
use ndarray::{Array2, ArrayD};
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
fn phantom_writes_the_exact_sinogram_and_its_geometry_sidecar() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sino.npy");
    let geometry = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/geometries/parallel.json");
    let run = ctrecon(&[
        "phantom",
        "--geometry",
        geometry,
        "--fov-mm",
        "256",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let sino = read(&out);
    assert_eq!(sino.shape(), &[360, 363]);

    // The sidecar is the geometry it was made with, and the data are the exact projections.
    let sidecar: Geometry =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("sino.json")).unwrap())
            .unwrap();
    let given: Geometry =
        serde_json::from_str(&std::fs::read_to_string(geometry).unwrap()).unwrap();
    assert_eq!(sidecar, given);
    let Views::D2(views) = given.to_views().unwrap() else {
        panic!("parallel geometry is 2D")
    };
    let want = Phantom2::from_table(Table2::ModifiedSheppLogan, 128.0).project(&views);
    let worst = sino
        .iter()
        .zip(want.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst < 1e-5,
        "largest difference from the exact projection: {worst}"
    );
    // The head is 0.92·128 mm tall: the central ray at θ = 0 crosses about 2·0.92·128·μ.
    assert!(sino[[0, 181]] > 10.0, "central ray {}", sino[[0, 181]]);
}

#[test]
fn phantom_writes_a_supersampled_image_on_the_requested_grid() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("img.npy");
    let run = ctrecon(&[
        "phantom",
        "--size",
        "64",
        "--fov-mm",
        "128",
        "--supersample",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let img = read(&out).into_dimensionality::<ndarray::Ix2>().unwrap();
    let want: Array2<f32> = Phantom2::from_table(Table2::ModifiedSheppLogan, 64.0)
        .rasterize(&ImageGrid::square(64, 2.0), 3);
    assert_eq!(img, want);
}

#[test]
fn phantom_refuses_bad_options_with_a_message_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("img.npy");
    for args in [
        vec!["phantom", "--supersample", "0"],
        vec!["phantom", "--size", "0"],
        vec!["phantom", "--fov-mm", "-3"],
        vec!["phantom", "--dims", "4"],
        vec!["phantom", "--geometry", "/nonexistent/geometry.json"],
    ] {
        let mut args = args;
        args.extend(["--out", out.to_str().unwrap()]);
        let run = ctrecon(&args);
        assert!(!run.status.success(), "{args:?} succeeded");
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
        assert!(!stderr.trim().is_empty(), "{args:?}: no message");
        assert!(!out.exists(), "{args:?} wrote a file");
    }
}
