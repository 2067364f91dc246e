//! Crash recovery: the server process is killed (SIGKILL) while a job runs, restarted on the same data
//! directory, and the job completes; no job or dataset is lost and no partial result is ever served.

use crate::common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{assert_problem, cone_geometry, read_npy_f32};
use serde_json::{Value, json};

/// Start `ctrecon serve` on a free port over `dir`; returns the child and its base URL.
fn start(dir: &std::path::Path) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(["serve", "--bind", "127.0.0.1:0", "--workers", "2"])
        .arg("--data-dir")
        .arg(dir)
        .env("CTRECON_PROGRESS_INTERVAL_MS", "50")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("the binary starts");
    let stdout = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("the listening line");
    let url = line
        .trim()
        .strip_prefix("ctrecon listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    (child, url)
}

async fn job(client: &reqwest::Client, base: &str, id: &str) -> Value {
    client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_killed_with_the_server_is_requeued_and_completes_after_restart() {
    let dir = tempfile::tempdir().unwrap();
    let client = reqwest::Client::new();
    let (mut server, base) = start(dir.path());

    let sim = json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 40},
                     "geometry": cone_geometry(360, 128)});
    let r = client
        .post(format!("{base}/v1/simulations"))
        .json(&sim)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let dataset: Value = r.json().await.unwrap();
    let input = dataset["id"].as_str().unwrap();
    let spec = json!({"input": input, "algorithm": {"name": "fdk"},
                      "grid": {"nx": 160, "ny": 160, "nz": 160, "spacing_mm": [0.5, 0.5, 0.5]}});
    let r = client
        .post(format!("{base}/v1/jobs"))
        .json(&spec)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    // Kill the server while the job runs (its progress has been persisted at least once).
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let j = job(&client, &base, &id).await;
        if j["status"] == "running" && j["progress"].as_u64() > Some(5) {
            break;
        }
        assert_ne!(
            j["status"], "succeeded",
            "the job finished before the kill: make it slower"
        );
        assert!(Instant::now() < deadline, "{j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    server.kill().expect("SIGKILL");
    server.wait().expect("reaped");

    let (mut server, base) = start(dir.path());
    // The job is back (queued or running again); its dataset is intact; no result is served meanwhile.
    let j = job(&client, &base, &id).await;
    assert!(
        matches!(
            j["status"].as_str(),
            Some("queued" | "running" | "succeeded")
        ),
        "{j}"
    );
    let d: Value = client
        .get(format!("{base}/v1/datasets/{input}"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(d["sha256"], dataset["sha256"]);
    if j["status"] != "succeeded" {
        let r = client
            .get(format!("{base}/v1/jobs/{id}/result/volume.npy"))
            .send()
            .await
            .unwrap();
        assert_problem(r, 409, "job_not_succeeded").await;
    }
    let deadline = Instant::now() + Duration::from_secs(600);
    let done = loop {
        let j = job(&client, &base, &id).await;
        if matches!(
            j["status"].as_str(),
            Some("succeeded" | "failed" | "canceled")
        ) {
            break j;
        }
        assert!(Instant::now() < deadline, "{j}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 2);
    let vol = client
        .get(format!("{base}/v1/jobs/{id}/result/volume.npy"))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (shape, _) = read_npy_f32(&vol);
    assert_eq!(shape, [160, 160, 160]);
    assert_eq!(
        vol.len() as u64,
        done["result"]["volume"]["bytes"].as_u64().unwrap()
    );
    let list: Value = client
        .get(format!("{base}/v1/jobs"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["jobs"].as_array().unwrap().len(), 1);
    server.kill().ok();
    server.wait().ok();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_interrupted_too_often_fails_with_a_clear_reason() {
    let dir = tempfile::tempdir().unwrap();
    // A job that a previous process left running after its one allowed start.
    {
        let db = ctrecon::jobs::Db::open(&dir.path().join("ctrecon.sqlite"))
            .await
            .unwrap();
        let request: ctrecon::jobs::JobRequest = serde_json::from_value(json!({
            "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "algorithm": {"name": "fbp"},
            "grid": {"nx": 8, "ny": 8, "dx_mm": 1, "dy_mm": 1}}))
        .unwrap();
        let id = ctrecon::storage::JobId::generate();
        let job = ctrecon::jobs::Job {
            id,
            kind: "reconstruction".into(),
            status: ctrecon::jobs::JobStatus::Queued,
            progress: 0,
            stage: "queued".into(),
            request: ctrecon::jobs::JobSpec::Reconstruction(request),
            estimate_bytes: 1,
            attempts: 0,
            cancel_requested: false,
            error: None,
            result: None,
            created_us: ctrecon::jobs::model::now_us(),
            started_us: None,
            finished_us: None,
        };
        db.insert_job(&job, None).await.unwrap();
        assert!(db.claim(id).await.unwrap());
        // A partial result file a killed run might leave behind.
        std::fs::create_dir_all(dir.path().join("results").join(id.to_string())).unwrap();
        std::fs::write(
            dir.path()
                .join("results")
                .join(id.to_string())
                .join("volume.npy"),
            b"partial",
        )
        .unwrap();
    }
    let app = common::spawn_app_with(|s| {
        s.data_dir = dir.path().to_path_buf();
        s.max_attempts = 1;
    })
    .await;
    let list: Value = app
        .get("/v1/jobs?expand=attempts,error")
        .await
        .json()
        .await
        .unwrap();
    let j = &list["jobs"][0];
    assert_eq!(j["status"], "failed", "{j}");
    assert_eq!(j["error"]["code"], "attempts_exhausted");
    assert_eq!(j["attempts"], 1);
    let id = j["id"].as_str().unwrap();
    assert!(!dir.path().join("results").join(id).exists());
}
