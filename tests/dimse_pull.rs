//! A volume job whose input is a series on a PACS (`"input": {"pacs": …, "series_instance_uid": …}`):
//! ctrecon finds it on a real Orthanc by C-FIND, moves it to its own node by C-MOVE, assembles it like an
//! upload and runs the job on it. Checked: the pulled volume equals the written values exactly; an unknown
//! series, a peer that refuses the move and a peer that is down fail the job with the peer's answer, without
//! hanging; a cancel stops the retrieval; submissions that cannot pull are refused.
//!
//! Orthanc and DCMTK come from Debian packages. Without them the tests that need a peer print one skip line,
//! unless `CTRECON_REQUIRE_PEERS=1` (as in CI), when they fail.

use crate::common;
use crate::orthanc;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{TestApp, assert_problem, read_npy_f32};
use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::dimse::Peer;
use ctrecon::volume::{Frame, Volume};
use orthanc::{Orthanc, OrthancOptions, free_port, orthanc_present};
use serde_json::{Value, json};

fn peer(ae: &str, port: u16, store: bool, retrieve: bool) -> Peer {
    Peer {
        ae_title: ae.into(),
        host: "127.0.0.1".into(),
        port,
        store,
        query: true,
        retrieve,
    }
}

/// Value of voxel (k, j, i) of the synthetic series: a ramp (distinct everywhere) with two markers.
fn truth(k: usize, j: usize, i: usize) -> f32 {
    match (k, j, i) {
        (2, 5, 7) => 3000.0,
        (9, 30, 40) => -2000.0,
        _ => (k * 100 + j * 10 + i) as f32 - 1000.0,
    }
}

/// A synthetic CT series of `nz` slices of 48 × 40 (1 × 1 × 2.5 mm) written by ctrecon's own writer under
/// `dir`: its Series Instance UID and files.
fn synthetic(dir: &Path, nz: usize) -> (String, Vec<PathBuf>) {
    let data = ndarray::Array3::from_shape_fn((nz, 40, 48), |(k, j, i)| truth(k, j, i));
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [-24.0, -20.0, 15.0],
            spacing_mm: [1.0, 1.0, 2.5],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let meta = SeriesMeta {
        patient_id: Some("PULL-1".into()),
        series_description: "pull test".into(),
        series_number: 7,
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

/// Orthanc knowing ctrecon's node (on `node_port`) as `CTRECON`, holding the series written to `files`.
async fn orthanc_with(node_port: u16, files: &[PathBuf]) -> Orthanc {
    let o = Orthanc::start(OrthancOptions {
        ctrecon_port: Some(node_port),
        ..Default::default()
    })
    .await;
    for f in files {
        o.post("/instances", std::fs::read(f).unwrap()).await;
    }
    o
}

/// ctrecon with its node on `node_port` and `peers`.
async fn ctrecon(node_port: u16, peers: Vec<Peer>) -> TestApp {
    common::spawn_app_with(|s| {
        s.dicom.port = Some(node_port);
        s.dicom.stable_age_secs = 1;
        s.dicom.dimse_timeout_secs = 3;
        s.dicom.peers = peers;
    })
    .await
}

fn pull_job(pacs: &str, uid: &str) -> Value {
    json!({
        "kind": "volume",
        "input": {"pacs": pacs, "series_instance_uid": uid},
        "products": [{"type": "projection", "axis": "axial", "kind": "mip"}],
    })
}

fn files_in(dir: &Path) -> usize {
    std::fs::read_dir(dir).map(|d| d.count()).unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_series_pulled_from_orthanc_is_the_jobs_input_and_its_volume_equals_the_written_values() {
    if !orthanc_present() {
        return;
    }
    let src = tempfile::tempdir().unwrap();
    let nz = 12;
    let (uid, files) = synthetic(src.path(), nz);
    let node_port = free_port();
    let orthanc = orthanc_with(node_port, &files).await;
    let app = ctrecon(
        node_port,
        vec![peer("ORTHANC", orthanc.dicom_port, true, true)],
    )
    .await;
    let mut events = app.core.as_ref().unwrap().engine.subscribe();

    let job = app.submit(&pull_job("ORTHANC", &uid)).await;
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(job["status"], "queued", "{job}");
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");

    // Progress showed the retrieval, counting instances, before the volume work.
    let mut stages = Vec::new();
    while let Ok(e) = events.try_recv() {
        if e.id.to_string() == id {
            stages.push((e.stage, e.progress));
        }
    }
    let retrieving: Vec<_> = stages
        .iter()
        .filter(|(s, _)| s.starts_with("retrieving from ORTHANC"))
        .collect();
    assert!(!retrieving.is_empty(), "{stages:?}");
    assert!(retrieving.iter().all(|(_, p)| *p < 40), "{stages:?}");

    // The pulled series is stored like an upload; its volume is exactly what was written.
    let series = done["result"]["source_series"]
        .as_str()
        .unwrap()
        .to_string();
    let s: Value = app
        .get(&format!("/v1/series/{series}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(s["series_uid"], uid.as_str(), "{s}");
    let npy = app
        .get(&format!("/v1/series/{series}/volume.npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let (shape, data) = read_npy_f32(&npy);
    assert_eq!(shape, vec![nz, 40, 48]);
    let mut k_j_i = Vec::with_capacity(data.len());
    for k in 0..nz {
        for j in 0..40 {
            for i in 0..48 {
                k_j_i.push(truth(k, j, i));
            }
        }
    }
    assert!(
        data == k_j_i,
        "the pulled volume differs from the written one"
    );
    // The job's own volume (no steps) is the same, and its axial MIP holds the bright marker.
    assert_eq!(done["result"]["max"], 3000.0, "{done}");
    assert_eq!(done["result"]["min"], -2000.0, "{done}");
    // Nothing is left in the node's folders.
    let dimse = app.dir.path().join("dimse");
    assert_eq!(files_in(&dimse.join("incoming")), 0);
    assert_eq!(files_in(&dimse.join("complete")), 0);

    // Orthanc now sends to a port where nothing listens: its sub-operations fail, and so does the job, with
    // Orthanc's final status and counts.
    let r = orthanc
        .client
        .put(orthanc.url("/modalities/CTRECON"))
        .json(&json!({"AET": "CTRECON", "Host": "127.0.0.1", "Port": free_port()}))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success());
    let refused = app.submit(&pull_job("ORTHANC", &uid)).await;
    let refused = app.finish(refused["id"].as_str().unwrap()).await;
    assert_eq!(refused["status"], "failed", "{refused}");
    assert_eq!(refused["error"]["code"], "pull_failed", "{refused}");
    let detail = refused["error"]["detail"].as_str().unwrap();
    println!("refused move: {detail}");
    assert!(
        detail.contains("ORTHANC ended the C-MOVE") && detail.contains("0 completed"),
        "{detail}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_unknown_series_and_a_peer_that_is_down_fail_the_job_with_the_reason_without_hanging() {
    if !orthanc_present() {
        return;
    }
    let node_port = free_port();
    let orthanc = orthanc_with(node_port, &[]).await;
    let down_port = free_port();
    let app = ctrecon(
        node_port,
        vec![
            peer("ORTHANC", orthanc.dicom_port, true, true),
            peer("DOWN", down_port, true, true),
        ],
    )
    .await;

    let unknown = "1.2.826.0.1.3680043.2.1125.999.1";
    let job = app.submit(&pull_job("ORTHANC", unknown)).await;
    let job = app.finish(job["id"].as_str().unwrap()).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["code"], "pull_series_not_found", "{job}");
    let detail = job["error"]["detail"].as_str().unwrap();
    assert!(
        detail.contains("ORTHANC holds no series") && detail.contains(unknown),
        "{detail}"
    );

    let started = Instant::now();
    let job = app.submit(&pull_job("DOWN", unknown)).await;
    let job = app.finish(job["id"].as_str().unwrap()).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["code"], "pull_failed", "{job}");
    assert!(
        job["error"]["detail"]
            .as_str()
            .unwrap()
            .contains("C-FIND of series"),
        "{job}"
    );
    // The DIMSE timeout is 3 s: a peer that is down fails the job well within it.
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "{:?}",
        started.elapsed()
    );

    // A peer that accepts the association but never answers: failed after the DIMSE timeout, no hang.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let silent_port = silent.local_addr().unwrap().port();
    let app2 = ctrecon(free_port(), vec![peer("SILENT", silent_port, true, true)]).await;
    let started = Instant::now();
    let job = app2.submit(&pull_job("SILENT", unknown)).await;
    let job = app2.finish(job["id"].as_str().unwrap()).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["code"], "pull_failed", "{job}");
    let waited = started.elapsed();
    assert!(
        waited >= Duration::from_secs(3) && waited < Duration::from_secs(15),
        "{waited:?}"
    );
    drop(silent);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_cancel_during_the_retrieval_stops_it_and_the_job_ends_canceled() {
    if !orthanc_present() {
        return;
    }
    let src = tempfile::tempdir().unwrap();
    let (uid, files) = synthetic(src.path(), 240);
    let node_port = free_port();
    let orthanc = orthanc_with(node_port, &files).await;
    let app = ctrecon(
        node_port,
        vec![peer("ORTHANC", orthanc.dicom_port, true, true)],
    )
    .await;
    let job = app.submit(&pull_job("ORTHANC", &uid)).await;
    let id = job["id"].as_str().unwrap().to_string();
    let during = app
        .wait_until(&id, 60, |j| {
            j["stage"]
                .as_str()
                .is_some_and(|s| s.starts_with("retrieving from ORTHANC"))
                || j["status"] != "queued" && j["status"] != "running"
        })
        .await;
    assert_eq!(during["status"], "running", "{during}");
    let r = app
        .client
        .post(app.url(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    let canceled_at = Instant::now();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "canceled", "{done}");
    assert!(done["result"].is_null(), "{done}");
    assert!(
        canceled_at.elapsed() < Duration::from_secs(5),
        "{:?}",
        canceled_at.elapsed()
    );
    // What had arrived is removed rather than left for the stable age to assemble.
    let incoming = app.dir.path().join("dimse/incoming");
    for _ in 0..50 {
        if files_in(&incoming) == 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(files_in(&incoming), 0);
}

#[tokio::test]
async fn a_pull_is_refused_at_submission_without_the_node_a_known_peer_retrieve_rights_or_a_valid_uid()
 {
    let uid = "1.2.826.0.1.3680043.2.1125.1";
    let off = common::spawn_app_with(|s| {
        s.dicom.peers = vec![peer("PACS", 104, true, true)];
    })
    .await;
    let r = off.post_json("/v1/jobs", &pull_job("PACS", uid)).await;
    let p = assert_problem(r, 409, "dicom_node_off").await;
    assert!(p["detail"].as_str().unwrap().contains("dicom.port"), "{p}");

    let on = common::spawn_app_with(|s| {
        s.dicom.port = Some(0);
        s.dicom.peers = vec![
            peer("PACS", 104, true, true),
            peer("NORETRIEVE", 105, true, false),
            peer("NOSTORE", 106, false, true),
        ];
    })
    .await;
    let r = on.post_json("/v1/jobs", &pull_job("ELSEWHERE", uid)).await;
    let p = assert_problem(r, 422, "unknown_peer").await;
    assert!(p["detail"].as_str().unwrap().contains("ELSEWHERE"), "{p}");
    for who in ["NORETRIEVE", "NOSTORE"] {
        let r = on.post_json("/v1/jobs", &pull_job(who, uid)).await;
        let p = assert_problem(r, 422, "peer_not_permitted").await;
        assert!(p["detail"].as_str().unwrap().contains(who), "{p}");
    }
    let r = on.post_json("/v1/jobs", &pull_job("PACS", "1.2.abc")).await;
    assert_problem(r, 422, "invalid_parameter").await;
    let mut extra = pull_job("PACS", uid);
    extra["input"]["study"] = json!("1.2");
    let r = on.post_json("/v1/jobs", &extra).await;
    let p = assert_problem(r, 422, "invalid_request").await;
    assert!(p["detail"].as_str().unwrap().contains("study"), "{p}");
    // Nothing was queued.
    let list: Value = on.get("/v1/jobs").await.json().await.unwrap();
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_readme_pull_example_runs_as_written_against_orthanc() {
    if !orthanc_present() {
        return;
    }
    let have = |t: &str| {
        std::process::Command::new(t)
            .arg("--version")
            .output()
            .is_ok()
    };
    if !(have("curl") && have("jq") && have("dcmdump")) {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "curl, jq or dcmdump is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: the README's pull example needs curl, jq and dcmdump");
        return;
    }
    let config = common::readme_blocks("json pacs-config");
    let scripts = common::readme_blocks("sh pacs-pull");
    assert_eq!((config.len(), scripts.len()), (1, 1));
    let config: Value = serde_json::from_str(&config[0]).unwrap();
    let mut node: ctrecon::dimse::NodeSettings =
        serde_json::from_value(config["dicom"].clone()).unwrap();
    let node_port = free_port();
    let o = orthanc_with(node_port, &[]).await;
    node.port = Some(node_port);
    for p in &mut node.peers {
        if p.ae_title == "ORTHANC" {
            p.port = o.dicom_port;
        }
    }
    let app = common::spawn_app_with(|s| s.dicom = node).await;
    let work = tempfile::tempdir().unwrap();
    let (uid, _) = synthetic(&work.path().join("series"), 6);
    let host = app.base.trim_start_matches("http://").to_string();
    let script = format!(
        "set -euo pipefail\ncurl() {{ command curl --fail-with-body \"$@\"; }}\n{}",
        scripts[0]
            .replace("localhost:8080", &host)
            .replace(" 4242 ", &format!(" {} ", o.dicom_port))
    );
    let dir = work.path().to_path_buf();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("timeout")
            .args(["300", "bash", "-c"])
            .arg(&script)
            .current_dir(dir)
            .env("TCP_NODELAY", "1")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expected: Vec<&str> = scripts[0]
        .lines()
        .filter_map(|l| {
            l.trim()
                .strip_prefix("# {")
                .map(|_| l.trim().trim_start_matches("# "))
        })
        .collect();
    let printed: Vec<&str> = stdout.lines().filter(|l| l.starts_with('{')).collect();
    assert_eq!(printed, expected, "{stdout}");
    // The job pulled the series written above.
    let jobs: Value = app.get("/v1/jobs?expand=all").await.json().await.unwrap();
    let series = jobs["jobs"][0]["result"]["source_series"]
        .as_str()
        .unwrap()
        .to_string();
    let s: Value = app
        .get(&format!("/v1/series/{series}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(s["series_uid"], uid.as_str(), "{s}");
}

fn dcmtk_present() -> bool {
    let ok = ["findscu", "movescu", "storescu", "storescp"]
        .iter()
        .all(|t| {
            std::process::Command::new(t)
                .arg("--version")
                .output()
                .is_ok()
        });
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "DCMTK (findscu, movescu, storescu, storescp) is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: DCMTK is not installed (apt-get install dcmtk)");
    }
    ok
}

/// A DCMTK tool run to its end (TCP_NODELAY set, as PEERS.md advises), in `cwd` when given.
async fn run(tool: &str, args: &[String], cwd: Option<&Path>) -> std::process::Output {
    let (tool, args, cwd) = (tool.to_string(), args.to_vec(), cwd.map(Path::to_path_buf));
    tokio::task::spawn_blocking(move || {
        let mut c = std::process::Command::new(tool);
        c.args(args).env("TCP_NODELAY", "1");
        if let Some(d) = cwd {
            c.current_dir(d);
        }
        c.output().unwrap()
    })
    .await
    .unwrap()
}

fn strings(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

fn text(o: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A child process killed when dropped.
struct Running(std::process::Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `storescp` as `DEST` on `port`, writing into `dir`, with extra `options`.
fn storescp(port: u16, dir: &Path, options: &[String]) -> Running {
    let mut a = strings(&["--aetitle", "DEST", "--output-directory"]);
    a.push(dir.to_string_lossy().into_owned());
    a.extend(options.iter().cloned());
    a.push(port.to_string());
    Running(
        std::process::Command::new("storescp")
            .args(a)
            .env("TCP_NODELAY", "1")
            .spawn()
            .unwrap(),
    )
}

/// `findscu` (Study Root) at IMAGE level for `series_uid` with extra `options`: its output and the number of
/// match responses it received (each extracted to a file).
async fn find_images(
    node_port: u16,
    series_uid: &str,
    options: &[&str],
) -> (std::process::Output, usize) {
    let out_dir = tempfile::tempdir().unwrap();
    let mut a = strings(&["-S", "-v", "-X", "-aet", "TESTSCU", "-aec", "CTRECON"]);
    a.extend(strings(options));
    for k in [
        "QueryRetrieveLevel=IMAGE".to_string(),
        format!("SeriesInstanceUID={series_uid}"),
        "SOPInstanceUID".to_string(),
    ] {
        a.push("-k".into());
        a.push(k);
    }
    a.extend(strings(&["127.0.0.1", &node_port.to_string()]));
    let out = run("findscu", &a, Some(out_dir.path())).await;
    (out, files_in(out_dir.path()))
}

/// Whether a DCMTK tool's output reports a final response with status Cancel (FE00).
fn says_canceled(o: &std::process::Output) -> bool {
    text(o).lines().any(|l| {
        let l = l.to_lowercase();
        (l.contains("final") || l.contains("status"))
            && (l.contains("cancel") || l.contains("fe00"))
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_c_cancel_stops_a_c_find_and_a_c_move_in_progress_with_the_counts_so_far() {
    if !dcmtk_present() {
        return;
    }
    let n = 300;
    let src = tempfile::tempdir().unwrap();
    let (uid, _) = synthetic(src.path(), n);
    let node_port = free_port();
    let dest_port = free_port();
    let app = ctrecon(
        node_port,
        vec![
            peer("TESTSCU", 1, true, true),
            peer("DEST", dest_port, true, true),
        ],
    )
    .await;
    let sent = run(
        "storescu",
        &strings(&[
            "-aet",
            "TESTSCU",
            "-aec",
            "CTRECON",
            "+sd",
            "127.0.0.1",
            &node_port.to_string(),
            &src.path().to_string_lossy(),
        ]),
        None,
    )
    .await;
    assert!(sent.status.success(), "{}", text(&sent));
    // The series is assembled and indexed once its stable age passed.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, found) = find_images(node_port, &uid, &[]).await;
        if found == n {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{found} of {n} instances indexed"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }

    // C-FIND: findscu cancels after the first match; the node stops and answers Cancel.
    let (out, found) = find_images(node_port, &uid, &["--cancel", "1"]).await;
    assert!(says_canceled(&out), "{}", text(&out));
    assert!(
        (1..n).contains(&found),
        "{found} matches of {n} before the cancel took effect"
    );

    // C-MOVE: movescu cancels after the first pending response; the node stops sending to DEST.
    let received = tempfile::tempdir().unwrap();
    let _dest = storescp(dest_port, received.path(), &[]);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut a = strings(&[
        "-S", "-v", "-aet", "TESTSCU", "-aem", "DEST", "-aec", "CTRECON", "--cancel", "1",
    ]);
    for k in [
        "QueryRetrieveLevel=SERIES".to_string(),
        format!("SeriesInstanceUID={uid}"),
    ] {
        a.push("-k".into());
        a.push(k);
    }
    a.extend(strings(&["127.0.0.1", &node_port.to_string()]));
    let out = run("movescu", &a, None).await;
    assert!(says_canceled(&out), "{}", text(&out));
    let stored = files_in(received.path());
    assert!(
        (1..n).contains(&stored),
        "{stored} instances of {n} moved before the cancel took effect"
    );

    // The node is still there and answers the whole series again.
    let (_, found) = find_images(node_port, &uid, &[]).await;
    assert_eq!(found, n);
    drop(app);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_peer_that_accepts_only_ct_in_implicit_vr_gets_the_ct_re_encoded_and_the_rest_fails_per_instance()
 {
    if !dcmtk_present() {
        return;
    }
    let dest_port = free_port();
    let received = tempfile::tempdir().unwrap();
    let cfg = received.path().join("ct-implicit.cfg");
    std::fs::write(
        &cfg,
        "[[TransferSyntaxes]]\n[ImplicitOnly]\nTransferSyntax1 = LittleEndianImplicit\n\n\
         [[PresentationContexts]]\n[CTOnly]\nPresentationContext1 = VerificationSOPClass\\ImplicitOnly\n\
         PresentationContext2 = CTImageStorage\\ImplicitOnly\n\n[[Profiles]]\n[CTImplicit]\n\
         PresentationContexts = CTOnly\n",
    )
    .unwrap();
    let out_dir = received.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let _dest = storescp(
        dest_port,
        &out_dir,
        &strings(&["-xf", &cfg.to_string_lossy(), "CTImplicit"]),
    );
    let app = common::spawn_app_with(|s| {
        s.dicom.peers = vec![peer("DEST", dest_port, true, true)];
    })
    .await;
    let src = tempfile::tempdir().unwrap();
    let (_, files) = synthetic(src.path(), 8);
    let mut form = reqwest::multipart::Form::new();
    for f in &files {
        form = form.part(
            "file",
            reqwest::multipart::Part::bytes(std::fs::read(f).unwrap())
                .file_name("x.dcm")
                .mime_str("application/dicom")
                .unwrap(),
        );
    }
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let up: Value = r.json().await.unwrap();
    let series = up["series"][0]["series"]["id"]
        .as_str()
        .unwrap()
        .to_string();
    // A derived CT series (axial planes every 2.5 mm) and a Secondary Capture MIP.
    let job = app
        .submit(&json!({"kind": "volume", "input": series, "products": [
            {"type": "mpr", "plane": "axial", "spacing_mm": 2.5},
            {"type": "projection", "axis": "axial", "kind": "mip"}]}))
        .await;
    let job_id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&job_id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let r = app
        .post_json(
            "/v1/deliveries",
            &json!({"job_id": job_id, "destination": "DEST"}),
        )
        .await;
    assert!(r.status().is_success(), "{}", r.status());
    let d: Value = r.json().await.unwrap();
    let path = format!("/v1/deliveries/{}", d["id"].as_str().unwrap());
    let deadline = Instant::now() + Duration::from_secs(60);
    let d = loop {
        let v: Value = app.get(&path).await.json().await.unwrap();
        if matches!(v["state"].as_str(), Some("succeeded" | "failed")) {
            break v;
        }
        assert!(Instant::now() < deadline, "{v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let instances = d["instances"].as_array().unwrap();
    let ct: Vec<&Value> = instances
        .iter()
        .filter(|i| i["sop_class_uid"] == "1.2.840.10008.5.1.4.1.1.2")
        .collect();
    let others: Vec<&Value> = instances
        .iter()
        .filter(|i| i["sop_class_uid"] != "1.2.840.10008.5.1.4.1.1.2")
        .collect();
    assert!(!ct.is_empty() && !others.is_empty(), "{d}");
    for i in &ct {
        assert_eq!(i["state"], "succeeded", "{d}");
        assert_eq!(i["status"], 0, "{d}");
    }
    for i in &others {
        assert_eq!(i["state"], "failed", "{d}");
        let detail = i["detail"].as_str().unwrap_or_default();
        assert!(
            detail.contains("DEST") && detail.contains("Secondary Capture Image Storage"),
            "{detail}"
        );
    }
    // storescp holds the CT instances, in implicit VR little endian, with the exported pixel values.
    let exported = app.dir.path().join(format!("results/{job_id}/dicom"));
    let originals: std::collections::BTreeMap<String, PathBuf> = std::fs::read_dir(&exported)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "dcm"))
        .map(|p| (ctrecon::dicom::read_part10(&p).unwrap().sop_instance_uid, p))
        .collect();
    let got: Vec<PathBuf> = std::fs::read_dir(&out_dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    assert_eq!(got.len(), ct.len());
    let limits = ctrecon::dicom::ReadLimits::default();
    for f in &got {
        let p10 = ctrecon::dicom::read_part10(f).unwrap();
        assert_eq!(p10.transfer_syntax, "1.2.840.10008.1.2");
        let sent = ctrecon::dicom::read_path(f, &limits).unwrap();
        let original =
            ctrecon::dicom::read_path(&originals[&p10.sop_instance_uid], &limits).unwrap();
        assert_eq!(original.transfer_syntax, "1.2.840.10008.1.2.1");
        assert!(sent.slices[0].stored == original.slices[0].stored);
        assert_eq!(sent.slices[0].position_mm, original.slices[0].position_mm);
    }
}
