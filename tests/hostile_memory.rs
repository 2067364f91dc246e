//! Compressed DICOM input against the memory budget, through every door. Files of a few hundred kilobytes
//! whose headers declare gigabytes of pixels — a deflated data set, RLE and JPEG-LS of 8192² zeros — are sent
//! to a real `ctrecon serve` process (memory budget 1 GiB, DICOM node on) as a ZIP upload, a multipart
//! upload, by STOW-RS and by C-STORE (DCMTK's `storescu`). The measure is the server's peak resident memory
//! (VmHWM in `/proc/<pid>/status`), not only its answers: a series is refused from what its headers declare,
//! before anything is decoded, and series that do fit are decoded only within the budget however many
//! arrive at once.
//!
//! C-STORE needs DCMTK (Debian's `dcmtk`); without it that door prints one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1` (as in CI), when it fails.

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use dicom_core::value::{PixelFragmentSequence, Value as DicomValue};
use dicom_core::{DataElement, PrimitiveValue, VR, dicom_value};
use dicom_dictionary_std::tags;
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use serde_json::Value;

include!("common/ports.rs");

const BUDGET: u64 = 1 << 30;
/// What the server may hold beyond the budget: its own code, runtime, database and buffers.
const SLACK: u64 = 256 << 20;
const MIB: u64 = 1 << 20;
const CT: &str = "1.2.840.10008.5.1.4.1.1.2";
const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const RLE: &str = "1.2.840.10008.1.2.5";
const JPEG_LS: &str = "1.2.840.10008.1.2.4.80";

/// A `ctrecon serve` child process; killed when dropped.
struct Server {
    child: Child,
    base: String,
    dicom_port: u16,
    _dir: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    fn start() -> Server {
        let dir = tempfile::tempdir().expect("temp dir");
        let dicom_port = free_port();
        let mut child = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
            .args(["serve", "--bind", "127.0.0.1:0"])
            .env("CTRECON_DATA_DIR", dir.path())
            .env("CTRECON_MEMORY_BUDGET_BYTES", BUDGET.to_string())
            .env("CTRECON_DICOM_PORT", dicom_port.to_string())
            .env("CTRECON_DICOM_STABLE_AGE_SECS", "1")
            .env_remove("CTRECON_DATABASE_URL")
            .env_remove("CTRECON_STORAGE_URL")
            .env_remove("CTRECON_TEST_LOGS")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(
                if std::env::var("CTRECON_TEST_LOGS").as_deref() == Ok("1") {
                    Stdio::inherit()
                } else {
                    Stdio::null()
                },
            )
            .spawn()
            .expect("ctrecon starts");
        let mut line = String::new();
        let mut stdout = BufReader::new(child.stdout.take().expect("stdout"));
        stdout.read_line(&mut line).expect("the first line");
        // The server goes on writing to its standard output: keep reading it.
        std::thread::spawn(move || std::io::copy(&mut stdout, &mut std::io::sink()));
        let base = line
            .trim()
            .strip_prefix("ctrecon listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
            .to_string();
        Server {
            child,
            base,
            dicom_port,
            _dir: dir,
        }
    }

    /// A line of `/proc/<pid>/status` in bytes (`VmHWM`, `VmRSS`).
    fn status_bytes(&self, key: &str) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .expect("the server's /proc status");
        let kib: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix(&format!("{key}:")))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap_or_else(|| panic!("no {key} in /proc status"));
        kib * 1024
    }

    fn peak(&self) -> u64 {
        self.status_bytes("VmHWM")
    }

    async fn metric(&self, name: &str, labels: &str) -> f64 {
        let text = reqwest::get(format!("{}/metrics", self.base))
            .await
            .expect("metrics")
            .text()
            .await
            .expect("metrics text");
        text.lines()
            .filter(|l| !l.starts_with('#'))
            .filter_map(|l| {
                let (key, value) = l.rsplit_once(' ')?;
                (key.starts_with(&format!("{name}{{")) && key.contains(labels))
                    .then(|| value.parse::<f64>().ok())
                    .flatten()
            })
            .sum()
    }

    /// Wait (up to 60 s) until `count` more series were refused from their headers than `before`.
    async fn refused_unread(&self, before: f64, count: f64) {
        let until = Instant::now() + Duration::from_secs(60);
        loop {
            let now = self
                .metric(
                    "ctrecon_series_ingested_total",
                    "outcome=\"refused_unread\"",
                )
                .await;
            if now >= before + count {
                return;
            }
            assert!(
                Instant::now() < until,
                "the series were not refused within 60 s ({now} refused unread)"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

fn el(tag: dicom_core::Tag, vr: VR, v: PrimitiveValue) -> DataElement<InMemDicomObject> {
    DataElement::new(tag, vr, v)
}

/// The attributes of slice `index` of a CT series of `side`² pixels, 16-bit signed, 0.1 mm pixels, slices
/// 1 mm apart (no pixel data).
fn ct_header(series: &str, index: usize, side: u16) -> InMemDicomObject {
    let sop = format!("{series}.{}", index + 1);
    InMemDicomObject::from_element_iter([
        el(tags::SOP_CLASS_UID, VR::UI, dicom_value!(Str, CT)),
        el(tags::SOP_INSTANCE_UID, VR::UI, dicom_value!(Str, sop)),
        el(tags::MODALITY, VR::CS, dicom_value!(Str, "CT")),
        el(tags::PATIENT_ID, VR::LO, dicom_value!(Str, "BOMB")),
        el(
            tags::STUDY_INSTANCE_UID,
            VR::UI,
            dicom_value!(Str, format!("{series}.0")),
        ),
        el(tags::SERIES_INSTANCE_UID, VR::UI, dicom_value!(Str, series)),
        el(
            tags::INSTANCE_NUMBER,
            VR::IS,
            dicom_value!(Str, (index + 1).to_string()),
        ),
        el(
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            dicom_value!(Strs, ["0".to_string(), "0".to_string(), index.to_string()]),
        ),
        el(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            PrimitiveValue::Strs(
                ["1", "0", "0", "0", "1", "0"]
                    .map(String::from)
                    .into_iter()
                    .collect(),
            ),
        ),
        el(
            tags::PIXEL_SPACING,
            VR::DS,
            dicom_value!(Strs, ["0.1".to_string(), "0.1".to_string()]),
        ),
        el(tags::SLICE_THICKNESS, VR::DS, dicom_value!(Str, "1")),
        el(tags::SAMPLES_PER_PIXEL, VR::US, dicom_value!(U16, [1])),
        el(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            dicom_value!(Str, "MONOCHROME2"),
        ),
        el(tags::ROWS, VR::US, dicom_value!(U16, [side])),
        el(tags::COLUMNS, VR::US, dicom_value!(U16, [side])),
        el(tags::BITS_ALLOCATED, VR::US, dicom_value!(U16, [16])),
        el(tags::BITS_STORED, VR::US, dicom_value!(U16, [16])),
        el(tags::HIGH_BIT, VR::US, dicom_value!(U16, [15])),
        el(tags::PIXEL_REPRESENTATION, VR::US, dicom_value!(U16, [1])),
        el(tags::RESCALE_INTERCEPT, VR::DS, dicom_value!(Str, "-1024")),
        el(tags::RESCALE_SLOPE, VR::DS, dicom_value!(Str, "1")),
    ])
}

fn part10(obj: InMemDicomObject, ts: &str) -> Vec<u8> {
    let file = obj
        .with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
        .expect("meta");
    let mut out = Vec::new();
    file.write_all(&mut out).expect("write");
    out
}

/// Slice `index` with `side`² zero pixels in a deflated data set (the zeros streamed into the deflater,
/// never held whole).
fn deflated_slice(series: &str, index: usize, side: u16) -> Vec<u8> {
    let file = part10(ct_header(series, index, side), EXPLICIT_LE);
    let meta_len = u32::from_le_bytes(file[140..144].try_into().expect("4 bytes")) as usize;
    let (meta, data) = (&file[144..144 + meta_len], &file[144 + meta_len..]);
    // The meta group again, its transfer syntax replaced by deflated explicit VR little endian.
    let mut kept = Vec::new();
    let mut at = 0;
    while at < meta.len() {
        let tag = [meta[at], meta[at + 1], meta[at + 2], meta[at + 3]];
        let long = matches!(&meta[at + 4..at + 6], b"OB" | b"OW" | b"UN" | b"SQ" | b"UT");
        let (head, len) = if long {
            (
                12,
                u32::from_le_bytes(meta[at + 8..at + 12].try_into().expect("4")) as usize,
            )
        } else {
            (8, u16::from_le_bytes([meta[at + 6], meta[at + 7]]) as usize)
        };
        if tag != [0x02, 0x00, 0x10, 0x00] {
            kept.extend_from_slice(&meta[at..at + head + len]);
        }
        at += head + len;
    }
    let ts = b"1.2.840.10008.1.2.1.99\0\0";
    kept.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I', ts.len() as u8, 0]);
    kept.extend_from_slice(ts);
    let mut out = vec![0u8; 128];
    out.extend_from_slice(b"DICM");
    out.extend_from_slice(&[0x02, 0x00, 0x00, 0x00, b'U', b'L', 4, 0]);
    out.extend_from_slice(&(kept.len() as u32).to_le_bytes());
    out.extend_from_slice(&kept);
    let mut z = flate2::write::DeflateEncoder::new(out, flate2::Compression::fast());
    z.write_all(data).expect("deflate");
    let bytes = u32::from(side) * u32::from(side) * 2;
    z.write_all(&[0xE0, 0x7F, 0x10, 0x00, b'O', b'W', 0, 0])
        .expect("deflate");
    z.write_all(&bytes.to_le_bytes()).expect("deflate");
    let zeros = vec![0u8; 1 << 20];
    let mut left = bytes as usize;
    while left > 0 {
        let n = left.min(zeros.len());
        z.write_all(&zeros[..n]).expect("deflate");
        left -= n;
    }
    z.finish().expect("deflate")
}

/// One RLE frame (PS3.5 Annex G) of `side`² 16-bit zeros: two segments (high and low bytes), each row a
/// run of replicated zero bytes, 128 at a time.
fn rle_zeros(side: u16) -> Vec<u8> {
    let row: Vec<u8> = (0..usize::from(side).div_ceil(128))
        .flat_map(|k| {
            let n = (usize::from(side) - k * 128).min(128);
            [(1i16 - n as i16) as i8 as u8, 0u8]
        })
        .collect();
    let segment: Vec<u8> = row.repeat(usize::from(side));
    let mut header = vec![0u8; 64];
    header[..4].copy_from_slice(&2u32.to_le_bytes());
    header[4..8].copy_from_slice(&64u32.to_le_bytes());
    header[8..12].copy_from_slice(&(64 + segment.len() as u32).to_le_bytes());
    let mut frame = header;
    frame.extend_from_slice(&segment);
    frame.extend_from_slice(&segment);
    if frame.len() % 2 == 1 {
        frame.push(0);
    }
    frame
}

/// One JPEG-LS (lossless) frame of `side`² 16-bit zeros.
fn jpeg_ls_zeros(side: u16) -> Vec<u8> {
    let words = vec![0u16; usize::from(side) * usize::from(side)];
    let mut o = jpegls::EncodeOptions::default();
    o.precision = Some(16);
    let mut out = Vec::new();
    jpegls::encode_with_options(&words, u32::from(side), u32::from(side), &o, &mut out)
        .expect("JPEG-LS encodes");
    if out.len() % 2 == 1 {
        out.push(0);
    }
    out
}

/// Slice `index` whose pixel data is the encapsulated `frame`, in transfer syntax `ts`.
fn encapsulated_slice(series: &str, index: usize, side: u16, frame: &[u8], ts: &str) -> Vec<u8> {
    let mut obj = ct_header(series, index, side);
    obj.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        DicomValue::PixelSequence(PixelFragmentSequence::new(vec![], vec![frame.to_vec()])),
    ));
    part10(obj, ts)
}

/// A series of `n` slices of `side`² zeros coded as `kind` says (`deflated`, `rle`, `jpeg-ls`).
fn series(uid: &str, n: usize, side: u16, kind: &str) -> Vec<Vec<u8>> {
    let frame = match kind {
        "rle" => Some((rle_zeros(side), RLE)),
        "jpeg-ls" => Some((jpeg_ls_zeros(side), JPEG_LS)),
        _ => None,
    };
    (0..n)
        .map(|i| match &frame {
            Some((f, ts)) => encapsulated_slice(uid, i, side, f, ts),
            None => deflated_slice(uid, i, side),
        })
        .collect()
}

fn zip_of(files: &[Vec<u8>]) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (i, f) in files.iter().enumerate() {
        w.start_file(format!("slice{i}.dcm"), opts)
            .expect("zip entry");
        w.write_all(f).expect("zip write");
    }
    w.finish().expect("zip").into_inner()
}

fn multipart(boundary: &str, content_type: &str, files: &[Vec<u8>], form: bool) -> Vec<u8> {
    let mut body = Vec::new();
    for (i, f) in files.iter().enumerate() {
        body.extend_from_slice(format!("--{boundary}\r\n").as_bytes());
        if form {
            body.extend_from_slice(
                format!("Content-Disposition: form-data; name=\"file\"; filename=\"s{i}.dcm\"\r\n")
                    .as_bytes(),
            );
        }
        body.extend_from_slice(format!("Content-Type: {content_type}\r\n\r\n").as_bytes());
        body.extend_from_slice(f);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    body
}

async fn post(url: String, content_type: &str, body: Vec<u8>) -> (u16, Value) {
    let r = reqwest::Client::new()
        .post(url)
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .expect("the request is answered");
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

fn uid(n: u32) -> String {
    format!("1.2.826.0.1.3680043.10.1045.{}.{n}", std::process::id())
}

fn dcmtk_present() -> bool {
    let ok = Command::new("storescu").arg("--version").output().is_ok();
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "DCMTK's storescu is missing and CTRECON_REQUIRE_PEERS=1"
        );
        eprintln!("skipped: C-STORE door (DCMTK is not installed: apt-get install dcmtk)");
    }
    ok
}

fn write_dir(dir: &Path, files: &[Vec<u8>]) {
    for (i, f) in files.iter().enumerate() {
        std::fs::write(dir.join(format!("s{i}.dcm")), f).expect("write a slice");
    }
}

fn report(what: &str, server: &Server, baseline: u64) {
    eprintln!(
        "{what}: peak RSS {} MiB (baseline {} MiB, budget {} MiB)",
        server.peak() / MIB,
        baseline / MIB,
        BUDGET / MIB
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn series_whose_headers_declare_gigabytes_are_refused_unread_at_every_door() {
    // Seven 8192² slices: 896 MiB of 16-bit pixels, 3.5 GiB once assembled; a few hundred kB on the wire.
    let deflated = series(&uid(1), 7, 8192, "deflated");
    let rle = series(&uid(2), 7, 8192, "rle");
    let jls = series(&uid(3), 7, 8192, "jpeg-ls");
    let sizes: Vec<usize> = [&deflated, &rle, &jls]
        .iter()
        .map(|s| s.iter().map(Vec::len).sum())
        .collect();
    eprintln!(
        "bombs on the wire (bytes): deflated {}, RLE {}, JPEG-LS {}",
        sizes[0], sizes[1], sizes[2]
    );
    assert!(
        sizes.iter().all(|&n| n < 16 << 20),
        "each bomb is small: {sizes:?}"
    );

    let server = Server::start();
    let baseline = server.peak();

    // A ZIP of deflated slices, three at once (the attack that took 11 GB).
    let zips: Vec<_> = (0..3)
        .map(|_| {
            post(
                format!("{}/v1/series", server.base),
                "application/zip",
                zip_of(&deflated),
            )
        })
        .collect();
    for (status, body) in futures_util::future::join_all(zips).await {
        assert_eq!(status, 413, "{body}");
        assert_eq!(body["code"], "series_too_large", "{body}");
    }
    report("ZIP of deflated slices ×3", &server, baseline);

    // A multipart form of RLE slices.
    let b = "ctrecon-bomb-boundary";
    let (status, body) = post(
        format!("{}/v1/series", server.base),
        &format!("multipart/form-data; boundary={b}"),
        multipart(b, "application/dicom", &rle, true),
    )
    .await;
    assert_eq!(
        (status, body["code"].as_str()),
        (413, Some("series_too_large")),
        "{body}"
    );
    report("multipart of RLE slices", &server, baseline);

    // STOW-RS of JPEG-LS slices: stored (they are valid instances), then refused once stable.
    let before = server
        .metric(
            "ctrecon_series_ingested_total",
            "outcome=\"refused_unread\"",
        )
        .await;
    let (status, body) = post(
        format!("{}/dicom-web/studies", server.base),
        &format!("multipart/related; type=\"application/dicom\"; boundary={b}"),
        multipart(b, "application/dicom", &jls, false),
    )
    .await;
    assert!(
        status == 200 || status == 202,
        "STOW-RS answered {status}: {body}"
    );
    server.refused_unread(before, 1.0).await;
    report("STOW-RS of JPEG-LS slices", &server, baseline);

    // C-STORE of RLE and JPEG-LS slices.
    if dcmtk_present() {
        let before = server
            .metric(
                "ctrecon_series_ingested_total",
                "outcome=\"refused_unread\"",
            )
            .await;
        // Each proposed in its own transfer syntax first (`-xr` RLE, `-xt` JPEG-LS lossless).
        for (n, files, propose) in [(4, &rle, "-xr"), (5, &jls, "-xt")] {
            let dir = tempfile::tempdir().expect("temp dir");
            // Other series UIDs than the uploads', so that the node's series are new ones.
            let renamed: Vec<Vec<u8>> = files
                .iter()
                .map(|f| replace_all(f, uid(n - 2).as_bytes(), uid(n).as_bytes()))
                .collect();
            write_dir(dir.path(), &renamed);
            let out = Command::new("storescu")
                .env("TCP_NODELAY", "1")
                .args([
                    "-aet",
                    "BOMBER",
                    "-aec",
                    "CTRECON",
                    propose,
                    "+sd",
                    "127.0.0.1",
                ])
                .arg(server.dicom_port.to_string())
                .arg(dir.path())
                .output()
                .expect("storescu runs");
            assert!(
                out.status.success(),
                "storescu: {}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        server.refused_unread(before, 2.0).await;
        report("C-STORE of RLE and JPEG-LS slices", &server, baseline);
    }

    let peak = server.peak();
    assert!(
        peak <= baseline + SLACK,
        "the server peaked at {} MiB (baseline {} MiB): something decoded what its headers declared",
        peak / MIB,
        baseline / MIB
    );
    assert!(server.status_bytes("VmRSS") <= baseline + SLACK);
}

/// `haystack` with every `from` replaced by `to` (same length).
fn replace_all(haystack: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    assert_eq!(from.len(), to.len());
    let mut out = haystack.to_vec();
    let mut i = 0;
    while i + from.len() <= out.len() {
        if &out[i..i + from.len()] == from {
            out[i..i + from.len()].copy_from_slice(to);
            i += from.len();
        } else {
            i += 1;
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn series_that_fit_are_decoded_within_the_budget_however_many_arrive_at_once() {
    // Three 4096² deflated slices: 96 MiB of pixels, about 400 MiB to decode and assemble; four uploads of
    // them at once need 1.6 GiB together, over the 1 GiB budget.
    let server = Server::start();
    let baseline = server.peak();
    let uploads: Vec<_> = (0..4)
        .map(|k| {
            let files = series(&uid(10 + k), 3, 4096, "deflated");
            post(
                format!("{}/v1/series", server.base),
                "application/zip",
                zip_of(&files),
            )
        })
        .collect();
    for (status, body) in futures_util::future::join_all(uploads).await {
        assert_eq!(status, 201, "{body}");
        assert_eq!(body["series"][0]["status"], "ready", "{body}");
        assert_eq!(
            body["series"][0]["series"]["shape"],
            serde_json::json!([3, 4096, 4096]),
            "{body}"
        );
    }
    report(
        "four uploads of 3 × 4096² deflated slices at once",
        &server,
        baseline,
    );
    let peak = server.peak();
    assert!(
        peak <= BUDGET + SLACK,
        "the server peaked at {} MiB, over the budget of {} MiB + {} MiB",
        peak / MIB,
        BUDGET / MIB,
        SLACK / MIB
    );
}
