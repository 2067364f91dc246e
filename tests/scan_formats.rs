//! Scans as scanners write them, made by an independent writer (Python `tifffile`: little- and big-endian,
//! 8/16-bit integer and 32-bit float, one file per view and multi-page) and read back by `ctrecon::scans`:
//! every pixel must come back exactly, the metadata must map to the geometry, and bad input must give an
//! error naming the file and key. Runs when `.venv-scans/` (scripts/install-peers.sh scans) or `python3` has
//! tifffile; otherwise prints one skip line, or fails under `CTRECON_REQUIRE_PEERS=1`.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Once;

use ctrecon::recon::geometry::{Angles, Geometry};
use ctrecon::scans::{self, Format, Intensity, ScanError};
use serde_json::json;

/// The Python that has tifffile: `.venv-scans/bin/python`, else `python3`; `None` (after one skip line, or
/// a panic under CTRECON_REQUIRE_PEERS=1) when neither imports it.
pub(crate) fn python() -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-scans/bin/python");
    let found = [venv, PathBuf::from("python3")].into_iter().find(|py| {
        Command::new(py)
            .args(["-c", "import tifffile, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    if found.is_none() {
        if std::env::var("CTRECON_REQUIRE_PEERS").as_deref() == Ok("1") {
            panic!(
                "tifffile is required (CTRECON_REQUIRE_PEERS=1): run scripts/install-peers.sh scans"
            );
        }
        static SKIP: Once = Once::new();
        SKIP.call_once(|| {
            eprintln!("SKIPPED: no Python with tifffile (run scripts/install-peers.sh scans)")
        });
    }
    found
}

/// `ctrecon recon --input <input> --algorithm <algorithm> --size 40 --pixel-mm 0.1 --centre <centre>`, run
/// in-process; the volume it wrote to `output`.
pub(crate) fn recon_40(
    input: &Path,
    algorithm: &str,
    centre: &str,
    output: &Path,
) -> ndarray::Array3<f32> {
    let args = ctrecon::cli::recon::ReconArgs {
        input: input.to_path_buf(),
        geometry: None,
        algorithm: algorithm.into(),
        filter: None,
        cutoff: None,
        params: None,
        size: 40,
        pixel_mm: 0.1,
        grid: None,
        max_bytes: 1 << 30,
        output: output.to_path_buf(),
        png: None,
        centre: centre.into(),
        preprocessing: None,
        slice: None,
        ww: None,
        wl: None,
    };
    ctrecon::cli::recon::run(args)
        .unwrap_or_else(|e| panic!("ctrecon recon --input {}: {e}", input.display()));
    ndarray_npy::read_npy(output).expect("read the volume")
}

/// Writes TIFFs as the jobs on stdin say; view `i` holds `(i·7919 + r·131 + c·17 + base) mod modulo`, times
/// `scale`, in the job's dtype and byte order.
const WRITER: &str = r#"
import sys, json, numpy as np, tifffile
for job in json.load(sys.stdin):
    n, nv, nu = job["views"], job["nv"], job["nu"]
    dt = np.dtype(job["dtype"]).newbyteorder(job["order"])
    def view(i):
        r = np.arange(nv)[:, None]; c = np.arange(nu)[None, :]
        v = (i * 7919 + r * 131 + c * 17 + job["base"]) % job["modulo"]
        return (v * job["scale"]).astype(dt)
    if job["layout"] == "pages":
        with tifffile.TiffWriter(job["path"], byteorder=job["order"]) as w:
            for i in range(n):
                w.write(view(i), photometric="minisblack", contiguous=False)
    else:
        for i in range(n):
            tifffile.imwrite(job["path"].format(i + job["first"]), view(i), byteorder=job["order"],
                             photometric="minisblack")
"#;

/// What the writer put in view `i`, pixel `(r, c)`.
fn expected(job: &serde_json::Value, i: usize, r: usize, c: usize) -> f32 {
    let base = job["base"].as_u64().unwrap_or(0) as usize;
    let modulo = job["modulo"].as_u64().unwrap_or(1) as usize;
    let v = (i * 7919 + r * 131 + c * 17 + base) % modulo;
    // float32 views are float64 products rounded once, as numpy's astype does.
    (v as f64 * job["scale"].as_f64().unwrap_or(1.0)) as f32
}

/// A writer job with defaults: `layout` "files" (path has `{}` for the number) or "pages".
pub(crate) fn job(
    path: &Path,
    layout: &str,
    dtype: &str,
    order: &str,
    views: usize,
    nv: usize,
    nu: usize,
) -> serde_json::Value {
    let modulo = match dtype {
        "uint8" => 256,
        "float32" => 1000,
        _ => 65536,
    };
    json!({"path": path.to_string_lossy(), "layout": layout, "dtype": dtype, "order": order, "views": views,
           "nv": nv, "nu": nu, "base": 5, "modulo": modulo, "scale": if dtype == "float32" { 0.001 } else { 1.0 },
           "first": 1})
}

pub(crate) fn write(py: &Path, jobs: &[serde_json::Value]) {
    let mut child = Command::new(py)
        .args(["-c", WRITER])
        .stdin(Stdio::piped())
        .spawn()
        .expect("start python");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin
            .write_all(serde_json::to_string(jobs).expect("json").as_bytes())
            .expect("write jobs");
    }
    assert!(
        child.wait().expect("python").success(),
        "tifffile writer failed"
    );
}

/// Every view of `scan` equals the writer's values.
fn assert_views_equal(scan: &mut scans::Scan, job: &serde_json::Value) {
    let (nv, nu) = scan.views.shape();
    assert_eq!(
        (nv, nu),
        (
            job["nv"].as_u64().unwrap_or(0) as usize,
            job["nu"].as_u64().unwrap_or(0) as usize
        )
    );
    let mut buf = vec![0f32; nv * nu];
    for i in 0..scan.views.view_count() {
        scan.views.read_view(i, &mut buf).expect("read view");
        for r in 0..nv {
            for c in 0..nu {
                assert_eq!(
                    buf[r * nu + c],
                    expected(job, i, r, c),
                    "view {i} pixel ({r}, {c})"
                );
            }
        }
    }
}

pub(crate) fn xtekct(name: &str, projections: usize, nx: usize, ny: usize) -> String {
    format!(
        "[XTekCT]\nName={name}\nInputFolderName=\nUnits=mm\nVoxelsX=8\nProjections={projections}\n\
         DetectorPixelsX={nx}\nDetectorPixelsY={ny}\nDetectorPixelSizeX=0.2\nDetectorPixelSizeY=0.2\n\
         SrcToObject=100\nSrcToDetector=400\nInitialAngle=0\nAngularStep=90\nObjectOffsetX=0.1\n\
         DetectorOffsetX=0\nDetectorOffsetY=0\nWhiteLevel=60000\n[Xrays]\nXraykV=120\n"
    )
}

#[test]
fn a_nikon_scan_written_by_tifffile_reads_back_exactly() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let j = write_nikon_views(&py, dir.path());
    std::fs::write(dir.path().join("ball.xtekct"), xtekct("ball", 4, 7, 5)).expect("xtekct");
    std::fs::write(
        dir.path().join("ball_ctdata.txt"),
        "Tomography angles\nProjection\tAngle(deg)\n\n1\t0.0\n2\t90.0\n3\t180.0\n4\t270.0\n",
    )
    .expect("ctdata");
    for path in [dir.path().join("ball.xtekct"), dir.path().to_path_buf()] {
        let mut scan = scans::open(&path).expect("open the Nikon scan");
        assert_eq!(scan.format, Format::NikonXtek);
        assert_eq!(
            scan.intensity,
            Intensity::FlatCorrected {
                white_level: 60000.0
            }
        );
        let Geometry::Cone(g) = &scan.geometry else {
            panic!("a cone beam")
        };
        assert_eq!(
            g.angles,
            Angles::List {
                degrees: vec![-180.0, -90.0, 0.0, 90.0]
            }
        );
        assert!(
            (g.detector.offset_u_mm - 0.4).abs() < 1e-12,
            "{}",
            g.detector.offset_u_mm
        );
        assert!(
            scan.provenance
                .iter()
                .any(|p| p.key == "SrcToObject" && p.origin == "ball.xtekct [XTekCT] SrcToObject")
        );
        assert!(
            scan.provenance
                .iter()
                .any(|p| p.key == "angles" && p.origin == "ball_ctdata.txt")
        );
        assert_views_equal(&mut scan, &j);
    }
}

#[test]
fn a_skyscan_scan_written_big_endian_reads_back_exactly() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let j = write_skyscan_scan(&py, dir.path());
    let mut scan = scans::open(dir.path()).expect("open the SkyScan scan");
    assert_eq!(scan.format, Format::BrukerSkyscan);
    let Geometry::Cone(g) = &scan.geometry else {
        panic!("a cone beam")
    };
    assert!((g.detector.du_mm - 0.09).abs() < 1e-12);
    assert_eq!(g.dso_mm, 100.0);
    assert_views_equal(&mut scan, &j);
}

#[test]
fn tiff_stacks_of_every_sample_type_and_byte_order_read_back_exactly() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let geometry = |n: usize, nv: usize, nu: usize| {
        json!({"type": "cone", "angles": {"count": n}, "dso_mm": 100, "dsd_mm": 200,
               "detector": {"nu": nu, "nv": nv, "du_mm": 0.5, "dv_mm": 0.5}})
        .to_string()
    };
    let pages_be = job(&dir.path().join("be.tif"), "pages", "uint16", ">", 3, 4, 5);
    let pages_f32 = job(&dir.path().join("f.tif"), "pages", "float32", "<", 2, 3, 6);
    std::fs::create_dir(dir.path().join("u8")).expect("mkdir");
    let files_u8 = job(
        &dir.path().join("u8/view{}.tif"),
        "files",
        "uint8",
        "<",
        11,
        2,
        3,
    );
    write(
        &py,
        &[pages_be.clone(), pages_f32.clone(), files_u8.clone()],
    );
    std::fs::write(dir.path().join("be.json"), geometry(3, 4, 5)).expect("json");
    std::fs::write(dir.path().join("f.json"), geometry(2, 3, 6)).expect("json");
    std::fs::write(dir.path().join("u8/geometry.json"), geometry(11, 2, 3)).expect("json");
    let mut be = scans::open(&dir.path().join("be.tif")).expect("big-endian pages");
    assert_eq!(
        be.intensity,
        Intensity::Raw {
            white_level: 65535.0
        }
    );
    assert_views_equal(&mut be, &pages_be);
    let mut f = scans::open(&dir.path().join("f.tif")).expect("float pages");
    assert_eq!(f.intensity, Intensity::Transmission);
    assert_views_equal(&mut f, &pages_f32);
    // view1 … view11: natural order, not view1, view10, view11, view2, …
    let mut u8s = scans::open(&dir.path().join("u8")).expect("a folder of 8-bit views");
    assert_eq!(u8s.format, Format::TiffStack);
    assert_views_equal(&mut u8s, &files_u8);
}

fn error_text(e: ScanError) -> String {
    e.to_string()
}

#[test]
fn bad_scans_give_errors_that_name_the_file_and_key() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    write_nikon_views(&py, dir.path());
    let x = dir.path().join("ball.xtekct");

    std::fs::write(&x, xtekct("ball", 5, 7, 5)).expect("xtekct");
    let msg = error_text(scans::open(&x).unwrap_err());
    assert!(
        msg.contains("ball.xtekct") && msg.contains("Projections"),
        "{msg}"
    );

    std::fs::write(&x, xtekct("ball", 4, 8, 5)).expect("xtekct");
    let msg = error_text(scans::open(&x).unwrap_err());
    assert!(
        msg.contains("ball.xtekct") && msg.contains("DetectorPixelsX"),
        "{msg}"
    );

    std::fs::write(
        &x,
        xtekct("ball", 4, 7, 5).replace("WhiteLevel=60000\n", ""),
    )
    .expect("xtekct");
    let msg = error_text(scans::open(&x).unwrap_err());
    assert!(
        msg.contains("ball.xtekct") && msg.contains("WhiteLevel"),
        "{msg}"
    );

    std::fs::write(
        &x,
        xtekct("ball", 4, 7, 5).replace("SrcToObject=100", "SrcToObject=1OO"),
    )
    .expect("xtekct");
    let msg = error_text(scans::open(&x).unwrap_err());
    assert!(msg.contains("SrcToObject") && msg.contains("1OO"), "{msg}");

    // A truncated projection: refused when the scan is opened (first view) or when the view is read.
    std::fs::write(&x, xtekct("ball", 4, 7, 5)).expect("xtekct");
    let third = dir.path().join("ball_0003.tif");
    let bytes = std::fs::read(&third).expect("read");
    std::fs::write(&third, &bytes[..bytes.len() - 20]).expect("truncate");
    let mut scan = scans::open(&x).expect("the first view is whole");
    let mut buf = vec![0f32; 35];
    let msg = error_text(scan.views.read_view(2, &mut buf).unwrap_err());
    assert!(
        msg.contains("ball_0003.tif") && msg.contains("truncated"),
        "{msg}"
    );
    let first = dir.path().join("ball_0001.tif");
    let bytes = std::fs::read(&first).expect("read");
    std::fs::write(&first, &bytes[..bytes.len() / 2]).expect("truncate");
    let e = match scans::open(&x) {
        Err(e) => e,
        Ok(mut scan) => scan.views.read_view(0, &mut buf).unwrap_err(),
    };
    let msg = error_text(e);
    assert!(msg.contains("ball_0001.tif"), "{msg}");

    // A stack without its geometry, and a file of no known format.
    let stack = dir.path().join("lone.tif");
    std::fs::copy(&third, &stack).expect("copy");
    let msg = error_text(scans::open(&stack).unwrap_err());
    assert!(
        msg.contains("lone.json") && msg.contains("geometry"),
        "{msg}"
    );
    let msg = error_text(scans::open(&dir.path().join("ball.xtekct.bak")).unwrap_err());
    assert!(msg.contains("ball.xtekct.bak"), "{msg}");
}

/// A small ball off the axis, seen by a Nikon scanner with offset axis and detector: ctrecon's projector
/// simulates it in the geometry mapped from the `.xtekct`, tifffile writes the views as the scanner would
/// (uint16 transmissions × WhiteLevel, the image turned as Nikon stores it), and FDK of what the reader gives
/// back puts the ball where it was.
#[test]
fn fdk_of_a_simulated_nikon_scan_puts_an_off_centre_ball_where_it_was() {
    use ctrecon::recon::algorithm::FbpParams;
    use ctrecon::recon::analytic::fdk;
    use ctrecon::recon::control::unattended;
    use ctrecon::recon::geometry::Views;
    use ctrecon::recon::grid::VolumeGrid;

    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let (xfile, centre) = write_ball_scan(&py, dir.path());
    let mut scan = scans::open(&xfile).expect("open");
    let li = scans::line_integrals(&mut scan, 1 << 30).expect("line integrals");
    assert_eq!(li.clamped, 0);
    let Ok(Views::D3(read_views)) = scan.geometry.to_views() else {
        panic!("cone views")
    };
    let grid = VolumeGrid::cube(40, 0.1);
    let vol = fdk(
        &read_views,
        li.projections.view(),
        &grid,
        &FbpParams::default(),
        unattended(),
    )
    .expect("fdk");
    assert_ball_at(&vol, &grid, centre);

    // The same through the CLI: `ctrecon recon --input ball.xtekct --algorithm fdk --size 40 --pixel-mm 0.1`.
    // The .xtekct states no calibrated centre, so the centre is found from the views (the default).
    let recon = |centre: &str| -> ndarray::Array3<f32> {
        let out = dir.path().join(format!("v-{centre}.npy"));
        recon_40(&xfile, "fdk", centre, &out)
    };
    let rms = |a: &ndarray::Array3<f32>, b: &ndarray::Array3<f32>| {
        let s: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum();
        (s / a.len() as f64).sqrt()
    };
    let found = recon("auto");
    assert_ball_at(&found, &grid, centre);
    let stated = recon("read");
    assert_ball_at(&stated, &grid, centre);

    // A file that leaves out its offsets (ObjectOffsetX, DetectorOffsetX: the axis projects 1.5 px off the
    // panel's centre): read as it is, the ball is smeared into a ring; found from the views, it is sharp
    // and in place again, as with the stated offsets.
    let text = std::fs::read_to_string(&xfile).expect("xtekct");
    let bare = text
        .replace("ObjectOffsetX=0.2\n", "")
        .replace("DetectorOffsetX=0.15\n", "");
    std::fs::write(&xfile, bare).expect("xtekct");
    let found = recon("auto");
    assert_ball_at(&found, &grid, centre);
    let wrong = recon("read");
    let (e_found, e_wrong) = (rms(&found, &stated), rms(&wrong, &stated));
    println!("RMS from the stated-offset volume: found {e_found:.2e}, as read {e_wrong:.2e}");
    assert!(
        e_found < 0.1 * e_wrong,
        "RMS difference from the reconstruction with the stated offsets: {e_found} with the centre \
         found, {e_wrong} with the centre as read"
    );
    // Pinned by the user: the stated value gives the ball back as well.
    let pinned = recon("0.45");
    assert_ball_at(&pinned, &grid, centre);
}

/// Write the Nikon scan of [`fdk_of_a_simulated_nikon_scan_puts_an_off_centre_ball_where_it_was`] into `dir`
/// (`ball.xtekct` + 120 uint16 TIFFs of 40 × 36, the views simulated by ctrecon's projector and written by
/// tifffile); answers the `.xtekct` and the ball's centre (mm).
pub(crate) fn write_ball_scan(py: &Path, dir: &Path) -> (PathBuf, [f64; 3]) {
    use ctrecon::recon::geometry::Views;
    use ctrecon::recon::grid::VolumeGrid;
    use ctrecon::recon::projector::forward_3d;
    use ctrecon::scans::{Orientation, ini::Ini, nikon};
    use ndarray::Array3;

    let text = "[XTekCT]\nName=ball\nUnits=mm\nProjections=120\nDetectorPixelsX=40\nDetectorPixelsY=36\n\
                DetectorPixelSizeX=0.3\nDetectorPixelSizeY=0.3\nSrcToObject=100\nSrcToDetector=300\n\
                InitialAngle=10\nAngularStep=3\nObjectOffsetX=0.2\nDetectorOffsetX=0.15\n\
                DetectorOffsetY=0.3\nWhiteLevel=60000\n";
    let xfile = dir.join("ball.xtekct");
    std::fs::write(&xfile, text).expect("xtekct");
    let x = nikon::parse(&mut Ini::parse(&xfile, text)).expect("parse");
    let Ok(Views::D3(views)) = nikon::geometry(&x, None).to_views() else {
        panic!("cone views")
    };

    // The ball: radius 0.45 mm at (0.7, −0.5, 0.4) mm, μ = 0.5/mm, on a fine grid (4× supersampled edges).
    let centre = [0.7, -0.5, 0.4];
    let fine = VolumeGrid::cube(64, 0.05);
    let ball = Array3::from_shape_fn((64, 64, 64), |(k, j, i)| {
        let mut inside = 0;
        for s in 0..64 {
            let o = |t: usize| (t as f64 + 0.5) / 4.0 - 0.5;
            let p = [
                fine.x(i) + o(s % 4) * 0.05,
                fine.y(j) + o((s / 4) % 4) * 0.05,
                fine.z(k) + o(s / 16) * 0.05,
            ];
            let d2: f64 = (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum();
            inside += (d2 < 0.45f64.powi(2)) as u32;
        }
        0.5 * inside as f32 / 64.0
    });
    let p = forward_3d(&views, ball.view(), &fine);
    let (nv, nu) = (36, 40);
    let mut stored = ndarray::Array3::<u16>::zeros((120, nv, nu));
    for i in 0..120 {
        for r in 0..nv {
            for c in 0..nu {
                let (ir, ic) = Orientation::TURNED.image_index(r, c, nv, nu);
                stored[[i, ir, ic]] = (60000.0 * (-p[[i, r, c]]).exp()).round() as u16;
            }
        }
    }
    let npy = dir.join("views.npy");
    ndarray_npy::write_npy(&npy, &stored).expect("npy");
    let script = "import sys, numpy as np, tifffile\na = np.load(sys.argv[1])\n\
                  for i in range(len(a)):\n    tifffile.imwrite(sys.argv[2].format(i + 1), a[i], photometric='minisblack')\n";
    let pattern = dir.join("ball_{:04d}.tif");
    let status = Command::new(py)
        .args([
            "-c",
            script,
            &npy.to_string_lossy(),
            &pattern.to_string_lossy(),
        ])
        .status()
        .expect("python");
    assert!(status.success());

    std::fs::remove_file(&npy).expect("remove views.npy");
    (xfile, centre)
}

/// The centroid of the voxels above half the peak lies within half a voxel of `centre` (mm).
pub(crate) fn assert_ball_at(
    vol: &ndarray::Array3<f32>,
    grid: &ctrecon::recon::grid::VolumeGrid,
    centre: [f64; 3],
) {
    let peak = vol.iter().copied().fold(f32::MIN, f32::max);
    let (mut w, mut c) = (0.0, [0.0; 3]);
    for ((k, j, i), &v) in vol.indexed_iter() {
        if v > peak / 2.0 {
            let v = f64::from(v);
            w += v;
            for (a, pos) in [grid.x(i), grid.y(j), grid.z(k)].into_iter().enumerate() {
                c[a] += v * pos;
            }
        }
    }
    let got = c.map(|s| s / w);
    for a in 0..3 {
        assert!(
            (got[a] - centre[a]).abs() < 0.05,
            "ball centre {got:?} mm, placed at {centre:?} mm (peak μ {peak})"
        );
    }
}

/// A SkyScan scan in `dir`: `rat_.log` and three big-endian uint16 TIFFs of 4 × 6 written by tifffile;
/// answers the tifffile job that wrote them (with the pixel values it used).
pub(crate) fn write_skyscan_scan(py: &Path, dir: &Path) -> serde_json::Value {
    let mut j = job(&dir.join("rat_{:08d}.tif"), "files", "uint16", ">", 3, 6, 4);
    j["first"] = json!(0);
    write(py, std::slice::from_ref(&j));
    let log = "[System]\nCamera Pixel Size (um)=9.0\n[Acquisition]\nFilename Prefix=rat_\nNumber of Files=3\n\
               Number of Rows=6\nNumber of Columns=4\nImage Pixel Size (um)=30\nObject to Source (mm)=100\n\
               Camera to Source (mm)=300\nRotation Step (deg)=120\nUse 360 Rotation=YES\nDepth (bits)=16\n\
               Flat Field Correction=ON\n";
    std::fs::write(dir.join("rat_.log"), log).expect("log");
    j
}

/// Four little-endian uint16 TIFFs of 7 × 5, `ball_0001.tif` …, written by tifffile into `dir` (the views of
/// the small Nikon scans, beside an [`xtekct`]); answers the tifffile job that wrote them.
pub(crate) fn write_nikon_views(py: &Path, dir: &Path) -> serde_json::Value {
    let j = job(
        &dir.join("ball_{:04d}.tif"),
        "files",
        "uint16",
        "<",
        4,
        5,
        7,
    );
    write(py, std::slice::from_ref(&j));
    j
}
