//! DICOM over HTTP against the real server: series uploads (multipart, ZIP, instance by instance), assembly
//! errors, volume jobs with every product, and DICOM results (derived CT series, Secondary Capture,
//! Encapsulated STL). The synthetic series are written by ctrecon from analytic ellipsoids of known geometry;
//! LIDC-IDRI-0001 runs when `scripts/fetch-test-data.sh` fetched it (required with `CTRECON_REQUIRE_TEST_DATA=1`).

use crate::common;

use std::f64::consts::PI;
use std::io::Write;

use common::{TestApp, assert_problem, cone_geometry, read_npy_f32, spawn_app, spawn_app_with};
use ctrecon::dicom::{
    ReadLimits, SeriesMeta, ZipLimits, read_upload, unpack, write_ct_series, write_enhanced_ct,
    write_secondary_capture, write_zip,
};
use ctrecon::recon::VolumeGrid;
use ctrecon::recon::control::unattended;
use ctrecon::recon::phantom::{Ellipsoid, Phantom3};
use ctrecon::series::{Assembled, AssemblyOptions};
use ctrecon::volume::{Frame, Volume, Window, mu_to_hu};
use serde_json::{Value, json};

const STUDY_UID: &str = "1.2.826.0.1.3680043.8.498.77";

/// Semi-axes (mm) of the body ellipsoid.
const AXES: [f64; 3] = [60.0, 75.0, 50.0];

fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 64,
        ny: 64,
        nz: 40,
        spacing_mm: [3.0, 3.0, 4.5],
        centre_mm: [4.5, -6.0, 10.0],
    }
}

/// An ellipsoid of +1000 HU in air (−1000 HU) with a +400 HU inclusion; 2×2×2 supersampled.
fn body() -> Volume {
    let e = |v: Value| -> Ellipsoid { serde_json::from_value(v).unwrap() };
    let p = Phantom3::new(
        vec![
            e(json!({"value": 1.0, "a": AXES[0] / 100.0, "b": AXES[1] / 100.0, "c": AXES[2] / 100.0})),
            e(json!({"value": -0.3, "a": 0.2, "b": 0.2, "c": 0.2, "x0": 0.2})),
        ],
        100.0,
    )
    .unwrap();
    let g = grid();
    Volume {
        data: p.rasterize(&g, 2).mapv(|v| 2000.0 * v - 1000.0),
        frame: Frame::from_grid(&g),
    }
}

fn meta(description: &str) -> SeriesMeta {
    SeriesMeta {
        study_uid: Some(STUDY_UID.into()),
        patient_id: Some("PHANTOM-7".into()),
        series_description: description.into(),
        series_number: 3,
        ..Default::default()
    }
}

/// The series' files and the quantisation step (HU) of its int16 pixels.
fn series_files(description: &str) -> (Vec<(String, Vec<u8>)>, f64) {
    let s = write_ct_series(&body(), &meta(description)).unwrap();
    (s.files, s.rescale_slope)
}

/// Deterministic shuffle (an LCG permutation).
fn shuffle<T>(v: &mut [T]) {
    let mut s: u64 = 0x2545_F491_4F6C_DD1D;
    for i in (1..v.len()).rev() {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        v.swap(i, (s >> 33) as usize % (i + 1));
    }
}

fn form(files: &[(String, Vec<u8>)]) -> reqwest::multipart::Form {
    files
        .iter()
        .fold(reqwest::multipart::Form::new(), |f, (name, bytes)| {
            f.part(
                "file",
                reqwest::multipart::Part::bytes(bytes.clone())
                    .file_name(name.clone())
                    .mime_str("application/dicom")
                    .unwrap(),
            )
        })
}

async fn post_form(app: &TestApp, query: &str, files: &[(String, Vec<u8>)]) -> reqwest::Response {
    app.client
        .post(app.url(&format!("/v1/series{query}")))
        .multipart(form(files))
        .send()
        .await
        .unwrap()
}

async fn post_bytes(app: &TestApp, path: &str, media: &str, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url(path))
        .header("content-type", media)
        .body(body)
        .send()
        .await
        .unwrap()
}

async fn bytes(app: &TestApp, path: &str, content_type: &str) -> Vec<u8> {
    let r = app.get(path).await;
    let status = r.status();
    let ct = r
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    let b = r.bytes().await.unwrap().to_vec();
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&b));
    assert_eq!(ct, content_type, "{path}");
    b
}

/// Upload the synthetic series as a multipart form; returns the stored series JSON.
async fn upload_body(app: &TestApp) -> Value {
    let (mut files, _) = series_files("body");
    shuffle(&mut files);
    let r = post_form(app, "", &files).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let v: Value = r.json().await.unwrap();
    v["series"][0]["series"].clone()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// Decode a ZIP of DICOM files into one assembled series.
fn assemble_zip(zip: Vec<u8>) -> (String, Assembled) {
    let files = unpack("result.zip", zip, &ZipLimits::default()).unwrap();
    let up = read_upload(&files, &ReadLimits::default(), unattended()).unwrap();
    assert!(up.rejected.is_empty(), "{:?}", up.rejected);
    assert_eq!(up.series.len(), 1);
    let g = up.series.into_iter().next().unwrap();
    let study = g.study_uid.clone().unwrap_or_default();
    (
        study,
        g.assemble(&AssemblyOptions::default(), true, unattended())
            .unwrap(),
    )
}

#[tokio::test]
async fn a_shuffled_multipart_series_becomes_an_hu_volume_with_exact_geometry() {
    let app = spawn_app().await;
    let (mut files, slope) = series_files("body");
    shuffle(&mut files);
    let r = post_form(&app, "", &files).await;
    assert_eq!(r.status(), 201);
    let location = r.headers()["location"].to_str().unwrap().to_string();
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"].as_array().unwrap().len(), 1, "{v}");
    let s = &v["series"][0];
    assert_eq!(s["status"], "ready");
    assert_eq!(s["report"]["instances"], 40);
    assert_eq!(s["report"]["modality"], "CT");
    let rec = &s["series"];
    assert_eq!(rec["shape"], json!([40, 64, 64]));
    assert_eq!(rec["study_uid"], STUDY_UID);
    let g = grid();
    let want = Frame::from_grid(&g);
    for c in 0..3 {
        assert!((f(&rec["frame"]["spacing_mm"][c]) - g.spacing_mm[c]).abs() < 1e-6);
        assert!((f(&rec["frame"]["origin_mm"][c]) - want.origin_mm[c]).abs() < 1e-4);
    }
    assert!(f(&rec["tilt_deg"]).abs() < 1e-6);
    assert!(
        (f(&rec["hu_min"]) + 1000.0).abs() <= slope && (f(&rec["hu_max"]) - 1000.0).abs() <= slope
    );
    // The stored HU volume equals the written one within half a quantisation step.
    let id = rec["id"].as_str().unwrap();
    let npy = bytes(
        &app,
        &format!("/v1/series/{id}/volume.npy"),
        "application/x-npy",
    )
    .await;
    let (shape, values) = read_npy_f32(&npy);
    assert_eq!(shape, [40, 64, 64]);
    let truth = body();
    let worst = values
        .iter()
        .zip(truth.data.iter())
        .map(|(a, b)| (a - b).abs() as f64)
        .fold(0.0, f64::max);
    assert!(
        worst <= slope / 2.0 + 1e-3,
        "worst {worst} HU, step {slope}"
    );
    let one: Value = app
        .get(&format!("/v1/series/{id}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(one["id"], id);
    assert_eq!(
        one["links"]["volume"],
        format!("/v1/series/{id}/volume.npy")
    );
    let up: Value = app.get(&location).await.json().await.unwrap();
    assert_eq!(up["upload"]["status"], "completed");
    assert_eq!(up["series"][0]["series"]["id"], id);
}

#[tokio::test]
async fn two_series_in_one_zip_are_split_and_a_missing_slice_is_refused_or_resampled() {
    let app = spawn_app().await;
    let (a, _) = series_files("first");
    let (b, _) = series_files("second");
    let mut all: Vec<(String, Vec<u8>)> = a
        .iter()
        .map(|(n, x)| (format!("a/{n}"), x.clone()))
        .collect();
    all.extend(b.iter().map(|(n, x)| (format!("b/{n}"), x.clone())));
    let r = post_bytes(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&all).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let series = v["series"].as_array().unwrap();
    assert_eq!(series.len(), 2);
    assert_eq!(v["upload"]["instances"], 80);
    let mut descriptions: Vec<&str> = series
        .iter()
        .map(|s| s["report"]["description"].as_str().unwrap())
        .collect();
    descriptions.sort();
    assert_eq!(descriptions, ["first", "second"]);
    assert!(
        series
            .iter()
            .all(|s| s["status"] == "ready" && s["report"]["instances"] == 40)
    );

    // The same ZIP under an Idempotency-Key answers the same upload; another body under it is refused.
    let zip = write_zip(&all).unwrap();
    let send = |body: Vec<u8>| {
        app.client
            .post(app.url("/v1/series"))
            .header("content-type", "application/zip")
            .header("idempotency-key", "pacs-batch-1")
            .body(body)
            .send()
    };
    let first: Value = send(zip.clone()).await.unwrap().json().await.unwrap();
    let again = send(zip).await.unwrap();
    assert_eq!(again.status(), 201);
    let again: Value = again.json().await.unwrap();
    assert_eq!(again["upload"]["id"], first["upload"]["id"]);
    assert_eq!(
        again["series"][0]["series"]["id"],
        first["series"][0]["series"]["id"]
    );
    let other = write_zip(&a).unwrap();
    assert_problem(send(other).await.unwrap(), 422, "idempotency_key_reused").await;
    // The same files again (a new upload) are answered with the series stored already, not stored twice.
    let ids = |v: &Value| {
        let mut ids: Vec<String> = v["series"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["series"]["id"].as_str().unwrap().to_string())
            .collect();
        ids.sort();
        ids
    };
    assert_ne!(first["upload"]["id"], v["upload"]["id"]);
    assert_eq!(ids(&first), ids(&v));
    assert!(
        first["series"]
            .as_array()
            .unwrap()
            .iter()
            .all(|s| s["report"]["warnings"]
                .to_string()
                .contains("series_already_stored")),
        "{first}"
    );
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("series"))
            .unwrap()
            .count(),
        2
    );

    // Slice 11 of 40 missing: refused with a message naming the gap, or resampled with a warning.
    let mut gappy = a.clone();
    gappy.remove(10);
    let p = assert_problem(
        post_form(&app, "", &gappy).await,
        422,
        "series_missing_slices",
    )
    .await;
    assert!(p["detail"].as_str().unwrap().contains("missing"), "{p}");
    let r = post_form(&app, "?uneven=resample", &gappy).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let rec = &v["series"][0]["series"];
    assert_eq!(rec["shape"][0], 40);
    assert!(
        rec["warnings"].as_array().unwrap().iter().any(|w| w["code"]
            .as_str()
            .unwrap()
            .contains("missing")
            || w["code"].as_str().unwrap().contains("resampled")),
        "{rec}"
    );

    // A ZIP whose only image is a secondary capture: not a CT series.
    let img = ndarray::Array2::from_shape_fn((16, 16), |(r, c)| (r * c) as f32);
    let (_, sc) = write_secondary_capture(
        img.view(),
        Window::new(100.0, 50.0).unwrap(),
        &meta("sc"),
        None,
    )
    .unwrap();
    let zip = write_zip(&[("sc.dcm".into(), sc)]).unwrap();
    assert_problem(
        post_bytes(&app, "/v1/series", "application/zip", zip).await,
        422,
        "dicom_not_ct",
    )
    .await;
}

/// Instances appended to one open upload all at once (as a PACS router sends them, several associations
/// or requests in flight): each append reads the upload and then writes it, so on SQLite each must hold
/// the write lock from its start; a deferred transaction whose snapshot went stale failed with a 500.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn instances_appended_to_one_upload_at_the_same_time_are_all_kept() {
    let app = spawn_app().await;
    let (files, _) = series_files("body");
    let r = post_bytes(&app, "/v1/series", "application/dicom", files[0].1.clone()).await;
    assert_eq!(r.status(), 201);
    let id = r.json::<Value>().await.unwrap()["upload"]["id"]
        .as_str()
        .unwrap()
        .to_string();
    let append = format!("/v1/series?upload={id}");
    let sends = files.iter().skip(1).map(|(_, file)| {
        let (app, append, file) = (&app, &append, file.clone());
        async move {
            let r = post_bytes(app, append, "application/dicom", file).await;
            let status = r.status();
            (status, r.text().await.unwrap())
        }
    });
    for (status, body) in futures_util::future::join_all(sends).await {
        assert_eq!(status, 200, "{body}");
    }
    let v: Value = app
        .get(&format!("/v1/uploads/{id}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(v["upload"]["instances"], files.len(), "{v}");
    let r = app
        .post_json(&format!("/v1/uploads/{id}/complete"), &json!({}))
        .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["report"]["instances"], files.len(), "{v}");
}

#[tokio::test]
async fn an_open_upload_collects_instances_and_stays_open_until_it_completes() {
    let app = spawn_app().await;
    let (files, _) = series_files("body");
    let r = post_bytes(&app, "/v1/series", "application/dicom", files[0].1.clone()).await;
    assert_eq!(r.status(), 201);
    let location = r.headers()["location"].to_str().unwrap().to_string();
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["upload"]["status"], "open");
    assert_eq!(v["upload"]["instances"], 1);
    let id = v["upload"]["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/v1/uploads/{id}"));
    let append = format!("/v1/series?upload={id}");
    for (k, (_, file)) in files.iter().enumerate().skip(1) {
        if k == 10 {
            continue;
        }
        let r = post_bytes(&app, &append, "application/dicom", file.clone()).await;
        assert_eq!(r.status(), 200);
        if k == 1 {
            // An instance is named by its SOP Instance UID, not by a hash of its bytes.
            let v: Value = r.json().await.unwrap();
            let sop = ctrecon::dicom::read_bytes("x", file, &Default::default())
                .unwrap()
                .sop_instance_uid;
            assert_eq!(v["appended"]["file"], sop.as_str(), "{v}");
        }
    }
    // Re-sending an instance changes nothing.
    let r = post_bytes(&app, &append, "application/dicom", files[0].1.clone()).await;
    let v: Value = r.json().await.unwrap();
    assert_eq!(
        (
            v["appended"]["duplicate"].clone(),
            v["upload"]["instances"].clone()
        ),
        (json!(true), json!(39))
    );
    // A broken instance is refused and leaves the upload as it was.
    let r = post_bytes(
        &app,
        &append,
        "application/dicom",
        b"not a dicom file at all".to_vec(),
    )
    .await;
    assert_problem(r, 422, "dicom_not_dicom").await;
    let truncated = files[3].1[..files[3].1.len() / 2].to_vec();
    let r = post_bytes(&app, &append, "application/dicom", truncated).await;
    assert_eq!(r.status(), 422);
    let v: Value = app.get(&location).await.json().await.unwrap();
    assert_eq!(v["upload"]["instances"], 39);

    // Completing with a slice missing fails, and the upload stays open for it.
    let complete = format!("/v1/uploads/{id}/complete");
    assert_problem(
        app.post_json(&complete, &json!({})).await,
        422,
        "series_missing_slices",
    )
    .await;
    let v: Value = app.get(&location).await.json().await.unwrap();
    assert_eq!(v["upload"]["status"], "open");
    let r = post_bytes(&app, &append, "application/dicom", files[10].1.clone()).await;
    assert_eq!(r.status(), 200);
    let r = app.post_json(&complete, &json!({})).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["shape"], json!([40, 64, 64]));
    assert_eq!(v["upload"]["instances"], 40);
    // Completed: nothing more goes in, and the instances are gone from the upload area.
    let r = post_bytes(&app, &append, "application/dicom", files[1].1.clone()).await;
    assert_problem(r, 409, "upload_closed").await;
    assert_problem(
        app.post_json(&complete, &json!({})).await,
        409,
        "upload_closed",
    )
    .await;
    assert!(!app.dir.path().join("uploads").join(&id).exists());

    let unknown = "/v1/series?upload=0192d1f2-7a3b-7c4d-8e5f-60718293a4b5";
    assert_problem(
        post_bytes(&app, unknown, "application/dicom", files[1].1.clone()).await,
        404,
        "upload_not_found",
    )
    .await;
    assert_problem(
        post_bytes(
            &app,
            "/v1/series?upload=../../etc",
            "application/dicom",
            files[1].1.clone(),
        )
        .await,
        400,
        "invalid_id",
    )
    .await;
    assert_problem(app.get("/v1/uploads/nope").await, 400, "invalid_id").await;
    assert_problem(
        app.get("/v1/series/0192d1f2-7a3b-7c4d-8e5f-60718293a4b5")
            .await,
        404,
        "series_not_found",
    )
    .await;
}

#[tokio::test]
async fn hostile_uploads_get_clear_errors_and_nothing_is_written_outside_the_data_directory() {
    let app = spawn_app().await;
    let (files, _) = series_files("body");
    assert_problem(
        post_bytes(&app, "/v1/series", "text/plain", b"hello".to_vec()).await,
        415,
        "unsupported_media_type",
    )
    .await;
    // A ZIP bomb: 64 MiB of zeros deflate to about 64 KiB.
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    zip.start_file("../../escape.dcm", zip::write::SimpleFileOptions::default())
        .unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..64 {
        zip.write_all(&zeros).unwrap();
    }
    let bomb = zip.finish().unwrap().into_inner();
    assert!(bomb.len() < 1 << 20);
    assert_problem(
        post_bytes(&app, "/v1/series", "application/zip", bomb).await,
        413,
        "zip_limits_exceeded",
    )
    .await;
    // A ZIP whose entries try to climb out: names are labels, the series is stored by id.
    let climbing: Vec<(String, Vec<u8>)> = files
        .iter()
        .map(|(n, b)| (format!("../../../tmp/{n}"), b.clone()))
        .collect();
    let r = post_bytes(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&climbing).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    // Over the upload limit (16 MiB in tests).
    let big = vec![0u8; 17 << 20];
    assert_problem(
        post_bytes(&app, "/v1/series", "application/zip", big).await,
        413,
        "body_too_large",
    )
    .await;
    // Files that are not DICOM, alone: refused with the reason.
    let junk = vec![
        ("a.dcm".to_string(), b"garbage".to_vec()),
        ("b.dcm".to_string(), vec![0u8; 200]),
    ];
    let p = assert_problem(post_form(&app, "", &junk).await, 422, "dicom_not_dicom").await;
    assert!(p["detail"].as_str().unwrap().contains("a.dcm"), "{p}");
    // Pixel data shorter than declared.
    let mut short = files[0].1.clone();
    short.truncate(short.len() - 1000);
    let r = post_form(&app, "", &[("short.dcm".to_string(), short)]).await;
    assert_eq!(r.status(), 422, "{}", r.text().await.unwrap());
    // Only the data directory's own layout exists, and no temporary file is left behind.
    let mut names: Vec<String> = std::fs::read_dir(app.dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with("ctrecon.sqlite"))
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "datasets",
            "instances",
            "results",
            "series",
            "tmp",
            "uploads"
        ]
    );
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("tmp"))
            .unwrap()
            .count(),
        0
    );
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("series"))
            .unwrap()
            .count(),
        1
    );
}

/// Surface area of an ellipsoid, Knud Thomsen's approximation (relative error ≤ 1.1 %).
fn ellipsoid_area(a: f64, b: f64, c: f64) -> f64 {
    let p = 1.6075;
    4.0 * PI * (((a * b).powf(p) + (a * c).powf(p) + (b * c).powf(p)) / 3.0).powf(1.0 / p)
}

#[tokio::test]
async fn a_volume_job_resamples_filters_and_makes_every_product_with_dicom_results() {
    let app = spawn_app().await;
    let series = upload_body(&app).await;
    let sid = series["id"].as_str().unwrap();
    let job = app
        .submit(&json!({
        "kind": "volume", "input": sid,
        "steps": [{"op": "resample", "spacing_mm": 3.0}, {"op": "median"}],
        "products": [
            {"type": "projection", "axis": "coronal", "kind": "mip"},
            {"type": "mpr", "plane": "sagittal", "slab": {"thickness_mm": 9, "kind": "mip"},
             "spacing_mm": 9, "extent_mm": 27},
            {"type": "mpr", "normal": [0, 1, 1], "pixel_mm": 2},
            {"type": "curved", "points_mm": [[-50, 0, 10], [0, 30, 10], [50, 0, 10]], "height": 40},
            {"type": "rotating", "frames": 8},
            {"type": "mesh", "iso": 0}
        ]}))
        .await;
    assert_eq!(job["kind"], "volume");
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let r = &done["result"];
    assert_eq!(r["units"], "hu");
    // z: 39 gaps of 4.5 mm = 175.5 mm → 59 samples of 3 mm.
    assert_eq!(r["shape"], json!([59, 64, 64]));
    let products = r["products"].as_array().unwrap();
    assert_eq!(products.len(), 6);
    assert_eq!(products[0]["shape"], json!([1, 59, 64]));
    assert_eq!(products[1]["shape"][0], 7);
    assert_eq!(products[4]["shape"][0], 8);
    // The mesh of the 0 HU surface is the body ellipsoid.
    let mesh = &products[5]["mesh"];
    assert_eq!(mesh["closed"], true);
    let v0 = 4.0 / 3.0 * PI * AXES[0] * AXES[1] * AXES[2];
    let a0 = ellipsoid_area(AXES[0], AXES[1], AXES[2]);
    let (vol, area) = (f(&mesh["volume_mm3"]), f(&mesh["area_mm2"]));
    println!("mesh: volume {vol:.0} mm³ (ellipsoid {v0:.0}), area {area:.0} mm² ({a0:.0})");
    assert!((vol - v0).abs() / v0 < 0.02, "volume {vol} vs {v0}");
    assert!((area - a0).abs() / a0 < 0.03, "area {area} vs {a0}");

    // Products in every format.
    let base = format!("/v1/jobs/{id}/result/products");
    let mip = bytes(&app, &format!("{base}/0?format=npy"), "application/x-npy").await;
    let (shape, px) = read_npy_f32(&mip);
    assert_eq!(shape, [1, 59, 64]);
    let centre = px[29 * 64 + 31];
    assert!(
        (centre - 1000.0).abs() < 1.0,
        "coronal MIP through the body: {centre} HU"
    );
    let png = bytes(&app, &format!("{base}/0?preset=bone"), "image/png").await;
    assert!(png.starts_with(b"\x89PNG"));
    let apng = bytes(
        &app,
        &format!("{base}/4?format=apng&preset=bone"),
        "image/apng",
    )
    .await;
    assert!(apng.windows(4).any(|w| w == b"acTL"));
    let sc = bytes(
        &app,
        &format!("{base}/1?format=dicom&frame=3"),
        "application/dicom",
    )
    .await;
    assert_eq!(&sc[128..132], b"DICM");
    assert!(sc.windows(25).any(|w| w == b"1.2.840.10008.5.1.4.1.1.7"));
    assert!(
        sc.windows(STUDY_UID.len())
            .any(|w| w == STUDY_UID.as_bytes())
    );
    let stl = bytes(&app, &format!("{base}/5"), "model/stl").await;
    let n = mesh["triangles"].as_u64().unwrap() as usize;
    assert_eq!(stl.len(), 84 + 50 * n);
    assert!(stl[..80].windows(9).any(|w| w == b"SPACE=LPS"));
    let encapsulated = bytes(&app, &format!("{base}/5?format=dicom"), "application/dicom").await;
    assert!(
        encapsulated
            .windows(29)
            .any(|w| w == b"1.2.840.10008.5.1.4.1.1.104.3")
    );
    assert!(encapsulated.windows(84).any(|w| w == &stl[..84]));
    assert_problem(
        app.get(&format!("{base}/0?format=stl")).await,
        422,
        "invalid_parameter",
    )
    .await;
    assert_problem(
        app.get(&format!("{base}/1?frame=7")).await,
        422,
        "slice_out_of_range",
    )
    .await;
    assert_problem(
        app.get(&format!("{base}/6")).await,
        404,
        "result_unavailable",
    )
    .await;
    assert_problem(app.get(&format!("{base}/x")).await, 400, "invalid_id").await;

    // Views of an HU volume use HU as they are; meshes take the full option set.
    let res = format!("/v1/jobs/{id}/result");
    let centre_slice = bytes(
        &app,
        &format!("{res}/slice?axis=axial&format=npy"),
        "application/x-npy",
    )
    .await;
    let (_, s) = read_npy_f32(&centre_slice);
    assert!(
        (s[32 * 64 + 20] - 1000.0).abs() < 1.0,
        "{}",
        s[32 * 64 + 20]
    );
    let small = bytes(
        &app,
        &format!("{res}/mesh.stl?iso=0&units=hu&largest=true&smoothing=5&target_triangles=2000"),
        "model/stl",
    )
    .await;
    let count = u32::from_le_bytes(small[80..84].try_into().unwrap());
    assert!(count <= 2000 && count > 100, "{count}");

    // The volume as a derived CT series: same HU and geometry, same study, a new series.
    let zip = bytes(&app, &format!("{res}/series.zip"), "application/zip").await;
    let (study, back) = assemble_zip(zip);
    assert_eq!(study, STUDY_UID);
    let npy = bytes(&app, &format!("{res}/volume.npy"), "application/x-npy").await;
    let (shape, values) = read_npy_f32(&npy);
    assert_eq!(back.volume.data.shape(), &shape[..]);
    let worst = values
        .iter()
        .zip(back.volume.data.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst <= 0.5 * 2000.0 / 65535.0 * 2.0 + 1e-2,
        "worst {worst} HU"
    );
    let frame: Frame = serde_json::from_value(r["frame"].clone()).unwrap();
    for c in 0..3 {
        assert!((back.volume.frame.origin_mm[c] - frame.origin_mm[c]).abs() < 1e-3);
        assert!((back.volume.frame.spacing_mm[c] - frame.spacing_mm[c]).abs() < 1e-6);
    }
    let enhanced = bytes(
        &app,
        &format!("{res}/series.zip?layout=enhanced"),
        "application/zip",
    )
    .await;
    let (_, back2) = assemble_zip(enhanced);
    assert_eq!(back2.volume.data.dim(), back.volume.data.dim());
    let mip_sc = bytes(
        &app,
        &format!("{res}/projection?axis=coronal&kind=mip&format=dicom&preset=bone"),
        "application/dicom",
    )
    .await;
    assert!(
        mip_sc
            .windows(25)
            .any(|w| w == b"1.2.840.10008.5.1.4.1.1.7")
    );
}

#[tokio::test]
async fn a_tilted_series_and_an_enhanced_multi_frame_file_come_through() {
    let app = spawn_app().await;
    // Gantry tilt of 12° about x: each slice moves 4.5·tan 12° mm posteriorly.
    let mut vol = body();
    let t = 12f64.to_radians();
    vol.frame.direction[2] = [0.0, t.sin(), t.cos()];
    vol.frame.spacing_mm[2] = 4.5 / t.cos();
    let tilted = write_ct_series(&vol, &meta("tilted")).unwrap();
    let r = post_form(&app, "", &tilted.files).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let rec = &v["series"][0]["series"];
    assert!((f(&rec["tilt_deg"]) - 12.0).abs() < 1e-3, "{rec}");
    assert!((f(&rec["normal_spacing_mm"]) - 4.5).abs() < 1e-4);
    assert!(
        rec["warnings"]
            .as_array()
            .unwrap()
            .iter()
            .any(|w| w["code"] == "gantry_tilt")
    );
    // Resampling makes it orthogonal: the frame's slice axis becomes the normal.
    let job = app
        .submit(&json!({"kind": "volume", "input": rec["id"], "steps": [{"op": "resample", "spacing_mm": 3}]}))
        .await;
    let done = app.finish(job["id"].as_str().unwrap()).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let frame: Frame = serde_json::from_value(done["result"]["frame"].clone()).unwrap();
    let n = frame.slice_normal();
    let d = frame.direction[2];
    assert!(
        (n[0] - d[0]).abs() + (n[1] - d[1]).abs() + (n[2] - d[2]).abs() < 1e-9,
        "{frame:?}"
    );
    // … so the series' tilt warning, stale after the resample, is not repeated on the job.
    assert!(
        !done["result"]["warnings"]
            .as_array()
            .is_some_and(|w| w.iter().any(|w| w["code"] == "gantry_tilt")),
        "{}",
        done["result"]
    );

    // One Enhanced CT file holding all 40 frames, appended to an open upload.
    let enhanced = write_enhanced_ct(&body(), &meta("enhanced")).unwrap();
    assert_eq!(enhanced.files.len(), 1);
    let r = post_bytes(
        &app,
        "/v1/series",
        "application/dicom",
        enhanced.files[0].1.clone(),
    )
    .await;
    let status = r.status();
    let answer: Value = r.json().await.unwrap();
    assert_eq!(status, 201, "{answer}");
    let id = answer["upload"]["id"].as_str().unwrap().to_string();
    let r = app
        .post_json(&format!("/v1/uploads/{id}/complete"), &json!({}))
        .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["report"]["frames"], 40);
    assert_eq!(v["series"][0]["series"]["shape"], json!([40, 64, 64]));
}

#[tokio::test]
async fn volume_jobs_are_checked_at_submission() {
    let app = spawn_app().await;
    let series = upload_body(&app).await;
    let sid = series["id"].as_str().unwrap();
    assert_problem(
        app.post_json(
            "/v1/jobs",
            &json!({"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5"}),
        )
        .await,
        404,
        "series_not_found",
    )
    .await;
    for (body, status, code) in [
        (
            json!({"kind": "volume", "input": sid, "steps": [{"op": "gaussian", "sigma_mm": -2}]}),
            422,
            "invalid_parameter",
        ),
        (
            json!({"kind": "volume", "input": sid, "steps": [{"op": "sharpen"}]}),
            422,
            "invalid_request",
        ),
        (
            json!({"kind": "volume", "input": sid, "colour": "red"}),
            422,
            "invalid_request",
        ),
        (
            json!({"kind": "volume", "input": "../x"}),
            422,
            "invalid_request",
        ),
        (
            json!({"kind": "tomosynthesis", "input": sid}),
            422,
            "invalid_request",
        ),
        (
            json!({"kind": "volume", "input": sid, "products": [{"type": "mpr", "plane": "axial", "size": [9000, 10]}]}),
            422,
            "invalid_parameter",
        ),
        (
            json!({"kind": "volume", "input": sid, "products": [{"type": "projection", "slab": [30, 50]}]}),
            422,
            "invalid_slab",
        ),
        (
            json!({"kind": "volume", "input": sid, "products": [{"type": "mesh", "iso": 0, "target_triangles": 2}]}),
            422,
            "invalid_mesh_options",
        ),
        (
            json!({"kind": "volume", "input": sid, "steps": [{"op": "resample", "spacing_mm": 0.05}]}),
            422,
            "invalid_parameter",
        ),
        // 631 × 631 × 586 voxels fit the voxel limit, but the median filter needs a second copy.
        (
            json!({"kind": "volume", "input": sid, "steps": [{"op": "resample", "spacing_mm": 0.3}, {"op": "median"}]}),
            422,
            "job_too_large",
        ),
    ] {
        assert_problem(app.post_json("/v1/jobs", &body).await, status, code).await;
    }
}

#[tokio::test]
async fn a_reconstruction_comes_back_as_dicom_and_feeds_a_volume_job() {
    let app = spawn_app().await;
    let dataset = app.simulate(cone_geometry(60, 48), 12.0).await;
    let job = app
        .submit(&json!({"input": dataset, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1.2, 1.2, 1.2]}}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(app.finish(&id).await["status"], "succeeded");
    let res = format!("/v1/jobs/{id}/result");
    let zip = bytes(&app, &format!("{res}/series.zip"), "application/zip").await;
    let (_, back) = assemble_zip(zip);
    let npy = bytes(&app, &format!("{res}/volume.npy"), "application/x-npy").await;
    let (shape, mu) = read_npy_f32(&npy);
    assert_eq!(back.volume.data.shape(), &shape[..]);
    // μ (1/mm) → HU with the service's μ_water (0.0192/mm), then int16 with a rescale.
    let hu: Vec<f32> = mu.iter().map(|&v| mu_to_hu(v, 0.0192)).collect();
    let range = hu.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = hu
        .iter()
        .zip(back.volume.data.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst <= range / 32767.0 + 0.05,
        "worst {worst} HU of ±{range}"
    );
    assert!((back.volume.frame.spacing_mm[2] - 1.2).abs() < 1e-6);
    let sc = bytes(
        &app,
        &format!("{res}/projection?axis=axial&kind=mip&format=dicom"),
        "application/dicom",
    )
    .await;
    assert_eq!(&sc[128..132], b"DICM");
    // The reconstruction's volume (μ) as input of a volume job.
    let v = app
        .submit(
            &json!({"kind": "volume", "input": id, "steps": [{"op": "gaussian", "sigma_mm": 0.5}],
                        "products": [{"type": "mesh", "iso": 0.1}]}),
        )
        .await;
    let vid = v["id"].as_str().unwrap().to_string();
    let done = app.finish(&vid).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["result"]["units"], "mu_per_mm");
    assert_eq!(done["result"]["products"][0]["mesh"]["closed"], true);
}

fn lidc_files() -> Option<Vec<(String, Vec<u8>)>> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if !dir.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
            dir.display()
        );
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
    Some(files)
}

#[tokio::test]
async fn lidc_over_http_series_mip_and_bone_mesh() {
    let Some(files) = lidc_files() else { return };
    let app = spawn_app_with(|s| {
        s.max_upload_bytes = 256 << 20;
        s.memory_budget_bytes = 4 << 30;
    })
    .await;
    let r = post_form(&app, "", &files).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let v: Value = r.json().await.unwrap();
    let rec = &v["series"][0]["series"];
    assert_eq!(rec["shape"], json!([133, 512, 512]));
    assert_eq!(rec["frame"]["spacing_mm"], json!([0.703125, 0.703125, 2.5]));
    let (lo, hi) = (f(&rec["hu_min"]), f(&rec["hu_max"]));
    assert!(
        lo >= -2048.0 && hi <= 4000.0 && hi > 1000.0,
        "HU {lo}..{hi}"
    );
    let job = app
        .submit(&json!({"kind": "volume", "input": rec["id"],
                        "products": [{"type": "projection", "axis": "coronal", "kind": "mip"},
                                     {"type": "mesh", "iso": 300}]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let mesh = &done["result"]["products"][1]["mesh"];
    println!("LIDC bone mesh over HTTP: {mesh}");
    // Integer HU at an integer iso-value: a closed 2-manifold all the same (no pinched vertex), and the STL as a
    // slicer welds it by position is that same surface.
    assert_eq!(
        (mesh["closed"].as_bool(), mesh["manifold"].as_bool()),
        (Some(true), Some(true)),
        "{mesh}"
    );
    let stl = bytes(
        &app,
        &format!("/v1/jobs/{id}/result/products/1"),
        "model/stl",
    )
    .await;
    let t = common::weld_stl(&stl).topology();
    assert!(t.closed && t.manifold, "{t:?}");
    assert_eq!(
        Some(t.euler_characteristic),
        mesh["euler_characteristic"].as_i64()
    );
    let area_cm2 = f(&mesh["area_mm2"]) / 100.0;
    let volume_cm3 = f(&mesh["volume_mm3"]) / 1000.0;
    assert!((1500.0..15000.0).contains(&area_cm2), "{area_cm2} cm²");
    assert!((200.0..3000.0).contains(&volume_cm3), "{volume_cm3} cm³");
    let png = bytes(
        &app,
        &format!("/v1/jobs/{id}/result/products/0?preset=bone"),
        "image/png",
    )
    .await;
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("lidc-coronal-mip-http.png");
    std::fs::write(&out, &png).unwrap();
    println!("coronal MIP written to {}", out.display());
    // The coronal MIP of a chest (looked at: ribs, spine, contrast in the vessels; z rows are 2.5 mm, columns
    // 0.70 mm): much of it is above 300 HU, and the band over the spine is brighter than the whole.
    let (shape, px) = read_npy_f32(
        &bytes(
            &app,
            &format!("/v1/jobs/{id}/result/products/0?format=npy"),
            "application/x-npy",
        )
        .await,
    );
    assert_eq!(shape, [1, 133, 512]);
    let bright = px.iter().filter(|&&v| v > 300.0).count() as f64 / px.len() as f64;
    assert!(
        (0.2..0.9).contains(&bright),
        "bone fraction of the MIP {bright}"
    );
    let mean = px.iter().map(|&v| v as f64).sum::<f64>() / px.len() as f64;
    let spine: Vec<f64> = (0..133)
        .flat_map(|r| (236..276).map(move |c| (r, c)))
        .map(|(r, c)| px[r * 512 + c] as f64)
        .collect();
    let spine_mean = spine.iter().sum::<f64>() / spine.len() as f64;
    assert!(
        spine_mean > mean + 100.0,
        "spine band {spine_mean} HU, whole MIP {mean} HU"
    );
}

/// pydicom's test files, each sent alone as `application/dicom` and as a one-file form: every answer is a 2xx or
/// a 4xx problem with a catalogue code (never a 5xx), and the service still answers afterwards.
#[tokio::test]
async fn every_file_of_the_pydicom_corpus_is_accepted_or_refused_with_a_4xx() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/pydicom");
    if !dir.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1",
            dir.display()
        );
        eprintln!("SKIPPED: {} is missing", dir.display());
        return;
    }
    let app = spawn_app_with(|s| s.max_upload_bytes = 64 << 20).await;
    fn walk(d: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else {
                out.push(p);
            }
        }
    }
    let mut paths = Vec::new();
    walk(&dir, &mut paths);
    paths.sort();
    assert!(paths.len() > 100, "{} files", paths.len());
    let (mut ok, mut refused) = (0, std::collections::BTreeMap::<String, usize>::new());
    for p in &paths {
        let name = p.strip_prefix(&dir).unwrap().to_string_lossy().into_owned();
        let body = std::fs::read(p).unwrap();
        for r in [
            post_bytes(&app, "/v1/series", "application/dicom", body.clone()).await,
            post_form(&app, "", &[(name.clone(), body.clone())]).await,
        ] {
            let status = r.status().as_u16();
            let text = r.text().await.unwrap();
            match status {
                200 | 201 => ok += 1,
                400..=499 => {
                    let v: Value =
                        serde_json::from_str(&text).unwrap_or_else(|_| panic!("{name}: {text}"));
                    let code = v["code"].as_str().unwrap_or_default().to_string();
                    assert!(
                        ctrecon::error_code::ErrorCode::from_code(&code).is_some(),
                        "{name}: {text}"
                    );
                    assert!(
                        !v["detail"].as_str().unwrap_or_default().is_empty(),
                        "{name}"
                    );
                    *refused.entry(code).or_default() += 1;
                }
                _ => panic!("{name}: {status} {text}"),
            }
        }
    }
    println!(
        "{} files: {ok} accepted, refused by code: {refused:?}",
        paths.len()
    );
    assert!(ok > 20, "{ok} accepted");
    assert_eq!(app.get("/healthz").await.status(), 200);
}
