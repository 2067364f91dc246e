//! The HTTP port under hostile load, against the real `ctrecon serve` binary on loopback: connections that
//! send nothing or half a request line are closed at the header timeout while `/healthz` keeps answering and
//! the descriptors come back; the caps per address and in total answer 503 at once and the loop serves
//! again as soon as connections close; an accept loop out of descriptors keeps running and recovers; idle
//! keep-alive connections close; a stalled upload is answered 408 with nothing left in `tmp/`; STOW-RS
//! refuses a declared length over the limit without reading the body. Attackers connect from 127.0.0.2 and
//! up, the health checks from 127.0.0.1. The figures are printed (`--nocapture`) for benches/README.md.

use std::net::{Ipv4Addr, SocketAddr};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::task::JoinSet;

use crate::roles::ctrecon;

/// A `ctrecon serve` child on 127.0.0.1 over a data directory of its own, its log in a file; killed when
/// dropped.
struct Server {
    child: Child,
    addr: SocketAddr,
    dir: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    fn start(env: &[(&str, &str)]) -> Self {
        use std::io::BufRead;
        let dir = tempfile::tempdir().expect("temp dir");
        let log = std::fs::File::create(dir.path().join("server.log")).expect("log file");
        let mut c = ctrecon();
        c.env("CTRECON_DATA_DIR", dir.path().join("data"))
            .env("CTRECON_WORKER_THREADS", "1")
            .env("RUST_LOG", "info");
        for (k, v) in env {
            c.env(k, v);
        }
        let mut child = c
            .args(["serve", "--bind", "127.0.0.1:0"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .expect("ctrecon starts");
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().expect("stdout"))
            .read_line(&mut line)
            .expect("the first line");
        let addr = line
            .trim()
            .strip_prefix("ctrecon listening on http://")
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"));
        Self { child, addr, dir }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Descriptors the server holds open.
    fn open_fds(&self) -> usize {
        std::fs::read_dir(format!("/proc/{}/fd", self.pid()))
            .expect("/proc/<pid>/fd")
            .count()
    }

    /// (VmRSS, VmHWM) of the server in KiB.
    fn memory_kib(&self) -> (u64, u64) {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.pid()))
            .expect("/proc/<pid>/status");
        let field = |name: &str| {
            status
                .lines()
                .find_map(|l| l.strip_prefix(name))
                .and_then(|v| v.split_whitespace().next())
                .and_then(|v| v.parse().ok())
                .unwrap_or(0)
        };
        (field("VmRSS:"), field("VmHWM:"))
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("server.log")).unwrap_or_default()
    }

    fn tmp_files(&self) -> usize {
        std::fs::read_dir(self.dir.path().join("data").join("tmp"))
            .map(|d| d.count())
            .unwrap_or(0)
    }

    fn alive(&mut self) -> bool {
        self.child.try_wait().expect("try_wait").is_none()
    }
}

/// A connection to `addr` from 127.0.0.`host`.
async fn connect_from(host: u8, addr: SocketAddr) -> TcpStream {
    let s = TcpSocket::new_v4().expect("socket");
    s.bind(SocketAddr::from((Ipv4Addr::new(127, 0, 0, host), 0)))
        .expect("bind a loopback source");
    s.connect(addr).await.expect("connect")
}

/// Everything the server sends until it closes (bounded by `limit`); `None` if it did not close in time.
async fn read_to_close(s: &mut TcpStream, limit: Duration) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    let mut buf = [0u8; 4096];
    let until = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(until, s.read(&mut buf)).await {
            Err(_) => return None,
            Ok(Ok(0)) | Ok(Err(_)) => return Some(out),
            Ok(Ok(n)) => out.extend_from_slice(&buf[..n]),
        }
    }
}

/// How long after `since` the server closed `s` (`None`: not within `limit` of `since`).
async fn closed_after(mut s: TcpStream, since: Instant, limit: Duration) -> Option<Duration> {
    read_to_close(&mut s, limit.saturating_sub(since.elapsed())).await?;
    Some(since.elapsed())
}

/// Status, lower-cased head and body of one HTTP/1.1 response.
fn parse(response: &[u8]) -> (u16, String, Vec<u8>) {
    let text = String::from_utf8_lossy(response);
    let Some(end) = text.find("\r\n\r\n") else {
        return (0, text.to_lowercase(), Vec::new());
    };
    let head = text[..end].to_lowercase();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, head, response[end + 4..].to_vec())
}

/// The `code` of a problem body.
fn code(body: &[u8]) -> String {
    serde_json::from_slice::<Value>(body).map_or_else(
        |e| format!("not JSON ({e}): {}", String::from_utf8_lossy(body)),
        |v| v["code"].as_str().unwrap_or("").to_string(),
    )
}

/// One request on a connection of its own from 127.0.0.`host`: status (0 when the server did not answer
/// within `limit`) and how long it took.
async fn request_from(
    host: u8,
    addr: SocketAddr,
    request: &str,
    limit: Duration,
) -> (u16, Duration) {
    let t = Instant::now();
    let answer = tokio::time::timeout(limit, async {
        let mut s = connect_from(host, addr).await;
        s.write_all(request.as_bytes()).await.ok()?;
        read_to_close(&mut s, limit).await
    })
    .await;
    let status = match answer {
        Ok(Some(bytes)) => parse(&bytes).0,
        _ => 0,
    };
    (status, t.elapsed())
}

const HEALTHZ: &str = "GET /healthz HTTP/1.1\r\nhost: ctrecon\r\nconnection: close\r\n\r\n";

async fn healthz(addr: SocketAddr, limit: Duration) -> (u16, Duration) {
    request_from(1, addr, HEALTHZ, limit).await
}

/// How many connections this test process can hold beside the server's own (`wanted` where the open-file
/// limit allows).
fn affordable(wanted: usize) -> usize {
    let limits = std::fs::read_to_string("/proc/self/limits").unwrap_or_default();
    let soft = limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(1024);
    let n = wanted.min(soft.saturating_sub(400));
    if n < wanted {
        println!("open-file limit {soft}: {n} connections instead of {wanted}");
    }
    n
}

/// What one wave of connections without a request saw.
struct Wave {
    connecting: Duration,
    first: Duration,
    last: Duration,
    fds_held: usize,
    /// How many connections were younger than the header timeout when `fds_held` was read: on a loaded machine
    /// opening them all can take longer than the timeout, and the oldest are rightly closed by then.
    should_be_open: usize,
    rss_held: u64,
}

/// `silent` connections that send nothing from 127.0.0.2–9 and `partial` that send half a request line from
/// 127.0.0.10–11, held until the server closes them (each must within `limit` of its connect).
async fn wave(
    server: &Server,
    silent: usize,
    partial: usize,
    header: Duration,
    limit: Duration,
) -> Wave {
    let addr = server.addr;
    let mut closing = JoinSet::new();
    let t0 = Instant::now();
    let mut opened = Vec::with_capacity(silent + partial);
    for i in 0..silent {
        let s = connect_from(2 + (i % 8) as u8, addr).await;
        let since = Instant::now();
        opened.push(since);
        closing.spawn(closed_after(s, since, limit));
    }
    for i in 0..partial {
        let mut s = connect_from(10 + (i % 2) as u8, addr).await;
        let since = Instant::now();
        opened.push(since);
        s.write_all(b"GET / HT")
            .await
            .expect("a partial request line");
        closing.spawn(closed_after(s, since, limit));
    }
    let connecting = t0.elapsed();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sampled = Instant::now();
    let (fds_held, (rss_held, _)) = (server.open_fds(), server.memory_kib());
    let should_be_open = opened
        .iter()
        .filter(|&&since| sampled.duration_since(since) + Duration::from_millis(100) < header)
        .count();
    let (mut first, mut last) = (Duration::MAX, Duration::ZERO);
    while let Some(closed) = closing.join_next().await {
        let after = closed
            .expect("a reader")
            .expect("the server closed a connection without a request");
        first = first.min(after);
        last = last.max(after);
    }
    Wave {
        connecting,
        first,
        last,
        fds_held,
        should_be_open,
        rss_held,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_without_a_request_are_closed_at_the_header_timeout_while_healthz_answers() {
    let header = Duration::from_secs(4);
    let server = Server::start(&[("CTRECON_HEADER_READ_TIMEOUT_MS", "4000")]);
    let addr = server.addr;
    let total = affordable(1800);
    let (silent, partial) = (total * 5 / 6, total / 6);
    for _ in 0..3 {
        assert_eq!(healthz(addr, Duration::from_secs(5)).await.0, 200);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (fds_before, (rss_before, _)) = (server.open_fds(), server.memory_kib());

    // A health checker on 127.0.0.1 throughout.
    let stop = Arc::new(AtomicBool::new(false));
    let checker = {
        let stop = stop.clone();
        tokio::spawn(async move {
            let (mut n, mut worst) = (0u32, Duration::ZERO);
            while !stop.load(Ordering::Relaxed) {
                let (status, took) = healthz(addr, Duration::from_secs(5)).await;
                assert_eq!(status, 200, "/healthz during the attack (after {took:?})");
                worst = worst.max(took);
                n += 1;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            (n, worst)
        })
    };

    // Two waves: the second shows what the first left behind is reused, not grown.
    let limit = header + Duration::from_secs(5);
    let mut after = Vec::new();
    for round in 1..=2 {
        let w = wave(&server, silent, partial, header, limit).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        let (fds_after, (rss_after, hwm)) = (server.open_fds(), server.memory_kib());
        println!(
            "header timeout, wave {round}: {total} connections ({silent} silent, {partial} with a partial \
             line) opened in {:?}, each closed {:?}..{:?} after it connected; descriptors {fds_before} -> {} \
             -> {fds_after}; VmRSS {rss_before} -> {} -> {rss_after} KiB (VmHWM {hwm} KiB), {:.1} KiB per \
             held connection",
            w.connecting,
            w.first,
            w.last,
            w.fds_held,
            w.rss_held,
            w.rss_held.saturating_sub(rss_before) as f64 / total as f64
        );
        assert!(
            w.should_be_open >= total / 2,
            "the machine is too slow for this test: only {} of {total} connections opened within the header \
             timeout of the sample",
            w.should_be_open
        );
        assert!(
            w.fds_held >= fds_before + w.should_be_open * 9 / 10,
            "the server holds the connections: {} descriptors, {fds_before} before, {} connections younger than \
             the header timeout",
            w.fds_held,
            w.should_be_open
        );
        assert!(
            w.first >= header - Duration::from_millis(50),
            "closed before the header timeout: {:?}",
            w.first
        );
        assert!(
            w.last <= header + Duration::from_millis(1500),
            "closed too long after the header timeout: {:?}",
            w.last
        );
        assert!(
            fds_after <= fds_before + 8,
            "descriptors back near the baseline: {fds_before} -> {fds_after}"
        );
        assert!(
            w.rss_held.saturating_sub(rss_before) < 64 * total as u64,
            "under 64 KiB per held connection: {rss_before} -> {} KiB",
            w.rss_held
        );
        after.push(rss_after);
    }
    stop.store(true, Ordering::Relaxed);
    let (checks, worst) = checker.await.expect("the health checker");
    println!("/healthz throughout: {checks} checks, slowest {worst:?}");
    assert!(
        checks >= 20 && worst < Duration::from_secs(1),
        "/healthz: {checks} checks, slowest {worst:?}"
    );
    assert!(
        after[1] <= after[0] + 4096,
        "the second wave reuses the memory of the first: VmRSS {} then {} KiB",
        after[0],
        after[1]
    );
}

/// Open `n` connections that send nothing, from 127.0.0.`hosts` in turn.
async fn hold(n: usize, hosts: std::ops::RangeInclusive<u8>, addr: SocketAddr) -> Vec<TcpStream> {
    let hosts: Vec<u8> = hosts.collect();
    let mut held = Vec::with_capacity(n);
    for i in 0..n {
        held.push(connect_from(hosts[i % hosts.len()], addr).await);
    }
    // The accept loop has taken them all before the test goes on.
    tokio::time::sleep(Duration::from_millis(300)).await;
    held
}

/// A connection from 127.0.0.`host` that is answered without sending anything: status, head, body and time.
async fn refused_from(host: u8, addr: SocketAddr) -> (u16, String, Vec<u8>, Duration) {
    let t = Instant::now();
    let mut s = connect_from(host, addr).await;
    let bytes = read_to_close(&mut s, Duration::from_secs(3))
        .await
        .expect("the server closes a refused connection");
    let (status, head, body) = parse(&bytes);
    (status, head, body, t.elapsed())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_over_the_cap_of_an_address_get_503_at_once_and_other_addresses_are_served() {
    let server = Server::start(&[("CTRECON_MAX_CONNECTIONS_PER_IP", "20")]);
    let addr = server.addr;
    let held = hold(20, 2..=2, addr).await;
    let mut slowest = Duration::ZERO;
    for _ in 0..5 {
        let (status, head, body, took) = refused_from(2, addr).await;
        assert_eq!(
            (status, code(&body).as_str()),
            (503, "too_many_connections")
        );
        assert!(
            head.contains("retry-after: 1") && head.contains("connection: close"),
            "{head}"
        );
        assert!(
            head.contains("content-type: application/problem+json"),
            "{head}"
        );
        slowest = slowest.max(took);
    }
    assert!(
        slowest < Duration::from_millis(500),
        "answered at once: {slowest:?}"
    );
    let (status, _) = request_from(3, addr, HEALTHZ, Duration::from_secs(2)).await;
    assert_eq!(status, 200, "another address is served");
    assert_eq!(healthz(addr, Duration::from_secs(2)).await.0, 200);
    drop(held);
    let t = Instant::now();
    loop {
        let (status, _) = request_from(2, addr, HEALTHZ, Duration::from_secs(1)).await;
        if status == 200 {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(2),
            "the address is served again ({status})"
        );
    }
    println!(
        "cap per address: 5 extra connections answered 503 within {slowest:?}; served again {:?} after the 20 closed",
        t.elapsed()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_over_the_total_cap_get_503_and_the_loop_serves_again_once_they_close() {
    let server = Server::start(&[("CTRECON_MAX_CONNECTIONS", "40")]);
    let addr = server.addr;
    let held = hold(40, 2..=5, addr).await;
    let (status, _, body, took) = refused_from(6, addr).await;
    assert_eq!(
        (status, code(&body).as_str()),
        (503, "too_many_connections")
    );
    assert!(
        took < Duration::from_millis(500),
        "answered at once: {took:?}"
    );
    assert_eq!(
        healthz(addr, Duration::from_secs(2)).await.0,
        503,
        "the cap holds for everyone"
    );
    drop(held);
    let t = Instant::now();
    let mut tries = 0;
    loop {
        tries += 1;
        if healthz(addr, Duration::from_secs(1)).await.0 == 200 {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(1),
            "served again within 1 s"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let recovered = t.elapsed();
    println!(
        "total cap: refused in {took:?}; served again {recovered:?} after the 40 closed ({tries} tries)"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_accept_loop_out_of_descriptors_keeps_running_and_serves_again_when_they_are_freed() {
    let mut server = Server::start(&[]);
    let addr = server.addr;
    assert_eq!(healthz(addr, Duration::from_secs(5)).await.0, 200);
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Leave the server 40 descriptors, then connect 80 times: accept fails with EMFILE from the 41st on.
    let soft = server.open_fds() + 40;
    let lowered = Command::new("prlimit")
        .args([
            "--pid",
            &server.pid().to_string(),
            &format!("--nofile={soft}:"),
        ])
        .status()
        .expect("prlimit runs");
    assert!(
        lowered.success(),
        "prlimit lowers the server's open-file limit"
    );
    let held = hold(80, 2..=5, addr).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (status, _) = healthz(addr, Duration::from_secs(1)).await;
    assert_eq!(status, 0, "out of descriptors, the server accepts nothing");
    let errors = server.log().matches("accept failed").count();
    assert!(
        (1..=4).contains(&errors),
        "accept errors are logged at most once a second: {errors} lines in about 2 s"
    );
    assert!(server.alive(), "the server still runs");

    let t = Instant::now();
    drop(held);
    loop {
        if healthz(addr, Duration::from_secs(1)).await.0 == 200 {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(3),
            "served again once descriptors are free"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let recovered = t.elapsed();
    println!(
        "EMFILE: {errors} accept warnings logged; served again {recovered:?} after the connections closed"
    );
    assert!(recovered < Duration::from_secs(2), "{recovered:?}");
    assert!(server.alive());
}

/// Read one response whose body has a `content-length`; returns its status.
async fn one_response(s: &mut TcpStream) -> u16 {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let n = tokio::time::timeout(Duration::from_secs(5), s.read(&mut buf))
            .await
            .expect("an answer")
            .expect("read");
        assert!(n > 0, "closed before the answer");
        got.extend_from_slice(&buf[..n]);
        let (status, head, body) = parse(&got);
        let length = head
            .lines()
            .find_map(|l| l.strip_prefix("content-length:"))
            .and_then(|v| v.trim().parse::<usize>().ok());
        if status > 0 && length.is_some_and(|l| body.len() >= l) {
            return status;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idle_keep_alive_connection_is_closed_at_the_idle_timeout_not_the_header_timeout() {
    let idle = Duration::from_secs(2);
    let server = Server::start(&[
        ("CTRECON_HEADER_READ_TIMEOUT_MS", "1000"),
        ("CTRECON_IDLE_TIMEOUT_MS", "2000"),
    ]);
    let get = b"GET /healthz HTTP/1.1\r\nhost: ctrecon\r\n\r\n";
    let mut s = connect_from(2, server.addr).await;
    s.write_all(get).await.unwrap();
    assert_eq!(one_response(&mut s).await, 200);
    // A second request after longer than the header timeout but within the idle one is served.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    s.write_all(get).await.unwrap();
    assert_eq!(one_response(&mut s).await, 200);
    let after = closed_after(s, Instant::now(), idle + Duration::from_secs(5))
        .await
        .expect("the idle connection is closed");
    println!("idle keep-alive connection closed {after:?} after its last response");
    assert!(
        after >= idle - Duration::from_millis(50) && after <= idle + Duration::from_millis(1000),
        "{after:?}"
    );
}

/// Headers of an upload of `length` bytes to `path` with `content_type`.
fn upload_head(path: &str, content_type: &str, length: u64) -> String {
    format!(
        "POST {path} HTTP/1.1\r\nhost: ctrecon\r\ncontent-type: {content_type}\r\n\
         content-length: {length}\r\nconnection: close\r\n\r\n"
    )
}

/// An upload to `path` of `length` bytes: the head and `prefix` at once, then `chunk` bytes every `every`
/// until `length` bytes are sent or the server answers. Returns the status, the problem code and how long
/// after the head the answer came.
struct Trickle<'a> {
    path: &'a str,
    content_type: &'a str,
    prefix: &'a str,
    length: usize,
    chunk: usize,
    every: Duration,
}

async fn trickle(addr: SocketAddr, t: Trickle<'_>) -> (u16, String, Duration) {
    let s = connect_from(2, addr).await;
    let (mut rd, mut wr) = s.into_split();
    let head = upload_head(t.path, t.content_type, t.length as u64);
    wr.write_all(format!("{head}{}", t.prefix).as_bytes())
        .await
        .unwrap();
    let since = Instant::now();
    let (mut left, chunk, every) = (t.length - t.prefix.len(), t.chunk, t.every);
    let writer = tokio::spawn(async move {
        while left > 0 {
            tokio::time::sleep(every).await;
            let n = chunk.min(left);
            if wr.write_all(&vec![b'x'; n]).await.is_err() {
                return;
            }
            left -= n;
        }
        // Keep the write half open until the answer.
        tokio::time::sleep(Duration::from_secs(30)).await;
    });
    let mut got = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(20), rd.read_to_end(&mut got)).await;
    let took = since.elapsed();
    writer.abort();
    let (status, _, body) = parse(&got);
    (status, code(&body), took)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_upload_is_answered_408_and_leaves_no_temporary_file() {
    let window = Duration::from_secs(2);
    let server = Server::start(&[
        ("CTRECON_UPLOAD_MIN_BYTES", "16384"),
        ("CTRECON_UPLOAD_PROGRESS_WINDOW_SECS", "2"),
    ]);
    let form = "--b\r\ncontent-disposition: form-data; name=\"f\"; filename=\"a.dcm\"\r\n\r\n";
    let part = "--b\r\ncontent-type: application/dicom\r\n\r\n";
    for (path, content_type, prefix) in [
        ("/v1/series", "application/zip", ""),
        ("/v1/series", "multipart/form-data; boundary=b", form),
        (
            "/dicom-web/studies",
            "multipart/related; type=\"application/dicom\"; boundary=b",
            part,
        ),
    ] {
        let slow = Trickle {
            path,
            content_type,
            prefix,
            length: 1 << 20,
            chunk: 100,
            every: Duration::from_millis(300),
        };
        let (status, code, took) = trickle(server.addr, slow).await;
        println!(
            "{path} ({content_type}) trickling 100 bytes every 300 ms: {status} {code} after {took:?}"
        );
        assert_eq!(
            (status, code.as_str()),
            (408, "upload_stalled"),
            "{path} {content_type}"
        );
        assert!(
            took >= window && took < window + Duration::from_millis(1500),
            "{took:?}"
        );
        assert_eq!(server.tmp_files(), 0, "nothing left in tmp/ after {path}");
    }
    // Above the rule's pace (10 KiB every 500 ms is 40 KiB a window) an upload is read to its end.
    let steady = Trickle {
        path: "/v1/series",
        content_type: "application/zip",
        prefix: "",
        length: 100 << 10,
        chunk: 10 << 10,
        every: Duration::from_millis(500),
    };
    let (status, code, took) = trickle(server.addr, steady).await;
    println!("a steady upload of 100 KiB over 5 s: {status} {code} after {took:?}");
    assert!(
        status != 408 && status != 0,
        "a slow but steady upload is read: {status} {code} after {took:?}"
    );
    assert!(took >= Duration::from_secs(4), "{took:?}");
    assert_eq!(server.tmp_files(), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stow_rs_refuses_a_declared_length_over_the_limit_before_reading_the_body() {
    let server = Server::start(&[("CTRECON_MAX_UPLOAD_BYTES", "1048576")]);
    let head = upload_head(
        "/dicom-web/studies",
        "multipart/related; type=\"application/dicom\"; boundary=b",
        3 << 30,
    );
    let t = Instant::now();
    let mut s = connect_from(2, server.addr).await;
    s.write_all(head.as_bytes()).await.unwrap();
    let bytes = read_to_close(&mut s, Duration::from_secs(3))
        .await
        .expect("answered and closed without the body");
    let (status, _, body) = parse(&bytes);
    println!(
        "STOW-RS declaring 3 GiB over a 1 MiB limit: {status} after {:?}",
        t.elapsed()
    );
    assert_eq!((status, code(&body).as_str()), (413, "body_too_large"));
    assert!(t.elapsed() < Duration::from_secs(1), "{:?}", t.elapsed());
}
