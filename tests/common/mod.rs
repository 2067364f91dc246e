//! Helpers of the API integration tests: a real server on a random port with a fresh data directory per
//! test, a client, and the requests most tests make.
#![allow(dead_code)]

use std::time::Duration;

use ctrecon::config::Settings;
use ctrecon::http::Application;
use serde_json::{Value, json};

pub struct TestApp {
    pub base: String,
    pub client: reqwest::Client,
    pub dir: tempfile::TempDir,
    /// The DICOM node's address, when the settings gave it a port.
    pub dicom: Option<std::net::SocketAddr>,
    /// The server's application (database, blob store, engine), for tests that act beside the API; `None`
    /// for a client of a server in another process ([`attach`]).
    pub core: Option<ctrecon::app::App>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Drop for TestApp {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }
}

/// Settings of a test server: port 0, two workers, small limits, frequent progress writes.
pub fn test_settings(dir: &std::path::Path) -> Settings {
    Settings {
        bind: "127.0.0.1:0".parse().expect("address"),
        data_dir: dir.to_path_buf(),
        worker_threads: 2,
        max_concurrent_jobs: 2,
        memory_budget_bytes: 1 << 30,
        max_upload_bytes: 16 << 20,
        max_json_bytes: 64 << 10,
        progress_interval_ms: 50,
        ..Settings::default()
    }
}

pub async fn spawn_app() -> TestApp {
    spawn_app_with(|_| {}).await
}

pub async fn spawn_app_with(configure: impl FnOnce(&mut Settings)) -> TestApp {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut settings = test_settings(dir.path());
    configure(&mut settings);
    let app = Application::build(settings)
        .await
        .expect("the service builds");
    let base = format!("http://{}", app.local_addr());
    let core = Some(app.app().clone());
    let dicom = ctrecon::dimse::serve_node(app.app().clone())
        .await
        .expect("the DICOM node starts");
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(app.run_until(async move {
        let _ = stopped.await;
    }));
    TestApp {
        base,
        client: reqwest::Client::new(),
        dir,
        dicom,
        core,
        stop: Some(stop),
    }
}

/// A client of the server at `base` (another process): `dir` is an empty directory of its own, not the
/// server's data directory.
pub fn attach(base: &str) -> TestApp {
    TestApp {
        base: base.trim_end_matches('/').to_string(),
        client: reqwest::Client::new(),
        dir: tempfile::tempdir().expect("temp dir"),
        dicom: None,
        core: None,
        stop: None,
    }
}

/// A 2D parallel-beam geometry covering a phantom of radius `scale_mm`.
pub fn parallel_geometry(views: usize, det: usize, spacing_mm: f64) -> Value {
    json!({"type": "parallel", "angles": {"count": views}, "det_count": det, "det_spacing_mm": spacing_mm})
}

/// A circular cone beam with an `n × n` panel of 1 mm (magnification 1.5).
pub fn cone_geometry(views: usize, n: usize) -> Value {
    json!({"type": "cone", "angles": {"count": views}, "dso_mm": 400, "dsd_mm": 600,
           "detector": {"nu": n, "nv": n, "du_mm": 1.0, "dv_mm": 1.0}})
}

impl TestApp {
    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    pub async fn post_json(&self, path: &str, body: &Value) -> reqwest::Response {
        self.client
            .post(self.url(path))
            .json(body)
            .send()
            .await
            .expect("request")
    }

    pub async fn get(&self, path: &str) -> reqwest::Response {
        self.client
            .get(self.url(path))
            .send()
            .await
            .expect("request")
    }

    /// Simulate the modified Shepp–Logan phantom (scale `scale_mm`) for `geometry`; returns the dataset id.
    pub async fn simulate(&self, geometry: Value, scale_mm: f64) -> String {
        let r = self
            .post_json(
                "/v1/simulations",
                &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": scale_mm},
                        "geometry": geometry}),
            )
            .await;
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
        let v: Value = r.json().await.expect("json");
        v["id"].as_str().expect("id").to_string()
    }

    /// Submit a job; returns its JSON (status 202 asserted).
    pub async fn submit(&self, body: &Value) -> Value {
        let r = self.post_json("/v1/jobs", body).await;
        assert_eq!(r.status(), 202, "{}", r.text().await.unwrap_or_default());
        r.json().await.expect("json")
    }

    pub async fn job(&self, id: &str) -> Value {
        let r = self.get(&format!("/v1/jobs/{id}")).await;
        assert_eq!(r.status(), 200);
        r.json().await.expect("json")
    }

    /// Poll a job until `done(job)` holds (at most `secs` seconds; this bounds a hang, it is not a timing).
    pub async fn wait_until(&self, id: &str, secs: u64, done: impl Fn(&Value) -> bool) -> Value {
        let deadline = std::time::Instant::now() + Duration::from_secs(secs);
        loop {
            let j = self.job(id).await;
            if done(&j) {
                return j;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "job {id} did not get there: {j}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Wait for a job to reach a terminal status.
    pub async fn finish(&self, id: &str) -> Value {
        self.wait_until(id, 600, |j| {
            matches!(
                j["status"].as_str(),
                Some("succeeded" | "failed" | "canceled")
            )
        })
        .await
    }
}

/// Assert `r` is a problem response with `status` and `code`; returns the body.
pub async fn assert_problem(r: reqwest::Response, status: u16, code: &str) -> Value {
    assert_eq!(
        r.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("application/problem+json"),
        "content type of a {status} {code}"
    );
    let got = r.status().as_u16();
    let v: Value = r.json().await.expect("problem json");
    assert_eq!((got, v["code"].as_str()), (status, Some(code)), "{v}");
    assert_eq!(v["status"], status);
    assert!(v["title"].is_string() && v["detail"].is_string() && v["type"].is_string());
    v
}

/// A `.npy` file: `descr`, shape text like `(2, 3)`, raw data bytes.
pub fn npy(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}\n");
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(data);
    out
}

/// The f32 values of a little-endian float32 `.npy` and its shape.
pub fn read_npy_f32(bytes: &[u8]) -> (Vec<usize>, Vec<f32>) {
    let a = ctrecon::storage::npy::decode_f32(bytes).expect("a valid .npy");
    (a.shape().to_vec(), a.iter().copied().collect())
}

/// A binary STL as a slicer or CAD reader takes it: the triangles, with the vertices at one position merged.
pub fn weld_stl(stl: &[u8]) -> ctrecon::mesh::Mesh {
    let (soup, _) = ctrecon::mesh::parse_stl_binary(stl).expect("a binary STL");
    let mut at = std::collections::HashMap::<[u32; 3], u32>::new();
    let mut out = ctrecon::mesh::Mesh::default();
    for t in &soup.triangles {
        let t = t.map(|v| {
            let p = soup.vertices[v as usize];
            *at.entry(p.map(f32::to_bits)).or_insert_with(|| {
                out.vertices.push(p);
                out.vertices.len() as u32 - 1
            })
        });
        out.triangles.push(t);
    }
    out
}

/// The fenced blocks of README.md with info string `lang` (for the README examples run against real peers).
pub fn readme_blocks(lang: &str) -> Vec<String> {
    let text =
        std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md"))
            .unwrap();
    let mut out = Vec::new();
    let mut open: Option<(String, String)> = None;
    for line in text.lines() {
        if let Some(fence) = line.trim_start().strip_prefix("```") {
            match open.take() {
                None => open = Some((fence.trim().to_string(), String::new())),
                Some((l, t)) if l == lang => out.push(t),
                Some(_) => {}
            }
        } else if let Some((_, t)) = open.as_mut() {
            t.push_str(line);
            t.push('\n');
        }
    }
    out
}
