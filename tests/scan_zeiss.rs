//! Zeiss Xradia `.txrm` scans written here stream by stream with the `cfb` crate, from the layout the
//! established readers (dxchange, xrmreader, txrm2tiff, CIL) document — `ImageInfo/*` scalars and per-view
//! float32 arrays, `ImageData<⌈n/100⌉>/Image<n>` little-endian images, `ReferenceData/Image`,
//! `Alignment/X-Shifts`/`Y-Shifts` — independently of ctrecon's reader, and read back by `ctrecon::scans`:
//! every value exactly, the geometry as CIL's `ZEISSDataReader` models it, the same file read by Python's
//! xrmreader to the same angles, shape and pixels, a simulated ball reconstructed where it was (library,
//! CLI and `POST /v1/scans`), and bad files refused naming the file and the stream.
//!
//! The xrmreader check runs when `.venv-scans/` has it (scripts/install-peers.sh scans); otherwise it prints
//! one skip line, or fails under `CTRECON_REQUIRE_PEERS=1`. Everything else needs no peer.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Once;

use ctrecon::recon::geometry::{Angles, Geometry};
use ctrecon::scans::{self, Format, Intensity, ScanError};
use serde_json::{Value, json};

use crate::common::{assert_problem, spawn_app};
use crate::scan_formats::assert_ball_at;

/// The streams of a compound file: path → bytes.
type Streams = BTreeMap<String, Vec<u8>>;

fn u32s(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}
fn i32s(v: &[i32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}
fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}
fn u16s(v: &[u16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Write `streams` as an OLE compound file of `version` (Xradia writes version 3, 512-byte sectors).
fn write_ole(path: &Path, streams: &Streams, version: cfb::Version) {
    let file = std::fs::File::create(path).expect("create");
    let mut ole = cfb::CompoundFile::create_with_version(version, file).expect("compound file");
    for (name, bytes) in streams {
        if let Some((folder, _)) = name.rsplit_once('/') {
            ole.create_storage_all(format!("/{folder}"))
                .expect("storage");
        }
        let mut s = ole.create_stream(format!("/{name}")).expect("stream");
        s.write_all(bytes).expect("write stream");
    }
    ole.flush().expect("flush");
}

/// View `n` (from 1) of an Xradia file lives in the folder of its hundred.
fn image_name(n: usize) -> String {
    format!("ImageData{}/Image{n}", n.div_ceil(100))
}

/// What the small test scan holds in view `i`, pixel `(r, c)`.
fn pixel(i: usize, r: usize, c: usize) -> u16 {
    ((i * 7919 + r * 131 + c * 17 + 5) % 65536) as u16
}

/// The small test scan: 103 uint16 views of 6 × 5 (two image folders), angles −180° + 3.5°·i, source
/// −20 mm and detector 60 mm from the axis (Zeiss's signs), 5 µm pixels, a reference, alignment shifts, stage
/// positions and magnifications.
fn small_scan() -> Streams {
    let (n, w, h) = (103usize, 6usize, 5usize);
    let mut s = Streams::new();
    let per_view = |f: &dyn Fn(usize) -> f32| f32s(&(0..n).map(f).collect::<Vec<_>>());
    s.insert("ImageInfo/ImageWidth".into(), i32s(&[w as i32]));
    s.insert("ImageInfo/ImageHeight".into(), i32s(&[h as i32]));
    s.insert("ImageInfo/DataType".into(), i32s(&[5]));
    s.insert("ImageInfo/NoOfImages".into(), i32s(&[n as i32]));
    s.insert("ImageInfo/ImagesTaken".into(), u32s(&[n as u32]));
    s.insert("ImageInfo/AcquisitionMode".into(), i32s(&[0]));
    s.insert("ImageInfo/XrayGeometry".into(), i32s(&[1]));
    s.insert(
        "ImageInfo/Angles".into(),
        per_view(&|i| -180.0 + 3.5 * i as f32),
    );
    s.insert("ImageInfo/StoRADistance".into(), per_view(&|_| -20.0));
    s.insert("ImageInfo/DtoRADistance".into(), per_view(&|_| 60.0));
    // dxchange and CIL spell it `pixelsize`: compound file names are compared without regard to case.
    s.insert("ImageInfo/pixelsize".into(), f32s(&[5.0]));
    s.insert("ImageInfo/CamPixelSize".into(), f32s(&[13.5]));
    s.insert("ImageInfo/OpticalMagnification".into(), f32s(&[4.0]));
    s.insert("ImageInfo/XrayMagnification".into(), f32s(&[4.0]));
    s.insert("ImageInfo/XPosition".into(), per_view(&|_| 1250.5));
    s.insert("ImageInfo/YPosition".into(), per_view(&|_| -300.0));
    s.insert("ImageInfo/ZPosition".into(), per_view(&|i| 10.0 + i as f32));
    s.insert(
        "Alignment/X-Shifts".into(),
        per_view(&|i| (i % 3) as f32 - 1.0),
    );
    s.insert(
        "Alignment/Y-Shifts".into(),
        per_view(&|i| 0.5 * (i % 2) as f32),
    );
    s.insert("ReferenceData/DataType".into(), i32s(&[5]));
    let reference: Vec<u16> = (0..h * w).map(|k| 40000 + k as u16 * 100).collect();
    s.insert("ReferenceData/Image".into(), u16s(&reference));
    for i in 0..n {
        let view: Vec<u16> = (0..h * w).map(|k| pixel(i, k / w, k % w)).collect();
        s.insert(image_name(i + 1), u16s(&view));
    }
    s
}

fn message(e: ScanError) -> String {
    e.to_string()
}

#[test]
fn a_txrm_written_stream_by_stream_reads_back_exactly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("scan.txrm");
    write_ole(&file, &small_scan(), cfb::Version::V3);
    for path in [file.clone(), dir.path().to_path_buf()] {
        let mut scan = scans::open(&path).expect("open the .txrm");
        assert_eq!(scan.format, Format::ZeissXradia);
        assert_eq!(scan.format.to_string(), "zeiss_xradia");
        assert_eq!(scan.views.view_count(), 103);
        assert_eq!(scan.views.shape(), (5, 6));
        assert_eq!(
            scan.intensity,
            Intensity::Raw {
                white_level: 65535.0
            }
        );
        assert_eq!(scan.orientation, scans::Orientation::AS_STORED);
        let Geometry::Cone(g) = &scan.geometry else {
            panic!("a cone beam")
        };
        // ctrecon's β = −(Zeiss angle); the magnitudes of the distances; the pixel magnified 4×.
        let want: Vec<f64> = (0..103)
            .map(|i| -f64::from(-180.0 + 3.5 * i as f32))
            .collect();
        assert_eq!(g.angles, Angles::List { degrees: want });
        assert_eq!((g.dso_mm, g.dsd_mm), (20.0, 80.0));
        assert!(
            (g.detector.du_mm - 0.02).abs() < 1e-15,
            "{}",
            g.detector.du_mm
        );
        assert!((g.detector.dv_mm - 0.02).abs() < 1e-15);
        assert_eq!((g.detector.nu, g.detector.nv), (6, 5));
        assert_eq!((g.detector.offset_u_mm, g.detector.offset_v_mm), (0.0, 0.0));
        let flat = scan.flat.as_ref().expect("the reference is the flat");
        assert_eq!(flat.len(), 30);
        for (k, &f) in flat.iter().enumerate() {
            assert_eq!(f, 40000.0 + 100.0 * k as f32);
        }
        let origin = |key: &str| {
            scan.provenance
                .iter()
                .find(|p| p.key == key)
                .map(|p| (p.value.clone(), p.origin.clone()))
        };
        assert_eq!(
            origin("ImageInfo/StoRADistance"),
            Some((
                "103 values, -20 … -20 mm".into(),
                "scan.txrm ImageInfo/StoRADistance".into()
            ))
        );
        assert_eq!(origin("ImageInfo/PixelSize").map(|o| o.0), Some("5".into()));
        assert_eq!(
            origin("ImageInfo/ImagesTaken").map(|o| o.0),
            Some("103".into())
        );
        assert!(origin("ReferenceData/Image").is_some());
        assert!(origin("Alignment/X-Shifts").is_some());
        for key in [
            "CamPixelSize",
            "OpticalMagnification",
            "XrayMagnification",
            "XPosition",
            "YPosition",
            "ZPosition",
        ] {
            assert!(
                scan.notes
                    .iter()
                    .any(|n| n.contains(key) && n.contains("not applied")),
                "{key} in {:?}",
                scan.notes
            );
        }
        for i in [0usize, 1, 2, 99, 100, 102] {
            let want = [0.5 * (i % 2) as f64, (i % 3) as f64 - 1.0];
            assert_eq!(scan.views.shift(i), Some(want), "view {i}");
        }
        let mut buf = vec![0f32; 30];
        for i in 0..103 {
            scan.views.read_view(i, &mut buf).expect("read view");
            for (k, &v) in buf.iter().enumerate() {
                assert_eq!(v, f32::from(pixel(i, k / 6, k % 6)), "view {i} pixel {k}");
            }
        }
        let e = scan.views.read_view(103, &mut buf).unwrap_err();
        assert!(
            matches!(
                e,
                ScanError::NoSuchView {
                    index: 103,
                    count: 103,
                    ..
                }
            ),
            "{e}"
        );
    }
}

#[test]
fn a_float32_txrm_of_version_4_without_images_taken_reads_back_exactly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("f.xrm");
    let mut s = Streams::new();
    s.insert("ImageInfo/ImageWidth".into(), i32s(&[3]));
    s.insert("ImageInfo/ImageHeight".into(), i32s(&[2]));
    s.insert("ImageInfo/DataType".into(), i32s(&[10]));
    s.insert("ImageInfo/NoOfImages".into(), i32s(&[2]));
    s.insert("ImageInfo/Angles".into(), f32s(&[10.0, -5.5]));
    s.insert("ImageInfo/StoRADistance".into(), f32s(&[30.0, 30.0]));
    s.insert("ImageInfo/DtoRADistance".into(), f32s(&[-90.0, -90.0]));
    s.insert("ImageInfo/PixelSize".into(), f32s(&[2.5]));
    s.insert("ReferenceData/Image".into(), f32s(&[0.5; 6]));
    s.insert(
        "ImageData1/Image1".into(),
        f32s(&[0.125, 1e-3, -2.0, 3.5, 0.0, 65535.5]),
    );
    s.insert(
        "ImageData1/Image2".into(),
        f32s(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
    );
    write_ole(&file, &s, cfb::Version::V4);
    let mut scan = scans::open(&file).expect("open the .xrm");
    assert_eq!(scan.intensity, Intensity::Raw { white_level: 1.0 });
    let Geometry::Cone(g) = &scan.geometry else {
        panic!("a cone beam")
    };
    assert_eq!(
        g.angles,
        Angles::List {
            degrees: vec![-10.0, 5.5]
        }
    );
    assert_eq!((g.dso_mm, g.dsd_mm), (30.0, 120.0));
    assert!((g.detector.du_mm - 0.01).abs() < 1e-15);
    assert_eq!(scan.flat.as_deref(), Some(&[0.5f32; 6][..]));
    assert_eq!(scan.views.shift(0), None);
    let mut buf = vec![0f32; 6];
    scan.views.read_view(0, &mut buf).expect("view 1");
    assert_eq!(buf, [0.125, 1e-3, -2.0, 3.5, 0.0, 65535.5]);
    scan.views.read_view(1, &mut buf).expect("view 2");
    assert_eq!(buf, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
}

/// Python with xrmreader (and numpy): `.venv-scans/bin/python`, else `python3`; `None` after one skip line,
/// or a panic under CTRECON_REQUIRE_PEERS=1, when neither has it.
fn xrmreader_python() -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-scans/bin/python");
    let check = format!("{SHIM}\nimport xrmreader, numpy");
    let found = [venv, PathBuf::from("python3")].into_iter().find(|py| {
        Command::new(py)
            .args(["-c", &check])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    if found.is_none() {
        if std::env::var("CTRECON_REQUIRE_PEERS").as_deref() == Ok("1") {
            panic!(
                "xrmreader is required (CTRECON_REQUIRE_PEERS=1): run scripts/install-peers.sh scans"
            );
        }
        static SKIP: Once = Once::new();
        SKIP.call_once(|| {
            eprintln!("SKIPPED: no Python with xrmreader (run scripts/install-peers.sh scans)")
        });
    }
    found
}

/// xrmreader 2.9.1 imports `dxchange.writer` for its file-extension check only, and PyPI's `dxchange` is
/// another project: this stand-in gives it that one helper (xrmreader's reading is its own, on olefile).
const SHIM: &str = r#"
import os, sys, types
_w = types.ModuleType("dxchange.writer")
_w.get_extension = lambda name: os.path.splitext(name)[1]
_d = types.ModuleType("dxchange")
_d.writer = _w
sys.modules["dxchange"] = _d
sys.modules["dxchange.writer"] = _w
"#;

/// Reads `argv[1]` with xrmreader and writes what it found to `argv[2]` as JSON.
const XRM_READ: &str = r#"
import json, warnings
warnings.simplefilter("ignore")
import numpy as np, xrmreader
m = xrmreader.read_metadata(sys.argv[1])
images = np.asarray(xrmreader.read_txrm(sys.argv[1]))
out = {
    "number_of_images": int(m["number_of_images"]),
    "image_width": int(m["image_width"]), "image_height": int(m["image_height"]),
    "pixel_size": float(m["pixel_size"]),
    "thetas": [float(t) for t in m["thetas"]],
    "x_shifts": [float(x) for x in m["x-shifts"]], "y_shifts": [float(y) for y in m["y-shifts"]],
    "source_isocenter_distance": float(m["source_isocenter_distance"]),
    "detector_isocenter_distance": float(m["detector_isocenter_distance"]),
    "reference": [float(v) for v in np.asarray(m["reference"]).ravel()],
    "shape": list(images.shape),
    "images": [float(v) for v in images.ravel()],
}
json.dump(out, open(sys.argv[2], "w"))
"#;

#[test]
fn xrmreader_reads_the_written_txrm_as_ctrecon_does() {
    let Some(py) = xrmreader_python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("scan.txrm");
    write_ole(&file, &small_scan(), cfb::Version::V3);
    let out = dir.path().join("xrm.json");
    let run = Command::new(&py)
        .args(["-c", &format!("{SHIM}\n{XRM_READ}")])
        .arg(&file)
        .arg(&out)
        .output()
        .expect("python");
    assert!(
        run.status.success(),
        "xrmreader failed: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let x: Value = serde_json::from_slice(&std::fs::read(&out).expect("json")).expect("json");
    let mut scan = scans::open(&file).expect("open");
    let (nv, nu) = scan.views.shape();
    let n = scan.views.view_count();
    assert_eq!(x["number_of_images"], json!(n));
    assert_eq!(
        (x["image_height"].clone(), x["image_width"].clone()),
        (json!(nv), json!(nu))
    );
    assert_eq!(x["shape"], json!([n, nv, nu]));
    assert_eq!(x["pixel_size"], json!(5.0));
    // xrmreader's angles are radians of the file's degrees; ctrecon's β is their negative.
    let Geometry::Cone(g) = &scan.geometry else {
        panic!("a cone beam")
    };
    let Angles::List { degrees } = &g.angles else {
        panic!("listed angles")
    };
    let thetas = x["thetas"].as_array().expect("thetas");
    assert_eq!(thetas.len(), n);
    for (t, b) in thetas.iter().zip(degrees) {
        let t = t.as_f64().expect("theta");
        assert!(
            (t + b.to_radians()).abs() < 1e-12,
            "xrmreader θ {t} rad, ctrecon β {b}°"
        );
    }
    assert_eq!(
        x["source_isocenter_distance"].as_f64().map(f64::abs),
        Some(g.dso_mm)
    );
    assert_eq!(
        x["detector_isocenter_distance"].as_f64().map(f64::abs),
        Some(g.dsd_mm - g.dso_mm)
    );
    for i in 0..n {
        let s = scan.views.shift(i).expect("shifts");
        assert_eq!(x["y_shifts"][i].as_f64(), Some(s[0]), "view {i}");
        assert_eq!(x["x_shifts"][i].as_f64(), Some(s[1]), "view {i}");
    }
    let reference: Vec<f32> = x["reference"]
        .as_array()
        .expect("reference")
        .iter()
        .map(|v| v.as_f64().unwrap_or(f64::NAN) as f32)
        .collect();
    assert_eq!(Some(&reference), scan.flat.as_ref());
    let images = x["images"].as_array().expect("images");
    let mut buf = vec![0f32; nv * nu];
    for i in 0..n {
        scan.views.read_view(i, &mut buf).expect("read");
        for (k, v) in buf.iter().enumerate() {
            assert_eq!(
                images[i * nv * nu + k].as_f64(),
                Some(f64::from(*v)),
                "view {i} pixel {k}"
            );
        }
    }
}

/// A tiny scan for the bad-input cases: 4 uint16 views of 3 × 2 at 0°, 90°, 180°, 270°.
fn tiny_scan() -> Streams {
    let mut s = Streams::new();
    s.insert("ImageInfo/ImageWidth".into(), i32s(&[3]));
    s.insert("ImageInfo/ImageHeight".into(), i32s(&[2]));
    s.insert("ImageInfo/DataType".into(), i32s(&[5]));
    s.insert("ImageInfo/NoOfImages".into(), i32s(&[4]));
    s.insert("ImageInfo/ImagesTaken".into(), u32s(&[4]));
    s.insert("ImageInfo/Angles".into(), f32s(&[0.0, 90.0, 180.0, 270.0]));
    s.insert("ImageInfo/StoRADistance".into(), f32s(&[-10.0; 4]));
    s.insert("ImageInfo/DtoRADistance".into(), f32s(&[30.0; 4]));
    s.insert("ImageInfo/PixelSize".into(), f32s(&[10.0]));
    for n in 1..=4 {
        s.insert(image_name(n), u16s(&[n as u16; 6]));
    }
    s
}

/// The error of opening `streams` written as `bad.txrm` (or of reading all its views).
fn open_error(dir: &Path, streams: &Streams) -> String {
    let file = dir.join("bad.txrm");
    write_ole(&file, streams, cfb::Version::V3);
    match scans::open(&file) {
        Err(e) => message(e),
        Ok(mut scan) => {
            let mut buf = vec![0f32; 6];
            (0..scan.views.view_count())
                .find_map(|i| scan.views.read_view(i, &mut buf).err())
                .map(message)
                .unwrap_or_else(|| panic!("{streams:?} was read"))
        }
    }
}

#[test]
fn bad_txrm_files_give_errors_that_name_the_file_and_stream() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let with = |edit: &dyn Fn(&mut Streams)| {
        let mut s = tiny_scan();
        edit(&mut s);
        s
    };
    let named = |msg: &str, words: &[&str]| {
        assert!(msg.contains("bad.txrm"), "{msg}");
        for w in words {
            assert!(msg.contains(w), "{w:?} not in {msg}");
        }
    };
    // The tiny scan itself is fine.
    let ok = d.join("ok.txrm");
    write_ole(&ok, &tiny_scan(), cfb::Version::V3);
    scans::open(&ok).expect("the tiny scan reads");

    // A truncated image stream.
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageData1/Image3".into(), u16s(&[3; 5]));
        }),
    );
    named(&msg, &["ImageData1/Image3", "10 bytes", "12 bytes"]);
    // ImagesTaken contradicting the angles, the images, or NoOfImages.
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/Angles".into(), f32s(&[0.0, 90.0, 180.0]));
        }),
    );
    named(
        &msg,
        &[
            "ImageInfo/ImagesTaken",
            "ImageInfo/Angles",
            "3 32-bit values",
        ],
    );
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/ImagesTaken".into(), u32s(&[3]));
        }),
    );
    named(&msg, &["ImagesTaken", "ImageData1/Image4"]);
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/ImagesTaken".into(), u32s(&[5]));
            s.insert("ImageInfo/NoOfImages".into(), i32s(&[5]));
        }),
    );
    named(&msg, &["ImagesTaken", "no stream ImageData1/Image5"]);
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/NoOfImages".into(), i32s(&[3]));
        }),
    );
    named(&msg, &["ImagesTaken = 4", "NoOfImages = 3"]);
    // Missing required streams.
    for stream in [
        "ImageInfo/PixelSize",
        "ImageInfo/StoRADistance",
        "ImageInfo/Angles",
        "ImageInfo/DataType",
    ] {
        let msg = open_error(
            d,
            &with(&|s| {
                s.remove(stream);
            }),
        );
        named(&msg, &[stream, "missing"]);
    }
    let msg = open_error(
        d,
        &with(&|s| {
            s.remove("ImageInfo/ImagesTaken");
            s.remove("ImageInfo/NoOfImages");
        }),
    );
    named(&msg, &["ImagesTaken", "missing"]);
    // DataType 6 (int32) is not read; angles that turn back are refused.
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/DataType".into(), i32s(&[6]));
        }),
    );
    named(&msg, &["ImageInfo/DataType = 6", "int32", "unsupported"]);
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/Angles".into(), f32s(&[0.0, 90.0, 80.0, 270.0]));
        }),
    );
    named(&msg, &["ImageInfo/Angles", "view 3"]);
    // A zero size, a lying width.
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/ImageWidth".into(), i32s(&[-3]));
        }),
    );
    named(&msg, &["ImageInfo/ImageWidth", "-3"]);
    let msg = open_error(
        d,
        &with(&|s| {
            s.insert("ImageInfo/ImageWidth".into(), i32s(&[1 << 15]));
            s.insert("ImageInfo/ImageHeight".into(), i32s(&[1 << 15]));
        }),
    );
    named(&msg, &["ImageWidth × ImageHeight", "over a limit"]);

    // A file named .txrm that is not an OLE file; an OLE file cut short.
    let fake = d.join("bad.txrm");
    std::fs::write(&fake, b"Xradia? no: plain text\n").expect("write");
    let e = scans::open(&fake).unwrap_err();
    assert!(matches!(e, ScanError::NotAScan { .. }), "{e}");
    named(&message(e), &["not an OLE compound file"]);
    let bytes = std::fs::read(&ok).expect("read");
    std::fs::write(&fake, &bytes[..bytes.len() / 2]).expect("truncate");
    named(&open_error_of(&fake), &[]);
}

fn open_error_of(file: &Path) -> String {
    match scans::open(file) {
        Err(e) => message(e),
        Ok(mut scan) => {
            let mut buf = vec![0f32; 6];
            (0..scan.views.view_count())
                .find_map(|i| scan.views.read_view(i, &mut buf).err())
                .map(message)
                .expect("a truncated file fails")
        }
    }
}

/// The ball scan: 120 uint16 views of 40 × 36 over a full turn, source 60 mm and detector 120 mm from the axis,
/// 100 µm pixels at the object (0.3 mm on the panel).
const BALL: (usize, usize, usize) = (120, 40, 36);
const S_MM: f64 = 60.0;
const D_MM: f64 = 120.0;
const PIXEL_UM: f64 = 100.0;
/// A ball of radius 0.45 mm and μ = 0.5/mm at (0.7, −0.5, 0.4) mm.
const CENTRE: [f64; 3] = [0.7, -0.5, 0.4];
const RADIUS: f64 = 0.45;
const MU: f64 = 0.5;

fn zeiss_angle(i: usize) -> f32 {
    -180.0 + 3.0 * i as f32
}
/// The alignment of view `i`: `(y, x)` whole pixels.
fn ball_shift(i: usize) -> (i32, i32) {
    ((i % 3) as i32 - 1, (i % 5) as i32 - 2)
}
/// The open beam: ±10 % from pixel to pixel.
fn open_beam(r: usize, c: usize) -> f64 {
    50000.0 * (1.0 + 0.1 * (((r + 2 * c) % 3) as f64 - 1.0))
}

/// The transmission CIL's model of the scan gives at (fractional) image pixel `(r, c)` of view `i` (row 0 at
/// the bottom): the mean over 3 × 3 points of the pixel of `exp(−μ · chord)` through the ball.
fn transmission(i: usize, r: f64, c: f64) -> f64 {
    let (_, w, h) = BALL;
    let p = PIXEL_UM / 1000.0 * (S_MM + D_MM) / S_MM;
    let t = -f64::from(zeiss_angle(i)).to_radians();
    let rot = |v: [f64; 3]| {
        let (s, co) = t.sin_cos();
        [co * v[0] - s * v[1], s * v[0] + co * v[1], v[2]]
    };
    let src = rot([0.0, -S_MM, 0.0]);
    let det = rot([0.0, D_MM, 0.0]);
    let u = rot([p, 0.0, 0.0]);
    let mut sum = 0.0;
    for k in 0..9 {
        let (a, b) = (
            (k % 3) as f64 / 3.0 - 1.0 / 3.0,
            (k / 3) as f64 / 3.0 - 1.0 / 3.0,
        );
        let (cu, rv) = (
            c + a - (w as f64 - 1.0) / 2.0,
            r + b - (h as f64 - 1.0) / 2.0,
        );
        let x = [det[0] + cu * u[0], det[1] + cu * u[1], det[2] + rv * p];
        let d: [f64; 3] = std::array::from_fn(|j| x[j] - src[j]);
        let len = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let m: [f64; 3] = std::array::from_fn(|j| CENTRE[j] - src[j]);
        let along = (0..3).map(|j| m[j] * d[j]).sum::<f64>() / len;
        let miss2 = m.iter().map(|v| v * v).sum::<f64>() - along * along;
        let chord = 2.0 * (RADIUS * RADIUS - miss2).max(0.0).sqrt();
        sum += (-MU * chord).exp();
    }
    sum / 9.0
}

/// Write the ball scan to `file`: each view as the scanner stores it, `round(open beam · T)` with T taken
/// where the alignment shift says the object was (`T(r + y, c + x)`), the open beam as `ReferenceData/Image`.
fn write_ball_txrm(file: &Path) {
    let (n, w, h) = BALL;
    let mut s = Streams::new();
    let per_view = |f: &dyn Fn(usize) -> f32| f32s(&(0..n).map(f).collect::<Vec<_>>());
    s.insert("ImageInfo/ImageWidth".into(), i32s(&[w as i32]));
    s.insert("ImageInfo/ImageHeight".into(), i32s(&[h as i32]));
    s.insert("ImageInfo/DataType".into(), i32s(&[5]));
    s.insert("ImageInfo/NoOfImages".into(), i32s(&[n as i32]));
    s.insert("ImageInfo/ImagesTaken".into(), u32s(&[n as u32]));
    s.insert("ImageInfo/Angles".into(), per_view(&zeiss_angle));
    s.insert(
        "ImageInfo/StoRADistance".into(),
        per_view(&|_| -S_MM as f32),
    );
    s.insert("ImageInfo/DtoRADistance".into(), per_view(&|_| D_MM as f32));
    s.insert("ImageInfo/PixelSize".into(), f32s(&[PIXEL_UM as f32]));
    s.insert(
        "Alignment/Y-Shifts".into(),
        per_view(&|i| ball_shift(i).0 as f32),
    );
    s.insert(
        "Alignment/X-Shifts".into(),
        per_view(&|i| ball_shift(i).1 as f32),
    );
    s.insert("ReferenceData/DataType".into(), i32s(&[5]));
    let flat: Vec<u16> = (0..h * w).map(|k| open_beam(k / w, k % w) as u16).collect();
    s.insert("ReferenceData/Image".into(), u16s(&flat));
    for i in 0..n {
        let (y, x) = ball_shift(i);
        let view: Vec<u16> = (0..h * w)
            .map(|k| {
                let (r, c) = (k / w, k % w);
                let t = transmission(i, (r as i32 + y) as f64, (c as i32 + x) as f64);
                (open_beam(r, c) * t).round() as u16
            })
            .collect();
        s.insert(image_name(i + 1), u16s(&view));
    }
    write_ole(file, &s, cfb::Version::V3);
}

/// A ball off the axis, seen by a Zeiss scanner with a patterned open beam and views that moved: the
/// reader's line integrals equal the analytic ones (the reference divided out before the shift, the shift's
/// sign as CIL's and xrmreader's), and FDK of them in the reader's geometry — from the library and from
/// `ctrecon recon --input ball.txrm` — puts the ball where it was.
#[test]
fn fdk_of_a_simulated_zeiss_scan_puts_an_off_centre_ball_where_it_was() {
    use ctrecon::recon::algorithm::FbpParams;
    use ctrecon::recon::analytic::fdk;
    use ctrecon::recon::control::unattended;
    use ctrecon::recon::geometry::Views;
    use ctrecon::recon::grid::VolumeGrid;

    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("ball.txrm");
    write_ball_txrm(&file);
    let mut scan = scans::open(&file).expect("open");
    let li = scans::line_integrals(&mut scan, 1 << 30).expect("line integrals");
    assert_eq!(li.clamped, 0);
    assert_eq!(li.shifted_views, 112);
    let (n, w, h) = BALL;
    let mut worst: f64 = 0.0;
    for i in 0..n {
        for r in 0..h {
            for c in 0..w {
                let want = -transmission(i, r as f64, c as f64).ln();
                worst = worst.max((f64::from(li.projections[[i, r, c]]) - want).abs());
            }
        }
    }
    assert!(
        worst < 1e-4,
        "line integrals differ from the analytic ones by up to {worst}"
    );

    let Ok(Views::D3(views)) = scan.geometry.to_views() else {
        panic!("cone views")
    };
    let grid = VolumeGrid::cube(40, 0.1);
    let vol = fdk(
        &views,
        li.projections.view(),
        &grid,
        &FbpParams::default(),
        unattended(),
    )
    .expect("fdk");
    assert_ball_at(&vol, &grid, CENTRE);

    // `ctrecon recon --input ball.txrm --algorithm fdk --size 40 --pixel-mm 0.1` (centre found from the views).
    let out = dir.path().join("v.npy");
    let cli = crate::scan_formats::recon_40(&file, "fdk", "auto", &out);
    assert_ball_at(&cli, &grid, CENTRE);
}

async fn post_octets(app: &crate::common::TestApp, name: &str, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url(&format!("/v1/scans?filename={name}")))
        .header("content-type", "application/octet-stream")
        .body(body)
        .send()
        .await
        .expect("request")
}

/// `POST /v1/scans` takes a `.txrm` as one file and in a ZIP, records the alignment step and the centre
/// found, and an FDK job of the dataset puts the ball where it was; bad `.txrm` files are 422 problems.
#[tokio::test]
async fn a_txrm_imports_as_one_file_or_zip_and_bad_ones_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("ball.txrm");
    write_ball_txrm(&file);
    let bytes = std::fs::read(&file).expect("read");
    let app = spawn_app().await;

    let r = post_octets(&app, "ball.txrm", bytes.clone()).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let d: Value = r.json().await.expect("json");
    assert_eq!(d["format"], "zeiss_xradia");
    assert_eq!(d["scan"]["format"], "zeiss_xradia");
    assert_eq!(d["shape"], json!([120, 36, 40]));
    assert_eq!(d["geometry"]["dso_mm"], json!(60.0), "{d}");
    assert_eq!(d["geometry"]["dsd_mm"], json!(180.0), "{d}");
    let steps = &d["scan"]["preprocessing"];
    assert_eq!(
        steps[0],
        json!({"step": "normalise", "dark": false, "flat": true})
    );
    assert_eq!(steps[1], json!({"step": "align", "shifted_views": 112}));
    assert_eq!(steps[2]["step"], "minus_log");
    assert_eq!(steps[2]["clamped_pixels"], 0);
    assert_eq!(
        steps[3],
        json!({"step": "orient", "flip_rows": false, "flip_cols": false})
    );
    let provenance = d["scan"]["provenance"].as_array().expect("provenance");
    assert!(
        provenance
            .iter()
            .any(|p| p["origin"] == "ball.txrm ImageInfo/Angles"
                && p["value"] == "120 values, -180 … 177°"),
        "{d}"
    );
    let cal = &d["scan"]["calibration"];
    assert_eq!(cal["centre"], "found", "{cal}");
    let found = cal["offset_u_mm"].as_f64().expect("offset");
    assert!(
        found.abs() < 0.03,
        "the axis projects on the panel's centre: found {found} mm"
    );

    // The same file in a ZIP's folder: the same dataset.
    let zip =
        ctrecon::dicom::write_zip(&[("zeiss/ball.txrm".to_string(), bytes.clone())]).expect("zip");
    let r = app
        .client
        .post(app.url("/v1/scans"))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let z: Value = r.json().await.expect("json");
    assert_eq!((&z["sha256"], &z["scan"]), (&d["sha256"], &d["scan"]));

    // FDK of the dataset.
    let id = d["id"].as_str().expect("id");
    let job = app
        .submit(&json!({"input": id, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 40, "ny": 40, "nz": 40, "spacing_mm": [0.1, 0.1, 0.1]}}))
        .await;
    let job_id = job["id"].as_str().expect("job id").to_string();
    let done = app.finish(&job_id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let r = app
        .get(&format!("/v1/jobs/{job_id}/result/volume.npy"))
        .await;
    let (shape, data) = crate::common::read_npy_f32(&r.bytes().await.expect("volume"));
    let vol = ndarray::Array3::from_shape_vec((shape[0], shape[1], shape[2]), data).expect("3-D");
    assert_ball_at(
        &vol,
        &ctrecon::recon::grid::VolumeGrid::cube(40, 0.1),
        CENTRE,
    );

    // ImagesTaken contradicting the angles: scan_invalid naming the file and the streams.
    let mut s = tiny_scan();
    s.insert("ImageInfo/Angles".into(), f32s(&[0.0, 90.0, 180.0]));
    let bad = dir.path().join("bad.txrm");
    write_ole(&bad, &s, cfb::Version::V3);
    let r = post_octets(&app, "scan.txrm", std::fs::read(&bad).expect("read")).await;
    let p = assert_problem(r, 422, "scan_invalid").await;
    let detail = p["detail"].as_str().expect("detail");
    assert!(
        detail.contains("scan.txrm") && detail.contains("ImagesTaken") && detail.contains("Angles"),
        "{detail}"
    );
    assert!(!detail.contains("/tmp/"), "no server path in {detail}");
    // Not an OLE file: not recognised as a scan.
    let r = post_octets(&app, "scan.txrm", b"not a compound file".to_vec()).await;
    assert_problem(r, 422, "scan_not_recognised").await;
}
