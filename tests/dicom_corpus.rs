//! pydicom 3.0.2's test files as a corpus of odd inputs. Every file goes through the reader on its own thread
//! with a time limit: it must either decode to the pixel values pydicom gives (statistics in
//! `.testdata/reference.json`, computed by `scripts/fetch-test-data.sh`) or be refused with a typed error. Nothing
//! may panic or hang. Without the data the test prints a skip notice, unless `CTRECON_REQUIRE_TEST_DATA=1`.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use ctrecon::dicom::{DicomError, Instance, ReadLimits, read_bytes};
use serde_json::Value;

fn data_dir(sub: &str) -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(".testdata")
        .join(sub);
    if d.exists() {
        return Some(d);
    }
    if std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() == Ok("1") {
        panic!(
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1: run scripts/fetch-test-data.sh",
            d.display()
        );
    }
    eprintln!(
        "SKIPPED: {} is missing (run scripts/fetch-test-data.sh)",
        d.display()
    );
    None
}

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            files(&p, out);
        } else {
            out.push(p);
        }
    }
}

/// Lossy transfer syntaxes: decoders may differ by rounding (JPEG baseline/extended, JPEG-LS near-lossless,
/// JPEG 2000 lossy).
const LOSSY: &[&str] = &[
    "1.2.840.10008.1.2.4.50",
    "1.2.840.10008.1.2.4.51",
    "1.2.840.10008.1.2.4.81",
    "1.2.840.10008.1.2.4.91",
];

/// Statistics of our decoded values in pydicom's layout (frames × rows × columns × samples).
fn stats(inst: &Instance) -> (usize, usize, usize, usize, f64, f64, f64, f64) {
    let s0 = &inst.slices[0];
    let (mut lo, mut hi, mut sum, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0usize);
    for s in &inst.slices {
        for &v in &s.stored {
            let v = v as f64;
            lo = lo.min(v);
            hi = hi.max(v);
            sum += v;
            n += 1;
        }
    }
    let first: f64 = s0.stored.iter().map(|&v| v as f64).sum::<f64>() / s0.stored.len() as f64;
    (
        inst.slices.len(),
        s0.rows,
        s0.columns,
        inst.samples_per_pixel as usize,
        lo,
        hi,
        sum / n as f64,
        first,
    )
}

#[test]
fn pydicom_corpus_decodes_like_pydicom_or_is_refused() {
    let Some(dir) = data_dir("pydicom") else {
        return;
    };
    let reference: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.parent().unwrap().join("reference.json")).unwrap(),
    )
    .unwrap();
    let mut all = Vec::new();
    files(&dir, &mut all);
    all.sort();
    assert!(all.len() > 100, "{} files", all.len());
    let (mut equal, mut close, mut refused, mut unverified) = (vec![], vec![], vec![], vec![]);
    let mut mismatched = vec![];
    let mut codes: Vec<(String, &'static str)> = vec![];
    for path in &all {
        let rel = path
            .strip_prefix(&dir)
            .unwrap()
            .to_string_lossy()
            .replace('\\', "/");
        let bytes = std::fs::read(path).unwrap();
        let (tx, rx) = mpsc::channel();
        let label = rel.clone();
        std::thread::spawn(move || {
            let r = std::panic::catch_unwind(|| read_bytes(&label, &bytes, &ReadLimits::default()));
            let _ = tx.send(r);
        });
        let result: Result<Instance, DicomError> = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(Ok(r)) => r,
            Ok(Err(_)) => panic!("{rel}: the reader panicked"),
            Err(_) => panic!("{rel}: the reader hung (over 60 s)"),
        };
        let want = &reference["files"][&rel];
        match (result, want["status"].as_str()) {
            (Err(e), _) => {
                // Typed and clear: a stable code and a message naming the file.
                assert!(e.code().starts_with("dicom_") || e.code().starts_with("zip_"));
                assert!(e.to_string().contains(&rel), "{e}");
                codes.push((rel.clone(), e.code()));
                refused.push(format!("{rel} [{}]: {e}", e.code()));
            }
            (Ok(inst), Some("ok")) => {
                let (f, r, c, s, lo, hi, mean, first) = stats(&inst);
                let num = |k: &str| want[k].as_f64().unwrap();
                let shape_ok = (f, r, c, s)
                    == (
                        num("frames") as usize,
                        num("rows") as usize,
                        num("columns") as usize,
                        num("samples") as usize,
                    );
                let range = (num("max") - num("min")).max(1.0);
                let exact = shape_ok
                    && lo == num("min")
                    && hi == num("max")
                    && (mean - num("mean")).abs() <= 1e-6 * range
                    && (first - num("first_frame_mean")).abs() <= 1e-6 * range;
                // Lossy codecs: means within 1 % of the range, extremes within 5 %.
                let lossy = LOSSY.contains(&inst.transfer_syntax.as_str())
                    && shape_ok
                    && (lo - num("min")).abs() <= 0.05 * range
                    && (hi - num("max")).abs() <= 0.05 * range
                    && (mean - num("mean")).abs() <= 0.01 * range;
                let line = format!(
                    "{rel} ({}, {f}×{r}×{c}×{s}): ours [{lo}, {hi}] mean {mean:.4}, pydicom [{}, {}] mean {:.4} shape {}×{}×{}×{}",
                    inst.transfer_syntax,
                    num("min"),
                    num("max"),
                    num("mean"),
                    num("frames"),
                    num("rows"),
                    num("columns"),
                    num("samples")
                );
                if exact {
                    equal.push(rel);
                } else if lossy {
                    close.push(line);
                } else {
                    mismatched.push(line);
                }
            }
            (Ok(inst), status) => unverified.push(format!(
                "{rel} ({}; pydicom: {})",
                inst.transfer_syntax,
                status.unwrap_or("not in reference")
            )),
        }
    }
    println!(
        "corpus: {} files: {} decoded equal, {} lossy within tolerance, {} refused, {} decoded without a pydicom reference, {} mismatched",
        all.len(),
        equal.len(),
        close.len(),
        refused.len(),
        unverified.len(),
        mismatched.len()
    );
    println!("equal: {equal:?}");
    for l in &close {
        println!("lossy: {l}");
    }
    for l in &refused {
        println!("refused: {l}");
    }
    for l in &unverified {
        println!("unverified: {l}");
    }
    for l in &mismatched {
        println!("MISMATCH: {l}");
    }
    assert!(mismatched.is_empty(), "{} mismatched", mismatched.len());
    // The CT, MR, RT dose and native/RLE/deflate/JPEG 2000 files at least decode exactly.
    for must in [
        "CT_small.dcm",
        "MR_small.dcm",
        "MR_small_RLE.dcm",
        "MR_small_implicit.dcm",
        "MR_small_bigendian.dcm",
        "MR_small_jp2klossless.dcm",
        "image_dfl.dcm",
        "rtdose.dcm",
    ] {
        assert!(equal.iter().any(|e| e == must), "{must} not decoded equal");
    }
    let code_of = |rel: &str| codes.iter().find(|(r, _)| r == rel).map(|(_, c)| *c);
    // Grey JPEG-LS, lossless and near-lossless, decodes exactly as pydicom decodes it; colour JPEG-LS is
    // refused by name.
    for jls in [
        "MR_small_jpeg_ls_lossless.dcm",
        "JPEGLSNearLossless_08.dcm",
        "JPEGLSNearLossless_16.dcm",
    ] {
        assert!(equal.iter().any(|e| e == jls), "{jls} not decoded equal");
    }
    for jls in ["SC_rgb_jls_lossy_line.dcm", "SC_rgb_jls_lossy_sample.dcm"] {
        assert_eq!(code_of(jls), Some("dicom_unsupported"), "{jls}");
    }
    // Raw data sets (no preamble, DICM or meta group), explicit VR in either byte order, are parsed as
    // pydicom's `force=True` reads them: these two hold no image, which is now what refuses them.
    for raw in ["ExplVR_LitEndNoMeta.dcm", "ExplVR_BigEndNoMeta.dcm"] {
        assert_eq!(code_of(raw), Some("dicom_no_pixel_data"), "{raw}");
    }
    // A meta group without its group length is read.
    assert_eq!(
        code_of("no_meta_group_length.dcm"),
        Some("dicom_no_pixel_data")
    );
}
