//! What the LIDC journey checks on the views: the value under the cursor against the API's volume, window
//! changes against the window formula, the mesh against the API's triangle count; and the figures.

use std::time::Duration;

use fantoccini::actions::{InputSource, MouseActions, PointerAction};
use serde_json::{Value, json};

use super::browser::{Browser, decode_png};
use super::common::{TestApp, read_npy_f32};
use super::flow::{keys_to, pixel, right_drag, window, window_grey};

pub async fn slices_and_window(b: &Browser, app: &TestApp, token: &str, series: &str) {
    // The series itself in the viewer: axial slice 60, the pointer on the canvas.
    b.goto(&app.url(&format!("/#/series/{series}"))).await;
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    let axial = b.find(".view-axial").await;
    axial.send_keys(&keys_to(60)).await.expect("keys");
    b.until(
        "document.querySelector('.view-axial').dataset.index === '60'",
        10,
    )
    .await;
    let canvas = b.find(".view-axial canvas.image").await;
    let rect = b
        .js(
            "const r = document.querySelector('.view-axial canvas.image').getBoundingClientRect();
             const c = document.querySelector('.view-axial canvas.image');
             return [r.width, r.height, c.width, c.height];",
            vec![],
        )
        .await;
    let f = |k: usize| rect[k].as_f64().expect("number");
    let (dx, dy) = (-30.0, 20.0);
    let hover = MouseActions::new("mouse".into()).then(PointerAction::MoveToElement {
        element: canvas,
        duration: None,
        x: dx,
        y: dy,
    });
    b.client.perform_actions(hover).await.expect("hover");
    b.until(
        "document.querySelector('.view-axial .readout').dataset.value",
        10,
    )
    .await;
    let ro = ".view-axial .readout";
    let idx = |name: &'static str| async move {
        b.attr(ro, name)
            .await
            .expect("index")
            .parse::<usize>()
            .expect("usize")
    };
    let (i, j, k) = (
        idx("data-i").await,
        idx("data-j").await,
        idx("data-k").await,
    );
    assert_eq!(k, 60, "the axial view shows slice 60");
    // The pointer sits (dx, dy) CSS pixels from the canvas centre: that image pixel (±1 for rounding).
    let expect_i = ((f(0) / 2.0 + dx) / f(0) * f(2)).floor();
    let expect_j = ((f(1) / 2.0 + dy) / f(1) * f(3)).floor();
    assert!(
        (i as f64 - expect_i).abs() <= 1.0 && (j as f64 - expect_j).abs() <= 1.0,
        "pointer over pixel ({expect_i}, {expect_j}), readout says ({i}, {j})"
    );
    let shown: f32 = b
        .attr(ro, "data-value")
        .await
        .expect("value")
        .parse()
        .expect("f32");
    let npy = app
        .client
        .get(app.url(&format!("/v1/series/{series}/volume.npy")))
        .bearer_auth(token)
        .send()
        .await
        .expect("volume")
        .bytes()
        .await
        .expect("bytes");
    let (shape, data) = read_npy_f32(&npy);
    assert_eq!(shape, vec![133, 512, 512]);
    let truth = data[(k * shape[1] + j) * shape[2] + i];
    assert_eq!(
        shown, truth,
        "value under the cursor at voxel [{k}][{j}][{i}]"
    );
    let text = b.text(ro).await;
    assert!(text.contains("HU") && text.contains("LPS"), "{text}");
    b.shot("series-axial-60").await;

    // Window changes: the canvas pixel follows the window formula; presets and a right-drag.
    let mut sums = Vec::new();
    for preset in ["soft_tissue", "bone", "lung"] {
        b.js(
            "const s = document.getElementById('wl-preset'); s.value = arguments[0];
              s.dispatchEvent(new Event('change'));",
            vec![json!(preset)],
        )
        .await;
        let (ww, wl) = window(b).await;
        let want = window_grey(truth, ww, wl);
        b.until(
            &format!(
                "const c = document.querySelector('.view-axial canvas.image');
             return c.getContext('2d').getImageData({i}, {j}, 1, 1).data[0] === {want};"
            ),
            10,
        )
        .await;
        let (g, sum) = pixel(b, i, j).await;
        assert_eq!(g, want, "{preset}: W {ww} L {wl}, value {truth}");
        sums.push(sum);
    }
    assert_eq!((window(b).await), (1500.0, -600.0), "the lung preset");
    assert!(
        sums[0] != sums[1] && sums[1] != sums[2],
        "each window recolours the canvas: {sums:?}"
    );
    let before = window(b).await;
    right_drag(b, 60.0, -40.0).await;
    let after = window(b).await;
    assert!(
        after.0 > before.0 && after.1 > before.1,
        "right-drag widened and raised: {before:?} → {after:?}"
    );
    let want = window_grey(truth, after.0, after.1);
    b.until(
        &format!(
            "const c = document.querySelector('.view-axial canvas.image');
         return c.getContext('2d').getImageData({i}, {j}, 1, 1).data[0] === {want};"
        ),
        10,
    )
    .await;
    b.shot("series-window-drag").await;
}

/// Frames per second of `script`'s rAF loop over ~3 s (the script returns the count of frames).
async fn fps(b: &Browser, script: &str) -> f64 {
    let v = b
        .client
        .execute_async(script, vec![])
        .await
        .expect("measure");
    v.as_f64().unwrap_or(0.0)
}

pub async fn mesh_and_figures(b: &Browser, app: &TestApp, _token: &str, job: &Value) {
    let id = job["id"].as_str().expect("id");
    let products = job["result"]["products"].as_array().expect("products");
    let mesh = products
        .iter()
        .find(|p| p["type"] == "mesh")
        .expect("a mesh product");
    let triangles = mesh["mesh"]["triangles"].as_u64().expect("triangles");

    // Time to first slice: a fresh load of the finished job's page (not a hash change in the same page).
    b.goto("about:blank").await;
    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    let first = b.wait_for("#slice-panel[data-first-slice-ms]", 60).await;
    let first_ms = first
        .attr("data-first-slice-ms")
        .await
        .expect("attr")
        .unwrap_or_default();
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    let weight = b
        .js("const r = performance.getEntriesByType('resource').concat(performance.getEntriesByType('navigation'));
             const page = r.filter((e) => !e.name.includes('/v1/'));
             return [page.reduce((a, e) => a + (e.decodedBodySize || 0), 0), page.length];", vec![])
        .await;
    let scroll_fps = fps(b, "const done = arguments[arguments.length - 1];
        const v = document.querySelector('.view-axial'); const t0 = performance.now();
        const d0 = Number(v.dataset.draws); let dir = 1;
        const tick = () => {
          if (performance.now() - t0 > 3000) { done((Number(v.dataset.draws) - d0) / ((performance.now() - t0) / 1000)); return; }
          const i = Number(v.dataset.index); if (i > 120) dir = -1; if (i < 10) dir = 1;
          v.dispatchEvent(new WheelEvent('wheel', { deltaY: -dir, bubbles: true, cancelable: true }));
          requestAnimationFrame(tick);
        };
        requestAnimationFrame(tick);").await;

    // The mesh: drawn (non-background pixels) and the triangle count of the file equals the API's.
    b.find(".mesh-open")
        .await
        .click()
        .await
        .expect("open the mesh");
    let count = b.wait_for("#mesh-triangles[data-count]", 120).await;
    let shown = count
        .attr("data-count")
        .await
        .expect("attr")
        .expect("count");
    assert_eq!(
        shown.parse::<u64>().expect("u64"),
        triangles,
        "triangles shown vs the API's"
    );
    let api_shown = b.text(".mesh-api-triangles").await.replace(',', "");
    assert_eq!(api_shown, triangles.to_string());
    b.until(
        "Number(document.getElementById('mesh-canvas')?.dataset.frames || 0) > 3",
        60,
    )
    .await;
    b.js(
        "document.getElementById('mesh-canvas').scrollIntoView()",
        vec![],
    )
    .await;
    let png = b
        .find("#mesh-canvas")
        .await
        .screenshot()
        .await
        .expect("canvas screenshot");
    let (w, h, px) = decode_png(&png);
    let lit = px
        .chunks(4)
        .filter(|p| p[0] > 40 || p[1] > 40 || p[2] > 40)
        .count();
    let share = lit as f64 / f64::from(w * h);
    assert!(
        share > 0.02,
        "the mesh covers {:.1} % of the canvas",
        100.0 * share
    );
    b.shot("job-mesh").await;

    let canvas = b.find("#mesh-canvas").await;
    let f0: f64 = canvas
        .attr("data-frames")
        .await
        .expect("attr")
        .unwrap_or_default()
        .parse()
        .unwrap_or(0.0);
    let t0 = std::time::Instant::now();
    let mut drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: canvas.clone(),
            duration: None,
            x: 0.0,
            y: 0.0,
        })
        .then(PointerAction::Down {
            button: fantoccini::actions::MOUSE_BUTTON_LEFT,
        });
    for _ in 0..30 {
        drag = drag.then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(100)),
            x: 6.0,
            y: 1.0,
        });
    }
    drag = drag.then(PointerAction::Up {
        button: fantoccini::actions::MOUSE_BUTTON_LEFT,
    });
    b.client.perform_actions(drag).await.expect("rotate");
    let f1: f64 = canvas
        .attr("data-frames")
        .await
        .expect("attr")
        .unwrap_or_default()
        .parse()
        .unwrap_or(0.0);
    let rotate_fps = (f1 - f0) / t0.elapsed().as_secs_f64();
    b.shot("job-mesh-rotated").await;

    // The clipping plane cuts the mesh: fewer lit pixels with the axial plane half-way.
    let lit_pixels = |png: Vec<u8>| {
        let (_, _, px) = decode_png(&png);
        px.chunks(4)
            .filter(|p| p[0] > 40 || p[1] > 40 || p[2] > 40)
            .count()
    };
    let whole = lit_pixels(
        b.find("#mesh-canvas")
            .await
            .screenshot()
            .await
            .expect("shot"),
    );
    b.js(
        "const s = document.getElementById('clip-axis'); s.value = 'z'; s.dispatchEvent(new Event('change'));",
        vec![],
    )
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let clipped = lit_pixels(
        b.find("#mesh-canvas")
            .await
            .screenshot()
            .await
            .expect("shot"),
    );
    assert!(
        clipped < whole * 9 / 10,
        "clipping removes part of the mesh: {clipped} vs {whole} lit pixels"
    );
    b.shot("job-mesh-clipped").await;

    // The jobs list shows the job as succeeded; a tablet-width layout of the job page.
    b.goto(&app.url("/#/jobs")).await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{id}'] [data-status=succeeded]"),
        30,
    )
    .await;
    b.shot("jobs-list").await;
    b.client.set_window_size(820, 1180).await.expect("resize");
    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    b.shot("job-tablet").await;

    eprintln!(
        "FIGURES viewer: first slice {first_ms} ms after opening the finished job; page weight {} bytes in {} files; \
         scrolling {scroll_fps:.1} slices/s; mesh of {triangles} triangles rotating at {rotate_fps:.1} frames/s",
        weight[0], weight[1]
    );
}
