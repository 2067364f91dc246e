//! Helical CT over HTTP: a helical geometry simulated by `POST /v1/simulations`, reconstructed by an
//! `fdk` job (the helical weighted FBP), compared with the phantom.

use crate::common;

use common::{read_npy_f32, spawn_app};
use serde_json::{Value, json};

/// Four turns at pitch 1 of a 16-row detector (10.7 mm at the rotation axis, magnification 1.5) climb
/// from z = −21 to +21 mm: the 16 central slices of the grid are well inside the data's coverage, and the
/// helical FBP of the exact projections matches the phantom there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_helical_simulation_reconstructs_with_fdk_to_the_phantom() {
    let app = spawn_app().await;
    let geometry = json!({"type": "helical", "dso_mm": 400, "dsd_mm": 600, "pitch": 1.0, "turns": 4,
        "views_per_turn": 120, "z_start_mm": -21.33, "rotation": "cw",
        "detector": {"nu": 96, "nv": 16, "du_mm": 1.0, "dv_mm": 1.0}});
    let input = app.simulate(geometry, 28.0).await;
    let dataset: Value = app
        .get(&format!("/v1/datasets/{input}"))
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(dataset["geometry"]["type"], "helical", "{dataset}");
    let job = app
        .submit(
            &json!({"input": input, "algorithm": {"name": "fdk", "filter": "hann"},
            "grid": {"nx": 64, "ny": 64, "nz": 16, "spacing_mm": [1.0, 1.0, 1.0]},
            "outputs": ["volume", "metrics"]}),
        )
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["result"]["shape"], json!([16, 64, 64]));
    let m: Value = app
        .get(&format!("/v1/jobs/{id}/result/metrics"))
        .await
        .json()
        .await
        .unwrap();
    let rmse = m["rmse"].as_f64().unwrap();
    assert!(rmse < 0.06, "RMSE {rmse}: {m}");
    let r = app.get(&format!("/v1/jobs/{id}/result/volume.npy")).await;
    assert_eq!(r.status(), 200);
    let (shape, values) = read_npy_f32(&r.bytes().await.unwrap());
    assert_eq!(shape, [16, 64, 64]);
    let grid = ctrecon::recon::VolumeGrid {
        nx: 64,
        ny: 64,
        nz: 16,
        spacing_mm: [1.0, 1.0, 1.0],
        centre_mm: [0.0, 0.0, 0.0],
    };
    let truth = ctrecon::recon::phantom::Phantom3::from_table(
        ctrecon::recon::phantom::Table3::ModifiedSheppLogan,
        28.0,
    )
    .rasterize(&grid, 1);
    // Blocks of 2 × 2 × 2 voxels in the large uniform regions: the centre and either side of it.
    for (y0, x0) in [(31, 31), (31, 24), (40, 38)] {
        let (mut got, mut want) = (0.0f32, 0.0f32);
        for z in 7..9 {
            for y in y0..y0 + 2 {
                for x in x0..x0 + 2 {
                    got += values[(z * 64 + y) * 64 + x] / 8.0;
                    want += truth[[z, y, x]] / 8.0;
                }
            }
        }
        assert!(
            (got - want).abs() < 0.03,
            "block ({y0}, {x0}): {got}, phantom {want}"
        );
    }
    eprintln!("helical FBP 64²×16 vs phantom: {m}");
}
