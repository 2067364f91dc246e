//! A web frontend's developer generates a client from `openapi.yaml` and uses it: `openapi-typescript`
//! (npm) turns the document into TypeScript types, `tsc` type-checks `tests/peers/ts-client/client.ts`
//! against them, and the compiled client (through `openapi-fetch`) simulates a scan, submits an FBP job,
//! follows it to its end and reads a slice and the metrics from a real server. The node packages are
//! installed into `tests/peers/ts-client/node_modules` by `scripts/install-peers.sh ts-client`; without
//! them (or without Node.js) the test prints one skip line, or fails under `CTRECON_REQUIRE_PEERS=1`.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::spawn_app_with;
use serde_json::Value;

const TOKEN: &str = "generated-client-token";

fn client_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/ts-client")
}

/// The installed packages, or `None` after one skip line.
fn installed() -> Option<PathBuf> {
    let modules = client_dir().join("node_modules");
    let node = Command::new("node").arg("--version").output().is_ok();
    let ok = node
        && ["openapi-typescript", "openapi-fetch", "typescript"]
            .iter()
            .all(|p| modules.join(p).join("package.json").is_file());
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "Node.js or the generated-client packages are missing and CTRECON_REQUIRE_PEERS=1 \
             (scripts/install-peers.sh ts-client)"
        );
        eprintln!(
            "skipped: Node.js or tests/peers/ts-client/node_modules is missing (scripts/install-peers.sh ts-client)"
        );
        return None;
    }
    Some(modules)
}

fn run(cmd: &mut Command, what: &str) -> String {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{what}: cannot start: {e}"));
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// Every `operationId` of the document, in order.
fn operation_ids(yaml: &str) -> Vec<String> {
    yaml.lines()
        .filter_map(|l| l.strip_prefix("      operationId: "))
        .map(|s| s.trim().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_generated_from_the_contract_submits_follows_and_reads_a_job() {
    let Some(modules) = installed() else {
        return;
    };
    let work = tempfile::tempdir().expect("temp dir");
    for f in ["client.ts", "tsconfig.json", "package.json"] {
        std::fs::copy(client_dir().join(f), work.path().join(f)).expect("copy the client");
    }
    std::os::unix::fs::symlink(&modules, work.path().join("node_modules")).expect("link modules");

    // 1. Generate the types, as the README's "A generated client" shows.
    let spec = Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi.yaml");
    run(
        Command::new("node")
            .arg(modules.join("openapi-typescript/bin/cli.js"))
            .arg(&spec)
            .args(["--default-non-nullable", "false", "-o", "gen/api.d.ts"])
            .current_dir(work.path()),
        "openapi-typescript",
    );
    // The command is the README's.
    assert!(
        include_str!("../README.md").contains(
            "$ npx openapi-typescript openapi.yaml --default-non-nullable false -o gen/api.d.ts\n"
        ),
        "README.md shows the generation command this test runs"
    );
    let generated =
        std::fs::read_to_string(work.path().join("gen/api.d.ts")).expect("generated types");
    // Every operation is a named entry of `operations` (none is left anonymous).
    let ops = generated
        .split("export interface operations {")
        .nth(1)
        .expect("an operations interface");
    let ids = operation_ids(include_str!("../openapi.yaml"));
    assert!(ids.len() >= 50, "{} operationIds", ids.len());
    for id in &ids {
        assert!(
            ops.contains(&format!("\n    {id}: {{")),
            "operations lacks {id}"
        );
    }

    // 2. Type-check and compile the client against them.
    run(
        Command::new("node")
            .arg(modules.join("typescript/bin/tsc"))
            .args(["-p", "."])
            .current_dir(work.path()),
        "tsc",
    );

    // 3. Run it against a real server.
    let app = spawn_app_with(|s| s.api_tokens = vec![TOKEN.into()]).await;
    let base = app.base.clone();
    let dir = work.path().to_path_buf();
    let out = tokio::task::spawn_blocking(move || {
        run(
            Command::new("node")
                .args(["build/client.js", &base, TOKEN])
                .current_dir(dir),
            "the generated client",
        )
    })
    .await
    .expect("client thread");
    let seen: Value = serde_json::from_str(out.trim()).expect("one JSON line");
    assert_eq!(seen["status"], "succeeded", "{seen}");
    assert_eq!(seen["png_signature"], "PNG", "{seen}");
    assert_eq!(seen["content_type"], "image/png", "{seen}");
    assert_eq!(
        (seen["png_width"].as_u64(), seen["png_height"].as_u64()),
        (Some(128), Some(128))
    );
    // FBP (Hann) of the exact parallel projections of Shepp–Logan on a 1.6 mm grid.
    let rmse = seen["metrics"]["rmse"].as_f64().expect("rmse");
    assert!(rmse > 0.0 && rmse < 0.1, "{seen}");
    assert_eq!(seen["missing_status"], 404, "{seen}");
    assert_eq!(seen["missing_code"], "job_not_found", "{seen}");
    // What the client did is what the server holds.
    let job: Value = app
        .client
        .get(app.url(&format!(
            "/v1/jobs/{}",
            seen["job"].as_str().expect("job id")
        )))
        .bearer_auth(TOKEN)
        .send()
        .await
        .expect("job")
        .json()
        .await
        .expect("json");
    assert_eq!(job["input"], seen["dataset"], "{job}");
    assert_eq!(job["status"], "succeeded", "{job}");
}
