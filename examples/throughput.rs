//! Throughput of 1, 2 and 4 workers on CPU-bound jobs, on one PostgreSQL job database.
//!
//! `cargo run --example throughput -- [--jobs 12] [--rounds 2] [--iterations 30] [--workers 1,2,4]`
//!
//! For each worker count N of `--workers` (1, 2 and 4 unless given; repeated `--rounds` times, interleaved, so that a change of the
//! machine's load touches every count alike): a fresh database on a throwaway cluster (as the tests make it,
//! `tests/common/postgres.rs`), an API that runs no jobs and N
//! workers as `ctrecon worker --workers 1 --threads 1` runs them (`Role::Worker`, one job at a time on a
//! pool of one thread), all in this process on one data directory. `--jobs` identical SIRT jobs (128 × 128
//! pixels from 180 views, `--iterations` iterations: CPU-bound, little I/O) are queued at once; the rate is
//! jobs over the time from the first job's creation to the last one's finish, and the median run time per
//! job shows how much the workers slow each other down.
//!
//! On a machine with C idle cores the expected rate of N workers is about min(N, C) times that of one. A
//! machine shared with other work gives fewer: before each service run, N threads of a plain CPU-bound loop
//! (no service, no I/O) measure how much faster N things run at once than one at that moment, and the
//! service's ratio is reported beside it (`machine`), so that what the service loses by itself shows apart
//! from what the machine's load takes.

use std::time::Duration;

use ctrecon::config::Settings;
use ctrecon::http::{Application, Role};
use serde_json::{Value, json};

#[path = "../tests/common/postgres.rs"]
mod cluster;

/// A ctrecon process of this example: its address, and the sender that stops it (gracefully) when dropped.
struct Node {
    base: String,
    _stop: tokio::sync::oneshot::Sender<()>,
}

/// Start a ctrecon process of `role` on its own runtime thread.
fn start(dir: &std::path::Path, url: &str, role: Role, jobs_at_once: usize) -> Node {
    let settings = Settings {
        bind: "127.0.0.1:0".parse().expect("address"),
        data_dir: dir.to_path_buf(),
        database_url: Some(url.to_string()),
        max_concurrent_jobs: jobs_at_once,
        worker_threads: 1,
        ..Settings::default()
    };
    let (tx, rx) = std::sync::mpsc::channel();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("runtime");
        runtime.block_on(async move {
            let app = Application::build_as(settings, role)
                .await
                .expect("the service builds");
            let _ = tx.send(format!("http://{}", app.local_addr()));
            let _ = app
                .run_until(async move {
                    let _ = stopped.await;
                })
                .await;
        });
    });
    Node {
        base: rx.recv().expect("the process starts"),
        _stop: stop,
    }
}

fn micros(job: &Value, field: &str) -> i64 {
    let t = job[field].as_str().expect("timestamp");
    ctrecon::jobs::model::parse_rfc3339(t).expect("RFC 3339")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn flag(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The worker counts of `--workers` (a comma-separated list), 1, 2 and 4 unless given.
fn worker_counts() -> Vec<usize> {
    let args: Vec<String> = std::env::args().collect();
    let counts: Vec<usize> = args
        .iter()
        .position(|a| a == "--workers")
        .and_then(|i| args.get(i + 1))
        .map(|v| {
            v.split(',')
                .filter_map(|n| n.trim().parse().ok())
                .filter(|&n| n > 0)
                .collect()
        })
        .unwrap_or_default();
    if counts.is_empty() {
        vec![1, 2, 4]
    } else {
        counts
    }
}

#[tokio::main]
async fn main() {
    let jobs = flag("--jobs", 12).max(1);
    let rounds = flag("--rounds", 2).max(1);
    let iterations = flag("--iterations", 30).max(1);
    let counts = worker_counts();
    println!(
        "cores: {}, jobs per run: {jobs}, SIRT iterations: {iterations}",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    for round in 0..rounds {
        let (mut one, mut spin_one) = (0.0, 0.0);
        for (k, &workers) in counts.iter().enumerate() {
            let spin = tokio::task::spawn_blocking(move || spin_rate(workers))
                .await
                .expect("spin");
            let (rate, run_s) = measure(workers, jobs, iterations).await;
            if k == 0 {
                // The ratios are against the first count (one worker unless `--workers` says otherwise).
                (one, spin_one) = (rate, spin);
            }
            println!(
                "round {round}: {workers} worker(s): {rate:6.3} jobs/s = {:.2} × {} worker(s) \
                 (machine: {:.2} × {} thread(s)), median run {run_s:.2} s",
                rate / one,
                counts[0],
                spin / spin_one,
                counts[0]
            );
        }
    }
}

/// Rounds per second of `threads` threads each running a CPU-bound loop for 3 s (no allocation, no I/O):
/// what the machine gives to that many things at once right now.
fn spin_rate(threads: usize) -> f64 {
    let seconds = 3.0;
    let handles: Vec<_> = (0..threads)
        .map(|t| {
            std::thread::spawn(move || {
                let mut v: Vec<f32> = (0..16_384).map(|i| (i + t) as f32 * 1e-4).collect();
                let start = std::time::Instant::now();
                let mut rounds = 0u64;
                while start.elapsed().as_secs_f64() < seconds {
                    for x in v.iter_mut() {
                        *x = (*x * 1.000_1 + 0.5).sin();
                    }
                    rounds += 1;
                }
                std::hint::black_box(&v);
                rounds
            })
        })
        .collect();
    let rounds: u64 = handles.into_iter().map(|h| h.join().unwrap_or(0)).sum();
    rounds as f64 / seconds
}

/// Jobs per second of `workers` workers, and the median run time of a job (s).
async fn measure(workers: usize, jobs: usize, iterations: usize) -> (f64, f64) {
    let url = cluster::database_url("throughput")
        .expect("PostgreSQL is not installed (scripts/install-peers.sh postgres)");
    let dir = tempfile::tempdir().expect("temp dir");
    let api = start(dir.path(), &url, Role::Api, 0);
    let base = api.base.clone();
    // Stopped (drained) when this measurement ends.
    let _workers: Vec<Node> = (0..workers)
        .map(|_| start(dir.path(), &url, Role::Worker, 1))
        .collect();
    let client = reqwest::Client::new();
    let sim: Value = client
        .post(format!("{base}/v1/simulations"))
        .json(
            &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 56},
                      "geometry": {"type": "parallel", "angles": {"count": 180}, "det_count": 192,
                                   "det_spacing_mm": 1.0}}),
        )
        .send()
        .await
        .expect("simulation")
        .json()
        .await
        .expect("json");
    let input = sim["id"].as_str().expect("dataset id").to_string();
    let mut ids = Vec::new();
    for _ in 0..jobs {
        let j: Value = client
            .post(format!("{base}/v1/jobs"))
            .json(
                &json!({"input": input, "algorithm": {"name": "sirt", "iterations": iterations},
                        "grid": {"nx": 128, "ny": 128, "dx_mm": 1.0, "dy_mm": 1.0}}),
            )
            .send()
            .await
            .expect("submit")
            .json()
            .await
            .expect("json");
        ids.push(j["id"].as_str().expect("job id").to_string());
    }
    let mut done = Vec::new();
    for id in &ids {
        loop {
            let j: Value = client
                .get(format!("{base}/v1/jobs/{id}"))
                .send()
                .await
                .expect("poll")
                .json()
                .await
                .expect("json");
            if j["status"] == "succeeded" {
                done.push(j);
                break;
            }
            assert!(j["status"] != "failed", "{j}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    let first = done
        .iter()
        .map(|j| micros(j, "created_at"))
        .min()
        .unwrap_or(0);
    let last = done
        .iter()
        .map(|j| micros(j, "finished_at"))
        .max()
        .unwrap_or(0);
    let runs = done
        .iter()
        .map(|j| (micros(j, "finished_at") - micros(j, "started_at")) as f64 / 1e6)
        .collect();
    (jobs as f64 / ((last - first) as f64 / 1e6), median(runs))
}
