//! The service's life cycle: shutdown drains open connections for a bounded time, jobs stopped by a graceful
//! shutdown go back to the queue without spending an attempt, and retention removes what has aged out.

use crate::common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::{cone_geometry, parallel_geometry, test_settings};
use ctrecon::config::Settings;
use ctrecon::http::Application;
use ctrecon::jobs::{Db, JobStatus};
use ctrecon::storage::JobId;
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// A real server over `dir` whose shutdown the test triggers and awaits.
struct Server {
    base: String,
    addr: SocketAddr,
    client: reqwest::Client,
    stop: Option<oneshot::Sender<()>>,
    served: Option<JoinHandle<std::io::Result<()>>>,
}

impl Server {
    async fn start(dir: &std::path::Path, configure: impl FnOnce(&mut Settings)) -> Self {
        let mut settings = test_settings(dir);
        configure(&mut settings);
        let app = Application::build(settings)
            .await
            .expect("the service builds");
        let addr = app.local_addr();
        let (stop, stopped) = oneshot::channel::<()>();
        let served = tokio::spawn(app.run_until(async move {
            let _ = stopped.await;
        }));
        Self {
            base: format!("http://{addr}"),
            addr,
            client: reqwest::Client::new(),
            stop: Some(stop),
            served: Some(served),
        }
    }

    /// Send the shutdown signal and wait for `run_until` to return; returns how long that took.
    async fn shut_down(&mut self) -> Duration {
        let t0 = Instant::now();
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(h) = self.served.take() {
            // Bounds a hang; the tests assert the real figure.
            tokio::time::timeout(Duration::from_secs(120), h)
                .await
                .expect("run_until returns")
                .expect("the serving task does not panic")
                .expect("serving ends without an I/O error");
        }
        t0.elapsed()
    }

    fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    async fn get_json(&self, path: &str) -> Value {
        let r = self
            .client
            .get(self.url(path))
            .send()
            .await
            .expect("request");
        assert_eq!(r.status(), 200, "GET {path}");
        r.json().await.expect("json")
    }

    async fn post_json(&self, path: &str, body: &Value) -> (u16, Value) {
        let r = self
            .client
            .post(self.url(path))
            .json(body)
            .send()
            .await
            .expect("request");
        (r.status().as_u16(), r.json().await.expect("json"))
    }

    async fn simulate(&self, geometry: Value) -> String {
        let (status, v) = self
            .post_json(
                "/v1/simulations",
                &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 40},
                        "geometry": geometry}),
            )
            .await;
        assert_eq!(status, 201, "{v}");
        v["id"].as_str().expect("id").to_string()
    }

    async fn submit(&self, body: &Value) -> String {
        let (status, v) = self.post_json("/v1/jobs", body).await;
        assert_eq!(status, 202, "{v}");
        v["id"].as_str().expect("id").to_string()
    }

    /// Poll job `id` until `done` holds (at most `secs`: this bounds a hang, it is not a timing).
    async fn wait_until(&self, id: &str, secs: u64, done: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let j = self.get_json(&format!("/v1/jobs/{id}")).await;
            if done(&j) {
                return j;
            }
            assert!(Instant::now() < deadline, "job {id} did not get there: {j}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }
}

fn terminal(j: &Value) -> bool {
    matches!(
        j["status"].as_str(),
        Some("succeeded" | "failed" | "canceled")
    )
}

/// A succeeded job whose volume is 2048 × 2048 float32 (16 MiB plus the header): more than the socket
/// buffers of a loopback connection can hold, so a client that stops reading keeps the response open.
async fn large_result(server: &Server) -> (String, u64) {
    let input = server.simulate(parallel_geometry(30, 256, 0.8)).await;
    let id = server
        .submit(&json!({"input": input, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 2048, "ny": 2048, "dx_mm": 0.04, "dy_mm": 0.04}}))
        .await;
    let j = server.wait_until(&id, 600, terminal).await;
    assert_eq!(j["status"], "succeeded", "{j}");
    let bytes = j["result"]["volume"]["bytes"]
        .as_u64()
        .expect("volume bytes");
    assert!(bytes > 16 << 20, "{bytes}");
    (id, bytes)
}

/// Open a raw connection with a small receive buffer, ask for `path` and read the response head and the
/// first bytes of the body; returns the stream, the declared body length and the body bytes read so far.
async fn start_download(addr: SocketAddr, path: &str) -> (tokio::net::TcpStream, u64, u64) {
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("receive buffer");
    let mut s = socket.connect(addr).await.expect("connect");
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: test\r\n\r\n").as_bytes())
        .await
        .expect("request");
    let mut head = Vec::new();
    let mut buf = [0u8; 1024];
    let end = loop {
        let n = s.read(&mut buf).await.expect("response");
        assert!(n > 0, "the connection closed before the response head");
        head.extend_from_slice(&buf[..n]);
        if let Some(p) = head.windows(4).position(|w| w == b"\r\n\r\n") {
            break p + 4;
        }
    };
    let text = String::from_utf8_lossy(&head[..end]).to_ascii_lowercase();
    assert!(text.starts_with("http/1.1 200"), "{text}");
    let length = text
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .and_then(|v| v.trim().parse::<u64>().ok())
        .expect("a content length");
    (s, length, (head.len() - end) as u64)
}

/// Read until the server closes the connection (or fails it); returns the bytes read.
async fn read_to_close(s: &mut tokio::net::TcpStream) -> u64 {
    let mut buf = vec![0u8; 1 << 16];
    let mut total = 0u64;
    loop {
        match s.read(&mut buf).await {
            Ok(0) | Err(_) => return total,
            Ok(n) => total += n as u64,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_a_large_body_is_cut_off_at_the_drain_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), |s| s.drain_timeout_ms = 1000).await;
    let (id, bytes) = large_result(&server).await;
    let (mut stream, length, read) =
        start_download(server.addr, &format!("/v1/jobs/{id}/result/volume.npy")).await;
    assert_eq!(length, bytes);

    // The client reads nothing more; the shutdown waits for the download only as long as the drain allows.
    let took = server.shut_down().await;
    assert!(
        took >= Duration::from_millis(900),
        "{took:?}: the drain did not wait"
    );
    assert!(
        took < Duration::from_secs(5),
        "{took:?}: the drain was not bounded"
    );

    // The connection was closed before the body was complete.
    let rest = read_to_close(&mut stream).await;
    assert!(read + rest < length, "{} of {length} bytes", read + rest);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_download_in_flight_at_shutdown_completes_within_the_drain_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), |s| s.drain_timeout_ms = 10_000).await;
    let (id, bytes) = large_result(&server).await;
    let (mut stream, length, read) =
        start_download(server.addr, &format!("/v1/jobs/{id}/result/volume.npy")).await;
    assert_eq!(length, bytes);

    // The shutdown begins while the body is still in flight; the client then reads the rest.
    let stop = tokio::spawn(async move {
        let took = server.shut_down().await;
        (server, took)
    });
    tokio::time::sleep(Duration::from_millis(300)).await;
    let rest = read_to_close(&mut stream).await;
    assert_eq!(read + rest, length, "the whole body arrives");
    let (_server, took) = stop.await.unwrap();
    assert!(
        took < Duration::from_secs(9),
        "{took:?}: waited for the whole timeout"
    );
}

/// A cone-beam FDK long enough to be stopped while it runs (about as long as the crash-recovery test's).
async fn long_job(server: &Server) -> String {
    let input = server.simulate(cone_geometry(360, 128)).await;
    server
        .submit(&json!({"input": input, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 160, "ny": 160, "nz": 160, "spacing_mm": [0.5, 0.5, 0.5]}}))
        .await
}

fn lifecycle_settings(s: &mut Settings) {
    s.max_attempts = 2;
    s.drain_timeout_ms = 2000;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_stopped_by_graceful_shutdowns_is_requeued_without_spending_attempts() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), lifecycle_settings).await;
    let id = long_job(&server).await;
    let job_path = format!("/v1/jobs/{id}");

    // More graceful restarts than the attempt limit (2) allows crashes.
    for round in 0..4 {
        let j = server
            .wait_until(&id, 300, |j| {
                terminal(j) || (j["status"] == "running" && j["progress"].as_u64() > Some(2))
            })
            .await;
        assert_eq!(
            j["status"], "running",
            "round {round}: the job finished before the shutdown: make it slower"
        );
        assert_eq!(j["attempts"], 1, "round {round}: {j}");

        // An open event stream does not hold the shutdown up; it ends.
        let mut events = server
            .client
            .get(server.url(&format!("{job_path}/events")))
            .send()
            .await
            .expect("events");
        assert_eq!(events.status(), 200);
        let took = server.shut_down().await;
        assert!(took < Duration::from_secs(10), "round {round}: {took:?}");
        let ended = tokio::time::timeout(Duration::from_secs(10), async {
            while let Ok(Some(_)) = events.chunk().await {}
        })
        .await;
        assert!(ended.is_ok(), "round {round}: the event stream stayed open");

        // Between the two processes the job is queued again with the attempt given back.
        {
            let db = Db::open(&dir.path().join("ctrecon.sqlite")).await.unwrap();
            let stored = db
                .get_job(JobId::parse(&id).unwrap())
                .await
                .unwrap()
                .expect("the job is kept");
            assert_eq!(stored.status, JobStatus::Queued, "round {round}");
            assert_eq!(stored.attempts, 0, "round {round}");
            assert_eq!(stored.stage, "requeued");
            assert_eq!(stored.started_us, None);
        }
        server = Server::start(dir.path(), lifecycle_settings).await;
        let j = server.get_json(&job_path).await;
        assert!(
            matches!(j["status"].as_str(), Some("queued" | "running")),
            "round {round}: {j}"
        );
    }
    let done = server.wait_until(&id, 600, terminal).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1, "{done}");
    assert_eq!(done["result"]["shape"], json!([160, 160, 160]));
    server.shut_down().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_asked_to_cancel_before_a_graceful_shutdown_ends_canceled() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), lifecycle_settings).await;
    let id = long_job(&server).await;
    let j = server
        .wait_until(&id, 300, |j| terminal(j) || j["status"] == "running")
        .await;
    assert_eq!(j["status"], "running", "{j}");
    let (status, _) = server
        .post_json(&format!("/v1/jobs/{id}/cancel"), &json!({}))
        .await;
    assert_eq!(status, 202);
    server.shut_down().await;
    let server = Server::start(dir.path(), lifecycle_settings).await;
    let j = server.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(j["status"], "canceled", "{j}");
    assert_eq!(j["attempts"], 1, "{j}");
}

fn keys(v: &Value) -> Vec<String> {
    let mut k: Vec<String> = v.as_object().expect("an object").keys().cloned().collect();
    k.sort();
    k
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn job_lists_are_summaries_and_fields_or_expand_select_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), |_| {}).await;
    let input = server.simulate(parallel_geometry(60, 128, 0.8)).await;
    let id = server
        .submit(&json!({"input": input, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 32, "ny": 32, "dx_mm": 2.5, "dy_mm": 2.5},
                        "outputs": ["volume", "metrics"]}))
        .await;
    assert_eq!(
        server.wait_until(&id, 600, terminal).await["status"],
        "succeeded"
    );
    let full = server.get_json(&format!("/v1/jobs/{id}")).await;

    let summary_keys = [
        "created_at",
        "finished_at",
        "id",
        "kind",
        "links",
        "progress",
        "stage",
        "started_at",
        "status",
    ];
    let list = server.get_json("/v1/jobs").await;
    let s = &list["jobs"][0];
    assert_eq!(keys(s), summary_keys);
    for k in summary_keys {
        assert_eq!(s[k], full[k], "{k}");
    }
    assert_eq!(
        s["links"]["metrics"],
        format!("/v1/jobs/{id}/result/metrics")
    );

    let e = server
        .get_json("/v1/jobs?expand=attempts,error,result")
        .await;
    let e = &e["jobs"][0];
    let mut expanded: Vec<&str> = summary_keys.to_vec();
    expanded.extend(["attempts", "error", "result"]);
    expanded.sort();
    assert_eq!(keys(e), expanded);
    assert_eq!(e["attempts"], 1);
    assert_eq!(e["error"], Value::Null);
    assert_eq!(e["result"], full["result"]);
    assert!(e["result"]["metrics"]["rmse"].is_number());

    let all = server.get_json("/v1/jobs?expand=all").await;
    assert_eq!(all["jobs"][0], full);
    let summary_bytes = serde_json::to_vec(&list).unwrap().len();
    let full_bytes = serde_json::to_vec(&all).unwrap().len();
    assert!(
        summary_bytes < full_bytes,
        "{summary_bytes} vs {full_bytes}"
    );

    let f = server.get_json("/v1/jobs?fields=status,progress").await;
    assert_eq!(
        f["jobs"][0],
        json!({"id": id, "status": "succeeded", "progress": 100})
    );
    let r = server.get_json("/v1/jobs?fields=request").await;
    let r = &r["jobs"][0];
    assert_eq!(keys(r), ["algorithm", "grid", "id", "input", "outputs"]);
    for k in ["algorithm", "grid", "input", "outputs"] {
        assert_eq!(r[k], full[k], "{k}");
    }

    for bad in [
        "fields=colour",
        "expand=status,secrets",
        "fields=",
        "expand=request,,x",
    ] {
        let resp = server
            .client
            .get(server.url(&format!("/v1/jobs?{bad}")))
            .send()
            .await
            .unwrap();
        if bad == "fields=" {
            // An empty list names no field: the id alone.
            assert_eq!(resp.status(), 200, "{bad}");
            let v: Value = resp.json().await.unwrap();
            assert_eq!(v["jobs"][0], json!({"id": id}));
            continue;
        }
        common::assert_problem(resp, 400, "invalid_query").await;
    }

    // A list served again (from the page cache) shows every write made since: a new job, then its end.
    assert_eq!(server.get_json("/v1/jobs").await, list);
    let second = server
        .submit(&json!({"input": input, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 16, "ny": 16, "dx_mm": 5.0, "dy_mm": 5.0}}))
        .await;
    let again = server.get_json("/v1/jobs").await;
    assert_eq!(again["jobs"].as_array().unwrap().len(), 2);
    assert_eq!(again["jobs"][0]["id"], second.as_str());
    let done = server.wait_until(&second, 600, terminal).await;
    assert_eq!(done["status"], "succeeded");
    let again = server.get_json("/v1/jobs").await;
    assert_eq!(again["jobs"][0]["status"], "succeeded");
    assert_eq!(again["jobs"][0]["progress"], 100);
    assert_eq!(again["jobs"][1], list["jobs"][0]);
}

/// `ctrecon_storage_bytes{kind="…"}` from `/metrics`.
async fn storage_bytes(server: &Server, kind: &str) -> u64 {
    let text = server
        .client
        .get(server.url("/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let prefix = format!("ctrecon_storage_bytes{{kind=\"{kind}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no {prefix} in\n{text}")) as u64
}

async fn status_of(server: &Server, path: &str) -> u16 {
    server
        .client
        .get(server.url(path))
        .send()
        .await
        .unwrap()
        .status()
        .as_u16()
}

/// Poll until `path` answers 404 (at most `secs`: this bounds a hang, it is not a timing).
async fn wait_gone(server: &Server, path: &str, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while status_of(server, path).await != 404 {
        assert!(Instant::now() < deadline, "{path} was never removed");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// The sweep deletes the rows first and the files after them, so the storage gauge follows a 404 shortly.
async fn wait_storage(server: &Server, kind: &str, bytes: u64, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let now = storage_bytes(server, kind).await;
        if now == bytes {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{kind}: {now} bytes stored, expected {bytes}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn retain_one_second(sweep_secs: u64) -> impl FnOnce(&mut Settings) {
    move |s| {
        s.retain_finished_jobs_secs = 1;
        s.retain_datasets_secs = 1;
        s.retain_series_secs = 1;
        s.retention_sweep_secs = sweep_secs;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_removes_what_aged_out_at_start_and_periodically_but_never_an_input_in_use() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path();

    // Retention off: a finished job, its dataset, and a CT series made from its DICOM export.
    let mut server = Server::start(data, |_| {}).await;
    let a = server.simulate(cone_geometry(60, 48)).await;
    let j1 = server
        .submit(&json!({"input": a, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1.2, 1.2, 1.2]}}))
        .await;
    assert_eq!(
        server.wait_until(&j1, 600, terminal).await["status"],
        "succeeded"
    );
    let zip = server
        .client
        .get(server.url(&format!("/v1/jobs/{j1}/result/series.zip")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let r = server
        .client
        .post(server.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(zip.to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let s1 = v["series"][0]["series"]["id"].as_str().unwrap().to_string();
    assert!(storage_bytes(&server, "datasets").await > 0);
    assert!(storage_bytes(&server, "series").await > 0);
    assert!(storage_bytes(&server, "results").await > 0);
    server.shut_down().await;
    tokio::time::sleep(Duration::from_millis(1200)).await;

    // A start with a retention of 1 s and no periodic sweep in sight: the sweep at start removed them all.
    let mut server = Server::start(data, retain_one_second(3600)).await;
    assert_eq!(status_of(&server, &format!("/v1/jobs/{j1}")).await, 404);
    assert_eq!(status_of(&server, &format!("/v1/datasets/{a}")).await, 404);
    assert_eq!(status_of(&server, &format!("/v1/series/{s1}")).await, 404);
    assert!(!data.join("datasets").join(format!("{a}.npy")).exists());
    assert!(!data.join("series").join(format!("{s1}.npy")).exists());
    assert!(!data.join("results").join(&j1).exists());
    for kind in ["datasets", "series", "results"] {
        assert_eq!(storage_bytes(&server, kind).await, 0, "{kind}");
    }
    server.shut_down().await;

    // Sweeping every second: a finished job and its dataset go; a dataset a running job uses stays.
    let server = Server::start(data, retain_one_second(1)).await;
    let b = server.simulate(cone_geometry(360, 128)).await;
    // Long enough to be running through every check below on any machine (it is canceled at the end): an FDK
    // of 160³ finished before them on a quiet one.
    let long = server
        .submit(
            &json!({"input": b, "algorithm": {"name": "sirt", "iterations": 10000},
                        "grid": {"nx": 160, "ny": 160, "nz": 160, "spacing_mm": [0.5, 0.5, 0.5]}}),
        )
        .await;
    let b_bytes = server.get_json(&format!("/v1/datasets/{b}")).await["bytes"]
        .as_u64()
        .unwrap();
    let c = server.simulate(parallel_geometry(30, 64, 1.0)).await;
    let j3 = server
        .submit(&json!({"input": c, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 16, "ny": 16, "dx_mm": 2.0, "dy_mm": 2.0}}))
        .await;
    assert_eq!(
        server.wait_until(&j3, 600, terminal).await["status"],
        "succeeded"
    );
    wait_gone(&server, &format!("/v1/jobs/{j3}"), 30).await;
    wait_gone(&server, &format!("/v1/datasets/{c}"), 30).await;
    // B was there while the job that reads it was still queued or running (checked in that order).
    assert_eq!(status_of(&server, &format!("/v1/datasets/{b}")).await, 200);
    let j = server.get_json(&format!("/v1/jobs/{long}")).await;
    assert!(
        matches!(j["status"].as_str(), Some("queued" | "running")),
        "the long job finished too soon: {j}"
    );
    wait_storage(&server, "datasets", b_bytes, 10).await;

    // Once the job is over, it and its dataset age out too.
    let (status, _) = server
        .post_json(&format!("/v1/jobs/{long}/cancel"), &json!({}))
        .await;
    assert_eq!(status, 202);
    wait_gone(&server, &format!("/v1/jobs/{long}"), 30).await;
    wait_gone(&server, &format!("/v1/datasets/{b}"), 30).await;
    wait_storage(&server, "datasets", 0, 10).await;
}

/// Each job and each request's computation runs on a pool of its own. On one shared pool, a thread waiting
/// for a stolen part of a simulation could take up a job started meanwhile and run it whole before
/// returning: the simulation then waited for the job (a request timeout after 10 min).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_simulation_never_waits_for_a_job_started_beside_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), |_| {}).await;
    let input = server.simulate(cone_geometry(120, 64)).await;
    // Runs for hours unless canceled.
    let long = json!({"input": input, "algorithm": {"name": "sirt", "iterations": 10000},
                      "grid": {"nx": 96, "ny": 96, "nz": 96, "spacing_mm": [0.5, 0.5, 0.5]}});
    for round in 0..10 {
        let (job, simulated) = tokio::join!(
            server.submit(&long),
            tokio::time::timeout(
                Duration::from_secs(60),
                server.simulate(cone_geometry(360, 128))
            )
        );
        assert!(
            simulated.is_ok(),
            "round {round}: the simulation waited for the job"
        );
        // The job ran beside the simulation.
        server
            .wait_until(&job, 120, |j| j["status"] != "queued")
            .await;
        let (status, _) = server
            .post_json(&format!("/v1/jobs/{job}/cancel"), &json!({}))
            .await;
        assert_eq!(status, 202);
        assert_eq!(
            server.wait_until(&job, 120, terminal).await["status"],
            "canceled"
        );
    }
    server.shut_down().await;
}
