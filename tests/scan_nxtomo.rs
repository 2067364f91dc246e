//! NeXus NXtomo scans (HDF5) written by ESRF's `nxtomo` package (its `NXtomo` API, with h5py for the
//! rewrites: chunked + deflate data, broken files) and read back by `ctrecon::scans`: every frame, angle,
//! dark and flat exactly, the geometry and the provenance; an off-centre ball simulated as a parallel beam
//! (raw counts with darks and flats that drift between the flat series, an off-centre rotation axis)
//! reconstructed by FBP where it was, through the library, `ctrecon recon` and `POST /v1/scans` + a job,
//! the centre found from the views; bad files refused naming the file and the HDF5 path. The other way
//! round, nxtomo reads the simulated NXtomo files `ctrecon phantom --out x.nx` writes: frames, keys, angles
//! and pixel size as written.
//!
//! Runs when `.venv-scans/` has nxtomo (scripts/install-peers.sh scans); otherwise prints one skip line,
//! or fails under `CTRECON_REQUIRE_PEERS=1`.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Once;

use ctrecon::recon::geometry::{Angles, Geometry};
use ctrecon::scans::{self, Format, Intensity, ScanError};
use serde_json::{Value, json};

use crate::common::{assert_problem, spawn_app};
use crate::scan_formats::assert_ball_at;

/// Writes the NXtomo files the job on stdin asks for (`kind`), answering what it wrote as JSON.
const WRITER: &str = r#"
import sys, json, numpy as np, h5py
from pint import get_application_registry
from nxtomo.application.nxtomo import NXtomo
ureg = get_application_registry()

def save(path, data, control, degrees, pixel_m):
    nx = NXtomo()
    nx.instrument.detector.data = data
    nx.instrument.detector.image_key_control = np.asarray(control)
    nx.sample.rotation_angle = np.asarray(degrees, dtype=np.float64) * ureg.degree
    nx.instrument.detector.x_pixel_size = pixel_m * ureg.meter
    nx.instrument.detector.y_pixel_size = pixel_m * ureg.meter
    nx.instrument.detector.distance = 0.25 * ureg.meter
    nx.save(path, data_path="/entry0000", overwrite=True)

def small(path):
    # darks, flats before, three projections, an alignment frame, flats after
    control = [2, 2, 1, 1, 0, 0, 0, -1, 1, 1]
    degrees = [0, 0, 0, 0, 10, 70, 130, 90, 180, 180]
    n, h, w = len(control), 4, 5
    f, r, c = np.meshgrid(np.arange(n), np.arange(h), np.arange(w), indexing="ij")
    data = (1000 + f * 97 + r * 13 + c * 3).astype(np.uint16)
    save(path, data, control, degrees, 6.5e-6)
    return {"data": data.tolist(), "control": control, "degrees": degrees}

def rewrite(path, **kw):
    """Rewrite a dataset of the file with h5py: kw name → (dataset path, array or None to delete, options)."""
    with h5py.File(path, "r+") as f:
        for key, (value, opts) in kw.items():
            del f[key]
            if value is not None:
                f.create_dataset(key, data=np.asarray(value), **opts)

def ball(path, job):
    n, h, w, du = job["views"], job["rows"], job["cols"], job["du_mm"]
    x, y, z = job["centre"]
    radius, mu, axis = job["radius_mm"], job["mu"], job["axis_shift_px"]
    darks, before, after = 4, 4, 4
    theta = np.arange(n) * 180.0 / n
    control = [2] * darks + [1] * before + [0] * n + [-1] + [1] * after
    degrees = [0.0] * (darks + before) + list(theta) + [90.0] + [180.0] * after
    cols = np.arange(w)
    flat0 = 1800.0 + 4.0 * cols[None, :] + 0.0 * np.arange(h)[:, None]
    flat1 = 1.03 * flat0
    dark = 100.0
    frames = []
    for k in range(darks):
        frames.append(np.full((h, w), dark))
    for k in range(before):
        frames.append(flat0)
    a0, a1 = darks + (before - 1) / 2.0, darks + before + n + 1 + (after - 1) / 2.0
    rr = np.arange(h)[:, None]
    cc = cols[None, :]
    for i, t in enumerate(np.radians(theta)):
        frame = darks + before + i
        wgt = (frame - a0) / (a1 - a0)
        flat = flat0 + wgt * (flat1 - flat0)
        u0 = x * np.cos(t) - y * np.sin(t)
        uc = (cc - (w - 1) / 2.0 - axis) * du
        vr = ((h - 1) / 2.0 - rr) * du  # image row 0 is the top
        d2 = radius**2 - (uc - u0) ** 2 - (vr - z) ** 2
        p = 2.0 * mu * np.sqrt(np.clip(d2, 0.0, None))
        frames.append(dark + (flat - dark) * np.exp(-p))
    frames.append(frames[-1])
    for k in range(after):
        frames.append(flat1)
    data = np.rint(np.stack(frames)).astype(np.uint16)
    save(path, data, control, degrees, du * 1e-3)

job = json.loads(sys.stdin.read())
path, kind = job["path"], job["kind"]
out = {}
if kind == "small":
    out = small(path)
elif kind == "small_deflate":
    out = small(path)
    with h5py.File(path, "r") as f:
        data = f["entry0000/instrument/detector/data"][()]
    rewrite(path, **{"entry0000/instrument/detector/data": (data, {"chunks": (1,) + data.shape[1:], "compression": "gzip"})})
    with h5py.File(path, "r") as f:
        d = f["entry0000/instrument/detector/data"]
        out["chunks"], out["compression"] = list(d.chunks), d.compression
elif kind == "ball":
    ball(path, job)
elif kind == "bad_image_key":
    small(path)
    rewrite(path, **{"entry0000/instrument/detector/image_key": ([0] * 9, {}),
                     "entry0000/instrument/detector/image_key_control": ([0] * 9, {})})
elif kind == "no_angles":
    small(path)
    rewrite(path, **{"entry0000/sample/rotation_angle": (None, {})})
elif kind == "complex":
    small(path)
    rewrite(path, **{"entry0000/instrument/detector/data": (np.zeros((10, 4, 5), np.complex64), {})})
elif kind == "not_nxtomo":
    with h5py.File(path, "w") as f:
        g = f.create_group("entry")
        g["definition"] = "NXmx"
        g["data"] = np.zeros((3, 4, 5), np.uint16)
print(json.dumps(out))
"#;

/// The Python of `.venv-scans` (or `python3`) when it has nxtomo and h5py.
fn nxtomo_python() -> Option<PathBuf> {
    let py = crate::scan_formats::python()?;
    let ok = Command::new(&py)
        .args(["-c", "import nxtomo, h5py"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return Some(py);
    }
    if std::env::var("CTRECON_REQUIRE_PEERS").as_deref() == Ok("1") {
        panic!("nxtomo is required (CTRECON_REQUIRE_PEERS=1): run scripts/install-peers.sh scans");
    }
    static SKIP: Once = Once::new();
    SKIP.call_once(|| {
        eprintln!("SKIPPED: no Python with nxtomo (run scripts/install-peers.sh scans)")
    });
    None
}

/// Run the writer on `job`; its answer.
fn write(py: &Path, job: &Value) -> Value {
    let mut child = Command::new(py)
        .args(["-c", WRITER])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin.write_all(job.to_string().as_bytes()).expect("job");
    }
    let out = child.wait_with_output().expect("python");
    assert!(
        out.status.success(),
        "writer failed on {job}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("writer's answer")
}

fn write_kind(py: &Path, path: &Path, kind: &str) -> Value {
    write(py, &json!({"path": path, "kind": kind}))
}

#[test]
fn an_nxtomo_written_by_nxtomo_reads_back_exactly() {
    let Some(py) = nxtomo_python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    for kind in ["small", "small_deflate"] {
        let file = dir.path().join(format!("{kind}.nx"));
        let job = write_kind(&py, &file, kind);
        if kind == "small_deflate" {
            assert_eq!(job["chunks"], json!([1, 4, 5]));
            assert_eq!(job["compression"], "gzip");
        }
        let frames: Vec<Vec<f32>> = job["data"]
            .as_array()
            .expect("frames")
            .iter()
            .map(|f| {
                f.as_array()
                    .expect("rows")
                    .iter()
                    .flat_map(|r| {
                        r.as_array()
                            .expect("row")
                            .iter()
                            .map(|v| v.as_f64().expect("value") as f32)
                    })
                    .collect()
            })
            .collect();
        for path in [file.clone(), dir.path().to_path_buf()] {
            if path.is_dir() && kind == "small_deflate" {
                continue; // the folder opens its first .nx
            }
            let mut scan = scans::open(&path).expect("open the .nx");
            assert_eq!(scan.format, Format::NxTomo);
            assert_eq!(scan.format.to_string(), "nxtomo");
            assert_eq!(scan.source, file);
            // Frames 4, 5, 6 are the projections; 7 (image_key_control −1) is left out.
            assert_eq!(scan.views.view_count(), 3);
            assert_eq!(scan.views.shape(), (4, 5));
            let mut view = vec![0f32; 20];
            let mut flat = vec![0f32; 20];
            for (i, frame) in [4usize, 5, 6].into_iter().enumerate() {
                scan.views.read_view(i, &mut view).expect("view");
                assert_eq!(view, frames[frame], "{kind}: view {i}");
                // Flat series at frames 2.5 and 8.5: interpolated by frame index.
                assert!(scan.views.view_flat(i, &mut flat));
                let w = (frame as f32 - 2.5) / 6.0;
                for k in 0..20 {
                    let (a, b) = (
                        (frames[2][k] + frames[3][k]) / 2.0,
                        (frames[8][k] + frames[9][k]) / 2.0,
                    );
                    assert!(
                        (flat[k] - (a + w * (b - a))).abs() < 1e-3,
                        "{kind}: flat of view {i}"
                    );
                }
            }
            let mut e = vec![0f32; 20];
            assert!(matches!(
                scan.views.read_view(3, &mut e),
                Err(ScanError::NoSuchView {
                    index: 3,
                    count: 3,
                    ..
                })
            ));
            let dark = scan.dark.as_ref().expect("dark");
            let all_flats = scan.flat.as_ref().expect("flat");
            for k in 0..20 {
                assert_eq!(dark[k], (frames[0][k] + frames[1][k]) / 2.0);
                let f = (frames[2][k] + frames[3][k] + frames[8][k] + frames[9][k]) / 4.0;
                assert!((all_flats[k] - f).abs() < 1e-3);
            }
            assert_eq!(scan.intensity, Intensity::Raw { white_level: 1.0 });
            assert_eq!(scan.orientation, scans::Orientation::ROWS_UP);
            let Geometry::Parallel3d(g) = &scan.geometry else {
                panic!("parallel3d, not {:?}", scan.geometry)
            };
            // β = −θ (module docs of scans::nxtomo).
            assert_eq!(
                g.angles,
                Angles::List {
                    degrees: vec![-10.0, -70.0, -130.0]
                }
            );
            assert_eq!((g.detector.nu, g.detector.nv), (5, 4));
            assert!(
                (g.detector.du_mm - 0.0065).abs() < 1e-12,
                "{}",
                g.detector.du_mm
            );
            assert!((g.detector.dv_mm - 0.0065).abs() < 1e-12);
            assert_eq!((g.detector.offset_u_mm, g.detector.offset_v_mm), (0.0, 0.0));
            let name = file.display().to_string();
            let origin = |key: &str| {
                scan.provenance
                    .iter()
                    .find(|p| p.key == key)
                    .unwrap_or_else(|| panic!("{key} in {:?}", scan.provenance))
                    .clone()
            };
            let a = origin("/entry0000/sample/rotation_angle");
            assert_eq!(a.origin, format!("{name} /entry0000/sample/rotation_angle"));
            assert_eq!(a.value, "3 projection angles, 10 … 130 degree");
            let k = origin("/entry0000/instrument/detector/image_key");
            assert!(
                k.value
                    .starts_with("3 projections, 4 flats, 2 darks, 1 alignment"),
                "{}",
                k.value
            );
            let p = origin("/entry0000/instrument/detector/x_pixel_size");
            assert_eq!(
                p.origin,
                format!("{name} /entry0000/instrument/detector/x_pixel_size")
            );
            assert!(
                scan.notes
                    .iter()
                    .any(|n| n.contains("detector/distance = 250 mm")),
                "{:?}",
                scan.notes
            );
        }
    }
}

fn open_error(file: &Path) -> ScanError {
    match scans::open(file) {
        Err(e) => e,
        Ok(mut scan) => {
            let (nv, nu) = scan.views.shape();
            let mut buf = vec![0f32; nv * nu];
            (0..scan.views.view_count())
                .find_map(|i| scan.views.read_view(i, &mut buf).err())
                .expect("a bad file fails")
        }
    }
}

#[test]
fn bad_nxtomo_files_give_errors_that_name_the_file_and_hdf5_path() {
    let Some(py) = nxtomo_python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let at = |name: &str| dir.path().join(name);
    let check = |file: &Path, e: ScanError, what: &[&str]| {
        let text = e.to_string();
        assert!(text.contains(&file.display().to_string()), "{text}");
        for w in what {
            assert!(text.contains(w), "{w} not in {text}");
        }
        e
    };
    // Truncated: the file cut to half.
    write_kind(&py, &at("t.nx"), "small");
    let bytes = std::fs::read(at("t.nx")).expect("read");
    std::fs::write(at("truncated.nx"), &bytes[..bytes.len() / 2]).expect("write");
    let e = check(&at("truncated.nx"), open_error(&at("truncated.nx")), &[]);
    assert!(!matches!(e, ScanError::NotAScan { .. }), "{e}");
    write_kind(&py, &at("key.nx"), "bad_image_key");
    let e = check(
        &at("key.nx"),
        open_error(&at("key.nx")),
        &["/entry0000/instrument/detector/image_key", "10 frames"],
    );
    assert!(matches!(e, ScanError::Mismatch { .. }), "{e}");
    write_kind(&py, &at("angles.nx"), "no_angles");
    let e = check(
        &at("angles.nx"),
        open_error(&at("angles.nx")),
        &["/entry0000/sample/rotation_angle"],
    );
    assert!(matches!(e, ScanError::Missing { .. }), "{e}");
    write_kind(&py, &at("complex.nx"), "complex");
    check(
        &at("complex.nx"),
        open_error(&at("complex.nx")),
        &["/entry0000/instrument/detector/data"],
    );
    std::fs::write(at("text.nx"), b"not an HDF5 file at all").expect("write");
    let e = check(&at("text.nx"), open_error(&at("text.nx")), &["HDF5"]);
    assert!(matches!(e, ScanError::NotAScan { .. }), "{e}");
    write_kind(&py, &at("mx.h5"), "not_nxtomo");
    let e = check(&at("mx.h5"), open_error(&at("mx.h5")), &["NXtomo"]);
    assert!(matches!(e, ScanError::NotAScan { .. }), "{e}");
}

/// The simulated ball: 180 views over a half turn (no view at 180°) of 48 × 40 pixels of 0.1 mm, the
/// rotation axis 2.3 pixels right of the panel's centre.
fn ball_job(path: &Path) -> Value {
    json!({"path": path, "kind": "ball", "views": 180, "rows": 40, "cols": 48, "du_mm": 0.1,
           "centre": CENTRE, "radius_mm": 0.5, "mu": 1.0, "axis_shift_px": AXIS_SHIFT_PX})
}
const CENTRE: [f64; 3] = [0.8, -0.5, 0.3];
const AXIS_SHIFT_PX: f64 = 2.3;

#[test]
fn fbp_of_a_simulated_nxtomo_puts_an_off_centre_ball_where_it_was() {
    let Some(py) = nxtomo_python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("scan.nx");
    write(&py, &ball_job(&file));
    // `ctrecon recon --input scan.nx --algorithm fbp --size 40 --pixel-mm 0.1`: the centre found.
    let out = dir.path().join("v.npy");
    let cli = crate::scan_formats::recon_40(&file, "fbp", "auto", &out);
    assert_ball_at(
        &cli,
        &ctrecon::recon::grid::VolumeGrid::cube(40, 0.1),
        CENTRE,
    );
}

async fn post_octets(app: &crate::common::TestApp, name: &str, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url(&format!("/v1/scans?filename={name}")))
        .header("content-type", "application/octet-stream")
        .body(body)
        .send()
        .await
        .expect("request")
}

/// `POST /v1/scans` takes an `.nx`, finds the off-centre axis, and an FBP job puts the ball where it was;
/// bad files are 422 problems, never 5xx.
#[tokio::test]
async fn an_nxtomo_imports_and_reconstructs_and_bad_ones_are_refused() {
    let Some(py) = nxtomo_python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("scan.nx");
    write(&py, &ball_job(&file));
    let app = spawn_app().await;
    let r = post_octets(&app, "scan.nx", std::fs::read(&file).expect("read")).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let d: Value = r.json().await.expect("json");
    assert_eq!(d["format"], "nxtomo");
    assert_eq!(d["shape"], json!([180, 40, 48]));
    assert_eq!(d["geometry"]["type"], "parallel3d", "{d}");
    let cal = &d["scan"]["calibration"];
    assert_eq!(cal["centre"], "found", "{cal}");
    let found = cal["offset_u_mm"].as_f64().expect("offset");
    // The axis at column (nu − 1)/2 + 2.3: offset_u = −2.3 px.
    assert!(
        (found + AXIS_SHIFT_PX * 0.1).abs() < 0.01,
        "found {found} mm"
    );
    assert_eq!(
        d["geometry"]["detector"]["offset_u_mm"].as_f64(),
        Some(found),
        "{d}"
    );

    let id = d["id"].as_str().expect("id");
    let job = app
        .submit(&json!({"input": id, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 40, "ny": 40, "nz": 40, "spacing_mm": [0.1, 0.1, 0.1]}}))
        .await;
    let job_id = job["id"].as_str().expect("job id").to_string();
    let done = app.finish(&job_id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let r = app
        .get(&format!("/v1/jobs/{job_id}/result/volume.npy"))
        .await;
    let (shape, data) = crate::common::read_npy_f32(&r.bytes().await.expect("volume"));
    let vol = ndarray::Array3::from_shape_vec((shape[0], shape[1], shape[2]), data).expect("3-D");
    assert_ball_at(
        &vol,
        &ctrecon::recon::grid::VolumeGrid::cube(40, 0.1),
        CENTRE,
    );

    // Bad files: 422, naming the upload's file and the HDF5 path, never a server path.
    for (kind, code, what) in [
        (
            "bad_image_key",
            "scan_invalid",
            "/entry0000/instrument/detector/image_key",
        ),
        (
            "no_angles",
            "scan_invalid",
            "/entry0000/sample/rotation_angle",
        ),
        ("not_nxtomo", "scan_not_recognised", "NXtomo"),
    ] {
        let bad = dir.path().join(format!("{kind}.nx"));
        write_kind(&py, &bad, kind);
        let r = post_octets(&app, "scan.nx", std::fs::read(&bad).expect("read")).await;
        let p = assert_problem(r, 422, code).await;
        let detail = p["detail"].as_str().expect("detail");
        assert!(
            detail.contains("scan.nx") && detail.contains(what),
            "{kind}: {detail}"
        );
        assert!(!detail.contains("/tmp/"), "no server path in {detail}");
    }
    let bytes = std::fs::read(dir.path().join("no_angles.nx")).expect("read");
    let r = post_octets(&app, "scan.nx", bytes[..bytes.len() / 2].to_vec()).await;
    assert!(r.status().is_client_error(), "truncated: {}", r.status());
    let r = post_octets(&app, "scan.nx", b"not an HDF5 file".to_vec()).await;
    assert_problem(r, 422, "scan_not_recognised").await;
}

/// Reads an NXtomo file with nxtomo (h5py for the frames), answering what it found as JSON.
const READER: &str = r#"
import sys, json, numpy as np, h5py
from nxtomo.application.nxtomo import NXtomo
path = sys.argv[1]
nx = NXtomo().load(path, "entry")
d = nx.instrument.detector
keys = [int(k.value) for k in d.image_key]
with h5py.File(path, "r") as f:
    data = f["entry/instrument/detector/data"]
    shape, dtype = list(data.shape), str(data.dtype)
    frames = [float(data[i].mean()) for i in range(data.shape[0])]
print(json.dumps({
    "keys": keys, "shape": shape, "dtype": dtype, "frame_means": frames,
    "degrees": [float(a) for a in np.asarray(nx.sample.rotation_angle.to("degree").magnitude)],
    "x_pixel_m": float(np.asarray(d.x_pixel_size.to("m").magnitude).ravel()[0]),
    "y_pixel_m": float(np.asarray(d.y_pixel_size.to("m").magnitude).ravel()[0]),
}))
"#;

#[test]
fn nxtomo_reads_the_simulated_nxtomo_ctrecon_writes() {
    let Some(py) = nxtomo_python() else { return };
    let dir = tempfile::tempdir().expect("dir");
    let file = dir.path().join("sample.nx");
    let geometry: Geometry = serde_json::from_value(json!({
        "type": "parallel3d", "angles": {"count": 6, "start_deg": 15, "range_deg": 180},
        "detector": {"nu": 8, "nv": 4, "du_mm": 0.05, "dv_mm": 0.1}}))
    .expect("geometry");
    // Each view a constant line integral 0.1·k: its raw counts are known.
    let projections = ndarray::Array3::from_shape_fn((6, 4, 8), |(k, _, _)| 0.1 * k as f32);
    let w = scans::simulated_nxtomo::write_nxtomo(&file, &geometry, projections.view())
        .expect("written");
    assert_eq!((w.projections, w.clipped), (6, 0));
    let out = Command::new(&py)
        .args(["-c", READER])
        .arg(&file)
        .output()
        .expect("python");
    assert!(
        out.status.success(),
        "nxtomo could not read the file: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("reader's answer");
    assert_eq!(v["keys"], json!([2, 2, 1, 1, 0, 0, 0, 0, 0, 0, 1, 1]));
    assert_eq!(v["shape"], json!([12, 4, 8]));
    assert_eq!(v["dtype"], "uint16");
    let (dark, flat) = (
        scans::simulated_nxtomo::DARK_LEVEL,
        scans::simulated_nxtomo::FLAT_LEVEL,
    );
    let means: Vec<f64> = serde_json::from_value(v["frame_means"].clone()).expect("means");
    for (i, m) in means.iter().enumerate() {
        let want = match i {
            0 | 1 => dark,
            2 | 3 | 10 | 11 => flat,
            k => (dark + (flat - dark) * (-0.1 * (k - 4) as f64).exp()).round(),
        };
        assert!(
            (m - want).abs() < 1e-9,
            "frame {i}: mean {m}, expected {want}"
        );
    }
    // ctrecon's β = 15° + 30°·k is the sample's θ = −β; darks and flats at 0.
    let degrees: Vec<f64> = serde_json::from_value(v["degrees"].clone()).expect("degrees");
    for (i, d) in degrees.iter().enumerate() {
        let want = if (4..10).contains(&i) {
            -(15.0 + 30.0 * (i - 4) as f64)
        } else {
            0.0
        };
        assert!((d - want).abs() < 1e-9, "frame {i}: {d}°, expected {want}°");
    }
    assert!((v["x_pixel_m"].as_f64().expect("x") - 5e-5).abs() < 1e-15);
    assert!((v["y_pixel_m"].as_f64().expect("y") - 1e-4).abs() < 1e-15);
}
