//! Fuzz regressions of the series-assembly, ZIP-ingest, geometry and upload targets: every input kept under
//! `tests/fuzz-regressions/TARGET` goes through the fuzz target's own entry point (the upload target's through
//! the real server) and must return without a panic or a 5xx; the seeds named `valid-*` and the hand-written
//! cases must still give the answers written next to them. (`tests/dicom_hostile.rs` replays the DICOM and
//! `.npy` targets.)

use crate::common;

use std::path::Path;

use ctrecon::recon::control::unattended;
use ctrecon::recon::geometry::Geometry;
use ctrecon::series::{UnevenPolicy, assemble, fuzz_slices};

fn inputs(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz-regressions")
        .join(target);
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .expect("regression folder")
        .map(|e| {
            let p = e.expect("entry").path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).expect("read"))
        })
        .collect();
    out.sort();
    out
}

fn replay(target: &str, entry: fn(&[u8])) -> usize {
    let all = inputs(target);
    for (name, bytes) in &all {
        let r = std::panic::catch_unwind(|| entry(bytes));
        assert!(r.is_ok(), "{target}/{name}: panicked");
    }
    all.len()
}

#[test]
fn series_assembly_inputs_replay_and_the_seeds_assemble_as_written() {
    assert!(replay("series_assembly", ctrecon::series::fuzz_entry) >= 3);
    let seed = |name: &str| {
        let (_, bytes) = inputs("series_assembly")
            .into_iter()
            .find(|(n, _)| n == name)
            .expect("seed");
        let (slices, opts) = fuzz_slices(&bytes);
        (assemble(slices, &opts, unattended()), opts)
    };
    // Three 4×4 axial slices 1 mm apart: a 3×4×4 volume; pixel byte b is stored as 16·b − 1024 and read with
    // slope 1, intercept 0 (the second pixel's byte is 16).
    let (even, _) = seed("three-even-axial-slices.bin");
    let even = even.expect("three even slices assemble");
    assert_eq!(even.volume.data.shape(), &[3, 4, 4]);
    assert!((even.normal_spacing_mm - 1.0).abs() < 1e-9);
    assert_eq!(even.volume.data[[0, 0, 1]], 16.0 * 16.0 - 1024.0);
    // A missing slice is refused by default and resampled when asked: 5 slices at 0..4 mm.
    let (gap, opts) = seed("four-slices-one-missing-resampled.bin");
    assert_eq!(opts.uneven, UnevenPolicy::Resample);
    let gap = gap.expect("a missing slice is resampled");
    assert_eq!(gap.volume.data.shape(), &[5, 4, 4]);
    assert!(
        gap.warnings
            .iter()
            .any(|w| w.code == "missing_slices_interpolated"),
        "{:?}",
        gap.warnings
    );
    // Reversed order with one position repeated: the duplicate is dropped, the order restored.
    let (rev, _) = seed("reversed-and-repeated.bin");
    let rev = rev.expect("reversed slices assemble");
    assert_eq!(rev.volume.data.shape(), &[3, 4, 4]);
}

#[test]
fn geometry_inputs_replay_and_the_seeds_parse_as_written() {
    assert!(replay("geometry_json", ctrecon::recon::geometry::fuzz_entry) >= 6);
    let shape = |name: &str| -> Result<Vec<usize>, String> {
        let (_, bytes) = inputs("geometry_json")
            .into_iter()
            .find(|(n, _)| n == name)
            .expect("seed");
        let g: Geometry = serde_json::from_slice(&bytes).map_err(|e| e.to_string())?;
        let views = g.to_views().map_err(|e| e.to_string())?;
        Ok(views.data_shape())
    };
    assert_eq!(shape("valid-parallel.json"), Ok(vec![360, 363]));
    assert!(shape("valid-fan-arc.json").is_ok());
    assert!(shape("valid-cone.json").is_ok());
    assert!(shape("valid-fan-matlab.json").is_ok());
    for refused in [
        "count-above-u64.json",
        "counts-and-distances-at-the-limits.json",
        "cone-detector-inside-orbit.json",
        "fan-matlab-sensor-and-turn-counts-overflow.json",
    ] {
        assert!(shape(refused).is_err(), "{refused} must be refused");
    }
}

#[test]
fn zip_ingest_inputs_replay_and_leave_no_scratch_files() {
    assert!(replay("zip_ingest", ctrecon::dicom::fuzz_zip_entry) >= 1);
    let left: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .expect("temp dir")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&format!("ctrecon-fuzz-zip-{}-", std::process::id())))
        .collect();
    assert!(left.is_empty(), "scratch left behind: {left:?}");
}

#[tokio::test]
async fn upload_inputs_get_a_client_answer_from_the_real_server() {
    let app = common::spawn_app().await;
    let mut answers = Vec::new();
    for (name, bytes) in inputs("upload") {
        let (media_type, body) = ctrecon::http::upload::fuzz_upload_request(&bytes);
        let r = app
            .client
            .post(app.url("/v1/series"))
            .header("content-type", media_type)
            .body(body.to_vec())
            .send()
            .await
            .expect("the server answers");
        let status = r.status().as_u16();
        let doc: serde_json::Value = r.json().await.unwrap_or_default();
        assert!(status < 500, "upload/{name}: {status} {doc}");
        answers.push((name, status, doc));
    }
    let get = |name: &str| {
        answers
            .iter()
            .find(|(n, _, _)| n == name)
            .unwrap_or_else(|| panic!("seed {name}"))
    };
    // One instance and a text file in a form: the series of one, the text refused by name.
    let (_, status, doc) = get("form-one-instance-and-text.bin");
    assert_eq!(*status, 201, "{doc}");
    assert_eq!(doc["series"].as_array().map(Vec::len), Some(1), "{doc}");
    assert_eq!(doc["rejected"].as_array().map(Vec::len), Some(1), "{doc}");
    for name in ["form-one-zip.bin", "zip-body.bin"] {
        let (_, status, doc) = get(name);
        assert_eq!(*status, 201, "{name}: {doc}");
        assert_eq!(
            doc["series"].as_array().map(Vec::len),
            Some(1),
            "{name}: {doc}"
        );
    }
    // One `application/dicom` instance opens an upload that later instances append to.
    let (_, status, doc) = get("instance-body.bin");
    assert_eq!(*status, 201, "{doc}");
    assert_eq!(doc["appended"]["series_uid"], "1.2.3.5", "{doc}");
    assert_eq!(doc["upload"]["instances"], 1, "{doc}");
    // A form that stops before its closing boundary is a cut upload.
    let (_, status, doc) = get("form-without-closing-boundary.bin");
    assert_eq!(*status, 400, "{doc}");
    assert_eq!(doc["code"], "truncated_upload", "{doc}");
    let health = app.get("/healthz").await;
    assert_eq!(health.status(), 200);
}
