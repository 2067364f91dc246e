//! Patient orientation over HTTP: one synthetic patient with three cube markers at known LPS points, written
//! as CT series in every acquisition (head-first and feet-first, supine and prone, rows/columns/slices stored
//! in reverse, coronal and sagittal images, a gantry tilt). Every slice, projection and product must show each
//! marker at the same screen pixel, in radiological display orientation, and say so in its PNG text chunks and
//! DICOM attributes.

mod common;

use common::{TestApp, read_npy_f32, spawn_app};
use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::volume::{Frame, Volume};
use dicom_dictionary_std::tags;
use ndarray::Array3;
use serde_json::{Value, json};

/// Samples per patient axis (x left, y posterior, z superior) and their spacing (mm); lower corner.
const N: [usize; 3] = [18, 14, 10];
const S: [f64; 3] = [0.8, 1.0, 2.0];
const O: [f64; 3] = [-7.0, -5.0, 40.0];

/// Marker cubes (3 samples a side) centred on lattice indices `[x, y, z]`, with their HU.
const MARKERS: [([usize; 3], f32); 3] =
    [([3, 3, 2], 300.0), ([13, 4, 6], 600.0), ([8, 10, 5], 900.0)];

/// HU of the patient at LPS point `p`: a marker inside its cube, 0 elsewhere.
fn patient(p: [f64; 3]) -> f32 {
    for (c, v) in MARKERS {
        if (0..3).all(|a| (((p[a] - O[a]) / S[a]) - c[a] as f64).abs() <= 1.5) {
            return v;
        }
    }
    0.0
}

/// A series of the patient whose index axes (column, row, slice) point along `direction` (signed patient
/// axes); every sample lies on the patient lattice.
fn acquisition(direction: [[f64; 3]; 3]) -> Volume {
    let axis = |d: [f64; 3]| (0..3).find(|&c| d[c] != 0.0).unwrap_or(0);
    let n: [usize; 3] = std::array::from_fn(|a| N[axis(direction[a])]);
    let mut origin = O;
    for d in direction {
        let c = axis(d);
        if d[c] < 0.0 {
            origin[c] = O[c] + (N[c] - 1) as f64 * S[c];
        }
    }
    let frame = Frame {
        spacing_mm: std::array::from_fn(|a| S[axis(direction[a])]),
        origin_mm: origin,
        direction,
    };
    let data = Array3::from_shape_fn((n[2], n[1], n[0]), |(k, j, i)| {
        patient(frame.position(k as f64, j as f64, i as f64))
    });
    Volume { data, frame }
}

/// A 12° gantry tilt: rows along x, columns posterior and inferior, slices stepping along z.
fn tilted() -> Volume {
    let t = 12f64.to_radians();
    let frame = Frame {
        spacing_mm: [S[0], S[1], S[2]],
        origin_mm: [O[0], O[1] - 1.0, O[2] + 1.5],
        direction: [[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, 1.0]],
    };
    let data = Array3::from_shape_fn((N[2] + 2, N[1] + 2, N[0]), |(k, j, i)| {
        patient(frame.position(k as f64, j as f64, i as f64))
    });
    Volume { data, frame }
}

const X: [f64; 3] = [1.0, 0.0, 0.0];
const Y: [f64; 3] = [0.0, 1.0, 0.0];
const Z: [f64; 3] = [0.0, 0.0, 1.0];
fn neg(v: [f64; 3]) -> [f64; 3] {
    v.map(|c| -c)
}

/// The acquisitions: name, index axes, files in reverse order.
fn acquisitions() -> Vec<(&'static str, [[f64; 3]; 3], bool)> {
    vec![
        ("head-first supine", [X, Y, Z], false),
        (
            "feet-first supine (rows right to left)",
            [neg(X), Y, neg(Z)],
            false,
        ),
        ("head-first prone", [neg(X), neg(Y), Z], false),
        ("feet-first prone", [X, neg(Y), neg(Z)], false),
        ("rows stored bottom to top", [X, neg(Y), neg(Z)], false),
        ("slices stored superior to inferior", [X, Y, Z], true),
        ("coronal images", [X, neg(Z), Y], false),
        ("sagittal images", [Y, neg(Z), neg(X)], true),
    ]
}

fn meta(description: &str) -> SeriesMeta {
    SeriesMeta {
        study_uid: Some("1.2.826.0.1.3680043.8.498.77".into()),
        frame_of_reference_uid: Some("1.2.826.0.1.3680043.8.498.78".into()),
        patient_id: Some("MARKERS".into()),
        series_description: description.into(),
        series_number: 3,
        ..Default::default()
    }
}

/// Upload `vol` as a ZIP of CT files; returns the series JSON.
async fn upload(app: &TestApp, vol: &Volume, name: &str, reverse: bool) -> Value {
    let mut files = write_ct_series(vol, &meta(name)).unwrap().files;
    if reverse {
        files.reverse();
    }
    let zip = write_zip(&files).unwrap();
    let r = app
        .client
        .post(app.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{name}: {}", r.text().await.unwrap());
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["status"], "ready", "{name}: {v}");
    v["series"][0]["series"].clone()
}

const PRODUCTS: &str = r#"[
    {"type": "projection", "axis": "axial", "kind": "mip"},
    {"type": "projection", "axis": "coronal", "kind": "mip"},
    {"type": "projection", "axis": "sagittal", "kind": "mip"},
    {"type": "mpr", "plane": "coronal"},
    {"type": "rotating", "frames": 4}
]"#;

/// Run a volume job with every product on the series; returns the job JSON once it succeeded.
async fn volume_job(app: &TestApp, series: &str) -> Value {
    let products: Value = serde_json::from_str(PRODUCTS).unwrap();
    let job = app
        .submit(&json!({"kind": "volume", "input": series, "steps": [], "products": products}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    done
}

async fn get_bytes(app: &TestApp, path: &str) -> Vec<u8> {
    let r = app.get(path).await;
    let status = r.status();
    let b = r.bytes().await.unwrap().to_vec();
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&b));
    b
}

async fn image(app: &TestApp, path: &str) -> (Vec<usize>, Vec<f32>) {
    read_npy_f32(&get_bytes(app, path).await)
}

/// The `tEXt` chunks of a PNG.
fn png_text(bytes: &[u8]) -> Vec<(String, String)> {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let reader = decoder.read_info().unwrap();
    reader
        .info()
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect()
}

/// Where a marker at lattice index `c` is seen in each display: axial `[y][x]`, coronal `[z↓][x]`,
/// sagittal `[z↓][y]`.
fn screen(axis: &str, c: [usize; 3]) -> (usize, usize) {
    match axis {
        "axial" => (c[1], c[0]),
        "coronal" => (N[2] - 1 - c[2], c[0]),
        _ => (N[2] - 1 - c[2], c[1]),
    }
}

fn slice_index(axis: &str, c: [usize; 3]) -> usize {
    match axis {
        "axial" => c[2],
        "coronal" => c[1],
        _ => c[0],
    }
}

const AXES: [&str; 3] = ["axial", "coronal", "sagittal"];

/// A 2D output: the path that asked for it, its shape and its values.
type Output = (String, Vec<usize>, Vec<f32>);

/// Every 2D output of a job as float images, keyed by what was asked.
async fn outputs(app: &TestApp, job: &str) -> Vec<Output> {
    let mut out = Vec::new();
    for axis in AXES {
        for (c, _) in MARKERS {
            let path = format!(
                "/v1/jobs/{job}/result/slice?axis={axis}&index={}&format=npy",
                slice_index(axis, c)
            );
            let (shape, data) = image(app, &path).await;
            out.push((path, shape, data));
        }
        let path = format!("/v1/jobs/{job}/result/projection?axis={axis}&kind=mip&format=npy");
        let (shape, data) = image(app, &path).await;
        out.push((path, shape, data));
    }
    for p in 0..5 {
        let path = format!("/v1/jobs/{job}/result/products/{p}?format=npy");
        let (shape, data) = image(app, &path).await;
        out.push((path, shape, data));
    }
    out
}

#[tokio::test]
async fn every_acquisition_shows_each_marker_at_the_same_screen_pixel() {
    let app = spawn_app().await;
    let mut reference: Option<Vec<Output>> = None;
    for (name, direction, reverse) in acquisitions() {
        let vol = acquisition(direction);
        let series = upload(&app, &vol, name, reverse).await;
        // Assembly brings every acquisition to the same canonical array.
        let f = &series["frame"];
        for a in 0..3 {
            for c in 0..3 {
                let want = if a == c { 1.0 } else { 0.0 };
                let got = f["direction"][a][c].as_f64().unwrap();
                assert!((got - want).abs() < 1e-6, "{name}: direction {f}");
            }
            let o = f["origin_mm"][a].as_f64().unwrap();
            assert!((o - O[a]).abs() < 1e-3, "{name}: origin {f}");
        }
        assert_eq!(series["shape"], json!([N[2], N[1], N[0]]), "{name}");
        let job = volume_job(&app, series["id"].as_str().unwrap()).await;
        let id = job["id"].as_str().unwrap();
        let got = outputs(&app, id).await;
        match &reference {
            None => {
                // Head-first supine: every marker where the radiological convention puts it.
                for (path, shape, data) in &got {
                    let axis = AXES.iter().find(|a| path.contains(&format!("axis={a}")));
                    let Some(axis) = axis else { continue };
                    let cols = shape[shape.len() - 1];
                    for (c, v) in MARKERS {
                        let is_slice = path.contains("/slice?");
                        let here = path.contains(&format!("index={}&", slice_index(axis, c)));
                        if is_slice && !here {
                            continue;
                        }
                        let (r, col) = screen(axis, c);
                        assert_eq!(data[r * cols + col], v, "{path}: marker {c:?}");
                    }
                }
                // The projection products are the projection views.
                for (p, axis) in AXES.iter().enumerate() {
                    let view = got.iter().find(|(path, _, _)| {
                        path.contains("/projection?") && path.contains(&format!("axis={axis}"))
                    });
                    let product = got
                        .iter()
                        .find(|(path, _, _)| path.contains(&format!("/products/{p}?")));
                    let (Some(view), Some(product)) = (view, product) else {
                        panic!("missing outputs")
                    };
                    assert_eq!(view.2, product.2, "{axis}");
                }
                reference = Some(got);
            }
            Some(want) => {
                for ((path, shape, data), (_, wshape, wdata)) in got.iter().zip(want) {
                    assert_eq!(shape, wshape, "{name}: {path}");
                    let worst = data
                        .iter()
                        .zip(wdata)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0.0f32, f32::max);
                    assert!(worst < 1e-3, "{name}: {path} differs by {worst}");
                }
            }
        }
        // Products and images name their screen sides.
        let products = &job["result"]["products"];
        let sides = |p: usize| products[p]["orientation"].clone();
        assert_eq!(
            sides(0),
            json!({"left": "R", "right": "L", "top": "A", "bottom": "P"}),
            "{name}"
        );
        assert_eq!(
            sides(1),
            json!({"left": "R", "right": "L", "top": "S", "bottom": "I"}),
            "{name}"
        );
        assert_eq!(
            sides(2),
            json!({"left": "A", "right": "P", "top": "S", "bottom": "I"}),
            "{name}"
        );
        assert_eq!(sides(3), sides(1), "{name}");
        assert_eq!(sides(4), sides(1), "{name}");
    }
}

#[tokio::test]
async fn a_tilted_series_shows_its_markers_where_the_image_plane_says() {
    let app = spawn_app().await;
    let vol = tilted();
    let series = upload(&app, &vol, "tilted", false).await;
    assert!(
        (series["tilt_deg"].as_f64().unwrap() - 12.0).abs() < 0.01,
        "{series}"
    );
    let job = volume_job(&app, series["id"].as_str().unwrap()).await;
    let id = job["id"].as_str().unwrap();
    // The projection products are the projection views, and say where they lie.
    for (p, axis) in AXES.iter().enumerate() {
        let (_, product) = image(
            &app,
            &format!("/v1/jobs/{id}/result/products/{p}?format=npy"),
        )
        .await;
        let (_, view) = image(
            &app,
            &format!("/v1/jobs/{id}/result/projection?axis={axis}&kind=mip&format=npy"),
        )
        .await;
        assert_eq!(product, view, "{axis}");
        let plane = &job["result"]["products"][p]["plane"];
        assert!(plane["first_pixel_mm"].is_array(), "{axis}: {plane}");
    }
    for axis in AXES {
        for (c, v) in MARKERS {
            let p: [f64; 3] = std::array::from_fn(|a| O[a] + c[a] as f64 * S[a]);
            // The index of the marker's plane on the display grid, from the middle image's placement.
            let png = get_bytes(
                &app,
                &format!("/v1/jobs/{id}/result/slice?axis={axis}&index=0"),
            )
            .await;
            let text = png_text(&png);
            let plane: Value =
                serde_json::from_str(&text.iter().find(|(k, _)| k == "ImagePlane").unwrap().1)
                    .unwrap();
            let first = |a: usize| plane["first_pixel_mm"][a].as_f64().unwrap();
            let fixed = match axis {
                "axial" => 2,
                "coronal" => 1,
                _ => 0,
            };
            // Display grids are axis-aligned: the fixed coordinate of image `index` grows by the grid step.
            let png1 = get_bytes(
                &app,
                &format!("/v1/jobs/{id}/result/slice?axis={axis}&index=1"),
            )
            .await;
            let plane1: Value = serde_json::from_str(
                &png_text(&png1)
                    .iter()
                    .find(|(k, _)| k == "ImagePlane")
                    .unwrap()
                    .1,
            )
            .unwrap();
            let d = plane1["first_pixel_mm"][fixed].as_f64().unwrap() - first(fixed);
            assert!(d > 0.0, "{axis}: {plane} → {plane1}");
            let index = ((p[fixed] - first(fixed)) / d).round() as usize;
            let path = format!("/v1/jobs/{id}/result/slice?axis={axis}&index={index}&format=npy");
            let (shape, data) = image(&app, &path).await;
            let png = get_bytes(
                &app,
                &format!("/v1/jobs/{id}/result/slice?axis={axis}&index={index}"),
            )
            .await;
            let plane: Value = serde_json::from_str(
                &png_text(&png)
                    .iter()
                    .find(|(k, _)| k == "ImagePlane")
                    .unwrap()
                    .1,
            )
            .unwrap();
            let g = |k: &str, a: usize| plane[k][a].as_f64().unwrap();
            let rel: Vec<f64> = (0..3).map(|a| p[a] - g("first_pixel_mm", a)).collect();
            let col =
                (0..3).map(|a| rel[a] * g("row_direction", a)).sum::<f64>() / g("pixel_mm", 1);
            let row = (0..3)
                .map(|a| rel[a] * g("column_direction", a))
                .sum::<f64>()
                / g("pixel_mm", 0);
            // Centroid of the marker's bright pixels near where the plane puts it.
            let (rows, cols) = (shape[0], shape[1]);
            let (mut sr, mut sc, mut sw) = (0.0, 0.0, 0.0);
            for r in 0..rows {
                for k in 0..cols {
                    let near = (r as f64 - row).abs() <= 3.0 && (k as f64 - col).abs() <= 3.0;
                    let w = data[r * cols + k] as f64;
                    if near && w > v as f64 / 4.0 {
                        sr += r as f64 * w;
                        sc += k as f64 * w;
                        sw += w;
                    }
                }
            }
            assert!(
                sw > 0.0,
                "{axis}: marker {c:?} not seen near ({row:.1}, {col:.1})"
            );
            let (cr, cc) = (sr / sw, sc / sw);
            assert!(
                (cr - row).abs() < 1.0 && (cc - col).abs() < 1.0,
                "{axis}: marker {c:?} at ({cr:.2}, {cc:.2}), expected ({row:.2}, {col:.2})"
            );
        }
    }
}

#[tokio::test]
async fn png_and_dicom_outputs_carry_their_orientation() {
    let app = spawn_app().await;
    let vol = acquisition([neg(X), Y, neg(Z)]);
    let series = upload(&app, &vol, "feet-first", false).await;
    let job = volume_job(&app, series["id"].as_str().unwrap()).await;
    let id = job["id"].as_str().unwrap();
    let want = [
        ("axial", ("R", "L", "A", "P"), ["L", "P"]),
        ("coronal", ("R", "L", "S", "I"), ["L", "F"]),
        ("sagittal", ("A", "P", "S", "I"), ["P", "F"]),
    ];
    for (axis, (l, r, t, b), patient_orientation) in want {
        let png = get_bytes(&app, &format!("/v1/jobs/{id}/result/slice?axis={axis}")).await;
        let text = png_text(&png);
        let o: Value =
            serde_json::from_str(&text.iter().find(|(k, _)| k == "Orientation").unwrap().1)
                .unwrap();
        assert_eq!(
            o,
            json!({"left": l, "right": r, "top": t, "bottom": b}),
            "{axis}"
        );
        let dcm = get_bytes(
            &app,
            &format!("/v1/jobs/{id}/result/projection?axis={axis}&format=dicom"),
        )
        .await;
        let obj = dicom_object::OpenFileOptions::new()
            .from_reader(&dcm[128..])
            .unwrap();
        let strs = |t| {
            obj.element(t)
                .unwrap()
                .to_multi_str()
                .unwrap()
                .iter()
                .map(|s| s.trim().to_string())
                .collect::<Vec<_>>()
        };
        assert_eq!(
            strs(tags::PATIENT_ORIENTATION),
            patient_orientation,
            "{axis}"
        );
        let iop: Vec<f64> = strs(tags::IMAGE_ORIENTATION_PATIENT)
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        let want_iop = match axis {
            "axial" => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            "coronal" => [1.0, 0.0, 0.0, 0.0, 0.0, -1.0],
            _ => [0.0, 1.0, 0.0, 0.0, 0.0, -1.0],
        };
        for (g, w) in iop.iter().zip(want_iop) {
            assert!((g - w).abs() < 1e-6, "{axis}: {iop:?}");
        }
        // The first pixel of a coronal or sagittal image is at the top: the superior end.
        let ipp: Vec<f64> = strs(tags::IMAGE_POSITION_PATIENT)
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        if axis != "axial" {
            let top = O[2] + (N[2] - 1) as f64 * S[2];
            assert!((ipp[2] - top).abs() < 1e-3, "{axis}: {ipp:?}");
        }
        // A product frame too.
        let dcm = get_bytes(
            &app,
            &format!("/v1/jobs/{id}/result/products/3?format=dicom"),
        )
        .await;
        let obj = dicom_object::OpenFileOptions::new()
            .from_reader(&dcm[128..])
            .unwrap();
        let po: Vec<String> = obj
            .element(tags::PATIENT_ORIENTATION)
            .unwrap()
            .to_multi_str()
            .unwrap()
            .iter()
            .map(|s| s.trim().to_string())
            .collect();
        assert_eq!(po, ["L", "F"]);
    }
}

#[tokio::test]
async fn reconstructions_keep_their_row_convention_and_astra_rows_run_up() {
    let app = spawn_app().await;
    let ds = app
        .simulate(common::parallel_geometry(90, 96, 1.0), 40.0)
        .await;
    let mut images = Vec::new();
    for convention in ["ctrecon", "astra"] {
        let job = app
            .submit(&json!({"input": ds, "algorithm": {"name": "fbp"},
                "grid": {"nx": 64, "ny": 64, "dx_mm": 1.25, "dy_mm": 1.25},
                "image_convention": convention}))
            .await;
        let id = job["id"].as_str().unwrap().to_string();
        let done = app.finish(&id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        let (shape, vol) =
            read_npy_f32(&get_bytes(&app, &format!("/v1/jobs/{id}/result/volume.npy")).await);
        assert_eq!(shape, vec![1, 64, 64]);
        let (_, img) = image(&app, &format!("/v1/jobs/{id}/result/slice?format=npy")).await;
        // Without a patient the image is the array as stored.
        assert_eq!(img, vol, "{convention}");
        let png = get_bytes(&app, &format!("/v1/jobs/{id}/result/slice")).await;
        let o: Value = serde_json::from_str(
            &png_text(&png)
                .iter()
                .find(|(k, _)| k == "Orientation")
                .unwrap()
                .1,
        )
        .unwrap();
        let (top, bottom) = if convention == "astra" {
            ("+y", "-y")
        } else {
            ("-y", "+y")
        };
        assert_eq!(
            o,
            json!({"left": "-x", "right": "+x", "top": top, "bottom": bottom})
        );
        images.push(vol);
    }
    // ASTRA's rows are ctrecon's upside down.
    for j in 0..64 {
        for i in 0..64 {
            assert_eq!(images[1][j * 64 + i], images[0][(63 - j) * 64 + i]);
        }
    }
    // Row 0 of ctrecon's image is the smallest y: the phantom is not symmetric in y, so the two differ.
    assert_ne!(images[0], images[1]);
}
