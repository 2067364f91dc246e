//! `POST /v1/series` against the real server: arbitrary multipart forms (and ZIP or single-instance bodies) go
//! through the multipart parser, the streaming spool, the ZIP ingest and the DICOM reader. The answer must be
//! a success or a client error — never a 5xx — and must come (libFuzzer's `-timeout` catches a hang).
#![no_main]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::LazyLock;
use std::time::Duration;

use ctrecon::config::Settings;
use ctrecon::http::Application;
use libfuzzer_sys::fuzz_target;

#[path = "contained.rs"]
mod contained;

/// The server, started once per fuzzing process in a data directory of its own under `fuzz/target`.
static SERVER: LazyLock<SocketAddr> = LazyLock::new(|| {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("target/upload-data");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("data directory");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime");
        rt.block_on(async move {
            let settings = Settings {
                bind: "127.0.0.1:0".parse().expect("address"),
                data_dir: dir,
                worker_threads: 1,
                max_concurrent_jobs: 1,
                max_upload_bytes: 1 << 20,
                ..Settings::default()
            };
            let app = Application::build(settings)
                .await
                .expect("the service builds");
            tx.send(app.local_addr()).expect("address sent");
            app.run_until(std::future::pending()).await.expect("serves");
        });
    });
    rx.recv().expect("the server starts")
});

/// The status code of one request, written by hand so the body is sent exactly as the input has it.
fn post(addr: SocketAddr, media_type: &str, body: &[u8]) -> u16 {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(30)))
        .expect("timeout");
    let head = format!(
        "POST /v1/series HTTP/1.1\r\nHost: fuzz\r\nContent-Type: {media_type}\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n",
        body.len()
    );
    // The server may answer and close before reading a refused body whole: write errors are not findings.
    let _ = s
        .write_all(head.as_bytes())
        .and_then(|()| s.write_all(body));
    let mut answer = Vec::new();
    let _ = s.read_to_end(&mut answer);
    let line = String::from_utf8_lossy(&answer[..answer.len().min(16)]).into_owned();
    line.split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no HTTP answer: {line:?}"))
}

fuzz_target!(init: contained::let_contained_panics_through(), |data: &[u8]| {
    let (media_type, body) = ctrecon::http::upload::fuzz_upload_request(data);
    let status = post(*SERVER, media_type, body);
    assert!(status < 500, "POST /v1/series answered {status}");
});
