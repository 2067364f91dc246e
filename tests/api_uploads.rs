//! Uploads against the real server: bad files refused one by one while the good ones are stored, bodies
//! streamed to disk (the allocation peak of a 64 MB upload is measured by a counting allocator in this test
//! binary), ZIP members inflated one by one under caps (a 1 GB zip bomb, an oversized member, climbing names),
//! the start-up sweep of orphan files, and DELETE of series and datasets.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use common::{TestApp, assert_problem, spawn_app_with};
use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::recon::VolumeGrid;
use ctrecon::volume::{Frame, Volume};
use serde_json::{Value, json};

/// The system allocator, counting the bytes live now and the most live since the last reset.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call is forwarded to the system allocator unchanged; only counters are updated beside it.
#[allow(unsafe_code)] // a counting allocator wraps the system one
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's layout.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `alloc` with this layout.
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded unchanged.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::Relaxed)
                    + (new_size - layout.size());
                PEAK.fetch_max(now, Ordering::Relaxed);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Tests that measure the allocation peak run alone (write); the others share (read).
static EXCLUSIVE: tokio::sync::RwLock<()> = tokio::sync::RwLock::const_new(());

/// Bytes allocated at the peak of `f` beyond what was live when it started.
async fn peak_delta<T>(f: impl std::future::Future<Output = T>) -> (T, usize) {
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let out = f.await;
    (out, PEAK.load(Ordering::Relaxed).saturating_sub(base))
}

const MIB: usize = 1 << 20;

/// A small CT series (8 slices of 32 × 32, 2 mm apart), written by ctrecon.
fn slices() -> Vec<(String, Vec<u8>)> {
    let g = VolumeGrid {
        nx: 32,
        ny: 32,
        nz: 8,
        spacing_mm: [1.5, 1.5, 2.0],
        centre_mm: [0.0, 0.0, 0.0],
    };
    let data = ndarray::Array3::from_shape_fn((8, 32, 32), |(z, y, x)| {
        (z * 100 + y * 3 + x) as f32 - 500.0
    });
    let vol = Volume {
        data,
        frame: Frame::from_grid(&g),
    };
    let meta = SeriesMeta {
        series_description: "uploads".into(),
        series_number: 1,
        ..Default::default()
    };
    write_ct_series(&vol, &meta).unwrap().files
}

async fn post(
    app: &TestApp,
    path: &str,
    media: &str,
    body: impl Into<reqwest::Body>,
) -> reqwest::Response {
    app.client
        .post(app.url(path))
        .header("content-type", media)
        .body(body)
        .send()
        .await
        .unwrap()
}

fn form(files: &[(String, Vec<u8>)]) -> reqwest::multipart::Form {
    files
        .iter()
        .fold(reqwest::multipart::Form::new(), |f, (n, b)| {
            f.part(
                "file",
                reqwest::multipart::Part::bytes(b.clone()).file_name(n.clone()),
            )
        })
}

/// `(file, code)` of every rejected file of an upload's answer, sorted.
fn rejected(v: &Value) -> Vec<(String, String)> {
    let mut r: Vec<(String, String)> = v["rejected"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            assert!(!r["detail"].as_str().unwrap().is_empty(), "{r}");
            (
                r["file"].as_str().unwrap().to_string(),
                r["code"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    r.sort();
    r
}

fn tmp_entries(app: &TestApp) -> usize {
    std::fs::read_dir(app.dir.path().join("tmp"))
        .unwrap()
        .count()
}

/// `n` bytes of `byte` as a stream of 64 KiB chunks (never held whole).
fn stream_of(n: usize, byte: u8) -> reqwest::Body {
    let chunk = 64 << 10;
    let chunks = (0..n.div_ceil(chunk)).map(move |i| {
        let len = chunk.min(n - i * chunk);
        Ok::<_, std::io::Error>(vec![byte; len])
    });
    reqwest::Body::wrap_stream(futures_util::stream::iter(chunks))
}

#[tokio::test]
async fn bad_files_in_a_zip_or_a_form_are_refused_one_by_one_and_the_good_slices_stored() {
    let _shared = EXCLUSIVE.read().await;
    let app = spawn_app_with(|_| {}).await;
    let good = slices();
    let n = good.len();
    let mut truncated = good[0].1.clone();
    truncated.truncate(truncated.len() / 2);
    let mut files = good.clone();
    files.push(("broken.dcm".into(), truncated));
    files.push(("notes.txt".into(), b"this is not DICOM".to_vec()));
    // Cut inside its meta group (preamble, `DICM` and part of the group): once a 500 for the whole upload.
    files.push(("cut-meta.dcm".into(), good[1].1[..150].to_vec()));

    // A ZIP: N slices stored, the two bad files listed with their reasons.
    let r = post(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&files).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"].as_array().unwrap().len(), 1, "{v}");
    assert_eq!(v["series"][0]["status"], "ready");
    assert_eq!(v["series"][0]["series"]["instances"], n);
    assert_eq!(v["series"][0]["series"]["shape"], json!([n, 32, 32]));
    assert_eq!(v["upload"]["instances"], n + 3);
    let refused = rejected(&v);
    assert_eq!(refused.len(), 3, "{v}");
    assert_eq!(refused[0].0, "broken.dcm");
    assert!(
        ["dicom_parse_error", "dicom_pixel_data_short"].contains(&refused[0].1.as_str()),
        "{refused:?}"
    );
    assert_eq!(
        refused[1],
        ("cut-meta.dcm".into(), "dicom_parse_error".into())
    );
    assert_eq!(refused[2], ("notes.txt".into(), "dicom_not_dicom".into()));
    // The stored series answers with its slices.
    let id = v["series"][0]["series"]["id"].as_str().unwrap();
    let s: Value = app
        .get(&format!("/v1/series/{id}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(s["shape"], json!([n, 32, 32]));

    // The same as a multipart form.
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form(&files))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], n);
    assert_eq!(rejected(&v).len(), 3);

    // A member whose bytes were damaged in the archive (CRC mismatch) is refused alone.
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let stored =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, bytes) in &good {
        zip.start_file(name.as_str(), zip::write::SimpleFileOptions::default())
            .unwrap();
        zip.write_all(bytes).unwrap();
    }
    let marker = b"a stored member that will be damaged in transit";
    zip.start_file("damaged.dcm", stored).unwrap();
    zip.write_all(marker).unwrap();
    let mut archive = zip.finish().unwrap().into_inner();
    let at = archive
        .windows(marker.len())
        .position(|w| w == marker)
        .unwrap();
    archive[at + 5] ^= 0xff;
    let r = post(&app, "/v1/series", "application/zip", archive).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], n);
    assert_eq!(
        rejected(&v),
        [("damaged.dcm".to_string(), "zip_invalid".to_string())]
    );

    // A single bad instance is a problem of its own.
    assert_problem(
        post(
            &app,
            "/v1/series",
            "application/dicom",
            b"plain text".to_vec(),
        )
        .await,
        422,
        "dicom_not_dicom",
    )
    .await;
    assert_eq!(tmp_entries(&app), 0);
}

#[tokio::test]
async fn a_64_mb_upload_streams_to_disk_and_a_too_large_one_is_refused_while_streaming() {
    let _alone = EXCLUSIVE.write().await;
    let app = spawn_app_with(|s| s.max_upload_bytes = 128 << 20).await;
    let good = slices();
    let size = 64 * MIB;
    // The counter sees what is held: 32 MiB kept alive show as a peak of at least 32 MiB.
    let (held, peak) = peak_delta(async { vec![1u8; 32 * MIB] }).await;
    assert!(peak >= 32 * MIB && held.len() == 32 * MIB, "{peak}");
    drop(held);

    // Warm up first (database connections and page cache, worker threads): the peak below is the upload's.
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form(&good))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);

    // A form of the good slices and a 64 MB part that is not DICOM.
    let mut f = form(&good);
    f = f.part(
        "file",
        reqwest::multipart::Part::stream_with_length(stream_of(size, b'x'), size as u64)
            .file_name("big.bin"),
    );
    let req = app.client.post(app.url("/v1/series")).multipart(f);
    let (r, peak) = peak_delta(async { req.send().await.unwrap() }).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], good.len());
    assert_eq!(
        rejected(&v),
        [("big.bin".to_string(), "dicom_not_dicom".to_string())]
    );
    assert_eq!(
        v["upload"]["bytes"].as_u64().unwrap() as usize,
        size + good.iter().map(|f| f.1.len()).sum::<usize>()
    );
    eprintln!(
        "64 MiB form: allocation peak {:.2} MiB",
        peak as f64 / MIB as f64
    );
    assert!(peak < 16 * MIB, "a 64 MB form peaked at {} MiB", peak / MIB);

    // The same body raw, sent as a ZIP that it is not: refused from its first bytes.
    let (r, peak) = peak_delta(post(
        &app,
        "/v1/series",
        "application/zip",
        stream_of(size, 0),
    ))
    .await;
    let p = assert_problem(r, 415, "unsupported_media_type").await;
    assert!(
        p["detail"]
            .as_str()
            .is_some_and(|d| d.contains("is not a ZIP archive")),
        "{p}"
    );
    eprintln!(
        "64 MiB ZIP body: allocation peak {:.2} MiB",
        peak as f64 / MIB as f64
    );
    assert!(peak < 16 * MIB, "a 64 MB body peaked at {} MiB", peak / MIB);
    let (r, peak) = peak_delta(post(
        &app,
        "/v1/series",
        "application/dicom",
        stream_of(size, 0),
    ))
    .await;
    assert_problem(r, 422, "dicom_not_dicom").await;
    eprintln!(
        "64 MiB instance: allocation peak {:.2} MiB",
        peak as f64 / MIB as f64
    );
    assert!(
        peak < 16 * MIB,
        "a 64 MB instance peaked at {} MiB",
        peak / MIB
    );
    assert_eq!(tmp_entries(&app), 0);

    // A 64 MiB sinogram (.npy, 2048 views of 8192 samples) in a form streams to disk as well.
    let (views, det) = (2048usize, 8192usize);
    let header = common::npy("<f4", &format!("({views}, {det})"), &[]);
    let data = views * det * 4;
    let chunks = std::iter::once(Ok::<_, std::io::Error>(header.clone()))
        .chain((0..data / (64 << 10)).map(|_| Ok::<_, std::io::Error>(vec![0u8; 64 << 10])));
    let form = reqwest::multipart::Form::new()
        .text(
            "geometry",
            common::parallel_geometry(views, det, 0.1).to_string(),
        )
        .part(
            "data",
            reqwest::multipart::Part::stream_with_length(
                reqwest::Body::wrap_stream(futures_util::stream::iter(chunks)),
                (header.len() + data) as u64,
            )
            .file_name("s.npy"),
        );
    let req = app.client.post(app.url("/v1/sinograms")).multipart(form);
    let (r, peak) = peak_delta(async { req.send().await.unwrap() }).await;
    let status = r.status();
    let v: Value = r.json().await.unwrap();
    assert_eq!(status, 201, "{v}");
    assert_eq!(v["shape"], json!([views, det]), "{v}");
    eprintln!(
        "64 MiB sinogram: allocation peak {:.2} MiB",
        peak as f64 / MIB as f64
    );
    assert!(
        peak < 16 * MIB,
        "a 64 MiB sinogram peaked at {} MiB",
        peak / MIB
    );
    assert_eq!(tmp_entries(&app), 0);

    // Over the limit with no declared length: refused while streaming, nothing left in tmp/.
    let small = spawn_app_with(|s| s.max_upload_bytes = 4 << 20).await;
    let r = post(
        &small,
        "/v1/series",
        "application/zip",
        stream_of(8 * MIB, 1),
    )
    .await;
    assert_problem(r, 413, "body_too_large").await;
    let r = small
        .client
        .post(small.url("/v1/series"))
        .multipart(reqwest::multipart::Form::new().part(
            "file",
            reqwest::multipart::Part::stream(stream_of(8 * MIB, 1)).file_name("a.dcm"),
        ))
        .send()
        .await
        .unwrap();
    assert_problem(r, 413, "body_too_large").await;
    assert_eq!(tmp_entries(&small), 0);
}

/// A ZIP of `members` (name, bytes) deflated, plus `extra` written by `add`.
fn zip_with(
    members: &[(String, Vec<u8>)],
    add: impl FnOnce(&mut zip::ZipWriter<std::io::Cursor<Vec<u8>>>),
) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, bytes) in members {
        zip.start_file(name.as_str(), zip::write::SimpleFileOptions::default())
            .unwrap();
        zip.write_all(bytes).unwrap();
    }
    add(&mut zip);
    zip.finish().unwrap().into_inner()
}

/// `zip` with the uncompressed size of member `name` declared as `size` in its local header and its central
/// directory entry (what a lying archive does).
fn declare_size(mut zip: Vec<u8>, name: &str, size: u32) -> Vec<u8> {
    let mut patched = 0;
    for (signature, size_at, name_at) in [(b"PK\x03\x04", 22, 30), (b"PK\x01\x02", 24, 46)] {
        let mut i = 0;
        while i + name_at + name.len() <= zip.len() {
            if &zip[i..i + 4] == signature
                && &zip[i + name_at..i + name_at + name.len()] == name.as_bytes()
            {
                zip[i + size_at..i + size_at + 4].copy_from_slice(&size.to_le_bytes());
                patched += 1;
            }
            i += 1;
        }
    }
    assert_eq!(patched, 2, "the member's two headers");
    zip
}

#[tokio::test]
async fn zip_bombs_oversized_members_and_climbing_names_are_refused_member_by_member() {
    let _alone = EXCLUSIVE.write().await;
    let app = spawn_app_with(|s| s.zip_max_member_bytes = 2 * MIB as u64).await;
    let good = slices();
    let n = good.len();

    // 1 GiB of zeros deflated to about 1 MiB, written in 1 MiB pieces (never held whole).
    let zeros = vec![0u8; MIB];
    let bomb = zip_with(&good, |z| {
        z.start_file("zeros.dcm", zip::write::SimpleFileOptions::default())
            .unwrap();
        for _ in 0..1024 {
            z.write_all(&zeros).unwrap();
        }
    });
    drop(zeros);
    let bomb_len = bomb.len();
    assert!(bomb_len < 2 * MIB, "{bomb_len} bytes");
    let started = Instant::now();
    let (r, peak) = peak_delta(post(&app, "/v1/series", "application/zip", bomb)).await;
    let took = started.elapsed();
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], n);
    assert_eq!(
        rejected(&v),
        [("zeros.dcm".to_string(), "zip_limits_exceeded".to_string())]
    );
    let detail = v["rejected"][0]["detail"].as_str().unwrap();
    assert!(detail.contains("its compressed size"), "{detail}");
    eprintln!(
        "1 GiB zip bomb ({} bytes): allocation peak {:.2} MiB, {took:?}",
        bomb_len,
        peak as f64 / MIB as f64
    );
    assert!(peak < 16 * MIB, "the bomb peaked at {} MiB", peak / MIB);
    assert!(took < Duration::from_secs(5), "the bomb took {took:?}");

    // A bomb alone: the upload is refused with the bomb's code.
    let only = zip_with(&[], |z| {
        z.start_file("z.dcm", zip::write::SimpleFileOptions::default())
            .unwrap();
        z.write_all(&vec![0u8; 8 * MIB]).unwrap();
    });
    assert_problem(
        post(&app, "/v1/series", "application/zip", only).await,
        413,
        "zip_limits_exceeded",
    )
    .await;

    // A member that declares 1 KiB and inflates to 64 MiB (within the ratio cap of its compressed size) is
    // refused at the size it declares, not inflated to the caps.
    let liar = zip_with(&good, |z| {
        z.start_file("liar.dcm", zip::write::SimpleFileOptions::default())
            .unwrap();
        for _ in 0..64 {
            z.write_all(&vec![0u8; MIB]).unwrap();
        }
    });
    let liar = declare_size(liar, "liar.dcm", 1024);
    let r = post(&app, "/v1/series", "application/zip", liar).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(
        rejected(&v),
        [("liar.dcm".to_string(), "zip_limits_exceeded".to_string())]
    );
    let detail = v["rejected"][0]["detail"].as_str().unwrap();
    assert!(
        detail.contains("inflates past the 1024 bytes it declares"),
        "{detail}"
    );

    // An archive whose end record declares 65 534 entries is refused before they are read.
    let mut many = write_zip(&good).unwrap();
    let end = many.len() - 22;
    assert_eq!(&many[end..end + 4], b"PK\x05\x06");
    many[end + 8..end + 12].copy_from_slice(&[0xFE, 0xFF, 0xFE, 0xFF]);
    let p = assert_problem(
        post(&app, "/v1/series", "application/zip", many).await,
        413,
        "zip_limits_exceeded",
    )
    .await;
    assert!(
        p["detail"].as_str().unwrap().contains("65534 entries"),
        "{p}"
    );

    // A member over the per-member cap (3 MiB that do not compress) is listed as refused.
    let mut noise = vec![0u8; 3 * MIB];
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    for b in noise.iter_mut() {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        *b = s as u8;
    }
    let mut files = good.clone();
    files.push(("huge.dcm".into(), noise));
    let r = post(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&files).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], n);
    let refused = v["rejected"].as_array().unwrap();
    assert_eq!(refused.len(), 1, "{v}");
    assert_eq!(refused[0]["file"], "huge.dcm");
    assert_eq!(refused[0]["code"], "zip_limits_exceeded");
    assert!(
        refused[0]["detail"]
            .as_str()
            .unwrap()
            .contains("limit of one entry"),
        "{v}"
    );

    // Names that climb out or are absolute stay labels: the slices are read, nothing lands outside.
    let climbing: Vec<(String, Vec<u8>)> = good
        .iter()
        .enumerate()
        .map(|(i, (_, b))| {
            let name = if i % 2 == 0 {
                format!("../../x{i}.dcm")
            } else {
                format!("/tmp/abs{i}.dcm")
            };
            (name, b.clone())
        })
        .collect();
    let r = post(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&climbing).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["series"]["instances"], n);
    let parent = app.dir.path().parent().unwrap();
    for i in 0..n {
        assert!(!parent.join(format!("x{i}.dcm")).exists());
        assert!(!std::path::Path::new(&format!("/tmp/abs{i}.dcm")).exists());
    }
    assert_eq!(tmp_entries(&app), 0);
}

/// The value of a Prometheus sample line `name{labels} value`, or 0 when absent.
fn sample(metrics: &str, series: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(series)?.trim().parse().ok())
        .unwrap_or(0.0)
}

#[tokio::test]
async fn start_up_removes_orphan_files_and_marks_rows_whose_file_is_missing() {
    let _shared = EXCLUSIVE.read().await;
    use ctrecon::http::Application;
    let dir = tempfile::tempdir().unwrap();
    let settings = common::test_settings(dir.path());
    let client = reqwest::Client::new();

    // A first run stores a series (two, in fact, by uploading twice) and a simulation.
    let app = Application::build(settings.clone()).await.unwrap();
    let base = format!("http://{}", app.local_addr());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let served = tokio::spawn(app.run_until(async move {
        let _ = stopped.await;
    }));
    let mut series_ids = Vec::new();
    for _ in 0..2 {
        let r = client
            .post(format!("{base}/v1/series"))
            .header("content-type", "application/zip")
            .body(write_zip(&slices()).unwrap())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
        let v: Value = r.json().await.unwrap();
        series_ids.push(v["series"][0]["series"]["id"].as_str().unwrap().to_string());
    }
    let r = client
        .post(format!("{base}/v1/simulations"))
        .json(
            &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 20.0},
                      "geometry": common::parallel_geometry(16, 32, 1.5)}),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let dataset: Value = r.json().await.unwrap();
    let dataset = dataset["id"].as_str().unwrap().to_string();
    // A finished job: its results folder has its row.
    let r = client
        .post(format!("{base}/v1/jobs"))
        .json(&json!({"input": dataset, "algorithm": {"name": "fbp"},
                      "grid": {"nx": 16, "ny": 16, "dx_mm": 1.25, "dy_mm": 1.25}}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let job: Value = r.json().await.unwrap();
    let job = job["id"].as_str().unwrap().to_string();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    loop {
        let j: Value = client
            .get(format!("{base}/v1/jobs/{job}"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if j["status"] != "queued" && j["status"] != "running" {
            assert_eq!(j["status"], "succeeded", "{j}");
            break;
        }
        assert!(std::time::Instant::now() < deadline, "{j}");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let _ = stop.send(());
    served.await.unwrap().unwrap();

    // What a kill -9 can leave: blobs renamed into place whose rows never landed, a row whose file is gone,
    // and files nobody named.
    let root = dir.path();
    let fresh = || uuid::Uuid::now_v7().to_string();
    std::fs::write(
        root.join("series").join(format!("{}.npy", fresh())),
        b"orphan",
    )
    .unwrap();
    std::fs::write(root.join("series").join("stray.npy"), b"orphan").unwrap();
    std::fs::write(
        root.join("datasets").join(format!("{}.npy", fresh())),
        b"orphan",
    )
    .unwrap();
    let upload_dir = root.join("uploads").join(fresh());
    std::fs::create_dir_all(&upload_dir).unwrap();
    std::fs::write(upload_dir.join("a.dcm"), b"orphan").unwrap();
    std::fs::write(root.join("tmp").join("half-written.part"), b"x").unwrap();
    // A job's results whose row was deleted before its folder was.
    let results_dir = root.join("results").join(fresh());
    std::fs::create_dir_all(&results_dir).unwrap();
    std::fs::write(results_dir.join("volume.npy"), b"orphan").unwrap();
    std::fs::remove_file(root.join("series").join(format!("{}.npy", series_ids[1]))).unwrap();

    // The second run sweeps before it serves.
    let app = Application::build(settings).await.unwrap();
    let base = format!("http://{}", app.local_addr());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(app.run_until(async move {
        let _ = stopped.await;
    }));
    let names = |sub: &str| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(root.join(sub))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    assert_eq!(names("series"), [format!("{}.npy", series_ids[0])]);
    assert_eq!(names("datasets"), [format!("{dataset}.npy")]);
    assert!(names("uploads").is_empty());
    assert!(names("tmp").is_empty());
    assert_eq!(names("results"), [job.as_str()]);
    let metrics = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let orphans = |kind: &str| {
        sample(
            &metrics,
            &format!("ctrecon_startup_orphans_removed_total{{kind=\"{kind}\"}}"),
        )
    };
    assert_eq!(
        (
            orphans("series"),
            orphans("dataset"),
            orphans("upload"),
            orphans("results")
        ),
        (2.0, 1.0, 1.0, 1.0),
        "{metrics}"
    );
    assert_eq!(
        sample(
            &metrics,
            "ctrecon_startup_missing_files_total{kind=\"series\"}"
        ),
        1.0
    );
    // The series whose volume is gone says so; the others are whole.
    let gone: Value = client
        .get(format!("{base}/v1/series/{}", series_ids[1]))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(gone["available"], false);
    let r = client
        .get(format!("{base}/v1/series/{}/volume.npy", series_ids[1]))
        .send()
        .await
        .unwrap();
    assert_problem(r, 410, "file_missing").await;
    let whole: Value = client
        .get(format!("{base}/v1/series/{}", series_ids[0]))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(whole["available"], true);
    let r = client
        .get(format!("{base}/v1/series/{}/volume.npy", series_ids[0]))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let d: Value = client
        .get(format!("{base}/v1/datasets/{dataset}"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(d["available"], true);
    let _ = stop.send(());
}

#[tokio::test]
async fn series_and_datasets_are_deleted_unless_a_queued_or_running_job_reads_them() {
    let _shared = EXCLUSIVE.read().await;
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 1).await;
    let dataset = app.simulate(common::cone_geometry(360, 128), 40.0).await;
    let r = post(
        &app,
        "/v1/series",
        "application/zip",
        write_zip(&slices()).unwrap(),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    let series = v["series"][0]["series"]["id"].as_str().unwrap().to_string();

    // A slow FDK reads the dataset; a volume job on the series waits behind it (one job at a time).
    let slow = app
        .submit(
            &json!({"input": dataset, "algorithm": {"name": "fdk", "filter": "hann"},
                        "grid": {"nx": 192, "ny": 192, "nz": 192, "spacing_mm": [1.0, 1.0, 1.0]},
                        "outputs": ["volume"]}),
        )
        .await;
    let slow = slow["id"].as_str().unwrap().to_string();
    let waiting = app
        .submit(&json!({"kind": "volume", "input": series,
                        "products": [{"type": "projection", "axis": "coronal", "kind": "mip"}]}))
        .await;
    let waiting = waiting["id"].as_str().unwrap().to_string();
    assert_eq!(app.job(&waiting).await["status"], "queued");
    let delete = |path: String| {
        let c = app.client.clone();
        let url = app.url(&path);
        async move { c.delete(url).send().await.unwrap() }
    };
    assert_problem(
        delete(format!("/v1/datasets/{dataset}")).await,
        409,
        "resource_in_use",
    )
    .await;
    assert_problem(
        delete(format!("/v1/series/{series}")).await,
        409,
        "resource_in_use",
    )
    .await;
    // Still there, files included.
    let series_file = app.dir.path().join("series").join(format!("{series}.npy"));
    let dataset_file = app
        .dir
        .path()
        .join("datasets")
        .join(format!("{dataset}.npy"));
    assert!(series_file.exists() && dataset_file.exists());

    // Once the jobs are canceled, both go: 204, the rows and the files.
    let r = app
        .post_json(&format!("/v1/jobs/{waiting}/cancel"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    let r = delete(format!("/v1/series/{series}")).await;
    assert_eq!(r.status(), 204);
    assert!(!series_file.exists());
    assert_problem(
        app.get(&format!("/v1/series/{series}")).await,
        404,
        "series_not_found",
    )
    .await;
    assert_problem(
        delete(format!("/v1/series/{series}")).await,
        404,
        "series_not_found",
    )
    .await;

    let r = app
        .post_json(&format!("/v1/jobs/{slow}/cancel"), &json!({}))
        .await;
    assert_eq!(r.status(), 202);
    app.finish(&slow).await;
    let r = delete(format!("/v1/datasets/{dataset}")).await;
    assert_eq!(r.status(), 204);
    assert!(!dataset_file.exists());
    assert_problem(
        app.get(&format!("/v1/datasets/{dataset}")).await,
        404,
        "dataset_not_found",
    )
    .await;
    assert_problem(
        delete(format!("/v1/datasets/{dataset}")).await,
        404,
        "dataset_not_found",
    )
    .await;
    assert_problem(
        delete("/v1/series/not-an-id".to_string()).await,
        400,
        "invalid_id",
    )
    .await;
    assert_problem(
        delete("/v1/datasets/nope".to_string()).await,
        400,
        "invalid_id",
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_being_assembled_and_jobs_share_one_memory_budget() {
    // Alone: the gauge is the process's, and other tests' uploads would set it too.
    let _alone = EXCLUSIVE.write().await;
    const BUDGET: u64 = 64 << 20;
    let app = spawn_app_with(|s| s.memory_budget_bytes = BUDGET).await;
    let engine = app.core.as_ref().expect("in process").engine.clone();
    let dataset = app
        .simulate(common::parallel_geometry(90, 48, 1.0), 20.0)
        .await;

    // While something holds the whole budget, an upload waits to be assembled and a job to start.
    let whole = engine.reserve_memory(BUDGET).await;
    let upload = {
        let (client, url) = (app.client.clone(), app.url("/v1/series"));
        tokio::spawn(async move {
            client
                .post(url)
                .header("content-type", "application/zip")
                .body(write_zip(&slices()).unwrap())
                .send()
                .await
                .unwrap()
        })
    };
    let job = app
        .submit(&json!({"input": dataset, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 32, "ny": 32, "dx_mm": 1.25, "dy_mm": 1.25}}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(!upload.is_finished(), "the upload waits for memory");
    assert_eq!(app.job(&id).await["status"], "queued");
    let metrics = app.get("/metrics").await.text().await.unwrap();
    assert_eq!(
        sample(&metrics, "ctrecon_memory_reserved_bytes"),
        BUDGET as f64
    );

    // Once it lets go, both go on.
    drop(whole);
    let r = tokio::time::timeout(Duration::from_secs(60), upload)
        .await
        .expect("the upload goes on")
        .unwrap();
    assert_eq!(r.status(), 201);
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let metrics = app.get("/metrics").await.text().await.unwrap();
    assert_eq!(sample(&metrics, "ctrecon_memory_reserved_bytes"), 0.0);
}
