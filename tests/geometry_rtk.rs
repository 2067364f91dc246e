//! RTK geometry XML against RTK itself (itk-rtk 2.7, `.venv-rtk/`, scripts/install-peers.sh rtk): files
//! `ctrecon geometry` writes are read by RTK's reader (which checks each projection matrix against its
//! parameters) and put sources and detectors where ctrecon's vectors say; files RTK writes, with every one
//! of its nine parameters in use, are read by `ctrecon geometry` into the vectors RTK's own geometry gives.
//! Without itk-rtk: one skip line, or a failure under `CTRECON_REQUIRE_PEERS=1`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Once;

use serde_json::{Value, json};

fn python() -> Option<PathBuf> {
    let py = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-rtk/bin/python");
    let ok = Command::new(&py)
        .args(["-c", "from itk import RTK"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return Some(py);
    }
    if std::env::var("CTRECON_REQUIRE_PEERS").as_deref() == Ok("1") {
        panic!("itk-rtk is required (CTRECON_REQUIRE_PEERS=1): run scripts/install-peers.sh rtk");
    }
    static SKIP: Once = Once::new();
    SKIP.call_once(|| eprintln!("SKIPPED: no itk-rtk (run scripts/install-peers.sh rtk)"));
    None
}

fn ctrecon(dir: &Path, args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_ctrecon"))
        .current_dir(dir)
        .args(args)
        .output()
        .expect("run ctrecon");
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "ctrecon {args:?}: {err}");
    err
}

/// Reads an RTK XML with RTK's reader, or writes one with RTK's writer from the projections given, and
/// prints per projection RTK's source position and the columns of its projection-to-fixed matrix, mapped
/// into ctrecon's frame (RTK's (x, y, z) is ctrecon's (x, −z, y)).
const RTK: &str = r#"
import sys, json, itk, numpy as np
from itk import RTK as rtk
job = json.load(sys.stdin)
if "write" in job:
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for p in job["write"]:
        g.AddProjection(*p)
    w = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    w.SetFilename(job["path"]); w.SetObject(g); w.WriteFile()
else:
    r = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    r.SetFilename(job["path"]); r.GenerateOutputInformation()
    g = r.GetOutputObject()
c = lambda p: [float(p[0]), -float(p[2]), float(p[1])]
out = []
for i in range(len(g.GetGantryAngles())):
    m = itk.array_from_matrix(g.GetProjectionCoordinatesToFixedSystemMatrix(i))
    out.append({"source": c(np.array(g.GetSourcePosition(i))), "origin": c(m[:3, 3]),
                "u": c(m[:3, 0]), "v": c(m[:3, 1]),
                "gantry_deg": float(np.degrees(g.GetGantryAngles()[i]))})
print(json.dumps(out))
"#;

fn rtk(py: &Path, job: Value) -> Vec<Value> {
    let mut child = Command::new(py)
        .args(["-c", RTK])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start python");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin
            .write_all(job.to_string().as_bytes())
            .expect("write job");
    }
    let out = child.wait_with_output().expect("python");
    assert!(
        out.status.success(),
        "itk-rtk: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice::<Vec<Value>>(&out.stdout).expect("RTK's JSON")
}

fn vec3(v: &Value) -> [f64; 3] {
    std::array::from_fn(|i| v[i].as_f64().expect("a number"))
}

/// ctrecon's per-view vectors `[s, d, u, v]` against RTK's source, origin and unit axes (the pitch
/// divided out), to 1e-6 mm.
fn assert_agree(vectors: &Value, rtk: &[Value], pitch: [f64; 2]) {
    let rows = vectors["vectors"].as_array().expect("vectors");
    assert_eq!(rows.len(), rtk.len());
    let mut worst = 0.0f64;
    for (k, (row, r)) in rows.iter().zip(rtk).enumerate() {
        let x: Vec<f64> = row
            .as_array()
            .expect("row")
            .iter()
            .map(|v| v.as_f64().expect("number"))
            .collect();
        let pairs = [
            ([x[0], x[1], x[2]], vec3(&r["source"]), 1.0),
            ([x[3], x[4], x[5]], vec3(&r["origin"]), 1.0),
            ([x[6], x[7], x[8]], vec3(&r["u"]), pitch[0]),
            ([x[9], x[10], x[11]], vec3(&r["v"]), pitch[1]),
        ];
        for (ours, theirs, scale) in pairs {
            for i in 0..3 {
                let d = (ours[i] / scale - theirs[i]).abs();
                worst = worst.max(d);
                assert!(d < 1e-6, "view {k}: ours {ours:?}/{scale}, RTK {theirs:?}");
            }
        }
    }
    println!("{} views agree with RTK to {worst:.1e} mm", rows.len());
}

#[test]
fn rtk_reads_the_geometry_xml_ctrecon_writes() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("temp dir");
    let cone = json!({"type": "cone", "angles": {"count": 36, "start_deg": 15, "range_deg": -250},
        "dso_mm": 600, "dsd_mm": 950,
        "detector": {"nu": 64, "nv": 40, "du_mm": 0.8, "dv_mm": 0.6, "offset_u_mm": 5.5, "offset_v_mm": -3}});
    std::fs::write(dir.path().join("cone.json"), cone.to_string()).expect("write");
    ctrecon(
        dir.path(),
        &["geometry", "--input", "cone.json", "--output", "g.xml"],
    );
    ctrecon(
        dir.path(),
        &["geometry", "--input", "cone.json", "--output", "v.json"],
    );
    let ours: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("v.json")).expect("read"))
            .expect("json");
    let path = dir.path().join("g.xml");
    let theirs = rtk(&py, json!({"path": path}));
    // RTK's gantry angles are ctrecon's view angles (in [0°, 360°)).
    for (k, r) in theirs.iter().enumerate() {
        let want = (15.0 - 250.0 * k as f64 / 36.0).rem_euclid(360.0);
        let got = r["gantry_deg"].as_f64().expect("angle");
        assert!((got - want).abs() < 1e-9, "view {k}: {got} vs {want}");
    }
    assert_agree(&ours, &theirs, [0.8, 0.6]);

    // A trajectory no circle describes: the source wobbles in radius and height, the panel rolls.
    let mut wobble = ours.clone();
    for (k, row) in wobble["vectors"]
        .as_array_mut()
        .expect("rows")
        .iter_mut()
        .enumerate()
    {
        let t = k as f64 * 0.4;
        let x: Vec<f64> = row
            .as_array()
            .expect("row")
            .iter()
            .map(|v| v.as_f64().expect("number"))
            .collect();
        let (s, c) = (t / 8.0).sin_cos();
        let mut y = x.clone();
        y[0] *= 1.0 + 0.05 * t.sin();
        y[1] *= 1.0 + 0.05 * t.sin();
        y[2] += 4.0 * t.cos();
        for i in 0..3 {
            let (eu, ev) = (x[6 + i] / 0.8, x[9 + i] / 0.6);
            y[6 + i] = 0.8 * (c * eu + s * ev);
            y[9 + i] = 0.6 * (-s * eu + c * ev);
        }
        *row = json!(y);
    }
    std::fs::write(dir.path().join("wobble.json"), wobble.to_string()).expect("write");
    let said = ctrecon(
        dir.path(),
        &["geometry", "--input", "wobble.json", "--output", "w.xml"],
    );
    assert!(said.contains("FBP/FDK: no"), "{said}");
    let theirs = rtk(&py, json!({"path": dir.path().join("w.xml")}));
    assert_agree(&wobble, &theirs, [0.8, 0.6]);
}

#[test]
fn ctrecon_reads_the_geometry_xml_rtk_writes() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("rtk.xml");
    // sid, sdd, gantry, projection offset x/y, out-of-plane, in-plane, source offset x/y.
    let projections: Vec<Value> = (0..20)
        .map(|k| {
            let k = k as f64;
            json!([
                500.0 + 3.0 * k,
                800.0 - 2.0 * k,
                18.0 * k + 7.0,
                4.0 - 0.3 * k,
                -2.0 + 0.2 * k,
                3.0 * (k * 0.5).sin(),
                -6.0 + 0.5 * k,
                1.5 * (k * 0.3).cos(),
                -0.7 + 0.1 * k
            ])
        })
        .collect();
    let theirs = rtk(&py, json!({"path": path, "write": projections}));
    let said = ctrecon(
        dir.path(),
        &[
            "geometry",
            "--input",
            "rtk.xml",
            "--detector",
            "32",
            "24",
            "--pitch-mm",
            "1.2",
            "0.9",
            "--output",
            "v.json",
        ],
    );
    assert!(
        said.contains("wrote v.json: 20 views, data shape [20, 24, 32]"),
        "{said}"
    );
    let ours: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("v.json")).expect("read"))
            .expect("json");
    assert_agree(&ours, &theirs, [1.2, 0.9]);
}
