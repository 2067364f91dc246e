//! Patient orientation over HTTP: one synthetic patient with three cube markers at known LPS points, written
//! as CT series in every acquisition (head-first and feet-first, supine and prone, rows, columns and slices
//! stored in reverse, coronal and sagittal images, a gantry tilt). Every slice and projection view and every
//! product (projections, thin and slab MPR series, an oblique and a curved MPR, a rotating projection, volume
//! and surface renderings, the derived CT series) must show each marker where its LPS point and the
//! radiological display convention put it, the same for every acquisition, and say so in its JSON, its PNG
//! text chunks and its DICOM attributes.
//!
//! `phantom`: the patient and its acquisitions; `geometry`: where a point appears on screen, from the
//! documented conventions; `products`: the products of a job and what each must show; `images`, `dicom`:
//! reading the outputs; `checks`: what every acquisition goes through; `tilted`: the gantry-tilted series.

use crate::common;

mod checks;
mod dicom;
mod geometry;
mod images;
mod phantom;
mod products;
mod tilted;

use common::{TestApp, read_npy_f32, spawn_app};
use serde_json::{Value, json};

use checks::{AXES, Seen, check_export, check_products, check_views};
use images::{get_bytes, npy, png_json};
use phantom::{N, O, acquisition, acquisitions, upload};
use products::{Product, products};

/// Run a volume job with `products` on the series; returns the job JSON once it succeeded.
async fn volume_job(app: &TestApp, series: &str, products: &[Value]) -> Value {
    let job = app
        .submit(&json!({"kind": "volume", "input": series, "steps": [], "products": products}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    done
}

/// One acquisition through every check; what it showed.
async fn acquisition_seen(
    app: &TestApp,
    list: &[Product],
    (name, direction, reverse): (&'static str, [[f64; 3]; 3], bool),
) -> Seen {
    let vol = acquisition(direction);
    let series = upload(app, &vol, name, reverse).await;
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
    let specs: Vec<Value> = list.iter().map(|p| p.spec.clone()).collect();
    let job = volume_job(app, series["id"].as_str().unwrap(), &specs).await;
    let id = job["id"].as_str().unwrap();
    let mut seen = Seen::default();
    check_views(app, id, name, &mut seen).await;
    check_products(app, &job, list, name, &mut seen).await;
    // The derived CT series of the volume.
    let zip = get_bytes(app, &format!("/v1/jobs/{id}/result/series.zip")).await;
    dicom::assert_volume_series(&dicom::unzip(&zip), &format!("{name}: series.zip"));
    check_export(app, &job, list, name).await;
    seen
}

#[tokio::test]
async fn every_acquisition_shows_each_marker_at_the_same_screen_pixel() {
    let app = spawn_app().await;
    let list = products();
    // Every acquisition at once: the requests mostly wait for the server's writes.
    let all = futures_util::future::join_all(
        acquisitions()
            .into_iter()
            .map(|a| acquisition_seen(&app, &list, a)),
    )
    .await;
    let names: Vec<&str> = acquisitions().iter().map(|a| a.0).collect();
    let (want, others) = all.split_first().unwrap();
    // The projection products are the projection views.
    for (p, axis) in AXES.iter().enumerate() {
        let view = want.grey.iter().find(|(path, _)| {
            path.contains("/projection?") && path.contains(&format!("axis={axis}"))
        });
        let product = want
            .grey
            .iter()
            .find(|(path, _)| path.ends_with(&format!("/products/{p}")));
        let (Some(view), Some(product)) = (view, product) else {
            panic!("missing outputs")
        };
        assert_eq!(view.1.data, product.1.data, "{axis}");
    }
    // Every acquisition shows what head-first supine shows.
    for (name, seen) in names[1..].iter().zip(others) {
        assert_eq!(seen.grey.len(), want.grey.len());
        for ((path, got), (_, w)) in seen.grey.iter().zip(&want.grey) {
            assert_eq!(
                (got.frames, got.rows, got.cols),
                (w.frames, w.rows, w.cols),
                "{name}: {path}"
            );
            let worst = got
                .data
                .iter()
                .zip(&w.data)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-3, "{name}: {path} differs by {worst}");
        }
        assert_eq!(seen.renders.len(), want.renders.len());
        for ((path, got), (_, w)) in seen.renders.iter().zip(&want.renders) {
            for (a, b) in got.iter().zip(w) {
                assert!(
                    (a.0 - b.0).abs() < 0.5 && (a.1 - b.1).abs() < 0.5,
                    "{name}: {path}: {got:?} vs {w:?}"
                );
            }
        }
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
        let img = npy(&app, &format!("/v1/jobs/{id}/result/slice?format=npy")).await;
        // Without a patient the image is the array as stored.
        assert_eq!(img.data, vol, "{convention}");
        let png = get_bytes(&app, &format!("/v1/jobs/{id}/result/slice")).await;
        let o = png_json(&png, "Orientation");
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
