//! ctrecon as a DICOMweb client and a complete instance index, against a real Orthanc with its DICOMweb
//! plugin: a rule whose destination is Orthanc's `/dicom-web` (HTTP basic authentication on in Orthanc)
//! STOWs its results there — checked through Orthanc's REST API (count, UIDs, pixel values of a derived
//! slice against the job's `volume.npy`) and `/v1/deliveries`; an origin that is down is tried again with
//! backoff until it is up; wrong credentials fail every instance with the HTTP status. Without Orthanc, one
//! skip line per test (a failure under `CTRECON_REQUIRE_PEERS=1`).
//!
//! Also, with no peer and the DICOM node off: QIDO-RS finds an HTTP-uploaded series and a volume job's
//! derived CT, Secondary Capture and Encapsulated STL results, which go with the job.

use crate::common;
use crate::orthanc;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{TestApp, spawn_app_with};
use ctrecon::config::Settings;
use ctrecon::config::dicom::WebPeer;
use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::storage::npy::decode_f32;
use ctrecon::volume::{Frame, Volume};
use orthanc::{Orthanc, OrthancOptions, free_port, orthanc_dicomweb_present};
use serde_json::{Value, json};

const SC: &str = "1.2.840.10008.5.1.4.1.1.7";
const CT: &str = "1.2.840.10008.5.1.4.1.1.2";
const STL: &str = "1.2.840.10008.5.1.4.1.1.104.3";

const USER: &str = "ctrecon";
const PASSWORD: &str = "a-long-test-password";

fn web_peer(name: &str, url: String, password: Option<&str>) -> WebPeer {
    WebPeer {
        name: name.into(),
        url,
        bearer_token: None,
        username: password.map(|_| USER.into()),
        password: password.map(Into::into),
        timeout_secs: 60,
        batch_instances: 5,
    }
}

/// A ctrecon without a DICOM node, fast retries, `peers` as its DICOMweb destinations.
async fn ctrecon(peers: Vec<WebPeer>, configure: impl FnOnce(&mut Settings)) -> TestApp {
    spawn_app_with(|s| {
        s.dicom.web_peers = peers;
        s.dicom.delivery_retry_base_ms = 200;
        s.dicom.delivery_retry_max_ms = 800;
        s.dicom.delivery_max_attempts = 100;
        s.max_upload_bytes = 64 << 20;
        configure(s);
    })
    .await
}

/// An Orthanc with the DICOMweb plugin, on `http_port` (0: any), with basic authentication when `auth`.
async fn orthanc(http_port: u16, auth: bool) -> Orthanc {
    Orthanc::start(OrthancOptions {
        http_port,
        // The plugin loads with a server entry; this test never uses it.
        dicomweb: Some(("http://127.0.0.1:9/dicom-web/".into(), None)),
        user: auth.then(|| (USER.to_string(), PASSWORD.to_string())),
        ..Default::default()
    })
    .await
}

/// A synthetic CT series of `nz` slices of 48 × 40 (1 × 1 × 2 mm): soft tissue with a 400 HU "bone"
/// block, written under `dir`; its study UID and files.
fn synthetic(dir: &Path, nz: usize) -> (String, Vec<PathBuf>) {
    let data = ndarray::Array3::from_shape_fn((nz, 40, 48), |(k, j, i)| {
        let bone = (8..32).contains(&i) && (10..30).contains(&j) && (2..nz - 2).contains(&k);
        if bone {
            400.0
        } else {
            40.0 + (i + 2 * j + 3 * k) as f32
        }
    });
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-24.0, -20.0, 10.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let study = ctrecon::dicom::new_uid();
    let meta = SeriesMeta {
        study_uid: Some(study.clone()),
        frame_of_reference_uid: Some(ctrecon::dicom::new_uid()),
        patient_id: Some("WEB-1".into()),
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
            p
        })
        .collect();
    (study, files)
}

async fn json_of(r: reqwest::Response) -> Value {
    r.json().await.expect("json")
}

async fn post_rule(app: &TestApp, rule: Value) {
    let r = app.post_json("/v1/rules", &rule).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
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

/// The one delivery of `rule` once it finished, with its instances.
async fn finished_delivery(app: &TestApp, rule: &str, secs: u64) -> Value {
    let list = until(app, &format!("/v1/deliveries?rule={rule}"), secs, |v| {
        let d = v["deliveries"].as_array().cloned().unwrap_or_default();
        d.len() == 1 && (d[0]["state"] == "succeeded" || d[0]["state"] == "failed")
    })
    .await;
    let id = list["deliveries"][0]["id"].as_str().unwrap();
    json_of(app.get(&format!("/v1/deliveries/{id}")).await).await
}

/// Upload files to ctrecon over HTTP (multipart), 201 asserted; the upload's answer.
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

/// Stored value → HU of a CT instance in Orthanc, frame 0, row-major; also rows, columns and the rescale
/// slope (one quantisation step, HU).
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

fn count_by(d: &Value, key: &str) -> BTreeMap<String, usize> {
    let mut m = BTreeMap::new();
    for i in d["instances"].as_array().unwrap() {
        *m.entry(i[key].as_str().unwrap_or("").to_string())
            .or_default() += 1;
    }
    m
}

/// The first value of attribute `tag` of a DICOM JSON object, as text.
fn text(item: &Value, tag: &str) -> String {
    match &item[tag]["Value"][0] {
        Value::String(s) => s.clone(),
        Value::Null => String::new(),
        v => v.to_string(),
    }
}

/// QIDO-RS instances of `study` on ctrecon: `(series number, SOP class, SOP instance UID)` each.
async fn qido_instances(app: &TestApp, study: &str) -> Vec<(i64, String, String)> {
    let r = app
        .client
        .get(app.url(&format!(
            "/dicom-web/studies/{study}/instances?includefield=00200011"
        )))
        .header("accept", "application/dicom+json")
        .send()
        .await
        .unwrap();
    if r.status() == 204 {
        return Vec::new();
    }
    assert_eq!(r.status(), 200);
    let v: Value = r.json().await.unwrap();
    v.as_array()
        .unwrap()
        .iter()
        .map(|i| {
            (
                text(i, "00200011").parse().unwrap_or(-1),
                text(i, "00080016"),
                text(i, "00080018"),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rule_with_a_dicomweb_destination_stows_its_results_into_orthanc_with_basic_auth() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let o = orthanc(0, true).await;
    let app = ctrecon(
        vec![web_peer("ORTHANC-WEB", o.url("/dicom-web"), Some(PASSWORD))],
        |_| {},
    )
    .await;
    post_rule(
        &app,
        json!({"name": "web", "send_volume": true, "destinations": ["ORTHANC-WEB"],
               "job": {"products": [{"type": "projection", "axis": "axial"},
                                    {"type": "mesh", "iso": 300}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let (study, files) = synthetic(dir.path(), 12);
    upload(&app, &files).await;

    let d = finished_delivery(&app, "web", 180).await;
    assert_eq!(d["state"], "succeeded", "{d}");
    assert_eq!(d["destination"], "ORTHANC-WEB");
    // The volume as 12 derived CT slices, the MIP as one Secondary Capture, the mesh as one STL — sent in
    // batches of 5, every one acknowledged in a Referenced SOP Sequence.
    let by_class = count_by(&d, "sop_class_uid");
    assert_eq!(
        by_class,
        BTreeMap::from([(CT.into(), 12), (SC.into(), 1), (STL.into(), 1)]),
        "{d}"
    );
    assert_eq!(d["counts"]["succeeded"], 14, "{d}");
    assert!(
        d["instances"]
            .as_array()
            .unwrap()
            .iter()
            .all(|i| i["state"] == "succeeded" && i["status"] == 0),
        "{d}"
    );
    let sent: BTreeSet<String> = d["instances"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["sop_instance_uid"].as_str().unwrap().to_string())
        .collect();

    // In Orthanc (its REST API behind the same credentials): exactly these instances, in the source's study.
    let ids = o.instances().await;
    assert_eq!(ids.len(), 14);
    let mut in_orthanc = BTreeSet::new();
    let mut ct_by_number = Vec::new();
    for id in &ids {
        let t = o.tags(id).await;
        assert_eq!(t["StudyInstanceUID"], study.as_str());
        in_orthanc.insert(t["SOPInstanceUID"].as_str().unwrap().to_string());
        if t["SOPClassUID"] == CT {
            let k: usize = t["InstanceNumber"]
                .as_str()
                .unwrap()
                .trim()
                .parse()
                .unwrap();
            ct_by_number.push((k, id.clone()));
        }
    }
    assert_eq!(in_orthanc, sent);

    // The pixels of one derived slice against the job's volume.npy (HU).
    let job_id = d["job_id"].as_str().unwrap();
    let job = app.job(job_id).await;
    assert_eq!(job["result"]["units"], "hu", "{job}");
    ct_by_number.sort();
    let (k, id) = ct_by_number[ct_by_number.len() / 2].clone();
    let (hu, rows, cols, step) = orthanc_hu(&o, &id).await;
    let npy = app
        .get(&format!("/v1/jobs/{job_id}/result/volume.npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let vol = decode_f32(&npy).unwrap();
    let shape = vol.shape().to_vec();
    assert_eq!((shape[0], shape[1], shape[2]), (12, rows, cols));
    let slice = vol.index_axis(ndarray::Axis(0), k - 1);
    let worst = slice
        .iter()
        .zip(&hu)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        (worst as f64) <= step / 2.0 + 1e-3,
        "largest difference {worst} HU, step {step}"
    );
    assert!(
        slice.iter().any(|&v| (v - 400.0).abs() < 1.0),
        "the bone block"
    );

    // ctrecon's own index holds the same results (same UIDs) beside the source, node off.
    let indexed = qido_instances(&app, &study).await;
    let derived: BTreeSet<String> = indexed
        .iter()
        .filter(|(n, _, _)| *n >= 900)
        .map(|(_, _, uid)| uid.clone())
        .collect();
    assert_eq!(derived, sent);
    assert_eq!(indexed.iter().filter(|(n, _, _)| *n == 2).count(), 12);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dicomweb_origin_that_is_down_is_tried_again_with_backoff_and_gets_the_results_once_up() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let port = free_port();
    let app = ctrecon(
        vec![web_peer(
            "LATER",
            format!("http://127.0.0.1:{port}/dicom-web/"),
            None,
        )],
        |_| {},
    )
    .await;
    post_rule(
        &app,
        json!({"name": "later", "destinations": ["LATER"],
               "job": {"products": [{"type": "projection", "axis": "coronal"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let (_, files) = synthetic(dir.path(), 10);
    upload(&app, &files).await;
    let queued = until(&app, "/v1/deliveries?rule=later", 60, |v| {
        v["deliveries"][0]["attempts"].as_u64().unwrap_or(0) >= 3
    })
    .await;
    let d = &queued["deliveries"][0];
    let id = d["id"].as_str().unwrap().to_string();
    let one = json_of(app.get(&format!("/v1/deliveries/{id}")).await).await;
    assert!(
        matches!(one["state"].as_str(), Some("queued") | Some("sending")),
        "{one}"
    );
    assert!(
        one["last_error"]
            .as_str()
            .unwrap_or("")
            .contains("STOW-RS to LATER"),
        "{one}"
    );
    if one["state"] == "queued" {
        assert!(one["next_attempt_at"].is_string(), "{one}");
    }
    let o = orthanc(port, false).await;
    let d = finished_delivery(&app, "later", 60).await;
    assert_eq!(d["state"], "succeeded", "{d}");
    assert!(d["attempts"].as_u64().unwrap() >= 4, "{d}");
    assert_eq!(d["instances"][0]["status"], 0);
    let ids = o.instances().await;
    assert_eq!(ids.len(), 1);
    let t = o.tags(&ids[0]).await;
    assert_eq!(t["SOPClassUID"], SC);
    assert_eq!(t["SOPInstanceUID"], d["instances"][0]["sop_instance_uid"]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_credentials_fail_every_instance_with_the_http_status_and_are_not_tried_again() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let o = orthanc(0, true).await;
    let app = ctrecon(
        vec![web_peer(
            "ORTHANC-WEB",
            o.url("/dicom-web"),
            Some("not-the-password"),
        )],
        |_| {},
    )
    .await;
    post_rule(
        &app,
        json!({"name": "denied", "send_volume": true, "destinations": ["ORTHANC-WEB"],
               "job": {"products": [{"type": "projection", "axis": "axial"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let (_, files) = synthetic(dir.path(), 8);
    upload(&app, &files).await;
    let d = finished_delivery(&app, "denied", 120).await;
    assert_eq!(d["state"], "failed", "{d}");
    assert_eq!(d["attempts"], 1, "{d}");
    assert_eq!(
        (
            d["counts"]["total"].as_u64(),
            d["counts"]["failed"].as_u64()
        ),
        (Some(9), Some(9)),
        "{d}"
    );
    for i in d["instances"].as_array().unwrap() {
        let detail = i["detail"].as_str().unwrap_or("");
        assert!(detail.contains("HTTP 401"), "{i}");
        assert!(
            i.get("status").is_none(),
            "no DICOM status for an HTTP refusal: {i}"
        );
    }
    assert!(d["last_error"].as_str().unwrap().contains("9 of 9"), "{d}");
    assert!(o.instances().await.is_empty());
}

/// `ctrecon_storage_bytes{kind="…"}` from `/metrics`.
async fn storage_bytes(app: &TestApp, kind: &str) -> f64 {
    let text = app.get("/metrics").await.text().await.unwrap();
    let prefix = format!("ctrecon_storage_bytes{{kind=\"{kind}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {prefix} in {text}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn qido_finds_an_http_upload_and_a_jobs_derived_ct_sc_and_stl_results_with_the_node_off() {
    let app = ctrecon(Vec::new(), |_| {}).await;
    assert!(app.dicom.is_none());
    let dir = tempfile::tempdir().unwrap();
    let (study, files) = synthetic(dir.path(), 12);
    let up = upload(&app, &files).await;
    let series_id = up["series"][0]["series"]["id"]
        .as_str()
        .unwrap()
        .to_string();

    // The upload itself: 12 CT instances in the index at once.
    let indexed = qido_instances(&app, &study).await;
    assert_eq!(indexed.len(), 12, "{indexed:?}");
    assert!(indexed.iter().all(|(n, c, _)| *n == 2 && c == CT));
    assert!(storage_bytes(&app, "instances").await > 0.0);

    let job = app
        .submit(&json!({"kind": "volume", "input": series_id,
                        "products": [{"type": "projection", "axis": "axial"},
                                     {"type": "mesh", "iso": 300}]}))
        .await;
    let job_id = job["id"].as_str().unwrap().to_string();
    // The `final` event means everything the job made is findable: one QIDO-RS query right after it
    // finds every result, with no waiting.
    let mut events = crate::sse::Sse::open(
        &app.client,
        &app.url(&format!("/v1/jobs/{job_id}/events")),
        None,
    )
    .await;
    let evs = events.until(120, |e| e.name == "final").await;
    let done = &evs.last().expect("a final event").data;
    assert_eq!(done["status"], "succeeded", "{done}");
    let all = qido_instances(&app, &study).await;
    assert_eq!(all.len(), 12 + 14, "{all:?}");
    // The source, the volume as a derived CT series (900), the MIP (901, Secondary Capture), the mesh
    // (902, Encapsulated STL).
    let mut by_series: BTreeMap<(i64, String), usize> = BTreeMap::new();
    for (n, class, _) in &all {
        *by_series.entry((*n, class.clone())).or_default() += 1;
    }
    assert_eq!(
        by_series,
        BTreeMap::from([
            ((2, CT.to_string()), 12),
            ((900, CT.to_string()), 12),
            ((901, SC.to_string()), 1),
            ((902, STL.to_string()), 1),
        ])
    );
    // The STL comes back by WADO-RS as the file that was indexed.
    let (_, _, stl_uid) = all.iter().find(|(_, c, _)| c == STL).unwrap();
    let series = app
        .client
        .get(app.url(&format!("/dicom-web/studies/{study}/series")))
        .header("accept", "application/dicom+json")
        .send()
        .await
        .unwrap();
    let series: Value = series.json().await.unwrap();
    let stl_series = series
        .as_array()
        .unwrap()
        .iter()
        .find(|s| text(s, "00200011") == "902")
        .map(|s| text(s, "0020000E"))
        .unwrap();
    let r = app
        .client
        .get(app.url(&format!(
            "/dicom-web/studies/{study}/series/{stl_series}/instances/{stl_uid}"
        )))
        .header("accept", "multipart/related; type=\"application/dicom\"")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let body = r.bytes().await.unwrap();
    let mesh = app
        .get(&format!("/v1/jobs/{job_id}/result/products/1"))
        .await
        .bytes()
        .await
        .unwrap();
    assert!(mesh.len() > 84, "a binary STL");
    assert!(
        body.windows(mesh.len()).any(|w| w == &mesh[..]),
        "the Encapsulated STL carries the job's mesh"
    );

    // Deleting the job takes its results out of the index.
    let r = app
        .client
        .delete(app.url(&format!("/v1/jobs/{job_id}")))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    let left = qido_instances(&app, &study).await;
    assert_eq!(left.len(), 12, "{left:?}");
    assert!(!app.dir.path().join("results").join(&job_id).exists());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_web_peer_with_a_bearer_token_stows_into_a_ctrecon_that_checks_it_and_peers_hide_it() {
    const TOKEN: &str = "bearer-test-token-5f0c9a";
    // The target: another ctrecon that takes only this token on every route, /dicom-web included.
    let target = spawn_app_with(|s| {
        s.api_tokens = vec![TOKEN.to_string()];
        s.max_upload_bytes = 64 << 20;
    })
    .await;
    let bearer = |name: &str, token: &str| WebPeer {
        bearer_token: Some(token.into()),
        ..web_peer(name, target.url("/dicom-web"), None)
    };
    let app = ctrecon(
        vec![
            bearer("TARGET", TOKEN),
            bearer("TARGET-WRONG", "not-the-token"),
        ],
        |_| {},
    )
    .await;
    // /v1/peers lists the web peers with their kind and which credentials they use, never the tokens.
    let peers = app.get("/v1/peers").await;
    assert_eq!(peers.status(), 200);
    let listed = peers.text().await.unwrap();
    assert!(
        !listed.contains(TOKEN) && !listed.contains("not-the-token"),
        "{listed}"
    );
    let peers: Value = serde_json::from_str(&listed).unwrap();
    let web = peers["web_peers"].as_array().unwrap();
    assert_eq!(web.len(), 2, "{peers}");
    assert_eq!(web[0]["kind"], "dicomweb");
    assert_eq!(web[0]["name"], "TARGET");
    assert_eq!(web[0]["url"], target.url("/dicom-web").as_str());
    assert_eq!(web[0]["auth"], "bearer");
    post_rule(
        &app,
        json!({"name": "bearer", "send_volume": true, "destinations": ["TARGET", "TARGET-WRONG"],
               "job": {"products": [{"type": "projection", "axis": "axial"}]}}),
    )
    .await;
    let dir = tempfile::tempdir().unwrap();
    let (study, files) = synthetic(dir.path(), 6);
    upload(&app, &files).await;
    let list = until(&app, "/v1/deliveries?rule=bearer", 180, |v| {
        let d = v["deliveries"].as_array().cloned().unwrap_or_default();
        d.len() == 2
            && d.iter()
                .all(|d| d["state"] == "succeeded" || d["state"] == "failed")
    })
    .await;
    let mut by_dest = BTreeMap::new();
    for d in list["deliveries"].as_array().unwrap() {
        let id = d["id"].as_str().unwrap();
        let full = json_of(app.get(&format!("/v1/deliveries/{id}")).await).await;
        by_dest.insert(d["destination"].as_str().unwrap().to_string(), full);
    }
    // With the token: every instance stored (the volume's six derived CT slices and the MIP).
    let ok = &by_dest["TARGET"];
    assert_eq!(ok["state"], "succeeded", "{ok}");
    assert_eq!(
        count_by(ok, "sop_class_uid"),
        BTreeMap::from([(CT.into(), 6), (SC.into(), 1)]),
        "{ok}"
    );
    // With a wrong token: refused by the target, 401 on every instance, nothing stored from it.
    let wrong = &by_dest["TARGET-WRONG"];
    assert_eq!(wrong["state"], "failed", "{wrong}");
    for i in wrong["instances"].as_array().unwrap() {
        assert_eq!(i["state"], "failed", "{wrong}");
        assert!(
            i["detail"].as_str().unwrap_or("").contains("401"),
            "{wrong}"
        );
    }
    // The target holds exactly the instances sent, in the source's study, each found by QIDO-RS with the
    // token; a derived slice has the job's HU values.
    let target_client = reqwest::Client::new();
    let found: Value = target_client
        .get(target.url(&format!(
            "/dicom-web/studies/{study}/instances?includefield=00200013"
        )))
        .bearer_auth(TOKEN)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let sent: BTreeSet<String> = ok["instances"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["sop_instance_uid"].as_str().unwrap().to_string())
        .collect();
    let there: BTreeSet<String> = found
        .as_array()
        .unwrap()
        .iter()
        .map(|i| text(i, "00080018"))
        .collect();
    assert_eq!(there, sent);
    let ct = found
        .as_array()
        .unwrap()
        .iter()
        .find(|i| text(i, "00080016") == CT && text(i, "00200013") == "3")
        .expect("derived slice 3");
    let r = target_client
        .get(text(ct, "00081190"))
        .bearer_auth(TOKEN)
        .header(
            "accept",
            "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let ct_type = r.headers()["content-type"].to_str().unwrap().to_string();
    let body = r.bytes().await.unwrap();
    let boundary = ct_type.split("boundary=").nth(1).unwrap().trim_matches('"');
    let start = body.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
    let end = body
        .windows(boundary.len() + 4)
        .rposition(|w| w == format!("\r\n--{boundary}").as_bytes())
        .unwrap();
    let inst = ctrecon::dicom::read_bytes(
        "slice 3",
        &body[start..end],
        &ctrecon::dicom::ReadLimits::default(),
    )
    .unwrap();
    let s = &inst.slices[0];
    let job_id = ok["job_id"].as_str().unwrap();
    let npy = app
        .get(&format!("/v1/jobs/{job_id}/result/volume.npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let vol = decode_f32(&npy).unwrap();
    let slice = vol.index_axis(ndarray::Axis(0), 2);
    let worst = slice
        .iter()
        .zip(&s.stored)
        .map(|(&v, &st)| (v as f64 - (st as f64 * s.rescale_slope + s.rescale_intercept)).abs())
        .fold(0.0f64, f64::max);
    assert!(
        worst <= s.rescale_slope / 2.0 + 1e-3,
        "largest difference {worst} HU, step {}",
        s.rescale_slope
    );
    // Without the token the target answers nothing.
    let r = target_client
        .get(target.url(&format!("/dicom-web/studies/{study}/instances")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
}
