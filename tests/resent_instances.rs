//! Instances sent again, on every door: the index keeps one copy per SOP Instance UID (the same bytes are
//! recognised, other bytes replace the earlier copy) and a series is assembled again only when what it
//! assembles to changed. `storescu` sends need DCMTK (one skip line without it, unless
//! `CTRECON_REQUIRE_PEERS=1`).

use crate::common;
use crate::dw;
use crate::hostile_uids::node_app;

use std::path::{Path, PathBuf};
use std::time::Duration;

use ctrecon::jobs::model::IndexScope;
use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use serde_json::Value;

pub fn dcmtk_present() -> bool {
    let ok = std::process::Command::new("storescu")
        .arg("--version")
        .output()
        .is_ok();
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "DCMTK (storescu) is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: DCMTK is not installed (apt-get install dcmtk)");
    }
    ok
}

/// `storescu` with `options` sending `files` as TESTSCU in one association: whether it succeeded, and what
/// it printed.
async fn run_storescu(
    app: &common::TestApp,
    options: &[&str],
    files: &[PathBuf],
) -> (bool, String) {
    let port = app.dicom.expect("a DICOM node").port().to_string();
    let mut args: Vec<String> = options.iter().map(|s| s.to_string()).collect();
    args.extend(
        ["-aet", "TESTSCU", "-aec", "CTRECON", "127.0.0.1", &port]
            .iter()
            .map(|s| s.to_string()),
    );
    args.extend(files.iter().map(|f| f.to_string_lossy().into_owned()));
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("storescu")
            .args(args)
            .env("TCP_NODELAY", "1")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// What `storescu` with `options` printed sending `files`.
pub async fn storescu_output(app: &common::TestApp, options: &[&str], files: &[PathBuf]) -> String {
    run_storescu(app, options, files).await.1
}

/// `storescu` sending `files`; asserts it succeeded.
async fn storescu(app: &common::TestApp, files: &[PathBuf]) {
    let (ok, text) = run_storescu(app, &[], files).await;
    assert!(ok, "{text}");
}

fn files_under(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| {
            if e.path().is_dir() {
                files_under(&e.path())
            } else {
                1
            }
        })
        .sum()
}

/// Wait until the node has handed every arrival over and the application recorded it (its folders empty).
async fn node_settled(app: &common::TestApp) {
    let dimse = app.dir.path().join("dimse");
    for _ in 0..1500 {
        if files_under(&dimse.join("incoming")) + files_under(&dimse.join("complete")) == 0 {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("the node did not hand its arrivals over within 30 s");
}

/// What is kept of series `uid`: (instance rows, distinct SOP Instance UIDs, series rows), and the files
/// under `instances/` and `series/` of the whole data directory.
async fn kept(app: &common::TestApp, uid: &str) -> ((usize, usize, usize), (usize, usize)) {
    let db = &app.core.as_ref().unwrap().db;
    let scope = IndexScope {
        study_uid: None,
        series_uid: Some(uid.to_string()),
    };
    let rows = db.indexed_instances(&scope).await.unwrap();
    let sops: std::collections::HashSet<_> = rows
        .iter()
        .map(|r| r.instance.sop_instance_uid.clone())
        .collect();
    let series = db.series_with_uid(uid).await.unwrap().len();
    let dir = app.dir.path();
    (
        (rows.len(), sops.len(), series),
        (
            files_under(&dir.join("instances")),
            files_under(&dir.join("series")),
        ),
    )
}

/// Wait until series `uid` has `n` series rows (at most 30 s).
async fn series_rows(app: &common::TestApp, uid: &str, n: usize) {
    for _ in 0..1500 {
        if kept(app, uid).await.0.2 >= n {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("series {uid} did not get {n} series rows within 30 s");
}

/// `good` with its Rescale Intercept one HU higher: the same SOP Instance UID, other content.
fn changed(good: &[u8]) -> Vec<u8> {
    let mut obj = dicom_object::from_reader(&good[128..]).expect("a Part 10 file");
    let b = obj
        .element(tags::RESCALE_INTERCEPT)
        .ok()
        .and_then(|e| e.to_float64().ok())
        .unwrap_or(0.0);
    let v = format!("{}", b + 1.0);
    obj.put(DataElement::new(
        tags::RESCALE_INTERCEPT,
        VR::DS,
        PrimitiveValue::from(v),
    ));
    let mut out = Vec::new();
    obj.write_all(&mut out).expect("written");
    out
}

fn write_all(dir: &Path, files: &[Vec<u8>]) -> Vec<PathBuf> {
    files
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let p = dir.join(format!("IM{i:03}.dcm"));
            std::fs::write(&p, b).unwrap();
            p
        })
        .collect()
}

#[tokio::test]
async fn a_series_sent_four_times_by_storescu_is_kept_once_and_rebuilt_only_when_it_changed() {
    if !dcmtk_present() {
        return;
    }
    let app = node_app().await;
    let src = tempfile::tempdir().unwrap();
    let (_, uid, files) = dw::synthetic(5, None, "RESEND-1");
    let paths = write_all(src.path(), &files);
    for send in 1..=4 {
        storescu(&app, &paths).await;
        if send == 1 {
            series_rows(&app, &uid, 1).await;
        }
        node_settled(&app).await;
        assert_eq!(
            kept(&app, &uid).await,
            ((5, 5, 1), (5, 1)),
            "after send {send}"
        );
    }
    // The same files through the other doors: recognised too.
    let zip = ctrecon::dicom::write_zip(
        &files
            .iter()
            .enumerate()
            .map(|(i, b)| (format!("IM{i}.dcm"), b.clone()))
            .collect::<Vec<_>>(),
    )
    .unwrap();
    let r = app
        .client
        .post(app.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let stored = app
        .core
        .as_ref()
        .unwrap()
        .db
        .series_with_uid(&uid)
        .await
        .unwrap();
    assert_eq!(
        v["series"][0]["series"]["id"],
        stored[0].id.to_string(),
        "{v}"
    );
    assert!(
        v["series"][0]["report"]["warnings"]
            .to_string()
            .contains("series_already_stored"),
        "{v}"
    );
    let parts: Vec<(&str, &[u8])> = files
        .iter()
        .map(|b| ("application/dicom", b.as_slice()))
        .collect();
    let (status, _) = dw::stow(
        &app.client,
        app.url("/dicom-web/studies"),
        dw::multipart(&parts),
    )
    .await;
    assert_eq!(status, 200);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        kept(&app, &uid).await,
        ((5, 5, 1), (5, 1)),
        "after the ZIP and STOW-RS"
    );

    // One instance with other content replaces its copy, and the series is rebuilt once, whole.
    let other = src.path().join("changed");
    std::fs::create_dir_all(&other).unwrap();
    let changed_path = write_all(&other, &[changed(&files[2])]);
    storescu(&app, &changed_path).await;
    series_rows(&app, &uid, 2).await;
    node_settled(&app).await;
    assert_eq!(kept(&app, &uid).await, ((5, 5, 2), (5, 2)));
    let newest = &app
        .core
        .as_ref()
        .unwrap()
        .db
        .series_with_uid(&uid)
        .await
        .unwrap()[0];
    assert_eq!(newest.instances, 5);
    // Sent again as it is now: nothing more.
    storescu(&app, &changed_path).await;
    node_settled(&app).await;
    assert_eq!(kept(&app, &uid).await, ((5, 5, 2), (5, 2)));
}

#[tokio::test]
async fn a_retry_loop_sending_one_instance_fifty_times_leaves_one_copy() {
    if !dcmtk_present() {
        return;
    }
    let app = node_app().await;
    let src = tempfile::tempdir().unwrap();
    let (_, uid, files) = dw::synthetic(5, None, "RESEND-2");
    let one = write_all(src.path(), &files[..1]);
    // Five associations of ten C-STOREs of the same instance, each after the last was handed over.
    let mut after_first = None;
    for round in 0..5 {
        storescu(&app, &vec![one[0].clone(); 10]).await;
        node_settled(&app).await;
        tokio::time::sleep(Duration::from_millis(1200)).await;
        node_settled(&app).await;
        let now = kept(&app, &uid).await;
        assert_eq!(
            (now.0.0, now.0.1, now.1.0),
            (1, 1, 1),
            "after round {round}"
        );
        assert_eq!(*after_first.get_or_insert(now), now, "after round {round}");
    }
}

#[tokio::test]
async fn four_http_uploads_and_four_stows_of_one_series_keep_five_instances_and_one_series() {
    let app = node_app().await;
    let (_, uid, files) = dw::synthetic(5, None, "RESEND-3");
    let named: Vec<(String, Vec<u8>)> = files
        .iter()
        .enumerate()
        .map(|(i, b)| (format!("IM{i}.dcm"), b.clone()))
        .collect();
    let mut ids = Vec::new();
    for send in 1..=4 {
        // ZIP and multipart forms in turn.
        let req = app.client.post(app.url("/v1/series"));
        let req = if send % 2 == 1 {
            req.header("content-type", "application/zip")
                .body(ctrecon::dicom::write_zip(&named).unwrap())
        } else {
            req.multipart(
                named
                    .iter()
                    .fold(reqwest::multipart::Form::new(), |f, (n, b)| {
                        f.part(
                            "file",
                            reqwest::multipart::Part::bytes(b.clone()).file_name(n.clone()),
                        )
                    }),
            )
        };
        let r = req.send().await.unwrap();
        assert_eq!(r.status(), 201, "upload {send}");
        let v: Value = r.json().await.unwrap();
        ids.push(v["series"][0]["series"]["id"].as_str().unwrap().to_string());
        let warned = v["series"][0]["report"]["warnings"]
            .to_string()
            .contains("series_already_stored");
        assert_eq!(warned, send > 1, "upload {send}: {v}");
        assert_eq!(
            kept(&app, &uid).await,
            ((5, 5, 1), (5, 1)),
            "after upload {send}"
        );
    }
    assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");

    // Another series by STOW-RS, four times: indexed once, assembled once.
    let (_, uid, files) = dw::synthetic(5, None, "RESEND-4");
    let parts: Vec<(&str, &[u8])> = files
        .iter()
        .map(|b| ("application/dicom", b.as_slice()))
        .collect();
    for send in 1..=4 {
        let (status, v) = dw::stow(
            &app.client,
            app.url("/dicom-web/studies"),
            dw::multipart(&parts),
        )
        .await;
        assert_eq!(status, 200, "STOW-RS {send}: {v}");
        assert_eq!(dw::seq_values(&v, "00081199", "00081155").len(), 5);
        assert_eq!(kept(&app, &uid).await.0.0, 5, "after STOW-RS {send}");
    }
    series_rows(&app, &uid, 1).await;
    let (_, again) = dw::stow(
        &app.client,
        app.url("/dicom-web/studies"),
        dw::multipart(&parts),
    )
    .await;
    assert_eq!(dw::seq_values(&again, "00081199", "00081155").len(), 5);
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert_eq!(kept(&app, &uid).await, ((5, 5, 1), (10, 2)));
}
