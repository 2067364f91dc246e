//! WADO-RS and STOW-RS details against real tools and analytic truth: instances stored compressed (JPEG
//! lossless, JPEG-LS and RLE made by DCMTK from a synthetic series; JPEG baseline and extended, JPEG 2000,
//! JPEG-LS near-lossless and colour RLE from the pydicom corpus) retrieved in explicit VR little endian with
//! the pixels decoded (equal to the original values where the compression is lossless, to the stored stream
//! decoded where it is not; read back by DCMTK), and as stored on `transfer-syntax=*`; rendered frames as
//! JPEG against the PNG of the same window, with `quality` and `viewport`; the STOW-RS size limits; and a
//! series sent in two STOW-RS requests, answered before assembly and assembled once.
//!
//! DCMTK comes from Debian's `dcmtk` package; without it the tests that need it print one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1`.

use crate::common;
use crate::dw;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{assert_problem, read_npy_f32, spawn_app_with};
use ctrecon::dicom::{Instance, ReadLimits, read_bytes};
use dw::{
    EXPLICIT_LE, STOW_TYPE, TOKEN, ctrecon, header, multipart, parts, seq_values, stow, synthetic,
    value,
};
use serde_json::Value;

fn dcmtk_present() -> bool {
    let ok = [
        "dcmcjpeg", "dcmcjpls", "dcmcrle", "dcmconv", "dcmodify", "dcmdump",
    ]
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
            "DCMTK is missing and CTRECON_REQUIRE_PEERS=1 (scripts/install-peers.sh dcmtk)"
        );
        eprintln!("skipped: DCMTK is not installed (scripts/install-peers.sh dcmtk)");
    }
    ok
}

fn corpus() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/pydicom");
    if !dir.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
            dir.display()
        );
        eprintln!("skipped: {} is missing", dir.display());
        return None;
    }
    Some(dir)
}

fn dcmtk(tool: &str, args: &[&str]) -> String {
    let out = std::process::Command::new(tool)
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{tool} {args:?}: {text}");
    text
}

fn read(label: &str, bytes: &[u8]) -> Instance {
    read_bytes(label, bytes, &ReadLimits::default())
        .unwrap_or_else(|e| panic!("{label} does not read: {e}"))
}

/// One instance of the test: its name, the file as stored, and whether its compression is lossless (then
/// the original uncompressed file, whose values the decoded ones must equal).
struct Case {
    name: String,
    stored: Vec<u8>,
    original: Option<Vec<u8>>,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_instances_are_sent_decoded_in_explicit_vr_unless_the_stored_syntax_is_asked_for()
 {
    if !dcmtk_present() {
        return;
    }
    let Some(pydicom) = corpus() else { return };
    let work = tempfile::tempdir().unwrap();
    let w = |name: &str| work.path().join(name).to_string_lossy().into_owned();
    // DCMTK compresses synthetic CT slices (signed 16-bit) losslessly in four syntaxes and deflates one.
    // One slice of its own per syntax, so that every part has its own SOP Instance UID.
    let (_, _, files) = synthetic(5, None, "DW-TS");
    let mut cases = Vec::new();
    let made: [(&str, &str, &[&str]); 5] = [
        ("jpeg-lossless-sv1", "dcmcjpeg", &["+e1"]),
        ("jpeg-lossless", "dcmcjpeg", &["+el"]),
        ("jpeg-ls", "dcmcjpls", &["+el"]),
        ("rle", "dcmcrle", &[]),
        ("deflate", "dcmconv", &["+td"]),
    ];
    for (k, (name, tool, opts)) in made.iter().enumerate() {
        let src = w(&format!("src-{k}.dcm"));
        std::fs::write(&src, &files[k % files.len()]).unwrap();
        let out = w(&format!("{name}.dcm"));
        let mut a: Vec<&str> = opts.to_vec();
        a.extend([src.as_str(), out.as_str()]);
        dcmtk(tool, &a);
        cases.push(Case {
            name: name.to_string(),
            stored: std::fs::read(&out).unwrap(),
            original: Some(files[k % files.len()].clone()),
        });
    }
    // The pydicom corpus: JPEG 2000 (a CT, and a YCbCr colour Secondary Capture that decodes to RGB),
    // JPEG baseline of YCbCr colour, colour RLE, JPEG-LS near-lossless, JPEG extended 12-bit, and the same
    // 12-bit stream turned progressive (SOF2), which no decoder of the build reads (the last). Each gets
    // UIDs of its own (DCMTK rewrites the header, the pixel data is left as it is).
    for (k, name) in [
        "693_J2KI.dcm",
        "GDCMJ2K_TextGBR.dcm",
        "SC_rgb_jpeg_dcmtk.dcm",
        "SC_rgb_rle.dcm",
        "JPEGLSNearLossless_16.dcm",
        "JPEG-lossy.dcm",
        "JPEG-lossy-progressive",
    ]
    .iter()
    .enumerate()
    {
        let out = w(&format!("corpus-{k}.dcm"));
        if *name == "JPEG-lossy-progressive" {
            let mut b = std::fs::read(pydicom.join("JPEG-lossy.dcm")).unwrap();
            let sof = b
                .windows(5)
                .position(|w| w == [0xFF, 0xC1, 0x00, 0x0B, 12])
                .unwrap();
            b[sof + 1] = 0xC2;
            std::fs::write(&out, b).unwrap();
        } else {
            std::fs::copy(pydicom.join(name), &out).unwrap();
        }
        let uid = |n: u32| format!("2.25.{}{n}", 1000 + k);
        dcmtk(
            "dcmodify",
            &[
                "-nb",
                "-i",
                &format!("StudyInstanceUID={}", uid(1)),
                "-i",
                &format!("SeriesInstanceUID={}", uid(2)),
                "-i",
                &format!("SOPInstanceUID={}", uid(3)),
                &out,
            ],
        );
        cases.push(Case {
            name: name.to_string(),
            stored: std::fs::read(&out).unwrap(),
            original: None,
        });
    }
    let (app, client) = ctrecon().await;
    let body = multipart(
        &cases
            .iter()
            .map(|c| ("application/dicom", c.stored.as_slice()))
            .collect::<Vec<_>>(),
    );
    let (status, v) = stow(&client, app.url("/dicom-web/studies"), body).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(seq_values(&v, "00081199", "00081155").len(), cases.len());

    let get = |url: String, accept: &'static str| {
        let client = client.clone();
        async move {
            let r = client
                .get(&url)
                .header("accept", accept)
                .send()
                .await
                .unwrap();
            if r.status() != 200 {
                panic!(
                    "{url} ({accept}): {} {}",
                    r.status(),
                    r.text().await.unwrap()
                );
            }
            let ct = r.headers()["content-type"].to_str().unwrap().to_string();
            let mut p = parts(&ct, &r.bytes().await.unwrap());
            assert_eq!(p.len(), 1);
            p.remove(0)
        }
    };
    // A progressive 12-bit JPEG is stored and sent as stored, and refused with 406 in explicit VR little
    // endian, whose pixels would have to be decoded.
    let undecodable = cases.pop().unwrap();
    let h = ctrecon::dicom::header_of(&undecodable.name, &undecodable.stored).unwrap();
    assert_eq!(h.transfer_syntax, "1.2.840.10008.1.2.4.51");
    assert!(read_bytes("12-bit", &undecodable.stored, &ReadLimits::default()).is_err());
    let url = app.url(&format!(
        "/dicom-web/studies/{}/series/{}/instances/{}",
        h.study_uid, h.series_uid, h.sop_instance_uid
    ));
    for accept in [
        "multipart/related; type=\"application/dicom\"",
        "multipart/related; type=\"application/dicom\"; transfer-syntax=1.2.840.10008.1.2.1",
    ] {
        let r = client
            .get(&url)
            .header("accept", accept)
            .send()
            .await
            .unwrap();
        let p = assert_problem(r, 406, "not_acceptable").await;
        assert!(
            p["detail"]
                .as_str()
                .unwrap_or("")
                .contains("explicit VR little endian"),
            "{p}"
        );
    }
    assert_eq!(
        get(
            url,
            "multipart/related; type=\"application/dicom\"; transfer-syntax=*"
        )
        .await
        .1,
        undecodable.stored
    );
    let mut syntaxes = std::collections::BTreeSet::new();
    for c in &cases {
        let stored = read(&c.name, &c.stored);
        syntaxes.insert(stored.transfer_syntax.clone());
        let url = app.url(&format!(
            "/dicom-web/studies/{}/series/{}/instances/{}",
            stored.study_uid.as_deref().unwrap(),
            stored.series_uid,
            stored.sop_instance_uid
        ));
        // Explicit VR little endian on request, and by default: the same bytes.
        let explicit = get(
            url.clone(),
            "multipart/related; type=\"application/dicom\"; transfer-syntax=1.2.840.10008.1.2.1",
        )
        .await;
        let default = get(url.clone(), "multipart/related; type=\"application/dicom\"").await;
        assert_eq!(
            header(&explicit.0, "content-type"),
            Some(&*format!(
                "application/dicom; transfer-syntax={EXPLICIT_LE}"
            )),
            "{}",
            c.name
        );
        assert_eq!(explicit.1, default.1, "{}", c.name);
        let sent = read(&c.name, &explicit.1);
        assert_eq!(sent.transfer_syntax, EXPLICIT_LE, "{}", c.name);
        assert_eq!(sent.sop_instance_uid, stored.sop_instance_uid);
        // Native pixel data of the declared size, in the meta group's syntax.
        let obj = dicom_object::from_reader(std::io::Cursor::new(&explicit.1[128..])).unwrap();
        assert_eq!(
            obj.meta().transfer_syntax().trim_end_matches('\0'),
            EXPLICIT_LE
        );
        let pixel = obj.element(dicom_dictionary_std::tags::PIXEL_DATA).unwrap();
        assert!(
            pixel.fragments().is_none(),
            "{}: still encapsulated",
            c.name
        );
        let bits: usize = obj
            .element(dicom_dictionary_std::tags::BITS_ALLOCATED)
            .unwrap()
            .to_int()
            .unwrap();
        let samples: usize = sent.slices.iter().map(|s| s.stored.len()).sum();
        assert_eq!(
            pixel.to_bytes().unwrap().len(),
            (samples * bits / 8).next_multiple_of(2),
            "{}",
            c.name
        );
        // The decoded values: those of the stored stream, and the original ones when lossless.
        assert_eq!(sent.slices.len(), stored.slices.len());
        for (a, b) in sent.slices.iter().zip(&stored.slices) {
            assert_eq!(a.stored, b.stored, "{}", c.name);
        }
        if let Some(original) = &c.original {
            assert_eq!(
                sent.slices[0].stored,
                read("original", original).slices[0].stored,
                "{}: lossless",
                c.name
            );
        }
        // Colour decoded from JPEG or JPEG 2000 is RGB, whatever YBR the stream was.
        if stored.samples_per_pixel == 3 {
            assert_eq!(sent.photometric, "RGB", "{}", c.name);
        } else {
            assert_eq!(sent.photometric, stored.photometric, "{}", c.name);
        }
        // DCMTK reads what was sent, in explicit VR little endian.
        let path = work.path().join(format!("sent-{}", c.name));
        std::fs::write(&path, &explicit.1).unwrap();
        let dump = dcmtk("dcmdump", &["+P", "0002,0010", &path.to_string_lossy()]);
        assert!(dump.contains("=LittleEndianExplicit"), "{}: {dump}", c.name);
        // The stored syntax on request: the stored bytes.
        let as_stored = get(
            url,
            "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
        )
        .await;
        assert_eq!(as_stored.1, c.stored, "{}", c.name);
        assert_eq!(
            header(&as_stored.0, "content-type"),
            Some(&*format!(
                "application/dicom; transfer-syntax={}",
                stored.transfer_syntax
            ))
        );
    }
    // JPEG baseline, extended and lossless (two), JPEG 2000 (two), JPEG-LS (two), RLE and deflate.
    assert_eq!(syntaxes.len(), 10, "{syntaxes:?}");
}

fn png_grey(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes.to_vec()))
        .read_info()
        .unwrap();
    let mut buf = vec![0; dec.output_buffer_size().unwrap()];
    let info = dec.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

fn jpeg_grey(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut dec = jpeg_decoder::Decoder::new(std::io::Cursor::new(bytes));
    let px = dec.decode().unwrap();
    let info = dec.info().unwrap();
    assert_eq!(info.pixel_format, jpeg_decoder::PixelFormat::L8);
    (info.width as u32, info.height as u32, px)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rendered_frames_come_as_jpeg_when_asked_with_the_quality_and_viewport_asked_for() {
    let (app, client) = ctrecon().await;
    let (study, series, files) = synthetic(4, None, "DW-R");
    let (status, v) = stow(
        &client,
        app.url("/dicom-web/studies"),
        multipart(&[("application/dicom", &files[1])]),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let sop = seq_values(&v, "00081199", "00081155")
        .into_iter()
        .next()
        .unwrap();
    let inst = format!("/dicom-web/studies/{study}/series/{series}/instances/{sop}");
    let fetch = |query: &str, accept: &str| {
        let (client, url, accept) = (
            client.clone(),
            app.url(&format!("{inst}/rendered{query}")),
            accept.to_string(),
        );
        async move {
            client
                .get(url)
                .header("accept", accept)
                .send()
                .await
                .unwrap()
        }
    };
    let ok = |r: reqwest::Response, ct: &'static str| async move {
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], ct);
        assert_eq!(
            r.headers()["content-location"].to_str().unwrap(),
            r.url().as_str().split('?').next().unwrap()
        );
        r.bytes().await.unwrap().to_vec()
    };
    let window = "?window=40,400";
    let png = png_grey(&ok(fetch(window, "image/png").await, "image/png").await);
    let jpeg90 = ok(
        fetch(&format!("{window}&quality=90"), "image/jpeg").await,
        "image/jpeg",
    )
    .await;
    let jpeg10 = ok(
        fetch(&format!("{window}&quality=10"), "image/jpeg").await,
        "image/jpeg",
    )
    .await;
    // The PNG is the window exactly: 40 + i + 2j + 3 HU at (j, i) of slice 1 outside the 400 HU block.
    assert_eq!((png.0, png.1), (48, 40));
    // (Slice 1 of 4 has no bone block.)
    let hu = |j: usize, i: usize| 40.0 + (i + 2 * j + 3) as f64;
    for (j, i) in [(0usize, 0usize), (5, 40), (39, 47)] {
        let want = ((hu(j, i) + 160.0) / 400.0 * 255.0).round();
        assert!((png.2[j * 48 + i] as f64 - want).abs() <= 1.0, "({j},{i})");
    }
    // The JPEG is the PNG within the JPEG error: a few grey levels on average at quality 90, more at 10.
    let mad = |jpeg: &[u8]| {
        let (w, h, px) = jpeg_grey(jpeg);
        assert_eq!((w, h), (48, 40));
        px.iter()
            .zip(&png.2)
            .map(|(&a, &b)| (a as f64 - b as f64).abs())
            .sum::<f64>()
            / px.len() as f64
    };
    let (m90, m10) = (mad(&jpeg90), mad(&jpeg10));
    println!("mean absolute difference from the PNG: {m90:.2} at quality 90, {m10:.2} at 10");
    assert!(m90 < 3.0, "{m90}");
    assert!(m10 < 20.0 && m10 > m90, "{m10} vs {m90}");
    assert!(jpeg10.len() < jpeg90.len());
    // Accept: JPEG preferred by q, any image is PNG, another type 406.
    let r = fetch(window, "image/png;q=0.5, image/jpeg").await;
    ok(r, "image/jpeg").await;
    let r = fetch(window, "image/*").await;
    ok(r, "image/png").await;
    assert_problem(fetch(window, "image/gif").await, 406, "not_acceptable").await;
    // A viewport of half the size: each pixel the mean of a 2 × 2 block (the window is linear there).
    let half = png_grey(
        &ok(
            fetch(&format!("{window}&viewport=24,20"), "image/png").await,
            "image/png",
        )
        .await,
    );
    assert_eq!((half.0, half.1), (24, 20));
    for (r, c) in [(0usize, 0usize), (7, 3), (19, 23)] {
        let block = [(0, 0), (0, 1), (1, 0), (1, 1)]
            .iter()
            .map(|(dr, dc)| png.2[(2 * r + dr) * 48 + 2 * c + dc] as f64)
            .sum::<f64>()
            / 4.0;
        assert!(
            (half.2[r * 24 + c] as f64 - block).abs() <= 1.0,
            "({r},{c}): {} vs {block}",
            half.2[r * 24 + c]
        );
    }
    // A viewport fits the frame with its aspect ratio.
    let wide = jpeg_grey(
        &ok(
            fetch(&format!("{window}&viewport=96,20"), "image/jpeg").await,
            "image/jpeg",
        )
        .await,
    );
    assert_eq!((wide.0, wide.1), (24, 20));
    for bad in [
        "?quality=0",
        "?quality=101",
        "?quality=high",
        "?viewport=0,10",
        "?viewport=48,40,0,0,24,20",
        "?annotation=patient",
    ] {
        let r = fetch(bad, "image/jpeg").await;
        assert_problem(r, 400, "invalid_query").await;
    }
    // The metadata names its resource too.
    let r = client
        .get(app.url(&format!("{inst}/metadata")))
        .send()
        .await
        .unwrap();
    assert_eq!(
        r.headers()["content-location"].to_str().unwrap(),
        app.url(&format!("{inst}/metadata"))
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stow_body_over_the_upload_limit_is_413_and_an_instance_over_the_instance_limit_a700() {
    let app = spawn_app_with(|s| {
        s.api_tokens = vec![TOKEN.to_string()];
        s.max_upload_bytes = 40_000;
        s.dicom.max_instance_bytes = 20_000;
    })
    .await;
    let client = reqwest::Client::builder()
        .default_headers(
            [(
                reqwest::header::AUTHORIZATION,
                format!("Bearer {TOKEN}").parse().unwrap(),
            )]
            .into_iter()
            .collect(),
        )
        .build()
        .unwrap();
    let (_, _, files) = synthetic(12, None, "DW-L");
    let slice = files[0].len();
    assert!(
        slice < 20_000 && slice * 12 > 40_000 && slice + 25_000 < 40_000,
        "{slice}"
    );
    let count = || {
        let client = client.clone();
        let url = app.url("/dicom-web/instances?PatientID=DW-L");
        async move {
            let v: Value = client.get(url).send().await.unwrap().json().await.unwrap();
            v.as_array().unwrap().len()
        }
    };
    // The whole body over the upload limit: 413, nothing stored.
    let all = multipart(
        &files
            .iter()
            .map(|f| ("application/dicom", f.as_slice()))
            .collect::<Vec<_>>(),
    );
    let r = client
        .post(app.url("/dicom-web/studies"))
        .header("content-type", STOW_TYPE)
        .body(all)
        .send()
        .await
        .unwrap();
    assert_problem(r, 413, "body_too_large").await;
    assert_eq!(count().await, 0);
    // An instance over the instance limit beside one within it: 202, A700 for the large one.
    let mut big = files[1].clone();
    big.resize(25_000, 0);
    let (status, v) = stow(
        &client,
        app.url("/dicom-web/studies"),
        multipart(&[
            ("application/dicom", &files[2]),
            ("application/dicom", &big),
        ]),
    )
    .await;
    assert_eq!(status, 202, "{v}");
    assert_eq!(
        seq_values(&v, "00081198", "00081197"),
        [(0xA700).to_string()].into()
    );
    assert_eq!(seq_values(&v, "00081199", "00081155").len(), 1);
    assert_eq!(count().await, 1);
    // Alone: 409.
    let (status, _) = stow(
        &client,
        app.url("/dicom-web/studies"),
        multipart(&[("application/dicom", &big)]),
    )
    .await;
    assert_eq!(status, 409);
    assert_eq!(count().await, 1);
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("tmp"))
            .map(|d| d.count())
            .unwrap_or(0),
        0,
        "temporaries left behind"
    );
}

/// The `.npy` volumes of assembled series in the data directory.
fn assembled(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir.join("series"))
        .map(|d| d.flatten().map(|e| e.path()).collect())
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_series_sent_in_two_stow_requests_is_answered_at_once_and_assembled_once_when_stable() {
    let (app, client) = ctrecon().await;
    let core = app.core.clone().unwrap();
    let (study, series, files) = synthetic(6, None, "DW-S");
    let body = |fs: &[Vec<u8>]| {
        multipart(
            &fs.iter()
                .map(|f| ("application/dicom", f.as_slice()))
                .collect::<Vec<_>>(),
        )
    };
    let (status, v) = stow(&client, app.url("/dicom-web/studies"), body(&files[..3])).await;
    assert_eq!(status, 200, "{v}");
    // Answered once stored and indexed: found at once, not assembled yet.
    let found = |path: String| {
        let client = client.clone();
        let url = app.url(&path);
        async move {
            let v: Value = client.get(url).send().await.unwrap().json().await.unwrap();
            v
        }
    };
    let inst = found(format!(
        "/dicom-web/studies/{study}/series/{series}/instances"
    ))
    .await;
    assert_eq!(inst.as_array().unwrap().len(), 3);
    assert!(assembled(app.dir.path()).is_empty());
    assert_eq!(core.stow_arriving(), vec![(series.clone(), 3)]);
    let (status, _) = stow(
        &client,
        app.url(&format!("/dicom-web/studies/{study}")),
        body(&files[3..]),
    )
    .await;
    assert_eq!(status, 200);
    assert_eq!(core.stow_arriving(), vec![(series.clone(), 6)]);
    // Stable after a second: one series of six slices, whose volume is the written values.
    let deadline = Instant::now() + Duration::from_secs(60);
    while assembled(app.dir.path()).is_empty() {
        assert!(Instant::now() < deadline, "the series was not assembled");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let volumes = assembled(app.dir.path());
    assert_eq!(volumes.len(), 1, "assembled once: {volumes:?}");
    assert!(core.stow_arriving().is_empty());
    let id = volumes[0]
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    let s: Value = client
        .get(app.url(&format!("/v1/series/{id}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(s["series_uid"], series.as_str());
    assert_eq!(s["instances"], 6);
    assert_eq!(s["shape"], serde_json::json!([6, 40, 48]));
    let npy = client
        .get(app.url(&format!("/v1/series/{id}/volume.npy")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (_, hu) = read_npy_f32(&npy);
    let mut worst = 0.0f32;
    for k in 0..6 {
        for j in 0..40 {
            for i in 0..48 {
                let bone = (8..32).contains(&i) && (10..30).contains(&j) && (2..4).contains(&k);
                let want = if bone {
                    400.0
                } else {
                    40.0 + (i + 2 * j + 3 * k) as f32
                };
                worst = worst.max((hu[(k * 40 + j) * 48 + i] - want).abs());
            }
        }
    }
    assert!(worst <= 0.5, "worst HU error {worst}");
    // The instances name their series now, and are still found once each.
    let inst = found(format!(
        "/dicom-web/studies/{study}/series/{series}/instances"
    ))
    .await;
    assert_eq!(inst.as_array().unwrap().len(), 6);
    assert_eq!(value(&inst[0], "0020000E"), Some(series));
}

/// 12-bit JPEG Extended as DCMTK writes it from CT slices (`dcmcjpeg +ee`, which maps the signed 16-bit
/// values to 12 bits under a new rescale) reads as DCMTK's own decoder (`dcmdjpeg`) decodes it, sample for
/// sample, and its Hounsfield units are the original's within the 12-bit step and the compression's error:
/// a synthetic series, and LIDC-IDRI-0001's first slices when present.
#[test]
fn twelve_bit_jpeg_extended_reads_as_dcmtk_decodes_it() {
    if !dcmtk_present() {
        return;
    }
    let work = tempfile::tempdir().unwrap();
    let w = |name: &str| work.path().join(name).to_string_lossy().into_owned();
    let (_, _, files) = synthetic(3, None, "DW-J12");
    let mut sources: Vec<(String, Vec<u8>)> = files
        .into_iter()
        .enumerate()
        .map(|(k, f)| (format!("synthetic-{k}"), f))
        .collect();
    // Already 12-bit JPEG Extended (its scan header's spectral values are not a sequential scan's; DCMTK
    // decodes it as sequential after a warning, and so does ctrecon).
    let made_elsewhere = corpus().map(|d| std::fs::read(d.join("JPEG-lossy.dcm")).unwrap());
    let lidc = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if lidc.is_dir() {
        let mut slices: Vec<PathBuf> = std::fs::read_dir(&lidc)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
            .collect();
        slices.sort();
        for p in slices.iter().step_by(40) {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            sources.push((name, std::fs::read(p).unwrap()));
        }
    } else {
        eprintln!("skipped (LIDC part): {} is missing", lidc.display());
    }
    if let Some(stored) = &made_elsewhere {
        let (jpeg, back) = (w("JPEG-lossy.dcm"), w("JPEG-lossy-dec.dcm"));
        std::fs::write(&jpeg, stored).unwrap();
        dcmtk("dcmdjpeg", &[&jpeg, &back]);
        let ours = read("JPEG-lossy.dcm", stored);
        let theirs = read("JPEG-lossy.dcm (dcmdjpeg)", &std::fs::read(&back).unwrap());
        assert_eq!(ours.transfer_syntax, "1.2.840.10008.1.2.4.51");
        assert_eq!(
            ours.slices[0].stored, theirs.slices[0].stored,
            "JPEG-lossy.dcm"
        );
    }
    for (name, original) in &sources {
        let (src, jpeg, back) = (
            w(&format!("{name}.dcm")),
            w(&format!("{name}-ee.dcm")),
            w(&format!("{name}-dec.dcm")),
        );
        std::fs::write(&src, original).unwrap();
        dcmtk("dcmcjpeg", &["+ee", &src, &jpeg]);
        dcmtk("dcmdjpeg", &[&jpeg, &back]);
        let stored = std::fs::read(&jpeg).unwrap();
        assert_eq!(
            ctrecon::dicom::header_of(name, &stored)
                .unwrap()
                .transfer_syntax,
            "1.2.840.10008.1.2.4.51"
        );
        let ours = read(name, &stored);
        let theirs = read(
            &format!("{name} (dcmdjpeg)"),
            &std::fs::read(&back).unwrap(),
        );
        let orig = read(&format!("{name} (original)"), original);
        let (a, b, o) = (&ours.slices[0], &theirs.slices[0], &orig.slices[0]);
        assert_eq!((a.rows, a.columns), (o.rows, o.columns), "{name}");
        let differ = a
            .stored
            .iter()
            .zip(&b.stored)
            .filter(|(x, y)| x != y)
            .count();
        assert_eq!(
            differ, 0,
            "{name}: {differ} samples differ from DCMTK's decoding"
        );
        assert!(
            a.stored.iter().all(|&v| (0.0..=4095.0).contains(&v)),
            "{name}: 12-bit values"
        );
        assert_eq!(
            (a.rescale_slope, a.rescale_intercept),
            (b.rescale_slope, b.rescale_intercept)
        );
        // Hounsfield units against the original: within four 12-bit steps (the new slope) on average, the
        // compression at DCMTK's default quality (90) included.
        let hu = |s: &ctrecon::series::Slice, k: usize| {
            f64::from(s.stored[k]) * s.rescale_slope + s.rescale_intercept
        };
        let n = o.stored.len();
        let mean_err = (0..n).map(|k| (hu(a, k) - hu(o, k)).abs()).sum::<f64>() / n as f64;
        assert!(
            mean_err <= 4.0 * a.rescale_slope.max(1.0),
            "{name}: mean |ΔHU| {mean_err:.2} (slope {})",
            a.rescale_slope
        );
        println!(
            "{name}: slope {:.4}, mean |ΔHU| {mean_err:.2}",
            a.rescale_slope
        );
    }
}
