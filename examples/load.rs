//! Load benchmark of the HTTP API: a real server on loopback with finished jobs in its list and jobs
//! running, and concurrent clients that poll it for a bounded time; reports latency percentiles per route.
//!
//! `cargo run --example load -- [--clients 50] [--secs 10] [--finished 30] [--running 2] [--query Q]`
//!
//! The server runs on its own runtime (as `ctrecon serve` does, default settings but the data directory and
//! port) and the clients on another, in this one process. Each client loops over `GET /v1/jobs` (with `Q` as
//! its query string, none by default), `GET /v1/jobs/{id}` of a running job and `GET /healthz`, reading
//! every body in full. The first second is warm-up and is not counted.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use ctrecon::config::Settings;
use ctrecon::http::Application;
use serde_json::{Value, json};

struct Args {
    clients: usize,
    secs: u64,
    finished: usize,
    running: usize,
    query: String,
}

fn args() -> Args {
    let mut a = Args {
        clients: 50,
        secs: 10,
        finished: 30,
        running: 2,
        query: String::new(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let value = it.next().unwrap_or_default();
        let n = || value.parse::<usize>().unwrap_or(0);
        match flag.as_str() {
            "--clients" => a.clients = n().max(1),
            "--secs" => a.secs = n().max(1) as u64,
            "--finished" => a.finished = n(),
            "--running" => a.running = n(),
            "--query" => a.query = value.clone(),
            other => {
                eprintln!("unknown option {other}");
                std::process::exit(2);
            }
        }
    }
    a
}

/// Start the server on its own runtime; returns its base URL.
fn start_server(dir: &std::path::Path) -> String {
    let settings = Settings {
        bind: "127.0.0.1:0".parse().expect("address"),
        data_dir: dir.to_path_buf(),
        ..Settings::default()
    };
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .thread_name("ctrecon-http")
            .build()
            .expect("server runtime");
        runtime.block_on(async move {
            let app = Application::build(settings)
                .await
                .expect("the service builds");
            let _ = tx.send(format!("http://{}", app.local_addr()));
            let _ = app.run_until(std::future::pending()).await;
        });
    });
    rx.recv().expect("the server starts")
}

async fn post(client: &reqwest::Client, url: String, body: Value) -> Value {
    let r = client.post(url).json(&body).send().await.expect("request");
    let status = r.status();
    let v: Value = r.json().await.expect("json");
    assert!(status.is_success(), "{status}: {v}");
    v
}

async fn status_of(client: &reqwest::Client, base: &str, id: &str) -> Value {
    client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .expect("request")
        .json()
        .await
        .expect("json")
}

/// Finished jobs (small FBPs of a simulated Shepp–Logan, with metrics) and long running ones (SIRT).
async fn populate(client: &reqwest::Client, base: &str, a: &Args) -> Vec<String> {
    let sim = post(
        client,
        format!("{base}/v1/simulations"),
        json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 40},
               "geometry": {"type": "parallel", "angles": {"count": 180}, "det_count": 256,
                            "det_spacing_mm": 0.4}}),
    )
    .await;
    let input = sim["id"].as_str().expect("dataset id").to_string();
    let mut finished = Vec::new();
    for _ in 0..a.finished {
        let j = post(
            client,
            format!("{base}/v1/jobs"),
            json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
                   "grid": {"nx": 64, "ny": 64, "dx_mm": 1.25, "dy_mm": 1.25},
                   "outputs": ["volume", "metrics"]}),
        )
        .await;
        finished.push(j["id"].as_str().expect("id").to_string());
    }
    for id in &finished {
        loop {
            let j = status_of(client, base, id).await;
            if j["status"] == "succeeded" {
                break;
            }
            assert!(j["status"] != "failed", "{j}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    let mut running = Vec::new();
    for _ in 0..a.running {
        let j = post(
            client,
            format!("{base}/v1/jobs"),
            json!({"input": input, "algorithm": {"name": "sirt", "iterations": 100000},
                   "grid": {"nx": 256, "ny": 256, "dx_mm": 0.35, "dy_mm": 0.35}}),
        )
        .await;
        running.push(j["id"].as_str().expect("id").to_string());
    }
    for id in &running {
        while status_of(client, base, id).await["status"] != "running" {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    running
}

#[derive(Default)]
struct Samples {
    micros: Vec<u64>,
    bytes: u64,
    errors: u64,
}

fn percentile(sorted: &[u64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)] as f64 / 1000.0
}

fn main() {
    ctrecon::config::limit_simd_from_env();
    let a = args();
    let dir = tempfile::tempdir().expect("temp dir");
    let base = start_server(dir.path());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("load-client")
        .build()
        .expect("client runtime");
    runtime.block_on(async move {
        let client = reqwest::Client::builder()
            .pool_max_idle_per_host(a.clients)
            .build()
            .expect("client");
        let running = populate(&client, &base, &a).await;
        let poll = running.first().cloned().unwrap_or_default();
        let routes = [
            ("GET /v1/jobs", format!("{base}/v1/jobs{}", a.query)),
            ("GET /v1/jobs/{id}", format!("{base}/v1/jobs/{poll}")),
            ("GET /healthz", format!("{base}/healthz")),
        ];
        let samples: Arc<Vec<Mutex<Samples>>> =
            Arc::new(routes.iter().map(|_| Mutex::default()).collect());
        let start = Instant::now();
        let warm = start + Duration::from_secs(1);
        let end = warm + Duration::from_secs(a.secs);
        let mut tasks = Vec::new();
        for c in 0..a.clients {
            let client = client.clone();
            let urls: Vec<String> = routes.iter().map(|r| r.1.clone()).collect();
            let samples = samples.clone();
            tasks.push(tokio::spawn(async move {
                let mut k = c;
                loop {
                    let t0 = Instant::now();
                    if t0 >= end {
                        return;
                    }
                    let route = k % urls.len();
                    k += 1;
                    let r = client.get(&urls[route]).send().await;
                    let (ok, n) = match r {
                        Ok(r) if r.status().is_success() => match r.bytes().await {
                            Ok(b) => (true, b.len() as u64),
                            Err(_) => (false, 0),
                        },
                        _ => (false, 0),
                    };
                    if t0 >= warm
                        && let Ok(mut s) = samples[route].lock()
                    {
                        if ok {
                            s.micros.push(t0.elapsed().as_micros() as u64);
                            s.bytes += n;
                        } else {
                            s.errors += 1;
                        }
                    }
                }
            }));
        }
        for t in tasks {
            let _ = t.await;
        }
        println!(
            "{} clients, {} s (after 1 s of warm-up), {} finished and {} running jobs listed, query `{}`",
            a.clients, a.secs, a.finished, a.running, a.query
        );
        println!("| route | requests | req/s | p50 ms | p99 ms | max ms | body bytes | errors |");
        println!("|---|---|---|---|---|---|---|---|");
        for (i, (name, _)) in routes.iter().enumerate() {
            let Ok(mut s) = samples[i].lock() else {
                continue;
            };
            s.micros.sort_unstable();
            let n = s.micros.len();
            println!(
                "| `{name}` | {n} | {:.0} | {:.1} | {:.1} | {:.1} | {} | {} |",
                n as f64 / a.secs as f64,
                percentile(&s.micros, 0.5),
                percentile(&s.micros, 0.99),
                percentile(&s.micros, 1.0),
                s.bytes / (n.max(1) as u64),
                s.errors
            );
        }
        for id in &running {
            let j = status_of(&client, &base, id).await;
            if j["status"] != "running" {
                eprintln!("warning: job {id} was no longer running at the end: {}", j["status"]);
            }
        }
    });
}
