//! The README's "Running on several machines" recipe, run as printed against a real PostgreSQL 15: its
//! `createuser` and `createdb` as the database's superuser would type them, then its exports and its three
//! `ctrecon` processes (an API-only server, a worker, a server that does both), each started in the
//! background as it would be on its own machine. Only addresses change: the database host and the
//! processes' addresses become free ports on 127.0.0.1 and the shared data directory a temporary one. A job
//! submitted to the API-only server is run by the others and read back from the third process.

use std::os::unix::process::CommandExt;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::cluster::{cluster, free_port};
use crate::common::readme_blocks;

/// Stops the block's process group (its `ctrecon` processes) when the test ends, however it ends.
struct Group(u32);

impl Drop for Group {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", "--", &format!("-{}", self.0)])
            .status();
    }
}

async fn get(client: &reqwest::Client, url: &str) -> Option<reqwest::Response> {
    client.get(url).send().await.ok()
}

async fn ready(client: &reqwest::Client, base: &str, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(r) = get(client, &format!("{base}/readyz")).await
            && r.status() == 200
        {
            return;
        }
        assert!(Instant::now() < deadline, "{base} is not ready");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_several_machines_recipe_runs_as_printed_on_postgresql() {
    let Some(pg) = cluster("docs: running on several machines") else {
        return;
    };
    let block = readme_blocks("console")
        .into_iter()
        .find(|b| b.contains("createuser ctrecon"))
        .expect("the README's several-machines block");
    let data = tempfile::tempdir().expect("temp dir");
    let (api, worker, both) = (free_port(), free_port(), free_port());
    let mut script = String::from("set -euo pipefail\n");
    for line in block.lines() {
        let line = line
            .replace("db.internal:5432", &format!("127.0.0.1:{}", pg.port))
            .replace("10.0.0.5:8080", &format!("127.0.0.1:{api}"))
            .replace("10.0.0.6:8081", &format!("127.0.0.1:{worker}"))
            .replace("127.0.0.1:8080", &format!("127.0.0.1:{both}"))
            .replace("/srv/ctrecon", &data.path().display().to_string());
        // Each `ctrecon` process runs on a machine of its own: here in the background.
        if line.trim_start().starts_with("ctrecon ") {
            let (command, comment) = line.split_once(" #").unwrap_or((&line, ""));
            script.push_str(&format!("{command} & #{comment}\n"));
        } else {
            script.push_str(&line);
            script.push('\n');
        }
    }
    script.push_str("wait\n");
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_ctrecon"))
        .parent()
        .expect("bin dir")
        .to_path_buf();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let log = std::fs::File::create(data.path().join("block.log")).expect("log");
    // The block's process group is killed when `_group` drops; the test ends right after, nothing to reap.
    #[allow(clippy::zombie_processes)]
    let child = Command::new("bash")
        .args(["-c", &script])
        .env("PATH", path)
        // The superuser's connection for createuser and createdb, as a DBA's shell has it.
        .env("PGHOST", "127.0.0.1")
        .env("PGPORT", pg.port.to_string())
        .env("PGUSER", "postgres")
        .stdin(Stdio::null())
        .stdout(log.try_clone().expect("log"))
        .stderr(log)
        .process_group(0)
        .spawn()
        .expect("bash runs the block");
    let _group = Group(child.id());
    let client = reqwest::Client::new();
    let base = |p: u16| format!("http://127.0.0.1:{p}");
    let log_text = || std::fs::read_to_string(data.path().join("block.log")).unwrap_or_default();
    for p in [api, worker, both] {
        let deadline = Instant::now() + Duration::from_secs(60);
        while get(&client, &format!("{}/healthz", base(p)))
            .await
            .is_none()
        {
            assert!(
                Instant::now() < deadline,
                "port {p} never answered; the block printed:\n{}",
                log_text()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        ready(&client, &base(p), 30).await;
    }
    // The worker answers health and metrics only.
    let r = get(&client, &format!("{}/v1/jobs", base(worker)))
        .await
        .expect("worker answers");
    assert_eq!(r.status(), 404);

    // A job submitted to the API-only process is run by the worker or the third process.
    let sim: Value = client
        .post(format!("{}/v1/simulations", base(api)))
        .json(&json!({"phantom": {"table": "shepp_logan", "scale_mm": 28},
                      "geometry": {"type": "parallel", "angles": {"count": 60},
                                   "det_count": 64, "det_spacing_mm": 1.0}}))
        .send()
        .await
        .expect("simulate")
        .json()
        .await
        .expect("json");
    let job: Value = client
        .post(format!("{}/v1/jobs", base(api)))
        .json(&json!({"input": sim["id"], "algorithm": {"name": "fbp"},
                      "grid": {"nx": 32, "ny": 32, "dx_mm": 2.0, "dy_mm": 2.0}}))
        .send()
        .await
        .expect("submit")
        .json()
        .await
        .expect("json");
    let id = job["id"].as_str().expect("job id").to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    let done = loop {
        let j: Value = client
            .get(format!("{}/v1/jobs/{id}", base(both)))
            .send()
            .await
            .expect("job")
            .json()
            .await
            .expect("json");
        if j["status"] == "succeeded" || j["status"] == "failed" {
            break j;
        }
        assert!(
            Instant::now() < deadline,
            "{j}\nthe block printed:\n{}",
            log_text()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1, "{done}");
    // The database is owned by the role of the URL, as the recipe says.
    let owner = Command::new("psql")
        .args(["-h", "127.0.0.1", "-U", "postgres", "-p"])
        .arg(pg.port.to_string())
        .args(["-At", "-d", "postgres", "-c"])
        .arg("SELECT pg_get_userbyid(datdba) FROM pg_database WHERE datname = 'ctrecon'")
        .output()
        .expect("psql");
    assert_eq!(String::from_utf8_lossy(&owner.stdout).trim(), "ctrecon");
}
