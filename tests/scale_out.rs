//! Several ctrecon processes on one job database, and leases that expire: the service end to end on
//! PostgreSQL (two API processes sharing Idempotency-Keys), a job whose worker was lost finished by another
//! after its lease (on SQLite and PostgreSQL, in-process; and on PostgreSQL with `kill -9` of a real
//! `ctrecon serve` process), a job queued on a busy process started at once by an idle one (`NOTIFY`), a
//! cancel posted to one process stopping the job another runs, and a database that cannot be reached
//! refusing the start of either role (`serve`, `worker`).
//!
//! PostgreSQL is a throwaway cluster (`common/postgres.rs`); without it those tests print one skip line,
//! unless `CTRECON_REQUIRE_PEERS=1`.

use crate::cluster;
use crate::common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{TestApp, cone_geometry, parallel_geometry, spawn_app_with};
use ctrecon::app::App;
use ctrecon::config::Settings;
use ctrecon::jobs::model::now_us;
use ctrecon::jobs::{Job, JobStore, Lease, Outcome, StoreError};
use serde_json::{Value, json};

fn fbp_job(input: &str) -> Value {
    json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0},
           "outputs": ["volume", "metrics"]})
}

fn fdk_job(input: &str, n: usize) -> Value {
    json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
           "grid": {"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]},
           "outputs": ["volume", "metrics"]})
}

/// The 2D FBP of the modified Shepp–Logan phantom (180 views) reconstructs it: RMSE 0.027 measured on
/// exact data (`api_jobs`), bound 0.04.
fn assert_fbp_result(done: &Value) {
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["result"]["shape"], json!([1, 64, 64]));
    let rmse = done["result"]["metrics"]["rmse"].as_f64().expect("rmse");
    assert!(rmse < 0.04, "RMSE {rmse}");
}

/// The SHA-256 of a file, hex.
fn sha256_of(path: &Path) -> String {
    use sha2::Digest;
    let bytes = std::fs::read(path).expect("result file");
    sha2::Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A server on `dir` (shared with others) whose settings `configure` adjusts.
async fn node_in(dir: &Path, configure: impl FnOnce(&mut Settings)) -> TestApp {
    spawn_app_with(|s| {
        s.data_dir = dir.to_path_buf();
        configure(s);
    })
    .await
}

/// A job that `app` admits, inserted and claimed by a "worker" that then dies (never sends a heartbeat):
/// returns its id and the lease it held.
async fn claimed_by_a_lost_worker(app: &App, body: Value) -> (ctrecon::storage::JobId, Lease) {
    let (spec, estimate) = app.admit(body).await.expect("admitted");
    for _ in 0..10 {
        let job = Job::queued(spec.clone(), estimate, now_us());
        app.db.insert_job(&job, None).await.expect("inserted");
        let lease = Lease {
            expires_us: now_us() + 1_000_000,
        };
        // An engine polling the queue at this very moment may take it first; then try another.
        match JobStore::claim(&app.db, job.id, lease).await {
            Ok(1) => return (job.id, lease),
            Ok(n) => panic!("first claim counted attempt {n}"),
            Err(StoreError::Illegal(_)) => continue,
            Err(e) => panic!("claim: {e}"),
        }
    }
    panic!("no job could be claimed before an engine took it");
}

/// The lost worker's job is re-queued when its lease expires and finished by the engine, whose result is
/// the only one: the lost worker's late outcome is refused.
async fn a_lost_workers_job_is_finished_by_the_engine_after_its_lease(
    database_url: Option<String>,
) {
    let dir = tempfile::tempdir().expect("temp dir");
    let app = node_in(dir.path(), |s| {
        s.database_url = database_url;
        s.lease_secs = 1;
    })
    .await;
    let handle = app.core.clone().expect("in-process server");
    let input = app.simulate(parallel_geometry(180, 128, 0.5), 28.0).await;
    let started = Instant::now();
    let (id, _) = claimed_by_a_lost_worker(&handle, fbp_job(&input)).await;
    let running = app.job(&id.to_string()).await;
    assert_eq!(
        (running["status"].as_str(), running["attempts"].as_u64()),
        (Some("running"), Some(1))
    );
    let done = app.finish(&id.to_string()).await;
    let waited = started.elapsed();
    assert_fbp_result(&done);
    assert_eq!(done["attempts"], 2, "{done}");
    // Not before the lease (1 s) expired; the expiry runs every third of it.
    assert!(waited >= Duration::from_millis(900), "{waited:?}");
    eprintln!("finished by the engine {waited:?} after the lost worker's claim");

    // The lost worker comes back with an outcome of its own: refused, and nothing changes.
    let job = handle.db.get_job(id).await.ok().flatten().expect("the job");
    let mut bogus = job.result.expect("a result");
    bogus.mean = -1.0;
    assert!(matches!(
        JobStore::finish(&handle.db, id, 1, &Outcome::Succeeded(Box::new(bogus))).await,
        Err(StoreError::Illegal(_))
    ));
    let after = app.job(&id.to_string()).await;
    assert_eq!(after["result"], done["result"]);
    let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
    let file = dir
        .path()
        .join("results")
        .join(id.to_string())
        .join("volume.npy");
    assert_eq!(sha256_of(&file), sha);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sqlite_a_lost_workers_job_is_finished_by_the_engine_after_its_lease() {
    a_lost_workers_job_is_finished_by_the_engine_after_its_lease(None).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_a_lost_workers_job_is_finished_by_the_engine_after_its_lease() {
    let Some(url) = cluster::database_url("postgres_a_lost_workers_job_is_finished") else {
        return;
    };
    a_lost_workers_job_is_finished_by_the_engine_after_its_lease(Some(url)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_runs_the_service_end_to_end_and_two_api_processes_share_idempotency_keys() {
    let Some(url) = cluster::database_url("postgres_runs_the_service_end_to_end") else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let a = node_in(dir.path(), |s| s.database_url = Some(url.clone())).await;
    let b = node_in(dir.path(), |s| s.database_url = Some(url.clone())).await;
    // 120 views of a 96² panel (magnification 1.5) around a phantom of scale 28 mm, as in `api_jobs`.
    let input = a.simulate(cone_geometry(120, 96), 28.0).await;
    let body = fdk_job(&input, 64);
    // The same Idempotency-Key posted to both API processes at once: one job.
    let post = |app: &TestApp| {
        app.client
            .post(app.url("/v1/jobs"))
            .header("idempotency-key", "scan-17")
            .json(&body)
            .send()
    };
    let (ra, rb) = tokio::join!(post(&a), post(&b));
    let (ra, rb) = (ra.expect("request"), rb.expect("request"));
    assert_eq!((ra.status().as_u16(), rb.status().as_u16()), (202, 202));
    let (ja, jb): (Value, Value) = (ra.json().await.unwrap(), rb.json().await.unwrap());
    assert_eq!(ja["id"], jb["id"]);
    let id = ja["id"].as_str().expect("id").to_string();
    let listed: Value = b.get("/v1/jobs").await.json().await.unwrap();
    assert_eq!(listed["jobs"].as_array().map(Vec::len), Some(1), "{listed}");

    // Either process may have run it; both answer with the same result.
    let done = b.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["result"]["shape"], json!([64, 64, 64]));
    assert_eq!(done["attempts"], 1);
    let m: Value = a
        .get(&format!("/v1/jobs/{id}/result/metrics"))
        .await
        .json()
        .await
        .unwrap();
    // FDK of exact data with a Hann window on 1 mm voxels (bounds of `api_jobs`).
    assert!(m["rmse"].as_f64().unwrap() < 0.06, "{m}");
    assert!(m["ssim"].as_f64().unwrap() > 0.75, "{m}");
    let r = a.get(&format!("/v1/jobs/{id}/result/volume.npy")).await;
    assert_eq!(r.status(), 200);
    let (shape, values) = common::read_npy_f32(&r.bytes().await.unwrap());
    assert_eq!(shape, [64, 64, 64]);
    // The centre of the phantom (modified Shepp–Logan: 0.2 inside the brain ellipse, 0.3 at the centre
    // with the overlapping ellipses of 0.1) lies within its value range.
    let centre = values[(32 * 64 + 32) * 64 + 32];
    assert!((0.0..=1.05).contains(&centre), "{centre}");

    // The DICOM node's tables are shared too: a rule created through one API process is listed by the
    // other, and both answer deliveries and DICOMweb searches from the same (still empty) tables.
    let r = a
        .post_json("/v1/rules", &json!({"name": "spine", "protocol": "spine"}))
        .await;
    assert_eq!(r.status(), 201);
    let listed: Value = b.get("/v1/rules").await.json().await.unwrap();
    let rules = listed["rules"].as_array().expect("rules");
    assert_eq!(rules.len(), 1, "{listed}");
    assert_eq!(
        (
            rules[0]["name"].as_str(),
            rules[0]["protocol"].as_str(),
            rules[0]["source"].as_str()
        ),
        (Some("spine"), Some("spine"), Some("api"))
    );
    let again = b
        .post_json("/v1/rules", &json!({"name": "spine", "protocol": "lung"}))
        .await;
    common::assert_problem(again, 409, "rule_exists").await;
    for app in [&a, &b] {
        let r = app.get("/v1/deliveries").await;
        assert_eq!(r.status(), 200);
        let d: Value = r.json().await.unwrap();
        assert_eq!(d, json!({"deliveries": []}));
        let r = app.get("/dicom-web/studies").await;
        assert_eq!(r.status(), 200);
        let found: Value = r.json().await.unwrap();
        assert_eq!(found, json!([]));
    }
}

/// `ctrecon serve` as a child process; killed when dropped.
struct Process {
    child: Child,
    base: String,
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn serve(dir: &Path, url: &str, extra: &[(&str, &str)]) -> Process {
    let mut child = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .arg("serve")
        .env("CTRECON_BIND", "127.0.0.1:0")
        .env("CTRECON_DATA_DIR", dir)
        .env("CTRECON_DATABASE_URL", url)
        .env("CTRECON_WORKER_THREADS", "2")
        .env("CTRECON_MAX_CONCURRENT_JOBS", "1")
        .env("CTRECON_PROGRESS_INTERVAL_MS", "50")
        .envs(extra.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("ctrecon serve starts");
    let stdout = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("the listening line");
    let base = line
        .trim()
        .strip_prefix("ctrecon listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    Process { child, base }
}

/// A client of a child process, with the helpers of `TestApp`.
fn client_of(p: &Process) -> TestApp {
    common::attach(&p.base)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_a_job_of_a_killed_process_is_finished_by_another_after_its_lease() {
    let Some(url) = cluster::database_url("postgres_a_job_of_a_killed_process") else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let lease = [("CTRECON_LEASE_SECS", "1")];
    let a = serve(dir.path(), &url, &lease);
    let api_a = client_of(&a);
    // Large enough to be still running seconds after a second process joined, on an idle machine too.
    let input = api_a.simulate(cone_geometry(360, 128), 40.0).await;
    let job = api_a.submit(&fdk_job(&input, 224)).await;
    let id = job["id"].as_str().expect("id").to_string();
    api_a
        .wait_until(&id, 120, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    // A second process joins; the job is A's while A's lease is renewed.
    let b = serve(dir.path(), &url, &lease);
    let api_b = client_of(&b);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let still = api_b.job(&id).await;
    assert_eq!(
        (still["status"].as_str(), still["attempts"].as_u64()),
        (Some("running"), Some(1)),
        "{still}"
    );
    // A dies in mid-job.
    drop(a);
    let killed = Instant::now();
    let done = api_b.finish(&id).await;
    eprintln!(
        "finished by the other process {:?} after the kill",
        killed.elapsed()
    );
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 2, "{done}");
    let m = &done["result"]["metrics"];
    assert!(m["rmse"].as_f64().unwrap() < 0.06, "{m}");
    // Exactly one result: the volume on disk is the one the job records.
    let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
    let results = dir.path().join("results").join(&id);
    assert_eq!(sha256_of(&results.join("volume.npy")), sha);
    let metrics: Value = api_b
        .get("/metrics")
        .await
        .text()
        .await
        .map(|t| json!(t))
        .unwrap();
    assert!(
        metrics
            .as_str()
            .unwrap_or("")
            .contains("ctrecon_lease_expiries_total"),
        "the expiry is counted"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_an_idle_process_is_woken_at_once_and_a_cancel_posted_to_one_process_stops_the_job_another_runs()
 {
    let Some(url) = cluster::database_url("postgres_a_cancel_posted_to_one_process") else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let a = serve(dir.path(), &url, &[]);
    let api_a = client_of(&a);
    let input = api_a.simulate(cone_geometry(360, 128), 40.0).await;
    let job = api_a.submit(&fdk_job(&input, 192)).await;
    let id = job["id"].as_str().expect("id").to_string();
    api_a
        .wait_until(&id, 120, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    let b = serve(dir.path(), &url, &[]);
    let api_b = client_of(&b);
    // A is busy (one job at a time): a job submitted to A starts at once on idle B, woken by a notification
    // (B's own look at the queue comes only every 2 s).
    tokio::time::sleep(Duration::from_millis(300)).await;
    let small = api_a.submit(&fdk_job(&input, 16)).await;
    let small = small["id"].as_str().expect("id").to_string();
    let small = api_b.finish(&small).await;
    assert_eq!(small["status"], "succeeded", "{small}");
    let waited_us = ctrecon::jobs::model::parse_rfc3339(small["started_at"].as_str().unwrap())
        .zip(ctrecon::jobs::model::parse_rfc3339(
            small["created_at"].as_str().unwrap(),
        ))
        .map(|(s, c)| s - c)
        .expect("timestamps");
    eprintln!(
        "queued on busy A, started on idle B after {} ms",
        waited_us / 1000
    );
    assert!(waited_us < 500_000, "{waited_us} µs");
    let posted = Instant::now();
    let r = api_b
        .post_json(&format!("/v1/jobs/{id}/cancel"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    let done = api_b
        .wait_until(&id, 30, |j| j["status"] == "canceled")
        .await;
    let took = posted.elapsed();
    eprintln!("canceled {took:?} after the cancel was posted to the other process");
    assert!(done["progress"].as_u64().unwrap() < 100);
    // A cancel reaches the running job by notification (the heartbeat, every second, is the fallback);
    // the core checks its flag at least once a second.
    assert!(took < Duration::from_secs(2), "{took:?} {done}");
    assert!(
        !dir.path()
            .join("results")
            .join(&id)
            .join("volume.npy")
            .exists(),
        "a canceled job leaves no result"
    );
}

#[test]
fn an_unreachable_database_stops_the_start_of_either_role_with_a_clear_message() {
    for role in [
        &["serve", "--bind", "127.0.0.1:0"][..],
        &["worker", "--health-bind", "127.0.0.1:0"][..],
    ] {
        let dir = tempfile::tempdir().expect("temp dir");
        let started = Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
            .args(role)
            .env("CTRECON_DATA_DIR", dir.path())
            // Port 9 (discard) on loopback: nothing listens there.
            .env(
                "CTRECON_DATABASE_URL",
                "postgres://ctrecon@127.0.0.1:9/ctrecon",
            )
            .output()
            .expect("ctrecon runs");
        assert!(!out.status.success(), "{role:?}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("database: cannot connect to postgres://ctrecon@127.0.0.1:9/ctrecon"),
            "{role:?}: {stderr}"
        );
        assert!(started.elapsed() < Duration::from_secs(30), "{role:?}");
        assert!(
            String::from_utf8_lossy(&out.stdout).is_empty(),
            "{role:?} never listened"
        );
    }
}
