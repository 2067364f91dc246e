//! The contract is exact: schemathesis (a real peer, pinned in tests/peers/schemathesis-requirements.txt and
//! installed by `scripts/install-peers.sh`) generates requests from the served `openapi.yaml`, valid and
//! invalid, sends them to a real server that requires a bearer token, and checks every answer against the
//! document: no 5xx, documented status codes, content types, headers and schemas, invalid data refused, valid
//! data accepted, and no route answering without the token. The run is reproducible (fixed seed) and bounded
//! (examples per operation), and must end with no failure.
//!
//! Before the run the test seeds the server with one of everything an operation can name — datasets, a
//! succeeded reconstruction and volume job, series, open uploads, rules, a failed delivery, a study stored by
//! STOW-RS, and a configured DICOM peer (the node itself) — and writes their ids to a file that
//! `tests/peers/schemathesis_hooks.py` reads: most valid requests then name things that exist, STOW-RS and
//! `POST /v1/series` get real DICOM bodies, and `POST /v1/sinograms` a real array. The hooks tally every
//! answer; at least [`MIN_SUCCESS_SHARE`] of the operations must reach a 2xx, so that the checks see the
//! success answers and not only 404s.
//!
//! Without schemathesis (neither `.peers/venv/bin/schemathesis` nor one on `PATH`) the test prints one skip
//! line and passes, unless `CTRECON_REQUIRE_PEERS=1` (as CI sets), where it fails.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::TestApp;
use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::dimse::Peer;
use ctrecon::volume::{Frame, Volume};
use serde_json::{Value, json};

const TOKEN: &str = "contract-test-token-0123456789";
/// Examples per operation and phase; with the fixed seed the run is the same every time.
const MAX_EXAMPLES: u32 = 40;
const SEED: u64 = 20_261_125;
/// Longer than any run here has taken: a hung run fails instead of blocking CI.
const LIMIT: Duration = Duration::from_secs(600);
/// The share of the operations that must answer at least one request with a 2xx.
const MIN_SUCCESS_SHARE: f64 = 0.8;
/// The DICOM node's own AE title, configured as a peer of itself: echo and deliveries reach a real node.
const OWN_AE: &str = "CTRECON-CONTRACT";
/// A peer nobody listens for: a delivery to it fails (one attempt), so that it can be retried.
const DEAD_AE: &str = "NOWHERE";

/// The schemathesis executable: the project's own (`scripts/install-peers.sh`), else one on `PATH`.
fn schemathesis() -> Option<PathBuf> {
    let own = Path::new(env!("CARGO_MANIFEST_DIR")).join(".peers/venv/bin/schemathesis");
    if own.is_file() {
        return Some(own);
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join("schemathesis"))
        .find(|p| p.is_file())
}

/// The last `n` lines of `text`.
fn tail(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// A client that sends the bearer token.
fn authorised() -> reqwest::Client {
    let mut headers = reqwest::header::HeaderMap::new();
    headers.insert(
        reqwest::header::AUTHORIZATION,
        format!("Bearer {TOKEN}").parse().expect("header value"),
    );
    reqwest::Client::builder()
        .default_headers(headers)
        .build()
        .expect("client")
}

/// `method path` with `body` sent as `media`, expecting `status`; the JSON answer.
async fn send(
    app: &TestApp,
    method: reqwest::Method,
    path: &str,
    body: Option<(&str, Vec<u8>)>,
    status: u16,
) -> Value {
    let mut req = app.client.request(method.clone(), app.url(path));
    if let Some((media, bytes)) = body {
        req = req.header("content-type", media).body(bytes);
    }
    let r = req.send().await.expect("request");
    let got = r.status().as_u16();
    let text = r.text().await.unwrap_or_default();
    assert_eq!(got, status, "seeding: {method} {path}: {text}");
    serde_json::from_str(&text).unwrap_or(Value::Null)
}

async fn post_json(app: &TestApp, path: &str, body: Value, status: u16) -> Value {
    let bytes = serde_json::to_vec(&body).expect("json");
    send(
        app,
        reqwest::Method::POST,
        path,
        Some(("application/json", bytes)),
        status,
    )
    .await
}

/// Poll `GET path` until `done` holds (bounds a hang; not a timing).
async fn until(app: &TestApp, path: &str, done: impl Fn(&Value) -> bool) -> Value {
    let started = Instant::now();
    loop {
        let v = send(app, reqwest::Method::GET, path, None, 200).await;
        if done(&v) {
            return v;
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "seeding: {path} stays {v}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn id_of(v: &Value) -> String {
    v["id"]
        .as_str()
        .unwrap_or_else(|| panic!("no id in {v}"))
        .to_string()
}

/// A small CT series (24 × 20, 6 slices of 2 mm) of its own study: the study UID, the series UID and the files.
fn series(patient: &str) -> (String, String, Vec<(String, Vec<u8>)>) {
    let data = ndarray::Array3::from_shape_fn((6, 20, 24), |(k, j, i)| {
        if (6..18).contains(&i) && (5..15).contains(&j) && (1..5).contains(&k) {
            400.0
        } else {
            (i + j + k) as f32
        }
    });
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-12.0, -10.0, 0.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let meta = SeriesMeta {
        patient_id: Some(patient.into()),
        series_description: format!("contract {patient}"),
        series_number: 1,
        ..Default::default()
    };
    let s = write_ct_series(&vol, &meta).expect("a synthetic series");
    (s.study_uid, s.series_uid, s.files)
}

/// The ZIP of `files`.
fn zip_of(files: &[(String, Vec<u8>)]) -> Vec<u8> {
    ctrecon::dicom::write_zip(files).expect("a ZIP")
}

/// A multipart/related body of DICOM parts and its Content-Type.
fn stow_body(files: &[(String, Vec<u8>)]) -> (String, Vec<u8>) {
    let boundary = "contract-boundary-7d9c";
    let mut body = Vec::new();
    for (_, bytes) in files {
        body.extend_from_slice(
            format!("--{boundary}\r\nContent-Type: application/dicom\r\n\r\n").as_bytes(),
        );
        body.extend_from_slice(bytes);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (
        format!("multipart/related; type=\"application/dicom\"; boundary={boundary}"),
        body,
    )
}

/// Seed the server with one of everything an operation names; write what the hooks need under `dir`.
async fn seed(app: &TestApp, dir: &Path) -> Value {
    use reqwest::Method;
    let geometry = common::parallel_geometry(24, 16, 1.0);
    let phantom = json!({"table": "modified_shepp_logan", "scale_mm": 6.0});
    let simulate = || json!({"phantom": phantom, "geometry": geometry});
    let dataset = id_of(&post_json(app, "/v1/simulations", simulate(), 201).await);
    let dataset_spare = id_of(&post_json(app, "/v1/simulations", simulate(), 201).await);
    let job_body = json!({"input": dataset, "algorithm": {"name": "fbp"},
                          "grid": {"nx": 16, "ny": 16, "dx_mm": 1, "dy_mm": 1},
                          "outputs": ["volume", "metrics"]});
    let job = id_of(&post_json(app, "/v1/jobs", job_body.clone(), 202).await);
    let job_spare = id_of(&post_json(app, "/v1/jobs", job_body.clone(), 202).await);

    // Series: one for reading and a volume job, one to delete; each also stored by STOW-RS.
    let (study, series_uid, files) = series("CONTRACT-1");
    let (_, _, spare_files) = series("CONTRACT-2");
    let uploaded = send(
        app,
        Method::POST,
        "/v1/series",
        Some(("application/zip", zip_of(&files))),
        201,
    )
    .await;
    let series_id = uploaded["series"][0]["series"]["id"]
        .as_str()
        .expect("series id")
        .to_string();
    let spare = send(
        app,
        Method::POST,
        "/v1/series",
        Some(("application/zip", zip_of(&spare_files))),
        201,
    )
    .await;
    let series_spare = spare["series"][0]["series"]["id"]
        .as_str()
        .expect("series id")
        .to_string();
    let (media, body) = stow_body(&files);
    send(
        app,
        Method::POST,
        "/dicom-web/studies",
        Some((&media, body)),
        200,
    )
    .await;
    let instances = send(
        app,
        Method::GET,
        &format!("/dicom-web/studies/{study}/series/{series_uid}/instances"),
        None,
        200,
    )
    .await;
    let instance = instances[0]["00080018"]["Value"][0]
        .as_str()
        .expect("an SOP Instance UID")
        .to_string();
    let volume_job = id_of(
        &post_json(
            app,
            "/v1/jobs",
            json!({"kind": "volume", "input": series_id,
                   "products": [{"type": "projection", "axis": "coronal", "kind": "mip"},
                                {"type": "mesh", "iso": 200}]}),
            202,
        )
        .await,
    );

    // Open uploads of a third series: one to read, one to cancel, one holding every file to complete.
    let (_, _, upload_files) = series("CONTRACT-3");
    let mut uploads = Vec::new();
    for _ in 0..3 {
        let v = send(
            app,
            Method::POST,
            "/v1/series",
            Some(("application/dicom", upload_files[0].1.clone())),
            201,
        )
        .await;
        uploads.push(id_of(&v["upload"]));
    }
    for (_, bytes) in &upload_files[1..] {
        let path = format!("/v1/series?upload={}", uploads[2]);
        send(
            app,
            Method::POST,
            &path,
            Some(("application/dicom", bytes.clone())),
            200,
        )
        .await;
    }

    // Rules: one to read and replace, one to delete.
    let rule = |name: &str| json!({"name": name, "job": {"products": [{"type": "projection", "axis": "axial"}]}});
    post_json(app, "/v1/rules", rule("contract"), 201).await;
    post_json(app, "/v1/rules", rule("contract-spare"), 201).await;

    for id in [&job, &job_spare, &volume_job] {
        let done = until(app, &format!("/v1/jobs/{id}"), |v| {
            v["status"] != "queued" && v["status"] != "running"
        })
        .await;
        assert_eq!(done["status"], "succeeded", "seeding: {done}");
    }
    // A delivery that fails, for retry.
    let delivery = id_of(
        &post_json(
            app,
            "/v1/deliveries",
            json!({"job_id": volume_job, "destination": DEAD_AE}),
            202,
        )
        .await,
    );
    until(app, &format!("/v1/deliveries/{delivery}"), |v| {
        v["state"] == "failed"
    })
    .await;

    // Bodies the hooks send as they are.
    let dicom = dir.join("instance.dcm");
    std::fs::write(&dicom, &files[0].1).expect("write");
    let npy = dir.join("sinogram.npy");
    let zeros = vec![0u8; 24 * 16 * 4];
    std::fs::write(&npy, common::npy("<f4", "(24, 16)", &zeros)).expect("write");
    json!({
        "dataset": [dataset], "dataset_spare": [dataset_spare],
        "job": [job], "job_spare": [job_spare], "volume_job": [volume_job],
        "series": [series_id], "series_spare": [series_spare],
        "upload": [uploads[0]], "upload_spare": [uploads[1]], "upload_complete": [uploads[2]],
        "rule": ["contract"], "rule_spare": ["contract-spare"],
        "delivery": [delivery], "peer": [OWN_AE],
        "study": [study], "series_uid": [series_uid], "instance": [instance],
        "job_body": job_body,
        "geometry": geometry.to_string(),
        "dicom_file": dicom, "npy_file": npy,
    })
}

/// What the hooks tallied of each operation ("METHOD /path"): the statuses it answered and the seconds its
/// answers took in all.
fn tally(path: &Path) -> BTreeMap<String, (BTreeSet<u16>, f64)> {
    let mut out: BTreeMap<String, (BTreeSet<u16>, f64)> = BTreeMap::new();
    for line in std::fs::read_to_string(path).unwrap_or_default().lines() {
        let mut words = line.split_whitespace();
        if let (Some(method), Some(route), Some(status), Some(secs)) =
            (words.next(), words.next(), words.next(), words.next())
            && let (Ok(status), Ok(secs)) = (status.parse(), secs.parse::<f64>())
        {
            let entry = out.entry(format!("{method} {route}")).or_default();
            entry.0.insert(status);
            entry.1 += secs;
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn schemathesis_finds_no_difference_between_openapi_yaml_and_the_server() {
    let Some(exe) = schemathesis() else {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "schemathesis is missing and CTRECON_REQUIRE_PEERS=1: run scripts/install-peers.sh"
        );
        println!("skipped: schemathesis not found (run scripts/install-peers.sh)");
        return;
    };
    let dicom_port = crate::cluster::free_port();
    let peer = |ae: &str, port: u16| Peer {
        ae_title: ae.into(),
        host: "127.0.0.1".into(),
        port,
        store: true,
        query: true,
        retrieve: true,
    };
    let mut app = common::spawn_app_with(|s| {
        s.api_tokens = vec![TOKEN.to_string()];
        s.dicom.port = Some(dicom_port);
        s.dicom.ae_title = OWN_AE.into();
        s.dicom.peers = vec![peer(OWN_AE, dicom_port), peer(DEAD_AE, 1)];
        s.dicom.delivery_max_attempts = 1;
        s.dicom.delivery_retry_base_ms = 100;
        s.dicom.delivery_retry_max_ms = 100;
    })
    .await;
    app.client = authorised();
    let report = tempfile::tempdir().expect("temp dir");
    let seeded = seed(&app, report.path()).await;
    let seed_file = report.path().join("seed.json");
    std::fs::write(&seed_file, seeded.to_string()).expect("write the seed");
    let tally_file = report.path().join("tally.txt");
    let peers = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers");
    let log = report.path().join("schemathesis.log");
    let started = Instant::now();
    let mut cmd = std::process::Command::new(&exe);
    cmd.arg("--config-file")
        .arg(peers.join("schemathesis.toml"))
        .arg("--no-color")
        .arg("run")
        .arg(app.url("/openapi.yaml"))
        .args(["--url", &app.base])
        .args(["--checks", "all"])
        .args(["--seed", &SEED.to_string()])
        .args(["--max-examples", &MAX_EXAMPLES.to_string()])
        .args(["--workers", "2"])
        .args(["--request-timeout", "60"])
        .args(["--generation-database", "none"])
        .args(["--header", &format!("Authorization: Bearer {TOKEN}")])
        .env("SCHEMATHESIS_HOOKS", peers.join("schemathesis_hooks.py"))
        .env("CTRECON_CONTRACT_SEED", &seed_file)
        .env("CTRECON_CONTRACT_TALLY", &tally_file)
        .env("NO_COLOR", "1")
        .env("COLUMNS", "160")
        .current_dir(report.path())
        .stdin(std::process::Stdio::null())
        .stdout(std::fs::File::create(&log).expect("log file"))
        .stderr(std::fs::File::create(report.path().join("stderr.log")).expect("log file"));
    let mut child = cmd.spawn().expect("schemathesis starts");
    // The server runs on this runtime: wait for schemathesis off it.
    let status = tokio::task::spawn_blocking(move || {
        loop {
            if let Some(status) = child.try_wait().expect("schemathesis status") {
                return Some(status);
            }
            if started.elapsed() > LIMIT {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    })
    .await
    .expect("waiting for schemathesis");
    let stdout = std::fs::read_to_string(&log).unwrap_or_default();
    let stderr = std::fs::read_to_string(report.path().join("stderr.log")).unwrap_or_default();
    let Some(status) = status else {
        panic!("schemathesis ran past {LIMIT:?}:\n{}", tail(&stdout, 100));
    };
    println!(
        "schemathesis took {:.0} s; its summary:\n{}",
        started.elapsed().as_secs_f64(),
        tail(&stdout, 25)
    );
    assert!(
        status.success(),
        "schemathesis found differences (exit {:?}):\n{}\n{}",
        status.code(),
        tail(&stdout, 400),
        tail(&stderr, 40)
    );
    // "N generated, N passed, M skipped": every test case passed.
    let cases = stdout
        .lines()
        .find(|l| l.contains(" generated, "))
        .unwrap_or_default();
    assert!(
        cases.contains(" passed") && !cases.contains("fail") && !stdout.contains("Runtime Error"),
        "no clean summary:\n{}",
        tail(&stdout, 60)
    );
    // Most operations reached a success: the checks saw real answers, not only 404s.
    let all: BTreeSet<String> = crate::api_errors::operations(include_str!("../openapi.yaml"))
        .into_iter()
        .map(|((method, path), _)| format!("{} {path}", method.to_uppercase()))
        .collect();
    let answered = tally(&tally_file);
    let (reached, not): (Vec<&String>, Vec<&String>) = all.iter().partition(|op| {
        answered
            .get(*op)
            .is_some_and(|(s, _)| s.iter().any(|c| (200..300).contains(c)))
    });
    let share = reached.len() as f64 / all.len() as f64;
    println!(
        "{} of {} operations answered a 2xx ({:.0} %); never: {}",
        reached.len(),
        all.len(),
        100.0 * share,
        not.iter()
            .map(|op| format!(
                "{op} {:?}",
                answered
                    .get(*op)
                    .map(|(s, _)| s.clone())
                    .unwrap_or_default()
            ))
            .collect::<Vec<_>>()
            .join("; ")
    );
    let mut slowest: Vec<(&String, f64)> =
        answered.iter().map(|(op, (_, secs))| (op, *secs)).collect();
    slowest.sort_by(|a, b| b.1.total_cmp(&a.1));
    println!(
        "server time by operation, slowest first: {}",
        slowest
            .iter()
            .take(8)
            .map(|(op, secs)| format!("{op} {secs:.1} s"))
            .collect::<Vec<_>>()
            .join("; ")
    );
    assert!(
        share >= MIN_SUCCESS_SHARE,
        "only {:.0} % of the operations reached a 2xx",
        100.0 * share
    );
}
