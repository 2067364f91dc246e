//! Preprocessing asked for at the door (`X-Ctrecon-Preprocessing` on `POST /v1/scans`) and on the command
//! line (`ctrecon recon --preprocessing`): the same steps, applied in the same order, recorded in the
//! dataset; stripe suppression removes most of the ring a bad detector column leaves; cropping, binning
//! and an angle subset keep the object where it is; bad steps are a 422 naming the parameter.

use std::path::Path;
use std::process::Command;

use ctrecon::recon::geometry::{Angles, ConeBeam, Geometry, Panel, Views};
use ctrecon::recon::phantom::{Ellipsoid, Phantom3};
use ctrecon::scans::simulated::write_nikon;
use ndarray::Array3;
use serde_json::{Value, json};

use crate::common::{self, TestApp, assert_problem, spawn_app};

fn geometry() -> Geometry {
    Geometry::Cone(ConeBeam {
        angles: Angles::Uniform {
            count: 120,
            start_deg: 0.0,
            range_deg: None,
            short_scan: false,
        },
        dso_mm: 200.0,
        dsd_mm: 600.0,
        detector: Panel {
            nu: 64,
            nv: 48,
            du_mm: 0.4,
            dv_mm: 0.4,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    })
}

/// Exact projections of a ball (radius 2 mm, μ 0.05/mm) off centre, with `stripe` added to detector column
/// 40 of every view (a pixel that responds differently: a ring in the image).
fn projections(stripe: f32) -> Array3<f32> {
    let ball = Ellipsoid {
        value: 0.05,
        a: 0.5,
        b: 0.5,
        c: 0.5,
        x0: 0.25,
        y0: -0.125,
        z0: 0.125,
        phi_deg: 0.0,
        theta_deg: 0.0,
        psi_deg: 0.0,
    };
    let phantom = Phantom3::new(vec![ball], 4.0).expect("phantom");
    let Ok(Views::D3(views)) = geometry().to_views() else {
        panic!("a cone beam")
    };
    let mut p = phantom.project(&views);
    p.slice_mut(ndarray::s![.., .., 40])
        .mapv_inplace(|x| x + stripe);
    p
}

/// The scan written as a Nikon XT H writes one, zipped.
fn nikon_zip(dir: &Path, stripe: f32) -> Vec<u8> {
    let xtekct = dir.join("ball.xtekct");
    write_nikon(&xtekct, &geometry(), projections(stripe).view()).expect("write scan");
    let mut files = Vec::new();
    for e in std::fs::read_dir(dir).expect("dir") {
        let p = e.expect("entry").path();
        let name = p.file_name().expect("name").to_string_lossy().into_owned();
        files.push((name, std::fs::read(&p).expect("read")));
    }
    files.sort();
    ctrecon::dicom::write_zip(&files).expect("zip")
}

async fn import(app: &TestApp, zip: &[u8], plan: Option<&Value>) -> reqwest::Response {
    let mut req = app
        .client
        .post(app.url("/v1/scans?centre=0"))
        .header("content-type", "application/zip")
        .body(zip.to_vec());
    if let Some(plan) = plan {
        req = req.header("x-ctrecon-preprocessing", plan.to_string());
    }
    req.send().await.expect("request")
}

const GRID: [usize; 3] = [40, 40, 40];
const VOXEL_MM: f64 = 0.2;

async fn fdk(app: &TestApp, zip: &[u8], plan: Option<&Value>) -> (Value, Array3<f32>, String) {
    let r = import(app, zip, plan).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let d: Value = r.json().await.expect("json");
    let j = app
        .submit(&json!({"input": d["id"], "algorithm": {"name": "fdk"},
            "grid": {"nx": GRID[0], "ny": GRID[1], "nz": GRID[2],
                     "spacing_mm": [VOXEL_MM, VOXEL_MM, VOXEL_MM]}}))
        .await;
    let id = j["id"].as_str().expect("job id").to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let bytes = app
        .get(&format!("/v1/jobs/{id}/result/volume.npy"))
        .await
        .bytes()
        .await
        .expect("volume");
    let (shape, data) = common::read_npy_f32(&bytes);
    let v = Array3::from_shape_vec((shape[0], shape[1], shape[2]), data).expect("volume");
    (d, v, id)
}

fn rms_diff(a: &Array3<f32>, b: &Array3<f32>) -> f64 {
    let s: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum();
    (s / a.len() as f64).sqrt()
}

/// Centre of mass of the voxels above half the peak (mm).
fn centroid(v: &Array3<f32>) -> [f64; 3] {
    let peak = v.iter().fold(0.0f32, |m, x| m.max(*x));
    let (mut w, mut c) = (0.0, [0.0; 3]);
    for ((z, y, x), &val) in v.indexed_iter() {
        if val > peak / 2.0 {
            let val = f64::from(val);
            w += val;
            for (i, k) in [x, y, z].into_iter().enumerate() {
                c[i] += val * ((k as f64) - (GRID[i] as f64 - 1.0) / 2.0) * VOXEL_MM;
            }
        }
    }
    c.map(|s| s / w)
}

#[tokio::test]
async fn stripes_crop_bin_and_angle_subsets_asked_at_the_door_are_applied_and_recorded() {
    let app = spawn_app().await;
    let (clean_dir, ring_dir) = (
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
    );
    let clean = nikon_zip(clean_dir.path(), 0.0);
    let ringed = nikon_zip(ring_dir.path(), 0.03);
    let (_, truth, _) = fdk(&app, &clean, None).await;
    let (_, ring, _) = fdk(&app, &ringed, None).await;
    let stripes = json!({"stripes": {"size": 5}});
    let (d, filtered, job) = fdk(&app, &ringed, Some(&stripes)).await;
    let steps = d["scan"]["preprocessing"].as_array().expect("steps");
    assert_eq!(
        steps.last(),
        Some(&json!({"step": "stripes", "method": "sorting", "size": 5})),
        "{d}"
    );
    // The job's volume and its DICOM say how it was derived: format, every step, the centre used.
    let job_json: Value = app
        .get(&format!("/v1/jobs/{job}"))
        .await
        .json()
        .await
        .expect("job");
    let derivation = job_json["result"]["derivation"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    for part in [
        "ctrecon fdk of a nikon_xtek scan: normalise(white_level=60000.0) > minus_log(",
        "> orient(flip_cols=true, flip_rows=true) > stripes(method=\"sorting\", size=5)",
        "; centre of rotation pinned (0.0000 mm)",
    ] {
        assert!(derivation.contains(part), "{part:?} not in {derivation:?}");
    }
    let dcm = app
        .get(&format!("/v1/jobs/{job}/result/slice?format=dicom"))
        .await
        .bytes()
        .await
        .expect("dicom");
    let obj = dicom_object::OpenFileOptions::new()
        .from_reader(&dcm[128..])
        .expect("a DICOM file");
    let written = obj
        .element(dicom_dictionary_std::tags::DERIVATION_DESCRIPTION)
        .expect("DerivationDescription")
        .to_str()
        .expect("text")
        .trim()
        .to_string();
    assert_eq!(written, derivation);
    // The ring is what the bad column adds: the difference from the same reconstruction of the clean
    // scan, without the filter and with it.
    let (_, filtered_clean, _) = fdk(&app, &clean, Some(&stripes)).await;
    let (before, after) = (
        rms_diff(&ring, &truth),
        rms_diff(&filtered, &filtered_clean),
    );
    let cost = rms_diff(&filtered_clean, &truth);
    println!(
        "ring artefact RMS: {before:.2e} without, {after:.2e} with the stripe filter \
         (the filter changes the clean scan's volume by {cost:.2e})"
    );
    assert!(before > 1e-4, "the bad column leaves a ring: {before}");
    assert!(after < 0.4 * before, "{after} vs {before}");

    // Every view-wise step at once: the data shrinks, the geometry follows, the ball stays put.
    let plan = json!({"angles": {"step": 2}, "crop": {"u0": 4, "v0": 4, "nu": 56, "nv": 40},
                      "bin": {"u": 2, "v": 2}, "linearise": {"coefficients": [0, 1]}});
    let (d, small, _) = fdk(&app, &clean, Some(&plan)).await;
    assert_eq!(d["shape"], json!([60, 20, 28]), "{d}");
    let det = &d["geometry"]["detector"];
    assert_eq!(
        (det["nu"].clone(), det["nv"].clone()),
        (json!(28), json!(20))
    );
    assert_eq!(
        (det["du_mm"].clone(), det["dv_mm"].clone()),
        (json!(0.8), json!(0.8))
    );
    let names: Vec<&str> = d["scan"]["preprocessing"]
        .as_array()
        .expect("steps")
        .iter()
        .filter_map(|s| s["step"].as_str())
        .collect();
    assert_eq!(
        names,
        [
            "normalise",
            "minus_log",
            "orient",
            "angle_subset",
            "crop",
            "bin",
            "linearise"
        ]
    );
    let (a, b) = (centroid(&truth), centroid(&small));
    println!("ball centroid: {a:?} mm from all views, {b:?} mm preprocessed");
    for i in 0..3 {
        assert!((a[i] - b[i]).abs() < 0.5 * VOXEL_MM, "{a:?} vs {b:?}");
    }

    // The command line applies the same plan to the same scan: the same volume.
    let out = clean_dir.path().join("cli.npy");
    let run = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(["recon", "--input"])
        .arg(clean_dir.path().join("ball.xtekct"))
        .args([
            "--algorithm",
            "fdk",
            "--centre",
            "0",
            "--size",
            "40",
            "--pixel-mm",
            "0.2",
        ])
        .args(["--preprocessing", &plan.to_string(), "--output"])
        .arg(&out)
        .output()
        .expect("ctrecon recon");
    let said = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{said}");
    assert!(
        said.contains("preprocessing: [{") && said.contains("\"step\":\"angle_subset\""),
        "{said}"
    );
    let bytes = std::fs::read(&out).expect("cli volume");
    let (shape, data) = common::read_npy_f32(&bytes);
    let cli = Array3::from_shape_vec((shape[0], shape[1], shape[2]), data).expect("volume");
    let top = small.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    let worst = small
        .iter()
        .zip(&cli)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
    assert!(
        worst <= 1e-5 * top,
        "door and CLI differ by {worst} (peak {top})"
    );
}

#[tokio::test]
async fn steps_that_cannot_apply_are_refused_naming_the_parameter() {
    let app = spawn_app().await;
    let dir = tempfile::tempdir().expect("dir");
    let zip = nikon_zip(dir.path(), 0.0);
    for (plan, words) in [
        ("{\"stripes\": {\"size\": 4}}", "size"),
        (
            "{\"crop\": {\"u0\": 60, \"v0\": 0, \"nu\": 10, \"nv\": 10}}",
            "exceeds the panel",
        ),
        ("{\"angles\": {\"start\": 500, \"step\": 1}}", "start"),
        ("{\"denoise\": {}}", "unknown field `denoise`"),
        ("{\"bin\": ", "X-Ctrecon-Preprocessing"),
    ] {
        let r = app
            .client
            .post(app.url("/v1/scans"))
            .header("content-type", "application/zip")
            .header("x-ctrecon-preprocessing", plan)
            .body(zip.clone())
            .send()
            .await
            .expect("request");
        let p = assert_problem(r, 422, "invalid_parameter").await;
        let detail = p["detail"].as_str().unwrap_or_default();
        assert!(detail.contains(words), "{plan}: {detail}");
    }
}
