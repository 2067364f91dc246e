//! Orientation labels of the slice viewer for oblique volumes (DESIGN §2): the page's label function
//! (`web/js/orient.js`), run in Chromium, against the server's own (`volume::direction_label`) over rotations
//! computed here, named cases as a radiologist reads them ("LA", "RP", "PI"), and the labels the page shows on
//! a tilted and an in-plane rotated series as uploaded.

use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::volume::{Frame, Volume, direction_label};
use ndarray::Array3;
use serde_json::{Value, json};

use super::browser;
use super::common::{TestApp, spawn_app_with};

type M3 = [[f64; 3]; 3];

fn neg(v: [f64; 3]) -> [f64; 3] {
    v.map(|c| -c)
}

/// The truth: [top, bottom, left, right] of a viewer plane for index axes `d` (i, j, k as LPS vectors).
/// Axial shows i to the right and j down; coronal i right and k up; sagittal j right and k up.
fn sides(plane: &str, d: &M3) -> [String; 4] {
    let (right, down) = match plane {
        "axial" => (d[0], d[1]),
        "coronal" => (d[0], neg(d[2])),
        _ => (d[1], neg(d[2])),
    };
    [
        direction_label(neg(down)),
        direction_label(down),
        direction_label(neg(right)),
        direction_label(right),
    ]
}

fn mul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

/// Rotation about patient axis `axis` (0 x, 1 y, 2 z) by `deg` degrees.
fn rot(axis: usize, deg: f64) -> M3 {
    let (s, c) = deg.to_radians().sin_cos();
    let (p, q) = ((axis + 1) % 3, (axis + 2) % 3);
    let mut m = [[0.0; 3]; 3];
    m[axis][axis] = 1.0;
    m[p][p] = c;
    m[q][q] = c;
    m[q][p] = s;
    m[p][q] = -s;
    m
}

/// Index axes of a volume turned by `r`: the columns of `r`.
fn axes_of(r: &M3) -> M3 {
    std::array::from_fn(|a| std::array::from_fn(|c| r[c][a]))
}

/// Directions of many oblique volumes: turns about each axis and compositions of them, including the
/// thresholds' neighbourhood (5.7° puts a component at sin ≈ 0.0993, 5.8° at 0.101).
fn cases() -> Vec<M3> {
    let angles = [
        0.0, 5.7, 5.8, 12.0, 30.0, 45.0, 60.0, 84.2, 90.0, 135.0, -30.0, -100.0, 180.0,
    ];
    let mut out = Vec::new();
    for axis in 0..3 {
        for a in angles {
            out.push(axes_of(&rot(axis, a)));
        }
    }
    for a in [20.0, -35.0, 70.0] {
        for b in [15.0, -50.0, 110.0] {
            for c in [10.0, 40.0, -80.0] {
                out.push(axes_of(&mul(&mul(&rot(2, a), &rot(0, b)), &rot(1, c))));
            }
        }
    }
    // A gantry tilt keeps the slice axis along z while the rows tilt (not orthogonal).
    let t = 12f64.to_radians();
    out.push([[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, 1.0]]);
    out
}

pub async fn label_function() {
    let Some(b) = browser::start("viewer: orientation labels", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|_| {}).await;
    b.goto(&app.url("/")).await;
    let cases = cases();
    let got = b
        .client
        .execute_async(
            "const done = arguments[arguments.length - 1];
             import('/web/js/orient.js').then((m) => done(arguments[0].map((d) =>
               ['axial', 'coronal', 'sagittal'].map((p) => m.planeSides(p, d)))))
               .catch((e) => done(String(e)));",
            vec![json!(cases)],
        )
        .await
        .expect("the label function runs");
    let got: Vec<[[String; 4]; 3]> =
        serde_json::from_value(got.clone()).unwrap_or_else(|e| panic!("{e}: {got}"));
    assert_eq!(got.len(), cases.len());
    let mut combined = 0;
    for (d, shown) in cases.iter().zip(&got) {
        for (p, plane) in ["axial", "coronal", "sagittal"].iter().enumerate() {
            assert_eq!(shown[p], sides(plane, d), "{plane} of {d:?}");
            combined += shown[p].iter().filter(|l| l.len() > 1).count();
        }
    }
    assert!(
        combined > 100,
        "oblique cases give combined labels: {combined}"
    );

    // Named cases, as written on films: an axial image turned 45° about z (exact components, so the tie
    // keeps the order L/R, A/P, S/I) reads LA at the top and RP at the bottom, RA on the left and LP on the
    // right; one turned 30° reads AL on top; a 12° tilt
    // puts AS above and PI below; axis-aligned stays single letters.
    let named = |d: M3| {
        let d = json!(d);
        let b = &b;
        async move {
            let v = b
                .client
                .execute_async(
                    "const done = arguments[arguments.length - 1];
                     import('/web/js/orient.js').then((m) => done(['axial', 'coronal', 'sagittal']
                       .map((p) => m.planeSides(p, arguments[0]).join(' '))));",
                    vec![d],
                )
                .await
                .expect("labels");
            serde_json::from_value::<Vec<String>>(v).expect("strings")
        }
    };
    let s = std::f64::consts::FRAC_1_SQRT_2;
    assert_eq!(named(axes_of(&rot(2, 30.0))).await[0], "AL PR RA LP");
    let t = 12f64.to_radians();
    let tilt = named([[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, 1.0]]).await;
    assert_eq!(tilt, ["AS PI R L", "S I R L", "S I AS PI"]);
    assert_eq!(
        named([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).await,
        ["A P R L", "S I R L", "S I A P"]
    );
    assert_eq!(
        named([[s, s, 0.0], [-s, s, 0.0], [0.0, 0.0, 1.0]]).await[0],
        "LA RP RA LP"
    );
}

/// A small CT series of a ball with index axes `direction`; returns the series JSON.
async fn upload(app: &TestApp, direction: M3, name: &str) -> Value {
    // Centred on the patient's origin whatever the direction: origin = −Σ dir[a]·spacing[a]·(n[a] − 1)/2.
    let (spacing_mm, n) = ([2.0, 2.0, 3.0], [24.0, 24.0, 10.0]);
    let origin_mm = std::array::from_fn(|c| {
        -(0..3)
            .map(|a| direction[a][c] * spacing_mm[a] * (n[a] - 1.0) / 2.0)
            .sum::<f64>()
    });
    let frame = Frame {
        spacing_mm,
        origin_mm,
        direction,
    };
    let data = Array3::from_shape_fn((10, 24, 24), |(k, j, i)| {
        let p = frame.position(k as f64, j as f64, i as f64);
        let r = p.iter().map(|c| c * c).sum::<f64>().sqrt();
        if r < 12.0 { 400.0 } else { -1000.0 }
    });
    let meta = SeriesMeta {
        study_uid: Some("1.2.826.0.1.3680043.8.498.61".into()),
        frame_of_reference_uid: Some("1.2.826.0.1.3680043.8.498.62".into()),
        patient_id: Some("OBLIQUE".into()),
        series_description: name.into(),
        series_number: 7,
        ..Default::default()
    };
    let files = write_ct_series(&Volume { data, frame }, &meta)
        .expect("a CT series")
        .files;
    let r = app
        .client
        .post(app.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(write_zip(&files).expect("zip"))
        .send()
        .await
        .expect("upload");
    assert_eq!(r.status(), 201, "{name}");
    let v: Value = r.json().await.expect("json");
    assert_eq!(v["series"][0]["status"], "ready", "{name}: {v}");
    v["series"][0]["series"].clone()
}

pub async fn oblique_series() {
    let Some(b) = browser::start("viewer: oblique series labels", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|_| {}).await;
    let t = 12f64.to_radians();
    for (name, direction) in [
        ("turned 30 degrees about z", axes_of(&rot(2, 30.0))),
        (
            "tilted 12 degrees",
            [[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, 1.0]],
        ),
    ] {
        let series = upload(&app, direction, name).await;
        let id = series["id"].as_str().expect("id");
        // The truth from the direction the server assembled (it may reorder axes, never turn them).
        let d: M3 =
            serde_json::from_value(series["frame"]["direction"].clone()).expect("direction");
        b.goto(&app.url(&format!("/#/series/{id}"))).await;
        b.wait_for("#slice-panel[data-volume-loaded]", 60).await;
        let mut seen = Vec::new();
        for plane in ["axial", "coronal", "sagittal"] {
            let shown: Vec<String> = serde_json::from_value(
                b.js(
                    "const v = document.querySelector(`.view-${arguments[0]}`);
                     return ['top', 'bottom', 'left', 'right'].map((s) => v.querySelector(`.orient-${s}`).textContent);",
                    vec![json!(plane)],
                )
                .await,
            )
            .expect("labels");
            assert_eq!(
                shown,
                sides(plane, &d).to_vec(),
                "{name}: {plane} view, direction {d:?}"
            );
            seen.push(shown.join(" "));
        }
        assert!(
            seen.iter().any(|s| s.split(' ').any(|l| l.len() == 2)),
            "{name}: combined labels {seen:?}"
        );
        eprintln!("{name}: labels {seen:?}");
        b.shot(&format!(
            "series-oblique-{}",
            name.split(' ').next().unwrap_or("x")
        ))
        .await;
    }
}
