//! The viewer's user journeys, step by step.

use std::time::{Duration, Instant};

use fantoccini::actions::{InputSource, MOUSE_BUTTON_RIGHT, MouseActions, PointerAction};
use fantoccini::key::Key;
use serde_json::{Value, json};

use super::browser::{self, Browser};
use super::common::{TestApp, spawn_app_with};

async fn enter_token(b: &Browser, token: &str) {
    let input = b.find("#token-input").await;
    input.send_keys(token).await.expect("type the token");
    b.find("#token-form button[type=submit]")
        .await
        .click()
        .await
        .expect("submit the token");
}

pub async fn token_and_server_down(token: &str) {
    let Some(b) = browser::start("viewer: token and server down", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|s| {
        s.api_tokens = vec![token.into()];
        s.drain_timeout_ms = 200;
    })
    .await;
    b.goto(&app.url("/")).await;
    let err = b.wait_for("#page-error", 20).await;
    let text = err.text().await.expect("text");
    // Before any token was entered the page asks for one; it does not say a token was refused.
    assert!(
        text.contains("Token needed") && text.contains("needs an API token"),
        "{text}"
    );
    assert!(!text.contains("Token refused"), "{text}");
    b.shot("error-token-needed").await;

    enter_token(&b, "not-the-token").await;
    b.until("document.querySelector('#banner:not([hidden]) .error-title')?.textContent === 'Token refused'", 20)
        .await;
    b.shot("error-wrong-token").await;

    enter_token(&b, token).await;
    b.wait_for("#jobs-table", 20).await;
    // The table is never empty: "Loading jobs…" from the moment it is drawn until its event stream is
    // open and the first page is in, then the empty state with the way to start a job.
    let rows = b
        .js(
            "return [...document.querySelectorAll('#jobs-table tbody tr')].map((r) => r.className);",
            vec![],
        )
        .await;
    let rows: Vec<String> = serde_json::from_value(rows).expect("classes");
    assert!(
        rows == ["loading"] || rows == ["empty"],
        "rows when the table appears: {rows:?}"
    );
    b.until(
        "return document.querySelector('#jobs-table tbody tr.empty') !== null",
        20,
    )
    .await;
    let empty = b.text("#jobs-table tbody").await;
    assert!(empty.starts_with("No jobs yet."), "{empty}");
    assert_eq!(
        b.attr("#jobs-table tbody tr.empty a", "href")
            .await
            .as_deref(),
        Some("#/send")
    );
    b.shot("jobs-empty").await;
    // Filtered to a status no job has: the empty state says so.
    b.js(
        "const s = document.getElementById('filter-status'); s.value = 'failed';
         s.dispatchEvent(new Event('change'));",
        vec![],
    )
    .await;
    b.until(
        "return document.querySelector('#jobs-table tbody')?.textContent.trim() === 'No jobs match these filters.'",
        20,
    )
    .await;
    b.js(
        "const s = document.getElementById('filter-status'); s.value = '';
         s.dispatchEvent(new Event('change'));",
        vec![],
    )
    .await;
    assert!(
        b.find("#banner")
            .await
            .attr("hidden")
            .await
            .expect("attr")
            .is_some()
    );

    let addr = app.base.trim_start_matches("http://").to_string();
    drop(app);
    let deadline = Instant::now() + Duration::from_secs(30);
    while std::net::TcpStream::connect(&addr).is_ok() {
        assert!(Instant::now() < deadline, "the server did not stop");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    b.find("#nav-send").await.click().await.expect("click");
    b.until("document.querySelector('#banner:not([hidden]) .error-title')?.textContent === 'Server unreachable'", 20)
        .await;
    let page = b.text("#page-error").await;
    assert!(page.contains("does not answer"), "{page}");
    b.shot("error-server-down").await;
}

fn lidc_paths() -> Option<Vec<String>> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    if !dir.is_dir() {
        assert!(
            std::env::var("CTRECON_REQUIRE_TEST_DATA").as_deref() != Ok("1"),
            "{} is missing and CTRECON_REQUIRE_TEST_DATA=1",
            dir.display()
        );
        eprintln!(
            "SKIPPED viewer LIDC test: {} is missing (run scripts/fetch-test-data.sh)",
            dir.display()
        );
        return None;
    }
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .expect("lidc dir")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .map(|p| {
            p.canonicalize()
                .expect("path")
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    files.sort();
    Some(files)
}

pub async fn api_json(app: &TestApp, token: &str, path: &str) -> Value {
    let r = app
        .client
        .get(app.url(path))
        .bearer_auth(token)
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 200, "{path}");
    r.json().await.expect("json")
}

/// The grey level the viewer's window formula gives a value (as slices.js computes it, in f64).
pub fn window_grey(v: f32, ww: f64, wl: f64) -> u8 {
    let lo = wl - ww / 2.0;
    let k = 255.0 / ww.max(1e-12);
    let g = (f64::from(v) - lo) * k;
    g.clamp(0.0, 255.0).floor() as u8
}

pub async fn window(b: &Browser) -> (f64, f64) {
    let ww = b.attr("#slice-panel", "data-ww").await.expect("data-ww");
    let wl = b.attr("#slice-panel", "data-wl").await.expect("data-wl");
    (ww.parse().expect("ww"), wl.parse().expect("wl"))
}

/// Grey level of the axial canvas at image pixel (i, j), and a checksum of the whole canvas.
pub async fn pixel(b: &Browser, i: usize, j: usize) -> (u8, u64) {
    let v = b
        .js(
            "const c = document.querySelector('.view-axial canvas.image');
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
             let sum = 0; for (let x = 0; x < d.length; x += 4) sum += d[x];
             return [d[(arguments[1] * c.width + arguments[0]) * 4], sum];",
            vec![json!(i), json!(j)],
        )
        .await;
    (
        v[0].as_u64().expect("grey") as u8,
        v[1].as_u64().expect("sum"),
    )
}

/// Upload LIDC-IDRI-0001 through the drop zone, run the bone protocol, then check the views, the stacks, the
/// mesh, the downloads and the tablet width (`checks`).
pub async fn lidc(token: &str) {
    let Some(files) = lidc_paths() else { return };
    let Some(b) = browser::start("viewer: LIDC in Chromium", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|s| {
        s.api_tokens = vec![token.into()];
        s.max_upload_bytes = 256 << 20;
        s.memory_budget_bytes = 4 << 30;
        s.request_timeout_secs = 120;
    })
    .await;
    b.goto(&app.url("/#/send")).await;
    b.wait_for("#page-error", 20).await;
    enter_token(&b, token).await;

    // 1. The drop zone's file input takes the 133 files; the assembly report lists 133 slices.
    let input = b.wait_for("#dicom-files", 20).await;
    input
        .send_keys(&files.join("\n"))
        .await
        .expect("choose the files");
    let ready = b
        .wait_for("#upload-report li.series[data-status=ready]", 180)
        .await;
    assert_eq!(
        ready.attr("data-slices").await.expect("attr").as_deref(),
        Some("133")
    );
    assert!(ready.text().await.expect("text").contains("133 slices"));
    let series = ready
        .attr("data-id")
        .await
        .expect("attr")
        .expect("series id");
    b.shot("upload-report").await;

    // 2. The server's bone protocol (a bone surface and a rotating MIP); the job page follows the job to
    //    `succeeded` through its event stream.
    b.wait_for("#upload-report form.protocol[data-ready]", 20)
        .await;
    super::ui::choose(&b, "#upload-report select.protocol-preset", "bone_stl").await;
    b.find("#upload-report .protocol-run")
        .await
        .click()
        .await
        .expect("run the protocol");
    b.until("location.hash.startsWith('#/job/')", 20).await;
    let hash = b.js("return location.hash", vec![]).await;
    let job_id = hash
        .as_str()
        .expect("hash")
        .trim_start_matches("#/job/")
        .to_string();
    b.wait_for(
        "#job-status [data-status=running], #job-status [data-status=succeeded]",
        60,
    )
    .await;
    b.wait_for("#job-status [data-status=succeeded]", 900).await;
    let job = api_json(&app, token, &format!("/v1/jobs/{job_id}")).await;
    assert_eq!(job["status"], "succeeded", "{job}");
    b.wait_for("#slice-panel[data-volume-loaded]", 120).await;
    b.wait_for(".product[data-type=rotating] .play", 60).await;
    b.shot("job-slices").await;

    super::checks::slices_and_window(&b, &app, token, &series).await;
    super::checks::mesh_and_figures(&b, &app, token, &job).await;
}

/// Right-drag on the axial view by (dx, dy) CSS pixels.
pub async fn right_drag(b: &Browser, dx: f64, dy: f64) {
    let canvas = b.find(".view-axial canvas.image").await;
    let drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: canvas,
            duration: None,
            x: 0.0,
            y: 0.0,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_RIGHT,
        })
        .then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(100)),
            x: dx,
            y: dy,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_RIGHT,
        });
    b.client.perform_actions(drag).await.expect("right-drag");
}

pub fn keys_to(index: usize) -> String {
    let mut s = String::new();
    s.push(char::from(Key::Home));
    for _ in 0..index {
        s.push(char::from(Key::Up));
    }
    s
}
