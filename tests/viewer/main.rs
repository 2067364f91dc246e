//! The built-in web viewer in a real headless Chromium (WebDriver) against the real server on a random port:
//! the page is served with its security headers, a DICOM series goes in through the drop zone's file input,
//! the server's bone protocol runs and the page follows it to `succeeded` through Server-Sent Events, the
//! value and LPS position under the cursor in each plane equal the API's volume and frame, crosshairs link
//! the planes, the scale bar measures what it says, wheel and keys step slices, window changes recolour the
//! canvas as the window formula says, the rotating MIP plays, the mesh is drawn and its triangle count, area
//! and volume are the API's, every download answers as the API does, the tablet width and the keyboard
//! alone work, and a wrong token or a stopped server give the page's messages. A dropped ZIP's report shows
//! refused files and warnings as the API does; the server's protocols (`GET /v1/protocols`) are the page's
//! presets, and the spine and lung protocols' slabs, MIP and MinIP are shown as the API's values windowed.
//! Renderings of a reconstructed phantom are shown as the API serves them, and a failed job's page shows
//! its problem; the list's filters, cancel and delete, and the phantom form agree with the API (its bounds
//! from `/v1/limits`, refusals placed by JSON Pointer); the list follows every job through one `/v1/events`
//! stream; oblique volumes get combined orientation labels; the page's files go gzip-compressed to clients
//! that take it. Screenshots of each view go to `screenshots/` in the target directory (or
//! `CTRECON_SCREENSHOT_DIR`); the figures (page load, time to first slice, frames per second, page weight)
//! are printed.

use crate::common;

mod browser;
mod checks;
mod downloads;
mod flow;
mod form;
mod list;
mod orient;
mod planes;
mod presets;
mod renders;
mod stacks;
mod ui;
mod window;

use common::spawn_app_with;

const TOKEN: &str = "viewer-test-token-0123456789abcdef";

#[tokio::test]
async fn the_page_and_its_modules_are_served_with_types_etags_and_a_strict_policy() {
    let app = spawn_app_with(|s| s.api_tokens = vec![TOKEN.into()]).await;
    let r = app.get("/").await;
    assert_eq!(r.status(), 200, "the page needs no token");
    let h = r.headers().clone();
    assert_eq!(h["content-type"], "text/html; charset=utf-8");
    let csp = h["content-security-policy"].to_str().expect("ascii");
    assert!(csp.contains("script-src 'self'") && csp.contains("style-src 'self'"));
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"));
    assert_eq!(h["x-content-type-options"], "nosniff");
    let html = r.text().await.expect("body");
    assert!(html.contains(r#"<script type="module" src="/web/js/app.js"></script>"#));

    let r = app.get("/web/js/app.js").await;
    assert_eq!(r.status(), 200);
    assert_eq!(
        r.headers()["content-type"],
        "text/javascript; charset=utf-8"
    );
    assert_eq!(r.headers()["cache-control"], "no-cache");
    let etag = r.headers()["etag"].clone();
    let again = app
        .client
        .get(app.url("/web/js/app.js"))
        .header("if-none-match", etag.clone())
        .send()
        .await
        .expect("request");
    assert_eq!(again.status(), 304);
    assert_eq!(again.headers()["etag"], etag);
    let three = app.get("/web/vendor/three/three.module.js").await;
    assert_eq!(three.status(), 200);
    assert!(three.text().await.expect("body").contains("REVISION"));

    // Names outside the table are not found (a request never becomes a file path).
    for missing in ["/web/js/nope.js", "/web/js", "/web/index.html/x"] {
        assert_eq!(app.get(missing).await.status(), 404, "{missing}");
    }
    // The API stays behind the token.
    assert_eq!(app.get("/v1/jobs").await.status(), 401);
}

/// GET `path` with `Accept-Encoding: accept` (none when empty) and `If-None-Match: etag` (none when empty).
async fn get_encoded(
    app: &common::TestApp,
    path: &str,
    accept: &str,
    etag: &str,
) -> reqwest::Response {
    let mut req = app.client.get(app.url(path));
    if !accept.is_empty() {
        req = req.header("accept-encoding", accept);
    }
    if !etag.is_empty() {
        req = req.header("if-none-match", etag);
    }
    req.send().await.expect("request")
}

fn header(r: &reqwest::Response, name: &str) -> String {
    r.headers()
        .get(name)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string()
}

#[tokio::test]
async fn the_pages_files_are_sent_gzipped_to_clients_that_take_it_with_an_etag_per_encoding() {
    use std::io::Read;
    let app = spawn_app_with(|s| s.api_tokens = vec![TOKEN.into()]).await;
    let web = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
    let mut plain_total = 0;
    let mut gzip_total = 0;
    for (path, file) in [
        ("/", "index.html"),
        ("/web/css/viewer.css", "css/viewer.css"),
        ("/web/js/app.js", "js/app.js"),
        ("/web/js/products.js", "js/products.js"),
        ("/web/js/orient.js", "js/orient.js"),
        (
            "/web/vendor/three/three.core.js",
            "vendor/three/three.core.js",
        ),
        (
            "/web/vendor/three/three.module.js",
            "vendor/three/three.module.js",
        ),
    ] {
        let embedded = std::fs::read(web.join(file)).expect("the file under web/");
        let plain = get_encoded(&app, path, "", "").await;
        assert_eq!(plain.status(), 200, "{path}");
        assert_eq!(header(&plain, "content-encoding"), "", "{path} unasked");
        assert_eq!(header(&plain, "vary"), "accept-encoding", "{path}");
        let plain_tag = header(&plain, "etag");
        assert!(plain.bytes().await.expect("body") == embedded, "{path}");

        let gz = get_encoded(&app, path, "gzip, deflate, br", "").await;
        assert_eq!(gz.status(), 200, "{path}");
        assert_eq!(header(&gz, "content-encoding"), "gzip", "{path}");
        assert_eq!(header(&gz, "vary"), "accept-encoding", "{path}");
        let gz_tag = header(&gz, "etag");
        assert_eq!(
            gz_tag,
            format!("{}-gzip\"", plain_tag.trim_end_matches('"')),
            "{path}"
        );
        let body = gz.bytes().await.expect("body");
        let mut unpacked = Vec::new();
        flate2::read::GzDecoder::new(&body[..])
            .read_to_end(&mut unpacked)
            .expect("a gzip stream");
        assert!(
            unpacked == embedded,
            "{path}: the gzip body unpacks to the file"
        );
        assert!(body.len() < embedded.len(), "{path}");
        plain_total += embedded.len();
        gzip_total += body.len();

        // Each representation revalidates with its own ETag only.
        let same = get_encoded(&app, path, "gzip", &gz_tag).await;
        assert_eq!(same.status(), 304, "{path}");
        assert_eq!(header(&same, "etag"), gz_tag);
        assert_eq!(
            get_encoded(&app, path, "gzip", &plain_tag).await.status(),
            200,
            "{path}"
        );
        let plain_again = get_encoded(&app, path, "identity", &plain_tag).await;
        assert_eq!(plain_again.status(), 304, "{path}");
        assert_eq!(
            get_encoded(&app, path, "", &gz_tag).await.status(),
            200,
            "{path}"
        );
        // A refused coding is not sent.
        let refused = get_encoded(&app, path, "gzip;q=0, br", "").await;
        assert_eq!(header(&refused, "content-encoding"), "", "{path}");
    }
    assert!(
        gzip_total * 4 < plain_total,
        "{gzip_total} of {plain_total} bytes"
    );
    eprintln!(
        "FIGURES viewer gzip: {plain_total} bytes of page files and three.js sent as {gzip_total} bytes"
    );
}

#[tokio::test]
async fn a_wrong_token_and_a_stopped_server_show_the_pages_messages() {
    flow::token_and_server_down(TOKEN).await;
}

#[tokio::test]
async fn the_default_window_is_a_preset_chosen_from_the_data() {
    window::default_window_from_the_data().await;
}

#[tokio::test]
async fn lidc_upload_bone_protocol_slices_window_and_mesh_in_chromium() {
    flow::lidc(TOKEN).await;
}

#[tokio::test]
async fn renderings_of_a_reconstructed_phantom_and_a_failed_jobs_problem_are_shown_as_the_api_serves_them()
 {
    renders::renderings().await;
}

#[tokio::test]
async fn the_list_filters_by_status_and_kind_and_cancel_and_delete_reach_the_api() {
    list::filters_cancel_delete().await;
}

#[tokio::test]
async fn the_phantom_form_creates_the_simulation_and_job_it_shows_and_places_refusals_by_field() {
    form::phantom_form().await;
}

#[tokio::test]
async fn the_list_follows_every_job_live_through_one_event_stream() {
    list::live_list().await;
}

#[tokio::test]
async fn the_pages_label_function_agrees_with_the_servers_on_oblique_directions() {
    orient::label_function().await;
}

#[tokio::test]
async fn oblique_series_show_combined_orientation_labels_in_all_three_planes() {
    orient::oblique_series().await;
}

#[tokio::test]
async fn a_dropped_zip_reports_refused_files_and_warnings_and_the_servers_protocols_show_as_stacks()
{
    presets::zip_and_protocols().await;
}
