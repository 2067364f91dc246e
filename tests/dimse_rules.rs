//! Processing rules, deliveries and peers against real peers: DCMTK `storescu` and Orthanc send series to
//! ctrecon's DICOM node, a rule runs a volume job, and its DICOM results arrive in Orthanc by C-STORE —
//! checked through Orthanc's REST API (counts, study, frame of reference, referenced series, pixel values
//! against ctrecon's own result). Also: retries with backoff while the peer is down, per-instance refusals
//! with the peer's DIMSE status, a series arriving twice running once, and bad input to the new routes.
//!
//! Without Orthanc or DCMTK each test prints one skip line, unless `CTRECON_REQUIRE_PEERS=1`.

use crate::common;
use crate::orthanc;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{TestApp, spawn_app_with};
use ctrecon::config::Settings;
use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::dimse::Peer;
use ctrecon::storage::npy::decode_f32;
use ctrecon::volume::{Frame, Volume};
use orthanc::{Orthanc, OrthancOptions, free_port, orthanc_present};
use serde_json::{Value, json};

const SC: &str = "1.2.840.10008.5.1.4.1.1.7";
const CT: &str = "1.2.840.10008.5.1.4.1.1.2";
const STL: &str = "1.2.840.10008.5.1.4.1.1.104.3";

fn peer(ae: &str, port: u16) -> Peer {
    Peer {
        ae_title: ae.into(),
        host: "127.0.0.1".into(),
        port,
        store: true,
        query: true,
        retrieve: true,
    }
}

/// A ctrecon with a DICOM node on a free port, callers TESTSCU (storescu) and ORTHANC, fast completion and
/// fast retries.
async fn ctrecon(orthanc_port: u16, configure: impl FnOnce(&mut Settings)) -> TestApp {
    spawn_app_with(|s| {
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = 1;
        s.dicom.dimse_timeout_secs = 10;
        s.dicom.peers = vec![peer("TESTSCU", 1), peer("ORTHANC", orthanc_port)];
        s.dicom.delivery_retry_base_ms = 200;
        s.dicom.delivery_retry_max_ms = 800;
        s.dicom.delivery_max_attempts = 100;
        s.max_upload_bytes = 64 << 20;
        configure(s);
    })
    .await
}

/// What a synthetic series is.
struct Source {
    study_uid: String,
    series_uid: String,
    for_uid: String,
    files: Vec<PathBuf>,
}

/// A synthetic CT series of `nz` slices of 48 × 40 (1 × 1 × 2 mm): soft tissue with a 400 HU "bone"
/// block, plus `bump` HU everywhere (to change the content); written under `dir`.
fn synthetic(dir: &Path, nz: usize, bump: f32, uids: Option<(&str, &str, &str)>) -> Source {
    let data = ndarray::Array3::from_shape_fn((nz, 40, 48), |(k, j, i)| {
        let bone = (8..32).contains(&i) && (10..30).contains(&j) && (2..nz - 2).contains(&k);
        let v = if bone {
            400.0
        } else {
            40.0 + (i + 2 * j + 3 * k) as f32
        };
        v + bump
    });
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-24.0, -20.0, 10.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let (study, series, for_uid) = match uids {
        Some((a, b, c)) => (a.to_string(), b.to_string(), c.to_string()),
        None => (
            ctrecon::dicom::new_uid(),
            String::new(),
            ctrecon::dicom::new_uid(),
        ),
    };
    let meta = SeriesMeta {
        study_uid: Some(study.clone()),
        frame_of_reference_uid: Some(for_uid.clone()),
        patient_id: Some("RULES-1".into()),
        series_description: "L-SPINE bone".into(),
        series_number: 2,
        ..Default::default()
    };
    let s = write_ct_series(&vol, &meta).unwrap();
    std::fs::create_dir_all(dir).unwrap();
    let files = s
        .files
        .iter()
        .map(|(name, bytes)| {
            let p = dir.join(name);
            std::fs::write(&p, bytes).unwrap();
            if !series.is_empty() {
                // The same series again: its own Series Instance UID.
                let mut obj = dicom_object::open_file(&p).unwrap();
                obj.put(dicom_core::DataElement::new(
                    dicom_dictionary_std::tags::SERIES_INSTANCE_UID,
                    dicom_core::VR::UI,
                    dicom_core::PrimitiveValue::from(series.as_str()),
                ));
                obj.write_to_file(&p).unwrap();
            }
            p
        })
        .collect();
    Source {
        study_uid: study,
        series_uid: if series.is_empty() {
            s.series_uid
        } else {
            series
        },
        for_uid,
        files,
    }
}

async fn storescu(port: u16, dir: &Path) {
    let dir = dir.to_string_lossy().to_string();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("storescu")
            .args(["-aet", "TESTSCU", "-aec", "CTRECON", "+sd", "127.0.0.1"])
            .arg(port.to_string())
            .arg(dir)
            .env("TCP_NODELAY", "1")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

async fn json_of(r: reqwest::Response) -> Value {
    r.json().await.expect("json")
}

async fn post_rule(app: &TestApp, rule: Value) -> Value {
    let r = app.post_json("/v1/rules", &rule).await;
    assert_eq!(r.status(), 201);
    json_of(r).await
}

/// Poll `GET path` until `done` holds (bounds a hang; not a timing).
async fn until(app: &TestApp, path: &str, secs: u64, done: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let v = json_of(app.get(path).await).await;
        if done(&v) {
            return v;
        }
        assert!(Instant::now() < deadline, "{path} did not get there: {v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// The deliveries of `rule` once every one has finished (at least `n`), each with its instances.
async fn finished_deliveries(app: &TestApp, rule: &str, n: usize, secs: u64) -> Vec<Value> {
    let list = until(app, &format!("/v1/deliveries?rule={rule}"), secs, |v| {
        let d = v["deliveries"].as_array().cloned().unwrap_or_default();
        d.len() >= n
            && d.iter()
                .all(|d| d["state"] == "succeeded" || d["state"] == "failed")
    })
    .await;
    let mut out = Vec::new();
    for d in list["deliveries"].as_array().unwrap() {
        out.push(
            json_of(
                app.get(&format!("/v1/deliveries/{}", d["id"].as_str().unwrap()))
                    .await,
            )
            .await,
        );
    }
    out
}

/// Upload files to ctrecon over HTTP (multipart), 201 asserted.
async fn upload(app: &TestApp, files: &[PathBuf]) -> Value {
    let mut form = reqwest::multipart::Form::new();
    for f in files {
        let part = reqwest::multipart::Part::bytes(std::fs::read(f).unwrap())
            .file_name(f.file_name().unwrap().to_string_lossy().to_string())
            .mime_str("application/dicom")
            .unwrap();
        form = form.part("file", part);
    }
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    json_of(r).await
}

/// Stored value → HU of a CT instance in Orthanc, frame 0, row-major.
/// Also the rescale slope (one quantisation step, HU).
async fn orthanc_hu(o: &Orthanc, id: &str) -> (Vec<f32>, usize, usize, f64) {
    let tags = o.tags(id).await;
    let num = |k: &str| -> f64 {
        tags[k]
            .as_str()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(0.0)
    };
    let (slope, intercept) = (num("RescaleSlope"), num("RescaleIntercept"));
    let raw = o.get_bytes(&format!("/instances/{id}/frames/0/raw")).await;
    let hu = raw
        .chunks_exact(2)
        .map(|b| (i16::from_le_bytes([b[0], b[1]]) as f64 * slope + intercept) as f32)
        .collect();
    (hu, num("Rows") as usize, num("Columns") as usize, slope)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_series_from_storescu_fires_the_spine_rule_and_the_results_arrive_in_orthanc() {
    if !orthanc_present() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), 24, 0.0, None);
    spine_round_trip(dir.path(), &src, true).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lidc_idri_0001_from_storescu_fires_the_spine_rule_and_the_results_arrive_in_orthanc() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if !dir.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            ".testdata/lidc is missing and CTRECON_REQUIRE_TEST_DATA=1"
        );
        eprintln!("skipped: .testdata/lidc is missing");
        return;
    }
    if !orthanc_present() {
        return;
    }
    let first = dir.join("1-001.dcm");
    let h = ctrecon::dicom::read_header(&first, 16 << 20).unwrap();
    let src = Source {
        study_uid: h.study_uid,
        series_uid: h.series_uid,
        for_uid: h.frame_of_reference_uid.unwrap(),
        files: Vec::new(),
    };
    spine_round_trip(&dir, &src, false).await;
}

/// `storescu` sends the series in `dir` to ctrecon, the spine rule runs, and its results arrive in Orthanc.
async fn spine_round_trip(dir: &Path, src: &Source, synthetic_bone: bool) {
    let o = Orthanc::start(OrthancOptions::default()).await;
    let app = ctrecon(o.dicom_port, |_| {}).await;
    let node = app.dicom.expect("node").port();
    // The peers and a C-ECHO to Orthanc.
    let peers = json_of(app.get("/v1/peers").await).await;
    assert_eq!(peers["peers"][1]["ae_title"], "ORTHANC");
    let echo = app.post_json("/v1/peers/ORTHANC/echo", &json!({})).await;
    assert_eq!(echo.status(), 200);
    let echo = json_of(echo).await;
    assert_eq!(
        (echo["status"].as_u64(), echo["success"].as_bool()),
        (Some(0), Some(true))
    );
    assert!(echo["round_trip_ms"].as_f64().unwrap() > 0.0);

    post_rule(
        &app,
        json!({"name": "spine", "protocol": "spine", "destinations": ["ORTHANC"],
               "match": {"modality": "CT", "calling_ae": ["TESTSCU"],
                         "instances": {"min": 10}, "slice_thickness_mm": {"max": 3}}}),
    )
    .await;
    storescu(node, dir).await;

    let deliveries = finished_deliveries(&app, "spine", 1, 120).await;
    let d = &deliveries[0];
    assert_eq!(d["state"], "succeeded", "{d}");
    assert_eq!(d["destination"], "ORTHANC");
    let total = d["counts"]["total"].as_u64().unwrap() as usize;
    assert_eq!(d["counts"]["succeeded"].as_u64().unwrap() as usize, total);
    assert!(
        d["instances"]
            .as_array()
            .unwrap()
            .iter()
            .all(|i| i["status"] == 0)
    );

    // The rule links its run: the series, the job and the delivery.
    let rule = json_of(app.get("/v1/rules/spine").await).await;
    let run = &rule["runs"][0];
    assert_eq!(run["series_uid"], src.series_uid.as_str());
    assert_eq!(run["calling_ae"], "TESTSCU");
    assert_eq!(run["deliveries"][0], d["id"]);
    let job_id = run["job_id"].as_str().unwrap().to_string();
    assert_eq!(d["job_id"], job_id.as_str());
    let job = app.job(&job_id).await;
    let products = job["result"]["products"].as_array().unwrap().clone();
    assert_eq!(products.len(), 3);
    let frames = |p: &Value| p["shape"][0].as_u64().unwrap() as usize;
    // Sagittal and coronal slabs as derived CT (one instance per slab), the MIP as one Secondary Capture.
    assert_eq!(total, frames(&products[0]) + frames(&products[1]) + 1);

    // In Orthanc: every instance, in the source's study and frame of reference, referencing the source.
    let ids = o.instances().await;
    assert_eq!(ids.len(), total);
    let studies = o.get("/studies").await;
    assert_eq!(studies.as_array().unwrap().len(), 1);
    let mut ct_by_number = Vec::new();
    let (mut n_ct, mut n_sc) = (0, 0);
    for id in &ids {
        let t = o.tags(id).await;
        assert_eq!(t["StudyInstanceUID"], src.study_uid.as_str());
        assert_eq!(t["FrameOfReferenceUID"], src.for_uid.as_str(), "{t}");
        assert_eq!(
            t["ReferencedSeriesSequence"][0]["SeriesInstanceUID"],
            src.series_uid.as_str()
        );
        assert!(
            t["DerivationDescription"]
                .as_str()
                .unwrap()
                .contains(&job_id)
        );
        match t["SOPClassUID"].as_str().unwrap() {
            CT => {
                n_ct += 1;
                if t["SeriesNumber"] == "901" {
                    ct_by_number.push((
                        t["InstanceNumber"]
                            .as_str()
                            .unwrap()
                            .parse::<usize>()
                            .unwrap(),
                        id.clone(),
                    ));
                }
            }
            SC => n_sc += 1,
            other => panic!("unexpected SOP class {other}"),
        }
    }
    assert_eq!((n_ct, n_sc), (total - 1, 1));
    // The pixels of one derived sagittal slab against ctrecon's own product.
    ct_by_number.sort();
    assert_eq!(ct_by_number.len(), frames(&products[0]));
    let (k, id) = ct_by_number[ct_by_number.len() / 2].clone();
    let (hu, rows, cols, step) = orthanc_hu(&o, &id).await;
    let npy = app
        .get(&format!("/v1/jobs/{job_id}/result/products/0?format=npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let stack = decode_f32(&npy).unwrap();
    let shape = stack.shape().to_vec();
    assert_eq!((shape[1], shape[2]), (rows, cols));
    let frame = stack.index_axis(ndarray::Axis(0), k - 1);
    let worst = frame
        .iter()
        .zip(&hu)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    // int16 with a rescale: within half a quantisation step (slabs average to non-integers).
    assert!(
        (worst as f64) <= step / 2.0 + 1e-3,
        "largest difference {worst} HU, step {step}"
    );
    if synthetic_bone {
        assert!(
            frame.iter().any(|&v| (v - 400.0).abs() < 1.0),
            "the bone block is in the slab"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn orthanc_pushes_a_series_into_ctrecon_and_the_bone_stl_rule_sends_back_a_mesh_and_a_rotating_mip()
 {
    if !orthanc_present() {
        return;
    }
    let ctrecon_port = free_port();
    let o = Orthanc::start(OrthancOptions {
        ctrecon_port: Some(ctrecon_port),
        ..Default::default()
    })
    .await;
    let app = ctrecon(o.dicom_port, |s| s.dicom.port = Some(ctrecon_port)).await;
    post_rule(
        &app,
        json!({"name": "bone", "protocol": "bone_stl", "destinations": ["ORTHANC"],
               "match": {"calling_ae": ["ORTHANC"]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), 20, 0.0, None);
    for f in &src.files {
        o.post("/instances", std::fs::read(f).unwrap()).await;
    }
    let series = o.get("/series").await;
    let sid = series[0].as_str().unwrap().to_string();
    let r = o
        .client
        .post(o.url("/modalities/CTRECON/store"))
        .json(&json!({"Resources": [sid], "Synchronous": true}))
        .send()
        .await
        .unwrap();
    assert!(
        r.status().is_success(),
        "{}",
        r.text().await.unwrap_or_default()
    );

    let d = finished_deliveries(&app, "bone", 1, 180).await.remove(0);
    assert_eq!(d["state"], "succeeded", "{d}");
    // One Encapsulated STL and 36 Secondary Capture frames of one series.
    let instances = d["instances"].as_array().unwrap();
    let count = |c: &str| instances.iter().filter(|i| i["sop_class_uid"] == c).count();
    assert_eq!((count(STL), count(SC), instances.len()), (1, 36, 37));
    // Orthanc holds the source series and the results.
    let all = o.instances().await;
    assert_eq!(all.len(), src.files.len() + 37);
    let series = o.get("/series?expand").await;
    assert_eq!(
        series.as_array().unwrap().len(),
        3,
        "source, STL and rotating MIP series"
    );
    // The STL keeps the source's study and frame of reference and references the source series.
    let mut stl = None;
    for id in &all {
        let t = o.tags(id).await;
        if t["SOPClassUID"] == STL {
            stl = Some(t);
        }
    }
    let stl = stl.expect("the STL instance in Orthanc");
    assert_eq!(stl["StudyInstanceUID"], src.study_uid.as_str());
    assert_eq!(stl["FrameOfReferenceUID"], src.for_uid.as_str());
    assert_eq!(
        stl["ReferencedSeriesSequence"][0]["SeriesInstanceUID"],
        src.series_uid.as_str()
    );
    let rule = json_of(app.get("/v1/rules/bone").await).await;
    assert_eq!(rule["runs"][0]["calling_ae"], "ORTHANC");
    let job = app.job(rule["runs"][0]["job_id"].as_str().unwrap()).await;
    let mesh = &job["result"]["products"][0]["mesh"];
    assert!(mesh["triangles"].as_u64().unwrap() > 100, "{mesh}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_delivery_to_a_peer_that_is_down_is_retried_with_backoff_and_succeeds_when_it_comes_back()
{
    if !orthanc_present() {
        return;
    }
    let port = free_port();
    let app = ctrecon(port, |_| {}).await;
    // An HTTP upload fires rules too.
    post_rule(
        &app,
        json!({"name": "later", "job": {"products": [{"type": "projection", "axis": "coronal"}]},
               "destinations": ["ORTHANC"]}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), 12, 0.0, None);
    upload(&app, &src.files).await;
    let queued = until(&app, "/v1/deliveries?rule=later", 60, |v| {
        v["deliveries"][0]["attempts"].as_u64().unwrap_or(0) >= 3
    })
    .await;
    let d = &queued["deliveries"][0];
    assert!(
        matches!(d["state"].as_str(), Some("queued") | Some("sending")),
        "{d}"
    );
    let one = json_of(
        app.get(&format!("/v1/deliveries/{}", d["id"].as_str().unwrap()))
            .await,
    )
    .await;
    assert!(
        one["last_error"].as_str().unwrap_or("").contains("ORTHANC"),
        "{one}"
    );
    if one["state"] == "queued" {
        assert!(one["next_attempt_at"].is_string(), "{one}");
    }
    let o = Orthanc::start(OrthancOptions {
        dicom_port: port,
        ..Default::default()
    })
    .await;
    let d = finished_deliveries(&app, "later", 1, 60).await.remove(0);
    assert_eq!(d["state"], "succeeded", "{d}");
    assert!(d["attempts"].as_u64().unwrap() >= 4, "{d}");
    assert_eq!(o.instances().await.len(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_peer_holds_up_only_its_own_deliveries() {
    if !orthanc_present() {
        return;
    }
    // SILENT accepts connections and never answers: each attempt waits for the DIMSE timeout (10 s).
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let silent_port = silent.local_addr().unwrap().port();
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for c in silent.incoming().flatten() {
            held.push(c);
        }
    });
    let o = Orthanc::start(OrthancOptions::default()).await;
    let app = ctrecon(o.dicom_port, |s| {
        s.dicom.peers.push(peer("SILENT", silent_port));
    })
    .await;
    // SILENT first: its delivery is queued (and claimed) before ORTHANC's.
    post_rule(
        &app,
        json!({"name": "both", "job": {"products": [{"type": "projection", "axis": "coronal"}]},
               "destinations": ["SILENT", "ORTHANC"]}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), 12, 0.0, None);
    upload(&app, &src.files).await;
    let list = until(&app, "/v1/deliveries?rule=both", 60, |v| {
        v["deliveries"].as_array().is_some_and(|d| {
            d.iter()
                .any(|d| d["destination"] == "ORTHANC" && d["state"] == "succeeded")
        })
    })
    .await;
    let of = |dest: &str| {
        list["deliveries"]
            .as_array()
            .unwrap()
            .iter()
            .find(|d| d["destination"] == dest)
            .cloned()
            .unwrap()
    };
    // ORTHANC got its instance while SILENT's first attempt was still waiting for an answer.
    assert_eq!(o.instances().await.len(), 1);
    let s = of("SILENT");
    assert_eq!(
        (s["state"].as_str(), s["attempts"].as_u64()),
        (Some("sending"), Some(1)),
        "{s}"
    );
    assert_eq!(of("ORTHANC")["attempts"], 1);
}

/// The rule `mixed`: an axial MIP (Secondary Capture) and the volume (derived CT), sent to `dest`.
async fn mixed_rule_delivered(app: &TestApp, dest: &str, slices: usize) -> Value {
    post_rule(
        app,
        json!({"name": "mixed", "send_volume": true, "destinations": [dest],
               "job": {"products": [{"type": "projection", "axis": "axial"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), slices, 0.0, None);
    upload(app, &src.files).await;
    finished_deliveries(app, "mixed", 1, 60).await.remove(0)
}

fn instances_in(d: &Value, state: &str) -> Vec<Value> {
    d["instances"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|i| i["state"] == state)
        .cloned()
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_answering_a_failure_status_shows_that_status_per_instance() {
    // The peer: a second ctrecon node that takes instances up to 3000 bytes and answers 0xA700 (out of
    // resources) for larger ones — the CT slices of this series, not its small Secondary Capture.
    let dir = tempfile::tempdir().unwrap();
    let receiver = ctrecon::dimse::DicomNode::start(
        &ctrecon::dimse::NodeSettings {
            ae_title: "RECEIVER".into(),
            port: Some(0),
            peers: vec![peer("CTRECON", 1)],
            max_instance_bytes: 3000,
            stable_age_secs: 60,
            ..Default::default()
        },
        dir.path(),
    )
    .await
    .unwrap();
    let port = receiver.local_addr().port();
    let app = ctrecon(1, |s| s.dicom.peers.push(peer("RECEIVER", port))).await;
    let d = mixed_rule_delivered(&app, "RECEIVER", 6).await;
    assert_eq!(d["state"], "failed", "{d}");
    let failed = instances_in(&d, "failed");
    assert_eq!(failed.len(), 6, "{d}");
    for i in &failed {
        assert_eq!(i["sop_class_uid"], CT);
        assert_eq!(i["status"], 0xA700, "{i}");
        assert!(i["detail"].as_str().unwrap().contains("larger than"), "{i}");
    }
    let stored = instances_in(&d, "succeeded");
    assert_eq!(stored.len(), 1);
    assert_eq!(
        (
            stored[0]["sop_class_uid"].as_str(),
            stored[0]["status"].as_u64()
        ),
        (Some(SC), Some(0))
    );
    assert!(d["last_error"].as_str().unwrap().contains("6 of 7"), "{d}");
    // A retry sends only what was not stored (and the peer refuses it again); only a failed delivery
    // can be retried.
    let id = d["id"].as_str().unwrap().to_string();
    let r = app
        .post_json(&format!("/v1/deliveries/{id}/retry"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    let again = finished_deliveries(&app, "mixed", 1, 60).await.remove(0);
    assert_eq!(
        (
            again["counts"]["failed"].as_u64(),
            again["counts"]["succeeded"].as_u64(),
            again["attempts"].as_u64()
        ),
        (Some(6), Some(1), Some(1))
    );
    problem(
        app.post_json(
            "/v1/deliveries/0192d1f2-7a3b-7c4d-8e5f-60718293a4b5/retry",
            &json!({}),
        )
        .await,
        404,
        "delivery_not_found",
    )
    .await;
    drop(receiver);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_series_arriving_twice_runs_once_and_changed_content_runs_again() {
    let app = ctrecon(1, |_| {}).await;
    post_rule(
        &app,
        json!({"name": "once", "job": {"products": [{"type": "projection"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let first = synthetic(&dir.path().join("a"), 6, 0.0, None);
    upload(&app, &first.files).await;
    upload(&app, &first.files).await;
    let runs = |v: &Value| v["runs"].as_array().map_or(0, |r| r.len());
    let rule = json_of(app.get("/v1/rules/once").await).await;
    assert_eq!(runs(&rule), 1, "{rule}");
    // The same UIDs with other pixel values: a new content hash, a new run.
    let changed = synthetic(
        &dir.path().join("b"),
        6,
        5.0,
        Some((&first.study_uid, &first.series_uid, &first.for_uid)),
    );
    upload(&app, &changed.files).await;
    let rule = json_of(app.get("/v1/rules/once").await).await;
    assert_eq!(runs(&rule), 2, "{rule}");
    let r = &rule["runs"];
    assert_eq!(r[0]["series_uid"], r[1]["series_uid"]);
    assert_ne!(r[0]["content_hash"], r[1]["content_hash"]);
    assert_ne!(r[0]["job_id"], r[1]["job_id"]);
}

/// Set Body Part Examined (0018,0015) of every file.
fn set_body_part(files: &[PathBuf], part: &str) {
    for f in files {
        let mut obj = dicom_object::open_file(f).unwrap();
        obj.put(dicom_core::DataElement::new(
            dicom_dictionary_std::tags::BODY_PART_EXAMINED,
            dicom_core::VR::CS,
            dicom_core::PrimitiveValue::from(part),
        ));
        obj.write_to_file(f).unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rule_matches_on_body_part_and_its_job_names_the_rule_and_its_deliveries() {
    // ORTHANC is a peer that is down: the delivery is made and waits for it.
    let app = ctrecon(free_port(), |_| {}).await;
    post_rule(
        &app,
        json!({"name": "lumbar", "match": {"body_part": "L*SPINE"}, "destinations": ["ORTHANC"],
               "job": {"products": [{"type": "projection"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let chest = synthetic(&dir.path().join("chest"), 6, 0.0, None);
    set_body_part(&chest.files, "CHEST");
    let spine = synthetic(&dir.path().join("spine"), 6, 0.0, None);
    set_body_part(&spine.files, "LSPINE");
    let bare = synthetic(&dir.path().join("bare"), 6, 0.0, None);
    for s in [&chest, &spine, &bare] {
        upload(&app, &s.files).await;
    }
    // Only the series whose Body Part Examined matches ran the rule.
    let rule = json_of(app.get("/v1/rules/lumbar").await).await;
    let runs = rule["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 1, "{rule}");
    assert_eq!(runs[0]["series_uid"], spine.series_uid.as_str());
    let job_id = runs[0]["job_id"].as_str().unwrap().to_string();
    // Its job names the rule, the source series and, once it succeeded, its delivery.
    let job = until(&app, &format!("/v1/jobs/{job_id}"), 120, |j| {
        j["deliveries"].as_array().is_some_and(|d| !d.is_empty())
    })
    .await;
    assert_eq!(job["status"], "succeeded", "{job}");
    assert_eq!(job["rule"]["name"], "lumbar", "{job}");
    assert_eq!(job["rule"]["run_id"], runs[0]["id"]);
    assert_eq!(job["rule"]["series_uid"], spine.series_uid.as_str());
    assert_eq!(job["rule"]["series_id"], runs[0]["series_id"]);
    assert_eq!(job["links"]["rule"], "/v1/rules/lumbar");
    assert_eq!(
        job["links"]["source_series"],
        format!("/v1/series/{}", runs[0]["series_id"].as_str().unwrap()).as_str()
    );
    assert_eq!(
        job["links"]["deliveries"],
        format!("/v1/deliveries?job_id={job_id}").as_str()
    );
    let d = &job["deliveries"].as_array().unwrap()[0];
    assert_eq!(d["destination"], "ORTHANC");
    let delivery = json_of(app.get(d["links"]["self"].as_str().unwrap()).await).await;
    assert_eq!(delivery["job_id"], job_id.as_str());
    assert_eq!(delivery["rule"], "lumbar");
    let listed = json_of(app.get(job["links"]["deliveries"].as_str().unwrap()).await).await;
    assert_eq!(listed["deliveries"][0]["id"], d["id"]);
    // A job no rule made names neither.
    let source = json_of(
        app.get(job["links"]["source_series"].as_str().unwrap())
            .await,
    )
    .await;
    assert_eq!(source["series_uid"], spine.series_uid.as_str());
    let plain = app
        .submit(&json!({"kind": "volume", "input": source["id"]}))
        .await;
    let plain = app.job(plain["id"].as_str().unwrap()).await;
    assert!(
        plain.get("rule").is_none() && plain.get("deliveries").is_none(),
        "{plain}"
    );
}

async fn problem(r: reqwest::Response, status: u16, code: &str) {
    assert_eq!(r.status(), status);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["code"], code, "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_to_rules_deliveries_and_peers_gets_stable_problem_codes() {
    let down = free_port();
    let app = ctrecon(down, |s| {
        s.dicom.rules = vec![json!({"name": "from-config", "protocol": "spine"})];
    })
    .await;
    let ok = json!({"name": "r1", "protocol": "spine", "destinations": ["ORTHANC"]});
    post_rule(&app, ok.clone()).await;
    problem(app.post_json("/v1/rules", &ok).await, 409, "rule_exists").await;
    let mut unknown_field = ok.clone();
    unknown_field["colour"] = json!("red");
    problem(
        app.post_json("/v1/rules", &unknown_field).await,
        422,
        "invalid_request",
    )
    .await;
    let mut unknown_peer = ok.clone();
    unknown_peer["name"] = json!("r2");
    unknown_peer["destinations"] = json!(["NOWHERE"]);
    problem(
        app.post_json("/v1/rules", &unknown_peer).await,
        422,
        "unknown_peer",
    )
    .await;
    let mut pattern = ok.clone();
    pattern["name"] = json!("r3");
    pattern["match"] = json!({"series_description": "spine[0-9]"});
    problem(
        app.post_json("/v1/rules", &pattern).await,
        422,
        "invalid_pattern",
    )
    .await;
    let neither = json!({"name": "r4"});
    problem(
        app.post_json("/v1/rules", &neither).await,
        422,
        "invalid_rule",
    )
    .await;
    problem(app.get("/v1/rules/none").await, 404, "rule_not_found").await;
    // The configuration's rule is listed and read-only.
    let list = json_of(app.get("/v1/rules").await).await;
    let names: Vec<&str> = list["rules"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["from-config", "r1"]);
    assert_eq!(list["rules"][0]["source"], "config");
    let r = app
        .client
        .delete(app.url("/v1/rules/from-config"))
        .send()
        .await
        .unwrap();
    problem(r, 409, "rule_read_only").await;
    // PUT replaces an API rule; DELETE removes it.
    let mut replaced = ok.clone();
    replaced["enabled"] = json!(false);
    let r = app
        .client
        .put(app.url("/v1/rules/r1"))
        .json(&replaced)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(json_of(r).await["enabled"], false);
    let r = app
        .client
        .delete(app.url("/v1/rules/r1"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    // Peers and deliveries.
    problem(
        app.post_json("/v1/peers/NOWHERE/echo", &json!({})).await,
        404,
        "peer_not_found",
    )
    .await;
    problem(
        app.post_json("/v1/peers/ORTHANC/echo", &json!({})).await,
        502,
        "peer_unreachable",
    )
    .await;
    let missing = "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5";
    problem(
        app.get(&format!("/v1/deliveries/{missing}")).await,
        404,
        "delivery_not_found",
    )
    .await;
    problem(app.get("/v1/deliveries/not-an-id").await, 400, "invalid_id").await;
    problem(
        app.get("/v1/deliveries?state=lost").await,
        400,
        "invalid_query",
    )
    .await;
    problem(
        app.post_json(
            "/v1/deliveries",
            &json!({"job_id": missing, "destination": "ORTHANC"}),
        )
        .await,
        404,
        "job_not_found",
    )
    .await;
    problem(
        app.post_json(
            "/v1/deliveries",
            &json!({"job_id": missing, "destination": "NOWHERE"}),
        )
        .await,
        422,
        "unknown_peer",
    )
    .await;
    problem(
        app.post_json(
            "/v1/deliveries",
            &json!({"job_id": missing, "destination": "ORTHANC", "x": 1}),
        )
        .await,
        422,
        "invalid_request",
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_readme_pacs_example_runs_as_written_against_orthanc() {
    if !orthanc_present() {
        return;
    }
    let have = |t: &str| {
        std::process::Command::new(t)
            .arg("--version")
            .output()
            .is_ok()
    };
    if !(have("curl") && have("jq")) {
        eprintln!("skipped: the README's PACS example needs curl and jq");
        return;
    }
    let config = common::readme_blocks("json pacs-config");
    let scripts = common::readme_blocks("sh pacs");
    assert_eq!(
        (config.len(), scripts.len()),
        (1, 1),
        "one configuration and one script"
    );
    let config: Value = serde_json::from_str(&config[0]).unwrap();
    let mut node: ctrecon::dimse::NodeSettings =
        serde_json::from_value(config["dicom"].clone()).unwrap();
    let o = Orthanc::start(OrthancOptions::default()).await;
    let node_port = free_port();
    let doc_node_port = node.port.unwrap();
    node.port = Some(node_port);
    for p in &mut node.peers {
        if p.ae_title == "ORTHANC" {
            p.port = o.dicom_port;
        }
    }
    let app = spawn_app_with(|s| s.dicom = node).await;
    let work = tempfile::tempdir().unwrap();
    synthetic(&work.path().join("series"), 16, 0.0, None);
    let host = app.base.trim_start_matches("http://").to_string();
    let script = format!(
        "set -euo pipefail\ncurl() {{ command curl --fail-with-body \"$@\"; }}\n{}",
        scripts[0]
            .replace("localhost:8080", &host)
            .replace("localhost:8042", &format!("127.0.0.1:{}", o.http_port))
            .replace(&format!(" {doc_node_port}"), &format!(" {node_port}"))
    );
    let dir = work.path().to_path_buf();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("timeout")
            .args(["300", "bash", "-c"])
            .arg(&script)
            .current_dir(dir)
            .env("TCP_NODELAY", "1")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Every `# {…}` line of the block is a line the block printed, in order.
    let expected: Vec<&str> = scripts[0]
        .lines()
        .filter_map(|l| {
            l.trim()
                .strip_prefix("# {")
                .map(|_| l.trim().trim_start_matches("# "))
        })
        .collect();
    let printed: Vec<&str> = stdout.lines().filter(|l| l.starts_with('{')).collect();
    assert_eq!(printed, expected, "{stdout}");
}

/// A ctrecon over `data` on its own runtime and thread, as a separate process would be: stopping it (the
/// returned sender) drops the runtime and every task of it, the delivery worker included.
fn ctrecon_on_thread(
    data: PathBuf,
    orthanc_port: u16,
) -> (
    String,
    std::sync::mpsc::Sender<()>,
    std::thread::JoinHandle<()>,
) {
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
    let handle = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async move {
            let mut s = common::test_settings(&data);
            s.dicom.peers = vec![peer("ORTHANC", orthanc_port)];
            s.dicom.delivery_retry_base_ms = 200;
            s.dicom.delivery_retry_max_ms = 400;
            s.dicom.delivery_max_attempts = 1000;
            let app = ctrecon::http::Application::build(s).await.unwrap();
            let base = format!("http://{}", app.local_addr());
            ctrecon::dimse::serve_node(app.app().clone()).await.unwrap();
            tokio::spawn(app.run_until(std::future::pending::<()>()));
            ready_tx.send(base).unwrap();
            tokio::task::spawn_blocking(move || stop_rx.recv())
                .await
                .ok();
        });
        rt.shutdown_timeout(Duration::from_secs(5));
    });
    let base = ready_rx.recv().unwrap();
    (base, stop_tx, handle)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_queued_delivery_survives_a_restart_and_is_sent_when_the_peer_is_up() {
    if !orthanc_present() {
        return;
    }
    let data = tempfile::tempdir().unwrap();
    let port = free_port();
    let client = reqwest::Client::new();
    let (base, stop, handle) = ctrecon_on_thread(data.path().to_path_buf(), port);
    let r = client
        .post(format!("{base}/v1/rules"))
        .json(
            &json!({"name": "keep", "job": {"products": [{"type": "projection"}]},
                      "destinations": ["ORTHANC"]}),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(dir.path(), 6, 0.0, None);
    let mut form = reqwest::multipart::Form::new();
    for f in &src.files {
        form = form.part(
            "file",
            reqwest::multipart::Part::bytes(std::fs::read(f).unwrap())
                .file_name("x.dcm")
                .mime_str("application/dicom")
                .unwrap(),
        );
    }
    let r = client
        .post(format!("{base}/v1/series"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    // Attempts fail while the peer is down.
    let deadline = Instant::now() + Duration::from_secs(60);
    let before = loop {
        let v: Value = client
            .get(format!("{base}/v1/deliveries?rule=keep"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if v["deliveries"][0]["attempts"].as_u64().unwrap_or(0) >= 2 {
            break v["deliveries"][0].clone();
        }
        assert!(Instant::now() < deadline, "{v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    stop.send(()).unwrap();
    tokio::task::spawn_blocking(move || handle.join().unwrap())
        .await
        .unwrap();

    // Restart over the same data with the peer up: the same delivery is sent.
    let o = Orthanc::start(OrthancOptions {
        dicom_port: port,
        ..Default::default()
    })
    .await;
    let (base, stop, handle) = ctrecon_on_thread(data.path().to_path_buf(), port);
    let deadline = Instant::now() + Duration::from_secs(60);
    let after = loop {
        let v: Value = client
            .get(format!(
                "{base}/v1/deliveries/{}",
                before["id"].as_str().unwrap()
            ))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if v["state"] == "succeeded" || v["state"] == "failed" {
            break v;
        }
        assert!(Instant::now() < deadline, "{v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(after["state"], "succeeded", "{after}");
    assert!(
        after["attempts"].as_u64() > before["attempts"].as_u64(),
        "{after}"
    );
    assert_eq!(o.instances().await.len(), 1);
    let list: Value = client
        .get(format!("{base}/v1/deliveries"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        list["deliveries"].as_array().unwrap().len(),
        1,
        "no second delivery: {list}"
    );
    stop.send(()).unwrap();
    tokio::task::spawn_blocking(move || handle.join().unwrap())
        .await
        .unwrap();
}
