//! The jobs list in Chromium against the API: the status and kind filters show exactly the jobs the API
//! lists for them, cancel and delete from the list and from a job's page reach the API (the job is then
//! `canceled`, or gone with 404; a keyboard alone reaches and presses Cancel), and the list follows every job live through one `GET /v1/events`
//! connection (counted by the server's request metrics), with no stream per job and no polling.

use std::time::Duration;

use fantoccini::key::Key;
use serde_json::json;

use super::browser::{self, Browser};
use super::common::{cone_geometry, parallel_geometry, spawn_app_with};
use super::ui::{api_ids, choose, click, endless, list_shows, page_ids, press, status_of, tab_to};

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
            // Filtered (n = 0 only happens with a filter here): the empty state names the filters.
            b.until(
                "return document.querySelector('#jobs-table tbody tr.empty') !== null",
                20,
            )
            .await;
            assert_eq!(
                b.text("#jobs-table tbody").await,
                "No jobs match these filters."
            );
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
    // The queued one by keyboard only: Tab to its Cancel button, Enter.
    let presses = tab_to(
        &b,
        &format!("#jobs-table tr[data-id='{queued}'] button.cancel"),
        60,
    )
    .await;
    press(&b, char::from(Key::Enter)).await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{queued}'] [data-status=canceled]"),
        20,
    )
    .await;
    eprintln!(
        "keyboard: Tab reached the queued job's Cancel in {presses} presses; Enter canceled it"
    );
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

/// Wait until the row of `id` shows `status` (`None`: until the row is gone).
async fn row_shows(b: &Browser, id: &str, status: Option<&str>, secs: u64) {
    let script = match status {
        Some(s) => format!(
            "return document.querySelector(\"#jobs-table tr[data-id='{id}'] [data-status='{s}']\") !== null;"
        ),
        None => {
            format!("return document.querySelector(\"#jobs-table tr[data-id='{id}']\") === null;")
        }
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(secs);
    while b.js(&script, vec![]).await != json!(true) {
        assert!(
            std::time::Instant::now() < deadline,
            "row {id} never showed {status:?}"
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

pub async fn live_list() {
    let Some(b) = browser::start("viewer: the list follows /v1/events", 1280, 800).await else {
        return;
    };
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 1).await;
    let flat = app.simulate(parallel_geometry(60, 64, 1.0), 28.0).await;
    let done = app
        .submit(&json!({"input": flat, "algorithm": {"name": "fbp"},
                        "grid": {"nx": 32, "ny": 32, "dx_mm": 2.0, "dy_mm": 2.0}}))
        .await["id"]
        .as_str()
        .expect("id")
        .to_string();
    assert_eq!(app.finish(&done).await["status"], "succeeded");
    // The page's own requests are recorded from the moment it shows the list.
    b.goto(&app.url("/#/send")).await;
    b.wait_for("#phantom-form", 20).await;
    b.js(
        "window.fetched = []; const f = window.fetch;
         window.fetch = (u, o) => { window.fetched.push(String(u)); return f(u, o); };
         location.hash = '#/jobs'; return true;",
        vec![],
    )
    .await;
    b.wait_for(&format!("#jobs-table tr[data-id='{done}']"), 20)
        .await;

    // Jobs created, run, canceled and deleted through the API appear, change and go on the page.
    let running = endless(&app, &flat).await;
    row_shows(&b, &running, Some("running"), 30).await;
    b.until(
        &format!(
            "Number(document.querySelector(\"#jobs-table tr[data-id='{running}'] progress\").value) > 0"
        ),
        60,
    )
    .await;
    let queued = endless(&app, &flat).await;
    row_shows(&b, &queued, Some("queued"), 20).await;
    assert_eq!(
        app.post_json(&format!("/v1/jobs/{queued}/cancel"), &json!({}))
            .await
            .status(),
        202
    );
    row_shows(&b, &queued, Some("canceled"), 20).await;
    b.wait_for(
        &format!("#jobs-table tr[data-id='{queued}'] button.delete"),
        20,
    )
    .await;
    assert_eq!(
        app.post_json(&format!("/v1/jobs/{running}/cancel"), &json!({}))
            .await
            .status(),
        202
    );
    row_shows(&b, &running, Some("canceled"), 30).await;
    let r = app
        .client
        .delete(app.url(&format!("/v1/jobs/{done}")))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    row_shows(&b, &done, None, 20).await;
    assert_eq!(page_ids(&b).await, api_ids(&app, "").await);
    b.shot("jobs-live").await;

    // All of it came through one event stream: no stream per job, and the list was fetched once (no
    // polling).
    let fetched: Vec<String> =
        serde_json::from_value(b.js("return window.fetched", vec![]).await).expect("urls");
    let count = |f: &dyn Fn(&String) -> bool| fetched.iter().filter(|u| f(u)).count();
    assert_eq!(count(&|u| u == "/v1/events"), 1, "{fetched:?}");
    assert_eq!(
        count(&|u| u.starts_with("/v1/jobs/") && u.ends_with("/events")),
        0,
        "{fetched:?}"
    );
    // (The page's own token check asks for one id; the list asks for pages of 50.)
    assert_eq!(
        count(&|u| u.starts_with("/v1/jobs?") && u.contains("limit=50")),
        1,
        "{fetched:?}"
    );
}
