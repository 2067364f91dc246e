//! A ZIP dropped on the page and the server's protocols run from it: the ZIP (a tilted CT series, a text file
//! and a cut-off DICOM file) goes in through the drop zone's file input; the assembly report shows the series
//! with the warnings the API gives it and each refused file with the API's reason; the protocol chooser lists
//! the server's protocols (`GET /v1/protocols`) and sends the listed steps and products; the spine protocol's
//! thick slabs and MIP and the lung protocol's MinIP and MIP slabs are shown as image stacks whose pixels are
//! the API's product values through the chosen window.

use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::jobs::model::ProductSpec;
use ctrecon::jobs::rules::JobTemplate;
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;
use serde_json::{Value, json};

use super::browser::{self, Browser};
use super::common::{TestApp, spawn_app_with};
use super::stacks::stack_matches;
use super::ui::{choose, click};

/// A CT series of 40 × 40 × 14 voxels (1 × 1 × 2.5 mm along the slice axis) under a gantry tilt of
/// `tilt_deg`: a ball of bone-like values on a ramp of air-like ones, so that every window shows structure.
fn ball_series(tilt_deg: f64) -> Vec<(String, Vec<u8>)> {
    let t = tilt_deg.to_radians();
    let frame = Frame {
        origin_mm: [-19.5, -19.5, -16.0],
        spacing_mm: [1.0, 1.0, 2.5 / t.cos()],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, t.sin(), t.cos()]],
    };
    let data = Array3::from_shape_fn((14, 40, 40), |(k, j, i)| {
        let p = frame.position(k as f64, j as f64, i as f64);
        let r = p.iter().map(|c| c * c).sum::<f64>().sqrt();
        if r < 14.0 {
            (200 + 40 * k + 5 * i) as f32
        } else {
            (25 * k + 3 * i) as f32 - 1000.0
        }
    });
    let meta = SeriesMeta {
        study_uid: Some("1.2.826.0.1.3680043.8.498.71".into()),
        frame_of_reference_uid: Some("1.2.826.0.1.3680043.8.498.72".into()),
        patient_id: Some("PRESETS".into()),
        series_description: format!("ball, tilt {tilt_deg} degrees"),
        series_number: 5,
        ..Default::default()
    };
    write_ct_series(&Volume { data, frame }, &meta)
        .expect("a CT series")
        .files
}

async fn api(app: &TestApp, path: &str) -> Value {
    let r = app.get(path).await;
    assert_eq!(r.status(), 200, "{path}");
    r.json().await.expect("json")
}

/// Texts of the elements matching `css`.
async fn texts(b: &Browser, css: &str) -> Vec<String> {
    let v = b
        .js(
            "return [...document.querySelectorAll(arguments[0])].map((e) => e.textContent.trim());",
            vec![json!(css)],
        )
        .await;
    serde_json::from_value(v).expect("strings")
}

/// Run protocol `name` from the protocol form under `scope` (the form lists the server's protocols and
/// holds the listed body); wait for the job to succeed on its page. Returns the job.
async fn run_protocol(
    b: &Browser,
    app: &TestApp,
    scope: &str,
    name: &str,
    listed: &[Value],
) -> Value {
    b.wait_for(&format!("{scope} form.protocol[data-ready]"), 20)
        .await;
    let options = b
        .js(
            "return [...document.querySelectorAll(arguments[0] + ' select.protocol-preset option')].map((o) => [o.value, o.textContent]);",
            vec![json!(scope)],
        )
        .await;
    let want: Vec<Value> = listed
        .iter()
        .map(|p| json!([p["name"], p["description"]]))
        .collect();
    assert_eq!(
        options,
        json!(want),
        "the page offers the server's protocols"
    );
    choose(b, &format!("{scope} select.protocol-preset"), name).await;
    let preset = listed
        .iter()
        .find(|p| p["name"] == name)
        .expect("a listed protocol");
    let shown: Value = serde_json::from_str(
        b.js(
            "return document.querySelector(arguments[0] + ' textarea.protocol-json').value;",
            vec![json!(scope)],
        )
        .await
        .as_str()
        .expect("text"),
    )
    .expect("the form holds JSON");
    let template =
        |v: Value| -> JobTemplate { serde_json::from_value(v).expect("steps and products") };
    assert_eq!(
        template(shown),
        template(json!({"steps": preset["steps"], "products": preset["products"]})),
        "{name}: the form holds the server's steps and products"
    );
    let before = b.js("return location.hash", vec![]).await;
    click(b, &format!("{scope} .protocol-run")).await;
    b.until(
        &format!(
            "location.hash.startsWith('#/job/') && location.hash !== {}",
            before
        ),
        20,
    )
    .await;
    let id = b
        .js("return location.hash.slice('#/job/'.length)", vec![])
        .await
        .as_str()
        .expect("id")
        .to_string();
    b.wait_for("#job-status [data-status=succeeded]", 300).await;
    let job = app.job(&id).await;
    assert_eq!(job["status"], "succeeded", "{job}");
    let sent: Vec<ProductSpec> = serde_json::from_value(job["products"].clone()).expect("products");
    let listed: Vec<ProductSpec> =
        serde_json::from_value(preset["products"].clone()).expect("products");
    assert_eq!(sent, listed, "{name}: the job runs the listed products");
    job
}

/// Each product of `job` is on the page as a stack with the product's orientation labels, its shown frame
/// the API's values through the chosen window.
async fn stacks_shown(b: &Browser, app: &TestApp, job: &Value) {
    let id = job["id"].as_str().expect("id");
    for p in job["result"]["products"].as_array().expect("products") {
        let k = p["index"].as_u64().expect("index") as usize;
        let card = format!(".product[data-index='{k}']");
        b.wait_for(&format!("{card}[data-frame]"), 60).await;
        for side in ["top", "bottom", "left", "right"] {
            assert_eq!(
                b.text(&format!("{card} .orient-{side}")).await,
                p["orientation"][side].as_str().unwrap_or(""),
                "product {k}: the {side} label"
            );
        }
        // Shown in proportion to its pixel size (mm), a few-cm image enlarged to about 320 px.
        let size = b
            .js(
                "const r = document.querySelector(arguments[0] + ' canvas.product-image').getBoundingClientRect();
                 return [r.width, r.height];",
                vec![json!(card)],
            )
            .await;
        let (w, h) = (size[0].as_f64().expect("w"), size[1].as_f64().expect("h"));
        let mm = |a: usize, b: usize| {
            p["shape"][a].as_f64().expect("size") * p["pixel_mm"][b].as_f64().expect("mm")
        };
        let (w_mm, h_mm) = (mm(2, 1), mm(1, 0));
        assert!(
            (w - h * w_mm / h_mm).abs() <= 1.0 && (w.max(h) - 320.0).abs() <= 1.0,
            "product {k}: {w} × {h} px for {w_mm} × {h_mm} mm"
        );
        let frames = p["shape"][0].as_u64().expect("frames") as usize;
        let (frame, pixels) = stack_matches(b, app, None, id, k).await;
        // A series of planes opens at its middle plane.
        assert_eq!(frame, (frames - 1) / 2, "product {k} of {frames} frames");
        eprintln!(
            "product {k} ({}): frame {frame} of {frames}, {pixels} pixels as the API's values windowed",
            p["type"].as_str().unwrap_or("")
        );
    }
}

pub async fn zip_and_protocols() {
    let Some(b) = browser::start("viewer: ZIP report and server protocols", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|_| {}).await;
    let listed = api(&app, "/v1/protocols").await["protocols"]
        .as_array()
        .expect("protocols")
        .clone();

    // The ZIP: 14 slices, a text file and a DICOM file cut off after 300 bytes.
    let mut files = ball_series(12.0);
    let cut = files[3].1[..300].to_vec();
    files.push(("notes.txt".into(), b"scanned on Tuesday\n".to_vec()));
    files.push(("cut-off.dcm".into(), cut));
    let dir = tempfile::tempdir().expect("temp dir");
    let zip = dir.path().join("tilted.zip");
    std::fs::write(&zip, write_zip(&files).expect("zip")).expect("write the ZIP");

    b.goto(&app.url("/#/send")).await;
    let input = b.wait_for("#dicom-files", 20).await;
    input
        .send_keys(&zip.to_string_lossy())
        .await
        .expect("choose the ZIP");
    let ready = b
        .wait_for("#upload-report li.series[data-status=ready]", 60)
        .await;
    assert_eq!(
        ready.attr("data-slices").await.expect("attr").as_deref(),
        Some("14")
    );
    assert_eq!(
        b.js(
            "return [document.getElementById('upload-progress').value, document.getElementById('upload-status').textContent];",
            vec![]
        )
        .await,
        json!([100, "done"])
    );
    let series_id = ready.attr("data-id").await.expect("attr").expect("id");
    let series = api(&app, &format!("/v1/series/{series_id}")).await;
    // The series' warnings as the API gives them (the series' own and its assembly report's, each once),
    // the gantry tilt among them; each refused file with the API's code and reason.
    let upload = api(
        &app,
        series["links"]["upload"].as_str().expect("the upload"),
    )
    .await;
    let s0 = &upload["series"][0];
    let mut warnings: Vec<String> = Vec::new();
    for w in s0["series"]["warnings"]
        .as_array()
        .into_iter()
        .chain(s0["report"]["warnings"].as_array())
        .flatten()
    {
        let line = format!(
            "{} {}",
            w["code"].as_str().unwrap_or(""),
            w["message"].as_str().unwrap_or("")
        );
        if !warnings.contains(&line) {
            warnings.push(line);
        }
    }
    assert!(
        warnings.iter().any(|w| w.starts_with("gantry_tilt ")),
        "{upload}"
    );
    assert_eq!(
        texts(&b, "#upload-report li.series .warnings li").await,
        warnings
    );
    let rejected: Vec<String> = upload["rejected"]
        .as_array()
        .expect("rejected")
        .iter()
        .map(|r| {
            format!(
                "{} {} {}",
                r["file"].as_str().unwrap_or(""),
                r["code"].as_str().unwrap_or(""),
                r["detail"].as_str().unwrap_or("")
            )
        })
        .collect();
    assert_eq!(rejected.len(), 2, "{rejected:?}");
    assert!(
        rejected
            .iter()
            .any(|r| r.starts_with("notes.txt dicom_not_dicom "))
    );
    assert!(rejected.iter().any(|r| r.starts_with("cut-off.dcm ")));
    assert_eq!(texts(&b, "#upload-report ul.rejected li").await, rejected);
    assert!(
        b.text("#upload-report").await.contains("2 refused files"),
        "{}",
        b.text("#upload-report").await
    );
    b.shot("upload-zip-report").await;

    // The spine protocol from the report: thick average slabs and a MIP, as stacks.
    let spine = run_protocol(&b, &app, "#upload-report", "spine", &listed).await;
    stacks_shown(&b, &app, &spine).await;
    // Another plane of the sagittal slabs through the slider.
    b.js(
        "const s = document.querySelector(\".product[data-index='0'] input.frame\"); s.value = '2';
         s.dispatchEvent(new Event('input'));",
        vec![],
    )
    .await;
    b.wait_for(".product[data-index='0'][data-frame='2']", 10)
        .await;
    let spine_id = spine["id"].as_str().expect("id");
    assert_eq!(stack_matches(&b, &app, None, spine_id, 0).await.0, 2);
    b.js(
        "document.getElementById('products').scrollIntoView();",
        vec![],
    )
    .await;
    b.shot("job-spine-stacks").await;

    // The lung protocol from the page of an untilted twin of the series (whose coronal MinIP sees the air
    // around the ball): a MinIP and MIP slabs, in the lung window.
    let r = app
        .client
        .post(app.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(write_zip(&ball_series(0.0)).expect("zip"))
        .send()
        .await
        .expect("upload");
    assert_eq!(r.status(), 201);
    let twin: Value = r.json().await.expect("json");
    let twin = twin["series"][0]["series"]["id"]
        .as_str()
        .expect("id")
        .to_string();
    b.goto(&app.url(&format!("/#/series/{twin}"))).await;
    let lung = run_protocol(&b, &app, "#series-summary", "lung", &listed).await;
    assert_eq!(lung["products"][0]["kind"], "minip", "{lung}");
    for k in 0..2 {
        b.wait_for(&format!(".product[data-index='{k}'][data-frame]"), 60)
            .await;
        choose(
            &b,
            &format!(".product[data-index='{k}'] select.preset"),
            "lung",
        )
        .await;
    }
    stacks_shown(&b, &app, &lung).await;
    b.js(
        "document.getElementById('products').scrollIntoView();",
        vec![],
    )
    .await;
    b.shot("job-lung-minip").await;
}
