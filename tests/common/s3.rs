//! An S3 server that checks SigV4 signatures (s3s-fs) for the tests of object storage: its own root
//! directory and port, one bucket, stopped when dropped; the settings that point a `ctrecon` process at it,
//! and what its root holds (an object is a file under `<root>/<bucket>/<key>`; s3s-fs keeps temporary files
//! and multipart parts as `.tmp.*` and `.upload*` files in the root itself).
//!
//! Without s3s-fs (`scripts/install-peers.sh s3`) [`s3`] prints one skip line and returns `None`, unless
//! `CTRECON_REQUIRE_PEERS=1`, where it fails.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const ACCESS_KEY: &str = "ctrecon-svc";
pub const SECRET_KEY: &str = "ctrecon-svc-secret";
pub const BUCKET: &str = "ctrecon-svc";
pub const PREFIX: &str = "site-a";

/// An s3s-fs process with its own root and port, stopped on drop.
pub struct S3Server {
    pub child: Child,
    /// `http://host:port`.
    pub endpoint: String,
    pub root: tempfile::TempDir,
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl S3Server {
    /// The file s3s-fs keeps object `key` (below the service's prefix) of the bucket in.
    pub fn object_file(&self, key: &str) -> PathBuf {
        self.root
            .path()
            .join(BUCKET)
            .join(PREFIX)
            .join(key.replace('/', std::path::MAIN_SEPARATOR_STR))
    }

    /// The objects under `key` (below the service's prefix), as relative paths, sorted.
    pub fn objects_under(&self, key: &str) -> Vec<String> {
        files_under(&self.object_file(key))
    }

    /// Files in the root that are not objects of a bucket: temporary files of puts and parts of multipart
    /// uploads not completed or aborted.
    pub fn unfinished(&self) -> Vec<String> {
        let Ok(entries) = std::fs::read_dir(self.root.path()) else {
            return Vec::new();
        };
        let mut out: Vec<String> = entries
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(".tmp.") || n.starts_with(".upload"))
            .collect();
        out.sort();
        out
    }

    /// Point `c` at bucket `bucket` with secret `secret` (the right access key), with the service's prefix.
    pub fn configure(&self, c: &mut Command, bucket: &str, secret: &str) {
        c.env("CTRECON_STORAGE_URL", format!("s3://{bucket}/{PREFIX}"))
            .env("CTRECON_STORAGE_ENDPOINT", &self.endpoint)
            .env("AWS_ACCESS_KEY_ID", ACCESS_KEY)
            .env("AWS_SECRET_ACCESS_KEY", secret)
            .env("AWS_REGION", "us-east-1");
    }

    /// Point `c` at the bucket with the right credentials.
    pub fn serve_to(&self, mut c: Command) -> Command {
        self.configure(&mut c, BUCKET, SECRET_KEY);
        c
    }
}

include!("ports.rs");

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

/// Start s3s-fs on `host` (an address of this machine) with one bucket, or say why not (one skip line; a
/// failure when peers are required).
pub fn s3_on(test: &str, host: &str) -> Option<S3Server> {
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
    let port = free_port_on(host);
    let child = Command::new(bin)
        .args(["--host", host, "--port", &port.to_string()])
        .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
        .arg(root.path())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("s3s-fs starts");
    let server = S3Server {
        child,
        endpoint: format!("http://{host}:{port}"),
        root,
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect((host, port)).is_err() {
        assert!(Instant::now() < deadline, "s3s-fs did not listen");
        std::thread::sleep(Duration::from_millis(10));
    }
    Some(server)
}

/// s3s-fs on loopback.
pub fn s3(test: &str) -> Option<S3Server> {
    s3_on(test, "127.0.0.1")
}

/// Files under `dir` (relative, sorted), for "what is here" assertions.
pub fn files_under(dir: &Path) -> Vec<String> {
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
