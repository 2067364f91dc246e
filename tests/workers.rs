//! Roles on one PostgreSQL job database: an API process that runs no jobs (`ctrecon serve --workers 0`) and
//! three `ctrecon worker` processes sharing its data directory. Thirty jobs of three kinds each succeed
//! exactly once; a worker killed with SIGKILL in mid-job loses the job to another after its lease; a worker
//! stopped with SIGTERM hands its job back without spending an attempt and exits cleanly. Bad role
//! configurations stop the start with the reason.
//!
//! PostgreSQL is a throwaway cluster (`common/postgres.rs`); without it the PostgreSQL tests print one skip
//! line, unless `CTRECON_REQUIRE_PEERS=1`.

#[path = "common/postgres.rs"]
mod cluster;
mod common;
#[path = "common/sse.rs"]
mod sse;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{TestApp, cone_geometry, parallel_geometry};
use serde_json::{Value, json};
use sse::Sse;

/// A `ctrecon` child process (`serve` or `worker`); killed when dropped.
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

impl Process {
    fn signal(&self, name: &str) {
        let ok = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .expect("kill runs")
            .success();
        assert!(ok, "kill -{name}");
    }
}

/// Start `ctrecon ARGS` on the shared directory and database; returns once it printed `ready_prefix` and
/// the address after it.
fn start(dir: &Path, url: &str, args: &[&str], ready_prefix: &str) -> Process {
    let mut child = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .args(args)
        .env("CTRECON_DATA_DIR", dir)
        .env("CTRECON_DATABASE_URL", url)
        .env("CTRECON_LEASE_SECS", "1")
        .env("CTRECON_PROGRESS_INTERVAL_MS", "50")
        .env("CTRECON_DRAIN_TIMEOUT_MS", "2000")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("ctrecon starts");
    let stdout = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("the first line");
    let base = line
        .trim()
        .strip_prefix(ready_prefix)
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    Process { child, base }
}

fn api(dir: &Path, url: &str) -> Process {
    start(
        dir,
        url,
        &["serve", "--bind", "127.0.0.1:0", "--workers", "0"],
        "ctrecon listening on ",
    )
}

fn worker(dir: &Path, url: &str) -> Process {
    start(
        dir,
        url,
        &[
            "worker",
            "--health-bind",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--threads",
            "1",
        ],
        "ctrecon worker health on ",
    )
}

/// The value of an unlabelled metric, or the sum over the series of a labelled one matching `labels`.
async fn metric(p: &Process, name: &str, labels: &str) -> f64 {
    let text = common::attach(&p.base)
        .get("/metrics")
        .await
        .text()
        .await
        .expect("metrics");
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (key, value) = l.rsplit_once(' ')?;
            let matches =
                key == name || (key.starts_with(&format!("{name}{{")) && key.contains(labels));
            matches.then(|| value.parse::<f64>().ok()).flatten()
        })
        .sum()
}

/// The worker running a job now (by its `ctrecon_jobs_running_here`), waiting up to `secs`.
async fn runner(workers: &[&Process], secs: u64) -> usize {
    let until = Instant::now() + Duration::from_secs(secs);
    loop {
        let mut busy = Vec::new();
        for (i, w) in workers.iter().enumerate() {
            if metric(w, "ctrecon_jobs_running_here", "").await >= 1.0 {
                busy.push(i);
            }
        }
        if let [one] = busy[..] {
            return one;
        }
        assert!(
            Instant::now() < until,
            "no single worker runs the job: {busy:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn sha256_of(path: &Path) -> String {
    use sha2::Digest;
    let bytes = std::fs::read(path).expect("result file");
    sha2::Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn fbp(input: &str) -> Value {
    json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}, "outputs": ["volume", "metrics"]})
}

fn sirt(input: &str) -> Value {
    json!({"input": input, "algorithm": {"name": "sirt", "iterations": 5},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}, "outputs": ["volume", "metrics"]})
}

fn fdk(input: &str, n: usize) -> Value {
    json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
           "grid": {"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]},
           "outputs": ["volume", "metrics"]})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_an_api_process_and_three_workers_run_every_job_exactly_once_through_kills_and_drains()
 {
    let Some(url) = cluster::database_url("postgres_api_and_three_workers") else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let a = api(dir.path(), &url);
    let client: TestApp = common::attach(&a.base);
    let workers: Vec<Process> = (0..3).map(|_| worker(dir.path(), &url)).collect();
    for w in &workers {
        let r = common::attach(&w.base).get("/healthz").await;
        assert_eq!(r.status(), 200, "a worker's health port answers");
        let r = common::attach(&w.base).get("/v1/jobs").await;
        assert_eq!(r.status(), 404, "a worker serves no API");
    }

    // Thirty jobs of three kinds.
    let flat = client.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let cone = client.simulate(cone_geometry(90, 48), 20.0).await;
    let mut ids = Vec::new();
    for k in 0..30 {
        let body = match k % 3 {
            0 => fbp(&flat),
            1 => sirt(&flat),
            _ => fdk(&cone, 32),
        };
        let job = client.submit(&body).await;
        ids.push(job["id"].as_str().expect("id").to_string());
    }
    for id in &ids {
        let done = client.finish(id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert_eq!(done["attempts"], 1, "{done}");
        let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
        let file = dir.path().join("results").join(id).join("volume.npy");
        assert_eq!(sha256_of(&file), sha);
    }
    // Exactly once: the workers' own counts add up to the thirty, and the API process ran none.
    let mut per_worker = Vec::new();
    for w in &workers {
        per_worker.push(metric(w, "ctrecon_jobs_finished_total", "status=\"succeeded\"").await);
    }
    eprintln!("jobs per worker: {per_worker:?}");
    assert_eq!(per_worker.iter().sum::<f64>(), 30.0, "{per_worker:?}");
    assert!(per_worker.iter().all(|&n| n >= 1.0), "{per_worker:?}");
    assert_eq!(metric(&a, "ctrecon_jobs_finished_total", "").await, 0.0);

    // SIGKILL in mid-job: another worker finishes it after the lease (1 s), as attempt 2.
    let big = client.simulate(cone_geometry(360, 128), 40.0).await;
    let job = client.submit(&fdk(&big, 192)).await;
    let id = job["id"].as_str().expect("id").to_string();
    client
        .wait_until(&id, 120, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    let mut workers: Vec<Option<Process>> = workers.into_iter().map(Some).collect();
    let live = |ws: &[Option<Process>]| -> Vec<usize> {
        (0..ws.len()).filter(|&i| ws[i].is_some()).collect()
    };
    let idx = {
        let alive = live(&workers);
        let refs: Vec<&Process> = alive
            .iter()
            .map(|&i| workers[i].as_ref().expect("live"))
            .collect();
        alive[runner(&refs, 30).await]
    };
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
        done["result"]["metrics"]["rmse"].as_f64().expect("rmse") < 0.06,
        "{done}"
    );
    let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
    let file = dir.path().join("results").join(&id).join("volume.npy");
    assert_eq!(sha256_of(&file), sha);
    assert!(
        metric(&a, "ctrecon_lease_expiries_total", "").await + {
            let mut n = 0.0;
            for i in live(&workers) {
                n += metric(
                    workers[i].as_ref().expect("live"),
                    "ctrecon_lease_expiries_total",
                    "",
                )
                .await;
            }
            n
        } >= 1.0
    );

    // SIGTERM in mid-job: the worker hands the job back (no attempt spent) and exits 0; the last one runs it.
    let job = client.submit(&fdk(&big, 192)).await;
    let id = job["id"].as_str().expect("id").to_string();
    client
        .wait_until(&id, 120, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    let idx = {
        let alive = live(&workers);
        let refs: Vec<&Process> = alive
            .iter()
            .map(|&i| workers[i].as_ref().expect("live"))
            .collect();
        alive[runner(&refs, 30).await]
    };
    let mut stopped = workers[idx].take().expect("live");
    stopped.signal("TERM");
    let t = Instant::now();
    let status = loop {
        if let Some(s) = stopped.child.try_wait().expect("wait") {
            break s;
        }
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the worker drains within its drain timeout"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(status.success(), "a drained worker exits 0: {status:?}");
    let done = client.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1, "a hand-back spends no attempt: {done}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_event_streams_of_every_api_process_follow_the_jobs_a_worker_runs() {
    let Some(url) = cluster::database_url("postgres_event_streams") else {
        return;
    };
    let dir = tempfile::tempdir().expect("temp dir");
    // Two API processes that run nothing and one worker: every event of the job comes from elsewhere.
    let (a, b) = (api(dir.path(), &url), api(dir.path(), &url));
    let _w = worker(dir.path(), &url);
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

    // A's list feed: B's submission, the worker's start and finish, in that order.
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
    let at = |what: (&str, &str)| {
        names
            .iter()
            .position(|(n, s)| (n.as_str(), s.as_str()) == what)
            .unwrap_or_else(|| panic!("no {what:?} in {names:?}"))
    };
    assert!(
        at(("created", "queued")) < at(("status", "running")),
        "{names:?}"
    );
    assert!(
        at(("status", "running")) < at(("status", "succeeded")),
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
        let out = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
            .args(args)
            .env("CTRECON_DATA_DIR", dir.path())
            .env_remove("CTRECON_DATABASE_URL")
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
