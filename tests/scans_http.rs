//! `POST /v1/scans` against the real server: a Nikon scan written by tifffile (see `scan_formats`) as a ZIP
//! and as a multipart form, imported view by view and reconstructed by an FDK job with the ball where it was
//! placed; a SkyScan scan; and bad scans refused with a problem naming the file and key, nothing left behind.

use std::path::Path;

use serde_json::{Value, json};

use crate::common::{self, TestApp, assert_problem, spawn_app};
use crate::scan_formats::{
    assert_ball_at, python, write_ball_scan, write_nikon_views, write_skyscan_scan, xtekct,
};

/// Every file of `dir` (recursively) as `(relative name, bytes)`, under `prefix`.
fn files_of(dir: &Path, prefix: &str) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).expect("read dir") {
        let p = e.expect("entry").path();
        let name = format!("{prefix}{}", p.file_name().expect("name").to_string_lossy());
        if p.is_dir() {
            out.extend(files_of(&p, &format!("{name}/")));
        } else {
            out.push((name, std::fs::read(&p).expect("read")));
        }
    }
    out.sort();
    out
}

fn zip_of(files: &[(String, Vec<u8>)]) -> Vec<u8> {
    ctrecon::dicom::write_zip(files).expect("zip")
}

async fn post_zip(app: &TestApp, zip: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url("/v1/scans"))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .await
        .expect("request")
}

async fn post_form(app: &TestApp, files: &[(String, Vec<u8>)]) -> reqwest::Response {
    let mut form = reqwest::multipart::Form::new();
    for (name, bytes) in files {
        form = form.part(
            "file",
            reqwest::multipart::Part::bytes(bytes.clone()).file_name(name.clone()),
        );
    }
    app.client
        .post(app.url("/v1/scans"))
        .multipart(form)
        .send()
        .await
        .expect("request")
}

/// Files under the data directory's `tmp/` and `datasets/` (the only dataset is the SkyScan one imported
/// first): nothing else once a refused import is answered.
fn leftovers(app: &TestApp) -> Vec<String> {
    let mut out: Vec<String> = ["tmp", "datasets"]
        .iter()
        .map(|d| app.dir.path().join(d))
        .filter(|d| d.is_dir())
        .flat_map(|d| files_of(&d, &format!("{}/", d.display())))
        .map(|(n, _)| n)
        .collect();
    let datasets = out.iter().filter(|n| n.ends_with(".npy")).count();
    assert_eq!(datasets, 1, "{out:?}");
    out.retain(|n| !n.ends_with(".npy"));
    out
}

/// FDK of dataset `input` on a 40³ grid of 0.1 mm; the volume.
async fn fdk_volume(app: &TestApp, input: &str) -> ndarray::Array3<f32> {
    let j = app
        .submit(&json!({"input": input, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 40, "ny": 40, "nz": 40, "spacing_mm": [0.1, 0.1, 0.1]}}))
        .await;
    let id = j["id"].as_str().expect("job id").to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let r = app.get(&format!("/v1/jobs/{id}/result/volume.npy")).await;
    assert_eq!(r.status(), 200);
    let bytes = r.bytes().await.expect("volume");
    let (shape, data) = common::read_npy_f32(&bytes);
    ndarray::Array3::from_shape_vec((shape[0], shape[1], shape[2]), data).expect("3-D volume")
}

#[tokio::test]
async fn a_nikon_scan_as_zip_or_form_imports_and_fdk_puts_the_ball_where_it_was() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let (_, centre) = write_ball_scan(&py, dir.path());
    let files = files_of(dir.path(), "");
    let app = spawn_app().await;
    let grid = ctrecon::recon::grid::VolumeGrid::cube(40, 0.1);

    // A ZIP of the scan's folder (one top folder, looked into).
    let in_folder: Vec<_> = files
        .iter()
        .map(|(n, b)| (format!("ball/{n}"), b.clone()))
        .collect();
    let r = post_zip(&app, zip_of(&in_folder)).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    assert!(r.headers().get("location").is_some());
    let d: Value = r.json().await.expect("json");
    assert_eq!(d["kind"], "scan");
    assert_eq!(d["format"], "nikon_xtek");
    assert_eq!(d["scan"]["format"], "nikon_xtek");
    assert_eq!(d["shape"], json!([120, 36, 40]));
    assert_eq!(d["dtype"], "float32");
    assert_eq!(d["geometry"]["type"], "cone", "{d}");
    let provenance = d["scan"]["provenance"].as_array().expect("provenance");
    assert!(
        provenance
            .iter()
            .any(|p| p["key"] == "SrcToObject" && p["origin"] == "ball.xtekct [XTekCT] SrcToObject"),
        "{d}"
    );
    let steps = d["scan"]["preprocessing"].as_array().expect("steps");
    assert_eq!(
        steps[0],
        json!({"step": "normalise", "white_level": 60000.0})
    );
    assert_eq!(steps[1]["step"], "minus_log");
    assert_eq!(steps[1]["clamped_pixels"], 0);
    // The .xtekct states no calibrated centre: it was found from the views (0.45 mm as the file's
    // ObjectOffsetX and DetectorOffsetX give it) and is the dataset's geometry.
    let cal = &d["scan"]["calibration"];
    assert_eq!(cal["centre"], "found", "{d}");
    let found = cal["offset_u_mm"].as_f64().expect("offset");
    assert!((found - 0.45).abs() < 0.01, "{cal}");
    assert_eq!(d["geometry"]["detector"]["offset_u_mm"], cal["offset_u_mm"]);
    assert_eq!(cal["estimate"]["method"], "opposite_views", "{cal}");
    let id = d["id"].as_str().expect("id").to_string();
    let got: Value = app
        .get(&format!("/v1/datasets/{id}"))
        .await
        .json()
        .await
        .expect("json");
    assert_eq!(got["scan"], d["scan"]);
    assert_ball_at(&fdk_volume(&app, &id).await, &grid, centre);

    // The same files as a multipart form: the same projections.
    let r = post_form(&app, &files).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let f: Value = r.json().await.expect("json");
    assert_eq!(f["sha256"], d["sha256"]);
    assert_eq!(f["scan"], d["scan"]);

    // The file with its offsets left out: found again from the views by default; as read (`centre=read`)
    // the geometry keeps the file's (absent) offset; pinned, the client's value.
    let bare: Vec<(String, Vec<u8>)> = files
        .iter()
        .map(|(n, b)| {
            if n.ends_with(".xtekct") {
                let text = String::from_utf8_lossy(b)
                    .replace("ObjectOffsetX=0.2\n", "")
                    .replace("DetectorOffsetX=0.15\n", "");
                (n.clone(), text.into_bytes())
            } else {
                (n.clone(), b.clone())
            }
        })
        .collect();
    let r = post_zip(&app, zip_of(&bare)).await;
    assert_eq!(r.status(), 201);
    let b: Value = r.json().await.expect("json");
    let again = b["scan"]["calibration"]["offset_u_mm"]
        .as_f64()
        .expect("offset");
    assert!((again - 0.45).abs() < 0.01, "{b}");
    for (query, centre, offset) in [("read", "read", 0.0), ("0.45", "pinned", 0.45)] {
        let r = app
            .client
            .post(app.url(&format!("/v1/scans?centre={query}")))
            .header("content-type", "application/zip")
            .body(zip_of(&bare))
            .send()
            .await
            .expect("post");
        assert_eq!(r.status(), 201);
        let v: Value = r.json().await.expect("json");
        assert_eq!(v["scan"]["calibration"]["centre"], centre, "{v}");
        assert_eq!(
            v["geometry"]["detector"]["offset_u_mm"],
            json!(offset),
            "{v}"
        );
    }
    let r = app
        .client
        .post(app.url("/v1/scans?centre=middle"))
        .header("content-type", "application/zip")
        .body(zip_of(&bare))
        .send()
        .await
        .expect("post");
    crate::common::assert_problem(r, 400, "invalid_query").await;
}

#[tokio::test]
async fn a_skyscan_scan_imports_and_bad_scans_are_refused_naming_file_and_key() {
    let Some(py) = python() else { return };
    let app = spawn_app().await;

    // SkyScan: `.log` + big-endian TIFFs.
    let dir = tempfile::tempdir().expect("tempdir");
    write_skyscan_scan(&py, dir.path());
    let r = post_form(&app, &files_of(dir.path(), "")).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let d: Value = r.json().await.expect("json");
    assert_eq!(
        (&d["format"], &d["shape"]),
        (&json!("bruker_skyscan"), &json!([3, 6, 4]))
    );

    // Nikon: 4 TIFFs of 7 × 5.
    let dir = tempfile::tempdir().expect("tempdir");
    write_nikon_views(&py, dir.path());
    let x = dir.path().join("ball.xtekct");

    // Projections=5 contradicts the 4 TIFFs.
    std::fs::write(&x, xtekct("ball", 5, 7, 5)).expect("xtekct");
    let r = post_zip(&app, zip_of(&files_of(dir.path(), ""))).await;
    let p = assert_problem(r, 422, "scan_invalid").await;
    let detail = p["detail"].as_str().expect("detail");
    assert!(
        detail.contains("ball.xtekct") && detail.contains("Projections"),
        "{detail}"
    );
    assert!(!detail.contains("/tmp/"), "no server path in {detail}");
    assert_eq!(leftovers(&app), Vec::<String>::new());

    // A truncated TIFF: named.
    std::fs::write(&x, xtekct("ball", 4, 7, 5)).expect("xtekct");
    let third = dir.path().join("ball_0003.tif");
    let bytes = std::fs::read(&third).expect("read");
    std::fs::write(&third, &bytes[..bytes.len() - 20]).expect("truncate");
    let r = post_form(&app, &files_of(dir.path(), "")).await;
    let p = assert_problem(r, 422, "scan_invalid").await;
    let detail = p["detail"].as_str().expect("detail");
    assert!(detail.contains("ball_0003.tif"), "{detail}");
    assert_eq!(leftovers(&app), Vec::<String>::new());

    // Unrelated files: not a scan.
    let unrelated = vec![
        ("notes.txt".to_string(), b"hello".to_vec()),
        ("data.csv".to_string(), b"1,2,3\n".to_vec()),
    ];
    let r = post_zip(&app, zip_of(&unrelated)).await;
    assert_problem(r, 422, "scan_not_recognised").await;

    // A name climbing out of the folder.
    let r = post_form(&app, &[("../evil.xtekct".to_string(), b"x".to_vec())]).await;
    assert_problem(r, 422, "scan_invalid").await;
    assert_eq!(leftovers(&app), Vec::<String>::new());

    // One file without its name; a body that is not a ZIP.
    let r = app
        .client
        .post(app.url("/v1/scans"))
        .header("content-type", "application/octet-stream")
        .body(b"x".to_vec())
        .send()
        .await
        .expect("request");
    assert_problem(r, 400, "invalid_query").await;
    let r = post_zip(&app, b"not a zip".to_vec()).await;
    assert_problem(r, 415, "unsupported_media_type").await;
}
