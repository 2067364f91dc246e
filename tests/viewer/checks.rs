//! What the LIDC journey checks on the views: the value under the cursor against the API's volume, window
//! changes against the window formula, the three planes (readouts, positions, crosshairs, scale bars, wheel;
//! see `planes`), the rotating MIP played as a loop, the mesh against the API's triangle count, area and
//! volume, every download, the tablet width and keyboard use; and the figures.

use std::time::Duration;

use fantoccini::actions::{InputSource, MouseActions, PointerAction};
use serde_json::{Value, json};

use super::browser::{Browser, decode_png};
use super::common::{TestApp, read_npy_f32};
use super::flow::{api_json, keys_to, pixel, right_drag, window, window_grey};
use super::planes::{Series, planes, scale_bars, wheel};
use super::ui::{fits_the_window, press, tab_to};

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

    // The three planes against the series' frame and volume, then the wheel.
    let info = api_json(app, token, &format!("/v1/series/{series}")).await;
    let s = Series::new(&info["frame"], &shape, &data);
    planes(b, &s).await;
    wheel(b, "axial").await;
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

/// Bytes of the page's own files fetched so far (not the API's answers): as received (gzip where the
/// server sent it so) and unpacked, and how many files.
async fn page_weight(b: &Browser) -> (u64, u64, u64) {
    let v = b
        .js(
            "const r = performance.getEntriesByType('resource').concat(performance.getEntriesByType('navigation'))
               .filter((e) => !e.name.includes('/v1/') && !e.name.includes('/healthz'));
             return [r.reduce((a, e) => a + (e.encodedBodySize || 0), 0),
                     r.reduce((a, e) => a + (e.decodedBodySize || 0), 0), r.length];",
            vec![],
        )
        .await;
    serde_json::from_value::<(u64, u64, u64)>(v).expect("numbers")
}

/// A number shown with thousands separators and a unit (`376,488.4 mm²`).
fn shown_number(text: &str) -> f64 {
    text.split_whitespace()
        .next()
        .map(|n| n.replace(',', ""))
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no number in {text:?}"))
}

/// The mesh: drawn (non-background pixels), the triangle count of the file and the area and volume shown
/// equal the API's; it turns under the mouse (the frame rate of that is returned) and the clipping plane
/// cuts it.
async fn mesh(b: &Browser, mesh: &Value) -> f64 {
    let triangles = mesh["mesh"]["triangles"].as_u64().expect("triangles");
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
    // Area and enclosed volume as the API measured them, to the 0.1 shown.
    for (css, key) in [(".mesh-area", "area_mm2"), (".mesh-volume", "volume_mm3")] {
        let want = mesh["mesh"][key].as_f64().expect("a measure");
        let text = b.text(css).await;
        assert!(
            (shown_number(&text) - want).abs() <= 0.05 + 1e-9 * want,
            "{key}: {want} from the API, {text:?} shown"
        );
    }
    // Drawn on demand: the first frame once loaded.
    b.until(
        "Number(document.getElementById('mesh-canvas')?.dataset.frames || 0) >= 1",
        60,
    )
    .await;
    b.js(
        "document.getElementById('mesh-canvas').scrollIntoView()",
        vec![],
    )
    .await;
    let lit_pixels = |png: Vec<u8>| {
        let (w, h, px) = decode_png(&png);
        let lit = px
            .chunks(4)
            .filter(|p| p[0] > 40 || p[1] > 40 || p[2] > 40)
            .count();
        (lit, w * h)
    };
    let (lit, all) = lit_pixels(
        b.find("#mesh-canvas")
            .await
            .screenshot()
            .await
            .expect("canvas screenshot"),
    );
    let share = lit as f64 / f64::from(all);
    assert!(
        share > 0.02,
        "the mesh covers {:.1} % of the canvas",
        100.0 * share
    );
    b.shot("job-mesh").await;

    // Turning it: frames drawn per second of dragging (one frame per pointer move at most).
    let canvas = b.find("#mesh-canvas").await;
    let frames = |c: &fantoccini::elements::Element| {
        let c = c.clone();
        async move {
            c.attr("data-frames")
                .await
                .expect("attr")
                .unwrap_or_default()
                .parse::<f64>()
                .unwrap_or(0.0)
        }
    };
    let f0 = frames(&canvas).await;
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
    for _ in 0..40 {
        drag = drag.then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(25)),
            x: 5.0,
            y: 1.0,
        });
    }
    drag = drag.then(PointerAction::Up {
        button: fantoccini::actions::MOUSE_BUTTON_LEFT,
    });
    b.client.perform_actions(drag).await.expect("rotate");
    let turned = frames(&canvas).await - f0;
    let rotate_fps = turned / t0.elapsed().as_secs_f64();
    assert!(
        turned >= 2.0,
        "the mesh is drawn again as it turns: {turned} frames"
    );
    let (turned_lit, _) = lit_pixels(
        b.find("#mesh-canvas")
            .await
            .screenshot()
            .await
            .expect("shot"),
    );
    assert!(turned_lit != lit, "the turned mesh looks different");
    b.shot("job-mesh-rotated").await;

    // The clipping plane cuts the mesh: fewer lit pixels with the axial plane half-way.
    let drawn = frames(&canvas).await;
    b.js(
        "const s = document.getElementById('clip-axis'); s.value = 'z'; s.dispatchEvent(new Event('change'));",
        vec![],
    )
    .await;
    b.until(
        &format!("Number(document.getElementById('mesh-canvas').dataset.frames) > {drawn}"),
        30,
    )
    .await;
    let (clipped, _) = lit_pixels(
        b.find("#mesh-canvas")
            .await
            .screenshot()
            .await
            .expect("shot"),
    );
    assert!(
        clipped < turned_lit * 9 / 10,
        "clipping removes part of the mesh: {clipped} vs {turned_lit} lit pixels"
    );
    b.shot("job-mesh-clipped").await;
    rotate_fps
}

pub async fn mesh_and_figures(b: &Browser, app: &TestApp, token: &str, job: &Value) {
    let id = job["id"].as_str().expect("id");
    let products = job["result"]["products"].as_array().expect("products");
    let index_of = |t: &str| {
        products
            .iter()
            .position(|p| p["type"] == t)
            .unwrap_or_else(|| panic!("a {t} product"))
    };
    let triangles = products[index_of("mesh")]["mesh"]["triangles"]
        .as_u64()
        .expect("triangles");

    // Time to first slice and page load: a fresh load of the finished job's page (not a hash change).
    b.goto("about:blank").await;
    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    let first = b.wait_for("#slice-panel[data-first-slice-ms]", 60).await;
    // The middle slice came with the header (its offset foreseen from the job's result shape), not after it.
    assert_eq!(
        first
            .attr("data-first-slice-early")
            .await
            .expect("attr")
            .as_deref(),
        Some("true"),
        "the first slice waited for the header"
    );
    let first_ms: f64 = first
        .attr("data-first-slice-ms")
        .await
        .expect("attr")
        .unwrap_or_default()
        .parse()
        .expect("ms");
    let load = b
        .until(
            "const n = performance.getEntriesByType('navigation')[0];
             return n && n.loadEventEnd > 0 ? [n.domContentLoadedEventEnd, n.loadEventEnd] : null;",
            30,
        )
        .await;
    let (ready_ms, load_ms) = (load[0].as_f64().expect("ms"), load[1].as_f64().expect("ms"));
    // Where the first slice's time goes: every request the page made before it, in ms since navigation.
    let timeline = b
        .js(
            "const first = Number(arguments[0]);
             return performance.getEntriesByType('resource')
               .filter((r) => r.startTime < first)
               .map((r) => `${new URL(r.name).pathname.replace(/[0-9a-f-]{36}/, '{id}')} ${r.startTime.toFixed(0)}–${r.responseEnd.toFixed(0)}`)
               .join(', ');",
            vec![serde_json::json!(first_ms)],
        )
        .await;
    // Loose bounds that hold on a loaded machine but not on a broken page (the figures are below).
    assert!(load_ms < 5000.0, "page load took {load_ms} ms");
    assert!(first_ms < 5000.0, "the first slice took {first_ms} ms");
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    let (page_gz, page_raw, page_files) = page_weight(b).await;
    let scroll_fps = fps(b, "const done = arguments[arguments.length - 1];
        const v = document.querySelector('.view-axial'); const t0 = performance.now();
        const d0 = Number(v.dataset.draws); let dir = 1;
        const tick = () => {
          if (performance.now() - t0 > 3000) { done((Number(v.dataset.draws) - d0) / ((performance.now() - t0) / 1000)); return; }
          const i = Number(v.dataset.index); if (i > 120) dir = -1; if (i < 10) dir = 1;
          v.dispatchEvent(new WheelEvent('wheel', { deltaY: -100 * dir, bubbles: true, cancelable: true }));
          requestAnimationFrame(tick);
        };
        requestAnimationFrame(tick);").await;
    assert!(
        scroll_fps > 1.0,
        "scrolling draws: {scroll_fps:.1} slices/s"
    );

    // The rotating MIP plays as a loop; its paused frame is the API's.
    super::stacks::plays(b, app, Some(token), id, index_of("rotating")).await;
    b.shot("job-rotating-mip").await;

    let rotate_fps = mesh(b, &products[index_of("mesh")]).await;
    let (all_gz, all_raw, all_files) = page_weight(b).await;

    super::downloads::every_download_answers(b, app, token, job).await;

    // The jobs list shows the job as succeeded.
    b.goto(&app.url("/#/jobs")).await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{id}'] [data-status=succeeded]"),
        30,
    )
    .await;
    b.shot("jobs-list").await;

    // A tablet's width: nothing wider than the window, the controls shown whole; the scale bars follow the
    // smaller zoom; Tab reaches the slice view, whose keys move the slice.
    b.client.set_window_size(820, 1180).await.expect("resize");
    fits_the_window(
        b,
        "jobs list at 820 px",
        &[
            "#nav-jobs",
            "#nav-send",
            "#token-input",
            "#filter-status",
            "#filter-kind",
        ],
    )
    .await;
    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    b.wait_for(".product[data-type=rotating][data-frame]", 60)
        .await;
    fits_the_window(
        b,
        "job page at 820 px",
        &[
            "#nav-jobs",
            "#nav-send",
            "#token-input",
            "#job-delete",
            "#wl-preset",
            "#wl-width",
            ".view-axial canvas.image",
            ".view-coronal canvas.image",
            ".view-sagittal canvas.image",
            ".mesh-open",
            ".product[data-type=rotating] button.play",
            "#downloads",
        ],
    )
    .await;
    // Two views side by side at this width (the layout follows the width the views get).
    let beside = b
        .js(
            "const a = document.querySelector('.view-axial').getBoundingClientRect();
             const c = document.querySelector('.view-coronal').getBoundingClientRect();
             return Math.abs(a.top - c.top) < 1 && c.left > a.right;",
            vec![],
        )
        .await;
    assert_eq!(
        beside,
        json!(true),
        "axial and coronal side by side at 820 px"
    );
    let frame = &job["result"]["frame"];
    let shape: Vec<usize> = serde_json::from_value(job["result"]["shape"].clone()).expect("shape");
    let spacing: [f64; 3] = serde_json::from_value(frame["spacing_mm"].clone()).expect("spacing");
    scale_bars(b, spacing, [shape[2], shape[1], shape[0]], "820 × 1180").await;
    b.shot("job-tablet").await;
    let presses = tab_to(b, ".view-axial", 80).await;
    let before: usize = b
        .attr(".view-axial", "data-index")
        .await
        .expect("index")
        .parse()
        .expect("a number");
    press(b, char::from(fantoccini::key::Key::Up)).await;
    b.until(
        &format!(
            "document.querySelector('.view-axial').dataset.index === '{}'",
            before + 1
        ),
        10,
    )
    .await;
    press(b, char::from(fantoccini::key::Key::PageDown)).await;
    b.until(
        &format!(
            "document.querySelector('.view-axial').dataset.index === '{}'",
            before - 9
        ),
        10,
    )
    .await;
    eprintln!(
        "keyboard: Tab reached the axial view in {presses} presses; Up and Page Down moved it {before} → {} → {}",
        before + 1,
        before - 9
    );
    b.goto(&app.url("/#/send")).await;
    b.wait_for("#phantom-form", 20).await;
    fits_the_window(
        b,
        "send page at 820 px",
        &["#dropzone", "#phantom-form button[type=submit]"],
    )
    .await;

    eprintln!(
        "FIGURES viewer: page load {load_ms:.0} ms (DOMContentLoaded {ready_ms:.0} ms); first slice {first_ms:.0} ms \
         after opening the finished job; page {page_raw} bytes in {page_files} files ({page_gz} sent), \
         {all_raw} bytes in {all_files} files with three.js ({all_gz} sent); scrolling {scroll_fps:.1} slices/s; \
         mesh of {triangles} triangles turning at {rotate_fps:.1} frames/s"
    );
    eprintln!(
        "FIGURES viewer first slice: requests before it (ms since navigation, start–end): {}",
        timeline.as_str().unwrap_or_default()
    );
}
