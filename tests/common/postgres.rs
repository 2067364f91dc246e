//! A throwaway PostgreSQL cluster for the tests of one test binary: `initdb` in a temporary directory, its
//! own port on 127.0.0.1, started once on first use and stopped (and removed) by a watchdog when the test
//! process exits. Each test gets a database of its own ([`database_url`]).
//!
//! Without PostgreSQL (no `initdb`) a test prints one skip line and returns, unless
//! `CTRECON_REQUIRE_PEERS=1`, where it fails. As root the server runs as the `postgres` user (`runuser`).
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;

pub struct Cluster {
    pub port: u16,
}

/// The directory of the PostgreSQL server programs, if installed.
fn bindir() -> Option<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .ok()?
        .filter_map(|e| e.ok())
        .map(|e| e.path().join("bin"))
        .filter(|b| b.join("initdb").exists() && b.join("pg_ctl").exists())
        .collect();
    found.sort();
    found.pop()
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

/// `program args…`, as the `postgres` user when we are root.
fn as_server_user(program: &Path) -> Command {
    if is_root() {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(program);
        c
    } else {
        Command::new(program)
    }
}

include!("ports.rs");

fn run(mut c: Command, what: &str) -> Result<(), String> {
    let out = c.output().map_err(|e| format!("{what}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{what}: {}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// Start a cluster listening on 127.0.0.1 and on `also` (an address of this host and the network whose
/// clients it trusts, as `10.1.2.1` and `10.1.2.0/24`), if given.
fn start_listening(also: Option<(&str, &str)>) -> Result<Cluster, String> {
    let bin =
        bindir().ok_or("PostgreSQL is not installed (no /usr/lib/postgresql/*/bin/initdb)")?;
    let root = tempfile::Builder::new()
        .prefix("ctrecon-pg-")
        .tempdir_in("/tmp")
        .map_err(|e| e.to_string())?
        .keep();
    let data = root.join("data");
    if is_root() {
        run(
            {
                let mut c = Command::new("chmod");
                c.arg("0755").arg(&root);
                c
            },
            "chmod",
        )?;
        run(
            {
                let mut c = Command::new("chown");
                c.arg("postgres:postgres").arg(&root);
                c
            },
            "chown",
        )?;
    }
    let mut init = as_server_user(&bin.join("initdb"));
    init.arg("-D").arg(&data).args([
        "-U",
        "postgres",
        "-A",
        "trust",
        "-E",
        "UTF8",
        "--locale=C.UTF-8",
    ]);
    run(init, "initdb")?;
    let mut listen = "127.0.0.1".to_string();
    if let Some((addr, net)) = also {
        listen = format!("{listen},{addr}");
        let hba = data.join("pg_hba.conf");
        let mut text = std::fs::read_to_string(&hba).map_err(|e| format!("pg_hba.conf: {e}"))?;
        text.push_str(&format!("host all all {net} trust\n"));
        std::fs::write(&hba, text).map_err(|e| format!("pg_hba.conf: {e}"))?;
    }
    let port = free_port();
    let mut ctl = as_server_user(&bin.join("pg_ctl"));
    ctl.arg("-D")
        .arg(&data)
        .arg("-l")
        .arg(root.join("log"))
        .args(["-w", "-o"])
        .arg(format!(
            "-p {port} -k {} -c listen_addresses={listen} -c fsync=off -c max_connections=300",
            root.display()
        ))
        .arg("start");
    run(ctl, "pg_ctl start")?;
    // Stop the server and remove its directory when this test process is gone (the watchdog runs as this
    // user, who may signal this process; the server is stopped as its own user).
    let as_user = if is_root() {
        "runuser -u postgres -- "
    } else {
        ""
    };
    let stop = format!(
        "while kill -0 {pid} 2>/dev/null; do sleep 0.5; done; {as_user}{ctl} -D {data} -m immediate stop >/dev/null 2>&1",
        pid = std::process::id(),
        ctl = bin.join("pg_ctl").display(),
        data = data.display(),
    );
    let mut watchdog = Command::new("/bin/sh");
    watchdog
        .arg("-c")
        .arg(format!("{stop}; rm -rf {}", root.display()))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    watchdog.spawn().map_err(|e| format!("watchdog: {e}"))?;
    Ok(Cluster { port })
}

/// The cluster of this test binary, or `None` (after one skip line) where PostgreSQL is missing.
pub fn cluster(test: &str) -> Option<&'static Cluster> {
    static CLUSTER: OnceLock<Result<Cluster, String>> = OnceLock::new();
    match CLUSTER.get_or_init(|| start_listening(None)) {
        Ok(c) => Some(c),
        Err(why) => {
            assert!(
                std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
                "{test}: {why}, and CTRECON_REQUIRE_PEERS=1 (run scripts/install-peers.sh)"
            );
            eprintln!("skipped {test}: {why}");
            None
        }
    }
}

/// A cluster of its own that also listens on `addr` and trusts clients of `net` (see [`start_listening`]),
/// or `None` (after one skip line) where PostgreSQL is missing. Stopped when the test process exits.
pub fn cluster_on(test: &str, addr: &str, net: &str) -> Option<Cluster> {
    match start_listening(Some((addr, net))) {
        Ok(c) => Some(c),
        Err(why) => {
            assert!(
                std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
                "{test}: {why}, and CTRECON_REQUIRE_PEERS=1 (run scripts/install-peers.sh)"
            );
            eprintln!("skipped {test}: {why}");
            None
        }
    }
}

/// A fresh, empty database on the cluster: its URL.
pub fn database_url(test: &str) -> Option<String> {
    let c = cluster(test)?;
    Some(database_on(c, "127.0.0.1"))
}

/// A fresh, empty database on cluster `c`: its URL through address `host`.
pub fn database_on(c: &Cluster, host: &str) -> String {
    let name = format!("t_{}", uuid_like());
    let out = Command::new("psql")
        .args(["-h", "127.0.0.1", "-U", "postgres", "-p"])
        .arg(c.port.to_string())
        .args(["-d", "postgres", "-v", "ON_ERROR_STOP=1", "-c"])
        .arg(format!("CREATE DATABASE {name}"))
        .output()
        .expect("psql runs");
    assert!(
        out.status.success(),
        "CREATE DATABASE: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    format!("postgres://postgres@{host}:{}/{name}", c.port)
}

fn uuid_like() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static N: AtomicU64 = AtomicU64::new(0);
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!(
        "{}_{t}_{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}
