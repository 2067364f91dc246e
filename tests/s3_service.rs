//! The service on S3 object storage: an API process (`serve --workers 0`) and two `ctrecon worker` processes,
//! each with a data directory of its own, share a PostgreSQL job database and an S3 server that checks SigV4
//! signatures (s3s-fs). Datasets uploaded to the API reach the workers through the bucket, results made by
//! the workers are served by the API straight from it (ranges too), a worker killed in mid-job leaves no
//! partial object and the job finishes on the other one, and deleting a job removes its objects. Wrong
//! credentials and a missing bucket stop the start with the reason. `compose.yaml` names only variables the
//! service reads.
//!
//! Without PostgreSQL or s3s-fs (`scripts/install-peers.sh postgres s3`) a test prints one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1`, where it fails.

#[path = "common/postgres.rs"]
mod cluster;
mod common;

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{TestApp, cone_geometry, parallel_geometry};
use serde_json::{Value, json};
use sha2::Digest;

const ACCESS_KEY: &str = "ctrecon-svc";
const SECRET_KEY: &str = "ctrecon-svc-secret";
const BUCKET: &str = "ctrecon-svc";
const PREFIX: &str = "site-a";

/// An s3s-fs process with its own root and port, stopped on drop.
struct S3Server {
    child: Child,
    endpoint: String,
    root: tempfile::TempDir,
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl S3Server {
    /// The file s3s-fs keeps object `key` of the bucket in.
    fn object_file(&self, key: &str) -> PathBuf {
        self.root
            .path()
            .join(BUCKET)
            .join(PREFIX)
            .join(key.replace('/', std::path::MAIN_SEPARATOR_STR))
    }
}

fn s3s_fs() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("CTRECON_S3S_FS") {
        return Some(PathBuf::from(p));
    }
    let local = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".peers/s3s/bin/s3s-fs");
    if local.is_file() {
        return Some(local);
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("s3s-fs"))
            .find(|p| p.is_file())
    })
}

/// Start s3s-fs with one bucket, or say why not (one skip line; a failure when peers are required).
fn s3(test: &str) -> Option<S3Server> {
    let Some(bin) = s3s_fs() else {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "{test}: s3s-fs is missing and CTRECON_REQUIRE_PEERS=1 (scripts/install-peers.sh s3)"
        );
        eprintln!("skipped {test}: s3s-fs is not installed (scripts/install-peers.sh s3)");
        return None;
    };
    let root = tempfile::tempdir().expect("temp dir");
    std::fs::create_dir(root.path().join(BUCKET)).expect("bucket directory");
    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let child = Command::new(bin)
        .args(["--host", "127.0.0.1", "--port", &port.to_string()])
        .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
        .arg(root.path())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("s3s-fs starts");
    let server = S3Server {
        child,
        endpoint: format!("http://127.0.0.1:{port}"),
        root,
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "s3s-fs did not listen");
        std::thread::sleep(Duration::from_millis(10));
    }
    Some(server)
}

/// A `ctrecon` child process; killed when dropped.
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

/// `ctrecon ARGS` with data directory `dir`, the bucket of `s3` (credentials `secret`, bucket `bucket`) and,
/// if given, the PostgreSQL database `url`.
fn command(dir: &Path, url: Option<&str>, s3: &S3Server, bucket: &str, secret: &str) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_ctrecon"));
    c.env("CTRECON_DATA_DIR", dir)
        .env("CTRECON_STORAGE_URL", format!("s3://{bucket}/{PREFIX}"))
        .env("CTRECON_STORAGE_ENDPOINT", &s3.endpoint)
        .env("AWS_ACCESS_KEY_ID", ACCESS_KEY)
        .env("AWS_SECRET_ACCESS_KEY", secret)
        .env("AWS_REGION", "us-east-1")
        .env("CTRECON_LEASE_SECS", "1")
        .env("CTRECON_PROGRESS_INTERVAL_MS", "50")
        .env("CTRECON_DRAIN_TIMEOUT_MS", "2000")
        .env_remove("CTRECON_DATABASE_URL");
    if let Some(url) = url {
        c.env("CTRECON_DATABASE_URL", url);
    }
    c
}

fn start(mut c: Command, args: &[&str], ready_prefix: &str) -> Process {
    let mut child = c
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
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

fn worker(dir: &Path, url: &str, s3: &S3Server) -> Process {
    start(
        command(dir, Some(url), s3, BUCKET, SECRET_KEY),
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

fn sha256_hex(bytes: &[u8]) -> String {
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The value of an unlabelled metric (summed over its series).
async fn metric(p: &Process, name: &str) -> f64 {
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
            (key == name || key.starts_with(&format!("{name}{{")))
                .then(|| value.parse::<f64>().ok())
                .flatten()
        })
        .sum()
}

fn fbp(input: &str) -> Value {
    json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}, "outputs": ["volume", "metrics"]})
}

fn fdk(input: &str, n: usize) -> Value {
    json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
           "grid": {"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]},
           "outputs": ["volume", "metrics"]})
}

/// The whole body of a GET, asserting `status`.
async fn body(client: &TestApp, path: &str, range: Option<&str>, status: u16) -> Vec<u8> {
    let mut req = client.client.get(client.url(path));
    if let Some(r) = range {
        req = req.header("range", r);
    }
    let r = req.send().await.expect("request");
    assert_eq!(r.status(), status, "GET {path} {range:?}");
    r.bytes().await.expect("body").to_vec()
}

/// Files under `dir` (relative, sorted), for "what is here" assertions.
fn files_under(dir: &Path) -> Vec<String> {
    fn walk(base: &Path, d: &Path, out: &mut Vec<String>) {
        let Ok(entries) = std::fs::read_dir(d) else {
            return;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(base, &p, out);
            } else if let Ok(rel) = p.strip_prefix(base) {
                out.push(rel.to_string_lossy().into_owned());
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_an_api_and_two_workers_with_their_own_directories_share_datasets_and_results() {
    let test = "s3_api_and_two_workers";
    let Some(url) = cluster::database_url(test) else {
        return;
    };
    let Some(s3) = s3(test) else {
        return;
    };
    let (api_dir, w1_dir, w2_dir) = (
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
    );
    let a = start(
        command(api_dir.path(), Some(&url), &s3, BUCKET, SECRET_KEY),
        &["serve", "--bind", "127.0.0.1:0", "--workers", "0"],
        "ctrecon listening on ",
    );
    let client = common::attach(&a.base);
    let mut workers = [
        Some(worker(w1_dir.path(), &url, &s3)),
        Some(worker(w2_dir.path(), &url, &s3)),
    ];

    // A dataset made on the API host is in the bucket before its 201.
    let flat = client.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let dataset_key = format!("datasets/{flat}.npy");
    let local = std::fs::read(api_dir.path().join(&dataset_key)).expect("the API's copy");
    let object = std::fs::read(s3.object_file(&dataset_key)).expect("the dataset's object");
    assert_eq!(sha256_hex(&object), sha256_hex(&local));

    // Jobs run on the workers, which fetch the dataset from the bucket into their own directories.
    let mut ids = Vec::new();
    for _ in 0..4 {
        let job = client.submit(&fbp(&flat)).await;
        ids.push(job["id"].as_str().expect("id").to_string());
    }
    let mut first_sha = None;
    for id in &ids {
        let done = client.finish(id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert!(
            done["result"]["metrics"]["rmse"].as_f64().expect("rmse") < 0.1,
            "{done}"
        );
        let sha = done["result"]["volume"]["sha256"]
            .as_str()
            .expect("sha")
            .to_string();
        // The same input and parameters give the same bytes on either worker.
        assert_eq!(first_sha.get_or_insert_with(|| sha.clone()), &sha);
        let key = format!("results/{id}/volume.npy");
        let object = std::fs::read(s3.object_file(&key)).expect("the volume's object");
        assert_eq!(sha256_hex(&object), sha);
        // The API host never had the result: it serves it from the bucket, whole and by range.
        assert!(!api_dir.path().join(&key).exists());
        let whole = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            None,
            200,
        )
        .await;
        assert_eq!(sha256_hex(&whole), sha);
        let part = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            Some("bytes=1000-5095"),
            206,
        )
        .await;
        assert_eq!(part, whole[1000..5096]);
        let tail = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            Some("bytes=-100"),
            206,
        )
        .await;
        assert_eq!(tail, whole[whole.len() - 100..]);
    }
    let mut fetched_by = 0;
    for d in [&w1_dir, &w2_dir] {
        if d.path().join(&dataset_key).exists() {
            fetched_by += 1;
            let copy = std::fs::read(d.path().join(&dataset_key)).expect("copy");
            assert_eq!(sha256_hex(&copy), sha256_hex(&local));
        }
    }
    assert!(fetched_by >= 1, "a worker fetched the dataset");

    // SIGKILL in mid-job: the other worker finishes it after the lease; the bucket holds one complete
    // result and no part of the killed attempt.
    let cone = client.simulate(cone_geometry(180, 96), 32.0).await;
    let job = client.submit(&fdk(&cone, 128)).await;
    let id = job["id"].as_str().expect("id").to_string();
    client
        .wait_until(&id, 300, |j| {
            j["status"] == "running" && j["progress"].as_u64() > Some(2)
        })
        .await;
    let mut busy = None;
    let until = Instant::now() + Duration::from_secs(30);
    while busy.is_none() {
        for (i, w) in workers.iter().enumerate() {
            if let Some(w) = w
                && metric(w, "ctrecon_jobs_running_here").await >= 1.0
            {
                busy = Some(i);
            }
        }
        assert!(Instant::now() < until, "no worker runs the job");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let idx = busy.expect("a busy worker");
    if let Some(mut w) = workers[idx].take() {
        w.child.kill().expect("SIGKILL");
        let _ = w.child.wait();
    }
    let done = client.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 2, "{done}");
    let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
    let objects = files_under(&s3.object_file(&format!("results/{id}")));
    assert_eq!(objects, ["metrics.json", "volume.npy"], "{objects:?}");
    let object =
        std::fs::read(s3.object_file(&format!("results/{id}/volume.npy"))).expect("object");
    assert_eq!(sha256_hex(&object), sha);
    let whole = body(
        &client,
        &format!("/v1/jobs/{id}/result/volume.npy"),
        None,
        200,
    )
    .await;
    assert_eq!(sha256_hex(&whole), sha);
    // 128³ float32 and the .npy header.
    assert!(whole.len() > 128 * 128 * 128 * 4, "{}", whole.len());

    // Deleting a job removes its objects; deleting a dataset removes its object.
    let r = client
        .client
        .delete(client.url(&format!("/v1/jobs/{}", ids[0])))
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 204);
    assert!(files_under(&s3.object_file(&format!("results/{}", ids[0]))).is_empty());
    assert!(
        s3.object_file(&format!("results/{}/volume.npy", ids[1]))
            .exists()
    );
    let r = client
        .client
        .delete(client.url(&format!("/v1/datasets/{cone}")))
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 204);
    assert!(!s3.object_file(&format!("datasets/{cone}.npy")).exists());
    assert!(s3.object_file(&dataset_key).exists());
}

/// Run `ctrecon serve` (SQLite) against the bucket with these credentials; it must stop at once, saying why.
fn refused_start(s3: &S3Server, bucket: &str, secret: &str) -> String {
    let dir = tempfile::tempdir().expect("dir");
    let started = Instant::now();
    let out = command(dir.path(), None, s3, bucket, secret)
        .args(["serve", "--bind", "127.0.0.1:0"])
        .output()
        .expect("ctrecon runs");
    assert!(!out.status.success(), "must not start");
    assert!(out.stdout.is_empty(), "never listened");
    assert!(started.elapsed() < Duration::from_secs(60));
    // No job database row was taken: nothing in the data directory's blob folders.
    assert!(files_under(&dir.path().join("results")).is_empty());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn s3_wrong_credentials_and_a_missing_bucket_stop_the_start_with_the_reason() {
    let Some(s3) = s3("s3_bad_configuration") else {
        return;
    };
    let e = refused_start(&s3, BUCKET, "not-the-secret");
    assert!(
        e.contains("object storage") && e.contains("refused the credentials"),
        "{e}"
    );
    let e = refused_start(&s3, "no-such-bucket", SECRET_KEY);
    assert!(
        e.contains("object storage") && e.contains("bucket does not exist"),
        "{e}"
    );
    // And the right ones work: the same command starts and listens.
    let dir = tempfile::tempdir().expect("dir");
    let p = start(
        command(dir.path(), None, &s3, BUCKET, SECRET_KEY),
        &["serve", "--bind", "127.0.0.1:0"],
        "ctrecon listening on ",
    );
    assert!(p.base.starts_with("http://127.0.0.1:"));
}

#[test]
fn compose_names_only_variables_the_service_reads() {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/compose.yaml"))
        .expect("compose.yaml");
    let names = |prefix: &str| -> Vec<String> {
        let mut out: Vec<String> = text
            .match_indices(prefix)
            .map(|(at, _)| {
                text[at..]
                    .chars()
                    .take_while(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || *c == '_')
                    .collect()
            })
            .collect();
        out.sort();
        out.dedup();
        out
    };
    let ours = names("CTRECON_");
    for needed in [
        "CTRECON_DATABASE_URL",
        "CTRECON_STORAGE_URL",
        "CTRECON_STORAGE_ENDPOINT",
        "CTRECON_DATA_DIR",
    ] {
        assert!(ours.iter().any(|n| n == needed), "{needed} in {ours:?}");
    }
    for name in &ours {
        let value = match name.as_str() {
            "CTRECON_BIND" => "0.0.0.0:8080",
            "CTRECON_DATABASE_URL" => "postgres://ctrecon@postgres:5432/ctrecon",
            "CTRECON_STORAGE_URL" => "s3://ctrecon/site",
            "CTRECON_STORAGE_ENDPOINT" => "http://s3:9000",
            "CTRECON_ALLOW_INSECURE" => "true",
            "CTRECON_DATA_DIR" => "/data",
            _ => "1",
        };
        let s = ctrecon::config::Settings::load(None, [(name.clone(), value.to_string())]);
        assert!(s.is_ok(), "{name}: {:?}", s.err());
    }
    #[cfg(feature = "s3")]
    for name in names("AWS_") {
        assert!(
            ctrecon::storage::object::AWS_VARIABLES.contains(&name.as_str()),
            "{name} is not read by the S3 adapter"
        );
    }
}
