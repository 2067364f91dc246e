//! The DICOM node against DCMTK (`echoscu`, `storescu`, `storescp`) and against hand-made associations:
//! allow-list, negotiation, streamed C-STORE, stable-age completion, refusals that leave nothing behind,
//! the association cap, and ctrecon sending by C-STORE.
//!
//! DCMTK comes from Debian's `dcmtk` package. Without it each test prints one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1` (as in CI), when it fails.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::Duration;

use ctrecon::dicom::{ReadLimits, SeriesMeta, read_part10, read_path, write_ct_series};
use ctrecon::dimse::command::{self, status};
use ctrecon::dimse::scu::{self, Caller};
use ctrecon::dimse::{CompletedSeries, DicomNode, NodeSettings, Peer};
use ctrecon::volume::{Frame, Volume};
use dicom_ul::association::client::ClientAssociationOptions;
use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu, PresentationContextResultReason};

pub(crate) const CT: &str = "1.2.840.10008.5.1.4.1.1.2";
pub(crate) const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";

pub(crate) fn dcmtk_present() -> bool {
    let ok = ["echoscu", "storescu", "storescp"].iter().all(|t| {
        std::process::Command::new(t)
            .arg("--version")
            .output()
            .is_ok()
    });
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "DCMTK (echoscu, storescu, storescp) is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: DCMTK is not installed (apt-get install dcmtk)");
    }
    ok
}

fn test_peer() -> Peer {
    Peer {
        ae_title: "TESTSCU".into(),
        host: "127.0.0.1".into(),
        port: 1,
        store: true,
        query: true,
        retrieve: true,
    }
}

pub(crate) async fn start_node(
    configure: impl FnOnce(&mut NodeSettings),
) -> (DicomNode, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let mut s = NodeSettings {
        port: Some(0),
        peers: vec![test_peer()],
        stable_age_secs: 1,
        dimse_timeout_secs: 10,
        ..NodeSettings::default()
    };
    configure(&mut s);
    let node = DicomNode::start(&s, dir.path()).await.unwrap();
    (node, dir)
}

/// A synthetic CT series of `nz` slices of 24 × 20 written to `dir`; returns its series UID and files.
pub(crate) fn synthetic_series(dir: &Path, nz: usize) -> (String, Vec<PathBuf>) {
    let data = ndarray::Array3::from_shape_fn((nz, 20, 24), |(k, j, i)| {
        (k * 100 + j * 10 + i) as f32 - 1000.0
    });
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-12.0, -10.0, 30.0],
            spacing_mm: [1.0, 1.0, 2.5],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let meta = SeriesMeta {
        patient_id: Some("NODE-1".into()),
        series_description: "node test".into(),
        series_number: 4,
        ..Default::default()
    };
    let s = write_ct_series(&vol, &meta).unwrap();
    std::fs::create_dir_all(dir).unwrap();
    let files = s
        .files
        .iter()
        .map(|(name, bytes)| {
            let p = dir.join(name);
            std::fs::write(&p, bytes).unwrap();
            p
        })
        .collect();
    (s.series_uid, files)
}

pub(crate) async fn run(tool: &str, args: &[String]) -> Output {
    let (tool, args) = (tool.to_string(), args.to_vec());
    tokio::task::spawn_blocking(move || {
        std::process::Command::new(tool)
            .args(args)
            .env("TCP_NODELAY", "1")
            .output()
            .unwrap()
    })
    .await
    .unwrap()
}

pub(crate) fn args(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

pub(crate) fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// `storescu` sending every file of `dir` as TESTSCU to CTRECON on 127.0.0.1:`port`.
pub(crate) async fn storescu(port: &str, dir: &Path) -> Output {
    let dir = dir.to_string_lossy();
    run(
        "storescu",
        &args(&[
            "-aet",
            "TESTSCU",
            "-aec",
            "CTRECON",
            "+sd",
            "127.0.0.1",
            port,
            &dir,
        ]),
    )
    .await
}

async fn echoscu(node: &DicomNode, calling: &str, called: &str) -> Output {
    let port = node.local_addr().port().to_string();
    run(
        "echoscu",
        &args(&["-aet", calling, "-aec", called, "127.0.0.1", &port]),
    )
    .await
}

pub(crate) async fn completed(node: &mut DicomNode) -> CompletedSeries {
    tokio::time::timeout(Duration::from_secs(60), node.next_completed())
        .await
        .expect("a series completes")
        .expect("the node runs")
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|it| it.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    v.sort();
    v
}

/// The stored values of every slice of every file, by SOP instance UID.
fn pixels_by_instance(files: &[PathBuf]) -> Vec<(String, Vec<f32>)> {
    let mut v: Vec<(String, Vec<f32>)> = files
        .iter()
        .map(|f| {
            let i = read_path(f, &ReadLimits::default()).unwrap();
            let px = i.slices.iter().flat_map(|s| s.stored.clone()).collect();
            (i.sop_instance_uid, px)
        })
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[tokio::test]
async fn echo_from_an_allowed_caller_succeeds_and_strangers_are_rejected() {
    if !dcmtk_present() {
        return;
    }
    let (node, _dir) = start_node(|_| {}).await;
    let ok = echoscu(&node, "TESTSCU", "CTRECON").await;
    assert!(ok.status.success(), "{}", text(&ok));
    let stranger = echoscu(&node, "STRANGER", "CTRECON").await;
    assert!(!stranger.status.success());
    assert!(
        text(&stranger).contains("Calling AE Title Not Recognized"),
        "{}",
        text(&stranger)
    );
    let wrong_called = echoscu(&node, "TESTSCU", "SOMEONE").await;
    assert!(!wrong_called.status.success());
    assert!(
        text(&wrong_called).contains("Called AE Title Not Recognized"),
        "{}",
        text(&wrong_called)
    );
}

#[tokio::test]
async fn a_series_sent_by_storescu_is_filed_whole_and_announced_once_stable() {
    if !dcmtk_present() {
        return;
    }
    let (mut node, dir) = start_node(|_| {}).await;
    let src = tempfile::tempdir().unwrap();
    let (series_uid, files) = synthetic_series(src.path(), 12);
    let port = node.local_addr().port().to_string();
    let out = storescu(&port, src.path()).await;
    assert!(out.status.success(), "{}", text(&out));
    let done = completed(&mut node).await;
    assert_eq!(done.series_uid, series_uid);
    assert_eq!(done.instances, 12);
    assert_eq!(done.calling_ae, "TESTSCU");
    let stored = files_in(&done.folder);
    assert_eq!(stored.len(), 12);
    // Every instance arrives exactly: same SOP instances, same stored pixel values.
    assert_eq!(pixels_by_instance(&stored), pixels_by_instance(&files));
    assert!(files_in(&dir.path().join("dimse/tmp")).is_empty());
    assert!(files_in(&dir.path().join("dimse/incoming")).is_empty());
}

#[tokio::test]
async fn lidc_sent_by_storescu_arrives_exactly() {
    let lidc = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if !lidc.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
            lidc.display()
        );
        eprintln!("skipped: {} is missing", lidc.display());
        return;
    }
    if !dcmtk_present() {
        return;
    }
    let (mut node, _dir) = start_node(|_| {}).await;
    let port = node.local_addr().port().to_string();
    let out = storescu(&port, &lidc).await;
    assert!(out.status.success(), "{}", text(&out));
    let done = completed(&mut node).await;
    assert_eq!(done.instances, 133);
    let originals: Vec<PathBuf> = files_in(&lidc)
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .collect();
    assert_eq!(
        pixels_by_instance(&files_in(&done.folder)),
        pixels_by_instance(&originals)
    );
}

pub(crate) type Client = dicom_ul::association::AsyncClientAssociation<tokio::net::TcpStream>;

pub(crate) async fn associate(node: &DicomNode, contexts: &[(&str, &str)]) -> Client {
    let mut o = ClientAssociationOptions::new()
        .calling_ae_title("TESTSCU")
        .called_ae_title("CTRECON");
    for (sop, ts) in contexts {
        o = o.with_presentation_context(*sop, vec![*ts]);
    }
    o.establish_async(node.local_addr()).await.unwrap()
}

#[tokio::test]
async fn undecodable_transfer_syntaxes_and_foreign_sop_classes_are_not_accepted() {
    let (node, _dir) = start_node(|_| {}).await;
    let assoc = associate(
        &node,
        &[
            (CT, "1.2.840.10008.1.2.4.80"),
            ("1.2.840.10008.5.1.4.1.1.4", EXPLICIT_LE),
            (CT, EXPLICIT_LE),
            (CT, "1.2.840.10008.1.2.4.90"),
            // MPEG-2 video: a syntax the reader cannot decode.
            (CT, "1.2.840.10008.1.2.4.100"),
        ],
    )
    .await;
    // Only the CT contexts are accepted, each in a syntax the reader decodes (JPEG-LS included); not MR
    // Image Storage, and not CT in MPEG-2 (context 9).
    let accepted: Vec<(u8, String, String)> = assoc
        .presentation_contexts()
        .iter()
        .filter(|pc| pc.reason == PresentationContextResultReason::Acceptance)
        .map(|pc| {
            (
                pc.id,
                pc.abstract_syntax.clone(),
                pc.transfer_syntax.clone(),
            )
        })
        .collect();
    assert_eq!(
        accepted,
        vec![
            (1, CT.to_string(), "1.2.840.10008.1.2.4.80".to_string()),
            (5, CT.to_string(), EXPLICIT_LE.to_string()),
            (7, CT.to_string(), "1.2.840.10008.1.2.4.90".to_string()),
        ]
    );
    let _ = assoc.release().await;
}

fn caller() -> Caller {
    Caller {
        ae_title: "TESTSCU".into(),
        timeout: Duration::from_secs(10),
        max_pdu_length: 16384,
    }
}

fn node_peer(node: &DicomNode) -> Peer {
    Peer {
        ae_title: "CTRECON".into(),
        port: node.local_addr().port(),
        ..test_peer()
    }
}

#[tokio::test]
async fn broken_and_mismatched_data_sets_are_refused_and_nothing_is_kept() {
    let (node, dir) = start_node(|_| {}).await;
    let src = tempfile::tempdir().unwrap();
    let (_, files) = synthetic_series(src.path(), 2);
    // Truncated inside the pixel data: its declared length overruns the data set.
    let bytes = std::fs::read(&files[0]).unwrap();
    let truncated = src.path().join("truncated.dcm");
    std::fs::write(&truncated, &bytes[..bytes.len() - 100]).unwrap();
    // The file meta names another SOP instance than the data set (same length, last digit changed).
    let mut bytes = std::fs::read(&files[1]).unwrap();
    let meta = read_part10(&files[1]).unwrap();
    let at = bytes[..meta.dataset_offset as usize]
        .windows(meta.sop_instance_uid.len())
        .position(|w| w == meta.sop_instance_uid.as_bytes())
        .unwrap()
        + meta.sop_instance_uid.len()
        - 1;
    bytes[at] = if bytes[at] == b'1' { b'2' } else { b'1' };
    let mismatched = src.path().join("mismatched.dcm");
    std::fs::write(&mismatched, &bytes).unwrap();

    let out = scu::store(&caller(), &node_peer(&node), &[truncated, mismatched])
        .await
        .unwrap();
    assert_eq!(out[0].status, Some(status::CANNOT_UNDERSTAND), "{out:?}");
    assert_eq!(out[1].status, Some(status::DATA_SET_MISMATCH), "{out:?}");
    assert!(out.iter().all(|o| o.detail.is_some()));
    assert!(files_in(&dir.path().join("dimse/tmp")).is_empty());
    assert!(files_in(&dir.path().join("dimse/incoming")).is_empty());
    assert!(node.arriving().is_empty());
}

#[tokio::test]
async fn an_association_aborted_mid_instance_leaves_nothing_behind() {
    let (node, dir) = start_node(|_| {}).await;
    let src = tempfile::tempdir().unwrap();
    let (_, files) = synthetic_series(src.path(), 1);
    let meta = read_part10(&files[0]).unwrap();
    let mut assoc = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    let pc = assoc.presentation_contexts()[0].id;
    let rq = command::store_request(1, CT, &meta.sop_instance_uid, None);
    let bytes = std::fs::read(&files[0]).unwrap();
    let first_half = bytes[meta.dataset_offset as usize..][..400].to_vec();
    // The start of a large instance: more than the node holds in memory before it writes to its file
    // (1 MiB), in fragments of 16 KiB.
    let mut fragments = vec![
        (PDataValueType::Command, rq),
        (PDataValueType::Data, first_half),
    ];
    fragments.extend((0..72).map(|_| (PDataValueType::Data, vec![0u8; 16 << 10])));
    for (value_type, data) in fragments {
        let is_last = value_type == PDataValueType::Command;
        assoc
            .send(&Pdu::PData {
                data: vec![PDataValue {
                    presentation_context_id: pc,
                    value_type,
                    is_last,
                    data,
                }],
            })
            .await
            .unwrap();
    }
    // The instance is being written…
    let tmp = dir.path().join("dimse/tmp");
    wait_for(|| files_in(&tmp).len() == 1).await;
    assoc.abort().await.unwrap();
    // …and is gone once the association is aborted.
    wait_for(|| files_in(&tmp).is_empty()).await;
    assert!(files_in(&dir.path().join("dimse/incoming")).is_empty());
    assert!(node.arriving().is_empty());
}

/// Poll a condition for up to 10 s (bounds a hang; not a timing).
async fn wait_for(cond: impl Fn() -> bool) {
    for _ in 0..500 {
        if cond() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("condition not reached in 10 s");
}

#[tokio::test]
async fn the_association_cap_turns_an_extra_caller_away_transiently() {
    if !dcmtk_present() {
        return;
    }
    let (node, _dir) = start_node(|s| s.max_associations = 1).await;
    let held = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    let busy = echoscu(&node, "TESTSCU", "CTRECON").await;
    assert!(!busy.status.success());
    assert!(text(&busy).contains("Transient"), "{}", text(&busy));
    held.release().await.unwrap();
    let mut ok = echoscu(&node, "TESTSCU", "CTRECON").await;
    for _ in 0..50 {
        if ok.status.success() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        ok = echoscu(&node, "TESTSCU", "CTRECON").await;
    }
    assert!(ok.status.success(), "{}", text(&ok));
}

/// A peer process, stopped when the test ends however it ends.
struct Running(std::process::Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

include!("common/ports.rs");

#[tokio::test]
async fn ctrecon_stores_a_series_into_storescp_and_reports_each_instance() {
    if !dcmtk_present() {
        return;
    }
    let out_dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let storescp = std::process::Command::new("storescp")
        .args(args(&[
            "--aetitle",
            "DEST",
            "--output-directory",
            &out_dir.path().to_string_lossy(),
            &port.to_string(),
        ]))
        .env("TCP_NODELAY", "1")
        .spawn()
        .unwrap();
    let storescp = Running(storescp);
    let dest = Peer {
        ae_title: "DEST".into(),
        host: "127.0.0.1".into(),
        port,
        store: false,
        query: false,
        retrieve: false,
    };
    let c = Caller {
        ae_title: "CTRECON".into(),
        ..caller()
    };
    let mut echoed = scu::echo(&c, &dest).await;
    for _ in 0..100 {
        if echoed.is_ok() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        echoed = scu::echo(&c, &dest).await;
    }
    assert_eq!(echoed.unwrap(), status::SUCCESS);

    let src = tempfile::tempdir().unwrap();
    let (_, files) = synthetic_series(src.path(), 5);
    let outcomes = scu::store(&c, &dest, &files).await.unwrap();
    assert_eq!(outcomes.len(), 5);
    assert!(outcomes.iter().all(|o| o.stored()), "{outcomes:?}");
    let received = files_in(out_dir.path());
    assert_eq!(received.len(), 5);
    assert_eq!(pixels_by_instance(&received), pixels_by_instance(&files));

    drop(storescp);
    let down = scu::echo(&c, &dest).await;
    assert!(down.is_err(), "a stopped peer cannot answer");
}

#[tokio::test]
async fn a_series_stored_into_the_service_becomes_a_series_of_the_api() {
    if !dcmtk_present() {
        return;
    }
    let app = common::spawn_app_with(|s| {
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = 1;
        s.dicom.peers = vec![test_peer()];
    })
    .await;
    let port = app.dicom.expect("a DICOM node").port().to_string();
    let src = tempfile::tempdir().unwrap();
    let (series_uid, _) = synthetic_series(src.path(), 12);
    let out = storescu(&port, src.path()).await;
    assert!(out.status.success(), "{}", text(&out));
    // The assembled volume appears as series/<id>.npy; the API then serves the series.
    let series_dir = app.dir.path().join("series");
    let mut id = None;
    for _ in 0..1500 {
        if let Some(f) = files_in(&series_dir).first() {
            id = f.file_stem().map(|s| s.to_string_lossy().into_owned());
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let id = id.expect("the received series is assembled within 30 s");
    let r = app.get(&format!("/v1/series/{id}")).await;
    assert_eq!(r.status(), 200);
    let v: serde_json::Value = r.json().await.unwrap();
    let body = v.get("series").unwrap_or(&v);
    assert_eq!(body["series_uid"], series_uid.as_str(), "{v}");
    assert_eq!(body["shape"], serde_json::json!([12, 20, 24]), "{v}");
    assert_eq!(body["instances"], 12, "{v}");
    // Voxel (k, j, i) holds k·100 + j·10 + i − 1000 HU (within the int16 quantisation step).
    let npy = app
        .get(&format!("/v1/series/{id}/volume.npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let header_len = u16::from_le_bytes([npy[8], npy[9]]) as usize;
    let data = &npy[10 + header_len..];
    let voxel = |k: usize, j: usize, i: usize| {
        let o = 4 * ((k * 20 + j) * 24 + i);
        f32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]])
    };
    for (k, j, i) in [(0, 0, 0), (5, 7, 11), (11, 19, 23)] {
        let want = (k * 100 + j * 10 + i) as f32 - 1000.0;
        assert!(
            (voxel(k, j, i) - want).abs() < 0.5,
            "voxel {k},{j},{i}: {} vs {want}",
            voxel(k, j, i)
        );
    }
    // Nothing is left in the node's folders once the series is recorded.
    for _ in 0..500 {
        if files_in(&app.dir.path().join("dimse/complete")).is_empty() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(files_in(&app.dir.path().join("dimse/complete")).is_empty());
}

/// Read from `stream` until the node ends the connection (at most 10 s, which bounds a hang): the bytes it
/// sent and how long it took. A reset counts as the end.
pub(crate) async fn until_closed(stream: &mut tokio::net::TcpStream) -> (Vec<u8>, Duration) {
    use tokio::io::AsyncReadExt;
    let t0 = std::time::Instant::now();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(Duration::from_secs(10), stream.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return (got, t0.elapsed()),
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
            Err(_) => panic!("the node kept the connection open for 10 s; it sent {got:?}"),
        }
    }
}

/// What a node that answered a bad input with an A-ABORT (PDU type 07), an A-ASSOCIATE-RJ (03, before an
/// association) or by closing sent.
fn aborted_or_closed(got: &[u8]) -> bool {
    got.is_empty() || got[0] == 0x07 || got[0] == 0x03
}

/// The node is still up (C-ECHO succeeds) and kept nothing of what it refused.
async fn still_up_and_nothing_kept(node: &DicomNode, dir: &Path) {
    let echo = echoscu(node, "TESTSCU", "CTRECON").await;
    assert!(echo.status.success(), "{}", text(&echo));
    assert!(files_in(&dir.join("dimse/tmp")).is_empty());
    assert!(files_in(&dir.join("dimse/incoming")).is_empty());
    assert!(node.arriving().is_empty());
}

#[tokio::test]
async fn malformed_pdus_are_aborted_and_the_node_stays_up_with_nothing_kept() {
    use tokio::io::AsyncWriteExt;
    if !dcmtk_present() {
        return;
    }
    let (node, dir) = start_node(|_| {}).await;
    // Not DICOM at all, an unknown PDU type, and an A-ASSOCIATE-RQ whose items overrun it.
    let mut rq = vec![0x01, 0x00, 0x00, 0x00, 0x00, 0x10, 0x00, 0x01, 0x00, 0x00];
    rq.extend_from_slice(&[0x10, 0x00, 0x7F, 0xFF, b'1', b'.', b'2', 0, 0, 0, 0, 0]);
    for garbage in [
        b"GET / HTTP/1.1\r\nHost: ctrecon\r\n\r\n".to_vec(),
        vec![0x42, 0x00, 0x00, 0x00, 0x00, 0x04, 1, 2, 3, 4],
        rq,
    ] {
        let mut s = tokio::net::TcpStream::connect(node.local_addr())
            .await
            .unwrap();
        s.write_all(&garbage).await.unwrap();
        let (got, _) = until_closed(&mut s).await;
        assert!(aborted_or_closed(&got), "{garbage:?} answered with {got:?}");
    }
    // Inside an association: a P-DATA-TF whose value item claims more bytes than the PDU holds, and a
    // P-DATA-TF and an A-ASSOCIATE-RQ that claim 1 GiB, over the negotiated maximum: aborted at once,
    // without waiting for (or making room for) what they claim.
    for pdu in [
        vec![
            0x04, 0x00, 0x00, 0x00, 0x00, 0x0A, 0x00, 0x00, 0x03, 0xE8, 0x01, 0x03, 0, 0, 0, 0,
        ],
        vec![
            0x04, 0x00, 0x40, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x10, 0x01, 0x00,
        ],
        vec![0x01, 0x00, 0x40, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00],
    ] {
        let mut assoc = associate(&node, &[(CT, EXPLICIT_LE)]).await;
        let stream = assoc.inner_stream();
        stream.write_all(&pdu).await.unwrap();
        let (got, took) = until_closed(stream).await;
        assert!(aborted_or_closed(&got), "{pdu:?} answered with {got:?}");
        assert!(
            took < Duration::from_secs(5),
            "{pdu:?} closed after {took:?}"
        );
    }
    still_up_and_nothing_kept(&node, dir.path()).await;
}

#[tokio::test]
async fn a_caller_that_falls_silent_is_dropped_after_the_association_or_dimse_timeout() {
    if !dcmtk_present() {
        return;
    }
    let (node, dir) = start_node(|s| {
        s.association_timeout_secs = 1;
        s.dimse_timeout_secs = 2;
    })
    .await;
    // Connected, and not a byte of A-ASSOCIATE-RQ: closed after the association timeout.
    let mut s = tokio::net::TcpStream::connect(node.local_addr())
        .await
        .unwrap();
    let (got, took) = until_closed(&mut s).await;
    assert!(aborted_or_closed(&got), "{got:?}");
    assert!(
        took >= Duration::from_millis(900) && took < Duration::from_secs(5),
        "closed after {took:?}"
    );
    // Associated, then silent: an A-ABORT after the DIMSE timeout.
    let mut assoc = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    let (got, took) = until_closed(assoc.inner_stream()).await;
    assert_eq!(got.first(), Some(&0x07), "an A-ABORT: {got:?}");
    assert!(
        took >= Duration::from_millis(1900) && took < Duration::from_secs(6),
        "aborted after {took:?}"
    );
    // Silent halfway through an instance: the same, and nothing of the instance is kept.
    let mut assoc = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    let src = tempfile::tempdir().unwrap();
    let (_, files) = synthetic_series(src.path(), 1);
    let p10 = read_part10(&files[0]).unwrap();
    let cmd = command::store_request(1, CT, &p10.sop_instance_uid, None);
    let pc = assoc.presentation_contexts()[0].id;
    assoc
        .send(&Pdu::PData {
            data: vec![PDataValue {
                presentation_context_id: pc,
                value_type: PDataValueType::Command,
                is_last: true,
                data: cmd,
            }],
        })
        .await
        .unwrap();
    let data = std::fs::read(&files[0]).unwrap();
    assoc
        .send(&Pdu::PData {
            data: vec![PDataValue {
                presentation_context_id: pc,
                value_type: PDataValueType::Data,
                is_last: false,
                data: data[p10.dataset_offset as usize..][..400].to_vec(),
            }],
        })
        .await
        .unwrap();
    let (got, _) = until_closed(assoc.inner_stream()).await;
    assert_eq!(got.first(), Some(&0x07), "an A-ABORT: {got:?}");
    still_up_and_nothing_kept(&node, dir.path()).await;
}

#[tokio::test]
async fn a_pdu_over_the_maximum_length_is_aborted_and_nothing_is_kept() {
    use tokio::io::AsyncWriteExt;
    if !dcmtk_present() {
        return;
    }
    let (node, dir) = start_node(|s| s.max_pdu_length = 16_384).await;
    let mut assoc = associate(&node, &[(CT, EXPLICIT_LE)]).await;
    // A P-DATA-TF of 100 000 bytes against a maximum of 16 384: refused from its header.
    let len: u32 = 100_000;
    let mut pdu = vec![0x04, 0x00];
    pdu.extend_from_slice(&len.to_be_bytes());
    pdu.extend_from_slice(&(len - 4).to_be_bytes());
    pdu.extend_from_slice(&[1, 0x02]);
    pdu.resize(6 + len as usize, 0);
    let stream = assoc.inner_stream();
    // The node may close before it has read the rest: a failed write is part of the answer.
    let _ = stream.write_all(&pdu).await;
    let (got, _) = until_closed(stream).await;
    assert!(aborted_or_closed(&got), "{got:?}");
    still_up_and_nothing_kept(&node, dir.path()).await;
}
