//! Shaded surfaces against the range of the data: an iso-value above every value of the volume is refused at
//! submission with the mesh product's code, and one that a smoothing step pushed above the data is named in the
//! job's warnings.

use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;
use serde_json::json;

use super::common::{assert_problem, spawn_app};
use super::{decode, get, lit, upload, upload_files};

#[tokio::test]
async fn a_shaded_surface_above_the_data_is_refused_and_one_the_steps_pushed_above_is_warned_about()
{
    let app = spawn_app().await;
    let sid = upload(&app).await;
    // The balls reach 1000 HU (1000.0077 as stored). A product whose every surface is above that (in HU, or in
    // the volume's own units, HU here) would be empty: refused before any work, pointing at its first iso-value.
    for (surfaces, units, at) in [
        (json!([{"iso": 1200}]), "hu", "/products/0/surfaces/0/iso"),
        (
            json!([{"iso": 1000.5}, {"iso": 2000}]),
            "hu",
            "/products/0/surfaces/0/iso",
        ),
        (
            json!([{"iso": 3000}]),
            "native",
            "/products/0/surfaces/0/iso",
        ),
    ] {
        let r = app
            .post_json(
                "/v1/jobs",
                &json!({"kind": "volume", "input": sid, "products": [
                    {"type": "surface_render", "surfaces": surfaces, "units": units, "size": [32, 32]}]}),
            )
            .await;
        let p = assert_problem(r, 422, "iso_out_of_range").await;
        assert_eq!(p["errors"][0]["pointer"], at, "{p}");
        // The series keeps its values through a rescale: its maximum is 1000 HU within 0.01.
        let detail = p["detail"].as_str().unwrap();
        assert!(
            detail.contains("is above every value of the volume (at most 1000.0")
                && detail.ends_with(" HU): the surface would be empty"),
            "{p}"
        );
    }
    // A 32-bit float overflow is no iso-value.
    let r = app
        .post_json(
            "/v1/jobs",
            &json!({"kind": "volume", "input": sid, "products": [
                {"type": "surface_render", "surfaces": [{"iso": -1e39}], "size": [32, 32]}]}),
        )
        .await;
    assert_problem(r, 422, "invalid_parameter").await;
    // At the maximum the plateau of the big ball is inside: the ball shows, and nothing is said.
    let job = app
        .submit(&json!({"kind": "volume", "input": sid, "products": [
            {"type": "surface_render", "surfaces": [{"iso": 1000}], "size": [32, 32]}]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let said = done["result"]["warnings"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    assert!(
        said.iter().all(|w| w["code"] != "iso_out_of_range"),
        "{said:?}"
    );
    let png = get(
        &app,
        &format!("/v1/jobs/{id}/result/products/0"),
        "image/png",
    )
    .await;
    let (w, _, frames) = decode(&png);
    let (n, _) = lit(&frames[0], w, 0);
    // The plateau (r ≤ 30 mm of the ball) spans about 2 × 30 / 6.9 mm ≈ 9 pixels across: about 50 lit.
    assert!(n > 30, "{n} pixels");

    // A protocol's second surface above the data (bone on a volume without bone): the first still shows, the
    // job runs and names the missing one.
    let job = app
        .submit(&json!({"kind": "volume", "input": sid, "products": [
            {"type": "surface_render", "surfaces": [{"iso": 1000}, {"iso": 2000, "opacity": 0.5}],
             "size": [32, 32]}]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let said: Vec<String> = done["result"]["warnings"]
        .as_array()
        .cloned()
        .unwrap_or_default()
        .iter()
        .filter(|w| w["code"] == "iso_out_of_range")
        .map(|w| w["message"].as_str().unwrap_or_default().to_string())
        .collect();
    assert_eq!(said.len(), 1, "{said:?}");
    assert!(said[0].contains("`surfaces[1].iso` 2000"), "{said:?}");
    let png = get(
        &app,
        &format!("/v1/jobs/{id}/result/products/0"),
        "image/png",
    )
    .await;
    let (w, _, frames) = decode(&png);
    assert_eq!(lit(&frames[0], w, 0).0, n, "the same ball as alone");

    // One voxel of 1000 HU in air: the bound after a smoothing step is still 1000 HU, so 500 HU is accepted,
    // but smoothing spreads the voxel to below 0 HU and the surface does not appear. The job says so.
    let frame = Frame {
        spacing_mm: [3.0; 3],
        origin_mm: [-24.0; 3],
        direction: Frame::AXIS_ALIGNED,
    };
    let spike = Array3::from_shape_fn((17, 17, 17), |(k, j, i)| {
        if (k, j, i) == (8, 8, 8) {
            1000.0
        } else {
            -1000.0
        }
    });
    let files = write_ct_series(
        &Volume { data: spike, frame },
        &SeriesMeta {
            series_description: "spike".into(),
            ..Default::default()
        },
    )
    .unwrap()
    .files;
    let spike_id = upload_files(&app, files).await;
    let job = app
        .submit(&json!({"kind": "volume", "input": spike_id,
                        "steps": [{"op": "gaussian", "sigma_mm": 3.0}],
                        "products": [{"type": "surface_render", "surfaces": [{"iso": 500}], "size": [32, 32]}]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let max = done["result"]["max"].as_f64().unwrap();
    assert!(max < 0.0, "smoothed maximum {max} HU");
    let warnings: Vec<&serde_json::Value> = done["result"]["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|w| w["code"] == "iso_out_of_range")
        .collect();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert_eq!(warnings[0]["code"], "iso_out_of_range");
    let message = warnings[0]["message"].as_str().unwrap();
    assert!(
        message.contains("products[0]: `surfaces[0].iso` 500 is above every value of the volume"),
        "{message}"
    );
    let png = get(
        &app,
        &format!("/v1/jobs/{id}/result/products/0"),
        "image/png",
    )
    .await;
    let (w, _, frames) = decode(&png);
    assert_eq!(lit(&frames[0], w, 0).0, 0);
}
