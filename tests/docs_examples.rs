//! Every example in README.md and docs/**/*.md runs as written. ```json blocks parse; geometries (an object
//! with a `type`) are accepted by the parser the server uses, down to per-view vectors, and so are the geometry
//! files under docs/; configuration files (```json config) load and validate as `serve --config` loads them. ```sh blocks are run by bash (`set -euo pipefail`, and `curl` answering an HTTP error
//! with a failure) in a fresh directory against a real `ctrecon serve` on a random port, with `ctrecon` on
//! the PATH, from an empty folder (nothing of the checkout is reachable but `$SERIES`, the folder of
//! LIDC-IDRI-0001 under `.testdata/` that the README's DICOM walk-throughs read); `localhost:8080` becomes
//! that port. Outputs shown as
//! `# {…}` comment lines must have their keys in what the block printed, in order. Set-up commands that build
//! or serve ctrecon itself are shown as ```console and are not run (this test is what they do).
//!
//! The shell examples need curl, jq and zip: without them the test prints one line and passes, unless `CI` is set.
//! Blocks reading `$SERIES` follow the test-data rule: skipped when it is absent, unless
//! `CTRECON_REQUIRE_TEST_DATA=1`.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Instant;

use ctrecon::config::Settings;
use ctrecon::recon::geometry::Geometry;
use serde_json::Value;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A fenced block: where it starts, its language and its text.
struct Block {
    at: String,
    lang: String,
    text: String,
}

fn markdown_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    let mut files = vec![root().join("README.md")];
    walk(&root().join("docs"), &mut files);
    files.sort();
    files
}

fn blocks() -> Vec<Block> {
    let mut out = Vec::new();
    for file in markdown_files() {
        let text = std::fs::read_to_string(&file).expect("a readable markdown file");
        let name = file
            .strip_prefix(root())
            .unwrap_or(&file)
            .display()
            .to_string();
        let mut open: Option<(usize, String, String)> = None;
        for (n, line) in text.lines().enumerate() {
            if let Some(fence) = line.trim_start().strip_prefix("```") {
                match open.take() {
                    None => open = Some((n + 1, fence.trim().to_string(), String::new())),
                    Some((start, lang, text)) => out.push(Block {
                        at: format!("{name}:{start}"),
                        lang,
                        text,
                    }),
                }
            } else if let Some((_, _, text)) = open.as_mut() {
                text.push_str(line);
                text.push('\n');
            }
        }
        assert!(open.is_none(), "{name}: a code block is not closed");
    }
    out
}

fn check_geometry(v: Value, at: &str) {
    let g: Geometry = serde_json::from_value(v).unwrap_or_else(|e| panic!("{at}: {e}"));
    g.to_views().unwrap_or_else(|e| panic!("{at}: {e}"));
}

/// A ctrecon configuration file, loaded as `ctrecon serve --config` loads it (unknown keys refused) and
/// validated as at start.
fn check_config(text: &str, at: &str) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("ctrecon.json");
    std::fs::write(&path, text).expect("config written");
    let settings =
        Settings::load(Some(&path), std::iter::empty()).unwrap_or_else(|e| panic!("{at}: {e}"));
    settings.validate().unwrap_or_else(|e| panic!("{at}: {e}"));
}

/// What every ```json block is: a geometry (an object with a `type`), a ctrecon configuration file (```json
/// config, or ```json pacs-config for the one the PACS walkthrough runs), or an Orthanc configuration (```json
/// orthanc). A block that is none of them fails, so no example escapes its check.
#[test]
fn every_json_example_parses_and_every_geometry_and_configuration_is_accepted() {
    let (mut geometries, mut configs, mut orthanc) = (0, 0, 0);
    for b in blocks().iter().filter(|b| b.lang.starts_with("json")) {
        let v: Value = serde_json::from_str(&b.text).unwrap_or_else(|e| panic!("{}: {e}", b.at));
        match b.lang.as_str() {
            "json" if v.get("type").is_some() => {
                check_geometry(v, &b.at);
                geometries += 1;
            }
            "json config" | "json pacs-config" => {
                check_config(&b.text, &b.at);
                configs += 1;
            }
            "json orthanc" => {
                assert!(
                    v.get("DicomWeb").is_some() || v.get("DicomModalities").is_some(),
                    "{}: an Orthanc configuration names its DicomWeb or DicomModalities",
                    b.at
                );
                orthanc += 1;
            }
            other => panic!(
                "{}: a ```{other} block that is neither a geometry nor tagged `json config` or \
                 `json orthanc`",
                b.at
            ),
        }
    }
    // The README shows parallel, fan (arc and flat), cone and fan_matlab geometries, the object-storage,
    // DICOM node and web-peer configurations, and Orthanc's DICOMweb client entry.
    assert!(geometries >= 5, "only {geometries} geometry examples found");
    assert!(configs >= 3, "only {configs} configuration examples found");
    assert!(orthanc >= 1, "no Orthanc configuration example found");
    // A key a configuration does not know is refused, as `serve --config` refuses it.
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("bad.json");
    std::fs::write(&path, r#"{"storage": {"url": "s3://b/p", "colour": 1}}"#).expect("written");
    assert!(Settings::load(Some(&path), std::iter::empty()).is_err());
    let dir = root().join("docs/geometries");
    let mut files = 0;
    for e in std::fs::read_dir(&dir).expect("docs/geometries").flatten() {
        let text = std::fs::read_to_string(e.path()).expect("a geometry file");
        let v: Value = serde_json::from_str(&text).unwrap_or_else(|e2| panic!("{e:?}: {e2}"));
        check_geometry(v, &e.path().display().to_string());
        files += 1;
    }
    assert!(files >= 3);
    // Unknown fields are still refused, fan_matlab included.
    let bad = r#"{"type": "fan_matlab", "rows": 8, "cols": 8, "d_px": 20, "sensor_geometry": "arc",
                  "sensor_spacing": 1, "colour": 1}"#;
    assert!(serde_json::from_str::<Geometry>(bad).is_err());
}

/// A `ctrecon serve` child process, killed when dropped.
struct Server {
    child: Child,
    port: u16,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Start the binary on a random port with `env`; returns once it prints the line it listens on.
/// The server's log (stderr) goes to `<data_dir>.log`, so that a failing example can show what the
/// server answered.
fn serve(data_dir: &Path, env: &[(&str, &str)]) -> Server {
    let log = std::fs::File::create(data_dir.with_extension("log")).expect("a log file");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_ctrecon"));
    cmd.args(["serve", "--bind", "127.0.0.1:0", "--data-dir"])
        .arg(data_dir)
        .env("CTRECON_LOG_FORMAT", "json")
        .stdout(Stdio::piped())
        .stderr(log);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().expect("ctrecon starts");
    let stdout = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("a first line");
    let port = line.trim().rsplit(':').next().and_then(|p| p.parse().ok());
    let Some(port) = port else {
        let _ = child.kill();
        let status = child.wait();
        panic!("ctrecon serve did not start ({status:?}): {line:?}");
    };
    Server { child, port }
}

#[test]
fn every_documented_environment_variable_lets_serve_start() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = serve(
        dir.path(),
        &[
            ("CTRECON_SIMD", "avx2"),
            ("CTRECON_LOG_FORMAT", "json"),
            ("CTRECON_REQUIRE_TEST_DATA", "0"),
            ("CTRECON_BENCH_CONE", "1"),
            ("CTRECON_MAX_ATTEMPTS", "2"),
        ],
    );
    let s = std::net::TcpStream::connect(("127.0.0.1", server.port));
    assert!(s.is_ok(), "{s:?}");
}

/// True when bash finds every one of `tools`.
fn have(tools: &str) -> bool {
    Command::new("bash")
        .args(["-c", &format!("command -v {tools}")])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// The keys of the JSON object on a `# {…}` output line, in order.
fn expected_keys(line: &str) -> Option<Vec<String>> {
    let rest = line.trim_start().strip_prefix("# {")?;
    let mut keys = Vec::new();
    let mut depth = 0usize;
    let mut chars = rest.char_indices().peekable();
    while let Some((i, c)) = chars.next() {
        match c {
            '{' | '[' => depth += 1,
            '}' | ']' if depth == 0 => break,
            '}' | ']' => depth -= 1,
            '"' => {
                let end = rest[i + 1..].find('"')? + i + 1;
                if depth == 0 && rest[end + 1..].starts_with(':') {
                    keys.push(rest[i + 1..end].to_string());
                }
                while chars.peek().is_some_and(|&(j, _)| j <= end) {
                    chars.next();
                }
            }
            _ => {}
        }
    }
    Some(keys)
}

/// Each `# {…}` line's keys appear, as `"key":`, in `out` after those of the line before.
fn check_outputs(block: &Block, out: &str) {
    let mut from = 0;
    for line in block.text.lines() {
        let Some(keys) = expected_keys(line) else {
            continue;
        };
        let mut first = None;
        for k in &keys {
            let pat = format!("\"{k}\":");
            let at = out[from..]
                .find(&pat)
                .unwrap_or_else(|| panic!("{}: no `{pat}` for `{line}` in:\n{out}", block.at));
            first.get_or_insert(from + at);
        }
        from = first.map_or(from, |f| f + 1);
    }
}

#[test]
fn every_shell_example_runs_against_a_real_server() {
    if !have("curl jq zip") {
        assert!(
            std::env::var_os("CI").is_none(),
            "curl, jq and zip are needed by the shell examples (CI installs them)"
        );
        println!("skipped: the shell examples need curl, jq and zip");
        return;
    }
    let testdata = root().join(".testdata/lidc");
    let required = std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() == Ok("1");
    let dir = tempfile::tempdir().expect("temp dir");
    let bin = dir.path().join("bin");
    std::fs::create_dir(&bin).expect("bin dir");
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_ctrecon"), bin.join("ctrecon")).expect("link");
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let server = serve(&dir.path().join("data"), &[]);
    let port = server.port.to_string();
    let mut ran = 0;
    for (n, b) in blocks().iter().enumerate().filter(|(_, b)| b.lang == "sh") {
        if b.text.contains("$SERIES") && !testdata.is_dir() {
            assert!(
                !required,
                "{}: .testdata/lidc is missing and CTRECON_REQUIRE_TEST_DATA=1",
                b.at
            );
            println!("skipped {}: .testdata/lidc is missing", b.at);
            continue;
        }
        // An empty folder of its own: a block may not assume it runs in the checkout.
        let work = dir.path().join(format!("block-{n}"));
        std::fs::create_dir(&work).expect("work dir");
        let script = format!(
            "set -euo pipefail\ncurl() {{ command curl --fail-with-body \"$@\"; }}\n{}",
            b.text
                .replace("localhost:8080", &format!("localhost:{port}"))
        );
        let started = Instant::now();
        // Five minutes bound a hang; the whole test takes well under that.
        let out = Command::new("timeout")
            .args(["300", "bash", "-c"])
            .arg(&script)
            .current_dir(&work)
            .env("PATH", &path)
            .env("SERIES", &testdata)
            .output()
            .expect("bash runs");
        let stdout = String::from_utf8_lossy(&out.stdout);
        println!(
            "{} ran in {:.1} s:\n{stdout}",
            b.at,
            started.elapsed().as_secs_f64()
        );
        if !out.status.success() {
            // What the server answered last: the requests that ended with an error, and its warnings.
            let log = std::fs::read_to_string(dir.path().join("data.log")).unwrap_or_default();
            let tail: Vec<&str> = log
                .lines()
                .filter(|l| {
                    ["\"WARN\"", "\"ERROR\"", "request refused"]
                        .iter()
                        .any(|s| l.contains(s))
                })
                .collect();
            println!(
                "server log, warnings, errors and refused requests (last 40):\n{}",
                tail[tail.len().saturating_sub(40)..].join("\n")
            );
        }
        assert!(
            out.status.success(),
            "{} failed ({}):\n{stdout}\n{}",
            b.at,
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        check_outputs(b, &stdout);
        ran += 1;
    }
    assert!(ran >= 3, "only {ran} shell examples ran");
    // The server is still there after every example.
    assert!(std::net::TcpStream::connect(("127.0.0.1", server.port)).is_ok());
}
