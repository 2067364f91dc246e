//! Over HTTP: iso-values above the data refused, and what a surface could not honour said by stable codes, in
//! the mesh product's `mesh.warnings` and in the mesh view's `X-Ctrecon-Warnings` header.

use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::volume::Volume;
use serde_json::json;

use super::common::{self, assert_problem, spawn_app, weld_stl};
use super::hu_torus;

/// Upload `vol` as a CT series (multipart, one part per file); returns the series JSON.
async fn upload_series(app: &common::TestApp, vol: &Volume) -> serde_json::Value {
    let meta = SeriesMeta {
        series_description: "torus".into(),
        ..Default::default()
    };
    let files = write_ct_series(vol, &meta).unwrap().files;
    let form = files
        .into_iter()
        .fold(reqwest::multipart::Form::new(), |f, (name, bytes)| {
            f.part(
                "file",
                reqwest::multipart::Part::bytes(bytes)
                    .file_name(name)
                    .mime_str("application/dicom")
                    .unwrap(),
            )
        });
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let v: serde_json::Value = r.json().await.unwrap();
    v["series"][0]["series"].clone()
}

#[tokio::test]
async fn an_iso_value_above_the_data_is_refused_and_unmet_requests_are_warned_about() {
    let app = spawn_app().await;
    let series = upload_series(&app, &hu_torus(14.0, 8.0, [48, 48, 24])).await;
    let sid = series["id"].as_str().unwrap().to_string();
    let max = series["hu_max"].as_f64().unwrap();
    assert!(max > 500.0 && max <= 1000.5, "{series}");
    let above = max + 10.0;

    // Above the maximum: refused at submission, with or without a smoothing step (which cannot raise it).
    for steps in [json!([]), json!([{"op": "gaussian", "sigma_mm": 1.0}])] {
        let r = app
            .post_json(
                "/v1/jobs",
                &json!({"kind": "volume", "input": sid, "steps": steps,
                                            "products": [{"type": "mesh", "iso": above}]}),
            )
            .await;
        let p = assert_problem(r, 422, "iso_out_of_range").await;
        assert!(p["detail"].as_str().unwrap().contains("products[0]"), "{p}");
    }

    // The torus at 0 HU (half the tube radius): closed, manifold, χ = 0 after decimation; four triangles
    // cannot be reached and that is said.
    let v = app
        .submit(&json!({"kind": "volume", "input": sid,
                        "products": [{"type": "mesh", "iso": 0, "target_triangles": 4}]}))
        .await;
    let id = v["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let mesh = &done["result"]["products"][0]["mesh"];
    let n = mesh["triangles"].as_u64().unwrap();
    assert!(n >= 14, "{mesh}");
    assert_eq!(
        (mesh["closed"].as_bool(), mesh["manifold"].as_bool()),
        (Some(true), Some(true)),
        "{mesh}"
    );
    assert_eq!(mesh["euler_characteristic"], 0, "{mesh}");
    assert_eq!(mesh["warnings"][0]["code"], "target_triangles_not_reached");
    let warning = mesh["warnings"][0]["message"].as_str().unwrap();
    assert!(
        warning.contains("target_triangles 4 not reached")
            && warning.contains(&format!("{n} triangles")),
        "{warning}"
    );
    // The view of that result refuses an iso-value above its data too.
    let r = app
        .get(&format!("/v1/jobs/{id}/result/mesh.stl?iso={above}"))
        .await;
    assert_problem(r, 422, "iso_out_of_range").await;
    let r = app
        .get(&format!("/v1/jobs/{id}/result/mesh.stl?iso=0"))
        .await;
    assert_eq!(r.status(), 200);

    // At the maximum, after smoothing lowered the ridge: accepted, and the empty surface says why.
    let v = app
        .submit(&json!({"kind": "volume", "input": sid,
                        "steps": [{"op": "gaussian", "sigma_mm": 1.5}],
                        "products": [{"type": "mesh", "iso": max}]}))
        .await;
    let done = app.finish(v["id"].as_str().unwrap()).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let product = &done["result"]["products"][0];
    assert_eq!(product["mesh"]["triangles"], 0, "{product}");
    assert_eq!(product["file"]["bytes"], 84);
    assert_eq!(product["mesh"]["closed"], false);
    assert_eq!(product["mesh"]["warnings"][0]["code"], "empty_surface");
    assert!(
        product["mesh"]["warnings"][0]["message"]
            .as_str()
            .unwrap()
            .contains("is empty"),
        "{product}"
    );
}

/// The warning codes of a response, in order.
fn warning_codes(r: &reqwest::Response) -> Vec<String> {
    r.headers()
        .get("x-ctrecon-warnings")
        .map(|v| {
            v.to_str()
                .unwrap()
                .split(',')
                .map(|c| c.trim().to_string())
                .collect()
        })
        .unwrap_or_default()
}

#[tokio::test]
async fn the_mesh_view_names_an_unreached_target_and_an_empty_surface_in_a_header() {
    let app = spawn_app().await;
    let series = upload_series(&app, &hu_torus(14.0, 8.0, [48, 48, 24])).await;
    let v = app
        .submit(&json!({"kind": "volume", "input": series["id"],
                        "products": [{"type": "mesh", "iso": 0, "target_triangles": 4}]}))
        .await;
    let id = v["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let reached = done["result"]["products"][0]["mesh"]["triangles"]
        .as_u64()
        .unwrap();

    // A torus cannot go down to 4 triangles: the view stops where the product stopped, and says so, on the
    // first answer, on the cached one and on a 304.
    let url = format!("/v1/jobs/{id}/result/mesh.stl?iso=0&target_triangles=4");
    let r = app.get(&url).await;
    assert_eq!(r.status(), 200);
    assert_eq!(warning_codes(&r), ["target_triangles_not_reached"]);
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    let stl = r.bytes().await.unwrap();
    // Welded by position, as a slicer reads it: the torus the product reached, a closed manifold.
    let welded = weld_stl(&stl);
    assert_eq!(welded.triangle_count() as u64, reached);
    assert!(reached >= 14, "{reached}");
    let t = welded.topology();
    assert!(
        t.closed && t.manifold && t.euler_characteristic == 0,
        "{t:?}"
    );
    let again = app.get(&url).await;
    assert_eq!(warning_codes(&again), ["target_triangles_not_reached"]);
    assert_eq!(again.bytes().await.unwrap(), stl);
    let r = app
        .client
        .get(app.url(&url))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    assert_eq!(warning_codes(&r), ["target_triangles_not_reached"]);

    // A reachable target and no target: nothing to say.
    for query in ["iso=0&target_triangles=400", "iso=0"] {
        let r = app
            .get(&format!("/v1/jobs/{id}/result/mesh.stl?{query}"))
            .await;
        assert_eq!(r.status(), 200);
        assert!(r.headers().get("x-ctrecon-warnings").is_none(), "{query}");
        let n = weld_stl(&r.bytes().await.unwrap()).triangle_count();
        assert!(n > 14 && (query == "iso=0" || n <= 400), "{query}: {n}");
    }

    // An iso-value within the data, but a clip that keeps only the space above the volume: an empty STL with a
    // 200, and the header says the surface is empty.
    let clip: String = json!({"planes": [{"point_mm": [0, 0, 1000], "normal": [0, 0, 1]}]})
        .to_string()
        .bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'_' | b'.' | b'-' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect();
    let r = app
        .get(&format!("/v1/jobs/{id}/result/mesh.stl?iso=0&clip={clip}"))
        .await;
    assert_eq!(r.status(), 200);
    assert_eq!(warning_codes(&r), ["empty_surface"]);
    assert_eq!(r.bytes().await.unwrap().len(), 84);
}
