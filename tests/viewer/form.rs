//! The phantom form in Chromium against the API: its bounds are those of `GET /v1/limits`, it creates the
//! simulation and the job with the values typed into it, and values the browser or the server refuse are
//! shown next to their field — the server's by the JSON Pointer of its problem; the form is also sent with
//! the keyboard alone.

use fantoccini::key::Key;
use serde_json::{Value, json};

use super::browser::{self, Browser};
use super::common::spawn_app_with;
use super::ui::{api_ids, choose, click, press, tab_to};

/// Type `value` into the phantom form's field `name` (a number input) or choose it (a select).
async fn fill(b: &Browser, name: &str, value: &str) {
    let css = format!("#phantom-form [name='{name}']");
    let tag = b.find(&css).await.tag_name().await.expect("tag");
    if tag == "select" {
        choose(b, &css, value).await;
    } else {
        let input = b.find(&css).await;
        input.clear().await.expect("clear");
        input.send_keys(value).await.expect("type");
    }
}

async fn field_error(b: &Browser, name: &str) -> String {
    b.text(&format!("#phantom-form .field-error[data-field='{name}']"))
        .await
}

pub async fn phantom_form() {
    let Some(b) = browser::start("viewer: phantom form", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|_| {}).await;
    b.goto(&app.url("/#/send")).await;
    b.wait_for("#phantom-form", 20).await;

    // The bounds are the server's.
    let limits: Value = app.get("/v1/limits").await.json().await.expect("json");
    let maxes = b
        .js(
            "return ['views', 'det_count', 'nv', 'noise', 'iterations', 'size'].map((n) =>
               Number(document.querySelector(`#phantom-form [name='${n}']`).max));",
            vec![],
        )
        .await;
    let l = |g: &str, k: &str| limits[g][k].as_f64().expect("a number");
    let maxes: Vec<f64> = serde_json::from_value(maxes).expect("numbers");
    assert_eq!(
        maxes,
        [
            l("geometry", "max_views"),
            l("geometry", "max_detector_elements"),
            l("geometry", "max_detector_elements"),
            l("simulation", "max_incident_photons"),
            l("algorithm", "max_iterations"),
            l("grid", "max_side")
        ]
    );

    // A cone beam: the cone's fields appear, the 3D algorithms replace the 2D ones.
    fill(&b, "type", "cone").await;
    let shown = b
        .js(
            "return ['dso_mm', 'dsd_mm', 'nv', 'iterations'].map((n) =>
               !document.querySelector(`#phantom-form label[data-field=${n}]`).hidden);",
            vec![],
        )
        .await;
    assert_eq!(shown, json!([true, true, true, false]));
    let algorithms = b
        .js(
            "return [...document.querySelector(\"#phantom-form [name='algorithm']\").options].map((o) => o.value);",
            vec![],
        )
        .await;
    assert_eq!(algorithms, json!(["fdk", "sirt", "cgls", "sart"]));
    for (name, value) in [
        ("table", "yu_ye_wang"),
        ("scale_mm", "12"),
        ("views", "0"),
        ("det_count", "32"),
        ("det_spacing_mm", "1.5"),
        ("dso_mm", "300"),
        ("dsd_mm", "450"),
        ("nv", "24"),
        ("noise", "0"),
        ("algorithm", "fdk"),
        ("filter", "hann"),
        ("size", "24"),
        ("pixel_mm", "1.25"),
    ] {
        fill(&b, name, value).await;
    }
    // 0 views: the browser refuses it next to the field; nothing is sent.
    click(&b, "#phantom-form button[type=submit]").await;
    b.until(
        "document.querySelector(\"#phantom-form .field-error[data-field='views']\").textContent !== ''",
        10,
    )
    .await;
    assert_eq!(api_ids(&app, "").await.len(), 0);

    // One past the bound: the browser refuses it next to the field; nothing is sent.
    let past = (l("geometry", "max_views") as u64 + 1).to_string();
    fill(&b, "views", &past).await;
    click(&b, "#phantom-form button[type=submit]").await;
    b.until(
        "document.querySelector(\"#phantom-form .field-error[data-field='views']\").textContent !== ''",
        10,
    )
    .await;
    assert_eq!(api_ids(&app, "").await.len(), 0);

    // A detector nearer than the source: the server's problem points at `/geometry/dsd_mm`, and the
    // message goes next to that field.
    fill(&b, "views", "36").await;
    fill(&b, "dsd_mm", "200").await;
    click(&b, "#phantom-form button[type=submit]").await;
    b.until(
        "[...document.querySelectorAll('#phantom-form .field-error')].some((e) => e.querySelector('.error'))",
        20,
    )
    .await;
    let placed = b
        .js(
            "return [...document.querySelectorAll('#phantom-form .field-error')].filter((e) => e.querySelector('.error')).map((e) => [e.dataset.field, e.textContent]);",
            vec![],
        )
        .await;
    eprintln!("the server's refusal of dsd < dso is shown at {placed}");
    let fields: Vec<&str> = placed
        .as_array()
        .expect("array")
        .iter()
        .filter_map(|p| p[0].as_str())
        .collect();
    // The detail names the source-to-detector distance first ("… must exceed the source-to-isocentre …").
    assert_eq!(fields, ["dsd_mm"], "{placed}");
    assert!(
        placed[0][1].as_str().is_some_and(|t| t.contains("200 mm")),
        "{placed}"
    );
    assert!(field_error(&b, "views").await.is_empty());
    assert_eq!(
        b.attr(
            "#phantom-form .field-error[data-field='dsd_mm'] .error",
            "data-pointer"
        )
        .await
        .as_deref(),
        Some("/geometry/dsd_mm")
    );
    assert_eq!(api_ids(&app, "").await.len(), 0);
    b.shot("phantom-form-error").await;

    // A grid larger than the orbit: the simulation passes, the job is refused at `/grid`, which is the
    // grid size's field.
    fill(&b, "dsd_mm", "450").await;
    fill(&b, "size", "500").await;
    click(&b, "#phantom-form button[type=submit]").await;
    b.until(
        "document.querySelector(\"#phantom-form .field-error[data-field='size'] .error\") !== null",
        30,
    )
    .await;
    assert_eq!(
        b.attr(
            "#phantom-form .field-error[data-field='size'] .error",
            "data-pointer"
        )
        .await
        .as_deref(),
        Some("/grid")
    );
    assert!(field_error(&b, "dsd_mm").await.is_empty());
    assert_eq!(api_ids(&app, "").await.len(), 0);
    fill(&b, "size", "24").await;
    click(&b, "#phantom-form button[type=submit]").await;
    b.until("location.hash.startsWith('#/job/')", 30).await;
    let id = b
        .js("return location.hash.slice('#/job/'.length)", vec![])
        .await
        .as_str()
        .expect("id")
        .to_string();
    let job = app.job(&id).await;
    assert_eq!(job["algorithm"]["name"], "fdk", "{job}");
    assert_eq!(job["algorithm"]["filter"], "hann", "{job}");
    assert_eq!(
        (&job["grid"]["nx"], &job["grid"]["ny"], &job["grid"]["nz"]),
        (&json!(24), &json!(24), &json!(24)),
        "{job}"
    );
    assert_eq!(
        job["grid"]["spacing_mm"],
        json!([1.25, 1.25, 1.25]),
        "{job}"
    );
    let ds: Value = app
        .get(&format!(
            "/v1/datasets/{}",
            job["input"].as_str().expect("input")
        ))
        .await
        .json()
        .await
        .expect("json");
    assert_eq!(ds["kind"], "simulation", "{ds}");
    assert_eq!(ds["phantom"]["table"], "yu_ye_wang", "{ds}");
    assert_eq!(ds["phantom"]["scale_mm"], json!(12.0), "{ds}");
    let g = &ds["geometry"];
    assert_eq!(g["type"], "cone", "{ds}");
    assert_eq!(g["angles"]["count"], 36, "{ds}");
    assert_eq!(
        (&g["dso_mm"], &g["dsd_mm"]),
        (&json!(300.0), &json!(450.0)),
        "{ds}"
    );
    assert_eq!(
        (&g["detector"]["nu"], &g["detector"]["nv"]),
        (&json!(32), &json!(24)),
        "{ds}"
    );
    assert_eq!(
        (&g["detector"]["du_mm"], &g["detector"]["dv_mm"]),
        (&json!(1.5), &json!(1.5)),
        "{ds}"
    );
    assert!(ds["noise"].is_null(), "no noise asked: {ds}");
    b.wait_for("#job-status [data-status=succeeded]", 120).await;
    assert_eq!(app.job(&id).await["status"], "succeeded");

    // A 2D scan with noise and an iterative algorithm.
    b.goto(&app.url("/#/send")).await;
    b.wait_for("#phantom-form", 20).await;
    for (name, value) in [
        ("table", "shepp_logan"),
        ("scale_mm", "20"),
        ("type", "parallel"),
        ("views", "45"),
        ("det_count", "48"),
        ("det_spacing_mm", "1"),
        ("noise", "100000"),
        ("algorithm", "sirt"),
        ("iterations", "7"),
        ("size", "40"),
        ("pixel_mm", "1"),
    ] {
        fill(&b, name, value).await;
    }
    let hidden = b
        .js(
            "return ['dso_mm', 'filter', 'iterations'].map((n) =>
               document.querySelector(`#phantom-form label[data-field=${n}]`).hidden);",
            vec![],
        )
        .await;
    assert_eq!(hidden, json!([true, true, false]));
    // Sent by keyboard only: from the top of the page (a click on its heading), Tab to the form's button,
    // Enter.
    click(&b, "#send-dicom h1").await;
    let presses = tab_to(&b, "#phantom-form button[type=submit]", 60).await;
    press(&b, char::from(Key::Enter)).await;
    eprintln!("keyboard: Tab reached the phantom form's button in {presses} presses");
    b.until(
        &format!("location.hash.startsWith('#/job/') && location.hash !== '#/job/{id}'"),
        30,
    )
    .await;
    let id2 = b
        .js("return location.hash.slice('#/job/'.length)", vec![])
        .await
        .as_str()
        .expect("id")
        .to_string();
    let job = app.job(&id2).await;
    assert_eq!(job["algorithm"]["name"], "sirt", "{job}");
    assert_eq!(job["algorithm"]["iterations"], 7, "{job}");
    assert_eq!(
        (&job["grid"]["nx"], &job["grid"]["ny"]),
        (&json!(40), &json!(40)),
        "{job}"
    );
    assert_eq!(
        (&job["grid"]["dx_mm"], &job["grid"]["dy_mm"]),
        (&json!(1.0), &json!(1.0)),
        "{job}"
    );
    let ds: Value = app
        .get(&format!(
            "/v1/datasets/{}",
            job["input"].as_str().expect("input")
        ))
        .await
        .json()
        .await
        .expect("json");
    assert_eq!(ds["phantom"]["table"], "shepp_logan", "{ds}");
    assert_eq!(ds["geometry"]["type"], "parallel", "{ds}");
    assert_eq!(ds["geometry"]["angles"]["count"], 45, "{ds}");
    assert_eq!(ds["geometry"]["det_count"], 48, "{ds}");
    assert_eq!(ds["noise"]["incident_photons"], json!(100000.0), "{ds}");
    b.wait_for("#job-status [data-status=succeeded]", 120).await;
    b.shot("phantom-job").await;
}
