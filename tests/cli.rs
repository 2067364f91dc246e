//! The `ctrecon` command line on files: phantoms, exact projections and their geometry sidecars.

use std::path::Path;
use std::process::Command;

use ctrecon::recon::geometry::{Geometry, Views};
use ctrecon::recon::grid::ImageGrid;
use ctrecon::recon::phantom::{Phantom2, Table2};
use ndarray::{Array2, ArrayD};
use ndarray_npy::ReadNpyExt;

use crate::common;

fn ctrecon(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(args)
        .output()
        .expect("run the ctrecon binary")
}

/// `ctrecon args`, which must succeed.
fn ctrecon_ok(args: &[&str]) {
    let run = ctrecon(args);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}

fn read(path: &Path) -> ArrayD<f32> {
    ArrayD::<f32>::read_npy(std::fs::File::open(path).expect("open npy")).expect("read npy")
}

#[test]
fn phantom_writes_the_exact_sinogram_and_its_geometry_sidecar() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sino.npy");
    let geometry = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/geometries/parallel.json");
    ctrecon_ok(&[
        "phantom",
        "--geometry",
        geometry,
        "--fov-mm",
        "256",
        "--out",
        out.to_str().unwrap(),
    ]);
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
    ctrecon_ok(&[
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
    let img = read(&out).into_dimensionality::<ndarray::Ix2>().unwrap();
    let want: Array2<f32> = Phantom2::from_table(Table2::ModifiedSheppLogan, 64.0)
        .rasterize(&ImageGrid::square(64, 2.0), 3);
    assert_eq!(img, want);
}

/// `args` with `--out out` fail with a message, without a panic, and write nothing.
fn refused<'a>(mut args: Vec<&'a str>, out: &'a Path) {
    args.extend(["--out", out.to_str().unwrap()]);
    let run = ctrecon(&args);
    assert!(!run.status.success(), "{args:?} succeeded");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    assert!(!stderr.trim().is_empty(), "{args:?}: no message");
    assert!(!out.exists(), "{args:?} wrote a file");
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
        refused(args, &out);
    }
}

/// A `[z][y][x]` volume of `n³` voxels of `voxel` mm (x, y, z) holding, at voxel centres, the distance inside
/// the nearest of the balls `(centre mm, radius mm)` (negative outside all).
fn balls(n: usize, voxel: [f64; 3], balls: &[([f64; 3], f64)]) -> ndarray::Array3<f32> {
    ndarray::Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        let p = [
            i as f64 * voxel[0],
            j as f64 * voxel[1],
            k as f64 * voxel[2],
        ];
        balls
            .iter()
            .map(|(c, r)| {
                r - ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt()
            })
            .fold(f64::NEG_INFINITY, f64::max) as f32
    })
}

#[test]
fn mesh_writes_the_stl_of_the_iso_surface_in_millimetres() {
    use ndarray_npy::WriteNpyExt;
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("balls.npy");
    let voxel = [0.5, 0.6, 0.8];
    // A big ball (radius 9 mm) and a small one (4 mm) apart.
    let (big, small) = (([12.0, 12.0, 14.0], 9.0), ([22.0, 26.0, 34.0], 4.0));
    balls(56, voxel, &[big, small])
        .write_npy(std::fs::File::create(&input).unwrap())
        .unwrap();
    let ball = |r: f64| 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    for (extra, want) in [
        (vec![], ball(9.0)),
        (vec!["--all-components"], ball(9.0) + ball(4.0)),
    ] {
        let out = dir.path().join("surface.stl");
        let mut args = vec![
            "mesh",
            "--input",
            input.to_str().unwrap(),
            "--iso",
            "0",
            "--voxel-mm",
            "0.5",
            "0.6",
            "0.8",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(extra.iter().copied());
        ctrecon_ok(&args);
        let mesh = common::weld_stl(&std::fs::read(&out).unwrap());
        let got = mesh.volume_mm3();
        assert!(
            (got - want).abs() / want < 0.02,
            "{extra:?}: {got} mm³, want {want}"
        );
        // The big ball sits where it was put, in millimetres from voxel [0][0][0].
        let xs = mesh.vertices.iter().map(|p| p[0] as f64);
        let min_x = xs.clone().fold(f64::INFINITY, f64::min);
        assert!(
            (min_x - (12.0 - 9.0)).abs() < 0.3,
            "{extra:?}: min x {min_x}"
        );
        let t = mesh.topology();
        assert!(t.closed && t.manifold, "{extra:?}: {t:?}");
    }
    // A negative iso-value is a value, not an option.
    let out = dir.path().join("shell.stl");
    ctrecon_ok(&[
        "mesh",
        "--input",
        input.to_str().unwrap(),
        "--iso",
        "-2",
        "--out",
        out.to_str().unwrap(),
    ]);
}

#[test]
fn mesh_refuses_bad_input_with_a_message_and_writes_nothing() {
    use ndarray_npy::WriteNpyExt;
    let dir = tempfile::tempdir().unwrap();
    let image = dir.path().join("image.npy");
    ndarray::Array2::<f32>::zeros((8, 8))
        .write_npy(std::fs::File::create(&image).unwrap())
        .unwrap();
    let volume = dir.path().join("volume.npy");
    balls(8, [1.0; 3], &[([4.0; 3], 2.0)])
        .write_npy(std::fs::File::create(&volume).unwrap())
        .unwrap();
    let out = dir.path().join("out.stl");
    let (image, volume) = (image.to_str().unwrap(), volume.to_str().unwrap());
    for args in [
        vec!["mesh", "--input", image, "--iso", "0"],
        vec!["mesh", "--input", "/nonexistent/v.npy", "--iso", "0"],
        vec![
            "mesh",
            "--input",
            volume,
            "--iso",
            "0",
            "--voxel-mm",
            "0",
            "1",
            "1",
        ],
        vec![
            "mesh",
            "--input",
            volume,
            "--iso",
            "0",
            "--voxel-mm",
            "1",
            "1",
        ],
        vec!["mesh", "--input", volume, "--iso", "nan"],
    ] {
        refused(args, &out);
    }
}

/// The geometries under docs/geometries/ ship inside the binary: `--geometry fan_arc` works from any
/// folder, gives the file's geometry, and an unknown name says which names exist.
#[test]
fn built_in_geometries_work_from_any_folder() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["parallel", "fan_arc", "cone", "parallel3d", "helical"] {
        let run = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
            .args(["phantom", "--geometry", name, "--out", "p.npy"])
            .current_dir(dir.path())
            .output()
            .expect("run ctrecon");
        assert!(
            run.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&run.stderr)
        );
        let written: Geometry = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("p.json")).expect("sidecar"),
        )
        .expect("geometry");
        let file = format!("{}/docs/geometries/{name}.json", env!("CARGO_MANIFEST_DIR"));
        let shipped: Geometry =
            serde_json::from_str(&std::fs::read_to_string(file).expect("docs file")).expect("json");
        assert_eq!(written, shipped, "{name}");
        let views = written.to_views().expect("views");
        assert_eq!(read(&dir.path().join("p.npy")).shape(), views.data_shape());
    }
    let run = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(["phantom", "--geometry", "fan_flat", "--out", "p.npy"])
        .current_dir(dir.path())
        .output()
        .expect("run ctrecon");
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("fan_flat") && err.contains("parallel, fan_arc, cone"),
        "{err}"
    );
}
