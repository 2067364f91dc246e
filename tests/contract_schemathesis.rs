//! The contract is exact: schemathesis (a real peer, pinned in tests/peers/schemathesis-requirements.txt and
//! installed by `scripts/install-peers.sh`) generates requests from the served `openapi.yaml`, valid and
//! invalid, sends them to a real server that requires a bearer token, and checks every answer against the
//! document: no 5xx, documented status codes, content types, headers and schemas, invalid data refused, valid
//! data accepted, and no route answering without the token. The run is reproducible (fixed seed) and bounded
//! (examples per operation), and must end with no failure.
//!
//! Without schemathesis (neither `.peers/venv/bin/schemathesis` nor one on `PATH`) the test prints one skip
//! line and passes, unless `CTRECON_REQUIRE_PEERS=1` (as CI sets), where it fails.

use crate::common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const TOKEN: &str = "contract-test-token-0123456789";
/// Examples per operation and phase; with the fixed seed the run is the same every time.
const MAX_EXAMPLES: u32 = 40;
const SEED: u64 = 20_261_125;
/// Longer than any run here has taken: a hung run fails instead of blocking CI.
const LIMIT: Duration = Duration::from_secs(600);

/// The schemathesis executable: the project's own (`scripts/install-peers.sh`), else one on `PATH`.
fn schemathesis() -> Option<PathBuf> {
    let own = Path::new(env!("CARGO_MANIFEST_DIR")).join(".peers/venv/bin/schemathesis");
    if own.is_file() {
        return Some(own);
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join("schemathesis"))
        .find(|p| p.is_file())
}

/// The last `n` lines of `text`.
fn tail(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn schemathesis_finds_no_difference_between_openapi_yaml_and_the_server() {
    let Some(exe) = schemathesis() else {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "schemathesis is missing and CTRECON_REQUIRE_PEERS=1: run scripts/install-peers.sh"
        );
        println!("skipped: schemathesis not found (run scripts/install-peers.sh)");
        return;
    };
    let app = common::spawn_app_with(|s| {
        s.api_tokens = vec![TOKEN.to_string()];
    })
    .await;
    let report = tempfile::tempdir().expect("temp dir");
    let peers = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers");
    let log = report.path().join("schemathesis.log");
    let started = Instant::now();
    let mut cmd = std::process::Command::new(&exe);
    cmd.arg("--config-file")
        .arg(peers.join("schemathesis.toml"))
        .arg("--no-color")
        .arg("run")
        .arg(app.url("/openapi.yaml"))
        .args(["--url", &app.base])
        .args(["--checks", "all"])
        .args(["--seed", &SEED.to_string()])
        .args(["--max-examples", &MAX_EXAMPLES.to_string()])
        .args(["--workers", "2"])
        .args(["--request-timeout", "60"])
        .args(["--generation-database", "none"])
        .args(["--header", &format!("Authorization: Bearer {TOKEN}")])
        .env("SCHEMATHESIS_HOOKS", peers.join("schemathesis_hooks.py"))
        .env("NO_COLOR", "1")
        .env("COLUMNS", "160")
        .current_dir(report.path())
        .stdin(std::process::Stdio::null())
        .stdout(std::fs::File::create(&log).expect("log file"))
        .stderr(std::fs::File::create(report.path().join("stderr.log")).expect("log file"));
    let mut child = cmd.spawn().expect("schemathesis starts");
    // The server runs on this runtime: wait for schemathesis off it.
    let status = tokio::task::spawn_blocking(move || {
        loop {
            if let Some(status) = child.try_wait().expect("schemathesis status") {
                return Some(status);
            }
            if started.elapsed() > LIMIT {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    })
    .await
    .expect("waiting for schemathesis");
    let stdout = std::fs::read_to_string(&log).unwrap_or_default();
    let stderr = std::fs::read_to_string(report.path().join("stderr.log")).unwrap_or_default();
    let Some(status) = status else {
        panic!("schemathesis ran past {LIMIT:?}:\n{}", tail(&stdout, 100));
    };
    println!(
        "schemathesis took {:.0} s; its summary:\n{}",
        started.elapsed().as_secs_f64(),
        tail(&stdout, 25)
    );
    assert!(
        status.success(),
        "schemathesis found differences (exit {:?}):\n{}\n{}",
        status.code(),
        tail(&stdout, 400),
        tail(&stderr, 40)
    );
    // "N generated, N passed, M skipped": every test case passed.
    let cases = stdout
        .lines()
        .find(|l| l.contains(" generated, "))
        .unwrap_or_default();
    assert!(
        cases.contains(" passed") && !cases.contains("fail") && !stdout.contains("Runtime Error"),
        "no clean summary:\n{}",
        tail(&stdout, 60)
    );
}
