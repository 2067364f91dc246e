//! The window the viewer opens with, chosen from the data as clinical viewers do: CT series of a chest
//! (lungs), a head (skull around brain, no fat), an abdomen (soft tissue and fat) and a bone block open in
//! the lung, brain, soft-tissue and bone presets, with the preset's width and level; a reconstruction of a
//! phantom in arbitrary units opens in the 0.5–99.5 % window instead.

use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;
use serde_json::json;

use super::browser::{self, Browser};
use super::common::{TestApp, parallel_geometry, spawn_app_with};

const N: usize = 48;

/// An 8-slice CT series of `N`² voxels of 1 mm whose value at (x, y) in mm from the centre is `hu`.
fn series(name: &str, number: i32, hu: impl Fn(f64, f64) -> f32) -> Vec<(String, Vec<u8>)> {
    let frame = Frame {
        origin_mm: [-23.5, -23.5, 0.0],
        spacing_mm: [1.0, 1.0, 2.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let c = (N as f64 - 1.0) / 2.0;
    let data = Array3::from_shape_fn((8, N, N), |(_, j, i)| hu(i as f64 - c, j as f64 - c));
    let meta = SeriesMeta {
        study_uid: Some(format!("1.2.826.0.1.3680043.8.498.80.{number}")),
        frame_of_reference_uid: Some(format!("1.2.826.0.1.3680043.8.498.81.{number}")),
        patient_id: Some(format!("WINDOW{number}")),
        series_description: name.into(),
        series_number: number,
        ..Default::default()
    };
    write_ct_series(&Volume { data, frame }, &meta)
        .expect("a CT series")
        .files
        .into_iter()
        .map(|(n, b)| (format!("{name}/{n}"), b))
        .collect()
}

fn chest(x: f64, y: f64) -> f32 {
    let body = (x / 22.0).powi(2) + (y / 16.0).powi(2) < 1.0;
    let lung = ((x.abs() - 10.0) / 7.5).powi(2) + (y / 11.0).powi(2) < 1.0;
    match (body, lung) {
        (true, true) => -850.0,
        (true, false) => 40.0,
        _ => -1000.0,
    }
}

fn head(x: f64, y: f64) -> f32 {
    let r = (x * x + y * y).sqrt();
    if r < 17.0 {
        35.0
    } else if r < 20.0 {
        1000.0
    } else {
        -1000.0
    }
}

fn abdomen(x: f64, y: f64) -> f32 {
    let e = (x / 22.0).powi(2) + (y / 18.0).powi(2);
    if e < 0.6 {
        55.0
    } else if e < 1.0 {
        -100.0
    } else {
        -1000.0
    }
}

fn bone(x: f64, y: f64) -> f32 {
    if x.abs() < 20.0 && y.abs() < 20.0 {
        700.0 + 2.0 * x as f32
    } else {
        -1000.0
    }
}

async fn upload(app: &TestApp, files: &[(String, Vec<u8>)]) -> String {
    let r = app
        .client
        .post(app.url("/v1/series"))
        .bearer_auth(super::TOKEN)
        .header("content-type", "application/zip")
        .body(write_zip(files).expect("zip"))
        .send()
        .await
        .expect("upload");
    assert_eq!(r.status(), 201);
    let v: serde_json::Value = r.json().await.expect("json");
    v["series"][0]["series"]["id"]
        .as_str()
        .expect("series id")
        .to_string()
}

/// Open `hash` and wait for the slice viewer's default window; returns (preset, ww, wl).
async fn opened_with(b: &Browser, app: &TestApp, hash: &str) -> (String, f64, f64) {
    b.goto(&app.url(&format!("/{hash}"))).await;
    b.until(
        "return document.querySelector('#slice-panel[data-preset][data-ww]') !== null",
        30,
    )
    .await;
    let preset = b
        .attr("#slice-panel", "data-preset")
        .await
        .expect("data-preset");
    let (ww, wl) = super::flow::window(b).await;
    (preset, ww, wl)
}

pub async fn default_window_from_the_data() {
    let Some(b) = browser::start("viewer: default window from the data", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|s| s.api_tokens = vec![super::TOKEN.into()]).await;
    b.goto(&app.url("/")).await;
    b.js(
        "sessionStorage.setItem('ctrecon.token', arguments[0]);",
        vec![json!(super::TOKEN)],
    )
    .await;
    // (series, HU of a voxel, preset expected, window width, window level)
    type Case = (&'static str, fn(f64, f64) -> f32, &'static str, f64, f64);
    let cases: [Case; 4] = [
        ("chest", chest, "lung", 1500.0, -600.0),
        ("head", head, "brain", 80.0, 40.0),
        ("abdomen", abdomen, "soft_tissue", 400.0, 40.0),
        ("bone", bone, "bone", 2500.0, 480.0),
    ];
    for (k, (name, hu, want, ww, wl)) in cases.into_iter().enumerate() {
        let id = upload(&app, &series(name, 10 + k as i32, hu)).await;
        let (preset, got_ww, got_wl) = opened_with(&b, &app, &format!("#/series/{id}")).await;
        assert_eq!(preset, want, "{name}");
        assert!(
            (got_ww - ww).abs() < 1e-6 && (got_wl - wl).abs() < 1e-6,
            "{name}: W {got_ww} L {got_wl}, the {want} preset is W {ww} L {wl}"
        );
        let menu = b
            .js("return document.getElementById('wl-preset').value;", vec![])
            .await;
        assert_eq!(menu, json!(want), "{name}: the menu shows the preset");
        b.shot(&format!("window-default-{name}")).await;
    }

    // A phantom reconstructed in arbitrary units is no CT of matter: the 0.5–99.5 % window.
    let auth = |r: reqwest::RequestBuilder| r.bearer_auth(super::TOKEN);
    let sim: serde_json::Value = auth(app.client.post(app.url("/v1/simulations")))
        .json(
            &json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 28},
                      "geometry": parallel_geometry(90, 64, 1.0)}),
        )
        .send()
        .await
        .expect("simulate")
        .json()
        .await
        .expect("json");
    let job: serde_json::Value = auth(app.client.post(app.url("/v1/jobs")))
        .json(&json!({"input": sim["id"], "algorithm": {"name": "fbp"},
                      "grid": {"nx": 48, "ny": 48, "dx_mm": 1.25, "dy_mm": 1.25}}))
        .send()
        .await
        .expect("submit")
        .json()
        .await
        .expect("json");
    let id = job["id"].as_str().expect("job id");
    let (preset, _, _) = opened_with(&b, &app, &format!("#/job/{id}")).await;
    assert_eq!(preset, "auto");
}
