//! Result fetch of a 64 MiB volume from S3-compatible object storage against the local data directory, in the
//! ways the service reads it: a whole-file read of the local copy; a worker's cache fill (`BlobStore::local`
//! on a miss: GET streamed into `tmp/`, synced, renamed); a whole GET streamed to memory as the API serves a
//! result it has no copy of; a 1 MiB ranged GET (the viewer's first slice). The server is s3s-fs on
//! 127.0.0.1 (SigV4 checked; `scripts/install-peers.sh s3`), so the figures are the protocol's and the
//! server's cost without a network. Wall clock, best and median of `ROUNDS`. Run with
//! `cargo bench --bench storage` (or `cargo test --release --bench storage`); without s3s-fs it prints a skip notice.

use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ctrecon::storage::mirror::Mirror;
use ctrecon::storage::object::{ObjectBlobs, S3Location};
use ctrecon::storage::port::{BlobKey, Blobs};
use ctrecon::storage::{BlobStore, JobId, ResultName};
use futures_util::StreamExt;

const SIZE: usize = 64 << 20;
const ROUNDS: usize = 7;

fn s3s_fs() -> Option<PathBuf> {
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

fn summary(name: &str, mut t: Vec<Duration>, bytes: usize) {
    t.sort();
    let best = t[0].as_secs_f64();
    let median = t[t.len() / 2].as_secs_f64();
    println!(
        "{name:<44} best {:>7.1} ms  median {:>7.1} ms  ({:.0} MB/s at the median)",
        best * 1e3,
        median * 1e3,
        bytes as f64 / median / 1e6
    );
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let Some(bin) = s3s_fs() else {
        eprintln!("SKIPPED: s3s-fs is not installed (scripts/install-peers.sh s3)");
        return;
    };
    let s3_root = tempfile::tempdir().expect("dir");
    std::fs::create_dir(s3_root.path().join("bench")).expect("bucket");
    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let mut server = Command::new(bin)
        .args(["--host", "127.0.0.1", "--port", &port.to_string()])
        .args(["--access-key", "bench", "--secret-key", "bench-secret"])
        .arg(s3_root.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("s3s-fs starts");
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        std::thread::sleep(Duration::from_millis(10));
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let data = tempfile::tempdir().expect("dir");
    let mut location = S3Location::parse("s3://bench/site").expect("url");
    location.endpoint = Some(format!("http://127.0.0.1:{port}"));
    location.region = Some("us-east-1".into());
    location.access_key_id = Some("bench".into());
    location.secret_access_key = Some("bench-secret".into());
    let objects = Arc::new(ObjectBlobs::s3(&location, &data.path().join("tmp")).expect("adapter"));
    let store = BlobStore::open(data.path())
        .expect("store")
        .with_mirror(Mirror::new(
            objects.clone(),
            rt.handle().clone(),
            "s3://bench/site",
        ));

    // One 64 MiB result, written as a job writes it (put to the bucket, then renamed into place).
    let job = JobId::generate();
    let path = store.result_path(job, &ResultName::Volume);
    let bytes: Vec<u8> = (0..SIZE).map(|i| (i % 251) as u8).collect();
    let t = Instant::now();
    store.write_atomic(&path, &bytes).expect("write");
    println!(
        "write_atomic of {} MiB (local file + PUT, multipart): {:.1} ms",
        SIZE >> 20,
        t.elapsed().as_secs_f64() * 1e3
    );
    let key = BlobKey::parse(&format!("results/{job}/volume.npy")).expect("key");

    let mut local = Vec::new();
    let mut fill = Vec::new();
    let mut get = Vec::new();
    let mut range = Vec::new();
    for _ in 0..ROUNDS {
        let t = Instant::now();
        let b = std::fs::read(&path).expect("read");
        local.push(t.elapsed());
        assert_eq!(b.len(), SIZE);

        std::fs::remove_file(&path).expect("evict");
        let t = Instant::now();
        let p = store.local(&path).expect("cache fill");
        fill.push(t.elapsed());
        assert_eq!(std::fs::metadata(p).expect("filled").len() as usize, SIZE);

        let t = Instant::now();
        let n = rt.block_on(async {
            let mut s = objects.get(&key, None).await.expect("get");
            let mut n = 0usize;
            while let Some(c) = s.next().await {
                n += c.expect("chunk").len();
            }
            n
        });
        get.push(t.elapsed());
        assert_eq!(n, SIZE);

        let t = Instant::now();
        let n = rt.block_on(async {
            let mut s = objects
                .get(&key, Some(32 << 20..(32 << 20) + (1 << 20)))
                .await
                .expect("ranged get");
            let mut n = 0usize;
            while let Some(c) = s.next().await {
                n += c.expect("chunk").len();
            }
            n
        });
        range.push(t.elapsed());
        assert_eq!(n, 1 << 20);
    }
    summary("local file, whole read", local, SIZE);
    summary("S3 → data directory (worker's cache fill)", fill, SIZE);
    summary("S3 GET streamed (API serving a result)", get, SIZE);
    summary("S3 ranged GET, 1 MiB", range, 1 << 20);
    let _ = server.kill();
    let _ = server.wait();
}
