//! Roles as deployed: an API process that runs no jobs (`ctrecon serve --workers 0`) and three `ctrecon
//! worker` processes, each with a data directory of its own, on one PostgreSQL job database and one S3
//! bucket. Thirty jobs of three kinds each succeed exactly once, each result in the bucket once with the
//! recorded SHA-256 and no unfinished object left; a worker killed with SIGKILL in mid-job loses the job to
//! another after its lease, without a second copy of its result; a worker stopped with SIGTERM hands its job
//! back without spending an attempt and exits cleanly. Event streams of every API process follow jobs run
//! elsewhere, and bad role configurations stop the start with the reason.
//!
//! PostgreSQL is a throwaway cluster (`common/postgres.rs`) and the S3 server s3s-fs (`common/s3.rs`);
//! without them a test prints one skip line, unless `CTRECON_REQUIRE_PEERS=1`.

use crate::cluster;
use crate::common;
use crate::roles;
use crate::s3;
use crate::sse;

use std::time::Instant;

use common::{TestApp, cone_geometry, parallel_geometry};
use roles::{Process, api, fbp, fdk, on, runner, sha256_of, sirt, worker};
use serde_json::json;
use sse::Sse;

/// The workers still alive.
fn live(ws: &[Option<Process>]) -> Vec<usize> {
    (0..ws.len()).filter(|&i| ws[i].is_some()).collect()
}

/// The index (in `ws`) of the live worker that runs a job now.
async fn busy_worker(ws: &[Option<Process>]) -> usize {
    let alive = live(ws);
    let refs: Vec<&Process> = alive.iter().filter_map(|&i| ws[i].as_ref()).collect();
    alive[runner(&refs, 30).await]
}

/// Submit a SIRT job long enough to be interrupted and wait until it runs with some progress.
async fn interruptible(client: &TestApp, input: &str) -> String {
    let job = client.submit(&sirt(input, 1500)).await;
    let id = job["id"].as_str().expect("id").to_string();
    client
        .wait_until(&id, 120, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    id
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_an_api_process_and_three_workers_with_their_own_directories_run_every_job_exactly_once()
{
    let test = "s3_api_and_three_workers";
    let Some(url) = cluster::database_url(test) else {
        return;
    };
    let Some(s3) = s3::s3(test) else {
        return;
    };
    let dirs: Vec<tempfile::TempDir> = (0..4).map(|_| tempfile::tempdir().expect("dir")).collect();
    let a = api(s3.serve_to(on(dirs[0].path(), &url)));
    let client: TestApp = common::attach(&a.base);
    let workers: Vec<Process> = dirs[1..]
        .iter()
        .map(|d| worker(s3.serve_to(on(d.path(), &url)), "127.0.0.1"))
        .collect();
    for w in &workers {
        let r = common::attach(&w.base).get("/healthz").await;
        assert_eq!(r.status(), 200, "a worker's health port answers");
        let r = common::attach(&w.base).get("/v1/jobs").await;
        assert_eq!(r.status(), 404, "a worker serves no API");
        let r = common::attach(&w.base).get("/readyz").await;
        assert_eq!(r.status(), 200);
        let ready: serde_json::Value = r.json().await.expect("json");
        assert_eq!(ready["object_storage"], "ok", "{ready}");
    }

    // Thirty jobs of three kinds.
    let flat = client.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let cone = client.simulate(cone_geometry(90, 48), 20.0).await;
    let mut ids = Vec::new();
    for k in 0..30 {
        let body = match k % 3 {
            0 => fbp(&flat),
            1 => sirt(&flat, 5),
            _ => fdk(&cone, 32),
        };
        let job = client.submit(&body).await;
        ids.push(job["id"].as_str().expect("id").to_string());
    }
    for id in &ids {
        let done = client.finish(id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert_eq!(done["attempts"], 1, "{done}");
        // The result is in the bucket once, whole: the object's bytes are those the job recorded.
        let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
        assert_eq!(
            sha256_of(&s3.object_file(&format!("results/{id}/volume.npy"))),
            sha
        );
        assert_eq!(
            s3.objects_under(&format!("results/{id}")),
            ["metrics.json", "volume.npy"]
        );
    }
    // Exactly once: the workers' own counts add up to the thirty, and the API process ran none.
    let mut per_worker = Vec::new();
    for w in &workers {
        per_worker.push(
            w.metric("ctrecon_jobs_finished_total", "status=\"succeeded\"")
                .await,
        );
    }
    eprintln!("jobs per worker: {per_worker:?}");
    assert_eq!(per_worker.iter().sum::<f64>(), 30.0, "{per_worker:?}");
    assert!(per_worker.iter().all(|&n| n >= 1.0), "{per_worker:?}");
    assert_eq!(a.metric("ctrecon_jobs_finished_total", "").await, 0.0);
    // The API host never held a result: every one is served from the bucket.
    assert!(s3::files_under(&dirs[0].path().join("results")).is_empty());
    // Thirty results and the two datasets, nothing else and nothing unfinished.
    assert_eq!(s3.objects_under("results").len(), 60);
    assert_eq!(s3.objects_under("datasets").len(), 2);
    assert_eq!(s3.unfinished(), Vec::<String>::new());

    // SIGKILL in mid-job: another worker finishes it after the lease (1 s), as attempt 2, and the bucket
    // holds one copy of its result.
    let mut workers: Vec<Option<Process>> = workers.into_iter().map(Some).collect();
    let id = interruptible(&client, &flat).await;
    let idx = busy_worker(&workers).await;
    workers[idx].as_ref().expect("live").signal("KILL");
    workers[idx] = None;
    let killed = Instant::now();
    let done = client.finish(&id).await;
    eprintln!(
        "finished by another worker {:?} after the kill",
        killed.elapsed()
    );
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 2, "{done}");
    assert!(
        done["result"]["metrics"]["rmse"].as_f64().expect("rmse") < 0.1,
        "{done}"
    );
    let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
    assert_eq!(
        sha256_of(&s3.object_file(&format!("results/{id}/volume.npy"))),
        sha
    );
    assert_eq!(
        s3.objects_under(&format!("results/{id}")),
        ["metrics.json", "volume.npy"]
    );
    assert_eq!(s3.unfinished(), Vec::<String>::new());
    let mut expiries = a.metric("ctrecon_lease_expiries_total", "").await;
    for i in live(&workers) {
        if let Some(w) = &workers[i] {
            expiries += w.metric("ctrecon_lease_expiries_total", "").await;
        }
    }
    assert!(expiries >= 1.0, "{expiries}");

    // SIGTERM in mid-job: the worker hands the job back (no attempt spent) and exits 0; the last one runs it.
    let id = interruptible(&client, &flat).await;
    let idx = busy_worker(&workers).await;
    let mut stopped = workers[idx].take().expect("live");
    stopped.signal("TERM");
    let status = stopped.exit_within(20).await;
    assert!(status.success(), "a drained worker exits 0: {status:?}");
    let done = client.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1, "a hand-back spends no attempt: {done}");
    assert_eq!(
        s3.objects_under(&format!("results/{id}")),
        ["metrics.json", "volume.npy"]
    );
    assert_eq!(s3.unfinished(), Vec::<String>::new());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_event_streams_of_every_api_process_follow_the_jobs_a_worker_runs() {
    let Some(url) = cluster::database_url("postgres_event_streams") else {
        return;
    };
    // Two API processes that run nothing and one worker on one data directory: every event of the job
    // comes from elsewhere.
    let dir = tempfile::tempdir().expect("temp dir");
    let (a, b) = (api(on(dir.path(), &url)), api(on(dir.path(), &url)));
    let _w = worker(on(dir.path(), &url), "127.0.0.1");
    let (ca, cb) = (common::attach(&a.base), common::attach(&b.base));
    let mut feed = Sse::open(&ca.client, &ca.url("/v1/events"), None).await;
    assert_eq!(feed.next(10).await.name, "ready");

    // A job submitted through B, long enough to report progress on the way.
    let flat = cb.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let job = cb
        .submit(
            &json!({"input": flat, "algorithm": {"name": "sirt", "iterations": 200},
                        "grid": {"nx": 96, "ny": 96, "dx_mm": 1.0, "dy_mm": 1.0},
                        "outputs": ["volume"]}),
        )
        .await;
    let id = job["id"].as_str().expect("id").to_string();

    // A's stream of the job: running with progress and residuals, then the final job as stored.
    let mut one = Sse::open(&ca.client, &ca.url(&format!("/v1/jobs/{id}/events")), None).await;
    let seen = one.until(120, |e| e.name == "final").await;
    let running: Vec<&sse::Ev> = seen
        .iter()
        .filter(|e| e.name == "progress" && e.data["status"] == "running")
        .collect();
    assert!(
        running.len() >= 3,
        "progress of a job run elsewhere reaches A's stream: {seen:?}"
    );
    assert!(
        running
            .iter()
            .any(|e| e.data["progress"].as_u64() > Some(0))
    );
    assert!(
        running
            .iter()
            .any(|e| e.data["residual"].as_f64().is_some()),
        "residuals travel too: {seen:?}"
    );
    let last = seen.last().expect("final");
    assert_eq!(last.data["status"], "succeeded", "{last:?}");
    assert_eq!(last.data["id"], id.as_str());

    // A's list feed: B's submission, the worker's start and finish. Notifications of different processes
    // are not ordered (the worker may claim the job before B's announcement of it reaches A), but the feed
    // never sends a job back: the statuses it shows of the job, the submission's included, only move on.
    let names: Vec<(String, String)> = feed
        .until(30, |e| {
            e.name == "status" && e.data["status"] == "succeeded" && e.data["id"] == id.as_str()
        })
        .await
        .into_iter()
        .filter(|e| e.data["id"] == id.as_str())
        .map(|e| {
            (
                e.name,
                e.data["status"].as_str().unwrap_or_default().to_string(),
            )
        })
        .collect();
    let rank = |s: &str| match s {
        "queued" => 0,
        "running" => 1,
        "succeeded" => 2,
        other => panic!("unexpected status {other} in {names:?}"),
    };
    assert!(
        names.iter().any(|(n, _)| n == "created"),
        "B's submission reaches A's feed: {names:?}"
    );
    assert!(
        names.windows(2).all(|w| rank(&w[0].1) <= rank(&w[1].1)),
        "a status went back: {names:?}"
    );
    let starts = names
        .iter()
        .filter(|(n, s)| n == "status" && s == "running")
        .count();
    assert!(starts <= 1, "the start is told once: {names:?}");
    assert_eq!(
        names.last().map(|(n, s)| (n.as_str(), s.as_str())),
        Some(("status", "succeeded")),
        "{names:?}"
    );

    // Deleted through B: A's feed says so.
    let r = cb
        .client
        .delete(cb.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    let gone = feed.until(30, |e| e.name == "deleted").await;
    assert_eq!(gone.last().expect("deleted").data["id"], id.as_str());
}

#[test]
fn roles_that_cannot_work_stop_the_start_with_the_reason() {
    let dir = tempfile::tempdir().expect("temp dir");
    let run = |args: &[&str]| {
        let out = roles::ctrecon()
            .args(args)
            .env("CTRECON_DATA_DIR", dir.path())
            .output()
            .expect("ctrecon runs");
        assert!(!out.status.success(), "{args:?} must not start");
        assert!(out.stdout.is_empty(), "{args:?} never listened");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = run(&["worker", "--health-bind", "127.0.0.1:0"]);
    assert!(
        e.contains("ctrecon worker needs a shared job database"),
        "{e}"
    );
    let e = run(&["serve", "--bind", "127.0.0.1:0", "--workers", "0"]);
    assert!(
        e.contains("max_concurrent_jobs") && e.contains("shared job database"),
        "{e}"
    );
}
