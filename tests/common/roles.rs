//! `ctrecon` processes in their roles, for the tests that run several of them: `serve --workers 0` (an API
//! that runs no jobs) and `ctrecon worker` (jobs only, with a health port), started from a prepared
//! [`Command`] and killed when dropped; their metrics, which of them runs a job, and the job bodies these
//! tests submit.
//!
//! A process's log goes nowhere unless `CTRECON_TEST_LOGS=1`, where it goes to the test's stderr.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

/// A `ctrecon` child process (`serve` or `worker`); killed when dropped.
pub struct Process {
    pub child: Child,
    /// `http://host:port` of its API or health port.
    pub base: String,
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Process {
    /// Send signal `name` (`KILL`, `TERM`).
    pub fn signal(&self, name: &str) {
        let ok = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .expect("kill runs")
            .success();
        assert!(ok, "kill -{name}");
    }

    /// Wait for the process to end, at most `secs` seconds.
    pub async fn exit_within(&mut self, secs: u64) -> ExitStatus {
        let t = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().expect("wait") {
                return s;
            }
            assert!(
                t.elapsed() < Duration::from_secs(secs),
                "the process did not end within {secs} s"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// The value of an unlabelled metric, or the sum over the series of a labelled one whose labels contain
    /// `labels`.
    pub async fn metric(&self, name: &str, labels: &str) -> f64 {
        let text = crate::common::attach(&self.base)
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
}

/// `ctrecon` with the settings every multi-process test uses: leases of 1 s, progress written every 50 ms,
/// a drain of at most 2 s, and no database or storage from the environment.
pub fn ctrecon() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_ctrecon"));
    c.env("CTRECON_LEASE_SECS", "1")
        .env("CTRECON_PROGRESS_INTERVAL_MS", "50")
        .env("CTRECON_DRAIN_TIMEOUT_MS", "2000")
        .env_remove("CTRECON_DATABASE_URL")
        .env_remove("CTRECON_STORAGE_URL")
        .env_remove("CTRECON_TEST_LOGS");
    c
}

/// `ctrecon` on data directory `dir` and the PostgreSQL database `url`.
pub fn on(dir: &Path, url: &str) -> Command {
    let mut c = ctrecon();
    c.env("CTRECON_DATA_DIR", dir)
        .env("CTRECON_DATABASE_URL", url);
    c
}

/// Run `c ARGS`; returns once it printed `ready_prefix` and the address after it.
pub fn start(mut c: Command, args: &[&str], ready_prefix: &str) -> Process {
    let logs = std::env::var("CTRECON_TEST_LOGS").as_deref() == Ok("1");
    let mut child = c
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(if logs {
            Stdio::inherit()
        } else {
            Stdio::null()
        })
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

/// An API process that runs no jobs, listening on a free port of 127.0.0.1.
pub fn api(c: Command) -> Process {
    start(
        c,
        &["serve", "--bind", "127.0.0.1:0", "--workers", "0"],
        "ctrecon listening on ",
    )
}

/// A worker running one job at a time on one thread, its health port on a free port of `host`.
pub fn worker(c: Command, host: &str) -> Process {
    start(
        c,
        &[
            "worker",
            "--health-bind",
            &format!("{host}:0"),
            "--workers",
            "1",
            "--threads",
            "1",
        ],
        "ctrecon worker health on ",
    )
}

/// The one worker of `workers` running a job now (by its `ctrecon_jobs_running_here`), waiting up to `secs`.
pub async fn runner(workers: &[&Process], secs: u64) -> usize {
    let until = Instant::now() + Duration::from_secs(secs);
    loop {
        let mut busy = Vec::new();
        for (i, w) in workers.iter().enumerate() {
            if w.metric("ctrecon_jobs_running_here", "").await >= 1.0 {
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

pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

pub fn sha256_of(path: &Path) -> String {
    sha256_hex(&std::fs::read(path).expect("a file to hash"))
}

/// 2D FBP of a parallel-beam dataset onto 64 × 64 pixels of 1 mm.
pub fn fbp(input: &str) -> Value {
    json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}, "outputs": ["volume", "metrics"]})
}

/// 2D SIRT of a parallel-beam dataset onto 64 × 64 pixels: `iterations` set how long it runs (it reports
/// progress after each).
pub fn sirt(input: &str, iterations: u32) -> Value {
    json!({"input": input, "algorithm": {"name": "sirt", "iterations": iterations},
           "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}, "outputs": ["volume", "metrics"]})
}

/// FDK of a cone-beam dataset onto `n³` voxels of 1 mm.
pub fn fdk(input: &str, n: usize) -> Value {
    json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
           "grid": {"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]},
           "outputs": ["volume", "metrics"]})
}
