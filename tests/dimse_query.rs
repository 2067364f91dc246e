//! C-FIND and C-MOVE of the DICOM node against DCMTK: `storescu` sends synthetic series with known
//! attributes into a running service, `findscu` queries them at study, series and image level (responses
//! extracted as files and read back), `movescu` retrieves them into `storescp`; derived results of a volume
//! job are found next to their source; the index outlives the process that wrote it.
//!
//! DCMTK comes from Debian's `dcmtk` package. Without it each test prints one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1` (as in CI), when it fails.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::Duration;

use common::TestApp;
use ctrecon::dicom::{ReadLimits, SeriesMeta, read_part10, read_path, write_ct_series};
use ctrecon::dimse::Peer;
use ctrecon::volume::{Frame, Volume};
use dicom_core::header::Header as _;
use dicom_object::OpenFileOptions;

fn dcmtk_present() -> bool {
    let ok = ["findscu", "movescu", "storescu", "storescp", "dcmodify"]
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
            "DCMTK (findscu, movescu, storescu, storescp, dcmodify) is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: DCMTK is not installed (apt-get install dcmtk)");
    }
    ok
}

fn peer(ae: &str, port: u16, query: bool, retrieve: bool) -> Peer {
    Peer {
        ae_title: ae.into(),
        host: "127.0.0.1".into(),
        port,
        store: true,
        query,
        retrieve,
    }
}

include!("common/ports.rs");

async fn run(tool: &str, args: &[String], cwd: Option<&Path>) -> Output {
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

/// Whether a DCMTK tool's final response names one of `statuses` (hex code or DCMTK's name, any case).
fn says(o: &Output, statuses: &[&str]) -> bool {
    let t = text(o).to_lowercase().replace([' ', '_'], "");
    t.lines()
        .filter(|l| {
            l.contains("finalfindresponse")
                || l.contains("finalmoveresponse")
                || l.contains("status")
        })
        .any(|l| statuses.iter().any(|s| l.contains(s)))
}

fn args(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A study written to `dir`: `nz` CT slices of 24 × 20 with the patient and study attributes given, set by
/// `dcmodify` after the crate's writer made the series. Returns (study UID, series UID, SOP UIDs, files).
struct Written {
    study_uid: String,
    series_uid: String,
    sop_uids: BTreeSet<String>,
    files: Vec<PathBuf>,
}

fn frame() -> Frame {
    Frame {
        origin_mm: [-12.0, -10.0, 30.0],
        spacing_mm: [1.0, 1.0, 2.5],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    }
}

async fn write_study(dir: &Path, nz: usize, patient: &str, attrs: &[(&str, &str)]) -> Written {
    write_series(dir, (nz, 20, 24), None, patient, attrs).await
}

/// A series of `shape` slices (in study `study_uid`, or a new study), as [`write_study`].
async fn write_series(
    dir: &Path,
    shape: (usize, usize, usize),
    study_uid: Option<String>,
    patient: &str,
    attrs: &[(&str, &str)],
) -> Written {
    let data =
        ndarray::Array3::from_shape_fn(shape, |(k, j, i)| (k * 100 + j * 10 + i) as f32 - 1000.0);
    let meta = SeriesMeta {
        study_uid,
        patient_id: Some(patient.into()),
        series_description: "query test".into(),
        series_number: 3,
        ..Default::default()
    };
    let s = write_ct_series(
        &Volume {
            data,
            frame: frame(),
        },
        &meta,
    )
    .unwrap();
    std::fs::create_dir_all(dir).unwrap();
    let mut files = Vec::new();
    for (name, bytes) in &s.files {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        files.push(p);
    }
    let mut a = vec!["-nb".to_string()];
    for (k, v) in attrs {
        a.push("-i".into());
        a.push(format!("{k}={v}"));
    }
    a.extend(files.iter().map(|f| f.to_string_lossy().into_owned()));
    let out = run("dcmodify", &a, None).await;
    assert!(out.status.success(), "{}", text(&out));
    let sop_uids = files
        .iter()
        .map(|f| {
            read_path(f, &ReadLimits::default())
                .unwrap()
                .sop_instance_uid
        })
        .collect();
    Written {
        study_uid: s.study_uid,
        series_uid: s.series_uid,
        sop_uids,
        files,
    }
}

async fn storescu(port: u16, dir: &Path) {
    let out = run(
        "storescu",
        &args(&[
            "-aet",
            "TESTSCU",
            "-aec",
            "CTRECON",
            "+sd",
            "+r",
            "127.0.0.1",
            &port.to_string(),
            &dir.to_string_lossy(),
        ]),
        None,
    )
    .await;
    assert!(out.status.success(), "{}", text(&out));
}

/// One response identifier: tag → value.
type Identifier = BTreeMap<u32, String>;

fn read_identifier(path: &Path) -> Identifier {
    let obj = OpenFileOptions::new()
        .open_file(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    obj.iter()
        .map(|e| {
            let t = e.tag();
            let v = e
                .to_str()
                .map(|s| s.trim_matches([' ', '\0']).to_string())
                .unwrap_or_default();
            (((t.group() as u32) << 16) | t.element() as u32, v)
        })
        .collect()
}

/// `findscu -S` (Study Root) as `calling` with `keys`; returns its output and the identifiers it received.
async fn findscu(port: u16, calling: &str, keys: &[&str]) -> (Output, Vec<Identifier>) {
    findscu_in("-S", port, calling, keys).await
}

/// `findscu` in the information model `model` (`-S` Study Root, `-P` Patient Root).
async fn findscu_in(
    model: &str,
    port: u16,
    calling: &str,
    keys: &[&str],
) -> (Output, Vec<Identifier>) {
    let out_dir = tempfile::tempdir().unwrap();
    let mut a = args(&[model, "-v", "-X", "-aet", calling, "-aec", "CTRECON"]);
    for k in keys {
        a.push("-k".into());
        a.push(k.to_string());
    }
    a.extend(args(&["127.0.0.1", &port.to_string()]));
    let out = run("findscu", &a, Some(out_dir.path())).await;
    let mut files: Vec<PathBuf> = std::fs::read_dir(out_dir.path())
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.sort();
    (out, files.iter().map(|f| read_identifier(f)).collect())
}

const STUDY_UID: u32 = 0x0020_000D;
const SERIES_UID: u32 = 0x0020_000E;
const SOP_UID: u32 = 0x0008_0018;

/// Wait until an IMAGE-level query of `series_uid` answers `n` instances.
async fn wait_indexed(port: u16, study_uid: &str, series_uid: &str, n: usize) {
    for _ in 0..300 {
        let (_, found) = findscu(
            port,
            "TESTSCU",
            &[
                "QueryRetrieveLevel=IMAGE",
                &format!("StudyInstanceUID={study_uid}"),
                &format!("SeriesInstanceUID={series_uid}"),
                "SOPInstanceUID",
            ],
        )
        .await;
        if found.len() == n {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("series {series_uid} was not indexed with {n} instances within 30 s");
}

async fn spawn(peers: Vec<Peer>, stable_age_secs: u64) -> (TestApp, u16) {
    let app = common::spawn_app_with(|s| {
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = stable_age_secs;
        s.dicom.dimse_timeout_secs = 10;
        s.dicom.peers = peers;
    })
    .await;
    let port = app.dicom.expect("a DICOM node").port();
    (app, port)
}

fn values(found: &[Identifier], tag: u32) -> Vec<&str> {
    found
        .iter()
        .map(|f| f.get(&tag).map(String::as_str).unwrap_or("<absent>"))
        .collect()
}

#[tokio::test]
async fn findscu_finds_received_studies_at_each_level_with_wildcards_and_date_ranges() {
    if !dcmtk_present() {
        return;
    }
    let (app, port) = spawn(
        vec![
            peer("TESTSCU", 1, true, true),
            peer("NOQUERY", 1, false, false),
        ],
        1,
    )
    .await;
    let src = tempfile::tempdir().unwrap();
    let a = write_study(
        &src.path().join("a"),
        6,
        "PAT-A",
        &[
            ("PatientName", "Doe^Jane"),
            ("PatientBirthDate", "19700102"),
            ("PatientSex", "F"),
            ("StudyDate", "20200315"),
            ("StudyTime", "093000"),
            ("AccessionNumber", "ACC-1"),
            ("StudyDescription", "CT CHEST"),
            ("BodyPartExamined", "CHEST"),
        ],
    )
    .await;
    let b = write_study(
        &src.path().join("b"),
        4,
        "PAT-B",
        &[
            ("PatientName", "Roe^Richard"),
            ("StudyDate", "20210707"),
            ("AccessionNumber", "ACC-2"),
            ("StudyDescription", "CT HEAD"),
        ],
    )
    .await;
    storescu(port, src.path()).await;
    wait_indexed(port, &a.study_uid, &a.series_uid, 6).await;
    wait_indexed(port, &b.study_uid, &b.series_uid, 4).await;

    // STUDY level, every study: requested keys are echoed, filled from the index.
    let (out, all) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            "StudyInstanceUID",
            "PatientName",
            "PatientID",
            "PatientBirthDate",
            "PatientSex",
            "StudyDate",
            "StudyTime",
            "AccessionNumber",
            "StudyDescription",
            "ModalitiesInStudy",
            "NumberOfStudyRelatedSeries",
            "NumberOfStudyRelatedInstances",
            "InstitutionName",
        ],
    )
    .await;
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(all.len(), 2, "{}", text(&out));
    // Ordered by study date.
    let first = &all[0];
    assert_eq!(first[&STUDY_UID], a.study_uid);
    assert_eq!(first[&0x0010_0010], "Doe^Jane");
    assert_eq!(first[&0x0010_0020], "PAT-A");
    assert_eq!(first[&0x0010_0030], "19700102");
    assert_eq!(first[&0x0010_0040], "F");
    assert_eq!(first[&0x0008_0020], "20200315");
    assert_eq!(first[&0x0008_0030], "093000");
    assert_eq!(first[&0x0008_0050], "ACC-1");
    assert_eq!(first[&0x0008_1030], "CT CHEST");
    assert_eq!(first[&0x0008_0061], "CT");
    assert_eq!(first[&0x0020_1206], "1");
    assert_eq!(first[&0x0020_1208], "6");
    assert_eq!(first[&0x0008_0052], "STUDY");
    // A key the index does not hold comes back empty.
    assert_eq!(first[&0x0008_0080], "");
    assert_eq!(all[1][&STUDY_UID], b.study_uid);
    assert_eq!(all[1][&0x0020_1208], "4");

    // Wildcards: person names case-insensitively, other strings as they are.
    let (_, doe) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            "PatientName=DOE*",
            "StudyInstanceUID",
        ],
    )
    .await;
    assert_eq!(values(&doe, STUDY_UID), vec![a.study_uid.as_str()]);
    let (_, head) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            "StudyDescription=CT?H*",
            "StudyInstanceUID",
        ],
    )
    .await;
    assert_eq!(values(&head, STUDY_UID), vec![b.study_uid.as_str()]);
    let (_, lower) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            "StudyDescription=ct*",
            "StudyInstanceUID",
        ],
    )
    .await;
    assert!(lower.is_empty());

    // Date ranges, open and closed.
    for (range, want) in [
        ("20210101-", vec![b.study_uid.as_str()]),
        ("-20201231", vec![a.study_uid.as_str()]),
        ("20200301-20200331", vec![a.study_uid.as_str()]),
        (
            "20200101-20211231",
            vec![a.study_uid.as_str(), b.study_uid.as_str()],
        ),
        ("20220101-", vec![]),
    ] {
        let (_, f) = findscu(
            port,
            "TESTSCU",
            &[
                "QueryRetrieveLevel=STUDY",
                &format!("StudyDate={range}"),
                "StudyInstanceUID",
            ],
        )
        .await;
        assert_eq!(values(&f, STUDY_UID), want, "StudyDate={range}");
    }
    // A list of UIDs.
    let (_, listed) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            &format!("StudyInstanceUID={}\\{}\\1.2.3", b.study_uid, a.study_uid),
        ],
    )
    .await;
    assert_eq!(listed.len(), 2);

    // SERIES level within a study.
    let (_, series) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=SERIES",
            &format!("StudyInstanceUID={}", a.study_uid),
            "SeriesInstanceUID",
            "Modality",
            "SeriesNumber",
            "SeriesDescription",
            "BodyPartExamined",
            "NumberOfSeriesRelatedInstances",
        ],
    )
    .await;
    assert_eq!(series.len(), 1);
    let s = &series[0];
    assert_eq!(s[&SERIES_UID], a.series_uid);
    assert_eq!(s[&STUDY_UID], a.study_uid);
    assert_eq!(s[&0x0008_0060], "CT");
    assert_eq!(s[&0x0020_0011], "3");
    assert_eq!(s[&0x0008_103E], "query test");
    assert_eq!(s[&0x0018_0015], "CHEST");
    assert_eq!(s[&0x0020_1209], "6");

    // IMAGE level: every instance, in instance-number order.
    let (_, images) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=IMAGE",
            &format!("StudyInstanceUID={}", a.study_uid),
            &format!("SeriesInstanceUID={}", a.series_uid),
            "SOPInstanceUID",
            "SOPClassUID",
            "InstanceNumber",
        ],
    )
    .await;
    let uids: BTreeSet<String> = images.iter().map(|i| i[&SOP_UID].clone()).collect();
    assert_eq!(uids, a.sop_uids);
    assert_eq!(
        values(&images, 0x0020_0013),
        vec!["1", "2", "3", "4", "5", "6"]
    );
    assert!(
        images
            .iter()
            .all(|i| i[&0x0008_0016] == "1.2.840.10008.5.1.4.1.1.2")
    );

    // Patient Root: the PATIENT level exists there.
    let (out, patients) = findscu_in(
        "-P",
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=PATIENT",
            "PatientName=roe*",
            "PatientID",
            "NumberOfPatientRelatedStudies",
        ],
    )
    .await;
    assert_eq!(patients.len(), 1, "{}", text(&out));
    assert_eq!(patients[0][&0x0010_0020], "PAT-B");
    assert_eq!(patients[0][&0x0010_0010], "Roe^Richard");
    assert_eq!(patients[0][&0x0020_1200], "1");

    // Refusals: a caller without the query permission, a level the model lacks, a malformed range.
    let (out, none) = findscu(
        port,
        "NOQUERY",
        &["QueryRetrieveLevel=STUDY", "StudyInstanceUID"],
    )
    .await;
    assert!(none.is_empty());
    assert!(says(&out, &["0x124", "notauthorized"]), "{}", text(&out));
    let (out, none) = findscu(
        port,
        "TESTSCU",
        &["QueryRetrieveLevel=PATIENT", "PatientID"],
    )
    .await;
    assert!(none.is_empty());
    assert!(
        says(&out, &["0xa900", "datasetdoesnotmatchsopclass"]),
        "{}",
        text(&out)
    );
    let (out, none) = findscu(
        port,
        "TESTSCU",
        &["QueryRetrieveLevel=STUDY", "StudyDate=2020-13"],
    )
    .await;
    assert!(none.is_empty());
    assert!(says(&out, &["0xc000", "unabletoprocess"]), "{}", text(&out));
    drop(app);
}

/// A peer process, stopped when the test ends however it ends.
struct Running(std::process::Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The pixel values of every file, by SOP Instance UID.
fn pixels_by_instance(files: &[PathBuf]) -> BTreeMap<String, Vec<f32>> {
    files
        .iter()
        .map(|f| {
            let i = read_path(f, &ReadLimits::default()).unwrap();
            let px = i.slices.iter().flat_map(|s| s.stored.clone()).collect();
            (i.sop_instance_uid, px)
        })
        .collect()
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|it| it.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    v.sort();
    v
}

async fn movescu(port: u16, calling: &str, dest: &str, keys: &[&str]) -> Output {
    let mut a = args(&["-S", "-v", "-aet", calling, "-aem", dest, "-aec", "CTRECON"]);
    for k in keys {
        a.push("-k".into());
        a.push(k.to_string());
    }
    a.extend(args(&["127.0.0.1", &port.to_string()]));
    run("movescu", &a, None).await
}

#[tokio::test]
async fn movescu_retrieves_a_series_into_storescp_instance_for_instance() {
    if !dcmtk_present() {
        return;
    }
    let out_dir = tempfile::tempdir().unwrap();
    let dest_port = free_port();
    let _storescp = Running(
        std::process::Command::new("storescp")
            .args(args(&[
                "+B",
                "--aetitle",
                "DEST",
                "--output-directory",
                &out_dir.path().to_string_lossy(),
                &dest_port.to_string(),
            ]))
            .env("TCP_NODELAY", "1")
            .spawn()
            .unwrap(),
    );
    let (app, port) = spawn(
        vec![
            peer("TESTSCU", 1, true, true),
            peer("NOMOVE", 1, true, false),
            peer("DEST", dest_port, false, false),
            peer("DOWN", free_port(), false, false),
        ],
        1,
    )
    .await;
    let src = tempfile::tempdir().unwrap();
    let a = write_study(
        &src.path().join("a"),
        7,
        "PAT-M",
        &[("StudyDate", "20190101")],
    )
    .await;
    let _b = write_study(&src.path().join("b"), 3, "PAT-N", &[]).await;
    storescu(port, src.path()).await;
    wait_indexed(port, &a.study_uid, &a.series_uid, 7).await;
    let series_keys = [
        "QueryRetrieveLevel=SERIES",
        &format!("StudyInstanceUID={}", a.study_uid),
        &format!("SeriesInstanceUID={}", a.series_uid),
    ];

    let out = movescu(port, "TESTSCU", "DEST", &series_keys).await;
    assert!(out.status.success(), "{}", text(&out));
    let received = files_in(out_dir.path());
    assert_eq!(received.len(), 7, "{}", text(&out));
    // Every SOP instance of the series arrived (and nothing of the other study), with the same pixels.
    let got = pixels_by_instance(&received);
    let want = pixels_by_instance(&a.files);
    assert_eq!(
        got.keys().cloned().collect::<BTreeSet<_>>(),
        a.sop_uids,
        "{}",
        text(&out)
    );
    assert_eq!(got, want);
    // Bit for bit: each received data set is the one storescu sent (storescp +B writes it as it came).
    let data_set = |f: &Path| {
        let p = read_part10(f).unwrap();
        let bytes = std::fs::read(f).unwrap();
        (
            p.sop_instance_uid,
            bytes[p.dataset_offset as usize..].to_vec(),
        )
    };
    let sent: BTreeMap<String, Vec<u8>> = a.files.iter().map(|f| data_set(f)).collect();
    let came: BTreeMap<String, Vec<u8>> = received.iter().map(|f| data_set(f)).collect();
    assert_eq!(came, sent);
    // One pending response after each instance but the last, then success.
    let log = text(&out);
    assert_eq!(log.matches("(Pending)").count(), 6, "{log}");
    assert!(
        log.contains("Received Final Move Response (Success)"),
        "{log}"
    );

    // An unknown destination, and a caller without the retrieve permission, are refused.
    let out = movescu(port, "TESTSCU", "NOBODY", &series_keys).await;
    assert!(
        says(&out, &["0xa801", "movedestinationunknown"]),
        "{}",
        text(&out)
    );
    let out = movescu(port, "NOMOVE", "DEST", &series_keys).await;
    assert!(says(&out, &["0x124", "notauthorized"]), "{}", text(&out));
    // A listed destination that does not answer: no sub-operation could be performed.
    let out = movescu(port, "TESTSCU", "DOWN", &series_keys).await;
    assert!(
        says(
            &out,
            &[
                "0xa702",
                "outofresourcessuboperations",
                "unabletoperformsuboperations"
            ]
        ),
        "{}",
        text(&out)
    );
    assert_eq!(files_in(out_dir.path()).len(), 7, "nothing more was sent");
    drop(app);
}

#[tokio::test]
async fn a_derived_result_is_found_next_to_its_source_and_the_index_outlives_its_process() {
    if !dcmtk_present() {
        return;
    }
    let out_dir = tempfile::tempdir().unwrap();
    let dest_port = free_port();
    let _storescp = Running(
        std::process::Command::new("storescp")
            .args(args(&[
                "--aetitle",
                "DEST",
                "--output-directory",
                &out_dir.path().to_string_lossy(),
                &dest_port.to_string(),
            ]))
            .env("TCP_NODELAY", "1")
            .spawn()
            .unwrap(),
    );
    let (app, port) = spawn(
        vec![
            peer("TESTSCU", 1, true, true),
            peer("DEST", dest_port, false, false),
        ],
        1,
    )
    .await;
    let src = tempfile::tempdir().unwrap();
    let a = write_study(
        &src.path().join("a"),
        5,
        "PAT-D",
        &[("StudyDate", "20220202")],
    )
    .await;
    storescu(port, src.path()).await;
    wait_indexed(port, &a.study_uid, &a.series_uid, 5).await;
    // The received series was assembled: run a volume job on it.
    let series_dir = app.dir.path().join("series");
    let sid = files_in(&series_dir)
        .first()
        .and_then(|f| f.file_stem().map(|s| s.to_string_lossy().into_owned()))
        .expect("an assembled series");
    let job = app
        .submit(&serde_json::json!({"kind": "volume", "input": sid}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");

    let series_query = [
        "QueryRetrieveLevel=SERIES",
        &format!("StudyInstanceUID={}", a.study_uid),
        "SeriesInstanceUID",
        "SeriesNumber",
        "SeriesDescription",
        "Modality",
        "NumberOfSeriesRelatedInstances",
    ];
    let mut found = Vec::new();
    for _ in 0..300 {
        found = findscu(port, "TESTSCU", &series_query).await.1;
        if found.len() == 2 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(
        found.len(),
        2,
        "the derived series is found in the source's study"
    );
    // Ordered by series number: the source (3), then the derived series (900).
    assert_eq!(found[0][&SERIES_UID], a.series_uid);
    assert_eq!(found[1][&0x0020_0011], "900");
    assert_eq!(found[1][&0x0008_0060], "CT");
    // The derived series carries the labels of the exported files a delivery sends.
    assert_eq!(found[1][&0x0008_103E], "ctrecon volume query test");
    assert_eq!(
        found[1][&0x0020_1209], "5",
        "one derived slice per source slice"
    );
    assert_ne!(found[1][&SERIES_UID], a.series_uid);
    // movescu retrieves the derived series into storescp: its five slices, each with the job's HU values
    // (within half a quantisation step).
    let derived_uid = found[1][&SERIES_UID].clone();
    let out = movescu(
        port,
        "TESTSCU",
        "DEST",
        &[
            "QueryRetrieveLevel=SERIES",
            &format!("StudyInstanceUID={}", a.study_uid),
            &format!("SeriesInstanceUID={derived_uid}"),
        ],
    )
    .await;
    assert!(out.status.success(), "{}", text(&out));
    let moved = files_in(out_dir.path());
    assert_eq!(moved.len(), 5, "{}", text(&out));
    let npy = app
        .get(&format!("/v1/jobs/{id}/result/volume.npy"))
        .await
        .bytes()
        .await
        .unwrap();
    let vol = ctrecon::storage::npy::decode_f32(&npy).unwrap();
    let mut numbers = BTreeSet::new();
    for f in &moved {
        let i = read_path(f, &ReadLimits::default()).unwrap();
        assert_eq!(i.series_uid, derived_uid);
        assert_eq!(i.study_uid.as_deref(), Some(a.study_uid.as_str()));
        let k = i.instance_number.unwrap() as usize - 1;
        numbers.insert(k);
        let s = &i.slices[0];
        let want = vol.index_axis(ndarray::Axis(0), k);
        assert_eq!(want.len(), s.stored.len());
        let worst = want
            .iter()
            .zip(&s.stored)
            .map(|(&v, &st)| (v as f64 - (st as f64 * s.rescale_slope + s.rescale_intercept)).abs())
            .fold(0.0f64, f64::max);
        assert!(
            worst <= s.rescale_slope / 2.0 + 1e-3,
            "slice {k}: largest difference {worst} HU, step {}",
            s.rescale_slope
        );
    }
    assert_eq!(numbers, (0..5).collect::<BTreeSet<_>>());
    // Study-level attributes come from the instances that have them (the derived ones carry no date).
    let (_, studies) = findscu(
        port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=STUDY",
            "StudyDate=20220101-",
            "StudyInstanceUID",
            "NumberOfStudyRelatedInstances",
        ],
    )
    .await;
    assert_eq!(values(&studies, STUDY_UID), vec![a.study_uid.as_str()]);
    assert_eq!(studies[0][&0x0020_1208], "10");

    // A second service on the same data directory answers the same from the database and files alone.
    let data_dir = app.dir.path().to_path_buf();
    let again = common::spawn_app_with(|s| {
        s.data_dir = data_dir.clone();
        s.dicom.port = Some(0);
        s.dicom.stable_age_secs = 1;
        s.dicom.peers = vec![peer("TESTSCU", 1, true, true)];
    })
    .await;
    let port2 = again.dicom.expect("a DICOM node").port();
    let (_, after) = findscu(port2, "TESTSCU", &series_query).await;
    assert_eq!(after, found);

    // Deleting the job removes its derived instances from the index.
    let r = app
        .client
        .delete(app.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    let (_, left) = findscu(port, "TESTSCU", &series_query).await;
    assert_eq!(values(&left, SERIES_UID), vec![a.series_uid.as_str()]);
    assert!(!app.dir.path().join(format!("results/{id}")).exists());
    // Deleting the source series removes its instances and their folder.
    let r = app
        .client
        .delete(app.url(&format!("/v1/series/{sid}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    let (_, gone) = findscu(port, "TESTSCU", &series_query).await;
    assert!(gone.is_empty());
    assert!(files_in(&app.dir.path().join("instances")).is_empty());
}

#[tokio::test]
async fn instances_of_a_series_still_arriving_are_not_listed() {
    if !dcmtk_present() {
        return;
    }
    let (app, port) = spawn(vec![peer("TESTSCU", 1, true, true)], 3600).await;
    let src = tempfile::tempdir().unwrap();
    let a = write_study(&src.path().join("a"), 4, "PAT-W", &[]).await;
    storescu(port, src.path()).await;
    // All four are on disk, in the node's folder of series still arriving …
    let incoming = app.dir.path().join("dimse/incoming").join(&a.series_uid);
    assert_eq!(files_in(&incoming).len(), 4);
    // … and no level lists them yet.
    for level in ["STUDY", "SERIES", "IMAGE"] {
        let (out, found) = findscu(
            port,
            "TESTSCU",
            &[
                &format!("QueryRetrieveLevel={level}"),
                &format!("StudyInstanceUID={}", a.study_uid),
                "SeriesInstanceUID",
                "SOPInstanceUID",
            ],
        )
        .await;
        assert!(out.status.success(), "{}", text(&out));
        assert!(found.is_empty(), "{level}: {found:?}");
    }
}

#[tokio::test]
async fn a_move_whose_destination_refuses_some_instances_ends_in_a_warning_with_the_rest_delivered()
{
    if !dcmtk_present() {
        return;
    }
    // The destination: another DICOM node that refuses instances over 6000 bytes (Out of Resources).
    let dest_dir = tempfile::tempdir().unwrap();
    let dest = ctrecon::dimse::DicomNode::start(
        &ctrecon::dimse::NodeSettings {
            ae_title: "SMALL".into(),
            port: Some(0),
            peers: vec![peer("CTRECON", 1, true, false)],
            stable_age_secs: 3600,
            max_instance_bytes: 6000,
            ..Default::default()
        },
        dest_dir.path(),
    )
    .await
    .unwrap();
    let (app, port) = spawn(
        vec![
            peer("TESTSCU", 1, true, true),
            peer("SMALL", dest.local_addr().port(), false, false),
        ],
        1,
    )
    .await;
    // One study: a series of 3 small slices (24 × 20) and one of 2 large ones (64 × 64).
    let src = tempfile::tempdir().unwrap();
    let small = write_series(&src.path().join("s"), (3, 20, 24), None, "PAT-S", &[]).await;
    let large = write_series(
        &src.path().join("l"),
        (2, 64, 64),
        Some(small.study_uid.clone()),
        "PAT-S",
        &[],
    )
    .await;
    assert_eq!(large.study_uid, small.study_uid);
    let size = |w: &Written| std::fs::metadata(&w.files[0]).unwrap().len();
    assert!(
        size(&small) < 5000 && size(&large) > 8000,
        "{} {}",
        size(&small),
        size(&large)
    );
    storescu(port, src.path()).await;
    wait_indexed(port, &small.study_uid, &small.series_uid, 3).await;
    wait_indexed(port, &large.study_uid, &large.series_uid, 2).await;

    // Debug output (-d) dumps each response, the failed SOP Instance UID list included.
    let study_key = format!("StudyInstanceUID={}", small.study_uid);
    let out = run(
        "movescu",
        &args(&[
            "-S",
            "-d",
            "-aet",
            "TESTSCU",
            "-aem",
            "SMALL",
            "-aec",
            "CTRECON",
            "-k",
            "QueryRetrieveLevel=STUDY",
            "-k",
            &study_key,
            "127.0.0.1",
            &port.to_string(),
        ]),
        None,
    )
    .await;
    let log = text(&out);
    assert_eq!(log.matches("Received Move Response").count(), 4, "{log}");
    assert!(
        says(&out, &["suboperationscompleteoneormorefailures", "0xb000"]),
        "{log}"
    );
    let failed_list = log
        .lines()
        .find(|l| l.contains("(0008,0058)"))
        .unwrap_or_else(|| panic!("no Failed SOP Instance UID List in {log}"));
    for uid in &large.sop_uids {
        assert!(
            failed_list.contains(uid.as_str()),
            "{uid} not in {failed_list}"
        );
    }
    for uid in &small.sop_uids {
        assert!(
            !failed_list.contains(uid.as_str()),
            "{uid} in {failed_list}"
        );
    }
    // The small instances arrived, the large ones did not.
    assert_eq!(dest.arriving(), vec![(small.series_uid.clone(), 3)]);
    drop(app);
}

fn orthanc_present() -> bool {
    let ok = Path::new("/usr/sbin/Orthanc").exists();
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "Orthanc is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: Orthanc is not installed (apt-get install orthanc)");
    }
    ok
}

fn element(tag: u32, vr: &str, value: &str) -> ctrecon::dicom::IdentifierElement {
    ctrecon::dicom::IdentifierElement {
        tag,
        vr: vr.into(),
        value: value.into(),
    }
}

#[tokio::test]
async fn ctrecon_finds_a_series_on_orthanc_and_moves_it_into_its_own_index() {
    if !dcmtk_present() || !orthanc_present() {
        return;
    }
    let t = tempfile::tempdir().unwrap();
    let (node_port, http_port, dicom_port) = (free_port(), free_port(), free_port());
    let config = serde_json::json!({
        "Name": "TEST-ORTHANC",
        "StorageDirectory": t.path().join("db"), "IndexDirectory": t.path().join("db"),
        "HttpPort": http_port, "RemoteAccessAllowed": false, "AuthenticationEnabled": false,
        "DicomServerEnabled": true, "DicomAet": "ORTHANC", "DicomPort": dicom_port,
        "DicomCheckCalledAet": false, "DicomAlwaysAllowStore": true, "DicomAlwaysAllowEcho": true,
        "DicomCheckModalityHost": false,
        "DicomModalities": { "CTRECON": [ "CTRECON", "127.0.0.1", node_port ] }
    });
    let config_path = t.path().join("orthanc.json");
    std::fs::write(&config_path, config.to_string()).unwrap();
    std::fs::create_dir_all(t.path().join("logs")).unwrap();
    let _orthanc = Running(
        std::process::Command::new("/usr/sbin/Orthanc")
            .arg(format!("--logdir={}", t.path().join("logs").display()))
            .arg(&config_path)
            .env("TCP_NODELAY", "1")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let rest = format!("http://127.0.0.1:{http_port}");
    let client = reqwest::Client::new();
    let mut ready = false;
    for _ in 0..200 {
        if client
            .get(format!("{rest}/system"))
            .send()
            .await
            .is_ok_and(|r| r.status() == 200)
        {
            ready = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(ready, "Orthanc answers within 10 s");
    let orthanc = Peer {
        ae_title: "ORTHANC".into(),
        host: "127.0.0.1".into(),
        port: dicom_port,
        store: true,
        query: true,
        retrieve: true,
    };
    let app = common::spawn_app_with(|s| {
        s.dicom.port = Some(node_port);
        s.dicom.stable_age_secs = 1;
        s.dicom.peers = vec![orthanc.clone(), peer("TESTSCU", 1, true, true)];
    })
    .await;
    // Orthanc holds a series (uploaded over its REST API); ctrecon does not.
    let src = tempfile::tempdir().unwrap();
    let a = write_study(
        &src.path().join("a"),
        4,
        "PAT-O",
        &[("StudyDate", "20230303")],
    )
    .await;
    for f in &a.files {
        let r = client
            .post(format!("{rest}/instances"))
            .body(std::fs::read(f).unwrap())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
    }
    let caller = ctrecon::dimse::scu::Caller {
        ae_title: "CTRECON".into(),
        timeout: Duration::from_secs(10),
        max_pdu_length: 65_536,
    };
    let keys = [
        element(0x0008_0052, "CS", "SERIES"),
        element(0x0008_0060, "CS", ""),
        element(STUDY_UID, "UI", ""),
        element(SERIES_UID, "UI", &a.series_uid),
        element(0x0020_1209, "IS", ""),
    ];
    let found = ctrecon::dimse::pull::find(&caller, &orthanc, &keys)
        .await
        .unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    let value = |tag: u32| {
        found[0]
            .iter()
            .find(|e| e.tag == tag)
            .map(|e| e.value.clone())
            .unwrap_or_default()
    };
    assert_eq!(value(STUDY_UID), a.study_uid);
    assert_eq!(value(0x0008_0060), "CT");
    assert_eq!(value(0x0020_1209), "4");

    let moved = ctrecon::dimse::pull::retrieve(
        &caller,
        &orthanc,
        "CTRECON",
        &[
            element(0x0008_0052, "CS", "SERIES"),
            element(STUDY_UID, "UI", &a.study_uid),
            element(SERIES_UID, "UI", &a.series_uid),
        ],
    )
    .await
    .unwrap();
    assert_eq!(moved.status, 0, "{moved:?}");
    assert_eq!(
        (moved.sub_operations.completed, moved.sub_operations.failed),
        (4, 0)
    );
    // The series arrived by C-STORE from Orthanc, was assembled and indexed: ctrecon now answers it.
    wait_indexed(node_port, &a.study_uid, &a.series_uid, 4).await;
    let (_, images) = findscu(
        node_port,
        "TESTSCU",
        &[
            "QueryRetrieveLevel=IMAGE",
            &format!("SeriesInstanceUID={}", a.series_uid),
            "SOPInstanceUID",
        ],
    )
    .await;
    let uids: BTreeSet<String> = images.iter().map(|i| i[&SOP_UID].clone()).collect();
    assert_eq!(uids, a.sop_uids);
    // An unknown destination: Orthanc 1.10 refuses the move with C000 (unable to process), reported as
    // the outcome's status.
    let refused = ctrecon::dimse::pull::retrieve(
        &caller,
        &orthanc,
        "NOBODY",
        &[
            element(0x0008_0052, "CS", "SERIES"),
            element(STUDY_UID, "UI", &a.study_uid),
            element(SERIES_UID, "UI", &a.series_uid),
        ],
    )
    .await;
    assert_eq!(refused.map(|m| m.status).ok(), Some(0xC000));
    drop(app);
}
