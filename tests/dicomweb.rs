//! DICOMweb against a real peer: Orthanc with its DICOMweb plugin as the client of ctrecon (STOW-RS of a
//! synthetic series into ctrecon, QIDO-RS finding it and the derived series a rule made of it, WADO-RS
//! retrieving the derived series into Orthanc, whose REST API then shows its UIDs and HU values equal to the
//! job's volume); the same STOW-RS, QIDO-RS and WADO-RS requests sent to Orthanc and to ctrecon, answers
//! compared; and bad input (boundaries, media types, non-DICOM parts, another study, unknown UIDs and
//! parameters, Accept) answered with the PS3.18 status or problem+json, nothing partial stored.
//!
//! Without Orthanc or its DICOMweb plugin each test prints one skip line, unless `CTRECON_REQUIRE_PEERS=1`.

use crate::common;
use crate::dw;
use crate::orthanc;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use common::read_npy_f32;
use dw::{
    EXPLICIT_LE, Part, STOW_TYPE, TOKEN, ctrecon, header, multipart, parts, seq_values, stow,
    synthetic, value,
};
use orthanc::{Orthanc, OrthancOptions, orthanc_dicomweb_present};
use serde_json::{Value, json};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn orthanc_stows_a_series_finds_it_and_retrieves_the_derived_series_with_its_hu_values() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let (app, client) = ctrecon().await;
    let o = Orthanc::start(OrthancOptions {
        dicomweb: Some((format!("{}/dicom-web/", app.base), Some(TOKEN.into()))),
        ..Default::default()
    })
    .await;
    let r = client
        .post(app.url("/v1/rules"))
        .json(
            &json!({"name": "spine", "protocol": "spine", "destinations": [],
                      "match": {"modality": "CT"}}),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());

    // Orthanc holds a synthetic series and pushes it into ctrecon by STOW-RS.
    let (study, series, files) = synthetic(16, None, "DW-1");
    for f in &files {
        o.post("/instances", f.clone()).await;
    }
    let lookup = o.post("/tools/lookup", study.clone().into_bytes()).await;
    let study_id = lookup[0]["ID"].as_str().unwrap().to_string();
    let pushed = o
        .client
        .post(o.url("/dicom-web/servers/ctrecon/stow"))
        .json(&json!({"Resources": [study_id], "Synchronous": true}))
        .send()
        .await
        .unwrap();
    let logs = || {
        let dir = o.dir.path().join("logs");
        std::fs::read_dir(&dir)
            .unwrap()
            .flatten()
            .map(|f| std::fs::read_to_string(f.path()).unwrap_or_default())
            .collect::<String>()
    };
    assert_eq!(pushed.status(), 200, "Orthanc's log:\n{}", logs());

    // ctrecon's QIDO-RS finds the series with all of its instances.
    let found: Value = client
        .get(app.url(&format!("/dicom-web/studies/{study}/series")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let source = found
        .as_array()
        .unwrap()
        .iter()
        .find(|s| value(s, "0020000E").as_deref() == Some(series.as_str()))
        .unwrap_or_else(|| panic!("the series is not found: {found}"));
    assert_eq!(value(source, "00201209").as_deref(), Some("16"));
    assert_eq!(value(source, "00080060").as_deref(), Some("CT"));

    // Orthanc's QIDO-RS through ctrecon finds the study, then the derived series once the rule's job ran.
    let studies = o
        .post(
            "/dicom-web/servers/ctrecon/qido",
            serde_json::to_vec(&json!({"Uri": "/studies", "Arguments": {"PatientID": "DW-1"}}))
                .unwrap(),
        )
        .await;
    assert_eq!(studies.as_array().unwrap().len(), 1, "{studies}");
    assert_eq!(
        value(&studies[0], "0020000D").as_deref(),
        Some(study.as_str()),
        "{studies}"
    );
    assert_eq!(value(&studies[0], "00100010").as_deref(), Some("WEB^DICOM"));
    let deadline = Instant::now() + Duration::from_secs(120);
    let derived = loop {
        let s = o
            .post(
                "/dicom-web/servers/ctrecon/qido",
                serde_json::to_vec(&json!({"Uri": format!("/studies/{study}/series")})).unwrap(),
            )
            .await;
        if let Some(d) = s
            .as_array()
            .unwrap()
            .iter()
            .find(|x| value(x, "0008103E").is_some_and(|d| d.starts_with("ctrecon ")))
        {
            break d.clone();
        }
        assert!(Instant::now() < deadline, "no derived series: {s}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let derived_uid = value(&derived, "0020000E").unwrap();
    // Orthanc's client drops IS numbers from what it relays: the count from ctrecon itself.
    let own: Value = client
        .get(app.url(&format!(
            "/dicom-web/studies/{study}/series?SeriesInstanceUID={derived_uid}"
        )))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(value(&own[0], "00200011").as_deref(), Some("900"));
    let n_derived: usize = value(&own[0], "00201209").unwrap().parse().unwrap();
    assert!(n_derived > 1);

    // Orthanc retrieves the derived series by WADO-RS: the same UIDs and the job's HU values.
    let before = o.instances().await.len();
    let pulled = o
        .post(
            "/dicom-web/servers/ctrecon/retrieve",
            serde_json::to_vec(&json!({"Resources": [{"Study": study, "Series": derived_uid}]}))
                .unwrap(),
        )
        .await;
    println!("Orthanc's WADO-RS retrieve: {pulled}");
    assert_eq!(o.instances().await.len(), before + n_derived);
    let ids = o
        .post("/tools/lookup", derived_uid.clone().into_bytes())
        .await;
    let series_id = ids[0]["ID"].as_str().unwrap().to_string();
    let instances: Vec<String> =
        serde_json::from_value(o.get(&format!("/series/{series_id}")).await["Instances"].clone())
            .unwrap();
    assert_eq!(instances.len(), n_derived);
    let rule: Value = client
        .get(app.url("/v1/rules/spine"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let job = rule["runs"][0]["job_id"].as_str().unwrap().to_string();
    let npy = client
        .get(app.url(&format!("/v1/jobs/{job}/result/volume.npy")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (shape, vol) = read_npy_f32(&npy);
    assert_eq!(shape[0], n_derived);
    let plane = shape[1] * shape[2];
    let mut worst = 0.0f64;
    for id in &instances {
        let t = o.tags(id).await;
        assert_eq!(t["StudyInstanceUID"], study.as_str());
        assert_eq!(t["SeriesInstanceUID"], derived_uid.as_str());
        let num = |k: &str| t[k].as_str().unwrap().trim().parse::<f64>().unwrap();
        let (slope, intercept) = (num("RescaleSlope"), num("RescaleIntercept"));
        let k = num("InstanceNumber") as usize - 1;
        let raw = o.get_bytes(&format!("/instances/{id}/frames/0/raw")).await;
        assert_eq!(raw.len(), plane * 2);
        for (n, b) in raw.chunks_exact(2).enumerate() {
            let hu = i16::from_le_bytes([b[0], b[1]]) as f64 * slope + intercept;
            let want = vol[k * plane + n] as f64;
            let err = (hu - want).abs();
            assert!(
                err <= slope,
                "slice {k} pixel {n}: {hu} HU in Orthanc, {want} in the job"
            );
            worst = worst.max(err);
        }
    }
    println!("{n_derived} derived instances in Orthanc; worst HU error {worst:.3}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_stow_qido_and_wado_requests_get_equivalent_answers_from_orthanc_and_ctrecon() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let (app, client) = ctrecon().await;
    let o = Orthanc::start(OrthancOptions {
        dicomweb: Some((format!("{}/dicom-web/", app.base), Some(TOKEN.into()))),
        ..Default::default()
    })
    .await;
    let (study, series, files) = synthetic(6, None, "DW-2");
    let body = multipart(
        &files
            .iter()
            .map(|f| ("application/dicom", f.as_slice()))
            .collect::<Vec<_>>(),
    );
    let roots = [o.url("/dicom-web"), app.url("/dicom-web")];
    let mut answers = Vec::new();
    for root in &roots {
        answers.push(stow(&client, format!("{root}/studies"), body.clone()).await);
    }
    for (status, v) in &answers {
        assert_eq!(*status, 200, "{v}");
        assert_eq!(seq_values(v, "00081199", "00081155").len(), 6);
        assert!(seq_values(v, "00081198", "00081197").is_empty(), "{v}");
    }
    assert_eq!(
        seq_values(&answers[0].1, "00081199", "00081155"),
        seq_values(&answers[1].1, "00081199", "00081155")
    );
    let url = seq_values(&answers[1].1, "00081199", "00081190");
    assert!(
        url.iter().all(|u| u.starts_with(&format!(
            "{}/dicom-web/studies/{study}/series/{series}/instances/",
            app.base
        ))),
        "{url:?}"
    );
    // The same instances again: 200, no duplicates (as Orthanc).
    let again = stow(&client, app.url("/dicom-web/studies"), body.clone()).await;
    assert_eq!(again.0, 200);

    // To another study's path: 409, FailureReason 272 for each instance, in both.
    let other = ctrecon::dicom::new_uid();
    for root in &roots {
        let (status, v) = stow(&client, format!("{root}/studies/{other}"), body.clone()).await;
        assert_eq!(status, 409, "{root}: {v}");
        assert_eq!(
            seq_values(&v, "00081198", "00081197"),
            BTreeSet::from(["272".to_string()]),
            "{root}: {v}"
        );
        assert_eq!(seq_values(&v, "00081198", "00081155").len(), 6);
    }

    // QIDO-RS: the same studies, series and instances with the same attributes.
    let get = |url: String| {
        let client = client.clone();
        async move {
            let r = client
                .get(url)
                .header("accept", "application/dicom+json")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200);
            r.json::<Value>().await.unwrap()
        }
    };
    let compared = [
        (
            "/studies?PatientID=DW-2",
            vec![
                "0020000D", "00100020", "00100010", "00201206", "00201208", "00080061",
            ],
        ),
        (
            &*format!("/studies/{study}/series"),
            vec!["0020000E", "00080060", "00200011", "0008103E", "00201209"],
        ),
        (
            &*format!("/studies/{study}/series/{series}/instances"),
            vec!["00080016", "00080018", "00200013"],
        ),
        (
            "/series?Modality=CT&PatientID=DW-2",
            vec!["0020000E", "0020000D", "00201209"],
        ),
    ]
    .map(|(p, t)| (p.to_string(), t));
    for (path, tags) in &compared {
        let a = get(format!("{}{path}", roots[0])).await;
        let b = get(format!("{}{path}", roots[1])).await;
        let key = |v: &Value| -> BTreeSet<Vec<Option<String>>> {
            v.as_array()
                .unwrap()
                .iter()
                .map(|d| tags.iter().map(|t| value(d, t)).collect())
                .collect()
        };
        assert_eq!(
            a.as_array().unwrap().len(),
            b.as_array().unwrap().len(),
            "{path}"
        );
        assert_eq!(key(&a), key(&b), "{path}:\nOrthanc {a}\nctrecon {b}");
    }
    let limited = get(app.url(&format!(
        "/dicom-web/studies/{study}/series/{series}/instances?limit=2&offset=3"
    )))
    .await;
    assert_eq!(limited.as_array().unwrap().len(), 2);
    assert_eq!(value(&limited[0], "00200013").as_deref(), Some("4"));
    // Each QIDO-RS answer carries the RetrieveURL (0008,1190) of what it found, back at ctrecon, and each
    // one retrieves it.
    let study_url = format!("{}/dicom-web/studies/{study}", app.base);
    let series_url = format!("{study_url}/series/{series}");
    let found = get(app.url("/dicom-web/studies?PatientID=DW-2")).await;
    assert_eq!(value(&found[0], "00081190"), Some(study_url.clone()));
    let found = get(app.url(&format!("/dicom-web/studies/{study}/series"))).await;
    assert_eq!(value(&found[0], "00081190"), Some(series_url.clone()));
    let found = get(app.url(&format!(
        "/dicom-web/studies/{study}/series/{series}/instances"
    )))
    .await;
    for d in found.as_array().unwrap() {
        let sop = value(d, "00080018").unwrap();
        assert_eq!(
            value(d, "00081190"),
            Some(format!("{series_url}/instances/{sop}"))
        );
    }
    let r = client
        .get(value(&found[0], "00081190").unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);

    // WADO-RS: the same multipart structure and the same instances.
    let mut bodies = Vec::new();
    for root in &roots {
        let r = client
            .get(format!("{root}/studies/{study}/series/{series}"))
            .header(
                "accept",
                "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let ct = r.headers()["content-type"].to_str().unwrap().to_string();
        assert!(
            ct.starts_with("multipart/related") && ct.contains("application/dicom"),
            "{ct}"
        );
        let body = r.bytes().await.unwrap();
        bodies.push(parts(&ct, &body));
    }
    assert_eq!(bodies[0].len(), 6);
    assert_eq!(bodies[1].len(), 6);
    // The study as a whole: the same six instances from both.
    for root in &roots {
        let r = client
            .get(format!("{root}/studies/{study}"))
            .header(
                "accept",
                "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{root}");
        let ct = r.headers()["content-type"].to_str().unwrap().to_string();
        let body = r.bytes().await.unwrap();
        bodies.push(parts(&ct, &body));
    }
    let sop = |p: &Part| {
        let obj =
            dicom_object::from_reader(std::io::Cursor::new(&p.1[128..])).expect("a DICOM part");
        obj.element(dicom_dictionary_std::tags::SOP_INSTANCE_UID)
            .unwrap()
            .to_str()
            .unwrap()
            .trim_end_matches('\0')
            .to_string()
    };
    let sa: BTreeSet<String> = bodies[0].iter().map(sop).collect();
    let sb: BTreeSet<String> = bodies[1].iter().map(sop).collect();
    assert_eq!(sa, sb);
    for study_parts in &bodies[2..] {
        assert_eq!(study_parts.iter().map(sop).collect::<BTreeSet<_>>(), sa);
    }
    // The metadata of the study and of the series: the same six instances from both, and ctrecon names
    // the resource in Content-Location.
    for path in [
        format!("/studies/{study}/metadata"),
        format!("/studies/{study}/series/{series}/metadata"),
    ] {
        let mut sops = Vec::new();
        for root in &roots {
            let r = client
                .get(format!("{root}{path}"))
                .header("accept", "application/dicom+json")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "{root}{path}");
            if root.starts_with(&app.base) {
                assert_eq!(
                    r.headers()["content-location"].to_str().unwrap(),
                    format!("{}/dicom-web{path}", app.base)
                );
            }
            let m: Value = r.json().await.unwrap();
            sops.push(
                m.as_array()
                    .unwrap()
                    .iter()
                    .filter_map(|d| value(d, "00080018"))
                    .collect::<BTreeSet<_>>(),
            );
        }
        assert_eq!(sops[0], sa, "{path}");
        assert_eq!(sops[1], sa, "{path}");
    }
    for p in &bodies[1] {
        assert!(
            header(&p.0, "content-type")
                .unwrap()
                .starts_with("application/dicom")
        );
        assert_eq!(
            header(&p.0, "content-length")
                .unwrap()
                .parse::<usize>()
                .unwrap(),
            p.1.len()
        );
        assert!(
            header(&p.0, "content-location")
                .unwrap()
                .contains("/instances/")
        );
        // The stored files, byte for byte.
        assert!(files.contains(&p.1));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_gets_the_ps3_18_status_or_a_problem_and_nothing_partial_is_stored() {
    let (app, client) = ctrecon().await;
    let (study, series, files) = synthetic(4, None, "DW-3");
    let count = || {
        let client = client.clone();
        let url = app.url("/dicom-web/instances?PatientID=DW-3");
        async move {
            client
                .get(url)
                .send()
                .await
                .unwrap()
                .json::<Value>()
                .await
                .unwrap()
                .as_array()
                .unwrap()
                .len()
        }
    };
    let problem = |status: u16, code: &'static str| {
        move |r: reqwest::Response| async move {
            assert_eq!(r.status().as_u16(), status);
            assert_eq!(r.headers()["content-type"], "application/problem+json");
            let v: Value = r.json().await.unwrap();
            assert_eq!(v["code"], code, "{v}");
        }
    };
    let body = multipart(&[("application/dicom", &files[0])]);
    // A wrong boundary, no boundary, not multipart, another type.
    let send = |ct: &'static str, body: Vec<u8>| {
        client
            .post(app.url("/dicom-web/studies"))
            .header("content-type", ct)
            .body(body)
            .send()
    };
    problem(400, "invalid_multipart")(
        send(
            "multipart/related; type=\"application/dicom\"; boundary=nope",
            body.clone(),
        )
        .await
        .unwrap(),
    )
    .await;
    problem(400, "invalid_multipart")(
        send(
            "multipart/related; type=\"application/dicom\"",
            body.clone(),
        )
        .await
        .unwrap(),
    )
    .await;
    problem(415, "unsupported_media_type")(
        send("application/dicom", files[0].clone()).await.unwrap(),
    )
    .await;
    problem(415, "unsupported_media_type")(
        send(
            "multipart/related; boundary=ctrecon-test-boundary-7f3a",
            body.clone(),
        )
        .await
        .unwrap(),
    )
    .await;
    // A truncated body: nothing stored.
    problem(400, "invalid_multipart")(
        send(STOW_TYPE, body[..body.len() - 40].to_vec())
            .await
            .unwrap(),
    )
    .await;
    // Without the token.
    let r = reqwest::Client::new()
        .post(app.url("/dicom-web/studies"))
        .header("content-type", STOW_TYPE)
        .body(body.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    assert_eq!(count().await, 0);

    // A non-DICOM part beside a good one: 202, the good one stored, C000 for the other.
    let mixed = multipart(&[
        ("application/dicom", &files[0]),
        ("application/dicom", b"not DICOM at all"),
    ]);
    let (status, v) = stow(&client, app.url("/dicom-web/studies"), mixed).await;
    assert_eq!(status, 202, "{v}");
    assert_eq!(
        seq_values(&v, "00081198", "00081197"),
        BTreeSet::from([(0xC000).to_string()])
    );
    assert_eq!(seq_values(&v, "00081199", "00081155").len(), 1);
    assert_eq!(count().await, 1);
    // Another study's path: 409, 272, nothing stored.
    let other = ctrecon::dicom::new_uid();
    let (status, v) = stow(
        &client,
        app.url(&format!("/dicom-web/studies/{other}")),
        multipart(&[("application/dicom", &files[1])]),
    )
    .await;
    assert_eq!(status, 409, "{v}");
    assert_eq!(
        seq_values(&v, "00081198", "00081197"),
        BTreeSet::from(["272".to_string()])
    );
    assert_eq!(count().await, 1);
    let tmp = app.dir.path().join("tmp");
    assert_eq!(
        std::fs::read_dir(&tmp).map(|d| d.count()).unwrap_or(0),
        0,
        "temporaries left behind"
    );

    // Unknown UIDs, unsupported parameters, fuzzy matching, Accept.
    let get = |path: String, accept: &'static str| {
        client.get(app.url(&path)).header("accept", accept).send()
    };
    let unknown = ctrecon::dicom::new_uid();
    problem(404, "dicomweb_not_found")(
        get(format!("/dicom-web/studies/{unknown}"), "*/*")
            .await
            .unwrap(),
    )
    .await;
    problem(404, "dicomweb_not_found")(
        get(
            format!("/dicom-web/studies/{study}/series/{unknown}/metadata"),
            "*/*",
        )
        .await
        .unwrap(),
    )
    .await;
    problem(400, "invalid_query")(
        get("/dicom-web/studies?PatientAge=030Y".into(), "*/*")
            .await
            .unwrap(),
    )
    .await;
    problem(400, "invalid_query")(
        get("/dicom-web/studies?fuzzymatching=true".into(), "*/*")
            .await
            .unwrap(),
    )
    .await;
    problem(400, "invalid_id")(
        get("/dicom-web/studies/not.a.uid/series".into(), "*/*")
            .await
            .unwrap(),
    )
    .await;
    problem(406, "not_acceptable")(
        get("/dicom-web/studies".into(), "application/dicom+xml")
            .await
            .unwrap(),
    )
    .await;
    let sop = {
        let obj = dicom_object::from_reader(std::io::Cursor::new(&files[0][128..])).unwrap();
        obj.element(dicom_dictionary_std::tags::SOP_INSTANCE_UID)
            .unwrap()
            .to_str()
            .unwrap()
            .trim_end_matches('\0')
            .to_string()
    };
    let inst = format!("/dicom-web/studies/{study}/series/{series}/instances/{sop}");
    problem(406, "not_acceptable")(get(format!("{inst}/rendered"), "image/gif").await.unwrap())
        .await;
    problem(406, "not_acceptable")(
        get(
            inst.clone(),
            "multipart/related; type=\"application/dicom\"; transfer-syntax=1.2.840.10008.1.2.4.50",
        )
        .await
        .unwrap(),
    )
    .await;
    problem(400, "invalid_query")(
        get(format!("{inst}/rendered?window=40"), "image/png")
            .await
            .unwrap(),
    )
    .await;

    // Rendered through a window: 400 HU is white, 40 + i + 2j HU at (0, j, i) maps linearly.
    let r = get(format!("{inst}/rendered?window=40,400,linear"), "image/png")
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let png = r.bytes().await.unwrap();
    let mut dec = png::Decoder::new(std::io::Cursor::new(png.to_vec()))
        .read_info()
        .unwrap();
    let mut buf = vec![0; dec.output_buffer_size().unwrap()];
    let info = dec.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (48, 40));
    for (j, i) in [(0usize, 0usize), (5, 7), (39, 47)] {
        let hu = 40.0 + (i + 2 * j) as f64;
        let want = ((hu - (40.0 - 200.0)) / 400.0 * 255.0).round();
        let got = buf[j * 48 + i] as f64;
        assert!((got - want).abs() <= 1.0, "({j},{i}): {got} vs {want}");
    }

    // Explicit VR little endian on request: the stored file, whose syntax it is.
    let r = get(
        inst.clone(),
        "multipart/related; type=\"application/dicom\"; transfer-syntax=1.2.840.10008.1.2.1",
    )
    .await
    .unwrap();
    assert_eq!(r.status(), 200);
    let ct = r.headers()["content-type"].to_str().unwrap().to_string();
    let p = parts(&ct, &r.bytes().await.unwrap());
    assert_eq!(p.len(), 1);
    assert_eq!(
        header(&p[0].0, "content-type"),
        Some(&*format!(
            "application/dicom; transfer-syntax={EXPLICIT_LE}"
        ))
    );
    assert_eq!(p[0].1, files[0]);

    // Metadata: the JSON model of the stored instance, UTF-8.
    let m: Value = get(format!("{inst}/metadata"), "application/dicom+json")
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(value(&m[0], "00080018").as_deref(), Some(sop.as_str()));
    assert_eq!(value(&m[0], "00100010").as_deref(), Some("WEB^DICOM"));
    assert_eq!(value(&m[0], "00280010").as_deref(), Some("40"));
    assert!(m[0].get("7FE00010").is_none());
    // Still up.
    assert_eq!(app.get("/healthz").await.status(), 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_instance_stored_in_implicit_vr_is_sent_as_stored_or_re_encoded_in_explicit_vr() {
    let (app, client) = ctrecon().await;
    let (study, series, files) = synthetic(4, None, "DW-4");
    let mut obj = dicom_object::from_reader(std::io::Cursor::new(&files[1][128..])).unwrap();
    obj.meta_mut()
        .set_transfer_syntax(&dicom_transfer_syntax_registry::entries::IMPLICIT_VR_LITTLE_ENDIAN);
    let mut implicit = Vec::new();
    obj.write_all(&mut implicit).unwrap();
    let (status, v) = stow(
        &client,
        app.url(&format!("/dicom-web/studies/{study}")),
        multipart(&[("application/dicom", &implicit)]),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let sop = obj
        .element(dicom_dictionary_std::tags::SOP_INSTANCE_UID)
        .unwrap()
        .to_str()
        .unwrap()
        .trim_end_matches('\0')
        .to_string();
    let pixels = |bytes: &[u8]| {
        let o = dicom_object::from_reader(std::io::Cursor::new(&bytes[128..])).unwrap();
        let ts = o
            .meta()
            .transfer_syntax()
            .trim_end_matches('\0')
            .to_string();
        (
            ts,
            o.element(dicom_dictionary_std::tags::PIXEL_DATA)
                .unwrap()
                .to_bytes()
                .unwrap()
                .to_vec(),
        )
    };
    let url = app.url(&format!(
        "/dicom-web/studies/{study}/series/{series}/instances/{sop}"
    ));
    let mut got = Vec::new();
    for ts in ["*", EXPLICIT_LE] {
        let r = client
            .get(&url)
            .header(
                "accept",
                format!("multipart/related; type=\"application/dicom\"; transfer-syntax={ts}"),
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let ct = r.headers()["content-type"].to_str().unwrap().to_string();
        let p = parts(&ct, &r.bytes().await.unwrap()).remove(0);
        got.push((header(&p.0, "content-type").unwrap().to_string(), p.1));
    }
    assert_eq!(
        got[0].0,
        "application/dicom; transfer-syntax=1.2.840.10008.1.2"
    );
    assert_eq!(got[0].1, implicit, "as stored, byte for byte");
    assert_eq!(
        got[1].0,
        format!("application/dicom; transfer-syntax={EXPLICIT_LE}")
    );
    let (ts, re_encoded) = pixels(&got[1].1);
    assert_eq!(ts, EXPLICIT_LE);
    assert_eq!(re_encoded, pixels(&files[1]).1, "the same pixel data");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_readme_orthanc_dicomweb_client_example_runs_as_written() {
    if !orthanc_dicomweb_present() {
        return;
    }
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    if !root.join(".testdata/lidc/1-010.dcm").is_file() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            ".testdata/lidc is missing and CTRECON_REQUIRE_TEST_DATA=1"
        );
        eprintln!("skipped: .testdata/lidc is missing");
        return;
    }
    let have = |t: &str| {
        std::process::Command::new(t)
            .arg("--version")
            .output()
            .is_ok()
    };
    if !(have("curl") && have("jq")) {
        eprintln!("skipped: the README's Orthanc example needs curl and jq");
        return;
    }
    let scripts = common::readme_blocks("sh dicomweb-orthanc");
    assert_eq!(scripts.len(), 1, "one script");
    // ctrecon as the README shows it (no token); Orthanc with the README's server entry for it.
    let app = common::spawn_app_with(|s| {
        s.dicom.stable_age_secs = 1;
        s.max_upload_bytes = 64 << 20;
    })
    .await;
    let o = Orthanc::start(OrthancOptions {
        dicomweb: Some((format!("{}/dicom-web/", app.base), Some("<token>".into()))),
        ..Default::default()
    })
    .await;
    let script = format!(
        "set -euo pipefail\ncurl() {{ command curl --fail-with-body \"$@\"; }}\n{}",
        scripts[0]
            .replace("localhost:8080", app.base.trim_start_matches("http://"))
            .replace("localhost:8042", &format!("127.0.0.1:{}", o.http_port))
    );
    // From a folder of its own, with the series where the README says (`$SERIES`).
    let work = tempfile::tempdir().unwrap();
    let dir = work.path().to_path_buf();
    let series = root.join(".testdata/lidc");
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("timeout")
            .args(["120", "bash", "-c"])
            .arg(&script)
            .current_dir(dir)
            .env("SERIES", series)
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
    // ctrecon holds the slice Orthanc pushed, as it was sent.
    let found: Value = app
        .get("/dicom-web/instances?PatientID=LIDC-IDRI-0001")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(found.as_array().unwrap().len(), 1, "{found}");
}
