//! Job overhead over compute: how long the service takes around a job whose computation is negligible.
//!
//! `cargo run --example overhead -- [--jobs 40] [--postgres]`
//!
//! With `--postgres` the same measurement follows on a PostgreSQL job database in the same run: a
//! throwaway cluster (as the tests make it, `tests/common/postgres.rs`) or the database `CTRECON_DATABASE_URL`
//! names.
//!
//! A real server on loopback (default settings but the data directory and port, on its own runtime) gets a
//! tiny simulated sinogram, then `--jobs` tiny FBP jobs one after the other (8 × 8 pixels from 16 views ×
//! 16 detector cells: microseconds of compute). For each it reports, as medians and 90th percentiles:
//! - `queue→finish`: the job's own `finished_at − created_at` (persist, wake, claim, run, record),
//!   `queue→claim`: `started_at − created_at` (persist, wake, claim) and `run`: `finished_at − started_at`;
//! - `client`: from sending `POST /v1/jobs` to seeing `succeeded` by polling `GET /v1/jobs/{id}` every ms.

use std::time::{Duration, Instant};

use ctrecon::config::Settings;
use ctrecon::http::Application;
use serde_json::{Value, json};

#[path = "../tests/common/postgres.rs"]
mod cluster;

fn start_server(dir: &std::path::Path, database_url: Option<String>) -> String {
    let settings = Settings {
        bind: "127.0.0.1:0".parse().expect("address"),
        data_dir: dir.to_path_buf(),
        database_url,
        ..Settings::default()
    };
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
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

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn micros(job: &Value, field: &str) -> i64 {
    let t = job[field].as_str().expect("timestamp");
    ctrecon::jobs::model::parse_rfc3339(t).expect("RFC 3339")
}

#[tokio::main]
async fn main() {
    let mut jobs = 40usize;
    let mut postgres = false;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        if flag == "--jobs" {
            jobs = args
                .next()
                .and_then(|v| v.parse().ok())
                .unwrap_or(jobs)
                .max(2);
        } else if flag == "--postgres" {
            postgres = true;
        }
    }
    println!("SQLite (the data directory):");
    measure(jobs, None).await;
    if postgres {
        let url = std::env::var("CTRECON_DATABASE_URL")
            .ok()
            .or_else(|| cluster::database_url("overhead"));
        match url {
            Some(url) => {
                println!("PostgreSQL ({}):", url.split('@').next_back().unwrap_or(""));
                measure(jobs, Some(url)).await;
            }
            None => println!("PostgreSQL: not installed"),
        }
    }
}

async fn measure(jobs: usize, database_url: Option<String>) {
    let dir = tempfile::tempdir().expect("temp dir");
    let base = start_server(dir.path(), database_url);
    let client = reqwest::Client::new();
    let sim: Value = client
        .post(format!("{base}/v1/simulations"))
        .json(
            &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 6},
                      "geometry": {"type": "parallel", "angles": {"count": 16}, "det_count": 16,
                                   "det_spacing_mm": 1.0}}),
        )
        .send()
        .await
        .expect("simulation")
        .json()
        .await
        .expect("json");
    let input = sim["id"].as_str().expect("dataset id").to_string();
    let (mut total, mut claim, mut run, mut seen) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for k in 0..jobs + 3 {
        let sent = Instant::now();
        let j: Value = client
            .post(format!("{base}/v1/jobs"))
            .json(&json!({"input": input, "algorithm": {"name": "fbp"},
                          "grid": {"nx": 8, "ny": 8, "dx_mm": 1.5, "dy_mm": 1.5}}))
            .send()
            .await
            .expect("submit")
            .json()
            .await
            .expect("json");
        let id = j["id"].as_str().expect("job id").to_string();
        let done = loop {
            let j: Value = client
                .get(format!("{base}/v1/jobs/{id}"))
                .send()
                .await
                .expect("poll")
                .json()
                .await
                .expect("json");
            if j["status"] == "succeeded" {
                break j;
            }
            assert!(j["status"] != "failed", "{j}");
            tokio::time::sleep(Duration::from_millis(1)).await;
        };
        if k < 3 {
            continue; // warm-up
        }
        seen.push(sent.elapsed().as_secs_f64() * 1e3);
        total.push((micros(&done, "finished_at") - micros(&done, "created_at")) as f64 / 1e3);
        claim.push((micros(&done, "started_at") - micros(&done, "created_at")) as f64 / 1e3);
        run.push((micros(&done, "finished_at") - micros(&done, "started_at")) as f64 / 1e3);
    }
    for (name, v) in [
        ("queue→finish", &mut total),
        ("queue→claim", &mut claim),
        ("run", &mut run),
        ("client", &mut seen),
    ] {
        println!(
            "{name:>13}: median {:7.2} ms, p90 {:7.2} ms over {jobs} jobs",
            percentile(v, 0.5),
            percentile(v, 0.9)
        );
    }
}
