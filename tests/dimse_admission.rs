//! The DICOM node under hostile load: TCP connections that never negotiate hold no association slot and are
//! closed (the oldest first when too many wait, the rest at the negotiation timeout), callers the allow-list
//! does not know take no slot, and a known caller over the cap is refused transiently. The attacks are real
//! sockets against a real node; the silent ones come from loopback addresses no peer uses (127.0.0.2, …).
//!
//! `load_twenty_thousand_connections` is ignored: it measures the figures of `LOAD-DIMSE.md` (run it alone
//! with `--ignored --nocapture`).

use crate::dimse_node::{
    CT, EXPLICIT_LE, args, associate, completed, dcmtk_present, free_port, run, start_node,
    storescu, synthetic_series, text,
};

use std::process::Output;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use ctrecon::dimse::DicomNode;
use dicom_ul::pdu::{
    AssociationRJ, AssociationRJResult, AssociationRJServiceProviderPresentationReason,
    AssociationRJServiceUserReason, AssociationRJSource, AssociationRQ, Pdu,
    PresentationContextProposed, UserVariableItem,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::task::JoinHandle;

/// A TCP connection to the node from `from`, a loopback address of the test's choosing.
async fn connect_from(from: &str, node: &DicomNode) -> std::io::Result<TcpStream> {
    connect_to(from, node.local_addr()).await
}

async fn connect_to(from: &str, to: std::net::SocketAddr) -> std::io::Result<TcpStream> {
    let s = TcpSocket::new_v4()?;
    s.bind(format!("{from}:0").parse().expect("an IPv4 address"))?;
    s.connect(to).await
}

/// A connection the test holds open (until dropped, even after the node closed its end) that sends
/// nothing, and when the node closed it.
struct Silent {
    opened: Instant,
    /// When the node closed its end (EOF or reset), and the bytes it sent before.
    closed: Arc<OnceLock<(Instant, Vec<u8>)>>,
    task: JoinHandle<()>,
}

impl Silent {
    fn is_closed(&self) -> bool {
        self.closed.get().is_some()
    }

    /// When the node closed it (waits at most 60 s).
    async fn closed(&self) -> (Instant, Vec<u8>) {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(60) {
            if let Some(c) = self.closed.get() {
                return c.clone();
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        panic!("the node kept a silent connection open for 60 s")
    }
}

impl Drop for Silent {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Watch `s` until the node closes it; `hold`: keep it open after that, as an attacker might.
fn watch(s: TcpStream, opened: Instant) -> Silent {
    watch_and(s, opened, true)
}

fn watch_and(mut s: TcpStream, opened: Instant, hold: bool) -> Silent {
    let closed = Arc::new(OnceLock::new());
    let seen = closed.clone();
    let task = tokio::spawn(async move {
        let mut got = Vec::new();
        let mut buf = [0u8; 256];
        loop {
            match s.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => got.extend_from_slice(&buf[..n]),
            }
        }
        let _ = seen.set((Instant::now(), got));
        if hold {
            std::future::pending::<()>().await;
        }
        drop(s);
    });
    Silent {
        opened,
        closed,
        task,
    }
}

/// `n` silent connections from `from`, opened one after the other.
async fn silent_from(from: &str, node: &DicomNode, n: usize) -> Vec<Silent> {
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let s = connect_from(from, node).await.expect("connect");
        out.push(watch(s, Instant::now()));
    }
    out
}

fn closed_indices(conns: &[Silent]) -> Vec<usize> {
    (0..conns.len()).filter(|&k| conns[k].is_closed()).collect()
}

/// Poll a condition for up to `within` (bounds a hang; not a timing).
async fn wait_until(within: Duration, cond: impl Fn() -> bool) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < within {
        if cond() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    cond()
}

/// TCP connections the node holds open on its address and port (accepted and not closed: those in the
/// listener's backlog have inode 0), distinct by inode, from the kernel's table.
fn held_by_node(node: &DicomNode) -> usize {
    let std::net::IpAddr::V4(ip) = node.local_addr().ip() else {
        panic!("the test node listens on IPv4")
    };
    // As the table writes it: the address as a little-endian word, then the port.
    let local = format!(
        "{:08X}:{:04X}",
        u32::from_le_bytes(ip.octets()),
        node.local_addr().port()
    );
    let table = std::fs::read_to_string("/proc/net/tcp").expect("/proc/net/tcp");
    let inodes: std::collections::HashSet<String> = table
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (f.len() > 9 && f[1] == local && f[3] == "01" && f[9] != "0").then(|| f[9].to_string())
        })
        .collect();
    inodes.len()
}

/// Assert that the node holds `n` connections open. The kernel's table is not read at one instant: while
/// other tests' connections come and go a read may miss a line or show one twice, so it is read until it
/// shows `n` (for at most 2 s).
async fn assert_node_holds(node: &DicomNode, n: usize) {
    let mut seen = Vec::new();
    for _ in 0..100 {
        let held = held_by_node(node);
        if held == n {
            return;
        }
        seen.push(held);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("the node holds {seen:?} connections, not {n}");
}

/// `echoscu` as the peer TESTSCU (ACSE timeout 30 s, so a node that never answers fails the test).
async fn echo(node: &DicomNode, calling: &str) -> Output {
    echo_on(node.local_addr().port(), calling).await
}

async fn echo_on(port: u16, calling: &str) -> Output {
    let port = port.to_string();
    run(
        "echoscu",
        &args(&[
            "-ta",
            "30",
            "-aet",
            calling,
            "-aec",
            "CTRECON",
            "127.0.0.1",
            &port,
        ]),
    )
    .await
}

/// An A-ASSOCIATE-RQ for verification calling CTRECON as `calling`.
fn request(calling: &str) -> Vec<u8> {
    let rq = Pdu::AssociationRQ(AssociationRQ {
        protocol_version: 1,
        calling_ae_title: calling.into(),
        called_ae_title: "CTRECON".into(),
        application_context_name: "1.2.840.10008.3.1.1.1".into(),
        presentation_contexts: vec![PresentationContextProposed {
            id: 1,
            abstract_syntax: "1.2.840.10008.1.1".into(),
            transfer_syntaxes: vec!["1.2.840.10008.1.2".into()],
        }],
        user_variables: vec![UserVariableItem::MaxLength(16_384)],
    });
    let mut buf = Vec::new();
    dicom_ul::pdu::write_pdu(&mut buf, &rq).expect("an A-ASSOCIATE-RQ");
    buf
}

/// The node's answer (one PDU) to an A-ASSOCIATE-RQ calling as `calling` from `from`.
async fn answer(node: &DicomNode, from: &str, calling: &str) -> Pdu {
    let mut s = connect_from(from, node).await.expect("connect");
    s.write_all(&request(calling)).await.expect("send");
    let mut header = [0u8; 6];
    tokio::time::timeout(Duration::from_secs(10), s.read_exact(&mut header))
        .await
        .expect("an answer within 10 s")
        .expect("an answer");
    let len = u32::from_be_bytes([header[2], header[3], header[4], header[5]]) as usize;
    let mut pdu = header.to_vec();
    pdu.resize(6 + len, 0);
    s.read_exact(&mut pdu[6..]).await.expect("the whole answer");
    dicom_ul::pdu::read_pdu(&pdu[..], 16_384, false)
        .expect("a PDU")
        .expect("complete")
}

fn secs(d: Duration) -> String {
    format!("{:.3} s", d.as_secs_f64())
}

#[tokio::test]
async fn a_peer_echoes_while_twenty_silent_sockets_from_another_address_are_open() {
    if !dcmtk_present() {
        return;
    }
    let (mut node, _dir) = start_node(|s| s.max_associations = 4).await;
    let attack = silent_from("127.0.0.2", &node, 20).await;
    // The node has taken them all once the 12 over the cap of 8 pending per address are closed.
    assert!(
        wait_until(Duration::from_secs(2), || closed_indices(&attack).len()
            >= 12)
        .await
    );
    let mut took = Vec::new();
    for _ in 0..5 {
        let t0 = Instant::now();
        let ok = echo(&node, "TESTSCU").await;
        took.push(t0.elapsed());
        assert!(ok.status.success(), "{}", text(&ok));
    }
    // The oldest 12 made room for the newest 8, which are still open (pending, holding no slot).
    assert_eq!(closed_indices(&attack), (0..12).collect::<Vec<_>>());
    assert_node_holds(&node, 8).await;
    eprintln!(
        "20 silent sockets, 8 held by the node: 5 C-ECHOs of the peer in {}",
        took.iter().map(|d| secs(*d)).collect::<Vec<_>>().join(", ")
    );
    // The attack ends; the node serves a series.
    drop(attack);
    let src = tempfile::tempdir().unwrap();
    let (series_uid, _) = synthetic_series(src.path(), 5);
    let out = storescu(&node.local_addr().port().to_string(), src.path()).await;
    assert!(out.status.success(), "{}", text(&out));
    let done = completed(&mut node).await;
    assert_eq!((done.series_uid, done.instances), (series_uid, 5));
}

#[tokio::test]
async fn silent_sockets_are_closed_at_the_negotiation_timeout_and_those_over_the_address_cap_at_once()
 {
    let (node, _dir) = start_node(|s| s.negotiation_timeout_secs = 2).await;
    let attack = silent_from("127.0.0.3", &node, 20).await;
    let last_opened = attack[19].opened;
    let mut at_once = Duration::ZERO;
    let (mut first_timeout, mut last_timeout) = (Duration::MAX, Duration::ZERO);
    for (k, conn) in attack.iter().enumerate() {
        let opened = conn.opened;
        let (at, got) = conn.closed().await;
        assert!(got.is_empty(), "connection {k} was sent {got:?}");
        if k < 12 {
            // Closed when the connection 8 places later arrived.
            at_once = at_once.max(at.saturating_duration_since(last_opened));
            assert!(
                at < last_opened + Duration::from_millis(500),
                "connection {k}"
            );
        } else {
            let after = at - opened;
            (first_timeout, last_timeout) = (first_timeout.min(after), last_timeout.max(after));
            assert!(
                after >= Duration::from_millis(1950) && after < Duration::from_secs(3),
                "connection {k} closed after {after:?}"
            );
        }
    }
    assert_node_holds(&node, 0).await;
    eprintln!(
        "12 over the cap closed at most {} after the last connected; 8 closed {}–{} after connecting",
        secs(at_once),
        secs(first_timeout),
        secs(last_timeout)
    );
}

#[tokio::test]
async fn a_crowd_from_many_addresses_closes_the_oldest_pending_connections_first() {
    if !dcmtk_present() {
        return;
    }
    let (node, _dir) = start_node(|s| {
        s.max_pending = 16;
        s.max_associations = 2;
    })
    .await;
    let mut crowd = Vec::new();
    for from in ["127.0.0.4", "127.0.0.5", "127.0.0.6"] {
        crowd.extend(silent_from(from, &node, 8).await);
    }
    // 24 for 16 places: the 8 oldest (all from 127.0.0.4) are closed.
    assert!(wait_until(Duration::from_secs(2), || closed_indices(&crowd).len() >= 8).await);
    assert_eq!(closed_indices(&crowd), (0..8).collect::<Vec<_>>());
    assert_node_holds(&node, 16).await;
    // The peer's connection takes the place of the oldest pending one and negotiates.
    let ok = echo(&node, "TESTSCU").await;
    assert!(ok.status.success(), "{}", text(&ok));
    assert!(wait_until(Duration::from_secs(2), || crowd[8].is_closed()).await);
    assert_eq!(closed_indices(&crowd), (0..9).collect::<Vec<_>>());
}

#[tokio::test]
async fn callers_off_the_allow_list_take_no_slot_and_a_peer_over_the_cap_is_refused_transiently() {
    if !dcmtk_present() {
        return;
    }
    let (node, _dir) = start_node(|s| s.max_associations = 2).await;
    let first = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    // Half a request, again and again from another address: pending, never a slot.
    let head = request("TESTSCU")[..40].to_vec();
    let mut slow = Vec::new();
    for _ in 0..6 {
        let mut s = connect_from("127.0.0.3", &node).await.unwrap();
        s.write_all(&head).await.unwrap();
        slow.push(s);
    }
    // The peer's title from an address that is not the peer's, and a stranger's title from the peer's
    // address: rejected permanently by the negotiation.
    for _ in 0..5 {
        let rj = answer(&node, "127.0.0.2", "TESTSCU").await;
        let want = Pdu::AssociationRJ(AssociationRJ {
            result: AssociationRJResult::Permanent,
            source: AssociationRJSource::ServiceUser(
                AssociationRJServiceUserReason::CallingAETitleNotRecognized,
            ),
        });
        assert_eq!(rj, want);
        let stranger = echo(&node, "STRANGER").await;
        assert!(
            text(&stranger).contains("Calling AE Title Not Recognized"),
            "{}",
            text(&stranger)
        );
    }
    // None of them took a slot: the second is still free.
    let second = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    // Both slots held by associations of the peer: its next request is refused, transiently.
    let busy = answer(&node, "127.0.0.1", "TESTSCU").await;
    let want = Pdu::AssociationRJ(AssociationRJ {
        result: AssociationRJResult::Transient,
        source: AssociationRJSource::ServiceProviderPresentation(
            AssociationRJServiceProviderPresentationReason::LocalLimitExceeded,
        ),
    });
    assert_eq!(busy, want);
    let busy = echo(&node, "TESTSCU").await;
    assert!(!busy.status.success());
    assert!(
        text(&busy).contains("Local Limit Exceeded"),
        "{}",
        text(&busy)
    );
    first.release().await.unwrap();
    let mut ok = echo(&node, "TESTSCU").await;
    for _ in 0..50 {
        if ok.status.success() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        ok = echo(&node, "TESTSCU").await;
    }
    assert!(ok.status.success(), "{}", text(&ok));
    second.release().await.unwrap();
    drop(slow);
}

#[tokio::test]
async fn after_a_flood_of_connections_the_node_serves_a_series() {
    if !dcmtk_present() {
        return;
    }
    let (mut node, _dir) = start_node(|_| {}).await;
    // 300 held open from five addresses, and 300 opened and dropped at once.
    let mut held = Vec::new();
    for k in 0..300 {
        let from = format!("127.0.0.{}", 10 + k % 5);
        let s = connect_from(&from, &node).await.unwrap();
        held.push(watch(s, Instant::now()));
        drop(connect_from("127.0.0.20", &node).await.unwrap());
    }
    // Eight per address stay pending; the node holds nothing else.
    assert!(
        wait_until(Duration::from_secs(5), || closed_indices(&held).len()
            >= 260)
        .await
    );
    assert_eq!(closed_indices(&held).len(), 260);
    assert_node_holds(&node, 40).await;
    let ok = echo(&node, "TESTSCU").await;
    assert!(ok.status.success(), "{}", text(&ok));
    drop(held);
    let src = tempfile::tempdir().unwrap();
    let (series_uid, _) = synthetic_series(src.path(), 5);
    let out = storescu(&node.local_addr().port().to_string(), src.path()).await;
    assert!(out.status.success(), "{}", text(&out));
    let done = completed(&mut node).await;
    assert_eq!((done.series_uid, done.instances), (series_uid, 5));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "load figures for LOAD-DIMSE.md; run alone"]
async fn load_twenty_thousand_connections() {
    load().await;
}

/// 20 000 silent connections from 100 addresses (200 each) against `ctrecon serve` with the default limits
/// (16 associations, 8 pending per address, 64 in all, negotiation timeout 5 s) in a process of its own,
/// whose descriptors are counted every 10 ms; then the peer's C-ECHOs and a C-STORE. The attacker lets a
/// connection go once the node closed it (its own descriptors: 20 000 here).
async fn load() {
    if !dcmtk_present() {
        return;
    }
    let port = free_port();
    let serve = serve_with(port, None).await;
    let pid = serve.child.id();
    let fds = move || std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count());
    let at_rest = fds();
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sampler = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut most = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                most = most.max(fds());
                std::thread::sleep(Duration::from_millis(10));
            }
            most
        })
    };
    let to = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let t0 = Instant::now();
    let (mut conns, mut failed) = (Vec::new(), 0usize);
    for k in 0..20_000 {
        match connect_to(&format!("127.0.0.{}", 2 + k % 100), to).await {
            Ok(s) => conns.push(watch_and(s, Instant::now(), false)),
            Err(_) => failed += 1,
        }
    }
    let opened_in = t0.elapsed();
    let closed_by_then = closed_indices(&conns).len();
    let mut echoes = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let ok = echo_on(port, "TESTSCU").await;
        echoes.push(t.elapsed());
        assert!(ok.status.success(), "{}", text(&ok));
    }
    let last_opened = conns.last().map(|c| c.opened).unwrap_or(t0);
    let mut all_closed_at = last_opened;
    for c in &conns {
        all_closed_at = all_closed_at.max(c.closed().await.0);
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let most = sampler.join().unwrap();
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let peak_rss = status
        .lines()
        .find(|l| l.starts_with("VmHWM"))
        .unwrap_or("");
    eprintln!(
        "{} connections opened in {} ({failed} failed to connect); {closed_by_then} closed by the node \
         by then; node descriptors: {at_rest} at rest, at most {most}; the last closed {} after the last \
         opened; peer C-ECHOs during the attack: {}; node {peak_rss}",
        conns.len(),
        secs(opened_in),
        secs(all_closed_at - last_opened),
        echoes
            .iter()
            .map(|d| secs(*d))
            .collect::<Vec<_>>()
            .join(", ")
    );
    drop(conns);
    let src = tempfile::tempdir().unwrap();
    synthetic_series(src.path(), 5);
    let t = Instant::now();
    let out = storescu(&port.to_string(), src.path()).await;
    assert!(out.status.success(), "{}", text(&out));
    eprintln!(
        "after the attack: storescu of 5 instances in {}",
        secs(t.elapsed())
    );
}

/// `ctrecon serve` in a process of its own, with a DICOM node on `port` that knows TESTSCU at 127.0.0.1;
/// killed when dropped.
struct Serve {
    child: std::process::Child,
    log: std::path::PathBuf,
    _dir: tempfile::TempDir,
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// [`Serve`] with its descriptors limited to `nofile` (`ulimit -Sn`) when given.
async fn serve_with(port: u16, nofile: Option<u32>) -> Serve {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    let settings = serde_json::json!({"dicom": {"port": port, "peers": [
        {"ae_title": "TESTSCU", "host": "127.0.0.1", "port": 1}]}});
    std::fs::write(&config, settings.to_string()).unwrap();
    let log = dir.path().join("stderr.log");
    let mut child = std::process::Command::new("sh")
        .arg("-c")
        .arg(match nofile {
            Some(n) => format!("ulimit -Sn {n} && exec \"$0\" \"$@\""),
            None => "exec \"$0\" \"$@\"".into(),
        })
        .arg(env!("CARGO_BIN_EXE_ctrecon"))
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--config",
        ])
        .arg(&config)
        .env("CTRECON_DATA_DIR", dir.path().join("data"))
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .expect("ctrecon starts");
    let stdout = child.stdout.take().expect("stdout");
    let ready = tokio::task::spawn_blocking(move || {
        std::io::BufReader::new(stdout)
            .lines()
            .take(4)
            .map_while(Result::ok)
            .any(|l| l.contains("DICOM node"))
    });
    let serve = Serve {
        child,
        log,
        _dir: dir,
    };
    assert!(ready.await.unwrap(), "the DICOM node did not start");
    serve
}

#[tokio::test]
async fn a_node_out_of_descriptors_keeps_accepting_and_serves_its_peer() {
    if !dcmtk_present() {
        return;
    }
    let port = free_port();
    // ctrecon serve uses about 24 descriptors at rest.
    let serve = serve_with(port, Some(64)).await;
    let pid = serve.child.id();
    let fds = || std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count());
    let at_rest = fds();
    // 400 silent connections from 50 addresses: 8 pending each would be 400, the node-wide cap 64, and the
    // process has fewer descriptors left than that.
    let to = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let mut crowd = Vec::new();
    for k in 0..400 {
        let s = connect_to(&format!("127.0.0.{}", 30 + k % 50), to)
            .await
            .unwrap();
        crowd.push(watch(s, Instant::now()));
    }
    let most = fds();
    let mut took = Vec::new();
    for _ in 0..3 {
        let t0 = Instant::now();
        let ok = echo_on(port, "TESTSCU").await;
        took.push(t0.elapsed());
        assert!(ok.status.success(), "{}", text(&ok));
    }
    let log = std::fs::read_to_string(&serve.log).unwrap();
    assert!(
        log.contains("DICOM accept failed") && log.contains("os error 24"),
        "the node never ran out of descriptors: {at_rest} at rest, {most} in the crowd\n{log}"
    );
    eprintln!(
        "64 descriptors, {at_rest} at rest, {most} in a crowd of 400: accept failed (EMFILE), and 3 \
         C-ECHOs of the peer in {}",
        took.iter().map(|d| secs(*d)).collect::<Vec<_>>().join(", ")
    );
    drop(crowd);
}
