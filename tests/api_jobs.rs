//! The job API end to end over HTTP against the real server: simulate → reconstruct → poll → results;
//! cancel; the concurrency limit; idempotency; Server-Sent Events; and (ignored) the load figure.

use crate::common;

use std::time::{Duration, Instant};

use common::{TestApp, cone_geometry, read_npy_f32, spawn_app, spawn_app_with};
use serde_json::{Value, json};

fn fdk_job(input: &str, n: usize, outputs: &[&str]) -> Value {
    json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
           "grid": {"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]},
           "outputs": outputs})
}

/// Width, height and bit depth from a PNG's IHDR.
fn png_header(bytes: &[u8]) -> (u32, u32, u8) {
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "PNG signature");
    assert_eq!(&bytes[12..16], b"IHDR");
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    (be(16), be(20), bytes[24])
}

async fn bytes_of(app: &TestApp, path: &str) -> (reqwest::header::HeaderMap, Vec<u8>) {
    let r = app.get(path).await;
    assert_eq!(r.status(), 200, "{path}");
    let h = r.headers().clone();
    (h, r.bytes().await.expect("body").to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_curl_flow_simulates_reconstructs_and_serves_slices_projections_meshes_and_metrics() {
    let app = spawn_app().await;
    // 120 views of a 96² panel of 1 mm, magnification 1.5: the isocentre field is ±32 mm; the phantom
    // (scale 28 mm) reaches 0.92 × 28 ≈ 26 mm.
    let input = app.simulate(cone_geometry(120, 96), 28.0).await;
    let r = app
        .post_json("/v1/jobs", &fdk_job(&input, 64, &["volume", "metrics"]))
        .await;
    assert_eq!(r.status(), 202);
    let location = r.headers()["location"].to_str().unwrap().to_string();
    let job: Value = r.json().await.unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/v1/jobs/{id}"));
    assert!(matches!(job["status"].as_str(), Some("queued" | "running")));

    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["progress"], 100);
    assert_eq!(done["result"]["shape"], json!([64, 64, 64]));
    assert!(done["started_at"].is_string() && done["finished_at"].is_string());

    // Metrics against the rasterised phantom: FDK of exact data with a Hann window on 1 mm voxels. The
    // modified Shepp–Logan values span 0..1; an RMSE below 0.06 (6 % of the range) and an SSIM above 0.75
    // fail for a misplaced, flipped or mis-scaled reconstruction.
    let m: Value = app
        .get(&format!("/v1/jobs/{id}/result/metrics"))
        .await
        .json()
        .await
        .unwrap();
    let rmse = m["rmse"].as_f64().unwrap();
    assert!(rmse < 0.06, "RMSE {rmse}");
    assert!(m["ssim"].as_f64().unwrap() > 0.75, "{m}");

    // The volume: float32 [64][64][64]. A 2 × 2 × 2 block at the centre of the field matches the phantom
    // there (rasterised at voxel centres) within 0.03 (3 % of the phantom's range).
    let (h, vol) = bytes_of(&app, &format!("/v1/jobs/{id}/result/volume.npy")).await;
    let (shape, values) = read_npy_f32(&vol);
    assert_eq!(shape, [64, 64, 64]);
    let sha = done["result"]["volume"]["sha256"].as_str().unwrap();
    assert_eq!(h["etag"].to_str().unwrap(), format!("\"{sha}\""));
    assert!(h["cache-control"].to_str().unwrap().contains("immutable"));
    let at = |z: usize, y: usize, x: usize| values[(z * 64 + y) * 64 + x];
    let grid = ctrecon::recon::VolumeGrid::cube(64, 1.0);
    let truth = ctrecon::recon::phantom::Phantom3::from_table(
        ctrecon::recon::phantom::Table3::ModifiedSheppLogan,
        28.0,
    )
    .rasterize(&grid, 1);
    let (mut got, mut want) = (0.0, 0.0);
    for z in 31..33 {
        for y in 31..33 {
            for x in 31..33 {
                got += at(z, y, x) / 8.0;
                want += truth[[z, y, x]] / 8.0;
            }
        }
    }
    assert!((got - want).abs() < 0.03, "centre {got}, phantom {want}");
    eprintln!("FDK 64³ vs phantom: {m}; centre {got} vs {want}");

    // Conditional and range requests.
    let url = app.url(&format!("/v1/jobs/{id}/result/volume.npy"));
    let r = app
        .client
        .get(&url)
        .header("if-none-match", format!("\"{sha}\""))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    let r = app
        .client
        .get(&url)
        .header("range", "bytes=0-5")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 206);
    assert_eq!(
        r.headers()["content-range"].to_str().unwrap(),
        format!("bytes 0-5/{}", vol.len())
    );
    assert_eq!(&r.bytes().await.unwrap()[..], b"\x93NUMPY");

    // A slice as 8- and 16-bit PNG and as .npy (equal to the volume's slice).
    let (h, png) = bytes_of(
        &app,
        &format!("/v1/jobs/{id}/result/slice?axis=axial&index=32&ww=0.6&wl=0.3"),
    )
    .await;
    assert_eq!(h["content-type"], "image/png");
    assert_eq!(png_header(&png), (64, 64, 8));
    let (_, png16) = bytes_of(
        &app,
        &format!("/v1/jobs/{id}/result/slice?axis=sagittal&preset=bone&depth=16"),
    )
    .await;
    assert_eq!(png_header(&png16), (64, 64, 16));
    let (_, s) = bytes_of(
        &app,
        &format!("/v1/jobs/{id}/result/slice?axis=axial&index=32&format=npy"),
    )
    .await;
    let (sshape, svals) = read_npy_f32(&s);
    assert_eq!(sshape, [64, 64]);
    assert_eq!(svals[..], values[32 * 64 * 64..33 * 64 * 64]);

    // A MIP over a coronal slab: its maximum is the volume's maximum over that slab.
    let (_, mip) = bytes_of(
        &app,
        &format!("/v1/jobs/{id}/result/projection?axis=coronal&kind=mip&slab_start=16&slab_end=48&format=npy"),
    )
    .await;
    let (mshape, mvals) = read_npy_f32(&mip);
    assert_eq!(mshape, [64, 64]);
    let slab_max = (0..64)
        .flat_map(|z| (16..48).flat_map(move |y| (0..64).map(move |x| (z, y, x))))
        .map(|(z, y, x)| at(z, y, x))
        .fold(f32::MIN, f32::max);
    let mip_max = mvals.iter().copied().fold(f32::MIN, f32::max);
    assert_eq!(mip_max, slab_max);
    let (_, mip_png) = bytes_of(
        &app,
        &format!("/v1/jobs/{id}/result/projection?axis=axial&kind=minip&preset=soft_tissue"),
    )
    .await;
    assert_eq!(png_header(&mip_png).0, 64);

    // The iso-surface of the skull (1.0 against 0.2 inside, 0 outside) as binary STL.
    let (h, stl) = bytes_of(&app, &format!("/v1/jobs/{id}/result/mesh.stl?iso=0.5")).await;
    assert_eq!(h["content-type"], "model/stl");
    let n = u32::from_le_bytes([stl[80], stl[81], stl[82], stl[83]]) as usize;
    assert!(n > 100, "{n} triangles");
    assert_eq!(stl.len(), 84 + 50 * n);
    assert!(!stl.starts_with(b"solid"));

    // Finished jobs can be deleted, with their files.
    let r = app
        .client
        .delete(app.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    assert_eq!(app.get(&format!("/v1/jobs/{id}")).await.status(), 404);
    assert!(!app.dir.path().join("results").join(&id).exists());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn analytic_and_iterative_jobs_on_a_2d_scan_reconstruct_the_phantom() {
    let app = spawn_app().await;
    // 180 parallel views, 128 detector elements of 0.5 mm (±32 mm) around a phantom of scale 28 mm.
    let input = app
        .simulate(common::parallel_geometry(180, 128, 0.5), 28.0)
        .await;
    let grid = json!({"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0});
    let mut ids = Vec::new();
    for (alg, bound) in [
        (json!({"name": "fbp", "filter": "hann"}), 0.04),
        (
            json!({"name": "sirt", "iterations": 200, "nonnegative": true}),
            0.04,
        ),
        (json!({"name": "cgls", "iterations": 30}), 0.08),
    ] {
        let j = app
            .submit(&json!({"input": input, "algorithm": alg, "grid": grid,
                            "outputs": ["volume", "metrics"]}))
            .await;
        ids.push((
            alg["name"].clone(),
            j["id"].as_str().unwrap().to_string(),
            bound,
        ));
    }
    for (name, id, bound) in ids {
        let done = app.finish(&id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert_eq!(done["result"]["shape"], json!([1, 64, 64]));
        let m = &done["result"]["metrics"];
        eprintln!("{name} 64² vs phantom: {m}");
        // The phantom spans 0..1. Measured RMSE on exact data: FBP (Hann) 0.027, SIRT (200 iterations,
        // non-negative) 0.024, CGLS (30 iterations, unregularised, noisier) 0.058; bounds leave ~40 %.
        assert!(m["rmse"].as_f64().unwrap() < bound, "{name}: {m}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_job_is_canceled_and_leaves_no_result_and_a_queued_one_is_canceled_at_once() {
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 1).await;
    // A slow FDK: 360 views onto a 192³ grid.
    let input = app.simulate(cone_geometry(360, 128), 40.0).await;
    let slow = app.submit(&fdk_job(&input, 192, &["volume"])).await;
    let slow = slow["id"].as_str().unwrap().to_string();
    let queued = app.submit(&fdk_job(&input, 192, &["volume"])).await;
    let queued = queued["id"].as_str().unwrap().to_string();

    app.wait_until(&slow, 120, |j| {
        j["status"] == "running" && j["progress"].as_u64() > Some(2)
    })
    .await;
    // The second job waits for the first (max_concurrent_jobs = 1): cancel it while queued.
    let r = app
        .post_json(&format!("/v1/jobs/{queued}/cancel"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    assert_eq!(app.job(&queued).await["status"], "canceled");

    let r = app
        .post_json(&format!("/v1/jobs/{slow}/cancel"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    let done = app.finish(&slow).await;
    assert_eq!(done["status"], "canceled", "{done}");
    assert!(done["error"].is_null());
    assert!(done["progress"].as_u64().unwrap() < 100);
    common::assert_problem(
        app.get(&format!("/v1/jobs/{slow}/result/volume.npy")).await,
        409,
        "job_not_succeeded",
    )
    .await;
    assert!(
        !app.dir
            .path()
            .join("results")
            .join(&slow)
            .join("volume.npy")
            .exists()
    );
    common::assert_problem(
        app.post_json(&format!("/v1/jobs/{slow}/cancel"), &json!({}))
            .await,
        409,
        "job_already_finished",
    )
    .await;
}

fn micros(t: &Value) -> i64 {
    ctrecon::jobs::model::parse_rfc3339(t.as_str().expect("timestamp")).expect("RFC 3339")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_jobs_all_finish_and_never_more_than_the_limit_run_at_once() {
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 2).await;
    let input = app.simulate(cone_geometry(90, 64), 20.0).await;
    let mut ids = Vec::new();
    for _ in 0..6 {
        let j = app.submit(&fdk_job(&input, 48, &["volume"])).await;
        ids.push(j["id"].as_str().unwrap().to_string());
    }
    let mut most_running = 0;
    loop {
        let list: Value = app
            .get("/v1/jobs?status=running&limit=200")
            .await
            .json()
            .await
            .unwrap();
        most_running = most_running.max(list["jobs"].as_array().unwrap().len());
        let open: Value = app
            .get("/v1/jobs?status=queued,running")
            .await
            .json()
            .await
            .unwrap();
        if open["jobs"].as_array().unwrap().is_empty() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(most_running <= 2, "{most_running} jobs ran at once");
    // From the recorded start and end times: at no instant did more than two jobs run.
    let mut spans = Vec::new();
    for id in &ids {
        let j = app.job(id).await;
        assert_eq!(j["status"], "succeeded", "{j}");
        spans.push((micros(&j["started_at"]), micros(&j["finished_at"])));
    }
    for &(start, _) in &spans {
        let overlapping = spans
            .iter()
            .filter(|&&(s, e)| s <= start && start < e)
            .count();
        assert!(overlapping <= 2, "{overlapping} jobs overlap at {start}");
    }
    // Pagination walks all six, newest first, without repeats.
    let page1: Value = app.get("/v1/jobs?limit=4").await.json().await.unwrap();
    let cursor = page1["next_cursor"].as_str().unwrap();
    let page2: Value = app
        .get(&format!("/v1/jobs?limit=4&cursor={cursor}"))
        .await
        .json()
        .await
        .unwrap();
    let listed: Vec<String> = page1["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .chain(page2["jobs"].as_array().unwrap())
        .map(|j| j["id"].as_str().unwrap().to_string())
        .collect();
    let mut expected = ids.clone();
    expected.reverse();
    assert_eq!(listed, expected);
    assert!(page2["next_cursor"].is_null());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idempotency_key_returns_the_same_resource_and_refuses_another_body() {
    let app = spawn_app().await;
    let sim = json!({"phantom": {"table": "shepp_logan", "scale_mm": 20},
                     "geometry": cone_geometry(30, 48)});
    let post = |path: &'static str, key: &'static str, body: Value| {
        let app = &app;
        async move {
            app.client
                .post(app.url(path))
                .header("idempotency-key", key)
                .json(&body)
                .send()
                .await
                .unwrap()
        }
    };
    let a = post("/v1/simulations", "sim-1", sim.clone()).await;
    assert_eq!(a.status(), 201);
    let a: Value = a.json().await.unwrap();
    let b: Value = post("/v1/simulations", "sim-1", sim.clone())
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(a["id"], b["id"]);
    let input = a["id"].as_str().unwrap();

    let job = fdk_job(input, 32, &["volume"]);
    let first = post("/v1/jobs", "job-1", job.clone()).await;
    assert_eq!(first.status(), 202);
    let first: Value = first.json().await.unwrap();
    // The same body with other key order and spacing is the same request.
    let reordered: Value =
        serde_json::from_str(&serde_json::to_string_pretty(&job).unwrap()).unwrap();
    let again = post("/v1/jobs", "job-1", reordered).await;
    assert_eq!(again.status(), 202);
    let again: Value = again.json().await.unwrap();
    assert_eq!(first["id"], again["id"]);
    let other = fdk_job(input, 40, &["volume"]);
    common::assert_problem(
        post("/v1/jobs", "job-1", other.clone()).await,
        422,
        "idempotency_key_reused",
    )
    .await;
    // Without a key, or with another key, a new job.
    let new: Value = app.submit(&job).await;
    assert_ne!(new["id"], first["id"]);
    let list: Value = app.get("/v1/jobs").await.json().await.unwrap();
    assert_eq!(list["jobs"].as_array().unwrap().len(), 2);
}

/// Read SSE events `(event, data)` from a response until a `final` event (or the stream ends).
async fn read_events(mut r: reqwest::Response) -> Vec<(String, Value)> {
    let mut buf = String::new();
    let mut out = Vec::new();
    while let Some(chunk) = r.chunk().await.expect("event stream") {
        buf.push_str(&String::from_utf8_lossy(&chunk));
        while let Some(end) = buf.find("\n\n") {
            let block: String = buf.drain(..end + 2).collect();
            let mut event = String::new();
            let mut data = String::new();
            for line in block.lines() {
                if let Some(e) = line.strip_prefix("event:") {
                    event = e.trim().to_string();
                } else if let Some(d) = line.strip_prefix("data:") {
                    data.push_str(d.trim());
                }
            }
            if event.is_empty() {
                continue;
            }
            let v: Value = serde_json::from_str(&data).expect("event data is JSON");
            let last = event == "final";
            out.push((event, v));
            if last {
                return out;
            }
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_sent_events_deliver_progress_and_the_final_state() {
    let app = spawn_app().await;
    let input = app.simulate(cone_geometry(180, 96), 28.0).await;
    let job = app.submit(&fdk_job(&input, 96, &["volume"])).await;
    let id = job["id"].as_str().unwrap();
    let r = app.get(&format!("/v1/jobs/{id}/events")).await;
    assert_eq!(r.status(), 200);
    assert!(
        r.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/event-stream")
    );
    let events = read_events(r).await;
    let (last, fin) = events.last().expect("events");
    assert_eq!(last, "final");
    assert_eq!(fin["status"], "succeeded");
    assert_eq!(fin["progress"], 100);
    let progress: Vec<&Value> = events
        .iter()
        .filter(|(e, _)| e == "progress")
        .map(|(_, v)| v)
        .collect();
    let running: Vec<u64> = progress
        .iter()
        .filter(|v| v["status"] == "running")
        .map(|v| v["progress"].as_u64().unwrap())
        .collect();
    assert!(running.len() >= 3, "{progress:?}");
    assert!(running.windows(2).all(|w| w[0] <= w[1]), "{running:?}");
    assert!(running.iter().all(|&p| p < 100));
    // A finished job's stream is just the final state.
    let again = read_events(app.get(&format!("/v1/jobs/{id}/events")).await).await;
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].1["status"], "succeeded");
}

/// The load figure: latency of `GET /v1/jobs/{id}` from 50 concurrent clients while reconstructions keep
/// both workers busy. Prints median and p99; run with `cargo test --release --test service api_jobs:: -- --ignored
/// --nocapture load`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement, not a check: prints the load figure"]
async fn load_figure_for_job_status_under_busy_workers() {
    let app = spawn_app_with(|s| {
        s.max_concurrent_jobs = 2;
        s.progress_interval_ms = 500;
    })
    .await;
    let input = app.simulate(cone_geometry(360, 128), 40.0).await;
    let a = app.submit(&fdk_job(&input, 224, &["volume"])).await;
    let _b = app.submit(&fdk_job(&input, 224, &["volume"])).await;
    let id = a["id"].as_str().unwrap().to_string();
    app.wait_until(&id, 120, |j| j["status"] == "running").await;
    let url = app.url(&format!("/v1/jobs/{id}"));
    let mut tasks = Vec::new();
    for _ in 0..50 {
        let client = reqwest::Client::new();
        let url = url.clone();
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            let mut errors = 0;
            for _ in 0..40 {
                let t = Instant::now();
                match client.get(&url).send().await {
                    Ok(r) if r.status() == 200 => {
                        let _ = r.bytes().await;
                        lat.push(t.elapsed());
                    }
                    _ => errors += 1,
                }
            }
            (lat, errors)
        }));
    }
    let mut all = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let (l, e) = t.await.unwrap();
        all.extend(l);
        errors += e;
    }
    let running = app.job(&id).await;
    all.sort();
    let pct = |p: f64| all[((all.len() - 1) as f64 * p).round() as usize];
    println!(
        "GET /v1/jobs/{{id}}: {} requests from 50 clients, {} errors, median {:?}, p99 {:?}, max {:?} (job still {})",
        all.len(),
        errors,
        pct(0.5),
        pct(0.99),
        all.last().unwrap(),
        running["status"]
    );
    assert_eq!(errors, 0);
    for id in [a["id"].as_str().unwrap(), _b["id"].as_str().unwrap()] {
        app.post_json(&format!("/v1/jobs/{id}/cancel"), &json!({}))
            .await;
    }
}
