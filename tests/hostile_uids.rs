//! Malformed UIDs on every door: a file whose Study, Series, SOP Instance, SOP Class or Frame of Reference
//! UID is a path, 10 001 digits, holds a NUL, has a leading zero, an empty component or 65 characters is
//! refused with `dicom_invalid_uid` by a ZIP upload, a multipart form, an appended `application/dicom`
//! instance, STOW-RS and C-STORE alike; nothing of it is stored or indexed, and nothing is written outside
//! the data directory.

use crate::common;
use crate::dw;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use ctrecon::dimse::Peer;
use ctrecon::dimse::command::status;
use ctrecon::dimse::scu::{self, Caller};
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::tags;
use serde_json::Value;

/// A caller the test servers let store.
pub fn store_peer() -> Peer {
    Peer {
        ae_title: "TESTSCU".into(),
        host: "127.0.0.1".into(),
        port: 1,
        store: true,
        query: true,
        retrieve: true,
    }
}

/// A server with its DICOM node on, series stable after a second, open to [`store_peer`].
pub async fn node_app() -> common::TestApp {
    common::spawn_app_with(|s| {
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = 1;
        s.dicom.peers = vec![store_peer()];
        s.max_upload_bytes = 64 << 20;
    })
    .await
}

/// C-STORE `files` to the node of `app` with ctrecon's own SCU, one association.
pub async fn c_store(app: &common::TestApp, files: &[PathBuf]) -> Vec<scu::StoreOutcome> {
    let caller = Caller {
        ae_title: "TESTSCU".into(),
        timeout: Duration::from_secs(20),
        max_pdu_length: 16384,
    };
    let peer = Peer {
        ae_title: "CTRECON".into(),
        port: app.dicom.expect("a DICOM node").port(),
        ..store_peer()
    };
    scu::store(&caller, &peer, files)
        .await
        .expect("an association")
}

/// The hostile values: what each one is, and the value.
fn bad_uids() -> Vec<(&'static str, String)> {
    vec![
        ("a path", "../../../tmp/pwned".to_string()),
        ("10 001 digits", "9".repeat(10_001)),
        ("a NUL inside", "1.2.3\0.4".to_string()),
        ("a leading zero", "1.02.3".to_string()),
        ("two dots", "1..2".to_string()),
        ("an empty last component", "1.2.".to_string()),
        ("65 characters", format!("1.{}", "2".repeat(63))),
    ]
}

/// `good` (a Part 10 file) with `tag` set to `value`; with `meta`, a SOP Instance UID goes into the file
/// meta too (so that a C-STORE request carries it as well).
fn with_uid(good: &[u8], tag: Tag, value: &str, meta: bool) -> Vec<u8> {
    let mut obj = dicom_object::from_reader(&good[128..]).expect("a Part 10 file");
    obj.put(DataElement::new(tag, VR::UI, PrimitiveValue::from(value)));
    if meta && tag == tags::SOP_INSTANCE_UID {
        obj.meta_mut().media_storage_sop_instance_uid = value.to_string();
        obj.meta_mut().update_information_group_length();
    }
    let mut out = Vec::new();
    obj.write_all(&mut out).expect("written");
    out
}

/// Every hostile file: (what, the file); with `meta`, a hostile SOP Instance UID is in the file meta too.
fn hostile_files(good: &[u8], meta: bool) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = bad_uids()
        .into_iter()
        .map(|(what, v)| {
            (
                format!("Study Instance UID, {what}"),
                with_uid(good, tags::STUDY_INSTANCE_UID, &v, meta),
            )
        })
        .collect();
    for (name, tag) in [
        ("Series Instance UID", tags::SERIES_INSTANCE_UID),
        ("SOP Instance UID", tags::SOP_INSTANCE_UID),
        ("Frame of Reference UID", tags::FRAME_OF_REFERENCE_UID),
        ("SOP Class UID", tags::SOP_CLASS_UID),
    ] {
        for (what, v) in bad_uids().into_iter().take(3) {
            out.push((format!("{name}, {what}"), with_uid(good, tag, &v, meta)));
        }
    }
    out
}

async fn post(app: &common::TestApp, path: &str, media: &str, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url(path))
        .header("content-type", media)
        .body(body)
        .send()
        .await
        .expect("request")
}

/// The problem answered: (status, code).
async fn problem(r: reqwest::Response) -> (u16, String) {
    let s = r.status().as_u16();
    let v: Value = r.json().await.unwrap_or(Value::Null);
    (s, v["code"].as_str().unwrap_or("").to_string())
}

fn files_under(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            files_under(&p, out);
        } else {
            out.push(p);
        }
    }
}

#[tokio::test]
async fn every_bad_uid_is_refused_on_every_door_with_one_code_and_nothing_is_kept() {
    let app = node_app().await;
    let (_, _, files) = dw::synthetic(3, None, "UID-1");
    let cases = hostile_files(&files[0], true);
    let want = (422, "dicom_invalid_uid".to_string());
    let src = tempfile::tempdir().unwrap();
    let mut on_disk = Vec::new();
    for (what, bytes) in &cases {
        // ZIP.
        let zip = ctrecon::dicom::write_zip(&[("bad.dcm".to_string(), bytes.clone())]).unwrap();
        let got = problem(post(&app, "/v1/series", "application/zip", zip).await).await;
        assert_eq!(got, want, "ZIP, {what}");
        // Multipart form.
        let form = reqwest::multipart::Form::new().part(
            "file",
            reqwest::multipart::Part::bytes(bytes.clone()).file_name("bad.dcm"),
        );
        let r = app
            .client
            .post(app.url("/v1/series"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        assert_eq!(problem(r).await, want, "multipart, {what}");
        // One instance appended (opening an upload).
        let got = problem(post(&app, "/v1/series", "application/dicom", bytes.clone()).await).await;
        assert_eq!(got, want, "append, {what}");
        // STOW-RS: the part fails (no part stored: 409) with FailureReason C000 and the code in a Warning.
        let r = post(
            &app,
            "/dicom-web/studies",
            dw::STOW_TYPE,
            dw::multipart(&[("application/dicom", bytes.as_slice())]),
        )
        .await;
        let warning = r
            .headers()
            .get("warning")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        assert_eq!(r.status(), 409, "STOW-RS, {what}");
        let v: Value = r.json().await.unwrap();
        assert_eq!(
            dw::seq_values(&v, "00081198", "00081197"),
            ["49152".to_string()].into(),
            "STOW-RS, {what}: {v}"
        );
        assert!(
            warning.starts_with("299 ctrecon \"part 1: dicom_invalid_uid: "),
            "STOW-RS, {what}: {warning}"
        );
        assert!(!warning.contains("pwned/"), "{warning}");
    }
    // C-STORE: every hostile file in one association, each refused with C000 and the code first in the
    // Error Comment. ctrecon's own SCU reads a file meta group as strictly as the node: a hostile SOP
    // Instance UID is in the data set only here, and in the request by `storescu` below.
    let sent = hostile_files(&files[0], false);
    for (k, (_, bytes)) in sent.iter().enumerate() {
        let path = src.path().join(format!("bad-{k}.dcm"));
        std::fs::write(&path, bytes).unwrap();
        on_disk.push(path);
    }
    let out = c_store(&app, &on_disk).await;
    assert_eq!(out.len(), sent.len());
    for ((what, _), o) in sent.iter().zip(&out) {
        assert_eq!(
            o.status,
            Some(status::CANNOT_UNDERSTAND),
            "C-STORE, {what}: {o:?}"
        );
        let comment = o.detail.as_deref().unwrap_or("");
        assert!(
            comment.starts_with("dicom_invalid_uid: "),
            "C-STORE, {what}: {comment}"
        );
    }
    // The request's Affected SOP Instance UID itself malformed (DCMTK sends what the file meta says).
    if crate::resent_instances::dcmtk_present() {
        let dir = src.path().join("meta");
        std::fs::create_dir_all(&dir).unwrap();
        for (k, (what, bytes)) in cases.iter().enumerate() {
            if !what.starts_with("SOP Instance UID") {
                continue;
            }
            let path = dir.join(format!("bad-{k}.dcm"));
            std::fs::write(&path, bytes).unwrap();
            let out = crate::resent_instances::storescu_output(&app, &["-d"], &[path]).await;
            // DCMTK cuts a long UID to 64 characters in the request: the data set's is then refused.
            assert!(
                out.contains("0xc000: Error: Cannot understand")
                    && out.contains("[dicom_invalid_uid: "),
                "storescu, {what}: {out}"
            );
        }
    }
    // A good series beside a bad file: stored, the bad file listed with the same code.
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default();
    for (i, f) in files.iter().enumerate() {
        zip.start_file(format!("IM{i}.dcm"), opts).unwrap();
        zip.write_all(f).unwrap();
    }
    zip.start_file("pwned.dcm", opts).unwrap();
    zip.write_all(&cases[0].1).unwrap();
    let body = zip.finish().unwrap().into_inner();
    let r = post(&app, "/v1/series", "application/zip", body).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["rejected"][0]["file"], "pwned.dcm", "{v}");
    assert_eq!(v["rejected"][0]["code"], "dicom_invalid_uid", "{v}");
    assert_eq!(v["series"][0]["report"]["instances"], 3, "{v}");

    // Nothing of the hostile files was kept: the index holds the good series only, no upload stayed open,
    // the node filed nothing, and no file anywhere under the data directory is named after a UID.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let core = app.core.as_ref().unwrap();
    let rows = core
        .db
        .indexed_instances(&Default::default())
        .await
        .unwrap();
    assert_eq!(rows.len(), 3, "{rows:?}");
    assert!(
        rows.iter()
            .all(|r| ctrecon::dicom::is_valid_uid(&r.instance.study_uid))
    );
    let mut all = Vec::new();
    files_under(app.dir.path(), &mut all);
    for p in &all {
        let rel = p.strip_prefix(app.dir.path()).unwrap().to_string_lossy();
        assert!(!rel.contains("pwned") && !rel.contains(".."), "{rel}");
    }
    let count = |sub: &str| {
        let mut v = Vec::new();
        files_under(&app.dir.path().join(sub), &mut v);
        v.len()
    };
    assert_eq!((count("instances"), count("series")), (3, 1));
    assert_eq!((count("uploads"), count("tmp")), (0, 0));
    assert_eq!((count("dimse/incoming"), count("dimse/tmp")), (0, 0));
    assert!(!Path::new("/tmp/pwned").exists());
}
