//! The jobs list and the job page in Chromium against the API: the status and kind filters show exactly the
//! jobs the API lists for them, cancel and delete from the list and from a job's page reach the API (the job
//! is then `canceled`, or gone with 404), and the phantom form creates the simulation and the job with the
//! values typed into it; values the browser or the server refuse are shown next to their field.

use std::time::Duration;

use serde_json::{Value, json};

use super::browser::{self, Browser};
use super::common::{TestApp, cone_geometry, parallel_geometry, spawn_app_with};

/// Ids of `GET /v1/jobs?{query}`, sorted.
async fn api_ids(app: &TestApp, query: &str) -> Vec<String> {
    let v: Value = app
        .get(&format!("/v1/jobs?limit=200&{query}"))
        .await
        .json()
        .await
        .expect("json");
    let mut ids: Vec<String> = v["jobs"]
        .as_array()
        .expect("jobs")
        .iter()
        .map(|j| j["id"].as_str().expect("id").to_string())
        .collect();
    ids.sort();
    ids
}

/// Ids of the rows the page lists, sorted.
async fn page_ids(b: &Browser) -> Vec<String> {
    let v = b
        .js(
            "return [...document.querySelectorAll('#jobs-table tbody tr[data-id]')].map((r) => r.dataset.id).sort();",
            vec![],
        )
        .await;
    serde_json::from_value(v).expect("ids")
}

/// Set a `<select>` as a user would (value, then `change`).
async fn choose(b: &Browser, css: &str, value: &str) {
    b.js(
        "const s = document.querySelector(arguments[0]); s.value = arguments[1];
         if (s.value !== arguments[1]) return false;
         s.dispatchEvent(new Event('change', { bubbles: true })); return true;",
        vec![json!(css), json!(value)],
    )
    .await
    .as_bool()
    .filter(|&ok| ok)
    .unwrap_or_else(|| panic!("{css} has no option {value}"));
}

/// Wait until the list shows exactly `want` (sorted ids).
async fn list_shows(b: &Browser, want: &[String], what: &str) {
    let text = serde_json::to_string(want).expect("json");
    let script = format!(
        "return JSON.stringify([...document.querySelectorAll('#jobs-table tbody tr[data-id]')].map((r) => r.dataset.id).sort()) === {};",
        serde_json::to_string(&text).expect("json")
    );
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while b.js(&script, vec![]).await != json!(true) {
        assert!(
            std::time::Instant::now() < deadline,
            "{what}: the page lists {:?}, the API {want:?}",
            page_ids(b).await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A 2D SIRT of 100 000 iterations: runs until it is canceled.
async fn endless(app: &TestApp, input: &str) -> String {
    let j = app
        .submit(
            &json!({"input": input, "algorithm": {"name": "sirt", "iterations": 100000},
                        "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await;
    j["id"].as_str().expect("id").to_string()
}

async fn status_of(app: &TestApp, id: &str) -> Value {
    app.job(id).await["status"].clone()
}

async fn click(b: &Browser, css: &str) {
    b.find(css).await.click().await.expect("click");
}

pub async fn filters_cancel_delete() {
    let Some(b) = browser::start("viewer: list filters, cancel and delete", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 1).await;
    // Finished jobs of both kinds, then one running and one queued behind it.
    let flat = app.simulate(parallel_geometry(60, 64, 1.0), 28.0).await;
    let fbp = app
        .submit(&json!({"input": flat, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 32, "ny": 32, "dx_mm": 2.0, "dy_mm": 2.0}}))
        .await["id"]
        .as_str()
        .expect("id")
        .to_string();
    assert_eq!(app.finish(&fbp).await["status"], "succeeded");
    let cone = app.simulate(cone_geometry(24, 24), 10.0).await;
    let fdk = app
        .submit(&json!({"input": cone, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1, 1, 1]}}))
        .await["id"]
        .as_str()
        .expect("id")
        .to_string();
    assert_eq!(app.finish(&fdk).await["status"], "succeeded");
    let vol = app
        .submit(&json!({"kind": "volume", "input": fdk, "products": [{"type": "projection"}]}))
        .await["id"]
        .as_str()
        .expect("id")
        .to_string();
    assert_eq!(app.finish(&vol).await["status"], "succeeded");
    let running = endless(&app, &flat).await;
    app.wait_until(&running, 60, |j| j["status"] == "running")
        .await;
    let queued = endless(&app, &flat).await;
    assert_eq!(status_of(&app, &queued).await, "queued");

    b.goto(&app.url("/#/jobs")).await;
    b.wait_for("#jobs-table tbody tr[data-id]", 20).await;
    list_shows(&b, &api_ids(&app, "").await, "no filter").await;
    assert_eq!(page_ids(&b).await.len(), 5);
    for (id, status) in [
        (&fbp, "succeeded"),
        (&vol, "succeeded"),
        (&running, "running"),
        (&queued, "queued"),
    ] {
        b.wait_for(
            &format!("#jobs-table tr[data-id='{id}'] .cell-status [data-status='{status}']"),
            10,
        )
        .await;
    }

    // Each filter and pair of filters lists what the API lists for it, and the address keeps it. The two
    // changes come in a row, as a user makes them: the answer to the first request may arrive after the
    // second was sent, and the page must keep only the newest.
    for (status, kind, n) in [
        ("succeeded", "", 3),
        ("succeeded", "volume", 1),
        ("", "reconstruction", 4),
        ("running", "", 1),
        ("queued", "reconstruction", 1),
        ("queued", "volume", 0),
        ("", "", 5),
    ] {
        choose(&b, "#filter-status", status).await;
        choose(&b, "#filter-kind", kind).await;
        let mut query = Vec::new();
        if !status.is_empty() {
            query.push(format!("status={status}"));
        }
        if !kind.is_empty() {
            query.push(format!("kind={kind}"));
        }
        let query = query.join("&");
        let want = api_ids(&app, &query).await;
        assert_eq!(want.len(), n, "the API's list for {query}");
        list_shows(&b, &want, &query).await;
        if n == 0 {
            assert_eq!(b.text("#jobs-table tbody").await, "No jobs.");
        }
        let hash = b.js("return location.hash", vec![]).await;
        let want_hash = if query.is_empty() {
            "#/jobs".to_string()
        } else {
            format!("#/jobs?{query}")
        };
        assert_eq!(hash, json!(want_hash));
        if (status, kind) == ("succeeded", "volume") {
            b.shot("jobs-filtered").await;
        }
    }
    assert_eq!(page_ids(&b).await, api_ids(&app, "").await);
    // Opened at a filtered address, the page starts filtered.
    b.goto(&app.url("/#/jobs?status=succeeded&kind=reconstruction"))
        .await;
    b.client.refresh().await.expect("reload");
    b.wait_for("#jobs-table tbody tr[data-id]", 20).await;
    list_shows(
        &b,
        &api_ids(&app, "status=succeeded&kind=reconstruction").await,
        "opened filtered",
    )
    .await;
    assert_eq!(
        b.js("return [document.getElementById('filter-status').value, document.getElementById('filter-kind').value]", vec![]).await,
        json!(["succeeded", "reconstruction"])
    );

    // Cancel from the list: the queued job at once, the running one within seconds; the rows follow.
    b.goto(&app.url("/#/jobs")).await;
    b.client.refresh().await.expect("reload");
    b.wait_for(
        &format!("#jobs-table tr[data-id='{queued}'] button.cancel"),
        20,
    )
    .await;
    click(
        &b,
        &format!("#jobs-table tr[data-id='{queued}'] button.cancel"),
    )
    .await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{queued}'] [data-status=canceled]"),
        20,
    )
    .await;
    assert_eq!(status_of(&app, &queued).await, "canceled");
    click(
        &b,
        &format!("#jobs-table tr[data-id='{running}'] button.cancel"),
    )
    .await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{running}'] [data-status=canceled]"),
        30,
    )
    .await;
    assert_eq!(status_of(&app, &running).await, "canceled");
    // A finished row offers Delete instead.
    b.wait_for(
        &format!("#jobs-table tr[data-id='{running}'] button.delete"),
        20,
    )
    .await;

    // Delete from the list: the row goes, the API answers 404.
    click(
        &b,
        &format!("#jobs-table tr[data-id='{fbp}'] button.delete"),
    )
    .await;
    b.until(
        &format!("document.querySelector(\"#jobs-table tr[data-id='{fbp}']\") === null"),
        20,
    )
    .await;
    assert_eq!(app.get(&format!("/v1/jobs/{fbp}")).await.status(), 404);
    assert_eq!(page_ids(&b).await, api_ids(&app, "").await);

    // Cancel and delete from a job's page.
    let third = endless(&app, &flat).await;
    b.goto(&app.url(&format!("/#/job/{third}"))).await;
    b.wait_for("#job-status [data-status=running]", 60).await;
    click(&b, "#job-cancel").await;
    b.wait_for("#job-status [data-status=canceled]", 30).await;
    assert_eq!(status_of(&app, &third).await, "canceled");
    b.shot("job-canceled").await;
    b.wait_for("#job-delete", 20).await;
    click(&b, "#job-delete").await;
    b.until("location.hash === '#/jobs'", 20).await;
    assert_eq!(app.get(&format!("/v1/jobs/{third}")).await.status(), 404);
    b.wait_for("#jobs-table tbody tr[data-id]", 20).await;
    list_shows(
        &b,
        &api_ids(&app, "").await,
        "after deleting from the job page",
    )
    .await;
    assert!(!page_ids(&b).await.contains(&third));
}

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

    // A detector nearer than the source: the server's problem goes next to the field it names (and not to
    // the detector rows, whose alias "nv" is inside "invalid").
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
    assert_eq!(api_ids(&app, "").await.len(), 0);
    b.shot("phantom-form-error").await;

    fill(&b, "dsd_mm", "450").await;
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
    click(&b, "#phantom-form button[type=submit]").await;
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
